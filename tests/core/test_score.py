"""Scoring and refining pre-touch poses: ranking sanity, refinement, sharding."""

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softgrip_jax import CASE_NAMES, FingerModel, Gripper, PolygonSDF, RefineStatus, refine, score
from softgrip_jax import Geometric

FINGER = FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=10)
GRIPPER = Gripper(left=FINGER, right=FINGER, base_separation=56.0)
DISC = PolygonSDF.regular((0.0, 38.0), 15.0, 128)


def test_ranking_sanity():
    poses = np.array([
        [0.0, 10.0, 0.0],   # the disc between both fingers, at mid-length: both wrap it
        [0.0, 80.0, 0.0],   # the fingers close below the disc, on nothing
        [0.0, -15.0, 0.0],  # both fingertips land on the disc's upper edge
        [-5.0, 5.0, 0.0],   # off-centre: the left finger lands tip-first
    ], np.float32)
    s = score(GRIPPER, DISC, poses, estimator=Geometric())
    cases = [(CASE_NAMES[int(a)], CASE_NAMES[int(b)]) for a, b in zip(s.grasp.left.case, s.grasp.right.case)]
    assert cases[0] == ("other", "other") and cases[1] == ("none", "none")
    assert cases[2] == ("tip", "tip") and cases[3][0] == "tip"
    assert bool(np.all(s.valid))
    assert float(s.score[0]) > max(float(s.score[1]), float(s.score[2]), float(s.score[3]))
    assert float(s.score[1]) == pytest.approx(0.0, abs=0.05)  # nothing touched, nothing gained
    np.testing.assert_allclose(s.components.touch[1], 0.0)
    # Both fingers squeeze the disc from opposite sides: opposition positive.
    assert float(s.components.opposition[0]) > 0.2


def test_invalid_candidates_rank_last_and_do_not_poison_the_batch():
    poses = np.array([[0.0, 10.0, 0.0], [np.nan, 0.0, 0.0], [28.0, 20.0, 0.0], [0.0, 10.0, 0.0]], np.float32)
    s = score(GRIPPER, DISC, poses, estimator=Geometric())
    assert s.valid.tolist() == [True, False, False, True]  # a NaN pose; the left finger starts inside the disc
    assert np.isneginf(s.score[1]) and np.isneginf(s.score[2])
    assert float(s.score[0]) == float(s.score[3])


@pytest.mark.slow
def test_refine_improves_an_off_centre_pose_and_keeps_it_valid():
    start = jnp.array([-6.0, 4.0, 0.05])
    before = score(GRIPPER, DISC, start[None], estimator=Geometric())
    result = refine(GRIPPER, DISC, start, max_steps=24, estimator=Geometric())
    assert bool(before.valid[0])
    assert int(result.status) == RefineStatus.IMPROVED and result.status_name == "improved"
    assert bool(result.score.valid)
    # The score's open tier lies in [0, 0.99] (the old unbounded sum was up to ~6): a third better.
    assert float(result.score.score) > 1.3 * float(before.score[0])
    assert float(result.start_score) == pytest.approx(float(before.score[0]), abs=1e-5)
    # The reported score is the refined pose's own.
    again = score(GRIPPER, DISC, result.pose[None], estimator=Geometric())
    assert float(again.score[0]) == pytest.approx(float(result.score.score), abs=1e-4)
    # All of it, integers (cases, statuses) and flags exactly: refine carries the score through the
    # minimiser as one float vector and unpacks it.
    mine, theirs = jax.tree_util.tree_flatten(result.score), jax.tree_util.tree_flatten(again)
    assert mine[1] == theirs[1]
    for a, b in zip(mine[0], theirs[0]):
        assert a.dtype == b.dtype and a.shape == b.shape[1:]
        if jnp.issubdtype(a.dtype, jnp.floating):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b[0]), rtol=1e-4, atol=1e-3)
        else:
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b[0]))



@pytest.mark.slow
def test_refine_of_one_pose_follows_its_row_of_a_batch():
    # One pose (3,) runs without vmap, a batch (B, 3) under it: two programs of the same algorithm.
    # Their first BFGS steps agree; later the rounding of two programs can send BFGS on a
    # non-smooth score to different poses, so after that only the guarantees are compared.
    starts = jnp.array([[-6.0, 4.0, 0.05], [3.0, -2.0, -0.1]])
    for steps in (4, 24):
        batch = refine(GRIPPER, DISC, starts, max_steps=steps, estimator=Geometric())
        for i in range(2):
            one = refine(GRIPPER, DISC, starts[i], max_steps=steps, estimator=Geometric())
            assert one.pose.shape == (3,) and one.score.score.shape == ()
            assert float(one.start_score) == pytest.approx(float(batch.start_score[i]), abs=1e-5)
            if steps == 4:
                np.testing.assert_allclose(one.pose, batch.pose[i], atol=1e-4)
                assert int(one.steps) == int(batch.steps[i]) and int(one.status) == int(batch.status[i])
            assert bool(one.score.valid) and float(one.score.score) >= float(one.start_score)
            again = score(GRIPPER, DISC, one.pose[None], estimator=Geometric())  # the pose's own score
            assert float(again.score[0]) == pytest.approx(float(one.score.score), abs=1e-4)

SHARDED = textwrap.dedent("""
    import os, sys
    import jax, jax.numpy as jnp, numpy as np
    assert len(jax.devices()) == 2, jax.devices()
    from softgrip_jax import FingerModel, Geometric, Gripper, PolygonSDF, score, score_pose
    f = FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=10)
    g = Gripper(left=f, right=f, base_separation=56.0)
    disc = PolygonSDF.regular((0.0, 38.0), 15.0, 128)
    rng = np.random.default_rng(0)
    poses = rng.uniform([-20, -20, -0.2], [20, 20, 0.2], (101, 3)).astype(np.float32)
    steps = []
    sharded = score(g, disc, poses, chunk_size=16, estimator=Geometric(), progress=lambda done, total: steps.append(done))
    assert steps == [32, 64, 96, 101], steps  # rounds of one 16-pose piece per device
    single = jax.jit(jax.vmap(lambda p: score_pose(g, disc, p, estimator=Geometric())), device=jax.devices()[0])(poses)
    np.testing.assert_array_equal(np.asarray(sharded.valid), np.asarray(single.valid))
    ok = np.asarray(single.valid)
    np.testing.assert_allclose(np.asarray(sharded.score)[ok], np.asarray(single.score)[ok], atol=1e-5)
    np.testing.assert_allclose(np.asarray(sharded.grasp.left.joints), np.asarray(single.grasp.left.joints), atol=1e-4)
    print("OK", int(ok.sum()))
""")


@pytest.mark.slow
def test_sharded_equals_unsharded():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", SHARDED], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.startswith("OK")


@pytest.mark.parametrize("steps", [0, -3, True])
def test_refine_refuses_a_max_steps_that_is_not_a_whole_number_of_iterations(steps):
    # No step would leave no evaluation of the start (refine reads the start's score from its
    # first poll): refused before anything is compiled, naming the argument.
    from softgrip_jax import SoftgripError

    with pytest.raises(SoftgripError, match=r"refine: max_steps must be a whole number of search steps >= 1"):
        refine(GRIPPER, DISC, jnp.array([0.0, 0.0, 0.0]), max_steps=steps, estimator=Geometric())
