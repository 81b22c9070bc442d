"""RGB-D frames in memory and on disk (README: "File formats").

A frame on disk is a folder of three files::

    color.png        8-bit, 3 channels (stored BGR, as every PNG written by OpenCV)
    depth.png        16-bit, 1 channel, in units of ``depth_scale`` metres, 0 = no reading
    intrinsics.json  {"width", "height", "fx", "fy", "ppx", "ppy", "depth_scale"[, "model", "coeffs"]}

The intrinsics are those of the colour camera, with pyrealsense2's names: ``fx``/``fy`` focal
lengths and ``ppx``/``ppy`` principal point in pixels, ``depth_scale`` in metres per depth unit,
and optionally the lens distortion, ``model`` (a name from :data:`DISTORTION_MODELS`) and its
``coeffs`` (absent: no distortion).
The depth image is registered to the colour image (pixel (u, v) of both sees the same point).
In place of ``depth.png`` a folder may hold floating-point depth in metres (Open3D's and ROS's
32FC1 convention), as ``depth.npy`` (a numpy array (H, W)) or ``depth.tiff`` (a 32-bit float TIFF);
:func:`load_frame` converts it to units of ``depth_scale`` (NaN, infinite, zero or negative: no
reading). :func:`save_frame` always writes ``depth.png``.
"""

from __future__ import annotations

import io
import json
import stat
import math
import os
import shutil
import uuid
import zlib
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from softgrip_base.errors import SoftgripError
from softgrip_base import input_guard, user_json

COLOR_FILE = "color.png"
DEPTH_FILE = "depth.png"
#: Floating-point depth in metres that :func:`load_frame` reads in place of ``depth.png``.
FLOAT_DEPTH_FILES = ("depth.npy", "depth.tiff")
INTRINSICS_FILE = "intrinsics.json"


class FrameError(SoftgripError):
    """A frame (folder, file or array) that cannot be used; the message names it and the fix."""


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of the colour camera and the depth unit.

    ``width``/``height`` in pixels; ``fx``, ``fy``, ``ppx``, ``ppy`` in pixels (x right, y down,
    origin at the centre of the top-left pixel, as pyrealsense2); ``depth_scale`` in metres per
    unit of the depth image (RealSense D4xx default: 0.001). ``model`` and ``coeffs``: the lens
    distortion (:data:`DISTORTION_MODELS`; ``"none"`` and ``()`` by default), honoured by
    :meth:`undistort_points` and :func:`undistort_frame`.

    Other tools' intrinsics: :meth:`from_matrix` (a 3x3 K and OpenCV's coefficients),
    :meth:`from_open3d` (``open3d.camera.PinholeCameraIntrinsic``), :meth:`from_realsense`
    (pyrealsense2's ``rs.intrinsics``) and :meth:`from_camera_info` (a ROS ``sensor_msgs/CameraInfo``
    message, or a dict).
    """

    width: int
    height: int
    fx: float
    fy: float
    ppx: float
    ppy: float
    depth_scale: float
    model: str = "none"
    coeffs: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if not _is_int(value) or value <= 0:
                raise FrameError(f"{name} must be a positive integer (pixels), got {value!r}")
        for name in ("fx", "fy", "ppx", "ppy", "depth_scale"):
            value = getattr(self, name)
            if not _is_number(value) or not math.isfinite(value):
                raise FrameError(f"{name} must be a finite number, got {value!r}")
        for name in ("fx", "fy", "depth_scale"):
            if getattr(self, name) <= 0:
                raise FrameError(f"{name} must be positive, got {getattr(self, name)!r}")
        for name in _FIELDS:  # plain Python numbers, so equality and JSON behave
            convert = int if name in ("width", "height") else float
            object.__setattr__(self, name, convert(getattr(self, name)))
        model, coeffs = _check_distortion(self.model, self.coeffs)
        object.__setattr__(self, "model", model)
        object.__setattr__(self, "coeffs", coeffs)
        _check_monotonic(self)

    def to_dict(self) -> dict[str, Any]:
        """The JSON object of ``intrinsics.json`` (``model`` and ``coeffs`` only with a distortion)."""
        d = asdict(self)
        if self.model == "none":
            del d["model"], d["coeffs"]
        else:
            d["coeffs"] = list(self.coeffs)
        return d

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 camera matrix K (float64)."""
        return np.array([[self.fx, 0.0, self.ppx], [0.0, self.fy, self.ppy], [0.0, 0.0, 1.0]])

    @property
    def distorted(self) -> bool:
        """Whether the lens distortion is anything but the identity."""
        return self.model != "none" and any(c != 0.0 for c in self.coeffs)

    @classmethod
    def from_matrix(cls, K: Any, width: int, height: int, depth_scale: float = 0.001, dist: Any = None,
                    model: str | None = None) -> Intrinsics:
        """From a 3x3 camera matrix K (pixels; OpenCV's convention, as pyrealsense2's: the origin at
        the centre of the top-left pixel) and optionally OpenCV's distortion coefficients ``dist``
        (k1, k2, p1, p2[, k3[, k4, k5, k6]]: ``"brown_conrady"`` for 4-5, ``"rational_polynomial"``
        for 8; or name the ``model``). K must have no skew.

        Example:
            >>> K = [[615.0, 0.0, 320.5], [0.0, 614.0, 240.5], [0.0, 0.0, 1.0]]
            >>> Intrinsics.from_matrix(K, 640, 480, 0.0001).fx
            615.0
        """
        k = np.asarray(K, dtype=np.float64)
        if k.shape != (3, 3) or not np.isfinite(k).all():
            raise FrameError(f"K must be a finite 3x3 camera matrix, got shape {k.shape}")
        if k[0, 1] != 0.0 or k[1, 0] != 0.0 or tuple(k[2]) != (0.0, 0.0, 1.0):
            raise FrameError(f"K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew), got {k.tolist()}")
        coeffs = () if dist is None else tuple(float(c) for c in np.ravel(dist))
        if model is None:
            model = "none" if not coeffs else "rational_polynomial" if len(coeffs) > 5 else "brown_conrady"
        return cls(width=width, height=height, fx=k[0, 0], fy=k[1, 1], ppx=k[0, 2], ppy=k[1, 2],
                   depth_scale=depth_scale, model=model, coeffs=coeffs)

    @classmethod
    def from_open3d(cls, intrinsic: Any = None, *, width: int | None = None, height: int | None = None,
                    intrinsic_matrix: Any = None, depth_scale: float = 0.001) -> Intrinsics:
        """From Open3D's ``PinholeCameraIntrinsic`` (or its fields ``width``, ``height``,
        ``intrinsic_matrix``, without importing open3d).

        ``depth_scale`` is in metres per depth unit, as everywhere here. Open3D's own
        ``depth_scale`` argument is the inverse (depth units per metre, 1000 for millimetres): a value
        of 1 or more is refused with that fix.

        Example:
            >>> Intrinsics.from_open3d(width=640, height=480, intrinsic_matrix=[[600, 0, 320], [0, 600, 240], [0, 0, 1]]).ppx
            320.0
        """
        if intrinsic is not None:
            missing = [name for name in ("width", "height", "intrinsic_matrix") if not hasattr(intrinsic, name)]
            if missing:
                raise FrameError(f"from_open3d: intrinsic is a {type(intrinsic).__name__} without "
                                 f"{', '.join(missing)}; pass an open3d.camera.PinholeCameraIntrinsic, or "
                                 f"width=, height= and intrinsic_matrix= (3x3 K in pixels)")
            width, height, intrinsic_matrix = intrinsic.width, intrinsic.height, intrinsic.intrinsic_matrix
        if width is None or height is None or intrinsic_matrix is None:
            raise FrameError("from_open3d needs a PinholeCameraIntrinsic, or width, height and intrinsic_matrix")
        if _is_number(depth_scale) and depth_scale >= 1.0:
            raise FrameError(f"depth_scale {depth_scale!r} looks like Open3D's depth units per metre; give metres "
                             f"per unit instead: depth_scale={1.0 / depth_scale!r}")
        return cls.from_matrix(intrinsic_matrix, width, height, depth_scale)

    @classmethod
    def from_camera_info(cls, info: Any, depth_scale: float = 0.001) -> Intrinsics:
        """From a ROS ``sensor_msgs/CameraInfo``: the message object itself (fields read by attribute:
        ROS 1's ``K``/``D``, ROS 2's ``k``/``d``) or a dict with the same keys. ``K``/``k``: 9 numbers
        row by row (pixels); ``D``/``d``: the coefficients of ``distortion_model`` (``plumb_bob``,
        ``rational_polynomial``, ``equidistant``); ``width``, ``height`` in pixels. ``depth_scale``:
        metres per depth unit (CameraInfo does not carry it).

        Example:
            >>> info = {"width": 640, "height": 480, "distortion_model": "plumb_bob",
            ...         "D": [0.1, -0.2, 0.0, 0.0, 0.05], "K": [600, 0, 320, 0, 600, 240, 0, 0, 1]}
            >>> Intrinsics.from_camera_info(info).model
            'brown_conrady'
        """
        if isinstance(info, Mapping):
            get = lambda *keys: next((info[k] for k in keys if k in info), None)  # noqa: E731
        elif any(hasattr(info, key) for key in ("K", "k")):  # a message object (ROS 1 or ROS 2)
            get = lambda *keys: next((getattr(info, k) for k in keys if hasattr(info, k)), None)  # noqa: E731
        else:
            raise FrameError(f"CameraInfo: got a {type(info).__name__}; pass a sensor_msgs/CameraInfo message "
                             f"(fields K or k, D or d, distortion_model, width, height) or a dict with those keys")
        k, d, name = get("K", "k"), get("D", "d"), get("distortion_model") or "plumb_bob"
        width, height = get("width"), get("height")
        if k is None or width is None or height is None:
            raise FrameError("CameraInfo needs K (or k), width and height")
        k = np.asarray(k, dtype=np.float64)
        if k.size != 9:
            raise FrameError(f"CameraInfo K must have 9 numbers, got {k.size}")
        model = _ROS_MODELS.get(str(name))
        if model is None:
            raise FrameError(f"CameraInfo distortion_model {name!r} is not supported; use one of "
                             f"{', '.join(sorted(_ROS_MODELS))}")
        coeffs = [] if d is None else list(np.ravel(d))
        return cls.from_matrix(k.reshape(3, 3), int(width), int(height), depth_scale,
                               dist=coeffs, model=model if any(coeffs) else "none")

    @classmethod
    def from_realsense(cls, intrinsics: Any, depth_scale: float = 0.001) -> Intrinsics:
        """From pyrealsense2's ``rs.intrinsics`` (e.g. ``profile.as_video_stream_profile().get_intrinsics()``),
        read by attribute: ``width``, ``height``, ``fx``, ``fy``, ``ppx``, ``ppy`` (pixels, the same
        conventions as here), ``model`` (an ``rs.distortion``; its name is kept: ``brown_conrady``,
        ``inverse_brown_conrady``, ``modified_brown_conrady``, ``kannala_brandt4``, ``none``) and
        ``coeffs`` (five numbers; the first four for ``kannala_brandt4``). All-zero coefficients read as
        ``"none"``. ``depth_scale``: metres per depth unit (``depth_sensor.get_depth_scale()``; not part of
        ``rs.intrinsics``). librealsense's float32 values are kept at their shortest decimals.

        Raises:
            FrameError: an object without those attributes, or a distortion model softgrip cannot undo
                (``ftheta``), named.

        Example (any object with the same attributes):
            >>> from types import SimpleNamespace
            >>> rs_intr = SimpleNamespace(width=640, height=480, fx=615.0, fy=614.5, ppx=320.25, ppy=240.5,
            ...                           model="distortion.brown_conrady", coeffs=[0.1, -0.2, 0.0, 0.0, 0.05])
            >>> intr = Intrinsics.from_realsense(rs_intr)
            >>> intr.model, intr.coeffs[0], intr.fx
            ('brown_conrady', 0.1, 615.0)
        """
        missing = [name for name in (*_FIELDS[:6], "model", "coeffs") if not hasattr(intrinsics, name)]
        if missing:
            raise FrameError(f"from_realsense: got a {type(intrinsics).__name__} without {', '.join(missing)}; "
                             f"pass pyrealsense2's rs.intrinsics (video_stream_profile.get_intrinsics())")
        model = intrinsics.model
        name = str(getattr(model, "name", model)).rsplit(".", 1)[-1]
        coeffs = tuple(_f32(c) for c in intrinsics.coeffs)
        if not any(coeffs):
            name, coeffs = "none", ()
        elif name not in DISTORTION_MODELS:
            raise FrameError(f"from_realsense: distortion model {name!r} (coeffs {list(coeffs)}) is not supported; "
                             f"use one of {', '.join(DISTORTION_MODELS)}, or undistort the frames before")
        elif name == "kannala_brandt4":
            coeffs = coeffs[:4]
        return cls(width=intrinsics.width, height=intrinsics.height, fx=_f32(intrinsics.fx), fy=_f32(intrinsics.fy),
                   ppx=_f32(intrinsics.ppx), ppy=_f32(intrinsics.ppy), depth_scale=depth_scale, model=name,
                   coeffs=coeffs)

    def undistort_points(self, points: Any) -> np.ndarray:
        """Pixel positions (..., 2) as an ideal pinhole camera with the same K would see them
        (OpenCV's ``undistortPoints`` with ``P = K``; ``cv2.fisheye`` for the equidistant model).
        Without distortion, the points unchanged."""
        pts = np.asarray(points, dtype=np.float64)
        if pts.shape[-1:] != (2,):
            raise FrameError(f"points must have shape (..., 2), got {pts.shape}")
        if not self.distorted:
            return pts.copy()
        _check_undistortable(self)
        flat = pts.reshape(-1, 1, 2)
        k, coeffs = self.matrix, np.asarray(self.coeffs, np.float64)
        if self.model == "kannala_brandt4":
            out = cv2.fisheye.undistortPoints(flat, k, coeffs[:4], P=k, criteria=_UNDISTORT_CRITERIA)
        elif self.model == "inverse_brown_conrady":
            # The coefficients map distorted to undistorted: apply them forward (projectPoints) to the
            # normalised distorted rays.
            rays = cv2.undistortPoints(flat, k, None).reshape(-1, 2)
            homogeneous = np.concatenate([rays, np.ones((len(rays), 1))], axis=1)
            out, _ = cv2.projectPoints(homogeneous, np.zeros(3), np.zeros(3), k, coeffs)
        else:
            out = cv2.undistortPoints(flat, k, coeffs, P=k, criteria=_UNDISTORT_CRITERIA)
        return out.reshape(pts.shape)

    @classmethod
    def from_dict(cls, d: Any, source: str = "intrinsics") -> Intrinsics:
        """Build from a JSON object; errors name ``source`` (usually the file) and the key.

        Keys other than the seven fields (and ``model``, ``coeffs``) are ignored. Integers are accepted
        for the float fields. The layout is the pydantic model :class:`softgrip_vision.intrinsics_schema.IntrinsicsDocument`
        (its JSON Schema: ``softgrip_base/schemas/intrinsics.schema.json``).
        """
        from softgrip_vision.intrinsics_schema import validate  # pydantic: imported only where intrinsics are read

        document, problem = validate(d)
        if document is None:
            raise FrameError(f"{source}: {problem}")
        d = document.model_dump()
        try:
            return cls(**{key: d[key] for key in _FIELDS}, model=d.get("model", "none"), coeffs=d.get("coeffs", ()))
        except FrameError as err:
            raise FrameError(f"{source}: {err}") from None


_FIELDS = ("width", "height", "fx", "fy", "ppx", "ppy", "depth_scale")


def _f32(value: Any) -> float:
    """Shortest decimal of a float32 (librealsense's type): 0.001, not 0.0010000000474974513."""
    return float(str(np.float32(value)))


#: Distortion models (pyrealsense2's names, plus OpenCV's rational polynomial) and how many
#: coefficients each takes. brown_conrady: OpenCV's k1, k2, p1, p2, k3 (ROS plumb_bob);
#: inverse_brown_conrady: the same polynomial mapping distorted to undistorted (RealSense);
#: rational_polynomial: OpenCV's 8; kannala_brandt4: OpenCV's fisheye k1-k4 (ROS equidistant);
#: modified_brown_conrady (RealSense) is recorded, but undistorting it is refused.
DISTORTION_MODELS: dict[str, tuple[int, ...]] = {
    "none": (0, 4, 5, 8), "brown_conrady": (4, 5), "inverse_brown_conrady": (5,),
    "rational_polynomial": (8,), "kannala_brandt4": (4, 5), "modified_brown_conrady": (5,),
}
#: Kept in a frame's intrinsics (a RealSense camera may report them) but not undistorted here.
_NOT_UNDISTORTED = {"modified_brown_conrady"}
_ROS_MODELS = {"plumb_bob": "brown_conrady", "rational_polynomial": "rational_polynomial",
               "equidistant": "kannala_brandt4", "none": "none", "": "none"}


def _check_distortion(model: Any, coeffs: Any) -> tuple[str, tuple[float, ...]]:
    if not isinstance(model, str) or model not in DISTORTION_MODELS:
        raise FrameError(f"model (lens distortion) must be one of {', '.join(DISTORTION_MODELS)}, got {model!r}")
    try:
        values = tuple(float(c) for c in coeffs)
    except (TypeError, ValueError):
        raise FrameError(f"coeffs must be a list of numbers, got {coeffs!r}") from None
    bad = next((index for index, value in enumerate(values) if not math.isfinite(value)), None)
    if bad is not None:
        raise FrameError(f"coeffs[{bad}] of the {model} lens model is {values[bad]!r}: the distortion "
                         f"coefficients must be finite numbers (a lens without distortion: all 0)")
    if model == "none" and any(values):
        raise FrameError(f"coeffs {list(values)} given with model 'none': name the distortion model")
    if values and len(values) not in DISTORTION_MODELS[model]:
        raise FrameError(f"model {model!r} takes {' or '.join(map(str, DISTORTION_MODELS[model]))} coefficients, "
                         f"got {len(values)}")
    names = _COEFF_NAMES.get(model, ())
    for index, (name, value) in enumerate(zip(names, values)):
        limit = _COEFF_LIMITS[model][name[0]]
        if abs(value) > limit:
            raise FrameError(
                f"coeffs[{index}] ({name}) of the {model} lens model is {value!r}, beyond any real lens "
                f"(|{name}| <= {limit:g} here; a RealSense D4xx colour camera has |k| < 0.1, an OpenCV calibration "
                f"of a webcam k1 in [-1, 1]): check the coefficients' order ({', '.join(names)}) and units")
    return model, values


#: Each model's coefficients by name, in the order of ``coeffs`` (OpenCV's and pyrealsense2's).
_COEFF_NAMES: dict[str, tuple[str, ...]] = {
    "brown_conrady": ("k1", "k2", "p1", "p2", "k3"),
    "inverse_brown_conrady": ("k1", "k2", "p1", "p2", "k3"),
    "modified_brown_conrady": ("k1", "k2", "p1", "p2", "k3"),
    "rational_polynomial": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "kannala_brandt4": ("k1", "k2", "k3", "k4", "k5"),
}
#: Largest |coefficient| accepted, by kind (k: radial, p: tangential), far beyond real lenses so that
#: only a mistake (units, order, a corrupted file, 1e30) is refused; whether the lens map is usable
#: over the image is checked separately (:func:`_check_monotonic`). Real values: a RealSense D4xx
#: colour camera |k| < 0.1 and |p| < 0.005; OpenCV calibrations of webcams and wide-angle lenses k1 in
#: [-1, 1] with k2, k3 up to a few units (higher orders offset each other); the rational model's
#: numerator and denominator terms reach tens together; fisheye (Kannala-Brandt) k1-k4 |k| < 1; the
#: tangential p of an assembled lens below 0.01 (0.05 moves an image corner by about 60 px).
_COEFF_LIMITS: dict[str, dict[str, float]] = {
    "brown_conrady": {"k": 20.0, "p": 0.05},
    "inverse_brown_conrady": {"k": 20.0, "p": 0.05},
    "modified_brown_conrady": {"k": 20.0, "p": 0.05},
    "rational_polynomial": {"k": 100.0, "p": 0.05},
    "kannala_brandt4": {"k": 5.0},
}


def _radial_map(intr: Intrinsics, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The model's radial map on normalised radii ``r`` (tangential terms aside) and the
    denominator that must stay positive: for the forward models (brown_conrady, rational,
    modified), the distorted radius of an ideal ray at radius r (tan of its angle off axis); for
    inverse_brown_conrady, the ideal radius of a distorted pixel at r; for kannala_brandt4, the
    distorted radius of a ray at angle r (rad) off axis."""
    c = np.zeros(8)
    c[:len(intr.coeffs)] = intr.coeffs
    r2 = r * r
    if intr.model == "kannala_brandt4":
        return r * (1 + c[0] * r2 + c[1] * r2**2 + c[2] * r2**3 + c[3] * r2**4), np.ones_like(r)
    numerator = 1 + c[0] * r2 + c[1] * r2**2 + c[4] * r2**3
    denominator = 1 + c[5] * r2 + c[6] * r2**2 + c[7] * r2**3  # 1 but for the rational model
    return r * numerator / np.where(denominator > 0, denominator, 1.0), denominator


def corner_radius(intr: Intrinsics) -> float:
    """The largest normalised radius ((u - ppx) / fx, (v - ppy) / fy) of the image's corners, the
    outer edges of the corner pixels."""
    u = np.array([-0.5, intr.width - 0.5]) - intr.ppx
    v = np.array([-0.5, intr.height - 0.5]) - intr.ppy
    return float(np.sqrt(np.max(u**2) / intr.fx**2 + np.max(v**2) / intr.fy**2))


def _check_monotonic(intr: Intrinsics) -> None:
    """Refuse a lens model that is not invertible over the image: its radial map (:func:`_radial_map`)
    must increase from the principal point out to the image's farthest corner, else two rays would meet at
    one pixel (a lens does not do that, a wrong sign or coefficient order does) and undistortion has no
    unique answer."""
    if not intr.distorted:
        return
    corner = corner_radius(intr)
    if intr.model == "inverse_brown_conrady":  # a map of distorted radii: over the image's own radii
        r = np.linspace(0.0, corner, 4001)
    elif intr.model == "kannala_brandt4":  # angles off axis, up to 90 degrees (beyond: no pinhole image)
        r = np.linspace(0.0, 0.5 * math.pi, 20001)[:-1]
    else:  # ideal radii (tan of the angle off axis) up to 89 degrees
        r = np.linspace(0.0, math.tan(math.radians(89.0)), 100001)
    mapped, denominator = _radial_map(intr, r)
    if intr.model != "inverse_brown_conrady":
        reached = np.nonzero(mapped >= corner)[0]
        if len(reached):  # the part of the map the image shows
            r, mapped, denominator = r[:reached[0] + 1], mapped[:reached[0] + 1], denominator[:reached[0] + 1]
    rising = (np.diff(mapped) > 0) & (denominator[1:] > 0)
    if not rising.all():
        stop = float(mapped[np.argmin(rising)]) * intr.fx
        raise FrameError(
            f"the {intr.model} lens model with coeffs {list(intr.coeffs)} folds back {stop:.0f} px from the "
            f"principal point, inside the image (its corners are {corner * intr.fx:.0f} px away): two rays would "
            f"meet at one pixel, which no lens does; check the coefficients' signs and order "
            f"({', '.join(_COEFF_NAMES[intr.model])}) and that they belong to this resolution")
    if intr.model not in ("inverse_brown_conrady", "kannala_brandt4") and mapped[-1] < corner:
        raise FrameError(
            f"the {intr.model} lens model with coeffs {list(intr.coeffs)} maps no ray within 89 degrees of the "
            f"optical axis to the image's corners ({corner * intr.fx:.0f} px from the principal point): check the "
            f"coefficients' signs and order ({', '.join(_COEFF_NAMES[intr.model])})")


#: OpenCV's iterative undistortion stops after 5 steps by default, up to pixels off for a strong
#: barrel (k1 -0.4, k2 0.2: 9 px at a 640x480 image's corners); these criteria converge to 1e-9.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


def undistort_frame(frame: Frame) -> Frame:
    """The frame as an ideal pinhole camera with the same K would see it: colour and depth remapped
    with OpenCV (:func:`undistortion_maps` and ``cv2.remap``: bilinear for colour, nearest for the
    registered depth so that no depth is invented between an edge's two sides), intrinsics without
    distortion (model ``"none"``, the same K). Pixels the lens does not see (a pincushion lens's ideal
    corners) are black with no depth reading. A frame without distortion is returned as it is, so
    calling it again is free.

    Why the whole frame, once, before segmentation (rather than the contours and keypoints later):
    every later step (segmentation, the finger's tube fit, the plane fit on depth, the object's
    signed-distance grid, the overlays) then works on one pinhole image in which straight edges are
    straight, and none of them can forget the lens; the cost is one remap, a few milliseconds at
    640x480.
    """
    intr = frame.intrinsics
    if not intr.distorted:
        return frame
    map_x, map_y = undistortion_maps(intr)
    color = cv2.remap(frame.color, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    depth = cv2.remap(frame.depth, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    plain = Intrinsics(**{**asdict(intr), "model": "none", "coeffs": ()})
    return Frame(color=color, depth=depth, intrinsics=plain)


def undistortion_maps(intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """For every pixel (v, u) of the ideal pinhole image (same K and size), where the lens images it
    in the distorted image: ``(map_x, map_y)``, each float32 (H, W) in pixels, for ``cv2.remap``.

    OpenCV's ``initUndistortRectifyMap`` (``cv2.fisheye``'s for kannala_brandt4); for RealSense's
    inverse_brown_conrady, whose polynomial maps distorted to ideal, its inverse by OpenCV's iteration.

    Raises:
        FrameError: a model this cannot undistort (modified_brown_conrady).
    """
    _check_undistortable(intr)
    size, k = (intr.width, intr.height), intr.matrix
    coeffs = np.asarray(intr.coeffs, np.float64)
    if not intr.distorted:
        v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float32)
        return u, v
    if intr.model == "kannala_brandt4":
        return cv2.fisheye.initUndistortRectifyMap(k, coeffs[:4], np.eye(3), k, size, cv2.CV_32FC1)
    if intr.model == "inverse_brown_conrady":
        v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
        source = distort_points(intr, np.stack([u, v], axis=-1)).astype(np.float32)
        return source[..., 0].copy(), source[..., 1].copy()
    return cv2.initUndistortRectifyMap(k, coeffs, None, k, size, cv2.CV_32FC1)


def _check_undistortable(intr: Intrinsics) -> None:
    if intr.model in _NOT_UNDISTORTED and intr.distorted:
        raise FrameError(f"undistorting the {intr.model!r} lens model is not supported; give the camera's "
                         f"intrinsics in another model (e.g. from its calibration with OpenCV)")


def distort_points(intr: Intrinsics, points: Any) -> np.ndarray:
    """Ideal (pinhole, same K) pixel positions (..., 2) -> where the lens images them (..., 2): the
    inverse of :meth:`Intrinsics.undistort_points`. OpenCV's ``projectPoints`` (``cv2.fisheye.distortPoints``
    for kannala_brandt4); without distortion, the points unchanged."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[-1:] != (2,):
        raise FrameError(f"points must have shape (..., 2), got {pts.shape}")
    if not intr.distorted:
        return pts.copy()
    _check_undistortable(intr)
    flat = pts.reshape(-1, 1, 2)
    k, coeffs = intr.matrix, np.asarray(intr.coeffs, np.float64)
    if intr.model == "inverse_brown_conrady":  # the inverse of applying the polynomial: OpenCV's iteration
        out = cv2.undistortPoints(flat, k, coeffs, P=k, criteria=_UNDISTORT_CRITERIA)
        return out.reshape(pts.shape)
    rays = cv2.undistortPoints(flat, k, None).reshape(-1, 2)
    if intr.model == "kannala_brandt4":
        return cv2.fisheye.distortPoints(rays.reshape(-1, 1, 2), k, coeffs[:4]).reshape(pts.shape)
    homogeneous = np.concatenate([rays, np.ones((len(rays), 1))], axis=1)
    out, _ = cv2.projectPoints(homogeneous, np.zeros(3), np.zeros(3), k, coeffs)
    return out.reshape(pts.shape)


@dataclass(frozen=True)
class Frame:
    """One registered RGB-D frame.

    ``color``: (H, W, 3) uint8, **RGB** channel order. ``depth``: (H, W) uint16 in units of
    ``intrinsics.depth_scale`` metres, 0 where the camera has no reading; at least one reading
    is required. ``intrinsics.width`` = W and ``intrinsics.height`` = H.

    A floating-point ``depth`` is taken as metres (Open3D's and ROS's 32FC1 convention) and stored
    as uint16 in units of ``depth_scale``, rounded to the nearest unit (RealSense D4xx: 1 mm; choose
    a smaller ``depth_scale`` for finer steps); NaN, infinite, zero and negative values mean no
    reading. Depth beyond 65535 units, or that looks like millimetres, is refused with the fix.

    Segmentation reads only saturation and value, which do not depend on the channel order: a BGR
    image gives the same measurements, with swapped colours in the plots. To catch one anyway,
    :func:`softgrip_vision.plausibility.check_channel_order` compares a region with its known colour.

    Example:
        >>> from synthetic.render import d405_intrinsics
        >>> metres = np.full((480, 640), 0.12, np.float32)  # 120 mm
        >>> metres[0, 0] = np.nan
        >>> frame = Frame(np.zeros((480, 640, 3), np.uint8), metres, d405_intrinsics())
        >>> frame.depth.dtype.name, int(frame.depth[1, 1]), int(frame.depth[0, 0]), float(frame.depth_mm[1, 1])
        ('uint16', 1200, 0, 120.0)
    """

    color: np.ndarray
    depth: np.ndarray
    intrinsics: Intrinsics

    def __post_init__(self) -> None:
        if isinstance(self.depth, np.ndarray) and np.issubdtype(self.depth.dtype, np.floating) \
                and isinstance(self.intrinsics, Intrinsics):
            object.__setattr__(self, "depth", depth_from_metres(self.depth, self.intrinsics.depth_scale))
        _check_frame(self.color, self.depth, self.intrinsics, "color", "depth", "intrinsics")

    @property
    def depth_mm(self) -> np.ndarray:
        """(H, W) float32 depth in millimetres, NaN where there is no reading."""
        depth = self.depth.astype(np.float32) * np.float32(self.intrinsics.depth_scale * 1000.0)
        depth[self.depth == 0] = np.nan
        return depth


#: Float depth whose median reading is beyond this (metres) is taken for millimetres and refused.
MAX_METRES = 20.0


def depth_from_metres(depth: np.ndarray, depth_scale: float, name: str = "depth") -> np.ndarray:
    """Float depth in metres (H, W) as uint16 units of ``depth_scale`` metres (0: no reading, where
    the input is NaN, infinite, zero or negative), rounded to the nearest unit.

    Raises:
        FrameError: the depth looks like millimetres, or exceeds 65535 units of ``depth_scale``.
    """
    metres = np.asarray(depth, dtype=np.float64)
    read = np.isfinite(metres) & (metres > 0)
    if read.any():
        median = float(np.median(metres[read]))
        if median > MAX_METRES:
            raise FrameError(f"{name} is floating-point, which is read as metres, but its median reading is "
                             f"{median:g} m: is it in millimetres? Divide it by 1000 (or pass uint16 depth "
                             f"units with their depth_scale)")
        deepest = float(metres[read].max())
        if deepest / depth_scale > np.iinfo(np.uint16).max + 0.5:
            raise FrameError(f"{name} reaches {deepest:g} m, more than 65535 units of depth_scale = "
                             f"{depth_scale:g} m: use a depth_scale of at least {deepest / 65535:.3g} m per unit "
                             f"in the intrinsics")
    units = np.zeros(metres.shape, np.uint16)
    units[read] = np.rint(metres[read] / depth_scale).astype(np.uint16)
    return units


def load_frame(path: str | os.PathLike[str]) -> Frame:
    """Read a frame folder (``color.png``, ``depth.png``, ``intrinsics.json``; or floating-point
    depth in metres as ``depth.npy`` or ``depth.tiff`` in place of ``depth.png``).

    Returns:
        ``Frame``: ``color`` uint8 (H, W, 3) RGB, ``depth`` uint16 (H, W) in units of
        ``intrinsics.depth_scale`` metres (0: no reading), ``intrinsics`` (px; metres per unit).

    Example:
        >>> from pathlib import Path
        >>> import softgrip_vision
        >>> data = Path(softgrip_vision.__file__).resolve().parents[1] / "data"  # the sample frames
        >>> frame = load_frame(data / "circle_open")
        >>> frame.color.shape, frame.depth.dtype.name, frame.intrinsics.fx, frame.intrinsics.depth_scale
        ((480, 640, 3), 'uint16', 385.0, 0.0001)
    """
    folder = Path(path)
    try:
        mode = os.stat(folder).st_mode
    except (FileNotFoundError, NotADirectoryError):
        raise FrameError(f"frame folder {folder} does not exist: give a folder written by "
                         f"'softgrip capture' (or one with {COLOR_FILE}, {DEPTH_FILE}, "
                         f"{INTRINSICS_FILE})") from None
    except OSError as err:  # a name too long, a loop of links, no permission: named, not a traceback
        raise FrameError(f"cannot open the frame folder {folder}: {input_guard.os_error_reason(err)}") from None
    if not stat.S_ISDIR(mode):
        raise FrameError(f"{folder} is not a folder: a frame is a folder with {COLOR_FILE}, "
                         f"{DEPTH_FILE} and {INTRINSICS_FILE}")
    color_path, intr_path = folder / COLOR_FILE, folder / INTRINSICS_FILE
    color = _read_png(color_path)
    _refuse_greyscale(color, color_path)
    if color.ndim == 3 and color.shape[2] == 3:
        color = cv2.cvtColor(color, cv2.COLOR_BGR2RGB)
    intrinsics = Intrinsics.from_dict(_read_json(intr_path), source=str(intr_path))
    depth_path = _depth_file(folder)
    if depth_path.name == DEPTH_FILE:
        depth = _read_png(depth_path)
    else:
        metres = _read_float_depth(depth_path)
        if metres.shape != color.shape[:2]:
            raise FrameError(f"{color_path} is {color.shape[1]}x{color.shape[0]} but {depth_path} is "
                             f"{metres.shape[1]}x{metres.shape[0]} (width x height): depth must be registered "
                             f"to the colour image, at the same size")
        depth = depth_from_metres(metres, intrinsics.depth_scale, name=str(depth_path))
    _check_frame(color, depth, intrinsics, str(color_path), str(depth_path), str(intr_path))
    return Frame(color=color, depth=depth, intrinsics=intrinsics)


#: A colour image whose three channels nowhere differ by more than this (of 255) is greyscale...
GREY_TOLERANCE = 2
#: ... when its grey levels span more than this: a picture (a flat fill is refused by segmentation as
#: "no gripper found" anyway).
GREY_MIN_CONTRAST = 16
_GREY_WHY = ("the gripper is told from the object by colour saturation: give the camera's colour image, not a "
             "greyscale or infrared one")


def greyscale_problem(color: np.ndarray) -> str | None:
    """What makes ``color`` (H, W[, C]) a greyscale image ("is greyscale (1 channel); ...": one
    channel, or three equal ones with some contrast), or None for a colour image. Segmentation tells
    the white fingers from the object by colour saturation, which a grey image does not have."""
    if color.ndim == 2 or (color.ndim == 3 and color.shape[2] in (1, 2)):
        return f"is greyscale (1 channel); softgrip needs 8-bit colour with 3 channels (RGB): {_GREY_WHY}"
    if color.ndim == 3 and color.shape[2] == 3 and color.dtype == np.uint8 and color.size:
        red, green, blue = cv2.split(np.ascontiguousarray(color))  # |a - b| of uint8 channels, exactly
        spread = max(int(cv2.absdiff(red, green).max()), int(cv2.absdiff(green, blue).max()))
        if spread <= GREY_TOLERANCE and int(green.max()) - int(green.min()) > GREY_MIN_CONTRAST:
            return f"is greyscale (its 3 channels are equal); softgrip needs colour: {_GREY_WHY}"
    return None


def _refuse_greyscale(color: np.ndarray, path: Path) -> None:
    """Refuse a one-channel ``color.png`` with that cause (three equal channels are refused where the
    frame is segmented: :func:`softgrip_vision.segmentation.segment_batch`)."""
    if color.ndim == 2 or (color.ndim == 3 and color.shape[2] in (1, 2)):
        raise FrameError(f"{path} {greyscale_problem(color)}")


def _depth_file(folder: Path) -> Path:
    """The folder's one depth file: ``depth.png``, or one of :data:`FLOAT_DEPTH_FILES`."""
    present = [folder / name for name in (DEPTH_FILE, *FLOAT_DEPTH_FILES) if (folder / name).exists()]
    if len(present) > 1:
        raise FrameError(f"{folder} holds {' and '.join(p.name for p in present)}: keep one depth file "
                         f"(remove the others), so that it is clear which one the frame is")
    return present[0] if present else folder / DEPTH_FILE  # (missing: _read_png names it)


def _read_float_depth(path: Path) -> np.ndarray:
    """Floating-point depth in metres (H, W) from ``depth.npy`` or a 32-bit float ``depth.tiff``."""
    if path.suffix == ".npy":
        try:
            depth = np.load(io.BytesIO(_read_file(path)), allow_pickle=False)
        except (OSError, ValueError) as error:
            raise FrameError(f"{path} is not a readable numpy array ({error}): save it with numpy.save") from None
    else:
        depth = cv2.imdecode(np.frombuffer(_read_file(path), np.uint8), cv2.IMREAD_UNCHANGED)
        if depth is None:
            raise FrameError(f"{path} is not a readable TIFF image: write it again, e.g. with "
                             f"cv2.imwrite(path, depth_metres.astype(numpy.float32))")
    if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.floating):
        raise FrameError(f"{path} must hold floating-point depth in metres, one channel (H, W), got "
                         f"{_describe(depth)}; integer depth in units of depth_scale goes in {DEPTH_FILE}")
    if not all(1 <= side <= MAX_IMAGE_SIDE for side in depth.shape):
        raise FrameError(f"{path} is {depth.shape[1]}x{depth.shape[0]}: a frame image may be at most "
                         f"{MAX_IMAGE_SIDE} px wide and high")
    return depth


def save_frame(frame: Frame, path: str | os.PathLike[str]) -> Path:
    """Write ``frame`` as the folder ``path`` and return it; never overwrites anything.

    The files are written into a hidden temporary sibling folder that is renamed to ``path`` once
    complete, so ``path`` either does not exist or holds a whole frame. Missing parent folders are
    created.

    Example:
        >>> import tempfile
        >>> from pathlib import Path
        >>> import numpy as np
        >>> from synthetic.render import d405_intrinsics
        >>> frame = Frame(np.zeros((480, 640, 3), np.uint8), np.full((480, 640), 1200, np.uint16), d405_intrinsics())
        >>> with tempfile.TemporaryDirectory() as root:
        ...     path = save_frame(frame, next_frame_dir(root))
        ...     print(path.name, int(load_frame(path).depth[0, 0]), next_frame_dir(root).name)
        frame_0000 1200 frame_0001
    """
    target = Path(path)
    _refuse_existing(target)
    color_png = _encode_png(cv2.cvtColor(frame.color, cv2.COLOR_RGB2BGR), target / COLOR_FILE)
    depth_png = _encode_png(frame.depth, target / DEPTH_FILE)
    intr_json = (json.dumps(frame.intrinsics.to_dict(), indent=2) + "\n").encode()
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.parent / f".{target.name}.{uuid.uuid4().hex[:12]}.partial"
    tmp.mkdir()  # not tempfile.mkdtemp: that makes the folder private (0700) instead of umask
    try:
        for name, data in ((COLOR_FILE, color_png), (DEPTH_FILE, depth_png),
                           (INTRINSICS_FILE, intr_json)):
            _write_file(tmp / name, data)
        _refuse_existing(target)
        os.rename(tmp, target)
    except BaseException as err:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(err, OSError):
            raise FrameError(f"could not write frame {target}: {err}") from err
        raise
    return target


def next_frame_dir(root: str | os.PathLike[str], prefix: str = "frame") -> Path:
    """The first of ``root/<prefix>_0000``, ``root/<prefix>_0001``, ... that does not exist.

    Example:
        >>> next_frame_dir("/nonexistent/frames").name
        'frame_0000'
    """
    root = Path(root)
    index = 0
    while (root / f"{prefix}_{index:04d}").exists():
        index += 1
    return root / f"{prefix}_{index:04d}"


def _check_frame(color: Any, depth: Any, intrinsics: Any,
                 color_name: str, depth_name: str, intr_name: str) -> None:
    """Validate a colour/depth/intrinsics triple; messages use the given names (file paths)."""
    if not isinstance(color, np.ndarray) or color.dtype != np.uint8 or color.ndim != 3 \
            or color.shape[2] != 3:
        raise FrameError(f"{color_name} must be an 8-bit colour image with 3 channels (RGB), got "
                         f"{_describe(color)}: convert it to 8-bit RGB")
    if isinstance(depth, np.ndarray) and depth.dtype == np.uint8:
        raise FrameError(f"{depth_name} is 8-bit: depth must be 16-bit (uint16) in units of "
                         f"depth_scale metres, 0 = no reading; save the camera's raw depth, not a "
                         f"visualisation")
    if not isinstance(depth, np.ndarray) or depth.dtype != np.uint16 or depth.ndim != 2:
        raise FrameError(f"{depth_name} must be a 16-bit single-channel depth image, got "
                         f"{_describe(depth)}")
    if color.shape[:2] != depth.shape:
        raise FrameError(f"{color_name} is {color.shape[1]}x{color.shape[0]} but {depth_name} is "
                         f"{depth.shape[1]}x{depth.shape[0]} (width x height): depth must be "
                         f"registered to the colour image, at the same size")
    if not isinstance(intrinsics, Intrinsics):
        raise FrameError(f"{intr_name} must be an Intrinsics, got {type(intrinsics).__name__}")
    if (intrinsics.width, intrinsics.height) != (depth.shape[1], depth.shape[0]):
        raise FrameError(f"{intr_name} says {intrinsics.width}x{intrinsics.height} but the images "
                         f"are {depth.shape[1]}x{depth.shape[0]}: use the intrinsics of the "
                         f"colour stream at this resolution")
    if not depth.any():
        raise FrameError(f"{depth_name} has no depth readings (every pixel is 0): check that the "
                         f"camera sees the scene within its depth range")


def _describe(array: Any) -> str:
    if not isinstance(array, np.ndarray):
        return type(array).__name__
    bits = {np.dtype(np.uint8): "8-bit", np.dtype(np.uint16): "16-bit"}.get(array.dtype,
                                                                           str(array.dtype))
    channels = 1 if array.ndim == 2 else array.shape[-1] if array.ndim == 3 else None
    if channels is None:
        return f"{bits} array of shape {array.shape}"
    return f"{bits} with {channels} channel(s)"


#: Largest width or height of a frame image (px), checked in the PNG header before decoding, so that a
#: file claiming 60000x60000 px (or a small file that inflates to gigabytes) is refused at once.
MAX_IMAGE_SIDE = 8192


def png_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG's header (its IHDR chunk), or None if there is none."""
    if len(data) >= 24 and data.startswith(_PNG_SIGNATURE) and data[12:16] == b"IHDR":
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    return None


def _read_png(path: Path) -> np.ndarray:
    data = _read_file(path)
    size = png_size(data)
    if size is not None and not all(1 <= side <= MAX_IMAGE_SIDE for side in size):
        raise FrameError(f"{path}: its header says {size[0]}x{size[1]} px; a frame image may be at most "
                         f"{MAX_IMAGE_SIDE} px wide and high (a RealSense gives up to 1920x1080): is it the "
                         f"right file, or damaged?")
    problem = _png_damage(data)
    image = None if problem else cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FrameError(f"{path} is not a readable PNG image ({problem or 'OpenCV cannot decode it'}): "
                         f"write it again, e.g. with 'softgrip capture'")
    return image


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _png_damage(data: bytes) -> str | None:
    """What is wrong with the PNG file structure of ``data`` (signature, chunk lengths and CRCs, the
    IEND chunk), or None. Checked before decoding, because libpng prints its own complaint about a
    damaged file on stderr before OpenCV gives up."""
    if not data:
        return "the file is empty"
    if not data.startswith(_PNG_SIGNATURE):
        return "no PNG signature"
    at = len(_PNG_SIGNATURE)
    while at + 12 <= len(data):
        length = int.from_bytes(data[at:at + 4], "big")
        kind, end = data[at + 4:at + 8], at + 12 + length
        if end > len(data):
            break
        if zlib.crc32(data[at + 4:end - 4]) != int.from_bytes(data[end - 4:end], "big"):
            return f"its {kind.decode('latin-1')!r} chunk at byte {at} is damaged (CRC mismatch)"
        if kind == b"IEND":
            return None
        at = end
    return f"truncated after {len(data)} bytes"


def _read_json(path: Path) -> Any:
    """The JSON object of ``intrinsics.json``. Its values are quoted in later messages only when it
    looks like intrinsics (an object with at least one of the fields): other JSON named by mistake
    is never echoed."""
    try:
        data = user_json.loads(_read_file(path, input_guard.MAX_INTRINSICS_BYTES).decode("utf-8-sig"))
    except UnicodeDecodeError as err:  # the offset only: the bytes are not quoted
        raise FrameError(f"{path} is not valid JSON (not UTF-8 text: invalid byte at offset {err.start}): it "
                         f"must be an object with keys {', '.join(_FIELDS)}") from None
    except json.JSONDecodeError as err:
        raise FrameError(f"{path} is not valid JSON ({err}): it must be an object with keys "
                         f"{', '.join(_FIELDS)}") from None
    if not isinstance(data, dict) or not set(_FIELDS) & set(data):
        raise FrameError(f"{path} is not camera intrinsics: expected a JSON object with keys {', '.join(_FIELDS)}; "
                         f"write it again, e.g. with 'softgrip capture'")
    return data


#: Largest frame file read (bytes): a 1920x1080 16-bit PNG without compression is about 4 MB.
MAX_FILE_BYTES = input_guard.MAX_FRAME_FILE_BYTES


def _read_file(path: Path, max_bytes: int | None = None) -> bytes:
    """The bytes of a frame file, through the input guard (``softgrip_base.input_guard``): a regular
    file (never a folder, FIFO or device) of at most ``max_bytes`` (default :data:`MAX_FILE_BYTES`)."""
    limit = MAX_FILE_BYTES if max_bytes is None else max_bytes
    return input_guard.read_user_file(
        path, what="the frame file", max_bytes=limit, error=FrameError,
        missing=f"missing: a frame folder needs {COLOR_FILE}, {DEPTH_FILE} and {INTRINSICS_FILE}")


def _encode_png(image: np.ndarray, name: Path) -> bytes:
    ok, buffer = cv2.imencode(".png", image)
    if not ok:
        raise FrameError(f"OpenCV could not encode {name} as PNG")
    return buffer.tobytes()


def _write_file(path: Path, data: bytes) -> None:
    with open(path, "xb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def _refuse_existing(path: Path) -> None:
    if os.path.lexists(path):
        raise FrameError(f"{path} already exists: captures are never overwritten; choose another "
                         f"folder or remove it first")


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) \
        and not isinstance(value, (bool, np.bool_))
