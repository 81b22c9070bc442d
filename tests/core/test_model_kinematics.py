"""FingerModel validation and the PCC chain against the paper's eqs. 1-3."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from softgrip_jax import FingerModel, Gripper, SoftgripError, forward_kinematics, link_angles, pcc_joints


def eq2_joints(length, theta, n):
    """Joints from eqs. 1-2: joint i on a circle through the base with chord angle Theta i / N.

    Links of length L/N are chords subtending 2 Theta / N of that circle, so its radius is
    rho = L / (2 N sin(Theta / N)) and the chord to joint i is 2 rho sin(Theta i / N).
    """
    i = np.arange(n + 1)
    chord_angle = theta * i / n
    if np.sin(theta / n) == 0:  # Theta = 0, or so small (subnormal) that the sine underflows
        chord = length * i / n
    else:
        chord = (length / n) * np.sin(theta * i / n) / np.sin(theta / n)
    return np.stack([chord * np.sin(chord_angle), chord * np.cos(chord_angle)], axis=-1)


@given(
    n=st.sampled_from([1, 2, 7, 10, 20, 40]),
    theta=st.floats(0.0, 1.5),
    length=st.floats(5.0, 200.0),
)
def test_pcc_chain_matches_eqs_1_to_3(n, theta, length):
    finger = FingerModel(length=length, theta_entire=theta, half_thickness=2.0, n_links=n)
    joints = np.asarray(pcc_joints(finger, jnp.zeros(2)), dtype=np.float64)
    links = np.linalg.norm(np.diff(joints, axis=0), axis=1)
    np.testing.assert_allclose(links, length / n, rtol=1e-5)  # eq. 1
    tip = joints[-1]
    assert math.atan2(tip[0], tip[1]) == pytest.approx(theta, abs=2e-5)  # chord angle = Theta
    np.testing.assert_allclose(joints, eq2_joints(length, theta, n), atol=2e-5 * length)  # eq. 2
    alpha = np.asarray(link_angles(jnp.float32(0.0), jnp.full((n,), 2 * theta / n)))
    np.testing.assert_allclose(alpha, theta * (2 * np.arange(n) + 1) / n, atol=2e-6)  # eq. 3


def test_forward_kinematics_rigid_rotation():
    joints = forward_kinematics(jnp.array([1.0, 2.0]), jnp.float32(math.pi / 2), jnp.zeros(4), jnp.float32(8.0))
    np.testing.assert_allclose(joints, [[1, 2], [3, 2], [5, 2], [7, 2], [9, 2]], atol=1e-5)


@pytest.mark.parametrize(
    "field, kwargs",
    [
        ("length", dict(length=0.0)),
        ("length", dict(length=float("nan"))),
        ("theta_entire", dict(theta_entire=-0.1)),
        ("theta_entire", dict(theta_entire=math.pi / 2)),
        ("theta_entire", dict(theta_entire=float("inf"))),
        ("half_thickness", dict(half_thickness=-1.0)),
        ("n_links", dict(n_links=0)),
    ],
)
def test_finger_model_rejects_bad_fields_by_name(field, kwargs):
    args = dict(length=52.0, theta_entire=0.5, half_thickness=4.0, n_links=10) | kwargs
    with pytest.raises(SoftgripError, match=f"FingerModel.{field}"):
        FingerModel(**args)


def test_gripper_rejects_bad_separation():
    f = FingerModel(length=52.0, theta_entire=0.5, half_thickness=4.0, n_links=10)
    with pytest.raises(SoftgripError, match="base_separation"):
        Gripper(left=f, right=f, base_separation=-3.0)


def test_finger_model_is_traceable():
    """Validation must not break grad/vmap over the parameters."""
    def tip_x(theta):
        return pcc_joints(FingerModel(length=50.0, theta_entire=theta, half_thickness=3.0, n_links=5), jnp.zeros(2))[-1, 0]

    thetas = jnp.array([0.1, 0.3, 0.6])
    np.testing.assert_allclose(jax.vmap(tip_x)(thetas), [eq2_joints(50.0, float(t), 5)[-1, 0] for t in thetas], rtol=1e-5)
    assert np.isfinite(jax.grad(tip_x)(jnp.float32(0.0)))
