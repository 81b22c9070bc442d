"""One-frame calibration (paper section IV-A, eqs. 4-5).

From a frame of the closed gripper with no object and a frame of the open gripper:

* Theta of each finger from the closed frame, eq. 4: ``atan((x_tip - x_base) / (y_tip - y_base))``,
  with x and y along the gripper's axes (y perpendicular to the line through both bases, so a camera
  rolled about its axis does not tilt the angle) and x mirrored for the right finger (it curls
  toward -x);
* L of each finger from the open frame, eq. 5: the base-tip distance of the straight finger;
* the half-thickness r of each finger from its mask in the open frame (the keypoints' tube fit);
* the base separation W: the distance between the two bases in the open frame.

All in millimetres in the gripper plane. :func:`one_frame_profile` works on keypoints already in
millimetres (anything with ``base_mm``, ``tip_mm``, ``half_thickness_mm`` and ``observed_mm(n)``,
such as :class:`softgrip_vision.keypoints.FingerKeypoints`); :func:`one_frame_from_frames` runs the vision
pipeline on two frames first.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Literal, Protocol, TypedDict

import jax.numpy as jnp
import numpy as np

from softgrip_calib.profile import CalibrationProfile, FingerEntry, FitEntry
from softgrip_jax import FingerFrame, SoftgripError, pcc_joints
from softgrip_vision.frames import Frame, undistort_frame
from softgrip_vision.geometry import PlaneCamera
from softgrip_vision.keypoints import SIDES, FingerKeypoints, finger_length, gripper_angle, theta_from_closed
from softgrip_vision.measure import (PLANE_AGREEMENT_MM, GripperMeasurement, MeasureSettings, MeasurementWarning,
                            PlaneDisagreementWarning, measure_gripper)
from softgrip_vision.segmentation import Segmentation, SegmentationSettings, segment


class FingerMeasurement(Protocol):
    """One finger seen in a frame, in millimetres in the gripper plane."""

    @property
    def base_mm(self) -> np.ndarray:
        """(2,) base point."""

    @property
    def tip_mm(self) -> np.ndarray:
        """(2,) tip point."""

    @property
    def half_thickness_mm(self) -> float:
        """Half-thickness r."""

    @property
    def length_mm(self) -> float:
        """Base-tip distance (L when the finger is open, eq. 5)."""

    @property
    def arc_length_mm(self) -> float:
        """Length of the centreline from base to tip."""

    def observed_mm(self, n_links: int) -> np.ndarray:
        """(N+1, 2) the centreline divided into N equal arc lengths, base first."""


#: How much longer than its base-tip distance an open finger's centreline may be (2 %; a straight
#: finger's measured centreline is within 1.1 % on every renderer variant, 10 degrees of tilt
#: included): beyond it the finger is bent, or its centreline runs along something else.
MAX_OPEN_BEND = 1.02


def one_frame_profile(
    closed: Sequence[FingerMeasurement],
    open_: Sequence[FingerMeasurement],
    n_links: int,
    *,
    label: str = "one frame pair",
    segmentation: dict | None = None,
    camera: dict | None = None,
    vision: dict | None = None,
) -> CalibrationProfile:
    """Calibrate both fingers from their keypoints in a closed (no object) and an open frame.

    Args:
        closed: [left, right] fingers of the closed gripper without an object (Theta, eq. 4).
        open_: [left, right] fingers of the open gripper (L by eq. 5, r, and the bases for W).
        n_links: number of links N of the model.
        label: how the profile's ``fit.frames`` names the frame pair.
        segmentation: segmentation settings to record (``{}`` if None).
        camera: ``{"name", "intrinsics"}`` to record (``"unspecified"`` if None).
        vision: the measurement settings and what was detected, to record (``{}`` if None).

    Returns:
        A profile with ``fit.method = "one-frame"``. Its residual is the RMS distance (mm) between
        the joints of the calibrated PCC shape (eqs. 1-3) hanging from the closed frame's bases and
        the closed fingers' observed positions (centreline in N equal arc lengths): how well one
        constant curvature describes the closed fingers.

    Raises:
        SoftgripError: a finger bent away from the gripper's centre (negative Theta: are the frames
            swapped?) or not below its base (``softgrip_vision.keypoints.KeypointError``), or a bad N.

    Example (the sample calibration pair, rendered with Theta 0.55 rad for both fingers):
        >>> from pathlib import Path
        >>> import softgrip_calib
        >>> from softgrip_vision.frames import load_frame
        >>> data = Path(softgrip_calib.__file__).resolve().parents[1] / "data"  # the sample frames
        >>> _, _, closed = frame_keypoints(load_frame(data / "calib_closed"))
        >>> _, _, opened = frame_keypoints(load_frame(data / "calib_open"))
        >>> profile = one_frame_profile(closed, opened, 20)
        >>> [round(profile.fingers[side].theta_entire, 2) for side in ("left", "right")], profile.fit.method
        ([0.55, 0.55], 'one-frame')
    """
    fingers: dict[str, FingerEntry] = {}
    squared = []
    angle = gripper_angle(closed[0].base_mm, closed[1].base_mm)  # the gripper's axis, as in the estimate
    for side, shut, straight in zip(SIDES, closed, open_):
        bend = straight.arc_length_mm / max(straight.length_mm, 1e-9)
        if bend > MAX_OPEN_BEND:  # eq. 5 would read a chord across a bend (or along a body) as L
            raise SoftgripError(
                f"the {side} finger of the open frame is not straight: its centreline runs "
                f"{straight.arc_length_mm:.1f} mm between a base and tip {straight.length_mm:.1f} mm apart "
                f"({100 * (bend - 1):.0f} % longer); eq. 5 needs the open gripper's straight fingers. Check that "
                f"the open frame shows the gripper open, and, if the gripper's body joins the fingers, leave it "
                f"out with the segmentation's roi or give the base end (--base-end)")
        theta = theta_from_closed(shut.base_mm, shut.tip_mm, side, angle)  # eq. 4
        if theta < 0:
            raise SoftgripError(
                f"the {side} finger of the closed frame bends away from the gripper's centre (Theta = "
                f"{theta:.3f} rad by eq. 4): pass the frame of the closed gripper as CLOSED and the open "
                f"one as --open")
        entry = FingerEntry(length=finger_length(straight.base_mm, straight.tip_mm), theta_entire=theta,
                            half_thickness=float(straight.half_thickness_mm), n_links=n_links)
        fingers[side] = entry
        model_joints = free_closure_joints(entry, shut.base_mm, side, angle)
        squared.append(np.sum((model_joints - shut.observed_mm(n_links)) ** 2, axis=-1))
    rms = float(np.sqrt(np.mean(squared)))
    base_separation = float(np.hypot(*(np.asarray(open_[1].base_mm) - np.asarray(open_[0].base_mm))))
    return CalibrationProfile(
        fingers=fingers, base_separation=base_separation, segmentation=dict(segmentation or {}),
        camera=dict(camera or {"name": "unspecified", "intrinsics": None}),
        fit=FitEntry(method="one-frame", frames=[label], residual_rms_mm=rms, frame_residual_rms_mm=[rms]),
        vision=dict(vision or {}),
    )


def free_closure_joints(entry: FingerEntry, base_mm: np.ndarray, side: str, angle: float = 0.0) -> np.ndarray:
    """(N+1, 2) joints (mm) of the closed, untouched finger (eqs. 1-3) hanging from ``base_mm``,
    mirrored for the right finger as the core mirrors it (a ``FingerFrame`` of handedness -1), on a
    gripper turned by ``angle`` (rad, see :func:`softgrip_vision.keypoints.gripper_angle`).

    Example:
        >>> import numpy as np
        >>> entry = FingerEntry(length=50.0, theta_entire=0.0, half_thickness=4.0, n_links=2)
        >>> free_closure_joints(entry, np.array([10.0, 0.0]), "right").tolist()
        [[10.0, 0.0], [10.0, 25.0], [10.0, 50.0]]
    """
    frame = FingerFrame(origin=jnp.asarray(base_mm, jnp.float32), angle=jnp.asarray(angle, jnp.float32),
                        handedness=jnp.asarray(1.0 if side == "left" else -1.0))
    return np.asarray(frame.to_world(pcc_joints(entry.model(), jnp.zeros(2))), np.float64)


def frame_measurement(frame: Frame, settings: SegmentationSettings | None = None,
                      measure: MeasureSettings | None = None, *,
                      center_hint: float | None = None) -> GripperMeasurement:
    """Segment a frame and measure its gripper (:func:`softgrip_vision.measure.measure_gripper`): the
    fitted gripper plane, both fingers' keypoints and the object's depth. Notes on what was measured
    (e.g. a steep camera tilt) are issued as :class:`softgrip_vision.measure.MeasurementWarning`.

    ``center_hint`` (px) is where another frame of the same set-up put the gripper's centre line
    (used to split fingers that touch); None to find it in this frame. A frame with lens distortion
    is undistorted first (:func:`softgrip_vision.frames.undistort_frame`): the measurement's pixels are those
    of the pinhole frame.

    Raises:
        SoftgripError: segmentation or keypoint failures (their messages say what to adjust).
    """
    frame = undistort_frame(frame)  # the lens undone before any millimetre is measured (free without one)
    seg = segment(frame, settings, center_hint=center_hint)
    measurement = measure_gripper(frame, seg, measure)
    for note in measurement.warnings():
        warnings.warn(note, MeasurementWarning, stacklevel=2)
    return measurement


def frame_keypoints(
    frame: Frame, settings: SegmentationSettings | None = None, measure: MeasureSettings | None = None
) -> tuple[Segmentation, PlaneCamera, tuple[FingerKeypoints, FingerKeypoints]]:
    """Segment a frame and find both fingers' keypoints, in the fitted gripper plane's millimetres
    (:func:`frame_measurement`).

    Raises:
        SoftgripError: segmentation or keypoint failures (their messages say what to adjust).

    Example (the camera's plane depth in mm; the fingers' L in mm):
        >>> from pathlib import Path
        >>> import softgrip_calib
        >>> from softgrip_vision.frames import load_frame
        >>> data = Path(softgrip_calib.__file__).resolve().parents[1] / "data"  # the sample frames
        >>> seg, camera, (left, right) = frame_keypoints(load_frame(data / "calib_open"))
        >>> round(camera.depth_mm), round(left.length_mm), round(right.length_mm)
        (120, 52, 52)
    """
    m = frame_measurement(frame, settings, measure)
    return m.segmentation, m.camera, m.keypoints


class PlaneDepths(TypedDict):
    """What :func:`plane_depths` returns: the plane's depth (mm) in each frame and which one is used."""

    open: float
    closed: float
    used: Literal["open"]


def plane_depths(opened: GripperMeasurement, closed: GripperMeasurement) -> PlaneDepths:
    """The gripper plane's depth (mm) in the open and in the closed frame of one gripper pose, both
    at the pixel halfway between the open frame's finger bases (where a tilted plane's depths are
    compared without the lever of the optical axis), and which one calibration uses:
    ``{"open", "closed", "used": "open"}`` (:func:`one_frame_from_frames` says why).

    Example (the sample calibration pair: both frames show the plane 120 mm deep):
        >>> from pathlib import Path
        >>> import softgrip_calib
        >>> from softgrip_vision.frames import load_frame
        >>> data = Path(softgrip_calib.__file__).resolve().parents[1] / "data"
        >>> depths = plane_depths(frame_measurement(load_frame(data / "calib_open")),
        ...                       frame_measurement(load_frame(data / "calib_closed")))
        >>> round(depths["open"]), round(depths["closed"]), depths["used"]
        (120, 120, 'open')
    """
    centre = 0.5 * (np.asarray(opened.keypoints[0].base_px) + np.asarray(opened.keypoints[1].base_px))
    return {"open": round(opened.plane_depth_at(centre), 3), "closed": round(closed.plane_depth_at(centre), 3),
            "used": "open"}


def one_frame_from_frames(
    closed_frame: Frame,
    open_frame: Frame,
    n_links: int,
    settings: SegmentationSettings | None = None,
    *,
    label: str = "one frame pair",
    camera_name: str = "unspecified",
    names: tuple[str, str] = ("the closed frame", "the open frame"),
    measure: MeasureSettings | None = None,
) -> CalibrationProfile:
    """:func:`one_frame_profile` on a closed frame without an object and an open frame.

    ``names`` (closed, open), e.g. the frame folders, start the error messages. ``measure`` says
    how the fingers are measured (base ends, relief); the profile records it in its ``softgrip_vision``
    section with what was detected in each frame (base ends, body, plane and tilt, relief). The
    closed frame is split at the open frame's centre line when its fingertips touch.

    The gripper plane is measured in both frames (:func:`plane_depths`), which show one gripper
    pose from one camera, so both must put it at the same depth; the profile records both under
    ``vision.plane_depth_mm``, and a :class:`~softgrip_vision.measure.PlaneDisagreementWarning` says when they
    differ by more than :data:`~softgrip_vision.measure.PLANE_AGREEMENT_MM`. Each frame's keypoints are
    converted through its own plane, and the calibration's millimetres (L, r and the base separation,
    the scale of everything the profile holds) are the open frame's: its straight fingers show their
    full width over their whole length, the widest band of readings clear of the mixed band at the
    outline, and nothing touches them, where the closed frame's curled tips may meet and narrow
    toward the image's edge. Theta (eq. 4) is a ratio of two lengths in the closed frame's plane:
    a depth error there scales both alike, so the closed plane only checks the open one.

    Raises:
        SoftgripError: the closed frame shows an object (eq. 4 needs a free closure), or the vision
            pipeline fails on either frame (the message names the frame and what to adjust).

    Example (the sample calibration pair, rendered with Theta 0.55 rad for both fingers):
        >>> from pathlib import Path
        >>> import softgrip_calib
        >>> data = Path(softgrip_calib.__file__).resolve().parents[1] / "data"  # the sample frames and profile
        >>> from softgrip_vision.frames import load_frame
        >>> profile = one_frame_from_frames(load_frame(data / "calib_closed"), load_frame(data / "calib_open"), 20)
        >>> [round(profile.fingers[side].theta_entire, 2) for side in ("left", "right")]
        [0.55, 0.55]
    """
    settings = settings or SegmentationSettings()
    measure = measure or MeasureSettings()

    def measured(frame: Frame, name: str, hint: float | None = None) -> GripperMeasurement:
        try:
            return frame_measurement(frame, settings, measure, center_hint=hint)
        except SoftgripError as err:
            raise type(err)(f"{name}: {err}") from None  # the same error type, naming the frame

    opened = measured(open_frame, names[1])
    closed = measured(closed_frame, names[0], opened.segmentation.center_column)
    if closed.segmentation.object.any():
        raise SoftgripError(
            f"{names[0]} shows an object ({int(closed.segmentation.object.sum())} px): eq. 4 needs the gripper "
            f"closed without touching anything; take the calibration frame without the object (or raise "
            f"the segmentation's object_min_saturation / min_object_px if that is not an object)")
    depths = plane_depths(opened, closed)
    if abs(depths["open"] - depths["closed"]) > PLANE_AGREEMENT_MM:
        warnings.warn(
            f"the gripper plane is {depths['open']:.2f} mm deep in {names[1]} but {depths['closed']:.2f} mm in "
            f"{names[0]} ({abs(depths['open'] - depths['closed']):.2f} mm apart, more than {PLANE_AGREEMENT_MM:g}); "
            f"the calibration uses the open frame's. Check that neither the camera nor the gripper moved between the "
            f"two frames, that the fingers have depth readings across their width (holes, a spatial or hole-filling "
            f"filter smoothing depth across their outline), and the fingers' relief in vision.detected (about the "
            f"half-thickness for a round finger, 0 for a flat front; set it with --finger-relief if known)",
            PlaneDisagreementWarning, stacklevel=2)
    vision = {**measure.to_dict(), "detected": {"open": opened.detected(), "closed": closed.detected()},
              "plane_depth_mm": depths}
    return one_frame_profile(closed.keypoints, opened.keypoints, n_links, label=label,
                             segmentation=settings.to_dict(),
                             camera={"name": camera_name, "intrinsics": closed_frame.intrinsics.to_dict()},
                             vision=vision)
