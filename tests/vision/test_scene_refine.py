"""Scene.refine: the core's refine on the scene's gripper and object, in the scene's coordinates."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from softgrip_calib.profile import load_profile
from softgrip_jax import Geometric, RefineStatus, SoftgripError, refine
from softgrip_vision.scene import frame_scene

DATA = Path(__file__).resolve().parents[2] / "data"


@pytest.fixture(scope="module")
def scene():
    return frame_scene(DATA / "circle_open", load_profile(DATA / "sample_profile.json"))


@pytest.mark.slow  # compiles the geometric refine of one pose and of a batch: about a minute
def test_scene_refine_is_the_core_refine_and_never_loses_score(scene):
    start = np.asarray(scene.pose, np.float32) + np.array([1.5, -1.0, 0.03], np.float32)
    one = scene.refine(start, estimator=Geometric(), max_steps=8)
    core = refine(scene.gripper, scene.sdf, start, estimator=Geometric(), max_steps=8)
    np.testing.assert_array_equal(one.pose, np.asarray(core.pose))
    assert isinstance(one.pose, np.ndarray) and one.pose.shape == (3,)
    assert one.score.score >= one.start_score  # never worse than its start
    steps = []
    batch = scene.refine(np.stack([start, np.asarray(scene.pose, np.float32)]), estimator=Geometric(), max_steps=8,
                         progress=lambda done, total: steps.append((done, total)))
    assert batch.pose.shape == (2, 3) and steps == [(2, 2)]
    assert np.all(batch.score.score >= batch.start_score)
    assert set(batch.status.tolist()) <= {int(s) for s in RefineStatus}


def test_scene_refine_names_a_bad_pose_or_weights(scene):
    with pytest.raises(SoftgripError, match="Scene.refine"):
        scene.refine(np.zeros((2, 2)))
    with pytest.raises(SoftgripError, match="ScoreWeights"):
        scene.refine(None, weights={"mu": 0.5})
