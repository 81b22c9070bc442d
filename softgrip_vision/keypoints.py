"""Finger keypoints from a finger mask: base, tip, centreline, half-thickness, L (eq. 5), Theta (eq. 4).

A finger in the image is a tube of half-width r around its centreline. Its tip end is rounded (the
centreline ends at the centre of the tip's cap); its base end is either rounded too (a free-standing
finger) or cut flat where the finger leaves the gripper's body, with the body in view above it or
not. From its mask:

1. **Ridge.** The finger's medial path: the cheapest 8-connected pixel path from the topmost pixel
   (the middle of the top row) to the pixel farthest from it inside the mask, each step costing its
   length times ``(D_max / D)^4`` with ``D`` OpenCV's exact distance transform of the mask, so the
   path keeps to the medial axis however the finger curls. It is resampled every pixel and smoothed
   (Gaussian, sigma 2 px). Only the mask's largest component counts, with its holes (e.g. unfilled
   depth holes) filled.
2. **Edges at sub-pixel precision.** Every measurement below reads the mask along straight lines
   (bilinear interpolation of the 0/1 mask, ``cv2.remap``) and takes the point where it crosses 1/2:
   the boundary halfway between the last pixel centre inside and the first outside, which is
   unbiased on average over the edge's sub-pixel phase.
3. **Tip.** Lines parallel to the ridge's last stretch, spread across the finger, each give a point
   of the tip's cap; a circle fitted to them (least squares) has the tip at its centre. Points on
   ``cut_column`` (where segmentation cut two touching fingertips apart) are left out.
4. **Base.** The distance transform along the ridge is about r on the finger; where it grows well
   beyond r toward the top, the ridge has entered the gripper's **body**: lines beside the finger,
   parallel to its axis, find the body's edge, and the base is where the finger's axis meets it.
   Without a body, lines parallel to the axis find the top end's profile: a half-circle (a
   **rounded** base, whose cap centre is the base) or a straight cut (a **flat** base, at the middle
   of the cut). ``rounded_base`` overrides the detection.
5. **Half-thickness.** Lines across the finger, every few pixels between its ends, give its width;
   r is half the median width, converted to millimetres point by point through the camera.
6. The centreline is the smoothed ridge trimmed to run from base to tip (for eq. 10's observed
   positions).

Everything is found in pixels and converted to millimetres in the gripper plane through a
:class:`~softgrip_vision.geometry.PlaneCamera` (which may be tilted: lengths and angles are measured in
millimetres). The left finger curls toward +x; the right finger's Theta is measured toward -x (the
scene mirrored about the gripper's centre line).

Uses ``scipy.sparse.csgraph.dijkstra`` for the path and OpenCV for the distance transform and the
line sampling.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple, cast

import cv2
import numpy as np
from numpy.typing import ArrayLike
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from softgrip_jax import SoftgripError
from softgrip_vision._masks import box
from softgrip_vision.coverage import edge_coverage
from softgrip_vision.geometry import PlaneCamera
from softgrip_vision.segmentation import Segmentation

Side = Literal["left", "right"]
SIDES: tuple[Side, Side] = ("left", "right")
BaseEnd = Literal["rounded", "flat"]
TipEnd = Literal["rounded", "flat", "unknown"]

_STEPS = ((0, 1), (1, 0), (1, 1), (1, -1))  # half of the 8 neighbours; the graph is undirected
_RIDGE_POWER = 4.0
_NEAR_CUT = 0.6  # a flat base end's centre curve is fitted from this many r from the cut
_SMOOTH_SIGMA_PX = 2.0
_SAMPLE_STEP_PX = 0.25  # step of the line sampling
_TIP_STRETCH = (4.0, 2.0)  # where the tip end's direction is read (arc lengths over r from the end)
_BODY_GROWTH = 1.3  # distance transform over r at which the ridge is inside something wider: the body
_LINES = 17  # lines across a cap or a cut end
_CAP_REACH = 0.85  # their spread across the finger, as a fraction of r
_CAP_ACROSS = np.linspace(-_CAP_REACH, _CAP_REACH, _LINES)
_CAP_FAN = np.radians(80.0)  # rays from a rounded end's rough centre fan over +-80 degrees
#: Height of a round finger's front surface (a fraction of its relief) at the mean of the points
#: where the lines across a cut end meet it: the mean of sqrt(1 - x^2) at their offsets x.
_CUT_FRONT = float(np.mean(np.sqrt(1.0 - _CAP_ACROSS**2)))
#: The quadratic coefficient a least-squares fit gives a half circle of radius 1 sampled on the lines
#: across a cap (about -0.67; -0.5 at the apex alone): the curvature of a rounded end.
_HALF_CIRCLE_CURVATURE = float(np.polyfit(_CAP_ACROSS, np.sqrt(1.0 - _CAP_ACROSS**2), 2)[0])


class KeypointError(SoftgripError):
    """A finger mask from which base and tip cannot be found; the message says why."""


@dataclass(frozen=True, eq=False)
class FingerKeypoints:
    """Base, tip and centreline of one finger, in pixels; millimetres through ``camera``.

    Attributes:
        side: ``"left"`` (curls toward +x) or ``"right"``.
        base_px: (2,) base point (u, v), px: where the finger leaves the gripper's body (a flat
            base), or the centre of its rounded base end.
        tip_px: (2,) tip point, px: the centre of the tip's rounded end.
        centreline_px: (K, 2) the centreline, px, base first and tip last, about 1 px apart.
        half_thickness_px: the finger's half-width r, px.
        camera: the gripper plane's camera.
        base_end: ``"rounded"`` or ``"flat"``: what the base end looks like (detected or given).
        body_in_view: True when the finger hangs from a gripper body seen in the mask.
        width_edges_px: (S, 2, 2) pairs of points on the finger's two sides, px, across the
            finger at S stations (for the half-thickness in mm).
        region: (H, W) bool, the finger alone: its mask without the body (for depth fits).
        tip_cap_px, base_cap_px: (K, 2) outline points of the rounded tip and base ends, px (None
            for a flat base), to place the ends again once the finger's relief is known.
        base_direction: (2,) unit vector square to a flat base's cut (or the body's edge), into the
            finger, px; None for a rounded base.
        tip_end: what the tip end looks like: ``"rounded"`` (a cap, as every fingertip), ``"flat"``
            (cut square, as a base end: the frame may be upside down) or ``"unknown"``.
    """

    side: Side
    base_px: np.ndarray
    tip_px: np.ndarray
    centreline_px: np.ndarray
    half_thickness_px: float
    camera: PlaneCamera
    base_end: BaseEnd = "rounded"
    body_in_view: bool = False
    width_edges_px: np.ndarray | None = None
    region: np.ndarray | None = None
    tip_cap_px: np.ndarray | None = None
    base_cap_px: np.ndarray | None = None
    base_direction: np.ndarray | None = None
    tip_end: TipEnd = "unknown"

    def with_camera(self, camera: PlaneCamera, relief_mm: float = 0.0,
                    base_relief_mm: float | None = None) -> FingerKeypoints:
        """The same keypoints, in millimetres through another camera (e.g. a fitted plane).

        ``relief_mm``: how far the finger's front surface lies in front of ``camera``'s plane (a
        round finger's, about r). A flat-cut base is seen where the cut meets the front surface,
        so that nearer point is moved along the plane's normal onto the plane (in perspective, the
        cut edge seen lies farther from the image centre than the base itself: r / depth of its
        distance from the optical axis). With the gripper's body in view, the base is read on the
        body's edge instead: ``base_relief_mm`` says how far the body's face lies in front of the
        plane (None: on it).
        """
        import dataclasses

        # The rounded ends again, in the geometry of this camera: on a round finger they are half
        # spheres, whose outlines perspective stretches away from the image centre (by 1 / cos of the
        # view angle): fitted as spheres; on a flat front they are half discs in the plane, which a
        # tilted plane draws as half ellipses (off the optical axis, by several percent): fitted as
        # circles in the plane's millimetres. Facing the camera, the latter is the pixel fit.
        if relief_mm > 0.5 * self.half_thickness_px * float(camera.local_mm_per_px(self.tip_px)):
            def centre(outline):
                return _sphere_centre_px(outline, camera)
        else:
            def centre(outline):
                return camera.mm_to_px(_circle_centre(camera.px_to_mm(outline)))
        ends = {}
        if self.tip_cap_px is not None:
            ends["tip_px"] = centre(self.tip_cap_px)
        if self.base_end == "rounded" and self.base_cap_px is not None:
            ends["base_px"] = centre(self.base_cap_px)
        if ends:
            centreline = self.centreline_px.copy()
            centreline[0] = ends.get("base_px", centreline[0])
            centreline[-1] = ends.get("tip_px", centreline[-1])
            self = dataclasses.replace(self, centreline_px=centreline, **ends)
        if self.body_in_view:
            front = base_relief_mm or 0.0
        else:
            # The cut is found along lines across the finger (their mean), where the front surface
            # stands _CUT_FRONT of the relief before the plane.
            front = _CUT_FRONT * relief_mm
        if self.base_end != "flat" or front == 0.0:
            return dataclasses.replace(self, camera=camera)
        # Across, the base is the middle of the sides (the silhouette, on the plane), so only the
        # shift along the finger applies.
        seen_at_front = camera.parallel(-front).px_to_mm(self.base_px)
        shift = camera.mm_to_px(seen_at_front) - self.base_px
        along = self.base_direction
        if along is None:  # the direction over 4 r: the first pixels may bend to a corner
            arc = _arc(self.centreline_px)
            along = _at(self.centreline_px, arc, min(4.0 * self.half_thickness_px, arc[-1])) - self.centreline_px[0]
            along = along / max(float(np.hypot(*along)), 1e-9)
        base_px = self.base_px + (shift @ along) * along
        rest = self.centreline_px[1:]
        rest = rest[(rest - base_px) @ along > 0.0]  # the centre beyond the moved base only
        centreline = np.vstack([base_px, rest])
        return dataclasses.replace(self, camera=camera, base_px=base_px, centreline_px=centreline)

    @property
    def base_mm(self) -> np.ndarray:
        """(2,) base point in the gripper plane, mm."""
        return self.camera.px_to_mm(self.base_px)

    @property
    def tip_mm(self) -> np.ndarray:
        """(2,) tip point in the gripper plane, mm."""
        return self.camera.px_to_mm(self.tip_px)

    @property
    def centreline_mm(self) -> np.ndarray:
        """(K, 2) centreline in the gripper plane, mm, base first."""
        return self.camera.px_to_mm(self.centreline_px)

    @property
    def half_thickness_mm(self) -> float:
        """Half-width r in mm: half the median width across the finger, measured in mm."""
        if self.width_edges_px is None or len(self.width_edges_px) == 0:
            middle = self.centreline_px[len(self.centreline_px) // 2]
            return float(self.half_thickness_px * self.camera.local_mm_per_px(middle))
        edges = self.camera.px_to_mm(self.width_edges_px)
        return 0.5 * float(np.median(np.hypot(*(edges[:, 1] - edges[:, 0]).T)))

    @property
    def length_mm(self) -> float:
        """Base-to-tip distance, mm: the finger length L when the finger is open (eq. 5)."""
        return finger_length(self.base_mm, self.tip_mm)

    @property
    def arc_length_mm(self) -> float:
        """Length of the centreline from base to tip, mm (L for any pose of an inextensible finger)."""
        return float(np.hypot(*np.diff(self.centreline_mm, axis=0).T).sum())

    @property
    def theta(self) -> float:
        """Entire bending angle from this (closed, untouched) finger, rad (eq. 4), from mm coordinates."""
        return theta_from_closed(self.base_mm, self.tip_mm, self.side)

    def observed_mm(self, n_links: int) -> np.ndarray:
        """(N+1, 2) the paper's observed positions (eq. 10): the centreline in N equal arc lengths, mm."""
        return resample_polyline(self.centreline_mm, n_links)

    def observed_px(self, n_links: int) -> np.ndarray:
        """(N+1, 2) the observed positions of :meth:`observed_mm` in pixels (for drawing)."""
        return self.camera.mm_to_px(self.observed_mm(n_links))


def finger_length(base: ArrayLike, tip: ArrayLike) -> float:
    """Eq. 5: the distance between base (2,) and tip (2,), in their unit.

    Example:
        >>> finger_length([0.0, 0.0], [3.0, 4.0])
        5.0
    """
    return float(np.hypot(*(np.asarray(tip, np.float64) - np.asarray(base, np.float64))))


def theta_from_closed(base: ArrayLike, tip: ArrayLike, side: Side = "left", gripper_angle: float = 0.0) -> float:
    """Eq. 4: the entire bending angle from a closed finger's base (2,) and tip (2,) (mm or px).

    ``atan((x_tip - x_base) / (y_tip - y_base))`` for the left finger, x and y along the gripper's
    axes: ``gripper_angle`` (rad) is the angle of the gripper's "down" from the image's downward
    vertical, positive toward +x (0: the fingers hang down the image; a camera rolled about its axis
    gives another angle, e.g. from the line through both bases). For the right finger the offset
    across the gripper is mirrored, so a right finger curling toward the centre also gives a
    positive angle. Use millimetres when fx != fy (pixels are not square then).

    Raises:
        KeypointError: the tip is not below the base (eq. 4 undefined), or a bad side.

    Example:
        >>> round(theta_from_closed([0.0, 0.0], [10.0, 50.0]), 4), round(theta_from_closed([0.0, 0.0], [-10.0, 50.0], "right"), 4)
        (0.1974, 0.1974)
        >>> round(theta_from_closed([0.0, 0.0], [10.0, 50.0], gripper_angle=0.1), 4)  # a gripper turned by 0.1 rad
        0.0974
    """
    sign = _sign(side)
    d = np.asarray(tip, np.float64) - np.asarray(base, np.float64)
    down = np.array([np.sin(gripper_angle), np.cos(gripper_angle)])
    across = np.array([down[1], -down[0]])
    dx, dy = float(d @ across), float(d @ down)
    if not dy > 0:
        raise KeypointError(f"the {side} finger's tip {np.asarray(tip).tolist()} is not below its base "
                            f"{np.asarray(base).tolist()} (y down): eq. 4 needs a bending angle below pi/2; "
                            f"is this a frame of the closed gripper without an object?")
    return float(np.arctan(sign * dx / dy))


def gripper_angle(left_base: ArrayLike, right_base: ArrayLike) -> float:
    """The angle (rad) of a gripper's "down" from the image's downward vertical, positive toward +x,
    from its two finger bases (2,): perpendicular to the line from the left base to the right one.

    Example:
        >>> gripper_angle([0.0, 0.0], [10.0, 0.0]), round(gripper_angle([0.0, 0.0], [10.0, -1.0]), 4)
        (0.0, 0.0997)
    """
    d = np.asarray(right_base, np.float64) - np.asarray(left_base, np.float64)
    return float(np.arctan2(-d[1], d[0])) + 0.0  # no -0.0


def resample_polyline(points: ArrayLike, n: int) -> np.ndarray:
    """Divide a polyline (K, 2), K >= 2, into ``n`` parts of equal arc length.

    Returns:
        (n+1, 2) float64 points at arc lengths k S / n, k = 0..n (first and last points kept).

    Example:
        >>> resample_polyline([[0.0, 0.0], [0.0, 10.0], [10.0, 10.0]], 4).tolist()
        [[0.0, 0.0], [0.0, 5.0], [0.0, 10.0], [5.0, 10.0], [10.0, 10.0]]
    """
    points = np.asarray(points, dtype=np.float64)
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise KeypointError(f"resample_polyline: n must be an integer >= 1, got {n!r}")
    if points.ndim != 2 or points.shape[1] != 2 or points.shape[0] < 2:
        raise KeypointError(f"resample_polyline: points must have shape (K, 2) with K >= 2, got {points.shape}")
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(points, axis=0).T))])
    stations = np.linspace(0.0, arc[-1], n + 1)
    return np.column_stack([np.interp(stations, arc, points[:, 0]), np.interp(stations, arc, points[:, 1])])


def finger_keypoints(mask: np.ndarray, camera: PlaneCamera, side: Side, rounded_base: bool | None = None, *,
                     cut_column: float | None = None, coverage: np.ndarray | None = None) -> FingerKeypoints:
    """Base, tip, centreline and half-thickness of the finger in ``mask`` (module docstring).

    Args:
        mask: (H, W) bool, the finger (and possibly the part of the gripper's body it hangs from);
            only its largest 8-connected component is used.
        camera: the gripper plane's camera, for the millimetre views.
        side: ``"left"`` or ``"right"``: which finger it is (for Theta).
        rounded_base: None (default) detects the base end; True: the base end is a rounded cap
            (its centre is the base); False: the finger is cut flat at its base (the middle of the
            cut, or where it leaves a body in view, is the base).
        cut_column: the column (px) along which segmentation cut this finger from the other one
            (touching fingertips), or None; mask edges on it are not the finger's outline.
        coverage: (H, W) float, how much of each pixel on the finger's edge the finger covers
            (:func:`softgrip_vision.coverage.edge_coverage`), for edges at sub-pixel precision; None reads
            the mask's edges (halfway between pixel centres).

    Raises:
        KeypointError: an empty mask, one too short for its thickness to have two ends, or an end
            cut off by the image border.

    Example (pixels, and the finger's L in mm):
        >>> from pathlib import Path
        >>> import softgrip_vision
        >>> data = Path(softgrip_vision.__file__).resolve().parents[1] / "data"  # the sample frames
        >>> from softgrip_vision.frames import load_frame
        >>> from softgrip_vision.geometry import PlaneCamera
        >>> from softgrip_vision.segmentation import segment
        >>> frame = load_frame(data / "calib_open")
        >>> seg = segment(frame)
        >>> k = finger_keypoints(seg.left_finger, PlaneCamera.from_frame(frame, seg.fingers), "left")
        >>> k.centreline_px.shape[1], round(k.length_mm), k.base_end, k.body_in_view
        (2, 52, 'rounded', False)
    """
    _sign(side)
    finger, contour = _finger_region(np.asarray(mask, dtype=bool), side)
    inside = cv2.distanceTransform(finger.view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    ridge = _ridge(finger, inside)
    line = _smooth(resample_polyline(ridge, max(1, int(np.ceil(_arc(ridge)[-1])))))
    arc = _arc(line)
    clearance = _bilinear(inside, line)
    radius = float(np.median(clearance[len(line) // 2:]))  # rough r (px) from the tip's half
    if arc[-1] < 4.0 * radius:
        raise KeypointError(f"the {side} finger is too short to find its base and tip ({arc[-1]:.0f} px long "
                            f"for a half-thickness of {radius:.0f} px): is the whole finger in view?")
    sampler = _Sampler(finger if coverage is None else np.where(_band(finger), coverage, finger))
    if cut_column is not None:  # the cut is not the finger's outline
        contour = contour[np.abs(contour[:, 0] - cut_column) > 1.0]
    tip, tip_cap = _cap_centre(line[::-1], radius, contour, sampler, f"{side} finger's tip", cut_column)
    intr = camera.intrinsics
    optics = (np.array([intr.ppx, intr.ppy]), 0.5 * (intr.fx + intr.fy))
    end_ = _base(sampler, line, arc, clearance, radius, rounded_base, contour, f"{side} finger's base", optics)
    tip_end = _tip_end(sampler, line, radius, f"{side} finger's tip", optics, cut_column)
    base, end, body, base_cap, base_direction = end_.point, end_.kind, end_.body, end_.cap, end_.direction
    first = int(np.argmin(np.hypot(*(line - base).T)))
    last = int(np.argmin(np.hypot(*(line - tip).T)))
    if last <= first + 1:
        raise KeypointError(f"the {side} finger's base and tip could not be told apart: is the whole finger in "
                            f"view and separate from the other finger?")
    if end_.lead_in is None:
        centreline = np.vstack([base, line[first + 1:last], tip])
    else:  # near a cut the ridge bends to the cut's corners: the centre of the sides instead
        resume = max(int(np.searchsorted(arc, end_.lead_in_to, side="right")), first + 1)
        if resume >= last:
            raise KeypointError(f"the {side} finger is too short beyond its base to follow: is the whole finger in "
                                f"view?")
        centreline = np.vstack([base, end_.lead_in[1:], line[resume:last], tip])
    edges = _width_edges(sampler, centreline, radius)
    half_thickness = 0.5 * float(np.median(np.hypot(*(edges[:, 1] - edges[:, 0]).T))) if len(edges) else radius
    axis = _direction(line, arc, arc[first] + radius, arc[first] + 3.0 * radius)
    region = finger & _beyond(finger.shape, base, axis)
    return FingerKeypoints(side=side, base_px=base, tip_px=tip, centreline_px=centreline,
                           half_thickness_px=half_thickness, camera=camera, base_end=end, body_in_view=body,
                           width_edges_px=edges, region=region, tip_cap_px=tip_cap, base_cap_px=base_cap,
                           base_direction=base_direction, tip_end=tip_end)


def gripper_keypoints(segmentation: Segmentation, camera: PlaneCamera, rounded_base: bool | None = None, *,
                      color: np.ndarray | None = None) -> tuple[FingerKeypoints, FingerKeypoints]:
    """(left, right) keypoints of a segmented frame (see :func:`finger_keypoints`); when segmentation
    cut the fingers apart at its centre column, edges on that column are not used. With the
    frame's ``color`` (H, W, 3), edges are read at sub-pixel precision from each edge pixel's colour
    (:func:`softgrip_vision.coverage.edge_coverage`).

    Example (L of both fingers, eq. 5, from the open sample frame, mm):
        >>> from pathlib import Path
        >>> import softgrip_vision
        >>> data = Path(softgrip_vision.__file__).resolve().parents[1] / "data"  # the sample frames
        >>> from softgrip_vision.frames import load_frame
        >>> from softgrip_vision.geometry import PlaneCamera
        >>> from softgrip_vision.segmentation import segment
        >>> frame = load_frame(data / "calib_open")
        >>> seg = segment(frame)
        >>> left, right = gripper_keypoints(seg, PlaneCamera.from_frame(frame, seg.fingers))
        >>> [round(finger_length(k.base_mm, k.tip_mm)) for k in (left, right)]
        [52, 52]
    """
    cut = _cut_column(segmentation)
    masks = (segmentation.left_finger, segmentation.right_finger)
    coverages = [None, None] if color is None else [edge_coverage(color, mask) for mask in masks]
    left, right = (finger_keypoints(mask, camera, side, rounded_base, cut_column=cut, coverage=coverage)
                   for mask, side, coverage in zip(masks, SIDES, coverages))
    return left, right


def _cut_column(segmentation: Segmentation) -> float | None:
    """The column (px) segmentation cut the fingers apart at (every split but two separate
    components), None when the fingers were separate regions."""
    return None if segmentation.split == "components" else float(segmentation.center_column)


def _sign(side: str) -> float:
    if side not in ("left", "right"):
        raise KeypointError(f"side must be 'left' or 'right', got {side!r}")
    return 1.0 if side == "left" else -1.0


def _finger_region(mask: np.ndarray, side: str) -> tuple[np.ndarray, np.ndarray]:
    """The largest 8-connected component of a 2-D mask with its holes filled, bool (H, W), and its
    outer boundary pixels (P, 2) (u, v), float64."""
    if mask.ndim != 2 or not mask.any():
        raise KeypointError(f"the {side} finger's mask is empty (or not 2-D, shape {mask.shape}): "
                            f"segment the frame first (softgrip_vision.segmentation.segment)")
    # On the mask's box one pixel wider (the image's edge where it meets it): the same components,
    # in the same order, and the same contour, moved by the box's corner.
    rows, cols = box(mask, 1) or (slice(None), slice(None))
    crop = np.ascontiguousarray(mask[rows, cols])
    _, labels, stats, _ = cv2.connectedComponentsWithStats(crop.view(np.uint8), connectivity=8)
    largest = (labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))).view(np.uint8)
    contours, _ = cv2.findContours(largest, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    filled = np.zeros(mask.shape, bool)
    filled[rows, cols] = cv2.drawContours(np.zeros_like(largest), contours, -1, 1, thickness=cv2.FILLED).view(bool)
    corner = np.array([cols.start or 0, rows.start or 0], np.float64)
    return filled, contours[0].reshape(-1, 2).astype(np.float64) + corner


def _ridge(finger: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """The finger's medial path: (K, 2) pixel centres (u, v) from the middle of the top row to the
    pixel geodesically farthest from it; ``depth`` (H, W) is the mask's distance transform."""
    where = box(finger, 0)  # the graph needs only the finger's box (the same nodes, in the same order)
    if where is None:
        raise KeypointError("the finger's mask is empty: no medial path")
    finger, depth = finger[where], depth[where]
    r, c = np.nonzero(finger)
    index = np.full(finger.shape, -1, np.int64)
    index[r, c] = np.arange(r.size)
    height, width = finger.shape
    head_parts, tail_parts, length_parts, clearance_parts = [], [], [], []
    for dr, dc in _STEPS:
        rr, cc = r + dr, c + dc
        ok = (rr < height) & (cc >= 0) & (cc < width)
        neighbour = np.full(r.size, -1, np.int64)
        neighbour[ok] = index[rr[ok], cc[ok]]
        linked = neighbour >= 0
        head_parts.append(np.flatnonzero(linked))
        tail_parts.append(neighbour[linked])
        length_parts.append(np.full(linked.sum(), np.hypot(dr, dc)))
        clearance_parts.append(np.minimum(depth[r[linked], c[linked]], depth[rr[linked], cc[linked]]))
    heads, tails, lengths, clearances = map(np.concatenate, (head_parts, tail_parts, length_parts, clearance_parts))

    def graph(weights: np.ndarray) -> csr_matrix:
        return csr_matrix((weights, (heads, tails)), shape=(r.size, r.size))

    top_row = np.flatnonzero(r == r.min())
    start = int(top_row[np.argmin(np.abs(c[top_row] - c[top_row].mean()))])
    # (cast: dijkstra takes one int index, as scipy documents, but scipy-stubs lists only arrays)
    end = int(np.argmax(dijkstra(graph(lengths), directed=False, indices=cast(Any, start))))
    cost = lengths * (depth.max() / clearances) ** _RIDGE_POWER
    _, predecessor = dijkstra(graph(cost), directed=False, indices=cast(Any, end), return_predecessors=True)
    path = [start]
    while path[-1] != end:
        path.append(int(predecessor[path[-1]]))
    return np.column_stack([c[path] + where[1].start, r[path] + where[0].start]).astype(np.float64)


def _arc(points: np.ndarray) -> np.ndarray:
    """(K,) arc length along a polyline (K, 2) from its first point."""
    return np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(points, axis=0).T))])


def _smooth(points: np.ndarray) -> np.ndarray:
    """(K, 2) a polyline sampled every pixel, Gaussian-smoothed along its length (ends replicated)."""
    blurred = cv2.GaussianBlur(points.reshape(-1, 1, 2), (1, 0), sigmaX=0.0, sigmaY=_SMOOTH_SIGMA_PX,
                               borderType=cv2.BORDER_REPLICATE)
    return blurred.reshape(-1, 2)


def _at(line: np.ndarray, arc: np.ndarray, s: float) -> np.ndarray:
    """(2,) the point of polyline ``line`` at arc length ``s`` (clamped to its ends)."""
    return np.array([np.interp(s, arc, line[:, 0]), np.interp(s, arc, line[:, 1])])


def _direction(line: np.ndarray, arc: np.ndarray, s0: float, s1: float) -> np.ndarray:
    """(2,) unit vector from the line's point at arc length s0 to the one at s1."""
    d = _at(line, arc, s1) - _at(line, arc, s0)
    return d / max(float(np.hypot(*d)), 1e-12)


_REMAP_ROWS = 32_000  # below OpenCV remap's SHRT_MAX limit on a map's rows


def _bilinear(image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(...,) bilinear samples of a float image at points (..., 2) (u, v); 0 outside."""
    p = np.asarray(points, np.float32).reshape(-1, 1, 2)
    image = np.asarray(image, np.float32)
    # OpenCV's remap takes maps of fewer than 2**15 rows: sample in blocks of that many points.
    out = [cv2.remap(image, block[..., 0], block[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=0.0).reshape(-1)
           for block in np.array_split(p, max(1, -(-len(p) // _REMAP_ROWS)))]
    return np.concatenate(out).reshape(np.asarray(points).shape[:-1])


class _Sampler:
    """Sub-pixel edges of a part along straight lines, from its coverage image (:mod:`softgrip_vision.coverage`:
    1 inside, 0 outside, the fraction covered on the edge pixels; or a 0/1 mask)."""

    def __init__(self, coverage: np.ndarray) -> None:
        self.coverage = np.asarray(coverage, np.float32)  # (read only: no copy when already float32)
        self.shape = coverage.shape

    def exits(self, starts: np.ndarray, direction: np.ndarray, reach: float, entering: bool = False) -> np.ndarray:
        """(K, 2) where each line from ``starts`` (K, 2) along ``direction`` (2,) or (K, 2) leaves the
        part (or enters it, with ``entering``) within ``reach`` px; NaN where it does not, or where the
        line runs off the image first.

        The edge is found where the bilinear coverage first drops below 1/2, and placed by the
        coverage integrated along the line from its start to one pixel past that point: the distance
        to a step edge whatever its sub-pixel position (the midpoint between pixel centres for a
        0/1 mask)."""
        starts = np.atleast_2d(np.asarray(starts, np.float64))
        direction = np.broadcast_to(np.asarray(direction, np.float64), starts.shape)
        steps = np.arange(0.0, reach + 1.0 + _SAMPLE_STEP_PX, _SAMPLE_STEP_PX)
        points = starts[:, None] + steps[None, :, None] * direction[:, None]
        values = _bilinear(self.coverage, points)
        if entering:
            values = 1.0 - values
        outside = values < 0.5
        first = np.argmax(outside, axis=1)
        found = outside.any(axis=1) & (values[:, 0] >= 0.5) & (steps[first] <= reach)
        beyond = np.minimum(first + int(round(1.0 / _SAMPLE_STEP_PX)), len(steps) - 1)
        upto = np.arange(len(steps))[None, :] <= beyond[:, None]
        trapezoids = 0.5 * (values[:, 1:] + values[:, :-1]) * _SAMPLE_STEP_PX
        distance = (trapezoids * upto[:, 1:]).sum(axis=1)
        hit = starts + distance[:, None] * direction
        off = (hit < 0.0).any(axis=1) | (hit[:, 0] > self.shape[1] - 1) | (hit[:, 1] > self.shape[0] - 1)
        hit[~found | off] = np.nan
        return hit


def _circle_centre(points: np.ndarray) -> np.ndarray:
    """(2,) centre of the least-squares (Kasa) circle through points (K, 2), K >= 3."""
    design = np.column_stack([2.0 * points, np.ones(len(points))])
    solution, *_ = np.linalg.lstsq(design, (points**2).sum(axis=1), rcond=None)
    return solution[:2]


def _sphere_centre_px(outline_px: np.ndarray, camera: PlaneCamera) -> np.ndarray:
    """(2,) the pixel of the centre of a sphere whose outline passes through ``outline_px`` (K, 2).

    A sphere's outline is a cone of rays about the ray to its centre: unit rays d_k with
    d_k . c = cos(alpha), a plane through their tips. So w solving d_k . w = 1 by least squares is
    that plane's normal, and the centre's ray is w / |w| (exact in perspective, where a circle fitted
    to the outline in pixels lies off-centre by up to the outline's stretch, a pixel here).
    """
    rays = camera.rays(outline_px)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    w, *_ = np.linalg.lstsq(rays, np.ones(len(rays)), rcond=None)
    i = camera.intrinsics
    return np.array([i.fx * w[0] / w[2] + i.ppx, i.fy * w[1] / w[2] + i.ppy])


def _lines_across(centre: np.ndarray, axis: np.ndarray, radius: float, reach: float = _CAP_REACH) -> np.ndarray:
    """(_LINES, 2) starts of lines parallel to ``axis`` spread over +-reach r across the finger."""
    normal = np.array([-axis[1], axis[0]])
    return centre + np.linspace(-reach, reach, _LINES)[:, None] * radius * normal


def _end_points(sampler: _Sampler, line: np.ndarray, arc: np.ndarray, s_in: float, s_out: float,
                radius: float, what: str, cut_column: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Points (K, 2) where lines parallel to the line's stretch [s_in, s_out], from s_in across
    the finger, leave the mask at its end; and that direction (2,). Points on the cut column or
    the image border are dropped; too few of them raise a KeypointError naming ``what``."""
    axis = _direction(line, arc, s_in, s_out)
    hits = sampler.exits(_lines_across(_at(line, arc, s_in), axis, radius), axis, abs(s_out - s_in) + 3.0 * radius)
    keep = np.isfinite(hits).all(axis=1)
    if cut_column is not None:
        keep &= np.abs(hits[:, 0] - cut_column) > 1.0
    if keep.sum() < 5:
        raise KeypointError(f"the {what} is cut off by the image border (or hidden), so its end cannot be "
                            f"found: keep the whole finger in view")
    return hits[keep], axis


def _cap_centre(line: np.ndarray, radius: float, contour: np.ndarray, sampler: _Sampler,
                what: str, cut_column: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(2,) centre of the rounded end at ``line[0]``: a circle fitted to its outline; and the
    outline points (K, 2) it was fitted to.

    ``line`` (K, 2) is the smoothed ridge starting at that end. The cap's centre lies about
    ``radius`` inside the end, and the ridge's direction another radius further in points out of
    the cap. The outline is read at sub-pixel level (``sampler``) along rays from that rough centre
    fanned over the cap's half circle, so a mask's staircase or pixel phase does not bias the
    centre; rays that end on the cut column (where segmentation cut touching fingers apart) are not
    used. The mask's boundary pixels ahead of the rough centre (``contour``) tell whether the cap
    touches the image border, and stand in if too few rays find the outline.
    """
    arc = _arc(line)
    rough, inner = _at(line, arc, radius), _at(line, arc, 2.0 * radius)
    outward = (rough - inner) / np.hypot(*(rough - inner))
    offset = contour - rough
    cap = contour[(offset @ outward > 0.0) & (np.hypot(*offset.T) < 2.0 * radius)]
    on_border = len(cap) and ((cap.min(axis=0) <= 0).any() or
                              (cap.max(axis=0) >= np.array(sampler.shape[::-1]) - 1).any())
    if len(cap) < 5 or on_border:
        raise KeypointError(f"the {what} is cut off by the image border (or hidden), so its rounded end "
                            f"cannot be found: keep the whole finger in view")
    angles = np.linspace(-_CAP_FAN, _CAP_FAN, _LINES)
    across = np.array([-outward[1], outward[0]])
    directions = np.cos(angles)[:, None] * outward + np.sin(angles)[:, None] * across
    hits = sampler.exits(np.broadcast_to(rough, directions.shape), directions, 3.0 * radius)
    keep = np.isfinite(hits).all(axis=1)
    if cut_column is not None:
        keep &= np.abs(hits[:, 0] - cut_column) > 1.0
    if keep.sum() >= _LINES // 2:
        cap = hits[keep]
    return _circle_centre(cap), cap


class _End(NamedTuple):
    """A finger's base end: ``point`` (2,) px; ``kind``; ``body`` in view; a rounded end's outline
    points ``cap`` (K, 2) px or None; a flat end's unit ``direction`` (2,) square to the cut, into the
    finger, or None; and for a flat end the finger's centre from the base on, ``lead_in`` (K, 2) px,
    up to the ridge's arc length ``lead_in_to`` (px), or None."""

    point: np.ndarray
    kind: BaseEnd
    body: bool
    cap: np.ndarray | None = None
    direction: np.ndarray | None = None
    lead_in: np.ndarray | None = None
    lead_in_to: float = 0.0


def _base(sampler: _Sampler, line: np.ndarray, arc: np.ndarray, clearance: np.ndarray, radius: float,
          rounded: bool | None, contour: np.ndarray, what: str,
          optics: tuple[np.ndarray, float]) -> _End:
    """The base end at the top end of ``line`` (see :class:`_End`).

    ``optics``: the principal point (2,) and focal length, px. The end is told by the curvature of
    its outline across the finger: a rounded cap's is a half circle's; a flat cut's is 0, except that
    the cut's edge on a round finger's front surface (nearer the camera than its sides) bulges
    outward in perspective, by the fraction q = (distance of the end from the principal point
    outward along the finger) / focal length of a half circle; the threshold lies midway.
    """
    wide = np.flatnonzero(clearance[: len(line) // 2] > _BODY_GROWTH * radius)
    if wide.size:  # the ridge runs out of something wider than the finger: the gripper's body
        s_finger = arc[wide.max()] + 2.0 * radius
        centre = _CentreCurve(sampler, line, arc, s_finger, s_finger + 4.0 * radius, radius, what)
        up, normal = centre.frame(s_finger)
        start = centre(s_finger)
        offsets = np.concatenate([np.linspace(1.2, 3.0, 8), -np.linspace(1.2, 3.0, 8)]) * radius
        hits = sampler.exits(start + offsets[:, None] * normal, up, 6.0 * radius, entering=True)
        found = np.isfinite(hits).all(axis=1)
        if found.sum() < 2:
            raise KeypointError(f"the {what} meets the gripper's body, but the body's edge beside the finger "
                                f"cannot be found: keep the finger's base in view")
        # The body's edge is the line through the points found (on one side or both: a body may end
        # flush with a finger's outer side); the base is where the finger's centre curve crosses it,
        # which holds for a finger leaving the body at an angle as for a straight one.
        edge = hits[found]
        direction = np.linalg.svd(edge - edge.mean(axis=0))[2][0]
        into = np.array([-direction[1], direction[0]])
        into = into if into @ up < 0.0 else -into
        s_base = centre.crossing(s_finger, edge.mean(axis=0), into, 6.0 * radius)
        s_ridge = s_finger + 4.0 * radius
        return _End(centre(s_base), "flat", True, direction=into, lead_in=centre.stretch(s_base, s_ridge),
                    lead_in_to=s_ridge)
    if rounded is None or rounded:
        try:
            looks_rounded = _end_looks_rounded(sampler, line, arc, radius, what, optics)
        except KeypointError:
            if rounded:
                raise
            looks_rounded = False
        if rounded or looks_rounded:
            cap_centre, cap = _cap_centre(line, radius, contour, sampler, what)
            return _End(cap_centre, "rounded", False, cap=cap)
    # Stations from 2.5 r on: nearer the cut the distance transform's ridge forks toward its corners
    # (more so when a round finger's cut bulges in perspective), and its direction there would
    # tilt the lines across the finger.
    s_in = 2.5 * radius
    centre = _CentreCurve(sampler, line, arc, 2.5 * radius, 6.0 * radius, radius, what)
    up, _ = centre.frame(s_in)
    hits = sampler.exits(_lines_across(centre(s_in), up, radius), up, 3.0 * radius)
    if (hits[:, 1] < 1.0).any() or np.isnan(hits).sum() > 2 * (_LINES // 2):
        raise KeypointError(f"the {what} is cut off by the image border: keep the whole finger in view")
    # Fitted again nearer the cut, across that curve rather than the ridge: a quadratic followed
    # 2.5 r past its stretch misses the centre of a bent finger (a circle's next term) by a pixel
    # at Theta 0.8, which tilts Theta (eq. 4) by 0.01 rad; followed 0.6 r, by a few hundredths.
    centre = centre.refitted(sampler, _NEAR_CUT * radius, 4.0 * radius, radius, what)
    # The cut is square to the finger where it ends, through the mean of its edge points (where a
    # round finger's cut bulges, lopsided, in perspective): the base is where the centre curve
    # crosses it, with the curve's own direction there (the finger may bend right below its base,
    # and the lines ran along its direction 2.5 r in).
    middle = np.nanmean(hits, axis=0)
    into = -up
    for _ in range(2):
        into = -centre.frame(centre.crossing(s_in, middle, into, 3.0 * radius))[0]
    # Again with the lines along the finger's direction at the cut, from just inside it: on a bent
    # finger the first lines (along its direction 2.5 r in) drift toward one side, and those near it
    # leave through the side before they reach the cut (pulling the base toward the tip).
    s_cut = centre.crossing(s_in, middle, into, 3.0 * radius)
    toward, _ = centre.frame(s_cut)
    hits = sampler.exits(_lines_across(centre(s_cut + _NEAR_CUT * radius), toward, radius), toward,
                         (_NEAR_CUT + 3.0) * radius)
    if np.isfinite(hits).all(axis=1).sum() >= _LINES // 2:
        middle = np.nanmean(hits, axis=0)
        for _ in range(2):
            into = -centre.frame(centre.crossing(s_in, middle, into, 3.0 * radius))[0]
    s_base = centre.crossing(s_in, middle, into, 3.0 * radius)
    s_ridge = 6.0 * radius
    return _End(centre(s_base), "flat", False, direction=into, lead_in=centre.stretch(s_base, s_ridge),
                lead_in_to=s_ridge)


def _end_looks_rounded(sampler: _Sampler, line: np.ndarray, arc: np.ndarray, radius: float, what: str,
                       optics: tuple[np.ndarray, float], cut_column: float | None = None,
                       stretch: tuple[float, float] = (2.5, 1.0)) -> bool:
    """Whether the finger's end at ``line[0]`` looks like a rounded cap rather than a flat cut,
    by the curvature of its outline across the finger (see :func:`_base`); the lines run along the
    line's direction over ``stretch`` (from, to: arc lengths in units of ``radius``).

    Raises:
        KeypointError: too few points of the end's outline (cut off by the border, or hidden).
    """
    top = _at(line, arc, 0.0)
    points, axis = _end_points(sampler, line, arc, stretch[0] * radius, stretch[1] * radius, radius, what,
                               cut_column)
    across = (points - top) @ np.array([-axis[1], axis[0]])
    along = (points - top) @ axis
    curvature = np.polyfit(across, along, 2)[0]
    principal, focal = optics
    q = max(0.0, float((top - principal) @ axis) / focal)
    return bool(curvature < 0.5 * (1.0 + q) * _HALF_CIRCLE_CURVATURE / radius)


def _tip_end(sampler: _Sampler, line: np.ndarray, radius: float, what: str, optics: tuple[np.ndarray, float],
             cut_column: float | None) -> TipEnd:
    """What the tip end at ``line[-1]`` looks like: ``"rounded"`` (a cap: every finger's tip),
    ``"flat"`` (cut square: the base end of an upside-down frame) or ``"unknown"`` (too little of
    its outline found, e.g. where segmentation cut it apart from the other fingertip)."""
    reverse = line[::-1]
    try:
        # The ridge ends at the farthest pixel: at a flat end, one of its corners (the distance
        # transform's ridge forks there within about r): its direction from 2 r to 4 r in.
        rounded = _end_looks_rounded(sampler, reverse, _arc(reverse), radius, what, optics, cut_column,
                                     stretch=_TIP_STRETCH)
        return "rounded" if rounded else "flat"
    except KeypointError:
        return "unknown"


class _CentreCurve:
    """The finger's centre over a stretch of the ridge: midpoints of its two sides at stations
    every pixel of arc length in [s_lo, s_hi], fitted by a quadratic in the arc length (so that it
    can be followed a little beyond the stretch, e.g. to where the finger leaves the body)."""

    def __init__(self, sampler: _Sampler, line: np.ndarray, arc: np.ndarray, s_lo: float, s_hi: float,
                 radius: float, what: str) -> None:
        stations = np.arange(s_lo, s_hi, 1.0)
        centres = np.stack([_at(line, arc, s) for s in stations])
        tangents = np.stack([_direction(line, arc, s - radius, s + radius) for s in stations])
        self.coefficients = self._fit(sampler, stations, centres, tangents, radius, what)

    @staticmethod
    def _fit(sampler: _Sampler, stations: np.ndarray, centres: np.ndarray, tangents: np.ndarray, radius: float,
             what: str) -> list[np.ndarray]:
        """Quadratics x(s), y(s) through the midpoints of the sides found across ``centres`` (K, 2),
        square to ``tangents`` (K, 2), at arc lengths ``stations`` (K,)."""
        normals = np.column_stack([-tangents[:, 1], tangents[:, 0]])
        sides = [sampler.exits(centres, sign * normals, 3.0 * radius) for sign in (1.0, -1.0)]
        middle = 0.5 * (sides[0] + sides[1])
        ok = np.isfinite(middle).all(axis=1)
        if ok.sum() < 5:
            raise KeypointError(f"the sides of the finger near its {what.split()[-1]} cannot be found: keep "
                                f"the whole finger in view")
        return [np.polyfit(stations[ok], middle[ok, k], 2) for k in (0, 1)]

    def refitted(self, sampler: _Sampler, s_lo: float, s_hi: float, radius: float, what: str) -> _CentreCurve:
        """The curve fitted again over [s_lo, s_hi], with the stations and the lines across the
        finger taken on this curve (not on the ridge, which forks near a cut end)."""
        stations = np.arange(s_lo, s_hi, 1.0)
        centres = np.stack([self(s) for s in stations])
        tangents = -np.stack([self.frame(s)[0] for s in stations])
        curve = copy.copy(self)
        curve.coefficients = self._fit(sampler, stations, centres, tangents, radius, what)
        return curve

    def __call__(self, s: float) -> np.ndarray:
        """(2,) the centre at arc length ``s`` (px)."""
        return np.array([np.polyval(c, s) for c in self.coefficients])

    def stretch(self, s_from: float, s_to: float) -> np.ndarray:
        """(K, 2) points of the curve every pixel of arc from ``s_from`` to ``s_to`` (both included)."""
        return np.stack([self(t) for t in np.append(np.arange(s_from, s_to, 1.0), s_to)])

    def crossing(self, s: float, point: np.ndarray, normal: np.ndarray, reach: float) -> float:
        """The arc length (px) where the curve, followed from ``s`` toward the base for at most
        ``reach`` px, crosses the line through ``point`` (2,) square to ``normal`` (2,) (where it
        comes nearest the line if it does not cross it)."""
        trial = s - np.linspace(0.0, reach + 3.0, 400)
        side = (np.stack([self(t) for t in trial]) - point) @ normal
        change = np.flatnonzero(np.sign(side[1:]) != np.sign(side[:-1]))
        if change.size == 0:
            return float(trial[np.argmin(np.abs(side))])
        k = change[0]
        return float(trial[k] + (trial[k + 1] - trial[k]) * side[k] / (side[k] - side[k + 1]))

    def frame(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        """(toward the base, across) unit vectors (2,) at arc length ``s``."""
        d = -np.array([np.polyval(np.polyder(c), s) for c in self.coefficients])
        d /= np.hypot(*d)
        return d, np.array([-d[1], d[0]])


def _width_edges(sampler: _Sampler, centreline: np.ndarray, radius: float) -> np.ndarray:
    """(S, 2, 2) both side points across the finger at stations every r/2 between its ends."""
    arc = _arc(centreline)
    stations = np.arange(2.0 * radius, arc[-1] - 2.0 * radius, max(0.5 * radius, 1.0))
    if stations.size == 0:
        return np.zeros((0, 2, 2))
    centres = np.stack([_at(centreline, arc, s) for s in stations])
    tangents = np.stack([_direction(centreline, arc, s - radius, s + radius) for s in stations])
    normals = np.column_stack([-tangents[:, 1], tangents[:, 0]])
    sides = [sampler.exits(centres, sign * normals, 3.0 * radius) for sign in (1.0, -1.0)]
    pairs = np.stack(sides, axis=1)
    return pairs[np.isfinite(pairs).all(axis=(1, 2))]


def _band(mask: np.ndarray) -> np.ndarray:
    """bool (H, W): the pixels 4-adjacent to the mask's boundary, inside and outside."""
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    u8 = mask.view(np.uint8)
    return cv2.dilate(u8, cross).view(bool) & ~cv2.erode(u8, cross).view(bool)


def _beyond(shape: tuple[int, int], base: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """bool (H, W): pixels on the finger's side of the line through ``base`` across ``axis``."""
    h, w = shape  # the same arithmetic as on np.indices(shape), split by column and row
    across = (np.arange(w) - base[0]) * axis[0]
    down = (np.arange(h) - base[1]) * axis[1]
    return across[None, :] + down[:, None] >= 0.0
