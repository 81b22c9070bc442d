"""One constructed scene per contact case (paper Fig. 6), with the joints each case's rule gives (softgrip_jax._deformation)."""

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from softgrip_jax import CASE_NAMES, ContactCase, FingerModel, PolygonSDF, Status
from softgrip_jax import estimate as _estimate
from softgrip_jax import Geometric

estimate = eqx.filter_jit(_estimate)
L, R_FINGER, N = 50.0, 3.0, 10


def chain(psi, turning):
    """Joints of a chain written out link by link (eq. 3 generalised): numpy, independent."""
    joints, angle, p = [np.zeros(2)], psi, np.zeros(2)
    for t in turning:
        link_angle = angle + t / 2
        p = p + (L / len(turning)) * np.array([math.sin(link_angle), math.cos(link_angle)])
        joints.append(p)
        angle += t
    return np.array(joints)


def run(theta, center, radius):
    finger = FingerModel(length=L, theta_entire=theta, half_thickness=R_FINGER, n_links=N)
    est = estimate(finger, PolygonSDF.regular(center, radius, n_vertices=720), jnp.zeros(2), estimator=Geometric())
    assert int(est.status) == Status.OK and bool(est.valid)
    return est, est.contact


def test_case_a_no_contact_is_the_free_pcc_shape():
    est, c = run(0.5, (70.0, 20.0), 6.0)
    assert int(est.case) == ContactCase.NONE
    np.testing.assert_allclose(est.joints, chain(0.0, [2 * 0.5 / N] * N), atol=1e-4)


def test_case_b_tip_rotates_the_free_shape_back_by_theta_remain():
    # The free tip at chord angle s = 0.25 is at (L/N) sin(s)/sin(s/N) (sin s, cos s) = (12.24, 47.94);
    # a circle touching it from +x at that moment: centre (12.24 + r + R, 47.94).
    theta, radius = 0.5, 5.0
    tip = (L / N) * math.sin(0.25) / math.sin(0.025) * np.array([math.sin(0.25), math.cos(0.25)])
    est, c = run(theta, (tip[0] + R_FINGER + radius, tip[1]), radius)
    assert CASE_NAMES[int(est.case)] == est.case_name == "tip"
    assert float(c.s1) == pytest.approx(0.25, abs=2e-3)
    assert float(c.n_g1) == pytest.approx(N, abs=1e-3)
    np.testing.assert_allclose(c.p_g1, tip, atol=0.05)
    np.testing.assert_allclose(c.p_o1, tip + np.array([R_FINGER, 0.0]), atol=0.05)
    # Theta_o1 is the angle of P_base -> P_g1: for a tip contact, the chord angle at contact.
    assert float(c.theta_o1) == pytest.approx(0.25, abs=2e-3)
    # psi = -(Theta - Theta_o1), turning 2 Theta / N.
    np.testing.assert_allclose(est.joints, chain(-(theta - float(c.theta_o1)), [2 * theta / N] * N), atol=1e-4)
    np.testing.assert_allclose(est.joints, chain(-(theta - 0.25), [2 * theta / N] * N), atol=0.1)
    # The rotated shape's tip lies on the ray to where it first touched (chord angle Theta_o1),
    # at the chord length of the fully bent shape, (L/N) sin(Theta)/sin(Theta/N): the paper keeps
    # Theta, so the tip stops short of the contact instead of penetrating the object.
    tip_est = np.asarray(est.joints[-1])
    assert math.atan2(*tip_est) == pytest.approx(float(c.theta_o1), abs=1e-5)
    assert np.linalg.norm(tip_est) == pytest.approx((L / N) * math.sin(theta) / math.sin(theta / N), abs=1e-3)


# A big circle (R = 40) whose leftmost point is 2 mm + r from the straight finger at mid-length:
# the finger's lower half touches first; the circle of radius L - L_g1 around P_o1 crosses the
# object further down at Theta_o1o2 of about 0.38 rad.
BIG = ((45.0, 25.0), 40.0)


def test_case_c_tip_and_other():
    theta = 0.6
    est, c = run(theta, *BIG)
    assert CASE_NAMES[int(est.case)] == est.case_name == "tip_and_other"
    assert 0 < float(c.n_g1) < N - 0.5 and bool(c.has_second)
    # Both contacts lie on the object's surface; the centreline points r outside them are the
    # remaining length L - L_g1 apart (the circle of Fig. 8 on the object dilated by r).
    centre, radius = np.asarray(BIG[0]), BIG[1]
    for p in (c.p_o1, c.p_o2):
        assert np.linalg.norm(np.asarray(p) - centre) == pytest.approx(radius, abs=0.05)
    g2 = np.asarray(c.p_o2) + R_FINGER * (np.asarray(c.p_o2) - centre) / radius
    assert np.linalg.norm(g2 - np.asarray(c.p_g1)) == pytest.approx(L - float(c.l_g1), abs=0.02)
    assert math.atan2(*(g2 - np.asarray(c.p_g1))) == pytest.approx(float(c.theta_o1o2), abs=2e-3)
    assert float(c.theta_remain) >= float(c.theta_o1o2)
    remain = theta - float(c.theta_o1) - float(c.theta_o1o2)  # eq. 9
    np.testing.assert_allclose(est.joints, chain(-remain, [2 * theta / N] * N), atol=1e-4)


def expected_case_d(theta, c):
    n_g1, theta_o1 = float(c.n_g1), float(c.theta_o1)
    remain = theta - theta_o1  # eq. 8
    turning = []
    for k in range(N):
        share = min(max(n_g1 - k, 0.0), 1.0)
        turning.append(share * 2 * theta_o1 / n_g1 + (1 - share) * 2 * remain / (N - n_g1))
    return chain(0.0, turning)


def test_case_d_when_the_tip_cannot_reach_the_second_point():
    theta = 0.35  # same scene as case (c), but Theta_remain < Theta_o1o2
    est, c = run(theta, *BIG)
    assert CASE_NAMES[int(est.case)] == est.case_name == "other"
    assert bool(c.has_second) and float(c.theta_remain) < float(c.theta_o1o2)
    np.testing.assert_allclose(est.joints, expected_case_d(theta, c), atol=1e-4)


def test_case_d_small_object_inside_the_remaining_reach():
    theta = 0.5
    est, c = run(theta, (8.0, 20.0), 3.0)
    assert CASE_NAMES[int(est.case)] == est.case_name == "other"
    assert not bool(c.has_second)  # the 6 mm object lies wholly inside the circle of radius L - L_g1
    joints = np.asarray(est.joints)
    np.testing.assert_allclose(joints, expected_case_d(theta, c), atol=1e-4)
    # The links up to the contact bend to Theta_o1: joint floor(N_g1) lies on that chord direction.
    k = int(float(c.n_g1))
    assert math.atan2(*joints[k]) == pytest.approx(float(c.theta_o1) * k / float(c.n_g1), abs=1e-3)
    # Total turning is still 2 Theta: the tip tangent is the free shape's.
    assert float(jnp.sum(est.turning)) == pytest.approx(2 * theta, abs=1e-5)
