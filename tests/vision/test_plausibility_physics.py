"""Plausibility from the physics the project knows: never a confident estimate of a frame that is
upside down, in the wrong scale, or of another gripper than the profile's, and never poses in
degrees or metres ranked as if they were rad and mm (issue 32).

Each refusal is checked on frames the renderer makes with its assumptions swept (the gripper's body
in view or not, base ends, finger sections, finger lengths), and the legitimate frames (data/ and
renderer variants) are checked to pass: a false alarm is the main risk.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
from pathlib import Path

import numpy as np
import pytest

from softgrip_calib.profile import FingerEntry, ProfileError, load_profile
from softgrip_cli import main
from softgrip_cli.cmd_score import PoseInputError, check_pose_units
from synthetic.render import Scene, d405_intrinsics, render
from synthetic.scenes import gripper_centrelines
from softgrip_vision.frames import Frame, FrameError, load_frame, save_frame
from softgrip_vision.measure import measure_gripper
from softgrip_vision.scene import FrameSceneError, frame_scene
from softgrip_vision.segmentation import SegmentationError, segment

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "data"
SAMPLE_PROFILE = DATA / "sample_profile.json"
CENTER = (0.0, -45.0)
SEPARATION = 64.0
LENGTH = 52.0
HALF_THICKNESS = 4.0


def _disc(center=(0.0, -20.0), radius=15.0) -> np.ndarray:
    t = np.linspace(0.0, 2.0 * np.pi, 64, endpoint=False)
    return np.column_stack([center[0] + radius * np.cos(t), center[1] + radius * np.sin(t)])


def _render(length=LENGTH, separation=SEPARATION, **scene) -> Frame:
    """An open gripper over a disc, as data/make_samples.py draws them (its settings overridable)."""
    scene.setdefault("object_polygon", _disc())
    return render(Scene(gripper_centrelines(CENTER, separation, length, 64), half_thickness=HALF_THICKNESS,
                        object_rgb=(235, 170, 30), seed=5, **scene), d405_intrinsics())


def _profile(length=LENGTH, half_thickness=HALF_THICKNESS, separation=SEPARATION, source=None):
    """The sample profile with the given sizes (mm), named ``source`` as the CLI names it."""
    base = load_profile(SAMPLE_PROFILE)
    fingers = {side: dataclasses.replace(f, length=length, half_thickness=half_thickness)
               for side, f in base.fingers.items()}
    profile = dataclasses.replace(base, fingers=fingers, base_separation=separation)
    if source:
        object.__setattr__(profile, "source", source)
    return profile


def _flip(frame: Frame, how: str) -> Frame:
    def op(a):
        return np.ascontiguousarray(a[::-1] if how == "flipud" else a[::-1, ::-1])

    return Frame(op(frame.color), op(frame.depth), frame.intrinsics)


def _measure(frame: Frame):
    return measure_gripper(frame, segment(frame))


@pytest.fixture(scope="module")
def circle_open() -> Frame:
    return load_frame(DATA / "circle_open")


# ---------------------------------------------------------------------------------------------
# 1. Orientation: bases at the gripper's body, tips free

# Renderer set-ups whose orientation the frame shows: a body in view (it joins the bases), or a
# flat-cut base (where a finger leaves a body) with a rounded tip.
ORIENTED = [
    {"palm": True, "palm_height_mm": 20.0, "base_end": "flat", "finger_section": "flat"},
    {"palm": True, "palm_height_mm": 20.0, "base_end": "rounded", "finger_section": "round"},
    {"palm": True, "palm_height_mm": 12.0, "base_end": "flat", "finger_section": "round"},
    {"palm": False, "base_end": "flat", "finger_section": "flat"},
    {"palm": False, "base_end": "flat", "finger_section": "round"},
    {"palm": False, "base_end": "flat", "finger_section": "flat", "tilt_deg": (6.0, 0.0), "depth_blur_px": 1.1},
]


def _id(setup: dict) -> str:
    return "-".join(f"{k}={v}" for k, v in setup.items()).replace(" ", "")


@pytest.mark.parametrize("setup", ORIENTED, ids=_id)
@pytest.mark.parametrize("how", ["flipud", "rot180"])
def test_an_upside_down_frame_is_refused_naming_the_fix(setup: dict, how: str) -> None:
    frame = _render(**setup)
    upright = _measure(frame)  # the frame the right way up is measured as the renderer drew it
    assert [round(float(k.base_mm[1])) for k in upright.keypoints] == [-45, -45]
    with pytest.raises((FrameError, SegmentationError)) as info:
        _measure(_flip(frame, how))
    message = str(info.value)
    assert "looks upside down" in message and "rotate" in message and "\n" not in message


def test_an_upside_down_frame_fails_in_the_estimate_command_with_exit_2(tmp_path: Path, capsys) -> None:
    frame = save_frame(_flip(_render(base_end="flat"), "rot180"), tmp_path / "upside_down")
    profile = tmp_path / "p.json"
    profile.write_text(SAMPLE_PROFILE.read_text())
    assert main(["estimate", str(frame), "--profile", str(profile), "--json", "--method", "geometric"]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and "Traceback" not in captured.err
    (line,) = captured.err.strip().splitlines()
    assert str(frame) in line and "looks upside down" in line and "rotate" in line


# ---------------------------------------------------------------------------------------------
# 2. Scale: depth_scale, focal lengths, principal point

def _with_intrinsics(frame: Frame, **changes) -> Frame:
    return Frame(frame.color, frame.depth, dataclasses.replace(frame.intrinsics, **changes))


@pytest.mark.parametrize(("changes", "named"), [
    ({"depth_scale": 0.001}, ["10", "depth_scale", "D435", "D405"]),   # a D435's unit on a D405 frame
    ({"fx": 430.0, "fy": 800.0}, ["fx = 430", "fy = 800", "differ"]),
    ({"fx": 385.0, "fy": 440.0}, ["differ by a factor 1.14"]),
    ({"ppx": 600.0, "ppy": 450.0}, ["ppx = 600", "principal point"]),
    ({"ppy": 330.0}, ["ppy = 330", "another resolution"]),
], ids=["depth_scale_x10", "fy800_fx430", "fy_14_percent", "pp_far", "ppy_19_percent"])
def test_a_frame_in_the_wrong_scale_is_refused_naming_the_field(circle_open: Frame, changes: dict, named) -> None:
    with pytest.raises(FrameSceneError) as info:
        frame_scene(_with_intrinsics(circle_open, **changes), _profile(52.2, 3.95, 64.0))
    message = str(info.value)
    assert all(part in message for part in named), message
    assert "\n" not in message


@pytest.mark.parametrize("changes", [{"fy": 395.0}, {"fx": 370.0}, {"ppx": 350.0, "ppy": 215.0}],
                         ids=["fy_2.6_percent", "fx_4_percent", "pp_5_percent_off"])
def test_real_cameras_calibrations_pass(circle_open: Frame, changes: dict) -> None:
    """fx, fy a few percent apart and a principal point a few percent off the centre are what real
    calibrations give: measured, not refused (the sizes move by those percent, within tolerance)."""
    scene = frame_scene(_with_intrinsics(circle_open, **changes), _profile(52.2, 3.95, 64.0))
    assert np.isfinite(scene.pose).all()


# ---------------------------------------------------------------------------------------------
# 3. The profile against the frame

@functools.lru_cache(maxsize=None)
def _open_gripper(length: float) -> Frame:
    """One rendered frame per finger length, shared by the tests (never modified)."""
    return _render(length=length)


@pytest.mark.parametrize("length", [45.0, 60.0])
@pytest.mark.parametrize(("wrong", "expected"), [
    ({"length": 5.0}, "length"), ({"length": 100.0}, "length"),
    ({"length": "x1.3"}, "length"),  # another gripper: 30 % longer fingers
    ({"separation": 90.0}, "base separation"), ({"half_thickness": 8.0}, "half-thickness"),
])
def test_a_profile_of_another_gripper_is_refused_naming_both_values(length: float, wrong: dict, expected: str) -> None:
    frame = _open_gripper(length)
    sizes = {"length": length, "half_thickness": HALF_THICKNESS, "separation": SEPARATION}
    assert np.isfinite(frame_scene(frame, _profile(**sizes)).pose).all()  # its own profile passes
    value = wrong.get("length")
    sizes.update({k: (length * 1.3 if v == "x1.3" else v) for k, v in wrong.items()})
    with pytest.raises(FrameSceneError) as info:
        frame_scene(frame, _profile(**sizes, source="other_gripper.json"))
    message = str(info.value)
    profile_value = sizes["separation"] if expected == "base separation" else sizes[
        "half_thickness" if expected == "half-thickness" else "length"]
    assert expected in message and "other_gripper.json" in message and f"says {profile_value:.4g} mm" in message
    assert "another gripper" in message and "\n" not in message, (value, message)


def test_the_frame_own_lengths_skip_the_length_comparison() -> None:
    scene = frame_scene(_open_gripper(60.0), _profile(length=100.0), length_from_frame=True)
    assert [round(float(v)) for v in (scene.gripper.left.length, scene.gripper.right.length)] == [60, 60]


def test_an_absurd_profile_value_is_refused_when_loaded(tmp_path: Path) -> None:
    data = json.loads(SAMPLE_PROFILE.read_text())
    for path, value in [(("fingers", "left", "length"), 1e29), (("gripper", "base_separation"), 5e3),
                        (("fingers", "right", "half_thickness"), 400.0)]:
        bad = json.loads(json.dumps(data))
        target = bad
        for key in path[:-1]:
            target = target[key]
        target[path[-1]] = value
        file = tmp_path / "bad.json"
        file.write_text(json.dumps(bad))
        with pytest.raises(ProfileError) as info:
            load_profile(file)
        assert str(file) in str(info.value) and ".".join(path) in str(info.value) and f"{value:g}" in str(info.value)


# ---------------------------------------------------------------------------------------------
# No false alarm: the legitimate frames pass

@pytest.mark.parametrize("name", sorted(p.name for p in DATA.glob("*_open")))
def test_the_sample_frames_pass_with_the_sample_profile(name: str) -> None:
    scene = frame_scene(DATA / name, load_profile(SAMPLE_PROFILE))
    assert abs(scene.pose[1] - CENTER[1]) < 0.5


VARIANTS = [
    {}, {"finger_section": "round"}, {"base_end": "flat"}, {"palm": True, "palm_height_mm": 20.0, "base_end": "flat"},
    {"tilt_deg": (8.0, -5.0)}, {"depth_blur_px": 1.7}, {"supersample": 3}, {"light_gain": 0.8, "light_gradient": 0.3},
    {"plane_depth_mm": 160.0}, {"object_depth_offset_mm": -2.0}, {"length": 45.0}, {"separation": 56.0},
    {"n_depth_holes": 12, "depth_noise_sigma_mm": 0.6},
]


@pytest.mark.parametrize("variant", VARIANTS, ids=lambda v: _id(v) or "default")
def test_renderer_variants_pass_with_their_own_profile(variant: dict) -> None:
    variant = dict(variant)
    sizes = {"length": variant.get("length", LENGTH), "separation": variant.get("separation", SEPARATION)}
    frame = _render(**variant)
    scene = frame_scene(frame, _profile(sizes["length"], HALF_THICKNESS, sizes["separation"]))
    assert abs(scene.pose[1] - CENTER[1]) < 1.0 and all(k.tip_end != "flat" for k in scene.keypoints)


# ---------------------------------------------------------------------------------------------
# 4. Pose units for softgrip score

@pytest.fixture(scope="module")
def circle_scene():
    """data/circle_open: the object centred at (0, -20) mm, the gripper at (0, -45) mm."""
    return frame_scene(DATA / "circle_open", load_profile(SAMPLE_PROFILE))


@pytest.mark.parametrize(("poses", "named"), [
    ([[0.0, -45.0, 10.0]], ["pose 1", "10 looks like degrees", "0.1745"]),
    ([[0.0, -45.0, 0.0], [0.0, -45.0, -90.0]], ["pose 2", "-90 looks like degrees", "-1.571"]),
    ([[0.0, -0.035, 0.0]], ["pose 1", "looks like metres", "(0, -35)"]),
    ([[0.0, -45.0, 0.0], [-0.002, -0.04, 0.1]], ["pose 2", "looks like metres", "(-2, -40)"]),
])
def test_poses_in_degrees_or_metres_are_refused_with_the_fix(circle_scene, poses, named) -> None:
    with pytest.raises(PoseInputError) as info:
        check_pose_units(np.array(poses), circle_scene, "poses.csv")
    message = str(info.value)
    assert message.startswith("poses.csv, pose") and all(part in message for part in named), message


@pytest.mark.parametrize("poses", [
    [[0.0, -45.0, 0.0], [3.0, -40.0, -0.2]],     # ordinary poses around the object
    [[0.0, -45.0, math.pi], [0.0, -45.0, -3.0]],  # up to half a turn is radians
    [[0.0, 0.0, 0.0]],                            # the origin is the origin in any unit
    [[0.5, -0.5, 0.0]],                           # near the origin, but in metres it would not reach either
])
def test_poses_in_mm_and_rad_pass(circle_scene, poses) -> None:
    check_pose_units(np.array(poses), circle_scene, "poses.csv")


def test_a_pose_near_the_origin_stays_legal_when_the_object_is_there() -> None:
    """The object around the origin: a pose 0.3 mm from the origin reaches it in mm, so it is mm."""
    frame = _render(object_polygon=_disc(center=(0.0, 5.0), radius=12.0))
    scene = frame_scene(frame, _profile())
    check_pose_units(np.array([[0.0, 0.3, 0.0], [0.2, -0.4, 0.05]]), scene, "poses.csv")


def test_score_exits_2_with_one_line_for_poses_in_degrees(tmp_path: Path, capsys) -> None:
    poses = tmp_path / "poses.csv"
    poses.write_text("x_mm,y_mm,angle_rad\n0,-45,0\n0,-45,10\n")
    code = main(["score", str(DATA / "circle_open"), "--profile", str(SAMPLE_PROFILE), "--poses", str(poses),
                 "--method", "geometric"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "Traceback" not in err
    last = err.splitlines()[-1]
    assert str(poses) in last and "looks like degrees" in last and "0.1745" in last


# ---------------------------------------------------------------------------------------------
# Upside down against the calibration: fingers that look the same either way up

def _fingers(bases, tips):
    from types import SimpleNamespace

    return [SimpleNamespace(base_px=np.asarray(b, float), tip_px=np.asarray(t, float)) for b, t in zip(bases, tips)]


_CALIBRATED = {"base_px": {"left": [219.0, 94.0], "right": [424.0, 94.0]},
               "tip_px": {"left": [219.0, 262.0], "right": [424.0, 262.0]}}


@pytest.mark.parametrize("turn", ["flipud", "rot180"])
def test_a_frame_turned_against_its_calibration_is_refused(turn):
    # The calibrated gripper in a 640x480 image turned over: what the frame's (upper) ends are is
    # derived by hand from v' = 479 - v (and u' = 639 - u for the 180-degree turn).
    from softgrip_vision.plausibility import check_orientation_against_calibration

    def turned(u, v):
        return (u, 479 - v) if turn == "flipud" else (639 - u, 479 - v)

    true_bases = [turned(219, 94), turned(424, 94)]
    true_tips = [turned(219, 262), turned(424, 262)]
    # The pipeline takes the upper ends as bases: the real tips; its "tips" are the real bases.
    with pytest.raises(FrameError, match="upside down against p.json"):
        check_orientation_against_calibration(_fingers(true_tips, true_bases), _CALIBRATED, (640, 480),
                                              profile_source="p.json")


@pytest.mark.parametrize("shift", [(0, 0), (0, 60), (120, -40), (-150, 100)])
def test_an_upright_or_moved_gripper_is_not_refused(shift):
    # Upright at the calibrated place, or moved in the image (a camera not fixed to the gripper):
    # either the bases are near the calibrated ones, or the tips are nowhere near a mirrored base.
    from softgrip_vision.plausibility import check_orientation_against_calibration

    du, dv = shift
    bases = [(219 + du, 94 + dv), (424 + du, 94 + dv)]
    tips = [(219 + du, 262 + dv), (424 + du, 262 + dv)]
    check_orientation_against_calibration(_fingers(bases, tips), _CALIBRATED, (640, 480))


def test_a_profile_without_recorded_positions_is_not_checked():
    from softgrip_vision.plausibility import check_orientation_against_calibration

    fingers = _fingers([(219, 217), (424, 217)], [(219, 385), (424, 385)])
    for detected in (None, {}, {"base_px": {"left": [1, 2]}}, {"base_px": "x", "tip_px": None}):
        check_orientation_against_calibration(fingers, detected, (640, 480))


def test_a_frame_of_the_closed_gripper_is_refused_and_the_open_one_is_not():
    # data/circle_closed's fingers are bent by about the profile's full closure (0.55 rad).
    profile = load_profile(Path(__file__).resolve().parents[2] / "data" / "sample_profile.json")
    data = Path(__file__).resolve().parents[2] / "data"
    with pytest.raises(FrameSceneError, match="frame of the closed gripper"):
        frame_scene(data / "circle_closed", profile, warn=lambda message: None)
    assert frame_scene(data / "circle_open", profile, warn=lambda message: None).keypoints


def test_fingers_ten_times_too_long_are_refused_as_a_scale_mistake():
    # A 52 mm finger through a depth_scale ten times too large measures 522 mm.
    from softgrip_vision.frames import Intrinsics
    from softgrip_vision.plausibility import check_gripper_size

    intrinsics = Intrinsics(640, 480, 385.0, 385.0, 320.0, 240.0, 0.001)
    check_gripper_size((52.2, 52.1), 64.0, intrinsics)
    with pytest.raises(FrameError, match="left finger measures 522 mm"):
        check_gripper_size((522.0, 521.0), 640.0, intrinsics)
