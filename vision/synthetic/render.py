"""Synthetic RGB-D frames of a two-finger soft gripper and an object, as a RealSense D405 sees them.

The camera looks straight at the gripper plane from ``plane_depth_mm`` (the paper's set-up: a D405
about 120 mm away). Scene geometry is given in millimetres in that plane (x right, y down, the
finger bases at the top) and projected with the pinhole model at the plane depth,
``u = fx * x / Z + ppx``, ``v = fy * y / Z + ppy``, pixel centres at integer (u, v). So converting
pixels back to millimetres at the plane depth recovers the geometry exactly, and a synthetic frame
goes through the same pipeline as a camera frame (``vision.frames``).

What is drawn, nearest last:
- background: far (``background_depth_mm``), darker, low saturation, with a smooth texture;
- object: the filled polygon in a saturated colour, at the plane depth plus a few millimetres;
- palm (optional): a light bar joining the finger bases, just above them, at the plane depth;
- fingers: each centreline swept by a disc of radius ``half_thickness`` (a capsule chain) in light,
  low-saturation silicone, shaded darker toward its edges, at the plane depth.

Masks are exact point samples at pixel centres (no anti-aliasing): a pixel belongs to a part when
its centre is inside it. Colour noise, depth noise growing with depth squared (stereo-like) and a
few small zero-depth holes on the foreground follow, all drawn from ``seed``.

Example:
    >>> from vision.synthetic.scenes import gripper_centrelines
    >>> from vision.synthetic.shapes import shape
    >>> scene = Scene(gripper_centrelines((0.0, -40.0), 50.0, 52.0, 64),
    ...               object_polygon=shape("clover") + (0.0, 12.0))
    >>> frame = render(scene, d405_intrinsics())
    >>> frame.color.shape, frame.depth.dtype.name
    ((480, 640, 3), 'uint16')
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from softgrip_jax import SoftgripError
from vision.frames import Frame, Intrinsics

LABEL_BACKGROUND = 0
LABEL_OBJECT = 1
LABEL_PALM = 2
LABEL_FIRST_FINGER = 3
"""Labels of :func:`render_labels`; finger k (in ``Scene.fingers`` order) is LABEL_FIRST_FINGER + k."""

_D405_FOCAL_PX_AT_640 = 385.0  # fx = fy of a D405 stream at 640 x 480
_D405_PP_OFFSET_PX_AT_640 = (1.6, -1.1)  # principal point minus image centre, a typical unit
_UINT16_MAX = 65535


def d405_intrinsics(width: int = 640, height: int = 480, depth_scale: float = 1e-4) -> Intrinsics:
    """Intrinsics like an Intel RealSense D405's, for an aligned colour + depth stream.

    Args:
        width, height: image size (px). The focal length scales with the width (about 79 degrees
            of horizontal field of view); the principal point sits a pixel or two off the centre.
        depth_scale: metres per depth unit (the D405 default is 1e-4 m = 0.1 mm).

    Returns:
        ``Intrinsics`` with fx = fy = 385 px at 640 x 480 (``Intrinsics`` validates the arguments).

    Example:
        >>> d405_intrinsics().fx, d405_intrinsics(320, 240).fx
        (385.0, 192.5)
    """
    k = width / 640.0
    return Intrinsics(
        width=width,
        height=height,
        fx=_D405_FOCAL_PX_AT_640 * k,
        fy=_D405_FOCAL_PX_AT_640 * k,
        ppx=0.5 * width + _D405_PP_OFFSET_PX_AT_640[0] * k,
        ppy=0.5 * height + _D405_PP_OFFSET_PX_AT_640[1] * k,
        depth_scale=depth_scale,
    )


def mm_to_px(points_mm: np.ndarray, intrinsics: Intrinsics, depth_mm: float | np.ndarray) -> np.ndarray:
    """Project points (..., 2) in mm in the plane at ``depth_mm`` (scalar or (...,)) to pixels (..., 2).

    Example (the principal point, then 1 mm right at 120 mm depth):
        >>> intr = d405_intrinsics()
        >>> mm_to_px([[0.0, 0.0], [1.0, 0.0]], intr, 120.0).round(3).tolist()
        [[321.6, 238.9], [324.808, 238.9]]
    """
    p = np.asarray(points_mm, dtype=np.float64)
    z = np.asarray(depth_mm, dtype=np.float64)
    u = intrinsics.fx * p[..., 0] / z + intrinsics.ppx
    v = intrinsics.fy * p[..., 1] / z + intrinsics.ppy
    return np.stack(np.broadcast_arrays(u, v), axis=-1)


def px_to_mm(points_px: np.ndarray, intrinsics: Intrinsics, depth_mm: float | np.ndarray) -> np.ndarray:
    """Back-project pixels (..., 2) to mm (..., 2) in the plane at ``depth_mm`` (scalar or (...,)).

    Example:
        >>> intr = d405_intrinsics()
        >>> px_to_mm(mm_to_px([[5.0, -3.0]], intr, 120.0), intr, 120.0).round(6).tolist()
        [[5.0, -3.0]]
    """
    p = np.asarray(points_px, dtype=np.float64)
    z = np.asarray(depth_mm, dtype=np.float64)
    x = (p[..., 0] - intrinsics.ppx) * z / intrinsics.fx
    y = (p[..., 1] - intrinsics.ppy) * z / intrinsics.fy
    return np.stack(np.broadcast_arrays(x, y), axis=-1)


def _as_polyline(points: np.ndarray, what: str, min_points: int) -> np.ndarray:
    """Validate and convert points to a finite float64 (n, 2) array with n >= min_points."""
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 2 or array.shape[0] < min_points:
        raise SoftgripError(
            f"{what} must be an (n, 2) array of mm with n >= {min_points}, got shape {array.shape}"
        )
    if not np.isfinite(array).all():
        raise SoftgripError(f"{what} contains non-finite coordinates")
    return array


def _check_rgb(rgb: tuple[int, int, int], what: str) -> tuple[int, int, int]:
    values = tuple(int(c) for c in rgb)
    if len(values) != 3 or not all(0 <= c <= 255 for c in values):
        raise SoftgripError(f"{what} must be three 0-255 levels (R, G, B), got {rgb!r}")
    return values  # type: ignore[return-value]


def _check_number(name: str, value: float, minimum: float, strict: bool) -> None:
    ok = math.isfinite(value) and (value > minimum if strict else value >= minimum)
    if not ok:
        relation = ">" if strict else ">="
        raise SoftgripError(f"{name} must be a finite number {relation} {minimum}, got {value!r}")


@dataclass(eq=False)
class Scene:
    """A gripper (and optionally an object) in the gripper plane, with the camera's imperfections.

    Lengths are millimetres in the gripper plane (x right, y down), depths millimetres from the
    camera, colours RGB levels 0-255. Arrays are converted to float64 and every field is checked
    on construction (SoftgripError, a ValueError, naming the field).

    Attributes:
        fingers: finger centrelines, each an open polyline (K, 2), K >= 2, base first (see
            ``vision.synthetic.scenes.gripper_centrelines``). May be empty (no gripper in view).
        half_thickness: finger half-thickness r (mm): a finger covers every point within r of its
            centreline.
        object_polygon: the object's outline (V, 2), already placed, or None for no object.
        plane_depth_mm: depth of the gripper plane; all geometry is projected at this depth.
        object_depth_offset_mm: the object's depth reading is plane_depth_mm plus this.
        background_depth_mm: depth of everything behind, beyond the object.
        gripper_rgb, object_rgb, background_rgb: base colours (the gripper light and unsaturated,
            the object saturated, the background darker and unsaturated).
        palm: draw a bar of the gripper's colour joining the finger bases, just above them.
        palm_height_mm: height of that bar.
        color_noise_sigma: standard deviation of the per-channel colour noise (levels).
        depth_noise_sigma_mm: standard deviation of the depth noise at the plane depth; it grows
            with the square of the depth.
        n_depth_holes: number of small zero-depth blobs, centred on the gripper or object.
        seed: seed of every random draw (texture, noise, holes).
    """

    fingers: list[np.ndarray]
    half_thickness: float = 4.0
    object_polygon: np.ndarray | None = None
    plane_depth_mm: float = 120.0
    object_depth_offset_mm: float = 3.0
    background_depth_mm: float = 400.0
    gripper_rgb: tuple[int, int, int] = (225, 225, 220)
    object_rgb: tuple[int, int, int] = (220, 40, 40)
    background_rgb: tuple[int, int, int] = (92, 88, 84)
    palm: bool = False
    palm_height_mm: float = 6.0
    color_noise_sigma: float = 3.0
    depth_noise_sigma_mm: float = 0.3
    n_depth_holes: int = 5
    seed: int = 0

    def __post_init__(self) -> None:
        self.fingers = [_as_polyline(f, f"fingers[{k}]", 2) for k, f in enumerate(self.fingers)]
        if self.object_polygon is not None:
            self.object_polygon = _as_polyline(self.object_polygon, "object_polygon", 3)
        self.gripper_rgb = _check_rgb(self.gripper_rgb, "gripper_rgb")
        self.object_rgb = _check_rgb(self.object_rgb, "object_rgb")
        self.background_rgb = _check_rgb(self.background_rgb, "background_rgb")
        for name in ("half_thickness", "plane_depth_mm", "palm_height_mm"):
            _check_number(name, getattr(self, name), 0.0, strict=True)
        for name in ("object_depth_offset_mm", "color_noise_sigma", "depth_noise_sigma_mm"):
            _check_number(name, getattr(self, name), 0.0, strict=False)
        _check_number("background_depth_mm", self.background_depth_mm,
                      self.plane_depth_mm + self.object_depth_offset_mm, strict=True)
        if int(self.n_depth_holes) != self.n_depth_holes or self.n_depth_holes < 0:
            raise SoftgripError(f"n_depth_holes must be a whole number >= 0, got {self.n_depth_holes!r}")
        if len(self.fingers) > 255 - LABEL_FIRST_FINGER:
            raise SoftgripError(f"at most {255 - LABEL_FIRST_FINGER} fingers, got {len(self.fingers)}")
        if self.palm and not self.fingers:
            raise SoftgripError("palm=True needs at least one finger to attach to")


class _PixelGrid(NamedTuple):
    """Pixel centres in mm in the gripper plane: columns xs (W,) and rows ys (H,), both increasing."""

    xs: np.ndarray
    ys: np.ndarray

    @classmethod
    def of(cls, intrinsics: Intrinsics, depth_mm: float) -> _PixelGrid:
        u, v = np.arange(intrinsics.width), np.arange(intrinsics.height)
        columns = px_to_mm(np.column_stack([u, np.zeros_like(u)]), intrinsics, depth_mm)
        rows = px_to_mm(np.column_stack([np.zeros_like(v), v]), intrinsics, depth_mm)
        return cls(xs=columns[:, 0], ys=rows[:, 1])

    def window(self, lo: np.ndarray, hi: np.ndarray) -> tuple[slice, slice]:
        """(rows, cols) slices of the pixel centres inside the box [lo, hi] (mm, (2,) each)."""
        cols = slice(np.searchsorted(self.xs, lo[0], "left"), np.searchsorted(self.xs, hi[0], "right"))
        rows = slice(np.searchsorted(self.ys, lo[1], "left"), np.searchsorted(self.ys, hi[1], "right"))
        return rows, cols


def _inside_polygon(polygon_mm: np.ndarray, grid: _PixelGrid) -> np.ndarray:
    """bool (H, W): pixel centres inside a closed polygon (V, 2) in mm, by the even-odd rule."""
    inside = np.zeros((grid.ys.size, grid.xs.size), dtype=bool)
    rows, cols = grid.window(polygon_mm.min(axis=0), polygon_mm.max(axis=0))
    ys, xs = grid.ys[rows], grid.xs[cols]
    window = inside[rows, cols]
    for (ax, ay), (bx, by) in zip(polygon_mm, np.roll(polygon_mm, -1, axis=0)):
        crossing = (ay > ys) != (by > ys)  # rows whose centre line crosses this edge
        if crossing.any():
            x_cross = ax + (ys[crossing] - ay) * (bx - ax) / (by - ay)
            window[crossing] ^= xs[None, :] < x_cross[:, None]
    return inside


def _distance_to_polyline(polyline_mm: np.ndarray, grid: _PixelGrid, reach_mm: float) -> np.ndarray:
    """float (H, W): distance (mm) from each pixel centre to an open polyline (K, 2) in mm.

    Exact within ``reach_mm`` of the polyline; pixels farther away read +inf.
    """
    distance = np.full((grid.ys.size, grid.xs.size), np.inf)
    for a, b in zip(polyline_mm[:-1], polyline_mm[1:]):
        rows, cols = grid.window(np.minimum(a, b) - reach_mm, np.maximum(a, b) + reach_mm)
        dx, dy = grid.xs[None, cols] - a[0], grid.ys[rows, None] - a[1]
        ab = b - a
        length2 = float(ab @ ab)
        t = np.clip((dx * ab[0] + dy * ab[1]) / length2, 0.0, 1.0) if length2 > 0.0 else 0.0
        np.minimum(distance[rows, cols], np.hypot(dx - t * ab[0], dy - t * ab[1]), out=distance[rows, cols])
    return distance


def _palm_polygon(scene: Scene) -> np.ndarray:
    """The palm bar (4, 2) in mm: spans the finger bases plus r each side, palm_height_mm above them."""
    bases = np.array([f[0] for f in scene.fingers])
    x0, x1 = bases[:, 0].min() - scene.half_thickness, bases[:, 0].max() + scene.half_thickness
    y1 = bases[:, 1].min()
    y0 = y1 - scene.palm_height_mm
    return np.array([(x0, y0), (x0, y1), (x1, y1), (x1, y0)])


def _layers(scene: Scene, intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Labels (H, W) uint8 (see LABEL_*) and each finger pixel's distance to its centreline over r.

    The second array is (H, W) float in [0, 1] on finger pixels and +inf elsewhere.
    """
    grid = _PixelGrid.of(intrinsics, scene.plane_depth_mm)
    labels = np.full((intrinsics.height, intrinsics.width), LABEL_BACKGROUND, dtype=np.uint8)
    if scene.object_polygon is not None:
        labels[_inside_polygon(scene.object_polygon, grid)] = LABEL_OBJECT
    if scene.palm:
        labels[_inside_polygon(_palm_polygon(scene), grid)] = LABEL_PALM
    nearest = np.full(labels.shape, np.inf)
    for k, finger in enumerate(scene.fingers):
        distance = _distance_to_polyline(finger, grid, scene.half_thickness)
        closer = (distance <= scene.half_thickness) & (distance < nearest)
        labels[closer] = LABEL_FIRST_FINGER + k
        nearest[closer] = distance[closer]
    return labels, nearest / scene.half_thickness


def render_labels(scene: Scene, intrinsics: Intrinsics) -> np.ndarray:
    """Ground-truth part of every pixel, uint8 (H, W): LABEL_BACKGROUND, LABEL_OBJECT, LABEL_PALM,
    or LABEL_FIRST_FINGER + k for finger k (where fingers overlap, the nearer centreline wins).

    These are exactly the masks :func:`render` paints; no noise or holes.

    Example:
        >>> from vision.synthetic.scenes import gripper_centrelines
        >>> from vision.synthetic.shapes import shape
        >>> scene = Scene(gripper_centrelines((0.0, -40.0), 60.0, 52.0), object_polygon=shape("circle", 20.0) + (0.0, 30.0))
        >>> sorted(set(render_labels(scene, d405_intrinsics()).ravel().tolist())) == [
        ...     LABEL_BACKGROUND, LABEL_OBJECT, LABEL_FIRST_FINGER, LABEL_FIRST_FINGER + 1]
        True
    """
    return _layers(scene, intrinsics)[0]


def _background_color(scene: Scene, shape_hw: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """float (H, W, 3): the background colour with a smooth, unsaturated brightness texture."""
    h, w = shape_hw
    coarse = rng.normal(size=(h // 40 + 2, w // 40 + 2)).astype(np.float32)
    texture = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC).astype(np.float64)
    return np.asarray(scene.background_rgb, dtype=np.float64) + 12.0 * texture[..., None]


def _hole_mask(labels: np.ndarray, n_holes: int, rng: np.random.Generator) -> np.ndarray:
    """bool (H, W): n small elliptic blobs (semi-axes 2-4 px), centred on foreground pixels
    (anywhere if there is no foreground)."""
    mask = np.zeros(labels.shape, dtype=np.uint8)
    rows, cols = np.nonzero(labels != LABEL_BACKGROUND)
    if rows.size == 0:
        rows, cols = np.indices(labels.shape).reshape(2, -1)
    for i in rng.integers(0, rows.size, size=n_holes):
        axes = tuple(int(a) for a in np.rint(rng.uniform(1.5, 4.0, size=2)))
        tilt_deg = float(rng.uniform(0.0, 180.0))
        cv2.ellipse(mask, (int(cols[i]), int(rows[i])), axes, tilt_deg, 0.0, 360.0, color=1, thickness=-1)
    return mask.astype(bool)


def render(scene: Scene, intrinsics: Intrinsics) -> Frame:
    """Render an aligned colour + depth frame of the scene.

    Returns:
        ``Frame`` with ``color`` uint8 (H, W, 3) RGB and ``depth`` uint16 (H, W) in units of
        ``intrinsics.depth_scale`` metres, 0 where there is no reading (the holes).

    Raises:
        SoftgripError (a ValueError): the background depth does not fit in uint16 depth units.

    Example (an open gripper 120 mm from the camera above a 20 mm disc):
        >>> from vision.synthetic.scenes import gripper_centrelines
        >>> from vision.synthetic.shapes import shape
        >>> scene = Scene(gripper_centrelines((0.0, -40.0), 60.0, 52.0), object_polygon=shape("circle", 20.0) + (0.0, 30.0))
        >>> frame = render(scene, d405_intrinsics())
        >>> frame.color.shape, frame.depth.dtype.name
        ((480, 640, 3), 'uint16')
    """
    mm_per_unit = 1000.0 * intrinsics.depth_scale
    if scene.background_depth_mm / mm_per_unit > _UINT16_MAX:
        raise SoftgripError(
            f"background_depth_mm={scene.background_depth_mm} does not fit in uint16 units of "
            f"depth_scale={intrinsics.depth_scale} m; use a larger depth_scale or a nearer background"
        )
    texture_rng, color_rng, depth_rng, hole_rng = np.random.default_rng(scene.seed).spawn(4)
    labels, off_centre = _layers(scene, intrinsics)
    shape_hw = labels.shape
    gripper = np.asarray(scene.gripper_rgb, dtype=np.float64)
    is_finger = labels >= LABEL_FIRST_FINGER

    color = _background_color(scene, shape_hw, texture_rng)
    color[labels == LABEL_OBJECT] = scene.object_rgb
    color[labels == LABEL_PALM] = 0.92 * gripper
    color[is_finger] = (1.0 - 0.2 * off_centre[is_finger, None] ** 2) * gripper  # rounded-surface shading
    color += color_rng.normal(scale=scene.color_noise_sigma, size=color.shape)

    depth_mm = np.full(shape_hw, scene.background_depth_mm)
    depth_mm[labels == LABEL_OBJECT] = scene.plane_depth_mm + scene.object_depth_offset_mm
    depth_mm[(labels == LABEL_PALM) | is_finger] = scene.plane_depth_mm
    sigma = scene.depth_noise_sigma_mm * (depth_mm / scene.plane_depth_mm) ** 2
    depth_mm += sigma * depth_rng.standard_normal(shape_hw)
    depth = np.clip(np.rint(depth_mm / mm_per_unit), 1, _UINT16_MAX).astype(np.uint16)
    depth[_hole_mask(labels, int(scene.n_depth_holes), hole_rng)] = 0

    return Frame(
        color=np.clip(np.rint(color), 0, 255).astype(np.uint8),
        depth=depth,
        intrinsics=intrinsics,
    )
