"""Robust quality (softgrip_jax._robust): K draws of what is uncertain, common to every candidate.

References: the probability of two-contact force closure under a uniform friction coefficient, by
hand (Nguyen's condition mu > tan a), and the nominal score itself when nothing is uncertain.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softgrip_base.errors import SoftgripError
from softgrip_jax import FingerModel, Geometric, Gripper, PolygonSDF, score
from softgrip_jax._quality import CLOSURE_EPSILON, edge_wrenches, epsilon_l1
from softgrip_jax._robust import Uncertainty, perturbations

FINGER = FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=8)
GRIPPER = Gripper(left=FINGER, right=FINGER, base_separation=56.0)
DISC = PolygonSDF.regular((0.0, 38.0), 15.0, 48)
POSES = jnp.array([[0.0, -8.0, 0.0], [2.0, -6.0, 0.05], [0.0, 10.0, 0.0], [-3.0, -9.0, -0.1]])


def test_the_closure_probability_under_uncertain_friction_by_hand() -> None:
    """Two contacts whose chord makes the angle a with both normals close iff mu > tan(a). With mu
    uniform on mu0 (1 +- s), P(closure) = (mu0 (1 + s) - tan a) / (2 s mu0): the draws of
    ``perturbations`` must give it (1,024 draws: within 4 binomial standard deviations)."""
    mu0, spread, a = 0.5, 0.4, 0.45
    draws = perturbations(GRIPPER, mu0, Uncertainty(samples=1024, mu_spread=spread, pose_mm=0.0, pose_rad=0.0))
    assert float(draws.mu.min()) >= mu0 * (1 - spread) - 1e-6 and float(draws.mu.max()) <= mu0 * (1 + spread) + 1e-6
    b = math.pi - 2 * a
    points = 10.0 * jnp.array([[1.0, 0.0], [math.cos(b), math.sin(b)]])
    closed = jax.vmap(lambda mu: epsilon_l1(edge_wrenches(points, points / 10.0, jnp.array([True, True]), mu,
                                                          jnp.zeros(2), 10.0)) > CLOSURE_EPSILON)(draws.mu)
    expected = (mu0 * (1 + spread) - math.tan(a)) / (2 * spread * mu0)
    sd = math.sqrt(expected * (1 - expected) / 1024)
    assert float(jnp.mean(closed)) == pytest.approx(expected, abs=4 * sd)


def test_draws_have_the_requested_spread_and_are_common() -> None:
    u = Uncertainty(samples=2000, pose_mm=0.7, pose_rad=0.02, theta=0.03, length=0.5, contour_mm=0.2, seed=5)
    d = perturbations(GRIPPER, 0.5, u)
    np.testing.assert_allclose(np.std(np.asarray(d.pose), axis=0), [0.7, 0.7, 0.02], rtol=0.1)
    assert float(jnp.std(d.gripper.left.theta_entire)) == pytest.approx(0.03, rel=0.1)
    assert float(jnp.std(d.gripper.right.length)) == pytest.approx(0.5, rel=0.1)
    assert float(jnp.std(d.contour)) == pytest.approx(0.2, rel=0.1)
    again = perturbations(GRIPPER, 0.5, u)
    assert bool(jnp.all(again.pose == d.pose))  # the same seed, the same draws
    other = perturbations(GRIPPER, 0.5, Uncertainty(samples=2000, pose_mm=0.7, seed=6))
    assert not bool(jnp.all(other.pose == d.pose))


@pytest.mark.parametrize("nothing", [
    Uncertainty(samples=2, pose_mm=0.0, pose_rad=0.0, mu_spread=0.0, reach=math.inf),
    Uncertainty(linear=True, pose_mm=0.0, pose_rad=0.0, mu_spread=0.0)], ids=["draws", "linear"])
@pytest.mark.slow  # compiles the robust score twice per case: 25-45 s
def test_without_uncertainty_the_robust_score_is_the_nominal_one(nothing) -> None:
    nominal = score(GRIPPER, DISC, POSES, estimator=Geometric())
    robust = score(GRIPPER, DISC, POSES, estimator=Geometric(), uncertainty=nothing)
    assert bool(jnp.any(nominal.force_closure))
    valid = np.asarray(nominal.valid)
    np.testing.assert_allclose(np.asarray(robust.quality_mean)[valid], np.asarray(nominal.quality)[valid], rtol=1e-5,
                               atol=1e-6)
    np.testing.assert_array_equal(np.asarray(robust.p_closure)[valid], np.asarray(nominal.force_closure, np.float32)[valid])
    assert np.all(np.isnan(np.asarray(robust.p_closure)[~valid]))  # not valid: not drawn
    np.testing.assert_allclose(np.asarray(robust.score), np.asarray(nominal.score), rtol=1e-6)


@pytest.mark.slow
def test_a_candidates_robust_quality_does_not_depend_on_its_batch() -> None:
    u = Uncertainty(samples=8, pose_mm=1.0, pose_rad=0.02, theta=0.02, contour_mm=0.3, reach=math.inf)
    whole = score(GRIPPER, DISC, POSES, estimator=Geometric(), uncertainty=u)
    i = int(np.flatnonzero(np.asarray(whole.valid))[-1])
    alone = score(GRIPPER, DISC, POSES[i:i + 1], estimator=Geometric(), uncertainty=u)
    assert float(alone.quality_mean[0]) == pytest.approx(float(whole.quality_mean[i]), abs=1e-6)
    assert float(alone.p_closure[0]) == float(whole.p_closure[i])
    closed = np.asarray(whole.force_closure)
    assert closed.any()
    # Expected quality is at most the best draw's; a closure grasp ranks on it.
    np.testing.assert_allclose(np.asarray(whole.score)[closed],
                               1 + np.asarray(whole.quality_mean)[closed] * (1 - np.asarray(whole.components.risk)[closed]),
                               rtol=1e-6)


@pytest.mark.parametrize("field", ["pose_mm", "mu_spread", "theta", "reach"])
def test_bad_uncertainty_is_refused_with_its_name(field) -> None:
    with pytest.raises(SoftgripError, match=f"Uncertainty.{field}"):
        Uncertainty(**{field: -1.0})
    with pytest.raises(SoftgripError, match="Uncertainty.samples"):
        Uncertainty(samples=0)


# ---------------------------------------------------------------------------------------------
# The linearisation (Uncertainty(linear=True))


def test_linear_moments_are_a_normal_margins_by_monte_carlo() -> None:
    """Phi(m / s) and E[max(m, 0)] of a normal margin, against numpy draws of it."""
    from softgrip_jax._robust import linear_moments

    rng = np.random.default_rng(3)
    for m, parts in ((0.05, [0.03, 0.04]), (-0.02, [0.01, 0.0, 0.02]), (0.2, [0.001])):
        draws = m + np.linalg.norm(parts) * rng.standard_normal(400_000)
        q, p = linear_moments(jnp.asarray(m, jnp.float32), jnp.asarray(parts, jnp.float32))
        assert float(p) == pytest.approx(np.mean(draws > 0), abs=3e-3)
        assert float(q) == pytest.approx(np.mean(np.maximum(draws, 0.0)), abs=3e-4)
    # No spread: a step and the margin itself.
    q, p = linear_moments(jnp.asarray([0.1, -0.1]), jnp.zeros((13, 2)))
    assert p.tolist() == [1.0, 0.0] and q.tolist() == pytest.approx([0.1, 0.0])


@pytest.mark.slow  # compiles the robust score anew (make test's 15-minute budget)
def test_linear_spread_is_the_finite_difference_gradient_of_the_quality() -> None:
    """Inside force closure the margin is the quality. Its derivatives in the pose and mu by
    central differences of the nominal score give sigma, and with it P = Phi(q / sigma) and the
    expected quality, which the linearised score must reproduce (its derivatives: forward mode)."""
    from scipy.stats import norm

    from softgrip_jax import ScoreWeights

    mu, spread, sx, sa = 0.5, 0.2, 0.3, 0.01
    u = Uncertainty(linear=True, pose_mm=sx, pose_rad=sa, mu_spread=spread)
    lin = score(GRIPPER, DISC, POSES, estimator=Geometric(), uncertainty=u)
    closed = np.flatnonzero(np.asarray(lin.force_closure))
    assert closed.size
    q0 = np.asarray(lin.quality)

    def quality(poses, m=mu):
        return np.asarray(score(GRIPPER, DISC, poses, ScoreWeights(mu=m), estimator=Geometric()).quality, np.float64)

    h = np.array([0.01, 0.01, 0.0005])
    grad = [(quality(POSES + np.eye(3)[j] * h[j]) - quality(POSES - np.eye(3)[j] * h[j])) / (2 * h[j]) for j in range(3)]
    dmu = (quality(POSES, mu + 1e-3) - quality(POSES, mu - 1e-3)) / 2e-3
    sigma = np.sqrt((sx * grad[0]) ** 2 + (sx * grad[1]) ** 2 + (sa * grad[2]) ** 2 + (mu * spread / np.sqrt(3) * dmu) ** 2)
    q0, sigma = q0[closed], sigma[closed]
    assert np.all(sigma > 0)
    t = q0 / sigma
    np.testing.assert_allclose(np.asarray(lin.p_closure)[closed], norm.cdf(t), atol=2e-3)
    expected = q0 * norm.cdf(t) + sigma * norm.pdf(t)
    np.testing.assert_allclose(np.asarray(lin.quality_mean)[closed], expected, rtol=2e-3, atol=1e-5)


@pytest.mark.slow  # compiles a large program (2,000 draws; a gradient through 4 draws)
def test_linear_agrees_with_many_draws_where_the_margin_is_smooth() -> None:
    """A small spread (0.2 mm, 0.005 rad, mu +- 10 %): the margin is nearly linear over it, and the
    linearised P(closure) and expected quality match 2,000 draws'."""
    kw = dict(pose_mm=0.2, pose_rad=0.005, mu_spread=0.1)
    lin = score(GRIPPER, DISC, POSES, estimator=Geometric(), uncertainty=Uncertainty(linear=True, **kw))
    draws = score(GRIPPER, DISC, POSES, estimator=Geometric(), uncertainty=Uncertainty(samples=2000, **kw))
    closed = np.asarray(lin.force_closure)
    assert closed.any()
    np.testing.assert_allclose(np.asarray(lin.p_closure)[closed], np.asarray(draws.p_closure)[closed], atol=0.05)
    np.testing.assert_allclose(np.asarray(lin.quality_mean)[closed], np.asarray(draws.quality_mean)[closed],
                               rtol=0.05, atol=2e-3)


@pytest.mark.slow  # compiles the robust score anew (make test's 15-minute budget)
def test_only_candidates_within_reach_of_closure_are_drawn() -> None:
    """reach = inf draws every valid candidate; reach = r only those in closure or whose closure
    margin is above -r: the others get NaN (not drawn), the rest the same values as with every draw."""
    import math

    x, y = jnp.meshgrid(jnp.linspace(-4.0, 4.0, 3), jnp.linspace(-12.0, 4.0, 5), indexing="ij")
    poses = jnp.stack([x.ravel(), y.ravel(), jnp.zeros(x.size)], axis=-1)
    kw = dict(samples=16, pose_mm=1.0, pose_rad=0.02, mu_spread=0.3)
    every = score(GRIPPER, DISC, poses, estimator=Geometric(), uncertainty=Uncertainty(reach=math.inf, **kw))
    reach = 0.05
    near = score(GRIPPER, DISC, poses, estimator=Geometric(), uncertainty=Uncertainty(reach=reach, **kw))
    margin, valid = np.asarray(every.margin), np.asarray(every.valid)
    drawn = valid & (np.asarray(every.force_closure) | (margin > -reach))
    assert np.asarray(every.force_closure).any() and (valid & ~drawn).any()
    assert np.all(drawn[np.asarray(every.force_closure)])  # closure poses are always drawn
    np.testing.assert_allclose(np.asarray(near.p_closure)[drawn], np.asarray(every.p_closure)[drawn], atol=1e-6)
    np.testing.assert_allclose(np.asarray(near.quality_mean)[drawn], np.asarray(every.quality_mean)[drawn], atol=1e-6)
    assert np.all(np.isnan(np.asarray(near.p_closure)[~drawn])) and np.all(np.isnan(np.asarray(near.quality_mean)[~drawn]))
    assert np.all(np.isfinite(np.asarray(every.p_closure)[valid]))
    # The nominal margin: the quality inside closure, negative outside, -1 where not valid.
    closed = np.asarray(every.force_closure)
    np.testing.assert_allclose(margin[closed], np.asarray(every.quality)[closed], rtol=1e-6)
    assert np.all(margin[valid & ~closed] <= 1e-5) and np.all(margin[~valid] == -1)


@pytest.mark.slow  # compiles a large program (2,000 draws; a gradient through 4 draws)
def test_the_robust_score_has_finite_gradients_in_and_out_of_closure() -> None:
    """refine climbs the robust score by gradient: its derivative in the pose must be finite where
    the candidate is in closure (drawn) and where it is not (not drawn: NaN only in the reports)."""
    from softgrip_jax import score_pose

    u = Uncertainty(samples=4, pose_mm=0.3, pose_rad=0.01, mu_spread=0.1)
    nominal = score(GRIPPER, DISC, POSES, estimator=Geometric())
    closed, valid = np.asarray(nominal.force_closure), np.asarray(nominal.valid)
    picks = [int(np.flatnonzero(closed)[0]), int(np.flatnonzero(valid & ~closed)[0])]
    value_and_grad = jax.jit(jax.value_and_grad(
        lambda p: score_pose(GRIPPER, DISC, p, estimator=Geometric(), uncertainty=u).score))
    for i in picks:
        value, grad = value_and_grad(POSES[i])
        assert np.isfinite(float(value)) and np.all(np.isfinite(np.asarray(grad))), (i, value, grad)
