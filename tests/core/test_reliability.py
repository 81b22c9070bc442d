"""Nothing silent in the core: a non-finite SDF, a far-away coordinate or an out-of-range parameter
is a status, never valid=True; a bad row never fails the batch's gradient; n_links is bounded."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from softgrip_jax import FingerModel, Gripper, PolygonSDF, SDFGrid, SoftgripError, Status, estimate, score
from softgrip_jax import Geometric, Mechanics

N = 4
DISC = PolygonSDF.regular((0.0, 38.0), 15.0, 16)
GRID = SDFGrid.sample(DISC, origin=(-60.0, -20.0), spacing=(2.0, 2.0), shape=(60, 60))
FINGER = FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=N)
GRIPPER = Gripper(left=FINGER, right=FINGER, base_separation=56.0)
POSES = jnp.array([[0.0, 0.0, 0.0], [3.0, 2.0, 0.1], [1e30, 0.0, 0.0], [0.0, -1e30, 0.0]])

_score = jax.jit(lambda sdf, poses: score(GRIPPER, sdf, poses, estimator=Geometric()))
_estimate_thetas = jax.jit(jax.vmap(lambda t: estimate(FingerModel(52.0, t, 4.0, N), DISC, jnp.array([-20.0, 0.0]),
                                                      estimator=Geometric())))


def _assert_nothing_valid_is_non_finite(result) -> None:
    valid = np.asarray(result.valid)
    assert np.isfinite(np.asarray(result.score)[valid]).all()
    for side in ("left", "right"):
        joints = np.asarray(getattr(result.grasp, side).joints)
        assert np.isfinite(joints[valid]).all()
    assert (np.asarray(result.status)[~valid] != Status.OK).all() | np.asarray(result.penetrating)[~valid].all()


def test_sdf_grid_with_nan_cells_gives_a_status_not_a_valid_nan_score() -> None:
    values = np.asarray(GRID.values).copy()
    values[25:30, 25:30] = np.nan
    poisoned = SDFGrid(values=jnp.asarray(values), origin=GRID.origin, spacing=GRID.spacing)
    clean, bad = _score(GRID, POSES), _score(poisoned, POSES)
    assert bool(clean.valid[0])
    assert not np.asarray(bad.valid).any()
    assert (np.asarray(bad.status)[:2] == Status.NON_FINITE_SDF).all()
    _assert_nothing_valid_is_non_finite(bad)


@pytest.mark.parametrize("sdf", [DISC, GRID], ids=["polygon", "grid"])
def test_huge_coordinates_are_a_status_and_leave_their_neighbours_alone(sdf) -> None:
    result = _score(sdf, POSES)
    status = np.asarray(result.status)
    assert (status[2:] == Status.COORDINATE_OUT_OF_RANGE).all() and not np.asarray(result.valid)[2:].any()
    sane = _score(sdf, POSES.at[2:].set(POSES[0]))  # the same shape: the same compilation
    np.testing.assert_allclose(np.asarray(result.score)[:2], np.asarray(sane.score)[:2], rtol=1e-5, atol=1e-5)
    _assert_nothing_valid_is_non_finite(result)


@settings(max_examples=15, deadline=None)
@given(theta=st.one_of(st.floats(-10.0, -1e-3), st.floats(np.pi / 2, 10.0)))
def test_theta_out_of_range_through_vmap_is_a_status(theta: float) -> None:
    est = _estimate_thetas(jnp.array([0.5, theta, 0.3, 0.5]))
    status = np.asarray(est.status)
    assert status[1] == Status.PARAMETER_OUT_OF_RANGE and not bool(est.valid[1])
    assert np.asarray(est.valid)[[0, 2, 3]].all()


def test_n_links_is_bounded() -> None:
    with pytest.raises(SoftgripError, match="n_links must be at most"):
        FingerModel(length=52.0, theta_entire=0.5, half_thickness=4.0, n_links=10**6)
    FingerModel(length=52.0, theta_entire=0.5, half_thickness=4.0, n_links=1000)


def test_one_nan_theta_does_not_fail_the_batch_gradient() -> None:
    disc = PolygonSDF.regular((22.0, 38.0), 15.0, 16)

    def tip(t):
        e = estimate(FingerModel(52.0, t, 4.0, N), disc, jnp.zeros(2), estimator=Mechanics())
        return jnp.where(e.valid, e.joints[-1, 0], 0.0)

    thetas = jnp.array([0.5, jnp.nan, 0.6, 0.4])
    grads = np.asarray(jax.jit(jax.grad(lambda ts: jnp.sum(jax.vmap(tip)(ts))))(thetas))
    good = [0, 2, 3]
    assert np.isfinite(grads[good]).all() and (np.abs(grads[good]) > 0).all()
    assert grads[1] == 0 or np.isnan(grads[1])
