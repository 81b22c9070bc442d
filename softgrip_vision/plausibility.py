"""Plausibility checks of a frame and its measurement: unit and calibration mistakes caught early.

A frame can be perfectly well-formed and still wrong: a ``depth_scale`` of 1000 instead of 0.001
(Open3D's "depth units per metre" where pyrealsense2's "metres per depth unit" is meant), focal
lengths in the wrong unit, a principal point from another resolution. Each of these used to give
confident millimetre figures that are off by factors of thousands. The checks here refuse them with
a :class:`~softgrip_vision.frames.FrameError` naming the field and the likely fix.

The bounds are deliberately wide (a gripper from a few millimetres to a few metres from the camera,
fingers from 2 mm to 1 m): they catch unit mistakes, not unusual set-ups.
"""

from __future__ import annotations

import math

import numpy as np

from softgrip_vision.frames import FrameError, Intrinsics

#: Depth (mm) of the gripper plane from the camera: "a few millimetres to a few metres".
GRIPPER_DEPTH_MM = (5.0, 5000.0)
#: A finger's length and the base separation (mm).
#: Soft grippers' fingers run from a few mm (micro-grippers) to about 20 cm; 300 mm leaves room
#: while a depth_scale ten times too large (a D435's 0.001 on a D405 frame, whose unit is 0.0001)
#: turns a 50 mm finger into 500 mm, which calibration would otherwise take as it is.
FINGER_LENGTH_MM = (2.0, 300.0)
BASE_SEPARATION_MM = (2.0, 1000.0)
#: Focal lengths (px) and the largest ratio fy / fx (or fx / fy). Digital sensors have square
#: pixels: factory calibrations of RealSense D400 colour streams give fx and fy within about 0.5 %
#: (e.g. 615.0 and 615.3 px), OpenCV's chessboard calibration of its sample 640x480 camera within
#: 0.01 %. The old analogue video formats with non-square pixels (PAL 768x576: 1.07, NTSC D1: 10/11)
#: stay inside 1.1; fx and fy taken from two resolutions (1280x720 scaled to 640x480: 1.33) or a
#: mistyped value do not.
FOCAL_PX = (1.0, 1.0e5)
MAX_ASPECT = 1.1
#: The old bound (how far outside the image the principal point could lie, as a fraction of the
#: image's size); kept for callers, the check uses :data:`PRINCIPAL_OFFSET`.
PRINCIPAL_MARGIN = 0.5
#: How far from the image's centre the principal point may lie, as a fraction of the image's width
#: (ppx) or height (ppy). A lens is centred on its sensor to within a few percent: RealSense D400
#: factory values lie within 2 % (e.g. ppy 248.5 of 480), OpenCV's sample calibration 3.5 %
#: (cx 342.4 of 640). 15 % leaves room for a cropped stream; the intrinsics of another resolution
#: (1280x720 ones on a 640x480 frame: 50 %, 848x480 ones: 16 %) land outside.
PRINCIPAL_OFFSET = 0.15


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
        softgrip_vision.frames.FrameError: intrinsics.json: fx = 1e-300 px is not a focal length a camera has ...
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
        if not abs(value - 0.5 * size) <= PRINCIPAL_OFFSET * size:
            raise FrameError(f"{source}: {name} = {value:g} px puts the principal point "
                             f"{abs(value - 0.5 * size) / size:.0%} of the image's size from the centre of the "
                             f"{intrinsics.width}x{intrinsics.height} image (a lens is centred within "
                             f"{PRINCIPAL_OFFSET:.0%}: about {size / 2:g}): are the intrinsics of another "
                             f"resolution or camera?")


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


def _ten_times_hint(length: float, hi: float, intrinsics: Intrinsics) -> str:
    """The likeliest scale mistake behind fingers too long: a D405 frame read with a D435's unit."""
    if math.isfinite(length) and hi < length <= 10 * hi and intrinsics.depth_scale >= 0.001:
        return ("; a D405 frame's depth_scale is 0.0001 m per unit, and a D435's 0.001 on it makes every size 10 "
                "times too large")
    return ""


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
                             f"{intrinsics.fy:g} px){_ten_times_hint(length, hi, intrinsics)}")
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
        softgrip_vision.frames.FrameError: color: the channels look swapped (BGR): ...
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
                         f"cv2.COLOR_BGR2RGB) (cv2.imread gives BGR), or read frames with softgrip_vision.frames.load_frame")


def straightness(keypoints) -> float:
    """Mean over the fingers of chord / arc (base-to-tip distance over centreline length): about 1
    for straight (open) fingers, smaller the more they curl (closed)."""
    ratios = [k.length_mm / k.arc_length_mm for k in keypoints if k.arc_length_mm > 0]
    return float(np.mean(ratios)) if ratios else float("nan")


# ---------------------------------------------------------------------------------------------
# Orientation: the bases at the gripper's body, the tips free

#: What to do about a frame that looks upside down (said by every orientation refusal).
UPSIDE_DOWN_FIX = ("the camera is mounted upside down or the image was flipped: rotate color and depth by 180 "
                   "degrees (np.rot90(image, 2)), or flip them back (np.flipud), or mount the camera so that the "
                   "fingers hang down the image")


#: How much taller than a finger is wide the gripper's body must be where it joins the fingers, to
#: be told from the bottom of one finger curled into a U (a finger's width tall there).
BODY_MIN_HEIGHT = 1.25


def body_below_fingers(region) -> bool:
    """Whether one gripper region (H, W) bool, whose two fingers segmentation could not cut apart,
    is joined by the gripper's body BELOW the fingers: it has no neck the right way up
    (:func:`softgrip_vision.segmentation.neck_column`) but has one flipped vertically, and there the region
    is more than :data:`BODY_MIN_HEIGHT` finger widths tall (a body, not the bottom of one finger
    curled into a U). Then the frame is upside down (a body joins the finger bases, above them, in
    an upright frame)."""
    import cv2

    from softgrip_vision.segmentation import neck_column

    region = np.asarray(region, bool)
    if neck_column(region) is not None:
        return False
    flipped = np.ascontiguousarray(region[::-1])
    neck = neck_column(flipped)
    if neck is None:
        return False
    distance = cv2.distanceTransform(flipped.view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    rows = np.flatnonzero(flipped.any(axis=1))
    width = 2.0 * float(np.median(distance[rows].max(axis=1)))  # a finger's width (px)
    column = flipped[:, int(round(neck))]
    return int(column.sum()) > BODY_MIN_HEIGHT * width


def check_orientation(keypoints, source: str | None = None) -> None:
    """Refuse a frame whose fingers look upside down: both fingers' tip ends cut flat while their
    base ends are rounded. A finger is cut flat where it leaves the gripper's body, and its tip is a
    rounded cap (:attr:`softgrip_vision.keypoints.FingerKeypoints.tip_end`), so that frame shows the fingers
    hanging from their tips. (A gripper body joining the fingers below them is refused by
    segmentation, :func:`body_below_fingers`. Fingers rounded at both ends with no body in view
    look the same either way up: nothing in the frame tells, and nothing is refused.)

    Raises:
        FrameError: says that the frame looks upside down and how to fix it.
    """
    if all(k.tip_end == "flat" and k.base_end == "rounded" for k in keypoints):
        prefix = f"{source}: " if source else ""
        raise FrameError(f"{prefix}the frame looks upside down: both fingers end flat-cut at the bottom (where a "
                         f"finger leaves the gripper's body) and rounded at the top (where its tip is); "
                         f"{UPSIDE_DOWN_FIX}")


#: A frame is upside down against its calibration when each of its tips lies within this fraction
#: of the finger's length (in the image) of a base the calibration's open frame found, mirrored as a
#: flipped or turned image would show it, and each of its bases at least SWAPPED_FAR from every
#: calibrated base. A camera fixed to the gripper (the
#: paper's set-up) sees the bases where calibration did; a camera that sees the gripper move
#: around would need the fingers to land tip for base by chance, within a fifth of their length.
SWAPPED_NEAR = 0.2
SWAPPED_FAR = 0.5


def check_orientation_against_calibration(keypoints, detected_open: dict | None, size: tuple[int, int],
                                          source: str | None = None, profile_source: str = "the profile") -> None:
    """Refuse a frame that shows the calibrated gripper upside down: its finger tips lie where the
    calibration's open frame had the bases once that frame is flipped vertically or turned 180
    degrees, and its bases lie far from the calibrated bases. Fingers rounded at both ends with no
    gripper body in view look the same either way up (:func:`check_orientation` cannot tell), but a
    camera fixed to the gripper sees the bases where calibration did.

    Args:
        keypoints: the frame's two :class:`~softgrip_vision.keypoints.FingerKeypoints` (px).
        size: the image's (width, height), px (the same as the calibration frames').
        detected_open: the profile's ``vision.detected.open`` (its ``base_px`` and ``tip_px``, px);
            profiles written before they were recorded have neither, and are not checked.

    Raises:
        FrameError: names the profile, the pixel positions and the fix.
    """
    if not isinstance(detected_open, dict):
        return
    try:
        bases = np.array([detected_open["base_px"][side] for side in ("left", "right")], np.float64)
        tips = np.array([detected_open["tip_px"][side] for side in ("left", "right")], np.float64)
    except (KeyError, TypeError, ValueError):
        return
    if bases.shape != (2, 2) or not np.isfinite(bases).all() or not np.isfinite(tips).all():
        return
    length_px = float(np.mean(np.linalg.norm(tips - bases, axis=1)))
    if length_px <= 0:
        return
    frame_bases = np.stack([np.asarray(k.base_px, np.float64) for k in keypoints])
    frame_tips = np.stack([np.asarray(k.tip_px, np.float64) for k in keypoints])

    def nearest(points, targets):  # (2,) distance of each point to the nearest target, px
        return np.linalg.norm(points[:, None, :] - targets[None, :, :], axis=-1).min(axis=1)

    width, height = size
    if (nearest(frame_bases, bases) < SWAPPED_FAR * length_px).any():
        return
    for turned, how in ((np.stack([bases[:, 0], height - 1 - bases[:, 1]], axis=1), "flipped vertically"),
                        ((width - 1, height - 1) - bases, "turned 180 degrees")):
        if (nearest(frame_tips, turned) <= SWAPPED_NEAR * length_px).all():
            prefix = f"{source}: " if source else ""
            found = ", ".join(f"({u:.0f}, {v:.0f})" for u, v in frame_tips)
            calibrated = ", ".join(f"({u:.0f}, {v:.0f})" for u, v in bases)
            raise FrameError(f"{prefix}the frame looks upside down against {profile_source}: the fingers' ends "
                             f"at {found} px are where calibration's finger bases, at {calibrated} px, fall in an "
                             f"image {how}; {UPSIDE_DOWN_FIX}")


# ---------------------------------------------------------------------------------------------
# The profile against the frame

#: How far (a fraction of the profile's value) a finger's arc length measured in an open frame may
#: differ from the profile's length L. Calibration measures L the same way, and on the sample frames
#: the two agree within 0.5 mm (1 %); 15 % (8 mm of a 52 mm finger) leaves room for a blurred or
#: partly hidden tip and a plane depth off by a tenth, while another gripper's profile, a length
#: typed in cm or inches, or a depth_scale off by a power of ten lands outside.
LENGTH_TOLERANCE = 0.15
#: The same for the finger's half-thickness r (blur and the edge's sub-pixel phase weigh more on a
#: width of a few tens of pixels) and for the base separation W.
THICKNESS_TOLERANCE = 0.30
SEPARATION_TOLERANCE = 0.25


class ProfileMismatchError(FrameError):
    """A frame whose gripper does not match the calibration profile (finger length, thickness or
    base separation beyond tolerance); the message names the profile, both values and the likely
    mistake."""


def _ratio(measured: float, expected: float) -> float:
    return measured / expected if expected > 0 and math.isfinite(measured) else float("inf")


def check_profile_match(keypoints, separation_mm: float, profile, *, source: str = "frame",
                        profile_source: str = "the profile", lengths: bool = True) -> None:
    """Refuse a frame whose gripper does not look like the profile's: each open finger's arc length
    (the centreline from base to tip: the same for a finger slightly bent) against the profile's L,
    its half-thickness against r, and the bases' distance against W, each within its tolerance
    (:data:`LENGTH_TOLERANCE`, :data:`THICKNESS_TOLERANCE`, :data:`SEPARATION_TOLERANCE`).

    Args:
        keypoints: (left, right) :class:`~softgrip_vision.keypoints.FingerKeypoints` in mm.
        separation_mm: the measured distance between the bases, mm.
        profile: the calibration profile (``fingers[side].length``, ``.half_thickness``,
            ``base_separation``, mm).
        source: how the frame is named in the message.
        profile_source: how the profile is named in the message.
        lengths: compare the finger lengths (False when the frame's own lengths are used).

    Raises:
        ProfileMismatchError: the first value out of tolerance, with the profile's value, the
            frame's, and the likely mistake: every size off by about one factor says the frame's
            scale is wrong (depth_scale, fx, fy), one size alone another gripper's profile.
    """
    checks = []  # (what, measured, profile's, tolerance)
    for k in keypoints:
        finger = profile.fingers[k.side]
        if lengths:
            checks.append((f"the {k.side} finger's length", k.arc_length_mm, float(finger.length), LENGTH_TOLERANCE))
        checks.append((f"the {k.side} finger's half-thickness", k.half_thickness_mm, float(finger.half_thickness),
                       THICKNESS_TOLERANCE))
    checks.append(("the base separation", separation_mm, float(profile.base_separation), SEPARATION_TOLERANCE))
    ratios = [_ratio(measured, expected) for _, measured, expected, _ in checks]
    for (what, measured, expected, tolerance), ratio in zip(checks, ratios):
        if expected <= 0 or abs(ratio - 1.0) <= tolerance:
            continue
        finite = [r for r in ratios if math.isfinite(r) and r > 0]
        common = float(np.exp(np.mean(np.log(finite)))) if finite else float("nan")
        if finite and all(abs(r / common - 1.0) <= 0.15 for r in finite) and abs(common - 1.0) > 0.3:
            ten = "; about 10 times: a D435's 0.001 on a D405 frame" if 7.0 < common < 14.0 else ""
            hint = (f"every size in the frame is {common:.3g} times the profile's, so the frame's scale is wrong: "
                    f"check depth_scale (metres per depth unit: D405 0.0001, D415/D435 0.001{ten}) and fx, fy")
        else:
            hint = (f"is {profile_source} for another gripper (or a value in it mistyped)? calibrate this gripper "
                    f"(softgrip calibrate), or check the frame's depth_scale and fx, fy")
        raise ProfileMismatchError(f"{source}: {what} measures {measured:.4g} mm but {profile_source} says "
                                   f"{expected:.4g} mm (more than {tolerance:.0%} apart): {hint}")
