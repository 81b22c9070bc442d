"""Finger keypoints from a finger mask: base, tip, centreline, L (eq. 5) and Theta (eq. 4).

A finger in the image is a tube of constant half-thickness r around its centreline, with rounded
ends (the centreline's ends are the centres of those end caps). From its mask:

1. **Centreline.** The finger's ridge: the cheapest 8-connected pixel path from the topmost pixel
   (the middle of the top row) to the pixel farthest from it inside the mask, each step costing its
   length times ``(D_max / D)^4`` with ``D`` OpenCV's exact distance transform of the mask, so the
   path keeps to the medial axis, however the finger curls (several points per row are fine). It is
   resampled every pixel and smoothed (Gaussian, sigma 2 px) to sub-pixel precision. Only the
   mask's largest component counts, with its holes (e.g. unfilled depth holes) filled.
2. **Tip and base.** The end caps are half-discs of radius r: each is a circle fitted (least squares)
   to the mask's contour points beyond the point r before the path's end (r roughly from the
   distance transform along the ridge), and its centre is the tip (or the base). A finger cut flat at the top,
   where it attaches to the gripper's body (``rounded_base=False``, e.g. with a segmentation region
   of interest that leaves the body out), has its base at the middle of its top edge instead.
3. The centreline is trimmed to run from base to tip; its arc length gives the half-thickness from
   the mask's area (a tube of length l and half-thickness r with two half-disc caps covers
   2 r l + pi r^2).

Everything is in pixels and, through a :class:`~vision.geometry.PlaneCamera`, in millimetres in the
gripper plane; angles and lengths are measured in millimetres. The mask itself is analysed as if
pixels were square: with fx != fy the rounded ends look slightly elliptic, which costs little (Theta
within 0.007 rad at 5 % anisotropy; a D405's fx and fy differ by well under 1 %). The left finger
curls toward +x; the right finger's Theta is measured toward -x (the scene mirrored about the
gripper's centre line, DESIGN section 3).

Uses ``scipy.sparse.csgraph.dijkstra`` for the path (scipy comes with jax).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import ArrayLike
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from softgrip_jax import SoftgripError
from vision.geometry import PlaneCamera
from vision.segmentation import Segmentation

Side = Literal["left", "right"]

_STEPS = ((0, 1), (1, 0), (1, 1), (1, -1))  # half of the 8 neighbours; the graph is undirected
_RIDGE_POWER = 4.0
_SMOOTH_SIGMA_PX = 2.0


class KeypointError(SoftgripError):
    """A finger mask from which base and tip cannot be found; the message says why."""


@dataclass(frozen=True, eq=False)
class FingerKeypoints:
    """Base, tip and centreline of one finger, in pixels; millimetres through ``camera``.

    Attributes:
        side: ``"left"`` (curls toward +x) or ``"right"``.
        base_px: (2,) base point (u, v), px: where the finger attaches.
        tip_px: (2,) tip point, px: the centre of the tip's rounded end.
        centreline_px: (K, 2) the centreline, px, base first and tip last, about 1 px apart.
        half_thickness_px: the finger's half-thickness r, px.
        camera: the gripper plane's camera.
    """

    side: Side
    base_px: np.ndarray
    tip_px: np.ndarray
    centreline_px: np.ndarray
    half_thickness_px: float
    camera: PlaneCamera

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
        """Half-thickness r in mm."""
        return self.half_thickness_px * self.camera.mm_per_px

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


def theta_from_closed(base: ArrayLike, tip: ArrayLike, side: Side = "left") -> float:
    """Eq. 4: the entire bending angle from a closed finger's base (2,) and tip (2,) (mm or px).

    ``atan((x_tip - x_base) / (y_tip - y_base))`` for the left finger; for the right one the
    horizontal offset is mirrored (-x), so a right finger curling toward the centre also gives a
    positive angle. Use millimetres when fx != fy (pixels are not square then).

    Raises:
        KeypointError: the tip is not below the base (eq. 4 undefined), or a bad side.

    Example:
        >>> round(theta_from_closed([0.0, 0.0], [10.0, 50.0]), 4), round(theta_from_closed([0.0, 0.0], [-10.0, 50.0], "right"), 4)
        (0.1974, 0.1974)
    """
    sign = _sign(side)
    dx, dy = np.asarray(tip, np.float64) - np.asarray(base, np.float64)
    if not dy > 0:
        raise KeypointError(f"the {side} finger's tip {np.asarray(tip).tolist()} is not below its base "
                            f"{np.asarray(base).tolist()} (y down): eq. 4 needs a bending angle below pi/2; "
                            f"is this a frame of the closed gripper without an object?")
    return float(np.arctan(sign * dx / dy))


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


def finger_keypoints(mask: np.ndarray, camera: PlaneCamera, side: Side, rounded_base: bool = True) -> FingerKeypoints:
    """Base, tip, centreline and half-thickness of the finger in ``mask``.

    Args:
        mask: (H, W) bool, the finger; only its largest 8-connected component is used.
        camera: the gripper plane's camera, for the millimetre views.
        side: ``"left"`` or ``"right"``: which finger it is (for Theta).
        rounded_base: True when the top end of the finger is rounded like the tip (a free-standing
            finger, as rendered); False when it is cut flat where it attaches (the gripper's body or
            the segmentation's region of interest), the base then being the middle of the top edge.

    Raises:
        KeypointError: an empty mask, or one too short for its thickness to have two ends.

    Example (pixels, and the finger's L in mm):
        >>> from pathlib import Path
        >>> import vision
        >>> from vision.frames import load_frame
        >>> data = Path(vision.__file__).resolve().parents[1] / "data"  # the sample frames
        >>> from vision.geometry import PlaneCamera
        >>> from vision.segmentation import segment
        >>> frame = load_frame(data / "calib_open")
        >>> seg = segment(frame)
        >>> k = finger_keypoints(seg.left_finger, PlaneCamera.from_frame(frame, seg.fingers), "left")
        >>> k.centreline_px.shape[1], round(k.length_mm)
        (2, 52)
    """
    _sign(side)
    finger, contour = _finger_region(np.asarray(mask, dtype=bool), side)
    ridge, ridge_depth = _ridge(finger)
    line = _smooth(resample_polyline(ridge, max(1, int(np.ceil(_arc(ridge)[-1])))))
    radius = float(ridge_depth.max())  # rough: distances between pixel centres run about 0.5 px long
    if _arc(line)[-1] < 4.0 * radius:
        raise KeypointError(f"the {side} finger is too short to find its base and tip ({_arc(line)[-1]:.0f} "
                            f"px long for a half-thickness of {radius:.0f} px): is the whole finger in view?")
    tip = _cap_centre(line[::-1], radius, contour, finger.shape, f"{side} finger's tip")
    if rounded_base:
        base = _cap_centre(line, radius, contour, finger.shape, f"{side} finger's base")
    else:
        base = _top_edge_centre(finger)
    first = int(np.argmin(np.hypot(*(line - base).T)))
    last = int(np.argmin(np.hypot(*(line - tip).T)))
    centreline = np.vstack([base, line[first + 1:last], tip])
    # The mask's area is 2 r l + c r^2 for a tube of length l with half-disc ends (c = pi for two).
    length, area, ends = _arc(centreline)[-1], float(finger.sum()), np.pi if rounded_base else np.pi / 2
    half_thickness = (np.sqrt(length**2 + ends * area) - length) / ends
    return FingerKeypoints(side=side, base_px=base, tip_px=tip, centreline_px=centreline,
                           half_thickness_px=float(half_thickness), camera=camera)


def gripper_keypoints(segmentation: Segmentation, camera: PlaneCamera,
                      rounded_base: bool = True) -> tuple[FingerKeypoints, FingerKeypoints]:
    """(left, right) keypoints of a segmented frame (see :func:`finger_keypoints`).

    Example (L of both fingers, eq. 5, from the open sample frame, mm):
        >>> from pathlib import Path
        >>> import vision
        >>> data = Path(vision.__file__).resolve().parents[1] / "data"  # the sample frames
        >>> from vision.frames import load_frame
        >>> from vision.geometry import PlaneCamera
        >>> from vision.segmentation import segment
        >>> frame = load_frame(data / "calib_open")
        >>> seg = segment(frame)
        >>> left, right = gripper_keypoints(seg, PlaneCamera.from_frame(frame, seg.fingers))
        >>> [round(finger_length(k.base_mm, k.tip_mm)) for k in (left, right)]
        [52, 52]
    """
    return (finger_keypoints(segmentation.left_finger, camera, "left", rounded_base),
            finger_keypoints(segmentation.right_finger, camera, "right", rounded_base))


def _sign(side: str) -> float:
    if side not in ("left", "right"):
        raise KeypointError(f"side must be 'left' or 'right', got {side!r}")
    return 1.0 if side == "left" else -1.0


def _finger_region(mask: np.ndarray, side: str) -> tuple[np.ndarray, np.ndarray]:
    """The largest 8-connected component of a 2-D mask with its holes filled, bool (H, W), and its
    outer boundary pixels (P, 2) (u, v), float64."""
    if mask.ndim != 2 or not mask.any():
        raise KeypointError(f"the {side} finger's mask is empty (or not 2-D, shape {mask.shape}): "
                            f"segment the frame first (vision.segmentation.segment)")
    _, labels, stats, _ = cv2.connectedComponentsWithStats(mask.view(np.uint8), connectivity=8)
    largest = (labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))).view(np.uint8)
    contours, _ = cv2.findContours(largest, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    filled = cv2.drawContours(np.zeros_like(largest), contours, -1, 1, thickness=cv2.FILLED)
    return filled.view(bool), contours[0].reshape(-1, 2).astype(np.float64)


def _ridge(finger: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The finger's medial path: (K, 2) pixel centres (u, v) from the middle of the top row to the
    pixel geodesically farthest from it, and (K,) the distance transform (px) along it."""
    rows, cols = np.nonzero(finger)
    top, left = rows.min() - 1, cols.min() - 1  # a crop with a one-pixel empty margin
    crop = np.zeros((rows.max() - top + 2, cols.max() - left + 2), np.uint8)
    r, c = rows - top, cols - left
    crop[r, c] = 1
    depth = cv2.distanceTransform(crop, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    index = np.full(crop.shape, -1, np.int64)
    index[r, c] = np.arange(r.size)
    heads, tails, lengths, clearances = [], [], [], []
    for dr, dc in _STEPS:
        neighbour = index[r + dr, c + dc]
        linked = neighbour >= 0
        heads.append(np.flatnonzero(linked))
        tails.append(neighbour[linked])
        lengths.append(np.full(linked.sum(), np.hypot(dr, dc)))
        clearances.append(np.minimum(depth[r[linked], c[linked]], depth[r[linked] + dr, c[linked] + dc]))
    heads, tails, lengths, clearances = map(np.concatenate, (heads, tails, lengths, clearances))

    def graph(weights: np.ndarray) -> csr_matrix:
        return csr_matrix((weights, (heads, tails)), shape=(r.size, r.size))

    top_row = np.flatnonzero(r == r.min())
    start = int(top_row[np.argmin(np.abs(c[top_row] - c[top_row].mean()))])
    end = int(np.argmax(dijkstra(graph(lengths), directed=False, indices=start)))
    cost = lengths * (depth.max() / clearances) ** _RIDGE_POWER
    _, predecessor = dijkstra(graph(cost), directed=False, indices=end, return_predecessors=True)
    path = [start]
    while path[-1] != end:
        path.append(int(predecessor[path[-1]]))
    return np.column_stack([c[path] + left, r[path] + top]).astype(np.float64), depth[r[path], c[path]]


def _arc(points: np.ndarray) -> np.ndarray:
    """(K,) arc length along a polyline (K, 2) from its first point."""
    return np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(points, axis=0).T))])


def _smooth(points: np.ndarray) -> np.ndarray:
    """(K, 2) a polyline sampled every pixel, Gaussian-smoothed along its length (ends replicated)."""
    blurred = cv2.GaussianBlur(points.reshape(-1, 1, 2), (1, 0), sigmaX=0.0, sigmaY=_SMOOTH_SIGMA_PX,
                               borderType=cv2.BORDER_REPLICATE)
    return blurred.reshape(-1, 2)


def _cap_centre(line: np.ndarray, radius: float, contour: np.ndarray, shape: tuple[int, int],
                what: str) -> np.ndarray:
    """(2,) centre of the rounded end at ``line[0]``: a circle fitted to the contour beyond it.

    ``line`` (K, 2) is the smoothed ridge starting at that end. The cap's centre lies about
    ``radius`` inside the end, and the ridge's direction another radius further in points out of
    the cap; the contour points ahead of the rough centre along it are the cap's half-circle.
    ``shape`` (H, W) is the image's: a cap touching the image border is cut off, not round.
    """
    arc = _arc(line)
    rough, inner = (np.array([np.interp(s, arc, line[:, 0]), np.interp(s, arc, line[:, 1])])
                    for s in (radius, 2.0 * radius))
    outward = (rough - inner) / np.hypot(*(rough - inner))
    offset = contour - rough
    cap = contour[(offset @ outward > 0.0) & (np.hypot(*offset.T) < 2.0 * radius)]
    on_border = (cap.min(axis=0) <= 0).any() or (cap.max(axis=0) >= np.array(shape[::-1]) - 1).any()
    if len(cap) < 5 or on_border:
        raise KeypointError(f"the {what} is cut off by the image border (or hidden), so its rounded end "
                            f"cannot be found: keep the whole finger in view")
    # Algebraic (Kasa) fit: |p|^2 = 2 c . p + (rho^2 - |c|^2), linear in c.
    design = np.column_stack([2.0 * cap, np.ones(len(cap))])
    solution, *_ = np.linalg.lstsq(design, (cap**2).sum(axis=1), rcond=None)
    return solution[:2]


def _top_edge_centre(finger: np.ndarray) -> np.ndarray:
    """(2,) middle of the top edge of the mask's top row: where a flat-cut finger attaches."""
    rows, cols = np.nonzero(finger)
    top = rows.min()
    return np.array([cols[rows == top].mean(), top - 0.5])
