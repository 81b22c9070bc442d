"""Derivatives through the contact (implicit differentiation of the root) against finite differences.

The functions under test are jitted once at module level with every scene quantity traced, so the
scenes share one compilation.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softgrip_jax import CASE_NAMES, ContactConfig, FingerModel, Gripper, PolygonSDF, estimate, estimate_grasp
from softgrip_jax import Geometric

FINE = ContactConfig(root_atol=1e-12, root_max_steps=200)
SCENES = {  # case: (Theta, circle centre, circle radius)
    "tip": (0.5, (20.24, 47.94), 5.0),
    "tip_and_other": (0.6, (45.0, 25.0), 40.0),
    "other": (0.5, (8.0, 20.0), 3.0),
}


def joints(theta, base, center, radius, config=FINE):
    finger = FingerModel(length=50.0, theta_entire=theta, half_thickness=3.0, n_links=10)
    return estimate(finger, PolygonSDF.regular(center, radius, 360), base, config, estimator=Geometric()).joints


joints_jit = jax.jit(joints, static_argnames="config")
case_jit = jax.jit(
    lambda t, b, c, r: estimate(
        FingerModel(length=50.0, theta_entire=t, half_thickness=3.0, n_links=10),
        PolygonSDF.regular(c, r, 360), b, FINE, estimator=Geometric()).case
)
jacobians = jax.jit(jax.jacfwd(joints, argnums=(0, 1, 2)), static_argnames="config")


def central_difference(f, x, h=1e-6):
    x = np.asarray(x, dtype=np.float64)
    cols = []
    for idx in np.ndindex(*x.shape):
        e = np.zeros_like(x)
        e[idx] = h
        cols.append((np.asarray(f(x + e)) - np.asarray(f(x - e))) / (2 * h))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("case", sorted(SCENES))
def test_joint_gradients_match_finite_differences(x64, case):
    theta, center, radius = SCENES[case]
    theta, base, center, radius = (jnp.float64(theta), jnp.array([0.3, -0.2]), jnp.array(center),
                                   jnp.float64(radius))
    assert CASE_NAMES[int(case_jit(theta, base, center, radius))] == case
    d_theta, d_base, d_center = jacobians(theta, base, center, radius)
    fd_theta = central_difference(lambda t: joints_jit(t, base, center, radius), theta)[..., 0]
    fd_base = central_difference(lambda b: joints_jit(theta, b, center, radius), base)
    fd_center = central_difference(lambda c: joints_jit(theta, base, c, radius), center)
    np.testing.assert_allclose(d_theta, fd_theta, atol=5e-3)
    np.testing.assert_allclose(d_base, fd_base, atol=5e-3)
    np.testing.assert_allclose(d_center, fd_center, atol=5e-3)
    # The object's position reaches the joints only through the contact prediction.
    assert np.abs(fd_center).max() > 0.1


tip_gradient = jax.jit(jax.grad(lambda t, b, c: jnp.sum(joints(t, b, c, jnp.float32(3.0), ContactConfig())[-1]),
                                argnums=(0, 1)))


@pytest.mark.parametrize("center", [(60.0, 20.0), (8.0, 20.0)])
@pytest.mark.parametrize("theta", [0.0, 1e-7, 1e-3])
def test_no_nan_gradients_at_zero_bending(center, theta):
    """Theta -> 0 (the start of the sweep, s = 0) must give finite derivatives, contact or not."""
    g_theta, g_base = tip_gradient(jnp.float32(theta), jnp.zeros(2), jnp.asarray(center))
    assert np.isfinite(g_theta) and np.all(np.isfinite(g_base))


def test_grasp_gradient_with_respect_to_pose_matches_finite_differences(x64):
    f = FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=10)
    gripper = Gripper(left=f, right=f, base_separation=50.0)
    sdf = PolygonSDF.regular((0.0, 35.0), 9.0, 360)

    @jax.jit
    def tips(pose):
        est = estimate_grasp(gripper, sdf, pose, FINE, estimator=Geometric())
        return jnp.concatenate([est.left.joints[-1], est.right.joints[-1]])

    pose = np.array([1.0, 2.0, 0.05])
    np.testing.assert_allclose(jax.jit(jax.jacfwd(tips))(jnp.asarray(pose)), central_difference(tips, pose), atol=5e-3)
