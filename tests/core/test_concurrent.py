"""Batches split into concurrent parts (softgrip_jax._concurrent): same results, one compilation."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softgrip_jax import FingerModel, Gripper, PolygonSDF, SDFGrid, SoftgripError, estimate_batch, score
from softgrip_jax._concurrent import CHUNK_ALIGN, MIN_PART, balanced_chunk, part_count, run_in_parts

FINGER = FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=4)
GRID = SDFGrid.sample(PolygonSDF.regular((30.0, 40.0), 8.0, 64), origin=(-40.0, -30.0), spacing=(0.5, 0.5),
                      shape=(200, 240))


def test_parts_give_the_whole_batch_results_in_order():
    # 3 parts of 257 rows, the last padded by 3: each candidate keeps its own result and place.
    n = 3 * MIN_PART + 2
    bases = np.random.default_rng(0).uniform([-20.0, -10.0], [40.0, 30.0], (n, 2)).astype(np.float32)
    whole = estimate_batch(FINGER, GRID, bases, method="geometric", workers=1)
    split = estimate_batch(FINGER, GRID, bases, method="geometric", workers=3)
    assert split.joints.shape == (n, 5, 2)
    # To float32 rounding: a part is a program of another shape, which XLA:CPU may vectorise
    # differently at a chunk's edge on some processors (1 ulp at 3 of 7,700 values on an AMD EPYC).
    np.testing.assert_allclose(split.joints, whole.joints, rtol=1e-6, atol=1e-5)
    np.testing.assert_array_equal(split.case, whole.case)
    assert len(set(np.asarray(whole.case).tolist())) >= 3  # a scene with contacts, not only case (a)


def test_part_count_rules():
    assert part_count(4, 10 * MIN_PART) == 4
    assert part_count(4, 2 * MIN_PART + 1) == 2  # never a part below MIN_PART candidates
    assert part_count(4, MIN_PART - 1) == 1 and part_count(4, 0) == 1
    assert 1 <= part_count(None, 100 * MIN_PART)
    for bad in (0, -2, 1.5, True, "2"):
        with pytest.raises(SoftgripError, match="workers must be a positive integer"):
            part_count(bad, 1000)


def test_chunks_are_equal_and_never_above_chunk_size():
    # As few chunks as chunk_size allows, all of one size: the last is not mostly padding.
    for rows in (1, 7, 2048, 2049, 2500, 50_000, 99_999):
        for chunk in (1, 100, 2048, 4096):
            size = balanced_chunk(rows, chunk)
            count = -(-rows // size)
            assert size <= chunk and count == -(-rows // chunk)
            if count == 1:
                assert size == rows
            elif size < chunk:
                assert size % CHUNK_ALIGN == 0 and count * size - rows < count * CHUNK_ALIGN
    assert balanced_chunk(2049, 2048) == 1152  # 2 chunks of 1152, not 2 of 2048
    for bad in (0, -1, True):  # (the tests check type hints too: a float would not get this far)
        with pytest.raises(SoftgripError, match="chunk_size must be a positive integer"):
            estimate_batch(FINGER, GRID, np.zeros((3, 2), np.float32), chunk_size=bad, method="geometric")


def test_traced_batches_run_as_one_part():
    # Under jit or grad the inputs are tracers: one part, and the gradient still flows.
    assert jax.jit(lambda x: part_count(4, 10 * MIN_PART, (x,)))(jnp.zeros(1)) == 1
    bases = jnp.asarray(np.random.default_rng(2).uniform([-20.0, -10.0], [10.0, 30.0], (2 * MIN_PART, 2)),
                        jnp.float32)

    def loss(theta):
        f = FingerModel(length=50.0, theta_entire=theta, half_thickness=3.0, n_links=4)
        return jnp.sum(estimate_batch(f, GRID, bases, method="geometric", workers=2).joints[:, -1, 0])

    assert np.isfinite(jax.grad(loss)(jnp.float32(0.5)))


def test_a_new_shape_compiles_once_for_all_parts():
    traces = []

    @functools.partial(jax.jit, static_argnames="chunk_size")
    def double(x, chunk_size):
        traces.append(x.shape)  # runs only while tracing
        return {"twice": 2.0 * x}

    xs = jnp.arange(4 * MIN_PART * 2, dtype=jnp.float32).reshape(-1, 2)
    out = run_in_parts(double, (), xs, (), 4, 2048)
    np.testing.assert_array_equal(out["twice"], 2.0 * xs)
    assert traces == [(MIN_PART, 2)]


@pytest.mark.slow  # compiles the score for several part shapes: about 50 s
def test_score_in_parts_matches_one_part():
    n = 2 * MIN_PART + 1
    rng = np.random.default_rng(3)
    poses = np.column_stack([rng.uniform(0.0, 60.0, n), rng.uniform(-10.0, 10.0, n),
                             rng.uniform(-0.2, 0.2, n)]).astype(np.float32)
    gripper = Gripper(FINGER, FINGER, 50.0)
    whole = score(gripper, GRID, poses, method="geometric", workers=1)
    split = score(gripper, GRID, poses, method="geometric", workers=2)
    np.testing.assert_allclose(split.score, whole.score, rtol=1e-6, atol=1e-6)  # float32 rounding, as above
    np.testing.assert_array_equal(split.valid, whole.valid)
    assert np.isfinite(np.asarray(whole.score)).sum() > 10  # some poses are valid, so scores were compared
