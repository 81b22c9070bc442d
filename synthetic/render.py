"""Synthetic RGB-D frames of a two-finger soft gripper and an object, as a RealSense D405 sees them.

The camera sees the gripper plane (the plane through the finger centrelines) ``plane_depth_mm``
away along its optical axis (the paper's set-up: a D405 about 120 mm away), facing it or turned by
``Scene.tilt_deg``. Scene geometry is given in millimetres in that plane (x right, y down, the finger
bases at the top). Every pixel is a ray of the pinhole model (pixel centres at integer (u, v)) cast
into the scene, so a tilted plane, an object face nearer or farther than the fingers and round
fingers all project as a camera sees them; :func:`project` gives the pixel of any scene point (the
ground truth of a test). Facing the camera, ``u = fx * x / Z + ppx``, ``v = fy * y / Z + ppy``.

What is drawn, nearest last:
- background: far (``background_depth_mm``), darker, low saturation, with a smooth texture;
- object: the filled polygon in a saturated colour, on its own face plane
  (``object_depth_offset_mm`` behind the gripper plane);
- palm (optional, the gripper's body in view): a light bar joining the finger bases, just above
  them, on the gripper plane;
- fingers: each centreline swept by a disc of radius ``half_thickness`` in light, low-saturation
  silicone, shaded darker toward its edges: a flat front on the gripper plane, or a round tube
  (ray-cast: the depth reads its front surface), with a rounded or flat-cut base end.

Labels and depth are point samples at pixel centres: a pixel belongs to a part when its centre's ray
hits it. Colour is the same point sample, or with ``supersample`` the mean of n x n samples
(anti-aliased edges). Lighting (gain and a gradient across the image), colour noise, the depth
sensor's spatial smoothing (``depth_blur_px``: a Gaussian filter of the depth image, which mixes a
finger's depth with the background's across its silhouette, as a stereo camera's correlation
window and spatial filter do), depth noise growing with depth squared (stereo-like) and a few small
zero-depth holes on the foreground follow, all drawn from ``seed``.

Example:
    >>> from synthetic.scenes import gripper_centrelines
    >>> from synthetic.shapes import shape
    >>> scene = Scene(gripper_centrelines((0.0, -40.0), 50.0, 52.0, 64),
    ...               object_polygon=shape("clover") + (0.0, 12.0))
    >>> frame = render(scene, d405_intrinsics())
    >>> frame.color.shape, frame.depth.dtype.name
    ((480, 640, 3), 'uint16')
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from softgrip_base import SoftgripError
from softgrip_vision.frames import DISTORTION_MODELS, Frame, Intrinsics, distort_points

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
            ``synthetic.scenes.gripper_centrelines``). May be empty (no gripper in view).
        half_thickness: finger half-thickness r (mm): a finger covers every point within r of its
            centreline.
        object_polygon: the object's outline (V, 2), already placed, or None for no object.
        plane_depth_mm: distance from the camera to the gripper plane (the plane through the finger
            centrelines) where it crosses the optical axis.
        object_depth_offset_mm: the object's front face lies on the plane parallel to the gripper
            plane this far behind it (negative: in front); its outline is drawn there, at its own
            depth, and ``object_polygon`` gives it in that plane's coordinates (those of the gripper
            plane moved along the normal).
        background_depth_mm: depth of everything behind, beyond the object.
        gripper_rgb, object_rgb, background_rgb: base colours (the gripper light and unsaturated,
            the object saturated, the background darker and unsaturated).
        palm: draw a bar of the gripper's colour joining the finger bases, just above them.
        palm_height_mm: height of that bar.
        color_noise_sigma: standard deviation of the per-channel colour noise (levels).
        depth_noise_sigma_mm: standard deviation of the depth noise at the plane depth; it grows
            with the square of the depth.
        n_depth_holes: number of small zero-depth blobs, centred on the gripper or object (cut
            after smoothing and noise: a hole reads 0, it is never mixed into its neighbours).
        depth_blur_px: standard deviation (px) of a Gaussian filter applied to the depth image
            alone, before noise and holes: a sensor's spatial smoothing and the mixed pixels at depth
            edges (a pixel near a finger's silhouette reads a weighted mean of the finger's and the
            background's depth). 0 keeps depth sharp at edges; about 1.1 px is a 5 x 5 filter, 1.7
            px a 9 x 9 one.
        seed: seed of every random draw (texture, noise, holes).
        tilt_deg: (a, b), the gripper plane turned by a degrees about the camera's x axis, then b
            about its y axis, about the point where the optical axis meets it (see
            :func:`plane_rotation`); (0, 0) faces the camera.
        finger_section: ``"flat"``, a finger whose front face is the gripper plane (depth reads the
            plane), or ``"round"``, a tube of radius r about its centreline: ray-cast, so the front
            surface is up to r nearer the camera and the outline is the tube's silhouette.
        base_end: ``"rounded"``, the finger's base end capped like its tip (a disc of radius r
            about the first point), or ``"flat"``, cut square across the centreline at the first
            point (where a finger leaves the gripper's body).
        supersample: colour samples per pixel side: 1 samples each pixel at its centre (hard edges);
            n > 1 averages n x n samples (anti-aliased edges, as a lens and sensor give). Labels and
            depth stay point samples at the pixel centres.
        light_gain: brightness factor of the whole image (exposure; 1 as given).
        light_gradient: brightness change across the image's width as a fraction (uneven lighting:
            0.3 makes the right edge 30 % brighter than the left).
        distortion: the lens, ``(model, coeffs)`` with a model of :data:`softgrip_vision.frames.DISTORTION_MODELS`
            and OpenCV's (pyrealsense2's) coefficients, e.g. ``("brown_conrady", (-0.1, 0.0, 0.0, 0.0, 0.0))``
            for a mild barrel; None (default) for a pinhole camera. Each pixel's ray is then the
            lens's (OpenCV's undistortion of the pixel), so the frame is what that lens would image,
            and its intrinsics carry the model and coefficients (see :func:`camera`).
    """

    fingers: list[np.ndarray]
    half_thickness: float = 4.0
    object_polygon: np.ndarray | None = None
    plane_depth_mm: float = 120.0
    object_depth_offset_mm: float = 0.0
    background_depth_mm: float = 400.0
    gripper_rgb: tuple[int, int, int] = (225, 225, 220)
    object_rgb: tuple[int, int, int] = (220, 40, 40)
    background_rgb: tuple[int, int, int] = (92, 88, 84)
    palm: bool = False
    palm_height_mm: float = 6.0
    color_noise_sigma: float = 3.0
    depth_noise_sigma_mm: float = 0.3
    n_depth_holes: int = 5
    depth_blur_px: float = 0.0
    seed: int = 0
    tilt_deg: tuple[float, float] = (0.0, 0.0)
    finger_section: str = "flat"
    base_end: str = "rounded"
    supersample: int = 1
    light_gain: float = 1.0
    light_gradient: float = 0.0
    distortion: tuple[str, tuple[float, ...]] | None = None

    def __post_init__(self) -> None:
        self.fingers = [_as_polyline(f, f"fingers[{k}]", 2) for k, f in enumerate(self.fingers)]
        if self.object_polygon is not None:
            self.object_polygon = _as_polyline(self.object_polygon, "object_polygon", 3)
        self.gripper_rgb = _check_rgb(self.gripper_rgb, "gripper_rgb")
        self.object_rgb = _check_rgb(self.object_rgb, "object_rgb")
        self.background_rgb = _check_rgb(self.background_rgb, "background_rgb")
        for name in ("half_thickness", "plane_depth_mm", "palm_height_mm"):
            _check_number(name, getattr(self, name), 0.0, strict=True)
        for name in ("color_noise_sigma", "depth_noise_sigma_mm", "depth_blur_px"):
            _check_number(name, getattr(self, name), 0.0, strict=False)
        _check_number("object_depth_offset_mm", self.object_depth_offset_mm, -self.plane_depth_mm, strict=True)
        _check_number("light_gain", self.light_gain, 0.0, strict=True)
        if not (math.isfinite(self.light_gradient) and abs(self.light_gradient) < 2.0):
            raise SoftgripError(f"light_gradient must be a finite fraction in (-2, 2), got {self.light_gradient!r}")
        tilt = tuple(float(t) for t in np.ravel(self.tilt_deg))
        if len(tilt) != 2 or not all(math.isfinite(t) and abs(t) < 60.0 for t in tilt):
            raise SoftgripError(f"tilt_deg must be two angles (degrees, |angle| < 60), got {self.tilt_deg!r}")
        self.tilt_deg = tilt  # type: ignore[assignment]
        if self.finger_section not in ("flat", "round"):
            raise SoftgripError(f"finger_section must be 'flat' or 'round', got {self.finger_section!r}")
        if self.base_end not in ("rounded", "flat"):
            raise SoftgripError(f"base_end must be 'rounded' or 'flat', got {self.base_end!r}")
        if int(self.supersample) != self.supersample or not 1 <= self.supersample <= 8:
            raise SoftgripError(f"supersample must be a whole number from 1 to 8, got {self.supersample!r}")
        _check_number("background_depth_mm", self.background_depth_mm,
                      self.plane_depth_mm + self.object_depth_offset_mm, strict=True)
        if int(self.n_depth_holes) != self.n_depth_holes or self.n_depth_holes < 0:
            raise SoftgripError(f"n_depth_holes must be a whole number >= 0, got {self.n_depth_holes!r}")
        if len(self.fingers) > 255 - LABEL_FIRST_FINGER:
            raise SoftgripError(f"at most {255 - LABEL_FIRST_FINGER} fingers, got {len(self.fingers)}")
        if self.palm and not self.fingers:
            raise SoftgripError("palm=True needs at least one finger to attach to")
        if self.distortion is not None:
            try:
                model, coeffs = self.distortion
                coeffs = tuple(float(c) for c in coeffs)
            except (TypeError, ValueError):
                raise SoftgripError(f"distortion must be (model, coeffs) or None, got {self.distortion!r}") from None
            if model not in DISTORTION_MODELS:
                raise SoftgripError(f"distortion's model must be one of {', '.join(DISTORTION_MODELS)}, got {model!r}")
            self.distortion = (model, coeffs)


def camera(scene: Scene, intrinsics: Intrinsics) -> Intrinsics:
    """The intrinsics of the frames :func:`render` makes of ``scene``: ``intrinsics`` with the scene's
    lens distortion (``Scene.distortion``), if any; the same K. Coefficients a real lens cannot have
    are refused here (:class:`softgrip_vision.frames.FrameError`, naming the coefficient).

    Example:
        >>> lens = Scene([], distortion=("brown_conrady", (-0.1, 0.0, 0.0, 0.0, 0.0)))
        >>> intr = camera(lens, d405_intrinsics())
        >>> intr.model, intr.coeffs[0], intr.fx
        ('brown_conrady', -0.1, 385.0)
    """
    if scene.distortion is None:
        return intrinsics
    if intrinsics.distorted:
        raise SoftgripError(f"the scene has a lens distortion and the intrinsics another ({intrinsics.model}); give "
                            f"one of them")
    model, coeffs = scene.distortion
    return dataclasses.replace(intrinsics, model=model, coeffs=coeffs)


def plane_rotation(tilt_deg: tuple[float, float]) -> np.ndarray:
    """(3, 3) rotation whose columns are the gripper plane's x axis, y axis and normal in camera
    coordinates: R = R_y(b) R_x(a) for ``tilt_deg = (a, b)`` (about the camera's x axis, then y).

    Example (no tilt: the camera's own axes):
        >>> plane_rotation((0.0, 0.0)).tolist()
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    """
    a, b = (math.radians(float(t)) for t in tilt_deg)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(a), -math.sin(a)], [0.0, math.sin(a), math.cos(a)]])
    ry = np.array([[math.cos(b), 0.0, math.sin(b)], [0.0, 1.0, 0.0], [-math.sin(b), 0.0, math.cos(b)]])
    return ry @ rx


def plane_points_3d(scene: Scene, points_mm: np.ndarray, offset_mm: float = 0.0) -> np.ndarray:
    """Camera coordinates (..., 3) in mm of gripper-plane points (..., 2) in mm, on the parallel
    plane ``offset_mm`` farther from the camera along the plane's normal (e.g. the object's face)."""
    rotation = plane_rotation(scene.tilt_deg)
    p = np.asarray(points_mm, dtype=np.float64)
    origin = np.array([0.0, 0.0, scene.plane_depth_mm]) + offset_mm * rotation[:, 2]
    return origin + p[..., :1] * rotation[:, 0] + p[..., 1:2] * rotation[:, 1]


def project(scene: Scene, points_mm: np.ndarray, intrinsics: Intrinsics, offset_mm: float = 0.0) -> np.ndarray:
    """Pixels (..., 2) where the camera sees gripper-plane points (..., 2) in mm (on the parallel
    plane at ``offset_mm``, see :func:`plane_points_3d`): the ground truth of any point a frame
    shows, e.g. the object's outline with ``offset_mm=scene.object_depth_offset_mm``. With the
    scene's lens distortion, where that lens images them.

    Example (untilted: the pinhole projection at the plane depth, as :func:`mm_to_px`):
        >>> scene = Scene([], plane_depth_mm=120.0)
        >>> project(scene, [[1.0, 0.0]], d405_intrinsics()).round(3).tolist()
        [[324.808, 238.9]]
    """
    xyz = plane_points_3d(scene, points_mm, offset_mm)
    pinhole = np.stack([intrinsics.fx * xyz[..., 0] / xyz[..., 2] + intrinsics.ppx,
                        intrinsics.fy * xyz[..., 1] / xyz[..., 2] + intrinsics.ppy], axis=-1)
    return distort_points(camera(scene, intrinsics), pinhole)  # through the lens, if the scene has one


class _Samples(NamedTuple):
    """Sample points of a window of the image: ``rows`` and ``cols`` slices of the (sample) grid and
    each sample's ray direction (h, w, 3), z = 1 (so a point at ray parameter t has depth t)."""

    rows: slice
    cols: slice
    rays: np.ndarray


class _Sampler:
    """Ray directions of every sample of the image, ``factor`` x ``factor`` samples per pixel (at
    the pixel centre when ``factor`` is 1), and windows of them around projected geometry."""

    def __init__(self, intrinsics: Intrinsics, factor: int):
        self.intrinsics, self.factor = intrinsics, factor
        self.shape = (intrinsics.height * factor, intrinsics.width * factor)

    def window(self, box_px: np.ndarray, margin_px: float) -> _Samples | None:
        """Samples within ``margin_px`` of the box [[u0, v0], [u1, v1]] (px); None when outside."""
        f = self.factor
        lo = np.floor((np.min(box_px, axis=0) - margin_px + 0.5) * f).astype(int)
        hi = np.ceil((np.max(box_px, axis=0) + margin_px + 0.5) * f).astype(int)
        c0, r0 = np.maximum(lo, 0)
        c1, r1 = np.minimum(hi, (self.shape[1], self.shape[0]))
        if c0 >= c1 or r0 >= r1:
            return None
        u = (np.arange(c0, c1) + 0.5) / f - 0.5
        v = (np.arange(r0, r1) + 0.5) / f - 0.5
        intr = self.intrinsics
        rays = np.empty((len(v), len(u), 3))
        if intr.distorted:  # the ray each sample of the distorted image sees: OpenCV's undistortion
            grid = np.stack(np.meshgrid(u, v), axis=-1)
            ideal = intr.undistort_points(grid)
            rays[..., 0] = (ideal[..., 0] - intr.ppx) / intr.fx
            rays[..., 1] = (ideal[..., 1] - intr.ppy) / intr.fy
        else:
            rays[..., 0], rays[..., 1] = ((u - intr.ppx) / intr.fx)[None, :], ((v - intr.ppy) / intr.fy)[:, None]
        rays[..., 2] = 1.0
        return _Samples(slice(r0, r1), slice(c0, c1), rays)


def _on_plane(scene: Scene, rays: np.ndarray, offset_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Where rays (..., 3) meet the gripper plane's parallel at ``offset_mm``: plane coordinates
    (..., 2) in mm and the depth (...,) in mm."""
    rotation = plane_rotation(scene.tilt_deg)
    normal = rotation[:, 2]
    origin = np.array([0.0, 0.0, scene.plane_depth_mm]) + offset_mm * normal
    t = (origin @ normal) / (rays @ normal)
    relative = t[..., None] * rays - origin
    return np.stack([relative @ rotation[:, 0], relative @ rotation[:, 1]], axis=-1), t


def _inside_polygon(polygon_mm: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """bool (...): points (..., 2) in mm inside a closed polygon (V, 2) in mm, by the even-odd rule."""
    inside = np.zeros(xy.shape[:-1], dtype=bool)
    x, y = xy[..., 0], xy[..., 1]
    for (ax, ay), (bx, by) in zip(polygon_mm, np.roll(polygon_mm, -1, axis=0)):
        if ay == by:
            continue
        crossing = (ay > y) != (by > y)
        x_cross = ax + (y - ay) * (bx - ax) / (by - ay)
        inside ^= crossing & (x < x_cross)
    return inside


def _distance_in_plane(polyline_mm: np.ndarray, xy: np.ndarray, flat_base: bool) -> np.ndarray:
    """(...): distance (mm) from plane points (..., 2) to an open polyline (K, 2); with
    ``flat_base`` the points behind the line across the first point (square to the first
    segment) read +inf: the finger is cut there."""
    distance = np.full(xy.shape[:-1], np.inf)
    for a, b in zip(polyline_mm[:-1], polyline_mm[1:]):
        ab = b - a
        length2 = float(ab @ ab)
        d = xy - a
        t = np.clip((d @ ab) / length2, 0.0, 1.0) if length2 > 0.0 else np.zeros(xy.shape[:-1])
        np.minimum(distance, np.hypot(d[..., 0] - t * ab[0], d[..., 1] - t * ab[1]), out=distance)
    if flat_base:
        distance[(xy - polyline_mm[0]) @ (polyline_mm[1] - polyline_mm[0]) < 0.0] = np.inf
    return distance


def _distance_to_rays(points_3d: np.ndarray, rays: np.ndarray, radius: float,
                      flat_base: bool) -> tuple[np.ndarray, np.ndarray]:
    """For a round finger: each ray's (..., 3) distance (mm) to the centreline polyline (K, 3) in
    camera coordinates, and the depth (mm) where it enters the tube of ``radius`` around it (+inf
    for rays that miss). With ``flat_base`` the tube is cut square across its axis at the first
    point (a ray entering behind the cut misses; the cut face itself, edge-on to a camera facing
    the plane, is not drawn)."""
    norm = np.linalg.norm(rays, axis=-1)
    u = rays / norm[..., None]
    best = np.full(rays.shape[:-1], np.inf)
    depth = np.full(rays.shape[:-1], np.inf)
    for a, b in zip(points_3d[:-1], points_3d[1:]):
        e = b - a
        c = float(e @ e)
        ue = u @ e
        ua = u @ a
        denom = c - ue**2
        # The segment parameter s nearest the ray (a line through the camera): unconstrained
        # minimiser of |t u - a - s e| over t and s, then clamped to the segment.
        s_free = np.where(denom > 1e-12, (ue * ua - (a @ e)) / np.where(denom > 1e-12, denom, 1.0), 0.0)
        s = np.clip(s_free, 0.0, 1.0)
        q = a + s[..., None] * e
        t = np.sum(u * q, axis=-1)
        gap = np.linalg.norm(t[..., None] * u - q, axis=-1)
        # Entry point: through a cylinder where s is inside the segment, a sphere at its ends.
        sin_angle = np.sqrt(np.clip(1.0 - ue**2 / c, 1e-12, 1.0))
        inside_segment = (s_free > 0.0) & (s_free < 1.0)
        half_chord = np.sqrt(np.clip(radius**2 - gap**2, 0.0, None)) / np.where(inside_segment, sin_angle, 1.0)
        t_entry = t - half_chord
        hit_depth = t_entry * u[..., 2]
        if flat_base:  # the tube is cut square across its axis at the first point
            gap[(t_entry[..., None] * u - points_3d[0]) @ (points_3d[1] - points_3d[0]) < 0.0] = np.inf
        closer = (gap <= radius) & (gap < best)
        best[closer] = gap[closer]
        depth[closer] = hit_depth[closer]
    return best, depth


def _palm_polygon(scene: Scene) -> np.ndarray:
    """The palm bar (4, 2) in mm: spans the finger bases plus r each side, palm_height_mm above them."""
    bases = np.array([f[0] for f in scene.fingers])
    x0, x1 = bases[:, 0].min() - scene.half_thickness, bases[:, 0].max() + scene.half_thickness
    y1 = bases[:, 1].min()
    y0 = y1 - scene.palm_height_mm
    return np.array([(x0, y0), (x0, y1), (x1, y1), (x1, y0)])


class _Layers(NamedTuple):
    """Per sample (H*f, W*f): label (see LABEL_*), depth (mm, of the nearest surface) and, on finger
    samples, the distance to the centreline over r in [0, 1] (+inf elsewhere)."""

    labels: np.ndarray
    depth_mm: np.ndarray
    off_centre: np.ndarray


def _dense(points_mm: np.ndarray, closed: bool, step_mm: float = 1.0) -> np.ndarray:
    """The polyline (closed: polygon) with points added every ``step_mm`` along its edges, so that the
    bounding box of its image through a lens (which bends straight edges) covers the edges too."""
    p = np.asarray(points_mm, np.float64)
    ends = np.roll(p, -1, axis=0) if closed else p[1:]
    starts = p if closed else p[:-1]
    out = [p]
    for a, b in zip(starts, ends):
        n = int(np.ceil(np.hypot(*(b - a)) / step_mm))
        if n > 1:
            out.append(a + (b - a) * np.linspace(0.0, 1.0, n + 1)[1:-1, None])
    return np.concatenate(out)


def _layers(scene: Scene, intrinsics: Intrinsics, factor: int = 1) -> _Layers:
    """Every sample's part, depth and finger shading coordinate; ``factor`` samples per pixel side."""
    lens = camera(scene, intrinsics)
    sampler = _Sampler(lens, factor)
    labels = np.full(sampler.shape, LABEL_BACKGROUND, dtype=np.uint8)
    depth = np.full(sampler.shape, scene.background_depth_mm)
    nearest = np.full(sampler.shape, np.inf)
    px_per_mm = max(intrinsics.fx, intrinsics.fy) / scene.plane_depth_mm

    def paint_polygon(polygon_mm: np.ndarray, offset_mm: float, label: int) -> None:
        outline = _dense(polygon_mm, closed=True) if lens.distorted else polygon_mm
        window = sampler.window(project(scene, outline, intrinsics, offset_mm), 2.0)
        if window is None:
            return
        xy, t = _on_plane(scene, window.rays, offset_mm)
        inside = _inside_polygon(polygon_mm, xy) & (t > 0.0)
        labels[window.rows, window.cols][inside] = label
        depth[window.rows, window.cols][inside] = t[inside]

    if scene.object_polygon is not None:
        paint_polygon(scene.object_polygon, scene.object_depth_offset_mm, LABEL_OBJECT)
    if scene.palm:
        paint_polygon(_palm_polygon(scene), 0.0, LABEL_PALM)
    r = scene.half_thickness
    flat_base = scene.base_end == "flat"
    for k, finger in enumerate(scene.fingers):
        line = _dense(finger, closed=False) if lens.distorted else finger
        window = sampler.window(project(scene, line, intrinsics), 1.5 * r * px_per_mm + 2.0)
        if window is None:
            continue
        if scene.finger_section == "round":
            distance, surface = _distance_to_rays(plane_points_3d(scene, finger), window.rays, r, flat_base)
        else:
            xy, surface = _on_plane(scene, window.rays, 0.0)
            distance = _distance_in_plane(finger, xy, flat_base)
        rows, cols = window.rows, window.cols
        closer = (distance <= r) & (distance < nearest[rows, cols])
        labels[rows, cols][closer] = LABEL_FIRST_FINGER + k
        nearest[rows, cols][closer] = distance[closer]
        depth[rows, cols][closer] = surface[closer]
    return _Layers(labels, depth, nearest / r)


def render_labels(scene: Scene, intrinsics: Intrinsics) -> np.ndarray:
    """Ground-truth part of every pixel, uint8 (H, W): LABEL_BACKGROUND, LABEL_OBJECT, LABEL_PALM,
    or LABEL_FIRST_FINGER + k for finger k (where fingers overlap, the nearer centreline wins).

    These are exactly the masks :func:`render` paints; no noise or holes.

    Example:
        >>> from synthetic.scenes import gripper_centrelines
        >>> from synthetic.shapes import shape
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


def _sample_colors(scene: Scene, layers: _Layers, background: np.ndarray) -> np.ndarray:
    """float (h, w, 3): each sample's colour before lighting and noise (the background's where
    nothing covers it; fingers shaded darker toward their edges, like a rounded surface)."""
    gripper = np.asarray(scene.gripper_rgb, dtype=np.float64)
    is_finger = layers.labels >= LABEL_FIRST_FINGER
    color = background.copy()
    color[layers.labels == LABEL_OBJECT] = scene.object_rgb
    color[layers.labels == LABEL_PALM] = 0.92 * gripper
    color[is_finger] = (1.0 - 0.2 * layers.off_centre[is_finger, None] ** 2) * gripper
    return color


def render(scene: Scene, intrinsics: Intrinsics) -> Frame:
    """Render an aligned colour + depth frame of the scene.

    Returns:
        ``Frame`` with ``color`` uint8 (H, W, 3) RGB and ``depth`` uint16 (H, W) in units of
        ``intrinsics.depth_scale`` metres, 0 where there is no reading (the holes); its intrinsics
        are :func:`camera` (``intrinsics`` with the scene's lens distortion, if any).

    With ``Scene.distortion``, each pixel's ray is the lens's, found by OpenCV's undistortion of the
    pixel (``cv2.undistortPoints``, or ``cv2.fisheye``'s), and the scene is ray-cast along it: the
    distorted image is made directly, not warped from a pinhole image (no resampling, and a barrel
    lens's wider view is drawn in full). Lighting, noise, depth smoothing and holes follow in the
    distorted image, as a sensor adds them.

    Raises:
        SoftgripError (a ValueError): the background depth does not fit in uint16 depth units.

    Example (an open gripper 120 mm from the camera above a 20 mm disc):
        >>> from synthetic.scenes import gripper_centrelines
        >>> from synthetic.shapes import shape
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
    lens = camera(scene, intrinsics)
    centres = _layers(scene, intrinsics)
    labels = centres.labels
    shape_hw = labels.shape
    background = _background_color(scene, shape_hw, texture_rng)
    if scene.supersample == 1:
        color = _sample_colors(scene, centres, background)
    else:
        f = int(scene.supersample)
        fine = _sample_colors(scene, _layers(scene, intrinsics, f), np.repeat(np.repeat(background, f, 0), f, 1))
        color = fine.reshape(shape_hw[0], f, shape_hw[1], f, 3).mean(axis=(1, 3))
    columns = np.arange(shape_hw[1]) / max(shape_hw[1] - 1, 1) - 0.5
    color *= scene.light_gain * (1.0 + scene.light_gradient * columns)[None, :, None]
    color += color_rng.normal(scale=scene.color_noise_sigma, size=color.shape)

    depth_mm = centres.depth_mm.copy()
    if scene.depth_blur_px > 0.0:
        depth_mm = cv2.GaussianBlur(depth_mm, (0, 0), sigmaX=float(scene.depth_blur_px),
                                    borderType=cv2.BORDER_REPLICATE)
    sigma = scene.depth_noise_sigma_mm * (depth_mm / scene.plane_depth_mm) ** 2
    depth_mm += sigma * depth_rng.standard_normal(shape_hw)
    depth = np.clip(np.rint(depth_mm / mm_per_unit), 1, _UINT16_MAX).astype(np.uint16)
    depth[_hole_mask(labels, int(scene.n_depth_holes), hole_rng)] = 0

    return Frame(
        color=np.clip(np.rint(color), 0, 255).astype(np.uint8),
        depth=depth,
        intrinsics=lens,
    )
