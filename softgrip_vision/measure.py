"""A segmented frame -> the gripper measured in millimetres: plane, keypoints, the object's depth.

The steps, each in its own module:

1. each finger's keypoints in pixels (:mod:`softgrip_vision.keypoints`): base (a rounded end, a flat cut, or
   where the finger leaves the gripper's body), tip, centreline, half-width, and the finger's own
   pixels without the body;
2. the gripper plane fitted to the fingers' depth readings (:func:`softgrip_vision.geometry.fit_gripper_plane`):
   its tilt from the camera and each finger's front-surface relief (a round finger's front is up to
   r nearer the camera than its outline), so that each finger's outline is converted at its own depth;
3. the object's front face: its depth relative to the gripper plane
   (:func:`softgrip_vision.geometry.face_offset_mm`), so that its outline is converted at that depth and lands in
   the gripper plane's millimetres.

How to measure is set by :class:`MeasureSettings` (a calibration profile's ``softgrip_vision`` section);
:meth:`GripperMeasurement.detected` is what a profile records of what was found.

Example (the open sample frame: rounded bases, no body in view, a plane facing the camera):
    >>> from pathlib import Path
    >>> import softgrip_vision
    >>> from softgrip_vision.frames import load_frame
    >>> from softgrip_vision.segmentation import segment
    >>> frame = load_frame(Path(softgrip_vision.__file__).resolve().parents[1] / "data" / "calib_open")
    >>> m = measure_gripper(frame, segment(frame))
    >>> [k.base_end for k in m.keypoints], m.body_in_view, m.plane.tilt_deg < 0.5
    (['rounded', 'rounded'], False, True)
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from softgrip_jax import SDFGrid, SoftgripError
from softgrip_vision.coverage import edge_coverage
from softgrip_vision.frames import Frame, FrameError, undistort_frame
from softgrip_vision.geometry import TILT_WARN_DEG, PlaneCamera, PlaneFit, face_offset_mm, fit_gripper_plane
from softgrip_vision.keypoints import FingerKeypoints, KeypointError, gripper_keypoints
from softgrip_vision.object_sdf import object_sdf
from softgrip_vision.segmentation import Segmentation

BaseEndSetting = Literal["auto", "rounded", "flat"]
BASE_END_SETTINGS: tuple[str, ...] = ("auto", "rounded", "flat")
#: The largest finger relief (mm) a profile may give: far beyond any finger's half-thickness.
MAX_RELIEF_MM = 50.0


class MeasureSettingsError(SoftgripError):
    """A bad measurement setting; the message names it."""


class MeasurementWarning(UserWarning):
    """Something measured in a frame that a user should check (e.g. a steep camera tilt)."""


class PlaneDisagreementWarning(MeasurementWarning):
    """Two frames of one gripper pose (calibration's open and closed frames) put the gripper plane
    at depths more than :data:`PLANE_AGREEMENT_MM` apart; the message names both depths."""


#: The largest difference (mm) between the gripper plane's depth measured in the open and in the
#: closed frame of one gripper pose before calibration warns (:class:`PlaneDisagreementWarning`).
PLANE_AGREEMENT_MM = 0.5


@dataclass(frozen=True)
class MeasureSettings:
    """How the gripper is measured (a calibration profile's ``softgrip_vision`` section).

    Attributes:
        base_end: ``"auto"`` (detect from each finger's mask), ``"rounded"`` (the base end is a cap
            whose centre is the base) or ``"flat"`` (the finger is cut flat where it leaves the
            gripper's body: the base is the middle of the cut).
        finger_relief_mm: how far (mm) each finger's outline lies behind its nearest front-surface
            depth reading: r for a round finger, 0 for a flat front; None (JSON ``"auto"``) measures
            it from the depth across the fingers.
    """

    base_end: BaseEndSetting = "auto"
    finger_relief_mm: float | None = None

    def __post_init__(self) -> None:
        if self.base_end not in BASE_END_SETTINGS:
            raise MeasureSettingsError(f"vision.base_end must be one of {', '.join(BASE_END_SETTINGS)}, got "
                                       f"{self.base_end!r}")
        relief = self.finger_relief_mm
        if relief is not None:
            if isinstance(relief, bool) or not isinstance(relief, (int, float)) or not math.isfinite(relief) \
                    or not 0.0 <= relief <= MAX_RELIEF_MM:
                raise MeasureSettingsError(f"vision.finger_relief_mm must be \"auto\" or a number of mm in "
                                           f"[0, {MAX_RELIEF_MM:g}], got {relief!r}")
            object.__setattr__(self, "finger_relief_mm", float(relief))

    @property
    def rounded_base(self) -> bool | None:
        """:func:`softgrip_vision.keypoints.finger_keypoints`' ``rounded_base`` for this setting."""
        return {"auto": None, "rounded": True, "flat": False}[self.base_end]

    def to_dict(self) -> dict[str, Any]:
        """``{"base_end", "finger_relief_mm"}`` for a profile (``"auto"`` for a measured relief)."""
        return {"base_end": self.base_end,
                "finger_relief_mm": "auto" if self.finger_relief_mm is None else self.finger_relief_mm}

    @classmethod
    def from_dict(cls, d: Any, source: str = "vision settings") -> MeasureSettings:
        """Build from a JSON object (missing keys: defaults; unknown keys refused; errors name
        ``source`` and the key). The ``"detected"`` and ``"plane_depth_mm"`` entries (what a
        profile recorded) are ignored."""
        if not isinstance(d, dict):
            raise MeasureSettingsError(f"{source}: expected a JSON object, got {type(d).__name__}")
        known = {"base_end", "finger_relief_mm", "detected", "plane_depth_mm"}
        unknown = sorted(set(d) - known)
        if unknown:
            raise MeasureSettingsError(f"{source}: unknown setting(s) {', '.join(unknown)}; valid ones: "
                                       f"base_end, finger_relief_mm")
        relief = d.get("finger_relief_mm", "auto")
        try:
            return cls(base_end=d.get("base_end", "auto"), finger_relief_mm=None if relief == "auto" else relief)
        except MeasureSettingsError as err:
            raise MeasureSettingsError(f"{source}: {err}") from None


@dataclass(frozen=True, eq=False)
class GripperMeasurement:
    """One frame's gripper in millimetres.

    Attributes:
        segmentation: the frame's :class:`~softgrip_vision.segmentation.Segmentation`.
        plane: the fitted gripper plane (its ``camera`` is :attr:`camera`).
        keypoints: (left, right) :class:`~softgrip_vision.keypoints.FingerKeypoints` through :attr:`camera`.
        object_offset_mm: the object's front face behind the gripper plane (mm, < 0: nearer the
            camera), or None (no object, or no depth on it: taken as 0).
    """

    segmentation: Segmentation
    plane: PlaneFit
    keypoints: tuple[FingerKeypoints, FingerKeypoints]
    object_offset_mm: float | None

    @property
    def camera(self) -> PlaneCamera:
        """The gripper plane's camera: the millimetre frame of the estimate."""
        return self.plane.camera

    @property
    def object_camera(self) -> PlaneCamera:
        """The plane of the object's front face, in the gripper plane's coordinates."""
        return self.camera.parallel(self.object_offset_mm or 0.0)

    @property
    def body_in_view(self) -> bool:
        """True when a finger hangs from a gripper body seen in the frame."""
        return any(k.body_in_view for k in self.keypoints)

    def object_sdf(self, frame: Frame) -> SDFGrid:
        """The object's signed-distance grid (mm, in the gripper plane's coordinates) from its
        outline at the depth of its own face, read at sub-pixel level from ``frame``'s colour (the
        frame this was measured in); far everywhere without an object (:func:`softgrip_vision.object_sdf.object_sdf`)."""
        mask = self.segmentation.object
        frame = undistort_frame(frame)  # the pixels the masks are in (the frame as given: undistorted again)
        return object_sdf(mask, self.object_camera, coverage=edge_coverage(frame.color, mask))

    def warnings(self) -> list[str]:
        """Sentences about what was measured that a user should check (empty when all is ordinary)."""
        out = []
        if self.plane.tilt_deg > TILT_WARN_DEG:
            out.append(f"the camera is tilted {self.plane.tilt_deg:.1f} degrees from the gripper plane (more than "
                       f"{TILT_WARN_DEG:g}): the fingers' sides start to show and millimetres lose accuracy; "
                       f"face the camera to the gripper")
        if self.plane.relief_measured and self.plane.mixed_band_capped:
            out.append(f"the depth readings mix with the background's as far as {self.plane.mixed_band_px:.1f} px "
                       f"into the fingers (of a half-width of about "
                       f"{min(k.half_thickness_px for k in self.keypoints):.1f} px): the relief of the fingers' "
                       f"front (round or flat) and with it the plane's depth may be off by a millimetre or "
                       f"more; turn off or weaken the camera's spatial filter, or give the relief "
                       f"(vision.finger_relief_mm, --finger-relief: the half-thickness for a round finger, 0 for a "
                       f"flat front)")
        if self.segmentation.object.any() and self.object_offset_mm is None:
            out.append("the object has no depth readings: its outline is taken in the gripper plane")
        return out

    def plane_depth_at(self, uv: Any) -> float:
        """The gripper plane's depth Z (mm) at pixel ``uv`` (u, v): where two frames of one pose are
        compared (a tilted plane's depth on the optical axis may lie far from the gripper)."""
        return float(self.camera.depth_at(np.asarray(uv, np.float64)))

    def detected(self) -> dict[str, Any]:
        """What was found, for a profile's ``vision.detected``: base ends, body, plane, relief."""
        sides = ("left", "right")
        return {
            "base_end": {side: k.base_end for side, k in zip(sides, self.keypoints)},
            # Where the fingers lay in the image (px): a frame later compared against them tells a
            # camera turned upside down even when the fingers look the same either way up.
            "base_px": {side: np.round(k.base_px, 1).tolist() for side, k in zip(sides, self.keypoints)},
            "tip_px": {side: np.round(k.tip_px, 1).tolist() for side, k in zip(sides, self.keypoints)},
            "body_in_view": self.body_in_view,
            "plane": self.camera.to_dict(),
            "mixed_band_px": round(self.plane.mixed_band_px, 2),
            "finger_relief_mm": {side: round(r, 3) for side, r in zip(sides, self.plane.relief_mm)},
            "finger_relief_measured": self.plane.relief_measured,
            "object_face_offset_mm": None if self.object_offset_mm is None else round(self.object_offset_mm, 3),
        }


def measure_gripper(frame: Frame, segmentation: Segmentation,
                    settings: MeasureSettings | None = None) -> GripperMeasurement:
    """Measure a segmented frame's gripper and object in millimetres (module docstring).

    Raises:
        SoftgripError: keypoints that cannot be found (``softgrip_vision.keypoints.KeypointError``) or no
            depth on the fingers (``softgrip_vision.frames.FrameError``); implausible intrinsics, gripper
            depth or finger sizes, or fingers that look upside down (``softgrip_vision.plausibility``, naming
            the field to fix); the message says what to adjust.
    """
    from softgrip_vision import plausibility

    settings = settings or MeasureSettings()
    if frame.intrinsics.distorted:  # millimetres from a pinhole model need the lens undone first
        raise FrameError(f"the frame has lens distortion ({frame.intrinsics.model}): undistort it before segmenting "
                         f"and measuring it (softgrip_vision.frames.undistort_frame), as frame_scene and frame_measurement do")
    plausibility.check_intrinsics(frame.intrinsics)  # before any millimetre is computed from them
    provisional = PlaneCamera.from_frame(frame, segmentation.fingers)  # keypoints are found in pixels
    plausibility.check_gripper_depth(provisional.depth_mm, frame.intrinsics)
    keypoints = gripper_keypoints(segmentation, provisional, settings.rounded_base, color=frame.color)
    plausibility.check_orientation(keypoints)  # bases at the gripper's body, tips free
    regions = [k.region for k in keypoints if k.region is not None]
    if len(regions) != len(keypoints):  # gripper_keypoints gives every finger its region
        raise KeypointError("a finger's keypoints have no region (the finger alone) to fit the gripper plane to")
    plane = fit_gripper_plane(frame, regions, [k.half_thickness_px for k in keypoints],
                              settings.finger_relief_mm, centrelines_px=[k.centreline_px for k in keypoints],
                              width_edges_px=[k.width_edges_px for k in keypoints])
    offset = face_offset_mm(frame, segmentation.object, plane.camera) if segmentation.object.any() else None
    body_front = None
    if any(k.body_in_view for k in keypoints):  # the body's edge gives the bases: at its face's depth
        body = segmentation.fingers & ~np.logical_or.reduce(regions)
        body_offset = face_offset_mm(frame, body, plane.camera)
        body_front = None if body_offset is None else -body_offset
    left, right = (k.with_camera(plane.camera, relief, body_front) for k, relief in zip(keypoints, plane.relief_mm))
    measured = (left, right)
    plausibility.check_gripper_size([k.length_mm for k in measured],
                                    float(np.hypot(*(measured[1].base_mm - measured[0].base_mm))), frame.intrinsics)
    return GripperMeasurement(segmentation=segmentation, plane=plane, keypoints=measured, object_offset_mm=offset)


def replace_settings(settings: MeasureSettings, **changes: Any) -> MeasureSettings:
    """``settings`` with some fields changed (validated again)."""
    return dataclasses.replace(settings, **changes)
