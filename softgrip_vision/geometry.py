"""Pixels <-> millimetres in the gripper plane, which may be tilted from the camera.

The gripper plane is the plane through the fingers' centrelines (the bending plane). In camera
coordinates (mm; X right, Y down, Z forward, the pinhole ``u = fx X / Z + ppx``, ``v = fy Y / Z +
ppy``, pixel centres at integer (u, v), as pyrealsense2) it passes through ``O = (0, 0, depth_mm)``
on the optical axis and has the unit normal ``n`` (pointing away from the camera; ``(0, 0, 1)`` when
the camera looks straight at it). Its millimetre axes are

    e_x = (x_hat - (x_hat . n) n) / |...|   (the image's x, tilted into the plane),   e_y = n x e_x,

and a point P has plane coordinates ``(e_x . (P - O), e_y . (P - O))``: y down, as the image. A
pixel maps to the plane point its ray hits (ray-plane intersection), so a camera tilted a few
degrees from the gripper plane still measures millimetres in the plane, not on a slanted image.

Parallel planes (``offset_mm`` along n: the object's front face a few mm nearer or farther, a
finger's front surface) share these coordinates: a point of any of them is given by its
orthogonal projection into the gripper plane. So each mask is converted at the depth of its own
outline and all land in one millimetre frame. With ``n = (0, 0, 1)`` and no offset the mapping is

    x_mm = (u - ppx) * Z / fx,    y_mm = (v - ppy) * Z / fy.

Example:
    >>> from softgrip_vision.frames import Intrinsics
    >>> intr = Intrinsics(width=640, height=480, fx=400.0, fy=400.0, ppx=320.0, ppy=240.0,
    ...                   depth_scale=1e-4)
    >>> camera = PlaneCamera(intr, depth_mm=120.0)
    >>> camera.px_to_mm([420.0, 240.0]).tolist()
    [30.0, 0.0]
    >>> camera.mm_to_px([30.0, 0.0]).tolist()
    [420.0, 240.0]
    >>> nearer = camera.parallel(-3.0)  # a face 3 mm nearer the camera: the same pixel is less far out
    >>> nearer.px_to_mm([420.0, 240.0]).round(6).tolist()
    [29.25, 0.0]
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from softgrip_vision.frames import Frame, FrameError, Intrinsics

#: A camera tilted more than this (degrees) from the gripper plane gets a warning: the finger's
#: sides and the object's walls start to show, which the planar model does not describe.
TILT_WARN_DEG = 15.0

_EDGE_PX = 1.5  # readings nearer a mask's edge than this (px) mix two surfaces; left out of fits
_MIN_READINGS = 30
_AXIS_PASSES = 4  # at most this many fits with the fingers' axes placed on the plane of the previous one
_COARSE_EVERY = 8  # the plane's first fit starts from one on every 8th reading (fewer passes over all of them)
_RELIEF_REACH = 0.85  # readings this far across the finger (fraction of r) or nearer its centre are fitted


def plane_depth_mm(frame: Frame, mask: np.ndarray, what: str = "the gripper region") -> float:
    """The median depth reading (mm) over ``mask``: the depth of a plane facing the camera.

    Args:
        frame: the RGB-D frame.
        mask: (H, W) bool, the pixels on the plane (usually both fingers).
        what: how error messages name the mask.

    Returns:
        The median over the pixels of ``mask`` that have a reading (depth > 0), in mm. The median
        ignores depth holes and outliers at the mask's edges (mixed foreground/background pixels).
        It is the depth of the fingers' front surface, not of their centrelines:
        :func:`fit_gripper_plane` measures the plane through the centrelines, and its tilt.

    Example:
        >>> from pathlib import Path
        >>> import softgrip_vision
        >>> data = Path(softgrip_vision.__file__).resolve().parents[1] / "data"  # the sample frames
        >>> from softgrip_vision.frames import load_frame
        >>> from softgrip_vision.segmentation import segment
        >>> frame = load_frame(data / "calib_open")
        >>> round(plane_depth_mm(frame, segment(frame).fingers))
        120

    Raises:
        FrameError: ``mask`` has the wrong shape, or no pixel of it has a depth reading.
    """
    readings = _readings(frame, mask, what)
    return float(np.median(readings)) * frame.intrinsics.depth_scale * 1000.0


def _readings(frame: Frame, mask: np.ndarray, what: str) -> np.ndarray:
    """The raw depth readings (depth units, > 0) of the pixels of ``mask``; errors name ``what``."""
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != frame.depth.shape:
        raise FrameError(f"mask of {what} is {mask.shape[1]}x{mask.shape[0]} but the frame is "
                         f"{frame.depth.shape[1]}x{frame.depth.shape[0]} (width x height)")
    readings = frame.depth[mask]
    readings = readings[readings > 0]
    if readings.size == 0:
        raise FrameError(f"no depth reading in {what} ({int(mask.sum())} pixels, all 0): the "
                         f"camera cannot measure the gripper plane; check that the gripper is within "
                         f"the camera's depth range (a D405 reads from about 70 mm) and not too shiny")
    return readings


def _unit_normal(normal: ArrayLike) -> np.ndarray:
    n = np.asarray(normal, dtype=np.float64).reshape(-1)
    if n.shape != (3,) or not np.isfinite(n).all() or not np.linalg.norm(n) > 0:
        raise FrameError(f"PlaneCamera.normal must be a finite, non-zero 3-vector, got {normal!r}")
    n = n / np.linalg.norm(n)
    if not n[2] > 0.1:  # within about 84 degrees of the optical axis, facing away from the camera
        raise FrameError(f"PlaneCamera.normal {n.round(4).tolist()} does not face the camera (its z "
                         f"component must be > 0.1: the plane seen at less than 84 degrees from the axis)")
    return n


@dataclass(frozen=True)
class PlaneCamera:
    """The pinhole camera restricted to a plane: pixels <-> plane millimetres (module docstring).

    Attributes:
        intrinsics: the colour camera's intrinsics (fx, fy, ppx, ppy in px).
        depth_mm: Z (mm, > 0) at which the gripper plane crosses the optical axis.
        normal: (3,) unit normal of the plane in camera coordinates, facing away from the camera
            (normalised on construction); ``(0, 0, 1)``: the camera looks straight at it.
        offset_mm: this plane lies ``offset_mm`` behind the gripper plane along the normal (< 0:
            nearer the camera), e.g. an object's front face; its points are given in the gripper
            plane's coordinates (orthogonal projection).
    """

    intrinsics: Intrinsics
    depth_mm: float
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
    offset_mm: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.intrinsics, Intrinsics):
            raise FrameError(f"PlaneCamera.intrinsics must be an Intrinsics, got "
                             f"{type(self.intrinsics).__name__}")
        depth = float(self.depth_mm)
        if not (math.isfinite(depth) and depth > 0.0):
            raise FrameError(f"PlaneCamera.depth_mm must be a finite depth > 0 mm, got "
                             f"{self.depth_mm!r}")
        offset = float(self.offset_mm)
        if not math.isfinite(offset):
            raise FrameError(f"PlaneCamera.offset_mm must be a finite number of mm, got {self.offset_mm!r}")
        object.__setattr__(self, "depth_mm", depth)
        object.__setattr__(self, "normal", tuple(float(c) for c in _unit_normal(self.normal)))
        object.__setattr__(self, "offset_mm", offset)
        if not self.axis_depth_mm > 0.0:
            raise FrameError(f"PlaneCamera: the plane offset by {offset:g} mm passes behind the camera "
                             f"(depth {depth:g} mm): give an offset that keeps it in front")

    @classmethod
    def from_frame(cls, frame: Frame, plane_mask: np.ndarray) -> PlaneCamera:
        """The camera of ``frame`` facing a plane at the median depth of ``plane_mask``
        (:func:`plane_depth_mm`); :func:`fit_gripper_plane` fits tilt and finger relief too."""
        return cls(frame.intrinsics, plane_depth_mm(frame, plane_mask))

    def parallel(self, offset_mm: float) -> PlaneCamera:
        """The plane ``offset_mm`` behind the gripper plane (< 0: nearer), same coordinates."""
        return dataclasses.replace(self, offset_mm=float(offset_mm))

    @functools.cached_property
    def axes(self) -> np.ndarray:
        """(3, 3) rows e_x, e_y, n: the plane's axes in camera coordinates (read-only: computed
        once per camera, every conversion between pixels and mm uses them)."""
        n = np.asarray(self.normal)
        ex = np.array([1.0, 0.0, 0.0]) - n[0] * n
        ex /= np.linalg.norm(ex)
        axes = np.stack([ex, np.cross(n, ex), n])
        axes.flags.writeable = False
        return axes

    @property
    def tilt_deg(self) -> float:
        """Angle between the plane's normal and the optical axis, degrees."""
        return float(np.degrees(np.arccos(np.clip(self.normal[2], -1.0, 1.0))))

    @property
    def axis_depth_mm(self) -> float:
        """Z (mm) at which this plane (with its offset) crosses the optical axis."""
        return self.depth_mm + self.offset_mm / self.normal[2]

    @property
    def spacing_mm(self) -> np.ndarray:
        """(2,) size of one pixel (Z / fx, Z / fy), mm, at the optical axis (everywhere when the
        plane faces the camera)."""
        return self.axis_depth_mm / np.array([self.intrinsics.fx, self.intrinsics.fy])

    @property
    def mm_per_px(self) -> float:
        """One length scale at the optical axis, mm per px: the geometric mean of the two spacings.

        Exact when fx = fy and the plane faces the camera; otherwise a length converted with it is
        off by at most ``|fx - fy| / (2 min(fx, fy))`` relative (about 0.1 % for a typical D405),
        plus the tilt's change of scale across the image (:meth:`local_mm_per_px` has it).
        """
        return float(np.sqrt(np.prod(self.spacing_mm)))

    @property
    def origin_mm(self) -> np.ndarray:
        """(2,) position in mm of the centre of pixel (0, 0)."""
        return self.px_to_mm(np.zeros(2))

    @property
    def faces_camera(self) -> bool:
        """True when the plane is perpendicular to the optical axis: the mapping is affine."""
        return self.normal == (0.0, 0.0, 1.0)

    def rays(self, uv: ArrayLike) -> np.ndarray:
        """(..., 3) the viewing rays ((u - ppx) / fx, (v - ppy) / fy, 1) of pixels (..., 2)."""
        uv = np.asarray(uv, dtype=np.float64)
        i = self.intrinsics
        return np.stack([(uv[..., 0] - i.ppx) / i.fx, (uv[..., 1] - i.ppy) / i.fy, np.ones(uv.shape[:-1])], -1)

    def depth_at(self, uv: ArrayLike) -> np.ndarray:
        """(...,) Z (mm) of this plane's point seen at pixels (..., 2)."""
        n = np.asarray(self.normal)
        return (self.depth_mm * n[2] + self.offset_mm) / (self.rays(uv) @ n)

    def points_3d(self, xy: ArrayLike) -> np.ndarray:
        """(..., 3) camera coordinates (mm) of plane points (..., 2) given in mm."""
        xy = np.asarray(xy, dtype=np.float64)
        ex, ey, n = self.axes
        origin = np.array([0.0, 0.0, self.depth_mm]) + self.offset_mm * n
        return origin + xy[..., :1] * ex + xy[..., 1:2] * ey

    def px_to_mm(self, uv: ArrayLike) -> np.ndarray:
        """Pixels (..., 2) (u right, v down) to mm (..., 2) in the plane; float64."""
        uv = np.asarray(uv, dtype=np.float64)
        if self.faces_camera:  # the affine case, exactly as a fronto-parallel pinhole
            principal = np.array([self.intrinsics.ppx, self.intrinsics.ppy])
            return (uv - principal) * self.spacing_mm
        points = self.rays(uv) * self.depth_at(uv)[..., None]
        ex, ey, _ = self.axes
        relative = points - np.array([0.0, 0.0, self.depth_mm])
        return np.stack([relative @ ex, relative @ ey], -1)

    def mm_to_px(self, xy: ArrayLike) -> np.ndarray:
        """Plane points in mm (..., 2) to pixels (..., 2); float64, the inverse of :meth:`px_to_mm`."""
        xy = np.asarray(xy, dtype=np.float64)
        if self.faces_camera:
            principal = np.array([self.intrinsics.ppx, self.intrinsics.ppy])
            return xy / self.spacing_mm + principal
        p = self.points_3d(xy)
        i = self.intrinsics
        return np.stack([i.fx * p[..., 0] / p[..., 2] + i.ppx, i.fy * p[..., 1] / p[..., 2] + i.ppy], -1)

    def grid_mm_to_px(self, xs: ArrayLike, ys: ArrayLike) -> np.ndarray:
        """(H, W, 2) pixels of the regular grid of plane points (xs[col], ys[row]) in mm, (W,) and
        (H,): :meth:`mm_to_px` of that grid, to the last bit, with its arithmetic split by row and
        column (the plane point of each node is a column's term plus a row's)."""
        xs, ys = np.asarray(xs, dtype=np.float64), np.asarray(ys, dtype=np.float64)
        if self.faces_camera:
            return self.mm_to_px(np.stack(np.broadcast_arrays(xs[None, :], ys[:, None]), axis=-1))
        ex, ey, n = self.axes
        origin = np.array([0.0, 0.0, self.depth_mm]) + self.offset_mm * n
        p = [(origin[k] + xs * ex[k])[None, :] + (ys * ey[k])[:, None] for k in range(3)]  # as points_3d
        i = self.intrinsics
        return np.stack([i.fx * p[0] / p[2] + i.ppx, i.fy * p[1] / p[2] + i.ppy], -1)

    def local_mm_per_px(self, uv: ArrayLike) -> np.ndarray:
        """(...,) length scale (mm per px) at pixels (..., 2): sqrt of the mapping's area change."""
        uv = np.asarray(uv, dtype=np.float64)
        du = self.px_to_mm(uv + [0.5, 0.0]) - self.px_to_mm(uv - [0.5, 0.0])
        dv = self.px_to_mm(uv + [0.0, 0.5]) - self.px_to_mm(uv - [0.0, 0.5])
        return np.sqrt(np.abs(du[..., 0] * dv[..., 1] - du[..., 1] * dv[..., 0]))

    def to_dict(self) -> dict[str, float | list[float]]:
        """``{"depth_mm", "normal", "tilt_deg"}`` for a profile (rounded; offset not included)."""
        return {"depth_mm": round(self.depth_mm, 4), "normal": [round(c, 6) for c in self.normal],
                "tilt_deg": round(self.tilt_deg, 3)}


@dataclass(frozen=True)
class PlaneFit:
    """The gripper plane fitted to the fingers' depth readings (:func:`fit_gripper_plane`).

    Attributes:
        camera: the plane through the fingers' outlines (where their silhouettes lie), tilted as
            measured: the millimetre frame of everything else.
        relief_mm: per finger region, how far its outline lies behind its nearest front-surface
            reading (at its ridge): about r for a finger of round cross-section, 0 for a flat front,
            within [0, r] when measured (one fraction of r measured for all the fingers, times each
            finger's half-thickness).
        relief_measured: True when ``relief_mm`` was measured from the depth across the fingers,
            False when it was given.
        readings: number of depth readings the fit used.
        residual_mm: robust spread (1.4826 MAD) of the readings about the fitted surface, mm.
        mixed_band_px: how far inward from the fingers' outlines (px) the depth readings were found
            mixed with the background's and left out (:func:`_mixed_band_px`; 1.5 px when sharp).
        mixed_band_capped: True when the mixing reached so far in that the band was capped: the
            readings left (the inner 40 % of the width) tell a round front from a flat one only by
            a few percent of its relief.
    """

    camera: PlaneCamera
    relief_mm: tuple[float, ...]
    relief_measured: bool
    readings: int
    residual_mm: float
    mixed_band_px: float = _EDGE_PX
    mixed_band_capped: bool = False

    @property
    def tilt_deg(self) -> float:
        """Angle between the gripper plane and the image plane, degrees."""
        return self.camera.tilt_deg


def fit_gripper_plane(frame: Frame, regions: Sequence[np.ndarray], half_thickness_px: Sequence[float],
                      relief_mm: float | None = None, *,
                      centrelines_px: Sequence[np.ndarray] | None = None,
                      width_edges_px: Sequence[np.ndarray | None] | None = None) -> PlaneFit:
    """Fit the plane through the fingers' outlines, and its tilt, to their depth readings.

    Every reading of a finger region (away from its edge) is a point P = Z ray(u, v) of its front
    surface. The surface is modelled as the plane n . P = c, lifted toward the camera across each
    finger by an elliptic bulge ``relief_k sqrt(1 - (rho / r)^2)``, rho being the pixel's distance
    from the finger's centreline (or, without one, r minus its distance to the mask's edge) and r
    the finger's half-width; a finger of round cross-section has relief r, a flat front relief 0,
    and either way its outline (the widest part of its cross-section) lies in the plane n . P = c.
    The relief is bounded to [0, r] (no front surface lies behind its own outline, and none stands
    out farther than a round section's): it is fitted as that fraction of the local half-thickness.

    Two bands of readings are left out. Near the outline the surface is steep, and a depth sensor
    smooths across the silhouette: a reading there is a mix of the finger's depth and the far
    background's, many millimetres too deep, and such mixing reaches several pixels inward for a
    stereo camera's correlation window or spatial filter. The mixed band is measured in each frame
    (:func:`_mixed_band_px`: where, going outward, the depth grows faster from one pixel ring to the
    next than any front surface of relief <= r can) and the regions are eroded by it; readings in the
    outer 15 % of the width are left out as well. The plane's two tilt angles, c and the relief are
    then found together by bounded robust least squares (scipy's trust-region solver with a soft-L1
    loss), so depth holes, flying pixels and a few wrong readings do not pull the plane. One relief
    fraction serves every finger (a gripper's fingers are alike): a relief per finger would trade off
    against the tilt about the axis between them (a nearer right finger reads as a tilt or as a
    larger relief alike).

    Args:
        frame: the RGB-D frame.
        regions: bool (H, W) masks, one per finger, of the finger alone (no gripper body).
        half_thickness_px: each finger's half-width r (px), as measured in its mask.
        relief_mm: the relief, mm, when known (e.g. from a profile) instead of measured; the same
            for every finger.
        centrelines_px: each finger's centreline (K, 2) in px (u, v), or None to take the distance
            transform's ridge; sub-pixel centrelines measure rho, and so the relief, better.
        width_edges_px: with ``centrelines_px``, each finger's side points (S, 2, 2) px across it at
            S stations (:attr:`softgrip_vision.keypoints.FingerKeypoints.width_edges_px`): r is then taken
            where each reading is, since perspective and tilt change it along the finger.

    Returns:
        The :class:`PlaneFit`. Fingers whose readings span too small an area to tell a tilt (less
        than about 10 px in some direction) give a plane facing the camera.

    Raises:
        FrameError: a mask of the wrong shape, or fewer than 30 depth readings in the regions.

    Example (the open sample frame: flat fronts in a plane facing the camera at 120 mm):
        >>> from pathlib import Path
        >>> import softgrip_vision
        >>> from softgrip_vision.frames import load_frame
        >>> from softgrip_vision.segmentation import segment
        >>> frame = load_frame(Path(softgrip_vision.__file__).resolve().parents[1] / "data" / "calib_open")
        >>> seg = segment(frame)
        >>> fit = fit_gripper_plane(frame, [seg.left_finger, seg.right_finger], [13.0, 13.0])
        >>> round(fit.camera.depth_mm), fit.tilt_deg < 0.5, [abs(r) < 0.3 for r in fit.relief_mm]
        (120, True, [True, True])
    """
    if len(regions) != len(half_thickness_px) or not regions:
        raise FrameError(f"fit_gripper_plane: give one half-thickness per region, got {len(regions)} regions "
                         f"and {len(half_thickness_px)} half-thicknesses")
    intr = frame.intrinsics
    scale = intr.depth_scale * 1000.0
    insides = []
    for k, region in enumerate(regions):
        region = np.asarray(region, dtype=bool)
        _readings(frame, region, f"finger region {k}")  # shape check and a clear error without readings
        insides.append(cv2.distanceTransform(region.view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE))
    depth_mm, has_depth = frame.depth * scale, frame.depth > 0
    bands = [_mixed_band_px(depth_mm, np.asarray(region, bool) & has_depth, inside, float(r_px), intr.fx)
             for region, inside, r_px in zip(regions, insides, half_thickness_px)]
    mixed, capped = max(b[0] for b in bands), any(b[1] for b in bands)
    rays, fractions, radii_px, labels = [], [], [], []
    for k, (region, inside, r_px) in enumerate(zip(regions, insides, half_thickness_px)):
        usable = np.asarray(region, bool) & (frame.depth > 0) & (inside >= max(_EDGE_PX, mixed))
        v, u = np.nonzero(usable)
        local_r = np.full(u.size, float(r_px))
        if centrelines_px is None:
            rho = np.clip(float(r_px) - (inside[v, u] - 0.5), 0.0, float(r_px))
        else:
            edges = None if width_edges_px is None else width_edges_px[k]
            rho, local_r = _across(np.column_stack([u, v]).astype(np.float64), centrelines_px[k], edges, float(r_px))
        keep = rho <= _RELIEF_REACH * local_r
        u, v, rho, local_r = u[keep], v[keep], rho[keep], local_r[keep]
        rays.append(np.column_stack([(u - intr.ppx) / intr.fx, (v - intr.ppy) / intr.fy, np.ones(u.size)])
                    * (frame.depth[v, u] * scale)[:, None])
        fractions.append(np.sqrt(np.clip(1.0 - (rho / np.maximum(local_r, 1e-9)) ** 2, 0.0, 1.0)))
        radii_px.append(local_r)
        labels.append(np.full(u.size, k))
    points, bulge, label = np.vstack(rays), np.concatenate(fractions), np.concatenate(labels)
    if len(points) < _MIN_READINGS:
        raise FrameError(f"only {len(points)} depth readings inside the fingers (at least {_MIN_READINGS} "
                         f"needed to fit the gripper plane): check the depth stream and the segmentation")
    directions = points / points[:, 2:]  # the rays (u', v', 1)
    uv = directions[:, :2]
    spread = np.linalg.eigvalsh(np.cov(uv.T * intr.fx)) if len(uv) > 2 else np.zeros(2)
    tilted = bool(spread.min() > 10.0**2)
    n_regions = len(regions)
    fixed = None if relief_mm is None else float(relief_mm)
    # Each reading's half-thickness in mm at the plane: r (px) times the plane's depth along its ray
    # over the focal length (first from the readings' median depth, then from the fitted plane).
    radius_px = np.concatenate(radii_px)
    radius_mm = radius_px * float(np.median(points[:, 2])) / intr.fx

    def unpack(p: np.ndarray) -> tuple[np.ndarray, float, float]:
        a, b = (p[0], p[1]) if tilted else (0.0, 0.0)
        normal = np.array([math.cos(a) * math.sin(b), -math.sin(a), math.cos(a) * math.cos(b)])
        return normal, p[2], (0.0 if fixed is not None else p[3])

    active = np.ones(len(points), bool)

    everything = slice(None)

    def residuals(p: np.ndarray, rows: slice = everything) -> np.ndarray:  # of the readings ``rows``
        normal, c, fraction = unpack(p)
        lift = fixed * bulge[rows] if fixed is not None else fraction * radius_mm[rows] * bulge[rows]
        return np.where(active[rows], points[rows] @ normal - c + lift, 0.0)

    def jacobian(p: np.ndarray, rows: slice = everything) -> np.ndarray:  # d residuals / d (a, b, c[, fraction])
        part = points[rows]
        out = np.zeros((len(part), len(p)))
        if tilted:
            a, b = p[0], p[1]
            out[:, 0] = part @ np.array([-math.sin(a) * math.sin(b), -math.cos(a), -math.sin(a) * math.cos(b)])
            out[:, 1] = part @ np.array([math.cos(a) * math.cos(b), 0.0, -math.cos(a) * math.sin(b)])
        out[:, 2] = -1.0
        if fixed is None:
            out[:, 3] = radius_mm[rows] * bulge[rows]
        out[~active[rows]] = 0.0
        return out

    def solve(start: np.ndarray, f_scale: float, rows: slice = everything):
        lower = [-np.inf, -np.inf, 0.0] + ([] if fixed is not None else [0.0])
        upper = [np.inf, np.inf, np.inf] + ([] if fixed is not None else [1.0])
        return least_squares(residuals, start, jac=jacobian, bounds=(lower, upper), loss="soft_l1",
                             f_scale=f_scale, x_scale="jac", args=(rows,))

    start = np.concatenate([[0.0, 0.0, float(np.median(points[:, 2]))], [] if fixed is not None else [0.5]])
    if len(points) >= _COARSE_EVERY * _MIN_READINGS:  # most of the way on a sample of the readings, then all
        start = solve(start, 1.0, slice(None, None, _COARSE_EVERY)).x
    solution = solve(start, 1.0)
    spread_mm = 1.4826 * float(np.median(np.abs(residuals(solution.x))))
    f_scale = max(2.0 * spread_mm, 0.02)
    normal, c, _ = unpack(solution.x)
    radius_mm = radius_px * (c / (directions @ normal)) / intr.fx
    solution = solve(solution.x, f_scale)
    normal, c, fraction = unpack(solution.x)
    if centrelines_px is not None and width_edges_px is not None and fixed is None and fraction > 0.0:
        # Again with each reading's distance from its finger's axis measured in the plane, from its
        # 3-D point: a round finger's front surface stands nearer the camera than its axis, so in
        # the image its bulge is displaced outward from the outline's centre (by r / depth of the
        # distance from the optical axis, several pixels at the image's sides), which the pixel
        # distance would read as a flatter bulge.
        # The axis is where the centreline's rays meet the plane, so it moves sideways with the
        # plane's depth (by the finger's distance from the optical axis over the depth: 0.3 mm per mm
        # at the image's sides): repeated until the plane's depth settles.
        for _ in range(_AXIS_PASSES):
            previous = c / normal[2]
            plane = PlaneCamera(intr, depth_mm=previous, normal=tuple(normal))
            bulge, measured_mm = _bulge_in_plane(points, label, plane, centrelines_px, width_edges_px)
            radius_mm = np.where(np.isfinite(measured_mm), measured_mm, radius_mm)
            # The outer band again, now measured in the plane: in perspective a round finger's near
            # side is compressed in the image (its steep flank there sits within the 85 % in pixels).
            active = bulge >= math.sqrt(1.0 - _RELIEF_REACH**2)
            solution = solve(solution.x, f_scale)
            normal, c, fraction = unpack(solution.x)
            if abs(c / normal[2] - previous) < 0.01:
                break
    final = residuals(solution.x)[active]
    camera = PlaneCamera(intr, depth_mm=c / normal[2], normal=tuple(normal))
    if fixed is not None:
        relief = np.full(n_regions, fixed)
    else:
        relief = np.array([fraction * float(np.median(radius_mm[label == k])) if np.any(label == k) else 0.0
                           for k in range(n_regions)])
    return PlaneFit(camera=camera, relief_mm=tuple(float(x) for x in relief), relief_measured=fixed is None,
                    readings=int(active.sum()), residual_mm=1.4826 * float(np.median(np.abs(final - np.median(final)))),
                    mixed_band_px=float(mixed), mixed_band_capped=bool(capped and fixed is None))


def _mixed_band_px(depth_mm: np.ndarray, readings: np.ndarray, inside: np.ndarray, r_px: float,
                   focal_px: float) -> tuple[float, bool]:
    """How far (px) inward from a finger's outline the depth readings mix with the background's.

    The readings are grouped in rings of one pixel by their distance from the region's edge (the
    distance transform ``inside``: ring k holds 0.5 <= inside - k < 1.5), and each ring's depth is
    a trimmed mean (robust to holes and flying pixels, not quantised as a median of 0.1 mm steps
    is). Going outward from the centre, a front surface of relief at most r deepens from ring
    k + 1 to ring k by at most the round section's drop there,
    ``(h(rho_{k+1}) - h(rho_k)) Z / f`` with ``h(rho) = sqrt(r^2 - rho^2)`` and ``rho_k = r - k + 0.5``
    (px). A ring deeper than that, by more than 0.1 mm and three standard errors, holds readings
    pulled toward the background; the band is the innermost such ring, plus a margin. Capped so
    that readings out to 40 % of the half-width remain.

    Returns:
        The erosion (px): readings with ``inside`` below it are mixed (``_EDGE_PX`` when no ring
        is), and whether it was capped.
    """
    if r_px <= 2.0:
        return _EDGE_PX, False
    rings = np.floor(inside[readings] + 0.5).astype(int)  # the readings' rings, in the image's order
    depths = depth_mm[readings]
    limit = int(math.floor(r_px))
    means, errors = {}, {}
    for k in range(1, limit + 1):
        values = depths[rings == k]
        if values.size < 20:
            continue
        trimmed = _trim_mean(values, 0.2)
        spread = 1.4826 * float(np.median(np.abs(values - np.median(values))))
        means[k], errors[k] = trimmed, 1.2 * max(spread, 0.05) / math.sqrt(values.size)
    if not means:
        return _EDGE_PX, False
    depth = float(np.median(list(means.values())))

    def height(k: int) -> float:
        rho = r_px - k + 0.5
        return math.sqrt(max(r_px**2 - rho**2, 0.0))

    band = 0
    for k in sorted(means):
        if k + 1 not in means:
            continue
        allowed = (height(k + 1) - height(k)) * depth / focal_px
        if means[k] - means[k + 1] > allowed + 0.1 + 3.0 * math.hypot(errors[k], errors[k + 1]):
            band = k
    if band == 0:
        return _EDGE_PX, False
    # Mixing fades like a Gaussian's tail: below the detectable step it still lifts the next ring or
    # two by a few hundredths of a millimetre, which the relief (a 10 % change of the bulge over the
    # inner half of the width) would amplify tenfold. One ring and a quarter of the band more go.
    wanted, cap = band + 1.5 + 0.25 * band, max(_EDGE_PX, 0.6 * r_px + 0.5)
    return float(min(wanted, cap)), bool(wanted > cap)


def _trim_mean(values: np.ndarray, proportion: float) -> float:
    """``scipy.stats.trim_mean(values, proportion)`` of a 1-D float array, without the cost of its
    array-API wrapper (a millisecond a call): the same partition and mean."""
    low = int(proportion * values.size)
    high = values.size - low
    return float(np.mean(np.partition(values, (low, high - 1))[low:high]))


def _bulge_in_plane(points: np.ndarray, label: np.ndarray, plane: PlaneCamera,
                    centrelines_px: Sequence[np.ndarray],
                    width_edges_px: Sequence[np.ndarray | None]) -> tuple[np.ndarray, np.ndarray]:
    """(P,) the elliptic bulge sqrt(1 - (rho / r)^2) of each reading (P, 3) in camera mm and (P,)
    r there (mm; NaN for a finger without side points), with rho
    the distance in ``plane`` from the reading's foot on it to its finger's axis (the centreline's
    rays met with the plane), and r the finger's half-thickness there: the outline's half-width on
    the plane times cos(beta), beta the ray's angle across the axis (a round finger's tangent rays
    make its outline r / cos(beta) wide)."""

    def on_plane(uv: np.ndarray) -> np.ndarray:
        return plane.points_3d(plane.px_to_mm(uv))

    normal = np.asarray(plane.normal)
    c = float(on_plane(np.zeros((1, 2)))[0] @ normal)
    bulge = np.zeros(len(points))
    radius = np.full(len(points), np.nan)
    for k, (line, edges) in enumerate(zip(centrelines_px, width_edges_px)):
        mine = label == k
        if not mine.any() or edges is None or len(edges) < 2:
            continue
        sides = on_plane(edges.reshape(-1, 2)).reshape(-1, 2, 3)
        half = 0.5 * np.linalg.norm(sides[:, 1] - sides[:, 0], axis=1)
        across = (sides[:, 1] - sides[:, 0]) / np.maximum(2.0 * half, 1e-9)[:, None]
        sight = sides.mean(axis=1) / np.linalg.norm(sides.mean(axis=1), axis=1, keepdims=True)
        half = half * np.sqrt(np.clip(1.0 - np.sum(sight * across, axis=1) ** 2, 0.0, 1.0))
        feet = points[mine] - (points[mine] @ normal - c)[:, None] * normal
        rho, local_r = _across(feet, on_plane(np.asarray(line, np.float64)), sides, 0.0, step=0.02, half=half)
        bulge[mine] = np.sqrt(np.clip(1.0 - (rho / np.maximum(local_r, 1e-9)) ** 2, 0.0, 1.0))
        radius[mine] = local_r
    return bulge, radius


def _across(points: np.ndarray, polyline: np.ndarray, edges: np.ndarray | None, r: float, *,
            step: float = 0.1, half: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Each point's distance (P,) to a polyline (K, D) and the half-width (P,) there, in their unit
    (px, or mm in 3-D).

    The polyline is resampled every ``step`` and searched with a k-d tree (scipy); the half-width is
    interpolated along it from ``edges`` (S, 2, D), side pairs across the finger (half their distance,
    or ``half`` (S,) when given), or is ``r`` without them."""
    polyline = np.asarray(polyline, np.float64)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(polyline, axis=0), axis=1))])
    fine = np.linspace(0.0, arc[-1], max(2, int(arc[-1] / step) + 1))
    dense = np.column_stack([np.interp(fine, arc, polyline[:, j]) for j in range(polyline.shape[1])])
    tree = cKDTree(dense)
    # (cast: scipy-stubs also allow one point's (float, int); points (P, D) give arrays)
    distance, nearest = cast(tuple[np.ndarray, np.ndarray], tree.query(points))
    if edges is None or len(edges) < 2:
        return distance, np.full(len(points), r)
    _, station = tree.query(0.5 * (edges[:, 0] + edges[:, 1]))
    order = np.argsort(fine[station])
    if half is None:
        half = 0.5 * np.linalg.norm(edges[:, 1] - edges[:, 0], axis=1)
    return distance, np.interp(fine[nearest], fine[station][order], half[order])


def face_offset_mm(frame: Frame, mask: np.ndarray, camera: PlaneCamera) -> float | None:
    """How far (mm) the surface seen in ``mask`` lies behind ``camera``'s plane along its normal.

    The median over the mask's readings away from its edge (``_EDGE_PX``) of ``n . P - c``: for an
    object, the depth of its front face relative to the gripper plane (< 0: nearer the camera).
    None when the mask has fewer than 30 such readings (no depth on the object).

    Example (the sample's disc has its face 3 mm behind the fingers' plane):
        >>> from pathlib import Path
        >>> import softgrip_vision
        >>> from softgrip_vision.frames import load_frame
        >>> from softgrip_vision.segmentation import segment
        >>> frame = load_frame(Path(softgrip_vision.__file__).resolve().parents[1] / "data" / "circle_open")
        >>> seg = segment(frame)
        >>> camera = PlaneCamera.from_frame(frame, seg.fingers)
        >>> round(face_offset_mm(frame, seg.object, camera))
        3
    """
    region = np.asarray(mask, dtype=bool)
    if region.shape != frame.depth.shape or not region.any():
        return None
    inside = cv2.distanceTransform(region.view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    v, u = np.nonzero(region & (frame.depth > 0) & (inside >= _EDGE_PX))
    if u.size < _MIN_READINGS:
        return None
    points = camera.rays(np.column_stack([u, v])) * (frame.depth[v, u] * frame.intrinsics.depth_scale * 1000.0)[:, None]
    n = np.asarray(camera.normal)
    return float(np.median(points @ n - camera.depth_mm * n[2]))
