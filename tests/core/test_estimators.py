"""Estimators are objects: a new one is one class; ``as_estimator`` turns a name (the command line's) into one."""

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxtyping import TypeCheckError

from softgrip_jax import (AbstractEstimator, FingerModel, Geometric, Gripper, Mechanics, MechanicsConfig, PolygonSDF,
                          SoftgripError, as_estimator, estimate, estimate_batch, estimate_grasp, pcc_joints, score)
from softgrip_jax._stage import finish
from softgrip_jax._kinematics import pcc_turning

FINGER = FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=10)
DISC = PolygonSDF.regular((20.0, 30.0), 8.0)  # the finger hanging from the origin closes onto it


class FreeClosure(AbstractEstimator):
    """A third estimator, defined here only: the finger closes as if the object were not there (its
    PCC shape, eqs. 1-3), whatever the contact prediction found."""

    name: ClassVar[str] = "free-closure"

    def deform(self, finger, sdf, stage, config):
        free = eqx.tree_at(lambda st: (st.psi, st.turning), stage,
                           (jnp.zeros_like(stage.psi), pcc_turning(finger.theta_entire, finger.n_links)))
        return finish(finger, free)


def _assert_same(a, b) -> None:
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    assert ta == tb
    for x, y in zip(la, lb):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.mark.slow  # compiles a new estimator through three entry points: about 45 s
def test_a_new_estimator_runs_through_estimate_estimate_batch_and_score():
    bases = jnp.array([[0.0, 0.0], [-60.0, 0.0], [3.0, -2.0]])  # touching, free, touching (mm)
    one = estimate(FINGER, DISC, bases[0], estimator=FreeClosure())
    many = estimate_batch(FINGER, DISC, bases, estimator=FreeClosure())
    geometric = estimate_batch(FINGER, DISC, bases, estimator=Geometric())
    assert bool(one.valid) and many.valid.tolist() == [True, True, True]
    # The untouched PCC shape at every base, though the geometric estimate bends at the touching ones.
    for k, base in enumerate(bases):
        np.testing.assert_allclose(np.asarray(many.joints[k]), np.asarray(pcc_joints(FINGER, base)), atol=1e-4)
    np.testing.assert_allclose(np.asarray(one.joints), np.asarray(pcc_joints(FINGER, bases[0])), atol=1e-4)
    assert float(jnp.max(jnp.abs(geometric.joints[0] - many.joints[0]))) > 1.0  # the contact changed it there
    np.testing.assert_allclose(np.asarray(geometric.joints[1]), np.asarray(many.joints[1]), atol=1e-4)  # free
    # By hand: link k of the PCC shape points at Theta (2k+1)/N from the vertical (eq. 3), so the tip is
    # (L/N) sum_k (sin, cos) of those: (L/N) (sin^2 Theta, sin(2 Theta) / 2) / sin(Theta / N).
    x = 0.5 / 10
    tip = 5.0 * np.array([np.sin(0.5) ** 2, np.sin(1.0) / 2.0]) / np.sin(x)  # [22.994, 42.091] mm
    np.testing.assert_allclose(np.asarray(one.joints[-1]), tip, atol=1e-3)

    gripper = Gripper(left=FINGER, right=FINGER, base_separation=50.0)
    poses = jnp.array([[0.0, 0.0, 0.0], [0.0, -100.0, 0.0]])
    scored = score(gripper, PolygonSDF.regular((0.0, 35.0), 9.0), poses, estimator=FreeClosure())
    assert scored.score.shape == (2,)
    left = estimate_grasp(gripper, PolygonSDF.regular((0.0, 35.0), 9.0), poses[0], estimator=FreeClosure()).left
    np.testing.assert_allclose(np.asarray(scored.grasp.left.joints[0]), np.asarray(left.joints), atol=1e-4)
    np.testing.assert_allclose(np.asarray(left.joints), np.asarray(pcc_joints(FINGER, jnp.array([-25.0, 0.0]))),
                               atol=1e-4)


def test_method_strings_and_estimator_objects_give_identical_results():
    bases = jnp.array([[0.0, 0.0], [-60.0, 0.0], [jnp.nan, 0.0]])
    _assert_same(estimate(FINGER, DISC, bases[0], estimator=Geometric()),
                 estimate(FINGER, DISC, bases[0], estimator=Geometric()))
    _assert_same(estimate_batch(FINGER, DISC, bases, estimator=Geometric()),
                 estimate_batch(FINGER, DISC, bases, estimator=Geometric()))
    config = MechanicsConfig(max_steps=8)
    _assert_same(estimate_batch(FINGER, DISC, bases, estimator=Mechanics(config)),
                 estimate_batch(FINGER, DISC, bases, estimator=Mechanics(config)))


def test_estimators_hash_by_value():
    a, b = Mechanics(MechanicsConfig(max_steps=8, penalty=2e4)), Mechanics(MechanicsConfig(max_steps=8, penalty=2e4))
    assert a == b and hash(a) == hash(b) and a is not b
    assert a != Mechanics() and Mechanics() == Mechanics(MechanicsConfig()) and Geometric() == Geometric()
    assert Geometric() != Mechanics() and {a: 1}[b] == 1
    assert jax.tree_util.tree_leaves(a) == []  # all static: a jit's static argument, or a leafless pytree
    # Equal estimators reuse one compiled program.
    run = jax.jit(estimate, static_argnames="estimator")
    run(FINGER, DISC, jnp.zeros(2), estimator=Geometric())
    size = run._cache_size()
    run(FINGER, DISC, jnp.zeros(2), estimator=Geometric())
    assert run._cache_size() == size


def test_as_estimator_is_the_one_alias():
    assert as_estimator() == Mechanics() and as_estimator(method="geometric") == Geometric()
    assert as_estimator(method="mechanics", mechanics=MechanicsConfig(max_steps=3)) == Mechanics(MechanicsConfig(max_steps=3))
    assert as_estimator(mechanics=MechanicsConfig(max_steps=3)) == Mechanics(MechanicsConfig(max_steps=3))
    with pytest.raises(SoftgripError, match="not both"):
        as_estimator(Geometric(), method="geometric")
    with pytest.raises(SoftgripError, match=r"estimator='geometric': pass the estimator itself, Geometric\(\)"):
        as_estimator("geometric")
    with pytest.raises(TypeError, match="method"):  # one way to name the estimator: the object
        estimate(FINGER, DISC, jnp.zeros(2), method="geometric")  # type: ignore[call-arg]
    with pytest.raises(SoftgripError, match="method must be one of 'geometric', 'mechanics'"):
        as_estimator(method="spring")
    with pytest.raises(SoftgripError, match="estimator must be"):
        as_estimator("spring")
    with pytest.raises((SoftgripError, TypeCheckError), match="MechanicsConfig"):  # (the tests' type checker first)
        Mechanics(config=3)


def test_an_estimator_with_a_field_that_is_not_static_is_refused():
    class Scaled(FreeClosure):
        scale: float = 1.0  # not static: it would be traced, and estimators are static arguments

    with pytest.raises(SoftgripError, match="must be static.*scale"):
        Scaled()


def test_exported_programs_are_keyed_by_the_estimators_class_and_settings():
    from softgrip_jax._export import static_ident

    tight = static_ident(Mechanics(MechanicsConfig(max_steps=8)))
    assert "softgrip_jax._estimators.Mechanics[mechanics]" in tight and "max_steps=8" in tight
    assert tight == static_ident(Mechanics(MechanicsConfig(max_steps=8)))
    assert len({tight, static_ident(Mechanics()), static_ident(Geometric())}) == 3
    # A class of the user's: its code is not in the package's source hash, so it is never exported.
    assert static_ident(FreeClosure()) is None and static_ident(4096) == "4096"
