"""softgrip_vision.stream.score_frames: the plain per-frame loop's results, in order, with the scoring
overlapped; a bad frame or bad poses raise after the results before them; stopping early leaves no
thread behind."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from softgrip_calib.profile import load_profile
from softgrip_jax import Geometric, SoftgripError
from softgrip_vision.scene import FrameSceneError, frame_scene
from softgrip_vision.stream import score_frames

DATA = Path(__file__).resolve().parents[2] / "data"
PROFILE = load_profile(DATA / "sample_profile.json")
FRAMES = [DATA / "circle_open", DATA / "square_open", DATA / "star_a_open"]


def around(scene):
    """Poses around the frame's own: the frame's pose, 4 mm to either side, 3 mm closer."""
    return scene.pose + np.array([[0.0, 0.0, 0.0], [-4.0, 0.0, 0.0], [4.0, 0.0, 0.0], [0.0, 3.0, 0.0]])


def _workers() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("softgrip-score")]


def test_the_results_are_the_plain_loops_in_order():
    streamed = list(score_frames(FRAMES, PROFILE, around, estimator=Geometric()))
    assert [s.scene.name for s in streamed] == [f.name for f in FRAMES]
    for folder, (scene, result) in zip(FRAMES, streamed):
        plain = frame_scene(folder, PROFILE)
        expected = plain.score(around(plain), estimator=Geometric())
        np.testing.assert_array_equal(scene.pose, plain.pose)
        np.testing.assert_array_equal(result.score, expected.score)
        np.testing.assert_array_equal(result.valid, expected.valid)
    assert not _workers()


def test_fixed_poses_are_scored_for_every_frame():
    poses = np.array([[0.0, -45.0, 0.0], [-4.0, -45.0, 0.0]])
    results = [r for _, r in score_frames(FRAMES[:2], PROFILE, poses, estimator=Geometric())]
    assert [r.score.shape for r in results] == [(2,), (2,)]
    # The disc and the square differ in front of the same gripper pose.
    assert not np.array_equal(results[0].score, results[1].score)


def test_a_bad_frame_raises_after_the_results_before_it():
    frames = [DATA / "circle_open", DATA / "circle_closed", DATA / "square_open"]
    seen = []
    with pytest.raises(FrameSceneError, match="circle_closed.*closed gripper"):
        for scene, result in score_frames(frames, PROFILE, around, estimator=Geometric()):
            seen.append((scene.name, result.score.shape))
    assert seen == [("circle_open", (4,))]  # the frame before the bad one, scored; none after it
    assert not _workers()


def test_bad_poses_raise_where_their_result_would_come():
    stream = score_frames(FRAMES[:1], PROFILE, lambda scene: np.zeros((2, 4)), estimator=Geometric())
    with pytest.raises(SoftgripError, match="Scene.score"):
        next(stream)
    assert not _workers()


def test_stopping_early_leaves_no_worker_behind():
    stream = score_frames(FRAMES * 3, PROFILE, around, estimator=Geometric())
    first = next(stream)
    assert first.scene.name == "circle_open"
    stream.close()
    assert not _workers()
