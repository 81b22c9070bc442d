"""The paper's own contact prediction and deformation (section IV-B/C), done on pixels as it describes.

This is the reference a user following the paper would write with numpy and OpenCV, and what
``bench_paper_speed.py`` checks the JAX core against and times it against. No JAX here.

The procedure, one function per step (equation and figure numbers are the paper's):

1. :func:`draw_object`: the object's contour drawn filled on a black image (Fig. 7 c).
2. :func:`sweep_joints`: the finger discretised into N rigid links (eqs. 1-3) at closing progress s.
3. :func:`draw_finger`: those links drawn as lines 2r thick (r the finger's half-thickness) on a
   second black image (Fig. 7 d, e).
4. :func:`first_overlap`: s increased step by step from 0 to Theta; at each step the two images
   are ANDed; the first step whose AND is not empty is the first contact (Fig. 7 f). That step is
   then narrowed down by halving it a few times.
5. :func:`first_contact_point`: the overlapping pixels nearest P_base along the finger give P_g1
   on the finger's centreline and its arc length L_g1 (Fig. 7 g, eq. 6).
6. :func:`contact_link`: N_g1 = L_g1 / L * N (eq. 7); within half a link of N it is the tip.
7. :func:`dilated_contour` and :func:`second_contact`: the circle of radius L_g2 = L - L_g1 around
   P_g1 drawn on a black image and ANDed with the contour of the object dilated by r; the crossing
   with the largest y is where the tip would land (Fig. 8 a, b).
8. :func:`contact_angles`: Theta_o1 (P_base -> P_g1), Theta_o1o2 (P_g1 -> that crossing), both from
   the downward vertical, and Theta_remain = Theta - Theta_o1 (Fig. 8 c, eq. 8).
9. :func:`classify`: the four cases of Fig. 6.
10. :func:`deformed_joints`: the joints of the case's deformation (Figs. 9-11, eq. 9).

Conventions are the JAX core's (``softgrip_jax._contact`` and ``_deformation``), so that the two
can be compared number for number:

* image axes x right, y down, millimetres; the finger hangs from P_base toward +y and curls toward
  +x; angles in radians from the downward vertical, positive toward +x;
* "step by step" (Fig. 7 d, e) is by default the PCC sweep: at closing progress s every link turns
  by 2 s / N, so the chain is the PCC shape (eqs. 2-3) whose base-tip chord is at s, and s runs from
  0 to Theta. ``sweep="rigid"`` is the literal reading of "the same angle beta for every link": the
  straight finger rotated about P_base by s;
* the paper's finger is a line and it measures angles to contact points; for a finger 2r thick the
  same construction runs on the centreline against the object dilated by r: Theta_o1 aims at P_g1
  on the centreline, and the Fig. 8 circle is centred at P_g1 and crosses the dilated contour;
* L_g1 is the arc length along the chain (eq. 6 is the same distance for the straight finger);
* case (d) splits the links at the fractional N_g1 (link k takes clip(N_g1 - k, 0, 1) of the first
  part's turning), as the core does.

Where the paper's literal pixel rule is refined, because the literal rule has an error of
millimetres that has nothing to do with the method:

* P_g1: the paper takes "the overlapping pixel nearest P_base". When the finger first overlaps a
  smooth object the overlap is a thin lens a few millimetres long (2 sqrt(2 R d) for a penetration
  d of one sweep step), so its end nearest the base is that far from the contact; against a face
  nearly parallel to the finger it is longer still. Here the first overlapping step is narrowed
  down by bisection until the overlap is as thin as the pixels allow, the pixel nearest the base
  picks the overlap region (the first contact along the finger, as the paper intends), and P_g1 is
  the centre of that region's extent along the finger.
* P_o2: the paper takes "the overlapping pixel whose y is the largest"; here that pixel picks the
  crossing and the crossing is the centroid of its few overlapping pixels (a 1-px circle against a
  2-px contour), not its lowest pixel.

Drawing is calibrated to OpenCV's rasterisation, as anyone checking their drawing against known
geometry would: ``fillPoly`` marks the pixels whose centres lie up to about 0.6 px outside the
outline (:data:`FILL_OVERREACH_PX`), and a line of even thickness 2k marks those within k px of its
centreline. The finger is therefore drawn with k = round(r / pixel - 0.6) and the object dilated by
r / pixel - 0.6 px, so that overlap starts when the centreline comes within r of the outline
(to within half a pixel, the granularity of OpenCV's integer thickness).

Example:
    >>> import numpy as np
    >>> square = np.array([[20.0, 20.0], [40.0, 20.0], [40.0, 40.0], [20.0, 40.0]])
    >>> est = estimate(square, (0.0, 0.0), PixelFinger(52.0, 0.5, 4.0, 10), pixel_mm=0.2)
    >>> int(est.case), est.joints.shape
    (3, (11, 2))
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np

#: Case values, as the core's ``ContactCase``: (a) none, (b) tip, (c) tip and other, (d) other.
NONE, TIP, TIP_AND_OTHER, OTHER = 0, 1, 2, 3

#: Default pixel size (mm). See ``bench_paper_speed.py`` for how faithfulness depends on it.
DEFAULT_PIXEL_MM = 0.1

#: How far (px) beyond a polygon's outline ``cv2.fillPoly`` marks pixel centres (measured on circles).
FILL_OVERREACH_PX = 0.6

_SHIFT = 4  # OpenCV fixed-point bits: coordinates are drawn to 1/16 px
_ONE = 1 << _SHIFT

Sweep = Literal["pcc", "rigid"]


@dataclass(frozen=True)
class PixelFinger:
    """The finger model's numbers (as ``softgrip_jax.FingerModel``): L (mm), Theta (rad), r (mm), N."""

    length: float
    theta_entire: float
    half_thickness: float
    n_links: int

    @classmethod
    def like(cls, finger) -> PixelFinger:
        """Plain floats from anything with ``FingerModel``'s field names (a FingerModel included)."""
        return cls(float(finger.length), float(finger.theta_entire), float(finger.half_thickness),
                   int(finger.n_links))


@dataclass(frozen=True)
class Raster:
    """A pixel grid on the plane: pixel (row i, column j) has its centre at origin + (j, i) * pixel_mm.

    Attributes:
        origin: (x, y) in mm of the centre of pixel (0, 0).
        pixel_mm: side of a pixel in mm.
        shape: (rows, columns).
    """

    origin: tuple[float, float]
    pixel_mm: float
    shape: tuple[int, int]

    @classmethod
    def covering(cls, lo, hi, pixel_mm: float) -> Raster:
        """The raster whose pixels cover the box from ``lo`` to ``hi`` (mm, each (x, y))."""
        lo = np.floor(np.asarray(lo, float) / pixel_mm) * pixel_mm
        cols, rows = (np.ceil((np.asarray(hi, float) - lo) / pixel_mm) + 1).astype(int)
        return cls((float(lo[0]), float(lo[1])), float(pixel_mm), (int(rows), int(cols)))

    def to_px(self, points_mm) -> np.ndarray:
        """(..., 2) mm -> (..., 2) pixel coordinates (x = column, y = row), fractional."""
        return (np.asarray(points_mm, float) - self.origin) / self.pixel_mm

    def to_fixed(self, points_mm) -> np.ndarray:
        """(..., 2) mm -> int32 fixed-point pixel coordinates for OpenCV drawing with ``shift``."""
        return np.round(self.to_px(points_mm) * _ONE).astype(np.int32)

    def to_mm(self, rows, cols) -> np.ndarray:
        """Pixel indices -> (M, 2) mm of the pixel centres."""
        return np.stack([self.origin[0] + np.asarray(cols) * self.pixel_mm,
                         self.origin[1] + np.asarray(rows) * self.pixel_mm], axis=-1)

    def window(self, lo, hi) -> tuple[Raster, tuple[int, int, int, int]]:
        """The sub-raster covering the box ``lo``..``hi`` (mm), and its (row0, row1, col0, col1) here.

        The window may reach beyond this raster; :func:`crop` pads it with black.
        """
        c0, r0 = np.floor(self.to_px(lo)).astype(int)
        c1, r1 = np.ceil(self.to_px(hi)).astype(int) + 1
        sub = Raster((self.origin[0] + c0 * self.pixel_mm, self.origin[1] + r0 * self.pixel_mm),
                     self.pixel_mm, (int(r1 - r0), int(c1 - c0)))
        return sub, (int(r0), int(r1), int(c0), int(c1))


def crop(image: np.ndarray, bounds: tuple[int, int, int, int]) -> np.ndarray:
    """``image[r0:r1, c0:c1]``, black where the window leaves the image (a view when it does not)."""
    r0, r1, c0, c1 = bounds
    h, w = image.shape
    if r0 >= 0 and c0 >= 0 and r1 <= h and c1 <= w:
        return image[r0:r1, c0:c1]
    out = np.zeros((r1 - r0, c1 - c0), image.dtype)
    rr0, rr1, cc0, cc1 = max(r0, 0), min(r1, h), max(c0, 0), min(c1, w)
    if rr0 < rr1 and cc0 < cc1:
        out[rr0 - r0:rr1 - r0, cc0 - c0:cc1 - c0] = image[rr0:rr1, cc0:cc1]
    return out


# ----------------------------------------------------------------------------------------------
# Step 1: the object on a black image (Fig. 7 c)


def draw_object(polygon_mm, raster: Raster) -> np.ndarray:
    """The object's contour (V, 2) in mm drawn filled in white on a black uint8 image (Fig. 7 c)."""
    image = np.zeros(raster.shape, np.uint8)
    cv2.fillPoly(image, [raster.to_fixed(polygon_mm).reshape(-1, 1, 2)], 255, cv2.LINE_8, _SHIFT)
    return image


# ----------------------------------------------------------------------------------------------
# Step 2: the discretised finger (eqs. 1-3)


def chain_joints(base, psi: float, turning, length: float) -> np.ndarray:
    """Joints (N+1, 2) in mm of N links of length L/N (eq. 1) at base rotation ``psi`` (rad).

    Link k points at alpha_k = psi + sum_{j<k} turning_j + turning_k / 2 from the downward
    vertical; with turning = 2 Theta / N this is eq. 3 (alpha_k = Theta (2k+1) / N) and the joints
    are those of eq. 2.
    """
    turning = np.asarray(turning, float)
    alpha = psi + np.cumsum(turning) - 0.5 * turning
    steps = (length / turning.size) * np.stack([np.sin(alpha), np.cos(alpha)], axis=-1)
    return np.asarray(base, float) + np.concatenate([np.zeros((1, 2)), np.cumsum(steps, axis=0)])


def sweep_joints(finger: PixelFinger, base, s: float, sweep: Sweep = "pcc") -> np.ndarray:
    """The finger's joints (N+1, 2) in mm at closing progress ``s`` (rad), the base-tip chord angle.

    ``"pcc"``: every link turned by 2 s / N (the PCC shape of eqs. 2-3 with Theta = s);
    ``"rigid"``: the straight finger rotated about P_base by s (every link at beta = s).
    """
    n = finger.n_links
    if sweep == "pcc":
        return chain_joints(base, 0.0, np.full(n, 2.0 * s / n), finger.length)
    return chain_joints(base, s, np.zeros(n), finger.length)


# ----------------------------------------------------------------------------------------------
# Step 3: the finger on a second black image (Fig. 7 d, e)


def finger_thickness(half_thickness: float, pixel_mm: float, overreach_px: float = FILL_OVERREACH_PX) -> int:
    """Line thickness (px, even) that makes a finger of half-thickness r overlap the object's pixels
    exactly when its centreline is within r of the outline: 2 round(r / pixel - overreach)."""
    return 2 * max(1, int(round(half_thickness / pixel_mm - overreach_px)))


def draw_finger(joints_mm, thickness_px: int, raster: Raster, out: np.ndarray | None = None) -> np.ndarray:
    """The links drawn as lines ``thickness_px`` thick (round joints and ends) in white on black."""
    image = np.zeros(raster.shape, np.uint8) if out is None else out
    cv2.polylines(image, [raster.to_fixed(joints_mm).reshape(-1, 1, 2)], False, 255, thickness_px, cv2.LINE_8,
                  _SHIFT)
    return image


def reach(finger: PixelFinger, base, margin_px: float = 2.0, pixel_mm: float = DEFAULT_PIXEL_MM):
    """The box (lo, hi) in mm that the finger covers while it closes: [-r, L + r] from the base in x
    and y (it curls toward +x, by less than pi/2)."""
    pad = finger.half_thickness + margin_px * pixel_mm
    base = np.asarray(base, float)
    return base - pad, base + finger.length + pad


# ----------------------------------------------------------------------------------------------
# Step 4: rotate step by step until the images overlap (Fig. 7 f)


def sweep_values(theta: float, angle_step: float) -> np.ndarray:
    """0, step, 2 step, ... and finally Theta itself (rad)."""
    values = np.arange(0.0, theta, angle_step)
    return np.append(values, theta) if theta > 0 else np.zeros(1)


@dataclass(frozen=True)
class Overlap:
    """The first sweep step at which the finger's pixels overlap the object's.

    Attributes:
        s: closing progress of that step (rad).
        step: its index (0: the open finger already overlaps).
        joints: (N+1, 2) chain at that step (mm).
        rows, cols: the overlapping pixels, in the window's indices.
        raster: the window the finger was drawn on.
        image: the window's overlap image (uint8, 255 where overlapping).
    """

    s: float
    step: int
    joints: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    raster: Raster
    image: np.ndarray


def first_overlap(object_window: np.ndarray, window: Raster, finger: PixelFinger, base, angle_step: float,
                  sweep: Sweep = "pcc", overreach_px: float = FILL_OVERREACH_PX, refine: int = 6) -> Overlap | None:
    """Close the finger step by step (s = 0, step, ..., Theta), drawing it afresh at each step on a
    black image and ANDing it with the object's image; the first non-empty AND (Fig. 7 f).

    The step that first overlaps is then halved ``refine`` times (bisection between it and the step
    before), so that the overlap is as thin as the pixels allow: the overlap of a step that went
    past the contact by d is a sliver as long as 2 sqrt(2 R d) along a surface of radius R, and
    longer along a face nearly parallel to the finger, which would blur where the contact is.

    Returns None if the finger reaches Theta without overlapping (case a).
    """
    thickness = finger_thickness(finger.half_thickness, window.pixel_mm, overreach_px)
    canvas = np.empty(window.shape, np.uint8)
    overlap = np.empty(window.shape, np.uint8)

    def overlapping(s: float) -> tuple[np.ndarray, bool]:
        joints = sweep_joints(finger, base, s, sweep)
        canvas[:] = 0
        draw_finger(joints, thickness, window, out=canvas)
        cv2.bitwise_and(canvas, object_window, dst=overlap)
        return joints, cv2.countNonZero(overlap) > 0

    values = sweep_values(finger.theta_entire, angle_step)
    for step, s in enumerate(values):
        joints, hit = overlapping(float(s))
        if hit:
            if step > 0:
                free, touching = float(values[step - 1]), float(s)
                for _ in range(refine):
                    middle = 0.5 * (free + touching)
                    if overlapping(middle)[1]:
                        touching = middle
                    else:
                        free = middle
                s = touching
                joints, _ = overlapping(touching)
            rows, cols = np.nonzero(overlap)
            return Overlap(float(s), step, joints, rows, cols, window, overlap.copy())
    return None


# ----------------------------------------------------------------------------------------------
# Step 5: the first contact point P_g1 and L_g1 (Fig. 7 g, eq. 6)


def project_on_chain(points_mm, joints_mm, length: float) -> tuple[np.ndarray, np.ndarray]:
    """Arc length (mm) from the base of each point's foot on the chain's centreline, and distance (mm)."""
    points = np.asarray(points_mm, float)[:, None, :]
    a, b = joints_mm[:-1], joints_mm[1:]
    d = b - a
    t = np.clip(np.sum((points - a) * d, -1) / np.sum(d * d, -1), 0.0, 1.0)
    dist = np.linalg.norm(points - a - t[..., None] * d, axis=-1)
    k = np.argmin(dist, axis=1)
    m = np.arange(points.shape[0])
    n = joints_mm.shape[0] - 1
    return (k + t[m, k]) * (length / n), dist[m, k]


def point_at_arc_length(joints_mm, length: float, l: float) -> np.ndarray:
    """The centreline point (mm) at arc length ``l`` (mm) along the chain."""
    n = joints_mm.shape[0] - 1
    u = float(np.clip(l / length * n, 0.0, n))
    k = min(int(u), n - 1)
    return joints_mm[k] + (u - k) * (joints_mm[k + 1] - joints_mm[k])


def first_contact_point(overlap: Overlap, finger: PixelFinger, gap_mm: float | None = None
                        ) -> tuple[np.ndarray, float, np.ndarray]:
    """P_g1 on the finger's centreline (mm), its arc length L_g1 from P_base (eq. 6, mm), and P_o1.

    Each overlapping pixel is projected on the centreline. The one nearest P_base along the finger
    starts the first contact region: the overlapping pixels that follow it along the finger with
    no gap longer than ``gap_mm`` (default r; a thin overlap breaks into isolated pixels, so pixel
    connectivity cannot tell regions apart). P_g1 is the centre of that region's extent along the
    finger, P_o1 its pixel nearest the centreline (the object point that went deepest).
    """
    gap = finger.half_thickness if gap_mm is None else gap_mm
    points = overlap.raster.to_mm(overlap.rows, overlap.cols)
    arc, dist = project_on_chain(points, overlap.joints, finger.length)
    order = np.argsort(arc)
    breaks = np.nonzero(np.diff(arc[order]) > gap)[0]
    first = order[: breaks[0] + 1] if breaks.size else order
    l_g1 = float(0.5 * (arc[first].min() + arc[first].max()))
    p_g1 = point_at_arc_length(overlap.joints, finger.length, l_g1)
    p_o1 = points[first][np.argmin(dist[first])]
    return p_g1, l_g1, p_o1


# ----------------------------------------------------------------------------------------------
# Step 6: the contact link (eq. 7)


def contact_link(l_g1: float, finger: PixelFinger) -> float:
    """N_g1 = L_g1 / L * N (eq. 7), fractional."""
    return l_g1 / finger.length * finger.n_links


# ----------------------------------------------------------------------------------------------
# Step 7: the circle of Fig. 8 against the object dilated by r


def dilated_contour(object_image: np.ndarray, half_thickness: float, raster: Raster,
                    overreach_px: float = FILL_OVERREACH_PX) -> np.ndarray:
    """Contour of the object dilated by r, as a band 2 px wide straddling it (uint8, 255 on it).

    The dilation is the set of pixels within r / pixel - overreach of an object pixel (OpenCV's
    exact Euclidean distance transform; the object's pixels already reach ``overreach_px`` beyond
    its outline); the contour is the
    morphological gradient: pixels with both dilated and free pixels among their 8 neighbours, so
    any 8-connected curve that crosses it has a pixel on it.
    """
    distance = cv2.distanceTransform(np.where(object_image > 0, 0, 255).astype(np.uint8), cv2.DIST_L2,
                                     cv2.DIST_MASK_PRECISE)
    dilated = (distance <= half_thickness / raster.pixel_mm - overreach_px).astype(np.uint8) * 255
    return cv2.morphologyEx(dilated, cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8))


def second_contact(contour: np.ndarray, raster: Raster, centre_mm, radius_mm: float) -> np.ndarray | None:
    """Where the circle of radius L_g2 around P_g1 crosses the dilated contour, lowest first (Fig. 8 b).

    The circle is drawn 1 px wide on a black image the size of its bounding box and ANDed with the
    contour; the overlapping pixel with the largest y picks the crossing, whose position is the
    centroid of its 8-connected overlapping pixels (mm). None if the circle crosses nothing.
    """
    if radius_mm <= 0:
        return None
    pad = radius_mm + 2 * raster.pixel_mm
    centre = np.asarray(centre_mm, float)
    window, bounds = raster.window(centre - pad, centre + pad)
    circle = np.zeros(window.shape, np.uint8)
    c = window.to_fixed(centre)
    cv2.circle(circle, (int(c[0]), int(c[1])), int(round(radius_mm / raster.pixel_mm * _ONE)), 255, 1,
               cv2.LINE_8, _SHIFT)
    overlap = cv2.bitwise_and(circle, crop(contour, bounds))
    if not cv2.countNonZero(overlap):
        return None
    rows, cols = np.nonzero(overlap)
    _, labels = cv2.connectedComponents(overlap, connectivity=8)
    lowest = np.argmax(rows)
    crossing = labels[rows, cols] == labels[rows[lowest], cols[lowest]]
    return window.to_mm(rows[crossing], cols[crossing]).mean(axis=0)


# ----------------------------------------------------------------------------------------------
# Steps 8-10: angles, case, deformation


def angle_from_vertical(v) -> float:
    """Angle (rad) of a vector from the downward vertical, positive toward +x."""
    return float(math.atan2(v[0], v[1]))


def contact_angles(base, p_g1, crossing, theta: float) -> tuple[float, float, float]:
    """Theta_o1 (P_base -> P_g1), Theta_o1o2 (P_g1 -> the crossing; 0 without one) and
    Theta_remain = Theta - Theta_o1 (eq. 8), in rad (Fig. 8 c)."""
    theta_o1 = angle_from_vertical(np.asarray(p_g1) - np.asarray(base, float))
    theta_o1o2 = angle_from_vertical(np.asarray(crossing) - p_g1) if crossing is not None else 0.0
    return theta_o1, theta_o1o2, theta - theta_o1


def classify(touches: bool, n_g1: float, n_links: int, has_second: bool, theta_remain: float,
             theta_o1o2: float, tip_tolerance: float = 0.5) -> int:
    """The case of Fig. 6: none; tip (N_g1 within ``tip_tolerance`` links of N); tip and another area
    (Theta_remain >= Theta_o1o2); another area only."""
    if not touches:
        return NONE
    if n_g1 >= n_links - tip_tolerance:
        return TIP
    return TIP_AND_OTHER if has_second and theta_remain >= theta_o1o2 else OTHER


def deformed_joints(case: int, finger: PixelFinger, base, theta_o1: float = 0.0, theta_o1o2: float = 0.0,
                    n_g1: float = 0.0) -> np.ndarray:
    """Joints (N+1, 2) in mm of the estimated deformation (Figs. 9-11, eq. 9).

    (a) the PCC shape of Theta (eqs. 1-3); (b) that shape rotated away from the object about P_base
    by Theta_remain = Theta - Theta_o1 (eq. 8); (c) rotated by Theta - Theta_o1 - Theta_o1o2 (eq. 9);
    (d) the first N_g1 links bent to the chord angle Theta_o1 (turning 2 Theta_o1 / N_g1), the rest
    by Theta_remain (turning 2 Theta_remain / (N - N_g1)), a fractional N_g1 splitting one link.
    """
    n, theta, length = finger.n_links, finger.theta_entire, finger.length
    free = np.full(n, 2.0 * theta / n)
    if case == NONE:
        return chain_joints(base, 0.0, free, length)
    if case == TIP:
        return chain_joints(base, -(theta - theta_o1), free, length)
    if case == TIP_AND_OTHER:
        return chain_joints(base, -(theta - theta_o1 - theta_o1o2), free, length)
    share = np.clip(n_g1 - np.arange(n), 0.0, 1.0)
    rate_first = 2.0 * theta_o1 / n_g1 if abs(n_g1) > 1e-12 else 0.0
    rate_rest = 2.0 * (theta - theta_o1) / (n - n_g1) if abs(n - n_g1) > 1e-12 else 0.0
    return chain_joints(base, 0.0, share * rate_first + (1.0 - share) * rate_rest, length)


# ----------------------------------------------------------------------------------------------
# The whole procedure


@dataclass(frozen=True)
class PixelEstimate:
    """The reference's estimate of one finger (mm and rad; the core's names).

    ``case`` and ``joints`` are the answer; the rest says how it was reached. Fields a case does
    not define are NaN (points) or 0.
    """

    case: int
    joints: np.ndarray  #: (N+1, 2) mm, base first
    touches: bool
    initial_overlap: bool  #: the open finger (s = 0) already overlaps the object
    s1: float  #: closing progress at first overlap (rad), narrowed down by bisection; Theta without contact
    p_g1: np.ndarray  #: first contact on the finger's centreline (mm)
    p_o1: np.ndarray  #: the object pixel that went deepest into the finger (mm)
    l_g1: float  #: arc length P_base -> P_g1 (eq. 6, mm)
    n_g1: float  #: eq. 7
    theta_o1: float
    theta_o1o2: float
    theta_remain: float  #: eq. 8
    has_second: bool  #: the Fig. 8 circle crosses the dilated contour
    p_cross: np.ndarray  #: that crossing (the tip's centreline at the second contact, mm)
    steps: int  #: sweep steps drawn, not counting the bisection of the first overlapping one


_NAN2 = np.full(2, np.nan)


@dataclass
class PixelScene:
    """One object drawn once (Fig. 7 c) and estimated against by any number of fingers.

    Attributes:
        image: the object filled in white on black (uint8).
        raster: where its pixels are (mm).
        overreach_px: how far beyond the true outline the image's object pixels reach (px):
            :data:`FILL_OVERREACH_PX` when drawn by :func:`draw_object`, about 0 for a mask whose
            pixels are those with centres inside the object.
    """

    image: np.ndarray
    raster: Raster
    overreach_px: float = FILL_OVERREACH_PX
    _contours: dict = field(default_factory=dict, repr=False)

    @classmethod
    def from_polygon(cls, polygon_mm, raster: Raster) -> PixelScene:
        """The object's contour (V, 2) in mm drawn filled on ``raster``."""
        return cls(draw_object(polygon_mm, raster), raster, FILL_OVERREACH_PX)

    @classmethod
    def from_mask(cls, mask: np.ndarray, raster: Raster, overreach_px: float = 0.0) -> PixelScene:
        """An object given as a mask (non-zero inside) on ``raster``."""
        return cls(np.where(np.asarray(mask) > 0, 255, 0).astype(np.uint8), raster, overreach_px)

    @classmethod
    def around(cls, polygon_mm, bases, finger: PixelFinger, pixel_mm: float = DEFAULT_PIXEL_MM) -> PixelScene:
        """The object drawn on a raster covering every finger's reach from ``bases`` ((B, 2) or (2,) mm),
        the Fig. 8 circle included (within L + r of each base)."""
        bases = np.atleast_2d(np.asarray(bases, float))
        pad = finger.length + finger.half_thickness + 3 * pixel_mm
        return cls.from_polygon(polygon_mm, Raster.covering(bases.min(0) - pad, bases.max(0) + pad, pixel_mm))

    def contour(self, half_thickness: float) -> np.ndarray:
        """:func:`dilated_contour` for this half-thickness, computed once."""
        key = round(half_thickness / self.raster.pixel_mm, 6)
        if key not in self._contours:
            self._contours[key] = dilated_contour(self.image, half_thickness, self.raster, self.overreach_px)
        return self._contours[key]

    def estimate(self, finger, base, angle_step: float | None = None, sweep: Sweep = "pcc",
                 tip_tolerance: float = 0.5) -> PixelEstimate:
        """The paper's procedure for one finger hanging from ``base`` (mm).

        Args:
            finger: a :class:`PixelFinger` or anything with ``FingerModel``'s fields.
            base: (2,) P_base in mm.
            angle_step: sweep increment (rad); default: the tip moves one pixel per step
                (pixel_mm / L).
            sweep: ``"pcc"`` or ``"rigid"`` (see the module docstring).
            tip_tolerance: N_g1 within this many links of N is the tip (case b).
        """
        finger = PixelFinger.like(finger)
        base = np.asarray(base, float)
        px = self.raster.pixel_mm
        step = angle_step if angle_step is not None else px / finger.length
        window, bounds = self.raster.window(*reach(finger, base, pixel_mm=px))
        hit = first_overlap(crop(self.image, bounds), window, finger, base, step, sweep, self.overreach_px)
        n_steps = len(sweep_values(finger.theta_entire, step))
        if hit is None:
            return PixelEstimate(
                case=NONE, joints=deformed_joints(NONE, finger, base), touches=False, initial_overlap=False,
                s1=finger.theta_entire, p_g1=_NAN2, p_o1=_NAN2, l_g1=0.0, n_g1=0.0, theta_o1=0.0,
                theta_o1o2=0.0, theta_remain=0.0, has_second=False, p_cross=_NAN2, steps=n_steps)
        p_g1, l_g1, p_o1 = first_contact_point(hit, finger)
        n_g1 = contact_link(l_g1, finger)
        crossing = second_contact(self.contour(finger.half_thickness), self.raster, p_g1, finger.length - l_g1)
        theta_o1, theta_o1o2, theta_remain = contact_angles(base, p_g1, crossing, finger.theta_entire)
        case = classify(True, n_g1, finger.n_links, crossing is not None, theta_remain, theta_o1o2,
                        tip_tolerance)
        return PixelEstimate(
            case=case, joints=deformed_joints(case, finger, base, theta_o1, theta_o1o2, n_g1), touches=True,
            initial_overlap=hit.step == 0, s1=hit.s, p_g1=p_g1, p_o1=p_o1, l_g1=l_g1, n_g1=n_g1,
            theta_o1=theta_o1, theta_o1o2=theta_o1o2, theta_remain=theta_remain,
            has_second=crossing is not None, p_cross=crossing if crossing is not None else _NAN2,
            steps=hit.step + 1)


def estimate(polygon_mm, base, finger, pixel_mm: float = DEFAULT_PIXEL_MM, angle_step: float | None = None,
             sweep: Sweep = "pcc") -> PixelEstimate:
    """The whole procedure for one finger and one object outline (V, 2) in mm; see
    :meth:`PixelScene.estimate`. The object is drawn at ``pixel_mm`` over the finger's reach."""
    finger = PixelFinger.like(finger)
    return PixelScene.around(polygon_mm, base, finger, pixel_mm).estimate(finger, base, angle_step, sweep)
