"""Calibration profiles on disk: a small, versioned JSON file (README: "File formats").

A profile says everything the estimator needs about one gripper and how it was obtained::

    {
      "version": 1,
      "gripper": {"base_separation": 64.0},
      "fingers": {
        "left":  {"length": 52.0, "theta_entire": 0.55, "half_thickness": 4.0, "n_links": 10,
                  "base_offset": [0.0, 0.0], "stiffness_ratio": 1.0, "base_compliance": 0.0},
        "right": {...}
      },
      "segmentation": {...},
      "camera": {"name": "synthetic", "intrinsics": {"width": 640, ...}},
      "vision": {"base_end": "auto", "finger_relief_mm": "auto", "detected": {...},
                 "plane_depth_mm": {"open": 120.02, "closed": 119.97, "used": "open"}},
      "fit": {"method": "least-squares", "estimate_method": "mechanics", "frames": [...], "residual_rms_mm": 0.41,
              "frame_residual_rms_mm": [...], "standard_errors": {"left.theta_entire": 0.002, ...},
              "skipped": [{"frame": "...", "reason": "..."}],
              "free_closure": "calib_open + calib_closed", "frame_start_residual_rms_mm": [...],
              "frame_mid_error_mm": [...], "frame_tip_error_mm": [...]}
    }

Each finger's entry uses the field names of :class:`softgrip_jax.FingerModel` (mm, rad), plus an
optional ``base_offset`` [dx, dy] (mm, image axes: x right, y down): the correction a least-squares
fit found between the finger base seen in an open frame and the base the estimate should use.
``stiffness_ratio`` (base-to-tip bending stiffness, > 0, default 1) and ``base_compliance`` (>= 0,
in units of the finger's bending compliance, default 0: clamped) are optional too; only the
mechanics estimate uses them. ``fit.estimate_method`` (optional) is the estimate a least-squares
fit went through, ``"geometric"`` or ``"mechanics"``; the commands estimate with it unless told
otherwise (absent: the profile says nothing, e.g. a one-frame calibration, which uses no estimate).
The other optional ``fit`` fields report a least-squares fit frame by frame: ``free_closure`` names
the pair in ``frames`` whose closed frame shows the gripper closed without an object (the one-frame
calibration's data), and ``frame_start_residual_rms_mm``, ``frame_mid_error_mm`` and
``frame_tip_error_mm`` give, per pair in ``frames``, the residual RMS at the start values and the
mean joint error of the fitted estimate at joint N // 2 and at the tip (mm); profiles without them
load as before.
``segmentation`` holds :class:`softgrip_vision.segmentation.SegmentationSettings` fields (``{}``: defaults);
``camera`` names the camera (serial number, ``"synthetic"``, or ``"unspecified"``) and its
intrinsics (pyrealsense2 names, or null). ``softgrip_vision`` (optional) says how the fingers are measured
(:class:`softgrip_vision.measure.MeasureSettings`: ``base_end`` ``"auto"``/``"rounded"``/``"flat"``,
``finger_relief_mm`` ``"auto"`` or mm) and records under ``detected`` what calibration found in its
frames (each finger's base end, whether the gripper's body was in view, the fitted plane with its
tilt, each finger's relief, the object's face offset, the band of depth readings mixed with the
background), and under ``plane_depth_mm`` the gripper plane's depth (mm) as the open and as the
closed frame measured it, with the frame whose plane the calibration's millimetres use (``"open"``;
calibration warns when the two differ by more than 0.5 mm): records for the user, not inputs.
Profiles without ``plane_depth_mm`` (written before it was recorded) load as before.

Loading validates every field and names the bad one as a path, e.g.
``fingers.left.theta_entire: expected a number in [0, pi/2), got "abc"``. Saving writes a temporary
file next to the target and renames it over the target (``os.replace``), so a profile on disk is
never half-written.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from jaxtyping import ArrayLike

from softgrip_jax import FingerModel, Gripper, SoftgripError
from softgrip_base import input_guard, user_json
from softgrip_calib import profile_schema
from softgrip_calib.profile_schema import MAX_MAGNITUDE, MAX_N_LINKS, show_value  # noqa: F401 - the limits are this module's API too
from softgrip_base.atomic_write import write_atomic
from softgrip_vision.frames import FrameError, Intrinsics
from softgrip_vision.measure import MeasureSettings, MeasureSettingsError
from softgrip_vision.segmentation import SegmentationError, SegmentationSettings

#: The profile format this code writes and reads.
PROFILE_VERSION = 1
SIDES: tuple[str, str] = ("left", "right")
Method = Literal["one-frame", "least-squares"]
METHODS: tuple[str, ...] = ("one-frame", "least-squares")
#: The estimates a least-squares fit can go through (``fit.estimate_method``; softgrip_jax.METHODS).
ESTIMATE_METHODS: tuple[str, ...] = ("geometric", "mechanics")


class ProfileError(SoftgripError):
    """A calibration profile that cannot be read or written; the message names the file and field."""


@dataclass(frozen=True)
class FingerEntry:
    """One finger's calibration: the :class:`~softgrip_jax.FingerModel` fields and a base offset.

    Attributes:
        length: finger length L, mm, > 0 (eq. 5).
        theta_entire: entire bending angle Theta, rad, in [0, pi/2) (eq. 4).
        half_thickness: half the finger thickness r, mm, >= 0.
        n_links: number of links N, 1 to :data:`MAX_N_LINKS`.
        base_offset: (dx, dy) mm in image axes, added to a base detected in an open frame.
        stiffness_ratio: bending stiffness at the base over that at the tip (dimensionless, > 0;
            1: uniform). Only the mechanics estimate uses it.
        base_compliance: compliance of the base's rotational spring in units of the whole finger's
            bending compliance L / mean(k) (dimensionless, >= 0; 0: clamped base). Only the
            mechanics estimate uses it.
    """

    length: float
    theta_entire: float
    half_thickness: float
    n_links: int
    base_offset: tuple[float, float] = (0.0, 0.0)
    stiffness_ratio: float = 1.0
    base_compliance: float = 0.0

    def model(self) -> FingerModel:
        """The core's finger model (float32 by default, as every core input)."""
        return FingerModel(length=self.length, theta_entire=self.theta_entire,
                           half_thickness=self.half_thickness, n_links=self.n_links,
                           stiffness_ratio=self.stiffness_ratio, base_compliance=self.base_compliance)


@dataclass(frozen=True)
class FitEntry:
    """How a profile was obtained.

    Attributes:
        method: ``"one-frame"`` (eqs. 4-5 from one closed and one open frame) or
            ``"least-squares"`` (several open/closed frame pairs).
        frames: labels of the frame pairs used (e.g. ``"OPEN + CLOSED"`` folder names).
        estimate_method: the estimate a least-squares fit went through (``"geometric"`` or
            ``"mechanics"``), which the commands then estimate with by default; None when not
            recorded (a one-frame calibration, or a profile written before it was recorded).
        residual_rms_mm: RMS over the used frames of the joint distances |estimated - observed|, mm;
            None when nothing was compared.
        frame_residual_rms_mm: the same per used frame, in the order of ``frames``.
        standard_errors: standard error of each fitted parameter (``"left.theta_entire"``: rad,
            ``"left.base_offset"``: [mm, mm]); empty for a one-frame calibration.
        skipped: frame pairs left out, each ``{"frame": label, "reason": why}``.
        estimate_method: see above.
        free_closure: the label (one of ``frames``) of the pair whose closed frame shows the gripper
            closed without an object (the free closure, eq. 4), when a least-squares fit used one;
            else None.
        frame_start_residual_rms_mm: per frame of ``frames``, the residual RMS (mm) at the fit's
            start values (empty when not recorded).
        frame_mid_error_mm: per frame, the mean over both fingers of the fitted joint distance
            |estimated - observed| at joint N // 2, mm (empty when not recorded).
        frame_tip_error_mm: the same at the tip, joint N, mm (empty when not recorded).
        model_selection: how a fit chose the stiffness model (:mod:`softgrip_calib.select`): ``{"chosen":
            model name, "reason": text, "candidates": [{"model", "parameters", "residual_rms_mm",
            "held_out_rms_mm", "failure"}, ...]}``; None when the model was given, not chosen.
    """

    method: Method
    frames: list[str]
    residual_rms_mm: float | None = None
    frame_residual_rms_mm: list[float] = field(default_factory=list)
    standard_errors: dict[str, float | list[float]] = field(default_factory=dict)
    skipped: list[dict[str, str]] = field(default_factory=list)
    estimate_method: str | None = None
    free_closure: str | None = None
    frame_start_residual_rms_mm: list[float] = field(default_factory=list)
    frame_mid_error_mm: list[float] = field(default_factory=list)
    frame_tip_error_mm: list[float] = field(default_factory=list)
    model_selection: dict[str, Any] | None = None


#: The optional per-frame lists of ``fit`` (each one value per frame of ``fit.frames``, mm >= 0).
_PER_FRAME = ("frame_residual_rms_mm", "frame_start_residual_rms_mm", "frame_mid_error_mm", "frame_tip_error_mm")


@dataclass(frozen=True)
class CalibrationProfile:
    """A gripper's calibration (see the module docstring for the JSON layout).

    Attributes:
        fingers: ``{"left": FingerEntry, "right": FingerEntry}``.
        base_separation: distance W between the two finger bases, mm, > 0 (JSON
            ``gripper.base_separation``).
        segmentation: :class:`~softgrip_vision.segmentation.SegmentationSettings` fields as a dict (``{}``
            for the defaults).
        camera: ``{"name": str, "intrinsics": dict | None}``.
        fit: how it was obtained.
        version: the format version, :data:`PROFILE_VERSION`.
        vision: :class:`~softgrip_vision.measure.MeasureSettings` fields and what was ``detected``
            (``{}``: defaults, nothing recorded).
    """

    fingers: dict[str, FingerEntry]
    base_separation: float
    segmentation: dict[str, Any]
    camera: dict[str, Any]
    fit: FitEntry
    version: int = PROFILE_VERSION
    vision: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """The JSON object written by :func:`save_profile`."""
        return {
            "version": self.version,
            "gripper": {"base_separation": self.base_separation},
            "fingers": {side: {"length": f.length, "theta_entire": f.theta_entire,
                               "half_thickness": f.half_thickness, "n_links": f.n_links,
                               "base_offset": list(f.base_offset), "stiffness_ratio": f.stiffness_ratio,
                               "base_compliance": f.base_compliance}
                        for side, f in self.fingers.items()},
            "segmentation": dict(self.segmentation),
            "camera": dict(self.camera),
            **({"vision": dict(self.vision)} if self.vision else {}),
            "fit": {"method": self.fit.method,
                    **({} if self.fit.estimate_method is None else {"estimate_method": self.fit.estimate_method}),
                    "frames": list(self.fit.frames),
                    "residual_rms_mm": self.fit.residual_rms_mm,
                    "frame_residual_rms_mm": list(self.fit.frame_residual_rms_mm),
                    "standard_errors": dict(self.fit.standard_errors),
                    "skipped": [dict(s) for s in self.fit.skipped],
                    **({} if self.fit.free_closure is None else {"free_closure": self.fit.free_closure}),
                    **{name: list(getattr(self.fit, name)) for name in _PER_FRAME[1:] if getattr(self.fit, name)},
                    **({} if self.fit.model_selection is None else {"model_selection": self.fit.model_selection})},
        }

    @classmethod
    def from_dict(cls, data: Any, source: str = "profile") -> CalibrationProfile:
        """Validate a JSON object field by field and build the profile.

        Raises:
            ProfileError: the first bad, missing or unknown field, as ``source: path: problem``.
        """
        return _parse(data, source)

    def segmentation_settings(self) -> SegmentationSettings:
        """The segmentation settings (defaults for fields the profile leaves out)."""
        return SegmentationSettings.from_dict(self.segmentation)

    def measure_settings(self) -> MeasureSettings:
        """How to measure the fingers (defaults for fields the profile leaves out)."""
        return MeasureSettings.from_dict(self.vision)

    def gripper(self) -> Gripper:
        """The core's :class:`~softgrip_jax.Gripper` (:func:`to_gripper`)."""
        return to_gripper(self)

    def corrected_bases(self, bases_mm: ArrayLike) -> np.ndarray:
        """(2, 2) [left, right] finger bases detected in an open frame (mm) plus each base offset."""
        offsets = np.array([self.fingers[side].base_offset for side in SIDES])
        return np.asarray(bases_mm, np.float64).reshape(2, 2) + offsets


def check_profile(profile: Any, name: str = "profile") -> None:
    """Raise :class:`ProfileError` unless ``profile`` is a :class:`CalibrationProfile`; the message
    says how to make one from what was given (a path, a plain dict read from a profile file)."""
    if isinstance(profile, CalibrationProfile):
        return
    from softgrip_jax._checks import describe

    if isinstance(profile, dict):
        fix = "make one with softgrip_calib.profile.CalibrationProfile.from_dict(d) (it checks every field)"
    elif isinstance(profile, (str, os.PathLike)):
        fix = "load the file with softgrip_calib.profile.load_profile(path)"
    else:
        fix = "load one with softgrip_calib.profile.load_profile(path), or make one with CalibrationProfile.from_dict(d)"
    raise ProfileError(f"{name}: got {describe(profile)}; a CalibrationProfile is needed: {fix}")


def to_gripper(profile: CalibrationProfile) -> Gripper:
    """The core's :class:`~softgrip_jax.Gripper` of a profile (base offsets are not part of it:
    apply them to detected bases with :meth:`CalibrationProfile.corrected_bases`).

    Example (lengths in mm, angles in rad):
        >>> from pathlib import Path
        >>> import softgrip_calib
        >>> data = Path(softgrip_calib.__file__).resolve().parents[1] / "data"  # the sample frames and profile
        >>> gripper = to_gripper(load_profile(data / "sample_profile.json"))
        >>> round(float(gripper.base_separation), 1), gripper.left.n_links, round(float(gripper.left.theta_entire), 2)
        (64.0, 20, 0.55)
    """
    check_profile(profile)
    return Gripper(left=profile.fingers["left"].model(), right=profile.fingers["right"].model(),
                   base_separation=profile.base_separation)


def _non_finite_number(value: Any, path: str) -> str | None:
    """The path of the first NaN or infinite number inside a JSON value, or None."""
    if isinstance(value, float) and not math.isfinite(value):
        return path
    if isinstance(value, dict):
        items = ((f"{path}.{k}", v) for k, v in value.items())
    elif isinstance(value, list):
        items = ((f"{path}[{i}]", v) for i, v in enumerate(value))
    else:
        return None
    for where, item in items:
        found = _non_finite_number(item, where)
        if found is not None:
            return found
    return None


def save_profile(profile: CalibrationProfile, path: str | os.PathLike[str], *, inputs=(),
                 force: bool = False) -> Path:
    """Validate ``profile`` and write it to ``path`` atomically (replacing an existing regular file,
    keeping its mode; ``inputs`` and ``force`` as in ``softgrip_base.atomic_write.check_output``).

    Raises:
        ProfileError: a field is out of range (named, as when loading), or the file cannot be written.

    Example:
        >>> import tempfile
        >>> from pathlib import Path
        >>> import softgrip_calib
        >>> data = Path(softgrip_calib.__file__).resolve().parents[1] / "data"  # the sample frames and profile
        >>> profile = load_profile(data / "sample_profile.json")
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     copy = load_profile(save_profile(profile, Path(folder) / "gripper.json"))
        >>> copy.to_dict() == profile.to_dict()
        True
    """
    check_profile(profile)
    path = Path(path)
    data = profile.to_dict()
    _parse(data, str(path))  # the same checks as loading: never write a profile that cannot be read
    text = json.dumps(data, indent=2, allow_nan=False) + "\n"
    try:
        write_atomic(path, text.encode("utf-8"), inputs=inputs, force=force, what="profile")
    except OSError as err:
        raise ProfileError(f"{path}: cannot write the profile there ({err.strerror}): check that the folder "
                           f"{path.parent} exists and is writable") from None
    return path


def load_profile(path: str | os.PathLike[str]) -> CalibrationProfile:
    """Read and validate a profile.

    Raises:
        ProfileError: missing or unreadable file, invalid JSON, or a bad field (named by its path).

    Example:
        >>> from pathlib import Path
        >>> import softgrip_calib
        >>> data = Path(softgrip_calib.__file__).resolve().parents[1] / "data"  # the sample frames and profile
        >>> profile = load_profile(data / "sample_profile.json")
        >>> profile.fit.method, round(profile.fingers["left"].length, 1)  # L in mm
        ('one-frame', 52.2)
    """
    path = Path(path)
    text = input_guard.read_user_text(path, what="the profile", max_bytes=input_guard.MAX_PROFILE_BYTES,
                                      error=ProfileError,
                                      missing="no such calibration profile; make one with `softgrip calibrate`")
    try:
        data = user_json.loads(text)
    except json.JSONDecodeError as err:
        raise ProfileError(f"{path}: not valid JSON ({err.msg} at line {err.lineno}, column {err.colno})") from None
    # Values are quoted in messages only from a file that looks like a profile: JSON of other data
    # (a token, a key store) named by mistake is never echoed.
    if not isinstance(data, dict):
        raise ProfileError(f"{path}: expected a JSON object (a calibration profile), got a JSON "
                           f"{_json_kind(data)}: is it the right file? Make one with `softgrip calibrate`")
    if not _PROFILE_KEYS & set(data):
        raise ProfileError(f"{path}: not a calibration profile (it has none of the fields "
                           f"{', '.join(sorted(_PROFILE_KEYS))}): is it the right file? Make one with "
                           f"`softgrip calibrate`")
    return _parse(data, str(path))


#: The top-level fields of a profile: a JSON object with none of them is some other file.
_PROFILE_KEYS = frozenset({"version", "gripper", "fingers", "camera", "fit"})


def _json_kind(data: Any) -> str:
    """The JSON type of ``data`` in words (``"list"``, ``"string"``, ...), never its content."""
    return {list: "list", str: "string", bool: "true/false", type(None): "null"}.get(type(data), "number")


# ---------------------------------------------------------------------------------------------
# Validation: the layout by softgrip_calib.profile_schema (pydantic), then what a field's type cannot say.


def _parse(data: Any, source: str) -> CalibrationProfile:
    if not isinstance(data, dict):
        raise ProfileError(f"{source}: expected a JSON object, got {show_value(data)}")
    document, problem = profile_schema.validate(data)
    if document is None:
        raise ProfileError(f"{source}: {problem}")
    if document.version != PROFILE_VERSION:
        newer = " (the file was written by a newer softgrip-jax)" if document.version > PROFILE_VERSION else ""
        raise ProfileError(f"{source}: version: expected {PROFILE_VERSION}{newer}, got {document.version}")
    try:
        SegmentationSettings.from_dict(document.segmentation, source=f"{source}: segmentation")
    except SegmentationError as err:
        raise ProfileError(str(err)) from None
    if document.camera.intrinsics is not None:
        try:
            Intrinsics.from_dict(document.camera.intrinsics, source=f"{source}: camera.intrinsics")
        except FrameError as err:
            raise ProfileError(str(err)) from None
    vision = data.get("vision", {})
    try:
        MeasureSettings.from_dict(vision, source=f"{source}: vision")
    except MeasureSettingsError as err:
        raise ProfileError(str(err)) from None
    where = _non_finite_number(vision.get("detected", {}), "vision.detected")
    if where is not None:  # a record only, but it must survive being written again
        raise ProfileError(f"{source}: {where}: expected a finite number (a record of what calibration detected)")
    fit = document.fit
    for name in _PER_FRAME:
        values = getattr(fit, name)
        if values and len(values) != len(fit.frames):
            raise ProfileError(f"{source}: fit.{name}: expected one value per frame in fit.frames "
                               f"({len(fit.frames)}), got {show_value(values)}")
    if fit.free_closure is not None and fit.free_closure not in fit.frames:
        raise ProfileError(f"{source}: fit.free_closure: expected the label of one of fit.frames, got "
                           f"{show_value(fit.free_closure)}")
    fingers = {side: FingerEntry(**{**getattr(document.fingers, side).model_dump(),
                                    "base_offset": tuple(getattr(document.fingers, side).base_offset)})
               for side in SIDES}
    return CalibrationProfile(
        fingers=fingers, base_separation=document.gripper.base_separation, segmentation=dict(data["segmentation"]),
        camera=dict(data["camera"]), version=PROFILE_VERSION, vision=dict(vision),
        fit=FitEntry(method=fit.method, frames=list(fit.frames), residual_rms_mm=fit.residual_rms_mm,
                     standard_errors=dict(data["fit"].get("standard_errors", {})),
                     skipped=[s.model_dump() for s in fit.skipped], estimate_method=fit.estimate_method,
                     free_closure=fit.free_closure, **{name: list(getattr(fit, name)) for name in _PER_FRAME},
                     model_selection=None if fit.model_selection is None else fit.model_selection.model_dump()))
