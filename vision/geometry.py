"""Pixels <-> millimetres in the gripper plane (DESIGN section 3).

The camera looks at the gripper plane, which lies ``depth_mm`` in front of it. A pixel (u, v) (pixel
centres at integer coordinates, x right, y down, as pyrealsense2) maps to the point of that plane

    x_mm = (u - ppx) * Z / fx,    y_mm = (v - ppy) * Z / fy,

so one pixel is ``Z / fx`` mm wide and ``Z / fy`` mm tall there. ``Z`` comes from the frame: a
robust statistic (the median) of the depth readings on the gripper.

Example:
    >>> from vision.frames import Intrinsics
    >>> intr = Intrinsics(width=640, height=480, fx=400.0, fy=400.0, ppx=320.0, ppy=240.0,
    ...                   depth_scale=1e-4)
    >>> camera = PlaneCamera(intr, depth_mm=120.0)
    >>> camera.px_to_mm([420.0, 240.0]).tolist()
    [30.0, 0.0]
    >>> camera.mm_to_px([30.0, 0.0]).tolist()
    [420.0, 240.0]
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from vision.frames import Frame, FrameError, Intrinsics


def plane_depth_mm(frame: Frame, mask: np.ndarray, what: str = "the gripper region") -> float:
    """Depth of the gripper plane: the median depth reading (mm) over ``mask``.

    Args:
        frame: the RGB-D frame.
        mask: (H, W) bool, the pixels on the plane (usually both fingers).
        what: how error messages name the mask.

    Returns:
        The median over the pixels of ``mask`` that have a reading (depth > 0), in mm. The median
        ignores depth holes and outliers at the mask's edges (mixed foreground/background pixels).

    Example:
        >>> from pathlib import Path
        >>> import vision
        >>> data = Path(vision.__file__).resolve().parents[1] / "data"  # the sample frames
        >>> from vision.frames import load_frame
        >>> from vision.segmentation import segment
        >>> frame = load_frame(data / "calib_open")
        >>> round(plane_depth_mm(frame, segment(frame).fingers))
        120

    Raises:
        FrameError: ``mask`` has the wrong shape, or no pixel of it has a depth reading.
    """
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
    return float(np.median(readings)) * frame.intrinsics.depth_scale * 1000.0


@dataclass(frozen=True)
class PlaneCamera:
    """The pinhole camera restricted to the gripper plane at depth ``depth_mm``.

    Attributes:
        intrinsics: the colour camera's intrinsics (fx, fy, ppx, ppy in px).
        depth_mm: distance Z of the gripper plane from the camera, mm, > 0.
    """

    intrinsics: Intrinsics
    depth_mm: float

    def __post_init__(self) -> None:
        if not isinstance(self.intrinsics, Intrinsics):
            raise FrameError(f"PlaneCamera.intrinsics must be an Intrinsics, got "
                             f"{type(self.intrinsics).__name__}")
        depth = float(self.depth_mm)
        if not (math.isfinite(depth) and depth > 0.0):
            raise FrameError(f"PlaneCamera.depth_mm must be a finite depth > 0 mm, got "
                             f"{self.depth_mm!r}")
        object.__setattr__(self, "depth_mm", depth)

    @classmethod
    def from_frame(cls, frame: Frame, plane_mask: np.ndarray) -> PlaneCamera:
        """The camera of ``frame`` at the median depth of ``plane_mask`` (see :func:`plane_depth_mm`)."""
        return cls(frame.intrinsics, plane_depth_mm(frame, plane_mask))

    @property
    def spacing_mm(self) -> np.ndarray:
        """(2,) size of one pixel in the plane, mm: (Z / fx, Z / fy)."""
        return self.depth_mm / np.array([self.intrinsics.fx, self.intrinsics.fy])

    @property
    def mm_per_px(self) -> float:
        """One length scale, mm per px: the geometric mean of the two pixel spacings.

        Exact when fx = fy; otherwise a length converted with it is off by at most
        ``|fx - fy| / (2 min(fx, fy))`` relative (about 0.1 % for a typical D405).
        """
        return float(np.sqrt(np.prod(self.spacing_mm)))

    @property
    def origin_mm(self) -> np.ndarray:
        """(2,) position in mm of the centre of pixel (0, 0)."""
        return self.px_to_mm(np.zeros(2))

    def px_to_mm(self, uv: ArrayLike) -> np.ndarray:
        """Pixels (..., 2) (u right, v down) to mm (..., 2) in the plane; float64."""
        uv = np.asarray(uv, dtype=np.float64)
        principal = np.array([self.intrinsics.ppx, self.intrinsics.ppy])
        return (uv - principal) * self.spacing_mm

    def mm_to_px(self, xy: ArrayLike) -> np.ndarray:
        """Plane points in mm (..., 2) to pixels (..., 2); float64, the inverse of :meth:`px_to_mm`."""
        xy = np.asarray(xy, dtype=np.float64)
        principal = np.array([self.intrinsics.ppx, self.intrinsics.ppy])
        return xy / self.spacing_mm + principal
