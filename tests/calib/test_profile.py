"""Calibration profiles: round trip, atomic writes, and a named error for every bad field."""

from __future__ import annotations

import copy
import json
import math
import os
from pathlib import Path

import numpy as np
import pytest

from softgrip_calib.profile import (PROFILE_VERSION, CalibrationProfile, FingerEntry, FitEntry, ProfileError, load_profile,
                           save_profile, to_gripper)
from softgrip_jax import Gripper, SoftgripError
from softgrip_vision.segmentation import SegmentationSettings
from synthetic.render import d405_intrinsics


def make_profile() -> CalibrationProfile:
    """A profile with every optional field filled in."""
    return CalibrationProfile(
        fingers={"left": FingerEntry(52.1, 0.55, 3.9, 10, (0.25, -0.5), stiffness_ratio=2.0, base_compliance=0.25),
                 "right": FingerEntry(51.8, 0.45, 4.1, 10, (-0.25, -0.5))},
        base_separation=64.2,
        segmentation=SegmentationSettings(roi=(10, 20, 600, 400)).to_dict(),
        camera={"name": "123456789012", "intrinsics": d405_intrinsics().to_dict()},
        fit=FitEntry(method="least-squares", frames=["open_0 + closed_0", "open_1 + closed_1"], residual_rms_mm=0.4,
                     frame_residual_rms_mm=[0.3, 0.5],
                     standard_errors={"left.theta_entire": 0.002, "left.base_offset": [0.1, 0.12],
                                      "left.stiffness_ratio": 0.05},
                     skipped=[{"frame": "open_2 + closed_2", "reason": "no gripper found"}],
                     estimate_method="mechanics", free_closure="open_1 + closed_1",
                     frame_start_residual_rms_mm=[0.6, 0.45], frame_mid_error_mm=[0.2, 0.3],
                     frame_tip_error_mm=[0.5, 0.6]),
    )


def test_round_trip(tmp_path: Path) -> None:
    profile = make_profile()
    path = save_profile(profile, tmp_path / "profile.json")
    loaded = load_profile(path)
    assert loaded == profile
    assert json.loads(path.read_text())["fingers"]["left"]["theta_entire"] == 0.55
    assert os.listdir(tmp_path) == ["profile.json"]  # no temporary file left behind


def test_finger_entries_use_the_finger_model_names(tmp_path: Path) -> None:
    data = json.loads(save_profile(make_profile(), tmp_path / "p.json").read_text())
    assert set(data) == {"version", "gripper", "fingers", "segmentation", "camera", "fit"}
    assert data["version"] == PROFILE_VERSION
    assert set(data["fingers"]["left"]) == {"length", "theta_entire", "half_thickness", "n_links", "base_offset",
                                            "stiffness_ratio", "base_compliance"}
    assert data["gripper"] == {"base_separation": 64.2}


def test_stiffness_fields_and_the_estimate_method_round_trip(tmp_path: Path) -> None:
    path = save_profile(make_profile(), tmp_path / "p.json")
    data = json.loads(path.read_text())
    assert data["fingers"]["left"]["stiffness_ratio"] == 2.0 and data["fingers"]["left"]["base_compliance"] == 0.25
    assert data["fingers"]["right"]["stiffness_ratio"] == 1.0 and data["fingers"]["right"]["base_compliance"] == 0.0
    assert data["fit"]["estimate_method"] == "mechanics"
    loaded = load_profile(path)
    assert (loaded.fingers["left"].stiffness_ratio, loaded.fingers["left"].base_compliance) == (2.0, 0.25)
    assert loaded.fit.estimate_method == "mechanics"
    assert loaded.fit.standard_errors["left.stiffness_ratio"] == 0.05
    # ... and the core's finger model gets them.
    left = to_gripper(loaded).left
    assert float(left.stiffness_ratio) == 2.0 and float(left.base_compliance) == pytest.approx(0.25)


def test_a_profile_without_the_stiffness_fields_loads_with_defaults(tmp_path: Path) -> None:
    """Profiles written before the mechanics estimate (the sample profile without those fields)
    still load: a uniform finger with a clamped base, and no recorded estimate method."""
    data = json.loads((Path(__file__).resolve().parents[2] / "data" / "sample_profile.json").read_text())
    for side in ("left", "right"):
        for name in ("stiffness_ratio", "base_compliance"):
            data["fingers"][side].pop(name, None)
    data["fit"].pop("estimate_method", None)
    sample = tmp_path / "old_profile.json"
    sample.write_text(json.dumps(data))
    profile = load_profile(sample)
    for side in ("left", "right"):
        assert profile.fingers[side].stiffness_ratio == 1.0 and profile.fingers[side].base_compliance == 0.0
    assert profile.fit.estimate_method is None
    assert "estimate_method" not in profile.to_dict()["fit"]  # not written when not known
    gripper = to_gripper(profile)
    assert float(gripper.right.stiffness_ratio) == 1.0 and float(gripper.right.base_compliance) == 0.0


def test_optional_fields_take_their_defaults(tmp_path: Path) -> None:
    data = make_profile().to_dict()
    for side in ("left", "right"):
        del data["fingers"][side]["base_offset"]
    for side in ("left", "right"):
        del data["fingers"][side]["stiffness_ratio"]
        del data["fingers"][side]["base_compliance"]
    for key in ("residual_rms_mm", "frame_residual_rms_mm", "standard_errors", "skipped", "estimate_method",
                "free_closure", "frame_start_residual_rms_mm", "frame_mid_error_mm", "frame_tip_error_mm"):
        del data["fit"][key]
    data["segmentation"] = {}
    data["camera"]["intrinsics"] = None
    profile = CalibrationProfile.from_dict(data)
    assert profile.fingers["left"].base_offset == (0.0, 0.0)
    assert (profile.fingers["left"].stiffness_ratio, profile.fingers["left"].base_compliance) == (1.0, 0.0)
    assert profile.fit.skipped == [] and profile.fit.residual_rms_mm is None and profile.fit.estimate_method is None
    assert profile.fit.free_closure is None and profile.fit.frame_start_residual_rms_mm == []
    assert profile.fit.frame_mid_error_mm == [] and profile.fit.frame_tip_error_mm == []
    # Not written when not recorded: a profile without them reads and writes as before.
    assert not {"free_closure", "frame_start_residual_rms_mm", "frame_mid_error_mm",
                "frame_tip_error_mm"} & set(profile.to_dict()["fit"])
    assert profile.segmentation_settings() == SegmentationSettings()


def test_to_gripper_and_corrected_bases() -> None:
    profile = make_profile()
    gripper = to_gripper(profile)
    assert isinstance(gripper, Gripper)
    assert float(gripper.left.theta_entire) == pytest.approx(0.55)
    assert float(gripper.right.length) == pytest.approx(51.8)
    assert gripper.right.n_links == 10
    assert float(gripper.base_separation) == pytest.approx(64.2)
    bases = profile.corrected_bases([[-32.0, -40.0], [32.0, -40.0]])
    np.testing.assert_allclose(bases, [[-31.75, -40.5], [31.75, -40.5]])


def _set(data: dict, keys: tuple, value) -> None:
    for key in keys[:-1]:
        data = data[key]
    data[keys[-1]] = value


def _delete(data: dict, keys: tuple) -> None:
    for key in keys[:-1]:
        data = data[key]
    del data[keys[-1]]


REQUIRED = [
    "version", "gripper", "gripper.base_separation", "fingers", "fingers.left", "fingers.right",
    *(f"fingers.{side}.{name}" for side in ("left", "right")
      for name in ("length", "theta_entire", "half_thickness", "n_links")),
    "segmentation", "camera", "camera.name", "camera.intrinsics", "fit", "fit.method", "fit.frames",
]


@pytest.mark.parametrize("path", REQUIRED)
def test_a_missing_field_is_named(tmp_path: Path, path: str) -> None:
    data = make_profile().to_dict()
    _delete(data, tuple(path.split(".")))
    file = tmp_path / "p.json"
    file.write_text(json.dumps(data))
    with pytest.raises(ProfileError) as info:
        load_profile(file)
    assert str(info.value) == f"{file}: {path}: expected a value (the field is missing)"


BAD_VALUES = [
    # (keys to set, value, the field as the message names it, what the message says)
    (("version",), "1", "version", 'expected 1, got "1"'),
    (("version",), 2, "version", "newer softgrip-jax"),
    (("gripper",), [64.0], "gripper", "expected a JSON object"),
    (("gripper", "base_separation"), "abc", "gripper.base_separation", 'a distance in mm > 0 and <= 1000, got "abc"'),
    (("gripper", "base_separation"), 0, "gripper.base_separation", "a distance in mm > 0 and <= 1000, got 0"),
    (("gripper", "base_separation"), True, "gripper.base_separation", "a distance in mm > 0 and <= 1000, got true"),
    (("fingers", "left", "theta_entire"), "abc", "fingers.left.theta_entire",
     'expected a number in [0, pi/2), got "abc"'),
    (("fingers", "left", "theta_entire"), 1.6, "fingers.left.theta_entire", "a number in [0, pi/2), got 1.6"),
    (("fingers", "right", "theta_entire"), -0.1, "fingers.right.theta_entire", "a number in [0, pi/2)"),
    (("fingers", "left", "length"), 0.0, "fingers.left.length", "a length in mm > 0"),
    (("fingers", "right", "length"), None, "fingers.right.length", "a length in mm > 0 and <= 1000, got null"),
    (("fingers", "left", "half_thickness"), -1.0, "fingers.left.half_thickness", "a half-thickness in mm >= 0"),
    (("fingers", "left", "n_links"), 10.5, "fingers.left.n_links", "an integer >= 1 and <= 100, got 10.5"),
    (("fingers", "left", "n_links"), 0, "fingers.left.n_links", "an integer >= 1"),
    (("fingers", "left", "n_links"), 101, "fingers.left.n_links", "an integer >= 1 and <= 100, got 101"),
    (("fingers", "left", "stiffness_ratio"), 1e31, "fingers.left.stiffness_ratio", "at most 1e+30 in magnitude"),
    (("fingers", "left", "length"), 1e29, "fingers.left.length", "a length in mm > 0 and <= 1000, got 1e+29"),
    (("fingers", "right", "half_thickness"), 300.0, "fingers.right.half_thickness", "<= 250, got 300"),
    (("gripper", "base_separation"), 1200.0, "gripper.base_separation", "<= 1000, got 1200"),
    (("fingers", "right", "n_links"), True, "fingers.right.n_links", "an integer >= 1"),
    (("fingers", "left", "base_offset"), [1.0], "fingers.left.base_offset", "two numbers"),
    (("fingers", "left", "base_offset"), "x", "fingers.left.base_offset", "a JSON array"),
    (("fingers", "left", "base_offset", 1), "a", "fingers.left.base_offset[1]", "a finite number of mm"),
    (("fingers", "left", "stiffness_ratio"), 0.0, "fingers.left.stiffness_ratio",
     "a base-to-tip stiffness ratio > 0 (1: uniform), got 0.0"),
    (("fingers", "right", "stiffness_ratio"), -2.0, "fingers.right.stiffness_ratio",
     "a base-to-tip stiffness ratio > 0"),
    (("fingers", "left", "stiffness_ratio"), "2", "fingers.left.stiffness_ratio", 'got "2"'),
    (("fingers", "left", "base_compliance"), -0.1, "fingers.left.base_compliance",
     "a base compliance >= 0 (0: clamped base), got -0.1"),
    (("fingers", "right", "base_compliance"), None, "fingers.right.base_compliance", "got null"),
    (("fingers", "left", "lenght"), 52.0, "fingers.left.lenght", "unknown field"),
    (("fingers", "middle"), {}, "fingers.middle", "unknown field"),
    (("segmentation",), "x", "segmentation", "a JSON object of segmentation settings"),
    (("segmentation", "hole_fill_px"), 4, "segmentation", "hole_fill_px must be 0 (off) or an odd number"),
    (("segmentation", "colour"), 1, "segmentation", "unknown segmentation setting(s) colour"),
    (("camera", "name"), 3, "camera.name", "a non-empty string, got 3"),
    (("camera", "name"), "", "camera.name", "a non-empty string"),
    (("camera", "intrinsics"), {"width": 640}, "camera.intrinsics", "fx"),
    (("camera", "lens"), "x", "camera.lens", "unknown field"),
    (("fit", "method"), "magic", "fit.method", 'one of "one-frame", "least-squares", got "magic"'),
    (("fit", "estimate_method"), "spring", "fit.estimate_method", 'one of "geometric", "mechanics", got "spring"'),
    (("fit", "frames"), "x", "fit.frames", "a JSON array"),
    (("fit", "frames", 0), 3, "fit.frames[0]", "a non-empty string"),
    (("fit", "residual_rms_mm"), -1.0, "fit.residual_rms_mm", "a number >= 0"),
    (("fit", "frame_residual_rms_mm"), [0.1, 0.2, 0.3], "fit.frame_residual_rms_mm", "one value per frame"),
    (("fit", "frame_residual_rms_mm", 0), "x", "fit.frame_residual_rms_mm[0]", "a number >= 0"),
    (("fit", "frame_start_residual_rms_mm"), [0.1], "fit.frame_start_residual_rms_mm", "one value per frame"),
    (("fit", "frame_mid_error_mm", 1), -0.5, "fit.frame_mid_error_mm[1]", "a number >= 0"),
    (("fit", "frame_tip_error_mm"), {}, "fit.frame_tip_error_mm", "a JSON array"),
    (("fit", "free_closure"), "open_9 + closed_9", "fit.free_closure", "the label of one of fit.frames"),
    (("fit", "free_closure"), 1, "fit.free_closure", "a non-empty string"),
    (("fit", "standard_errors"), [], "fit.standard_errors", "a JSON object"),
    (("fit", "standard_errors", "left.theta_entire"), -0.1, "fit.standard_errors.left.theta_entire",
     "a number >= 0"),
    (("fit", "standard_errors", "left.base_offset", 1), "x", "fit.standard_errors.left.base_offset[1]",
     "a number >= 0"),
    (("fit", "skipped", 0), {"frame": "x"}, "fit.skipped[0].reason", "the field is missing"),
    (("fit", "skipped", 0, "reason"), "", "fit.skipped[0].reason", "a non-empty string"),
    (("fit", "comment"), "x", "fit.comment", "unknown field"),
]


@pytest.mark.parametrize("keys, value, field, expected", BAD_VALUES, ids=[f"{c[2]}={c[1]!r}" for c in BAD_VALUES])
def test_a_bad_field_is_named(tmp_path: Path, keys: tuple, value, field: str, expected: str) -> None:
    data = make_profile().to_dict()
    _set(data, keys, value)
    file = tmp_path / "p.json"
    file.write_text(json.dumps(data))
    with pytest.raises(ProfileError) as info:
        load_profile(file)
    message = str(info.value)
    assert message.startswith(f"{file}: {field}: "), message
    assert expected in message, message
    assert isinstance(info.value, SoftgripError)


def test_non_finite_numbers_are_refused(tmp_path: Path) -> None:
    text = json.dumps(make_profile().to_dict()).replace('"theta_entire": 0.55', '"theta_entire": NaN')
    file = tmp_path / "p.json"
    file.write_text(text)
    with pytest.raises(ProfileError, match=r"fingers\.left\.theta_entire: expected a number in \[0, pi/2\), got NaN"):
        load_profile(file)


def test_non_finite_stiffness_is_refused(tmp_path: Path) -> None:
    text = json.dumps(make_profile().to_dict()).replace('"stiffness_ratio": 2.0', '"stiffness_ratio": Infinity')
    file = tmp_path / "p.json"
    file.write_text(text)
    with pytest.raises(ProfileError, match=r"fingers\.left\.stiffness_ratio: expected a base-to-tip stiffness ratio "
                                           r"> 0 \(1: uniform\), got Infinity"):
        load_profile(file)


def test_unreadable_files(tmp_path: Path) -> None:
    with pytest.raises(ProfileError, match="no such calibration profile"):
        load_profile(tmp_path / "missing.json")
    broken = tmp_path / "broken.json"
    broken.write_text('{"version": 1,')
    with pytest.raises(ProfileError, match=f"{broken}: not valid JSON"):
        load_profile(broken)
    listing = tmp_path / "list.json"
    listing.write_text("[]")
    with pytest.raises(ProfileError, match="expected a JSON object"):
        load_profile(listing)


def test_saving_an_invalid_profile_names_the_field_and_keeps_the_old_file(tmp_path: Path) -> None:
    path = save_profile(make_profile(), tmp_path / "p.json")
    before = path.read_bytes()
    bad = copy.deepcopy(make_profile())
    bad.fingers["left"] = FingerEntry(52.0, math.pi / 2, 4.0, 10)
    with pytest.raises(ProfileError, match=r"fingers\.left\.theta_entire"):
        save_profile(bad, path)
    assert path.read_bytes() == before


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path: Path, monkeypatch) -> None:
    path = save_profile(make_profile(), tmp_path / "p.json")
    before = path.read_bytes()

    def fail(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", fail)
    changed = make_profile()
    changed.fingers["left"] = FingerEntry(50.0, 0.5, 4.0, 10)
    with pytest.raises(ProfileError, match="No space left on device"):
        save_profile(changed, path)
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["p.json"]


def test_a_saved_profile_is_created_like_any_new_file(tmp_path: Path) -> None:
    previous = os.umask(0o022)
    try:
        path = save_profile(make_profile(), tmp_path / "p.json")
    finally:
        os.umask(previous)
    assert path.stat().st_mode & 0o777 == 0o644


def test_saving_into_a_missing_folder(tmp_path: Path) -> None:
    with pytest.raises(ProfileError, match="cannot write the profile there"):
        save_profile(make_profile(), tmp_path / "nowhere" / "p.json")


# --- the vision section: how fingers are measured, and what calibration detected ----------------


def test_the_vision_section_round_trips_and_is_optional(tmp_path: Path) -> None:
    import dataclasses

    detected = {"base_end": {"left": "flat", "right": "flat"}, "body_in_view": True,
                "plane": {"depth_mm": 121.5, "normal": [0.1, 0.0, 0.995], "tilt_deg": 5.7}}
    profile = dataclasses.replace(make_profile(), vision={"base_end": "flat", "finger_relief_mm": 3.5,
                                                           "detected": detected})
    loaded = load_profile(save_profile(profile, tmp_path / "p.json"))
    assert loaded.vision == profile.vision
    settings = loaded.measure_settings()
    assert settings.base_end == "flat" and settings.finger_relief_mm == 3.5 and settings.rounded_base is False
    # without the section: measured automatically
    plain = load_profile(save_profile(make_profile(), tmp_path / "plain.json"))
    assert plain.measure_settings().base_end == "auto" and plain.measure_settings().finger_relief_mm is None


@pytest.mark.parametrize("vision, field", [
    ({"base_end": "square"}, "vision.base_end"),
    ({"finger_relief_mm": -1.0}, "vision.finger_relief_mm"),
    ({"finger_relief_mm": "deep"}, "vision.finger_relief_mm"),
    ({"finger_relief": 1.0}, "finger_relief"),
    ({"detected": [1, 2]}, "vision.detected"),
])
def test_a_bad_vision_setting_is_named(tmp_path: Path, vision: dict, field: str) -> None:
    data = make_profile().to_dict()
    data["vision"] = vision
    path = tmp_path / "p.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ProfileError, match=field.replace(".", r"\.")):
        load_profile(path)


def test_the_planes_of_both_frames_round_trip_and_older_profiles_load_without_them(tmp_path: Path) -> None:
    import dataclasses

    depths = {"open": 120.02, "closed": 119.97, "used": "open"}
    profile = dataclasses.replace(make_profile(), vision={"base_end": "auto", "finger_relief_mm": "auto",
                                                           "detected": {}, "plane_depth_mm": depths})
    loaded = load_profile(save_profile(profile, tmp_path / "p.json"))
    assert loaded.vision["plane_depth_mm"] == depths
    assert loaded.measure_settings().finger_relief_mm is None  # a record, not a setting
    # the sample profile was written before the planes were recorded
    sample = load_profile(Path(__file__).resolve().parents[2] / "data" / "sample_profile.json")
    assert "plane_depth_mm" not in sample.vision


@pytest.mark.parametrize("depths, field", [
    ({"open": -1.0, "closed": 120.0, "used": "open"}, "vision.plane_depth_mm.open"),
    ({"open": 120.0, "closed": float("nan"), "used": "open"}, "vision.plane_depth_mm.closed"),
    ({"open": 120.0, "used": "open"}, "vision.plane_depth_mm.closed"),
    ({"open": 120.0, "closed": 120.0, "used": "mean"}, "vision.plane_depth_mm.used"),
    ({"open": 120.0, "closed": 120.0, "used": "open", "at": 1}, "vision.plane_depth_mm.at"),
    ([120.0, 120.0], "vision.plane_depth_mm"),
])
def test_a_bad_plane_record_is_named(tmp_path: Path, depths, field: str) -> None:
    data = make_profile().to_dict()
    data["vision"] = {"plane_depth_mm": depths}
    path = tmp_path / "p.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ProfileError, match=field.replace(".", r"\.")):
        load_profile(path)


def test_a_non_finite_number_in_the_detection_record_is_named(tmp_path: Path) -> None:
    data = json.loads((Path(__file__).resolve().parents[2] / "data" / "sample_profile.json").read_text())
    data["vision"]["detected"]["open"]["plane"]["depth_mm"] = float("nan")
    path = tmp_path / "nan.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ProfileError, match=r"vision\.detected\.open\.plane\.depth_mm: expected a finite number"):
        load_profile(path)


def test_the_profile_schema_file_is_the_models_and_an_independent_validator_agrees(tmp_path: Path) -> None:
    """softgrip_base/schemas/profile.schema.json is what softgrip_calib.profile_schema says (regenerate it with
    ``json_schema()`` after a change), and jsonschema, a validator independent of pydantic, accepts
    the sample profile and refuses what load_profile refuses."""
    jsonschema = pytest.importorskip("jsonschema")
    from softgrip_calib.profile_schema import json_schema

    root = Path(__file__).resolve().parents[2]
    on_disk = json.loads((root / "softgrip_base" / "schemas" / "profile.schema.json").read_text())
    assert on_disk == json_schema()
    validator = jsonschema.Draft202012Validator(on_disk)
    sample = json.loads((root / "data" / "sample_profile.json").read_text())
    validator.validate(sample)
    validator.validate(make_profile().to_dict())
    for keys, value in [(("fingers", "left", "theta_entire"), 1.6), (("fingers", "left", "lenght"), 52.0),
                        (("gripper", "base_separation"), 0), (("fit", "method"), "magic"),
                        (("fingers", "left", "n_links"), 101), (("fit", "standard_errors", "left.base_offset", 1), "x")]:
        data = make_profile().to_dict()
        _set(data, keys, value)
        assert not validator.is_valid(data), keys
        path = tmp_path / "p.json"
        path.write_text(json.dumps(data))
        with pytest.raises(ProfileError):
            load_profile(path)
