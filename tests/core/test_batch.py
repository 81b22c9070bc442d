"""Batches: one compilation per shape, bad candidates isolated, 100k candidates in one call."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softgrip_jax import (CASE_NAMES, FingerModel, Gripper, PolygonSDF, SDFGrid, Status, estimate,
                          estimate_batch, estimate_grasp_batch)
from softgrip_jax._batch import _estimate_batch
from softgrip_jax import Geometric, Mechanics

#: The paper's estimate: these tests check its batching (the mechanics one has its own tests).
geometric = functools.partial(estimate, estimator=Geometric())

FINGER = FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=10)
CIRCLE = PolygonSDF.regular((30.0, 40.0), 8.0, 128)
GRID = SDFGrid.sample(CIRCLE, origin=(-40.0, -30.0), spacing=(0.5, 0.5), shape=(200, 240))


def bases(n, seed, x_max=40.0):
    rng = np.random.default_rng(seed)
    return rng.uniform([-20.0, -10.0], [x_max, 30.0], (n, 2)).astype(np.float32)


def test_batch_compiles_once_per_shape():
    before = _estimate_batch._cache_size()
    first = estimate_batch(FINGER, GRID, bases(64, 0), chunk_size=16, estimator=Geometric())
    second = estimate_batch(FINGER, GRID, bases(64, 1), chunk_size=16, estimator=Geometric())
    assert _estimate_batch._cache_size() == before + 1
    assert not np.allclose(first.joints, second.joints)  # the second call really used new inputs
    assert set(np.unique(first.case)) > {0}  # the scene produces contacts, not just case (a)


def test_bad_candidates_are_flagged_and_isolated():
    good = bases(8, 2, x_max=10.0)  # left of the circle: no base starts in collision
    batch = good.copy()
    batch[2] = [np.nan, 0.0]  # NaN
    batch[5] = [500.0, 0.0]  # far outside the SDF grid (outside the image)
    out = estimate_batch(FINGER, GRID, batch, estimator=Geometric())
    clean = estimate_batch(FINGER, GRID, good, estimator=Geometric())
    assert out.valid.tolist() == [True, True, False, True, True, False, True, True]
    assert int(out.status[2]) == Status.NON_FINITE_INPUT and int(out.status[5]) == Status.BASE_OUTSIDE_SDF
    assert np.all(np.isnan(out.joints[2])) and np.all(np.isnan(out.joints[5]))
    keep = np.array([0, 1, 3, 4, 6, 7])
    np.testing.assert_array_equal(out.joints[keep], clean.joints[keep])
    np.testing.assert_array_equal(out.case[keep], clean.case[keep])


def test_bad_candidates_do_not_poison_gradients():
    batch = jnp.asarray(bases(6, 3)).at[1].set(jnp.nan).at[4].set(jnp.array([900.0, 900.0]))

    def loss(theta):
        f = FingerModel(length=50.0, theta_entire=theta, half_thickness=3.0, n_links=10)
        est = jax.vmap(geometric, in_axes=(None, None, 0))(f, GRID, batch)
        return jnp.sum(jnp.where(est.valid[:, None, None], est.joints, 0.0))

    assert np.isfinite(jax.jit(jax.grad(loss))(jnp.float32(0.5)))


def test_batch_refines_only_touching_fingers_with_the_same_results():
    # The batch refines the contact (root, second contact) only where the bracket holds a first
    # contact; every field must still equal the one-finger estimate's, case by case.
    f = FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=4)
    many = bases(300, 5)
    one = jax.jit(jax.vmap(geometric, in_axes=(None, None, 0)))(f, GRID, many)
    batch = estimate_batch(f, GRID, many, chunk_size=128, estimator=Geometric(), workers=1)
    np.testing.assert_array_equal(batch.case, one.case)
    np.testing.assert_array_equal(batch.status, one.status)
    assert len(set(np.asarray(one.case[one.valid]).tolist())) >= 3 and not bool(jnp.all(one.valid))
    for name in ("s1", "p_g1", "p_o1", "n_g1", "theta_o1", "theta_o1o2"):
        np.testing.assert_allclose(getattr(batch.contact, name), getattr(one.contact, name), atol=1e-4, err_msg=name)
    np.testing.assert_allclose(batch.joints, one.joints, atol=1e-4)


@pytest.mark.parametrize("estimator", [pytest.param(Geometric(), id="geometric"),
                                       pytest.param(Mechanics(), id="mechanics", marks=pytest.mark.slow)])
def test_a_vmapped_estimate_holds_the_grid_once_not_once_per_finger(estimator):
    # A lax.cond whose predicate is batched becomes a select over copies of all its operands,
    # the grid among them: the program's scratch memory then grows by a grid per finger. Two grids
    # of 1x and 4x the cells, 64 fingers: the scratch memory may grow by a few copies of the larger
    # grid's extra cells (padding, per-cell coefficients), not by 64.
    b = 64
    many = jnp.asarray(bases(b, 5))
    fine = SDFGrid.sample(CIRCLE, origin=(-40.0, -30.0), spacing=(0.25, 0.25), shape=(400, 480))
    one = functools.partial(estimate, estimator=estimator)
    program = jax.jit(jax.vmap(one, in_axes=(None, None, 0)))

    def scratch(grid):
        analysis = program.lower(FINGER, grid, many).compile().memory_analysis()
        return analysis.temp_size_in_bytes

    grown = scratch(fine) - scratch(GRID)
    extra_grid_bytes = fine.values.nbytes - GRID.values.nbytes
    assert grown < 8 * extra_grid_bytes, (grown, extra_grid_bytes)


@pytest.mark.slow
def test_vmap_over_100k_bases_matches_chunked_batch():
    many = bases(100_000, 4)
    vmapped = jax.jit(jax.vmap(geometric, in_axes=(None, None, 0)))(FINGER, GRID, many)
    assert vmapped.joints.shape == (100_000, 11, 2)
    # Invalid exactly where the open (straight) finger already overlaps the circle (+ r).
    foot_y = np.clip(40.0 - many[:, 1], 0.0, 50.0)
    gap = np.hypot(30.0 - many[:, 0], 40.0 - many[:, 1] - foot_y) - 8.0 - 3.0
    clear = np.abs(gap) > 0.1  # away from the polygon-vs-circle rounding band
    np.testing.assert_array_equal(np.asarray(vmapped.valid)[clear], gap[clear] > 0)
    np.testing.assert_array_equal(
        np.asarray(vmapped.status)[clear], np.where(gap[clear] > 0, Status.OK, Status.INITIAL_OVERLAP))
    assert np.all(np.isfinite(vmapped.joints))
    chunked = estimate_batch(FINGER, GRID, many[:1000], chunk_size=256, estimator=Geometric())
    np.testing.assert_allclose(vmapped.joints[:1000], chunked.joints, atol=1e-4)
    counts = np.bincount(np.asarray(vmapped.case), minlength=4)
    assert all(c > 0 for c in counts), dict(zip(CASE_NAMES, counts))  # every case occurs


def test_grasp_batch_is_mirror_symmetric():
    f = FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=10)
    gripper = Gripper(left=f, right=f, base_separation=50.0)
    sdf = PolygonSDF.regular((0.0, 35.0), 9.0, 128)  # symmetric about x = 0
    poses = np.array([[0.0, 0.0, 0.0], [0.0, 5.0, 0.0]], np.float32)
    est = estimate_grasp_batch(gripper, sdf, poses, estimator=Geometric())
    mirrored = np.asarray(est.right.joints) * np.array([-1.0, 1.0])
    np.testing.assert_allclose(est.left.joints, mirrored, atol=1e-4)
    np.testing.assert_array_equal(est.left.case, est.right.case)
    assert bool(jnp.all(est.valid))


def test_rotated_gripper_is_the_rotated_scene():
    f = FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=10)
    gripper = Gripper(left=f, right=f, base_separation=50.0)
    angle = 0.3
    # Row vectors: a point q in the upright gripper's frame sits at q @ rot in the turned one,
    # whose axes are (cos a, -sin a) across and (sin a, cos a) down.
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    verts = np.asarray(PolygonSDF.regular((5.0, 35.0), 9.0, 128).vertices)
    upright = estimate_grasp_batch(gripper, PolygonSDF(jnp.asarray(verts)), np.zeros((1, 3), np.float32), estimator=Geometric())
    turned = estimate_grasp_batch(gripper, PolygonSDF(jnp.asarray(verts @ rot)), np.array([[0, 0, angle]], np.float32), estimator=Geometric())
    np.testing.assert_allclose(np.asarray(turned.left.joints[0]), np.asarray(upright.left.joints[0]) @ rot, atol=1e-3)
    np.testing.assert_array_equal(turned.right.case, upright.right.case)
