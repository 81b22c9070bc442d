"""softgrip_vision.scene without compiling an estimate: frames from folders and from memory, warnings,
finger frames, conventions and bad poses (the estimate and score are in its doctest)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from softgrip_calib.profile import load_profile
from softgrip_jax import SoftgripError
from softgrip_vision.frames import Frame, load_frame
from softgrip_vision.scene import FrameSceneError, SceneWarning, frame_scene, pose_from_bases

DATA = Path(__file__).resolve().parents[2] / "data"
PROFILE = load_profile(DATA / "sample_profile.json")


@pytest.fixture(scope="module")
def scene():
    return frame_scene(DATA / "circle_open", PROFILE)


def test_a_frame_in_memory_gives_the_scene_of_its_folder(scene):
    loaded = load_frame(DATA / "circle_open")
    memory = frame_scene(Frame(np.array(loaded.color), np.array(loaded.depth), loaded.intrinsics), PROFILE)
    assert memory.path == "<memory>"
    assert memory.name == "frame in memory" and scene.name == "circle_open"  # what titles and captions show
    np.testing.assert_array_equal(memory.pose, scene.pose)
    np.testing.assert_array_equal(np.asarray(memory.sdf.values), np.asarray(scene.sdf.values))


def test_finger_frames_sit_w_apart_about_the_pose_near_the_measured_bases(scene):
    frames = scene.finger_frames
    bases = np.array([frames["left"]["base_mm"], frames["right"]["base_mm"]])
    # The model's bases: W/2 either side of the pose's centre along the measured base line, so
    # within a fraction of a mm of the measured ones (which are not exactly W apart).
    np.testing.assert_allclose(bases, scene.bases_mm, atol=0.1)
    np.testing.assert_allclose(pose_from_bases(*bases), scene.pose, atol=1e-4)
    assert (frames["left"]["handedness"], frames["right"]["handedness"]) == (1.0, -1.0)
    assert np.hypot(*(bases[1] - bases[0])) == pytest.approx(float(scene.gripper.base_separation), abs=1e-3)


def test_conventions_state_units_and_the_planes_depth(scene):
    conventions = scene.conventions
    assert conventions["units"] == {"length": "mm", "angle": "rad", "image": "px"}
    assert conventions["plane"]["depth_mm"] == pytest.approx(scene.camera.depth_mm, abs=1e-3)
    assert "y down" in conventions["axes"]


def test_warnings_go_to_the_callback_or_are_scene_warnings():
    wide = dataclasses.replace(PROFILE, base_separation=PROFILE.base_separation + 10.0)
    notes: list[str] = []
    frame_scene(DATA / "circle_open", wide, warn=notes.append)
    assert any("apart but the profile says" in note for note in notes)
    with pytest.warns(SceneWarning, match="apart but the profile says"):
        frame_scene(DATA / "circle_open", wide)


def test_bad_frames_and_poses_are_errors_naming_them(scene, tmp_path):
    with pytest.raises(FrameSceneError, match=str(tmp_path / "missing")):
        frame_scene(tmp_path / "missing", PROFILE)
    with pytest.raises(SoftgripError, match=r"shape \(3,\) or \(B, 3\).*got shape \(2, 2\)"):
        scene.score(np.zeros((2, 2)))
    with pytest.raises(SoftgripError, match=r"weights must be a softgrip_jax.ScoreWeights.*got dict"):
        scene.score(scene.pose, weights={"mu": 0.8})


def test_an_object_too_dark_for_the_thresholds_is_warned_about_and_a_frame_without_one_is_not(scene):
    # The sample's object darkened to a tenth of its brightness: HSV value below object_min_value.
    loaded = load_frame(DATA / "circle_open")
    color = np.array(loaded.color)
    color[scene.segmentation.object] = (color[scene.segmentation.object] * 0.1).astype(np.uint8)
    notes: list[str] = []
    dark = frame_scene(Frame(color, np.array(loaded.depth), loaded.intrinsics), PROFILE, warn=notes.append)
    assert not dark.has_object
    assert [n for n in notes if "neither object- nor gripper-coloured" in n and "object_min_value" in n], notes
    notes = []
    empty = frame_scene(DATA / "calib_open", PROFILE, warn=notes.append)  # the calibration frame: no object
    assert not empty.has_object and not [n for n in notes if "no object found" in n], notes


@pytest.mark.parametrize("band_px", [1, 2, 3])
def test_mixed_edge_pixels_around_the_gripper_are_not_taken_for_a_missed_object(band_px):
    # A stereo camera's "flying pixels": a band along the gripper's outline, in front of the background
    # (the gripper's depth) and of a colour between the gripper's and the background's, neither the
    # gripper's nor the object's. The calibration frame has no object: no warning about one.
    import cv2

    loaded = load_frame(DATA / "calib_open")
    gripper = frame_scene(loaded, PROFILE).segmentation.gripper
    band = cv2.dilate(gripper.astype(np.uint8), np.ones((2 * band_px + 1,) * 2, np.uint8)).astype(bool) & ~gripper
    color, depth = np.array(loaded.color), np.array(loaded.depth)
    color[band] = (0.5 * color[band] + 40.0).astype(np.uint8)  # halfway to a dark grey: value < 0.55
    depth[band] = np.median(loaded.depth[gripper])
    notes: list[str] = []
    scene = frame_scene(Frame(color, depth, loaded.intrinsics), PROFILE, warn=notes.append)
    assert not scene.has_object and not [n for n in notes if "no object found" in n], notes
