"""Plausibility checks of a frame and its measurement: unit and calibration mistakes caught early.

A frame can be perfectly well-formed and still wrong: a ``depth_scale`` of 1000 instead of 0.001
(Open3D's "depth units per metre" where pyrealsense2's "metres per depth unit" is meant), focal
lengths in the wrong unit, a principal point from another resolution. Each of these used to give
confident millimetre figures that are off by factors of thousands. The checks here refuse them with
a :class:`~vision.frames.FrameError` naming the field and the likely fix.

The bounds are deliberately wide (a gripper from a few millimetres to a few metres from the camera,
fingers from 2 mm to 1 m): they catch unit mistakes, not unusual set-ups.
"""

from __future__ import annotations

import math

import numpy as np

from vision.frames import FrameError, Intrinsics

#: Depth (mm) of the gripper plane from the camera: "a few millimetres to a few metres".
GRIPPER_DEPTH_MM = (5.0, 5000.0)
#: A finger's length and the base separation (mm).
FINGER_LENGTH_MM = (2.0, 1000.0)
BASE_SEPARATION_MM = (2.0, 1000.0)
#: Focal lengths (px) and the largest ratio fy / fx (or fx / fy).
FOCAL_PX = (1.0, 1.0e5)
MAX_ASPECT = 2.0
#: How far outside the image the principal point may lie, as a fraction of the image's size.
PRINCIPAL_MARGIN = 0.5


def check_intrinsics(intrinsics: Intrinsics, source: str = "intrinsics.json") -> None:
    """Refuse focal lengths and a principal point no real camera has.

    Raises:
        FrameError: names the field, its value and the fix.

    Example:
        >>> good = Intrinsics(width=640, height=480, fx=385.0, fy=385.0, ppx=320.0, ppy=240.0, depth_scale=0.001)
        >>> check_intrinsics(good)
        >>> check_intrinsics(Intrinsics(640, 480, 1e-300, 385.0, 320.0, 240.0, 0.001))
        Traceback (most recent call last):
        ...
        vision.frames.FrameError: intrinsics.json: fx = 1e-300 px is not a focal length a camera has ...
    """
    lo, hi = FOCAL_PX
    for name in ("fx", "fy"):
        value = getattr(intrinsics, name)
        if not lo <= value <= hi:
            raise FrameError(f"{source}: {name} = {value:g} px is not a focal length a camera has (expected "
                             f"{lo:g} to {hi:g} px; a RealSense at 640x480 has about 385-615): give the colour "
                             f"camera's focal length in pixels, as pyrealsense2's intrinsics report it")
    ratio = intrinsics.fy / intrinsics.fx
    if not 1.0 / MAX_ASPECT <= ratio <= MAX_ASPECT:
        raise FrameError(f"{source}: fx = {intrinsics.fx:g} and fy = {intrinsics.fy:g} px differ by a factor "
                         f"{max(ratio, 1 / ratio):.3g}; real pixels are nearly square: check that both are the "
                         f"colour camera's, at this resolution")
    for name, size in (("ppx", intrinsics.width), ("ppy", intrinsics.height)):
        value = getattr(intrinsics, name)
        if not -PRINCIPAL_MARGIN * size <= value <= (1 + PRINCIPAL_MARGIN) * size:
            raise FrameError(f"{source}: {name} = {value:g} px puts the principal point far outside the "
                             f"{intrinsics.width}x{intrinsics.height} image (it lies near its centre, about "
                             f"{size / 2:g}): are the intrinsics of another resolution or camera?")


def check_gripper_depth(depth_mm: float, intrinsics: Intrinsics, source: str = "intrinsics.json") -> None:
    """Refuse a gripper plane that is not between a few mm and a few metres from the camera: almost
    always a ``depth_scale`` in the wrong unit (or a depth image of another camera).

    Raises:
        FrameError: names depth_scale and the value that would put the gripper in range.
    """
    lo, hi = GRIPPER_DEPTH_MM
    if math.isfinite(depth_mm) and lo <= depth_mm <= hi:
        return
    scale = intrinsics.depth_scale
    hint = ""
    if scale > 0.1:
        hint = (f"; depth_scale is metres per depth unit (RealSense: 0.001, D405: 0.0001), and {scale:g} looks "
                f"like the inverse convention (depth units per metre): try depth_scale = {1.0 / scale:g}")
    elif scale < 1e-5:
        hint = f"; depth_scale {scale:g} metres per unit looks too small (RealSense: 0.001, D405: 0.0001)"
    raise FrameError(f"{source}: with depth_scale = {scale:g} the gripper lies {depth_mm:.4g} mm from the camera; "
                     f"a gripper between {lo:g} mm and {hi / 1000:g} m is expected{hint or ': check depth_scale and the depth image'}")


def check_gripper_size(lengths_mm, separation_mm: float, intrinsics: Intrinsics,
                       source: str = "intrinsics.json") -> None:
    """Refuse fingers and a base separation whose millimetres are implausible: the frame's scale
    (depth_scale, fx, fy) is wrong.

    Raises:
        FrameError: names the measured value and the fields that set the scale.
    """
    lo, hi = FINGER_LENGTH_MM
    for side, length in zip(("left", "right"), lengths_mm):
        if not (math.isfinite(length) and lo <= length <= hi):
            raise FrameError(f"{source}: the {side} finger measures {length:.4g} mm (expected {lo:g} mm to "
                             f"{hi / 1000:g} m): the frame's scale is wrong; check depth_scale "
                             f"({intrinsics.depth_scale:g} m per unit) and fx, fy ({intrinsics.fx:g}, "
                             f"{intrinsics.fy:g} px)")
    lo, hi = BASE_SEPARATION_MM
    if not (math.isfinite(separation_mm) and lo <= separation_mm <= hi):
        raise FrameError(f"{source}: the finger bases lie {separation_mm:.4g} mm apart (expected {lo:g} mm to "
                         f"{hi / 1000:g} m): the frame's scale is wrong; check depth_scale and fx, fy")


#: A region's mean colour counts as swapped when reversing its channels brings it this much closer
#: (ratio of distances) to the expected colour, and its red and blue differ by at least
#: SWAP_MIN_CONTRAST (0-255): a grey region says nothing about the channel order.
SWAP_RATIO = 0.5
SWAP_MIN_CONTRAST = 30.0


def check_channel_order(color, mask, expected_rgb, source: str = "color") -> None:
    """Refuse a colour image whose channels look swapped (BGR where RGB is expected): the mean colour
    of the pixels in ``mask`` (H, W) is compared with ``expected_rgb`` (0-255), as it is and with its
    channels reversed. Use it where a region's colour is known (a coloured calibration object, a
    marker); segmentation itself does not depend on the channel order.

    Raises:
        FrameError: names the fix (``cv2.cvtColor(color, cv2.COLOR_BGR2RGB)``, or load_frame).

    Example:
        >>> import numpy as np
        >>> red = np.zeros((4, 4, 3), np.uint8); red[..., 0] = 200
        >>> check_channel_order(red, np.ones((4, 4), bool), (220, 20, 20))
        >>> check_channel_order(red[..., ::-1], np.ones((4, 4), bool), (220, 20, 20))
        Traceback (most recent call last):
        ...
        vision.frames.FrameError: color: the channels look swapped (BGR): ...
    """
    pixels = np.asarray(color)[np.asarray(mask, bool)]
    if pixels.size == 0:
        return
    mean = pixels.reshape(-1, 3).astype(np.float64).mean(axis=0)
    expected = np.asarray(expected_rgb, np.float64)
    as_is, swapped = np.linalg.norm(mean - expected), np.linalg.norm(mean[::-1] - expected)
    if abs(mean[0] - mean[2]) >= SWAP_MIN_CONTRAST and swapped < SWAP_RATIO * as_is:
        raise FrameError(f"{source}: the channels look swapped (BGR): the region's mean colour is "
                         f"{np.round(mean).astype(int).tolist()} where {np.round(expected).astype(int).tolist()} "
                         f"(RGB) is expected, and reversed it matches; pass cv2.cvtColor(color, "
                         f"cv2.COLOR_BGR2RGB) (cv2.imread gives BGR), or read frames with vision.frames.load_frame")


def straightness(keypoints) -> float:
    """Mean over the fingers of chord / arc (base-to-tip distance over centreline length): about 1
    for straight (open) fingers, smaller the more they curl (closed)."""
    ratios = [k.length_mm / k.arc_length_mm for k in keypoints if k.arc_length_mm > 0]
    return float(np.mean(ratios)) if ratios else float("nan")
