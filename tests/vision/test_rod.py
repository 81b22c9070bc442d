"""The observed-closure rod (synthetic.rod): energy, free arc, contact, stiffness, base spring.

One object scene is shared: a left finger (L = 90 mm, Theta = 0.8 rad, r = 5 mm, base at (7, 0))
and a 12 mm circle whose surface comes within 1.75 mm of the free closed arc at mid-length, so the
free arc would overlap the finger's thickness by 3.25 mm there. Closures are cached per mechanics
and compile once per object structure.
"""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softgrip_jax import PolygonSDF, SoftgripError
from synthetic.rod import (
    RodMechanics,
    close_rod,
    free_arc_points,
    observed_joints,
    rod_energy,
)

BASE = (7.0, 0.0)
LENGTH, THETA, HALF_THICKNESS = 90.0, 0.8, 5.0
CENTRE_FROM_BASE, RADIUS = (30.0, 45.0), 12.0
M = RodMechanics().n_segments
STATIONS = np.arange(M + 1) * LENGTH / M  # arc length of each rod node, mm


def circle(handedness=1.0):
    """The scene's object for a left (+1) or right (-1) finger with the same base."""
    centre = (BASE[0] + handedness * CENTRE_FROM_BASE[0], BASE[1] + CENTRE_FROM_BASE[1])
    return PolygonSDF.regular(center=centre, radius=RADIUS, n_vertices=64)


@functools.cache
def closure_with_object(stiffness_ratio=1.0, base_compliance=0.0, handedness=1.0):
    mechanics = RodMechanics(stiffness_ratio=stiffness_ratio, base_compliance=base_compliance)
    return close_rod(
        jnp.array(BASE), THETA, LENGTH, HALF_THICKNESS, circle(handedness), mechanics=mechanics, handedness=handedness
    )


def as_np(x):
    return np.asarray(x, dtype=np.float64)


def link_directions(points):
    """(M,) direction of each segment, rad from the downward vertical, positive toward +x."""
    step = np.diff(as_np(points), axis=0)
    return np.arctan2(step[:, 0], step[:, 1])


def bending_moments(closure, mechanics):
    """(M,) elastic moment at each node, k_i (kappa0 l_i - phi_i) / l_i (units of mean(k) / L)."""
    voronoi = np.r_[0.5, np.ones(M - 1)] / M
    ratio = mechanics.stiffness_ratio
    stiffness = 2 / (ratio + 1) * (ratio + (1 - ratio) * np.arange(M) / M)
    return stiffness * (2 * THETA * voronoi - as_np(closure.turning)) / voronoi


def test_energy_gradient_matches_central_differences():
    mechanics = RodMechanics(stiffness_ratio=2.0, base_compliance=0.3)
    rng = np.random.default_rng(0)
    n_points = M * mechanics.samples_per_segment + 1
    with jax.enable_x64(True):
        rest = 2 * THETA / M
        x0 = jnp.asarray(np.r_[rest * (1 + 0.3 * rng.standard_normal(M)), 0.05])
        multipliers = jnp.asarray(rng.uniform(0.0, 0.5, n_points))

        def energy(x, sdf, lam):
            return rod_energy(
                x[:-1], x[-1], jnp.array(BASE), THETA, LENGTH, HALF_THICKNESS, sdf,
                mechanics=mechanics, multipliers=lam,
            )  # fmt: skip

        # The configuration must overlap the object, or the contact term would go untested.
        overlap = energy(x0, circle(), jnp.zeros(n_points)) - energy(x0, None, None)
        assert overlap > 1.0
        f = jax.jit(lambda x: energy(x, circle(), multipliers))
        grad = as_np(jax.grad(f)(x0))
        eps = 1e-6
        basis = eps * jnp.eye(x0.size)
        central = (as_np(jax.vmap(f)(x0 + basis)) - as_np(jax.vmap(f)(x0 - basis))) / (2 * eps)
    np.testing.assert_allclose(grad, central, rtol=1e-5, atol=1e-6 * np.abs(grad).max())


@pytest.mark.parametrize("handedness", [1.0, -1.0])
@pytest.mark.parametrize("theta", [0.3, 0.9, 1.4])
def test_free_closure_is_the_analytic_arc(theta, handedness):
    closure = close_rod(jnp.array(BASE), theta, LENGTH, HALF_THICKNESS, None, handedness=handedness)
    assert bool(closure.converged)
    assert float(closure.max_penetration) == 0.0 and not bool(jnp.any(closure.in_contact))
    assert float(closure.energy) < 1e-10
    arc = as_np(free_arc_points(BASE, theta, LENGTH, STATIONS, handedness))
    np.testing.assert_allclose(as_np(closure.points), arc, atol=0.05)
    tip = arc[-1] - BASE
    assert math.atan2(handedness * tip[0], tip[1]) == pytest.approx(theta, abs=1e-12)  # chord angle
    n_links = 7  # 96 / 7 is fractional: joints fall inside segments
    joints = as_np(free_arc_points(BASE, theta, LENGTH, np.arange(n_links + 1) * LENGTH / n_links, handedness))
    np.testing.assert_allclose(as_np(observed_joints(closure, n_links)), joints, atol=0.05)


def test_object_stops_the_finger_without_penetrating_and_the_free_part_keeps_its_rest_shape():
    closure = closure_with_object()
    contact = as_np(closure.in_contact).astype(bool)
    assert bool(closure.converged)
    assert float(closure.max_penetration) < RodMechanics().penetration_tol
    assert contact.any()
    free_tip = as_np(free_arc_points(BASE, THETA, LENGTH, LENGTH))
    assert np.linalg.norm(as_np(closure.points[-1]) - free_tip) > 1.0
    # Contact lies on the stretch of the free arc that would have overlapped the object.
    with jax.enable_x64(True):
        overlap = as_np(circle().distance(free_arc_points(BASE, THETA, LENGTH, STATIONS))) < HALF_THICKNESS
    assert overlap[1:-1].any() and not overlap[:20].any()
    assert overlap[contact].all()
    # Past the last contact no force acts: the finger keeps its rest curvature there ...
    beyond = np.nonzero(contact)[0].max() + 2
    np.testing.assert_allclose(as_np(closure.turning)[beyond:], 2 * THETA / M, rtol=1e-6)
    # ... and before the first contact the bending moment is that of one resultant contact force,
    # linear in the node position: m_i = a + P_i x F (discrete equilibrium of the whole solve).
    moments = bending_moments(closure, RodMechanics())
    before = np.nonzero(contact)[0].min() - 2
    nodes = as_np(closure.points)[:before]
    design = np.stack([np.ones(before), nodes[:, 1], -nodes[:, 0]], axis=1)
    fit, *_ = np.linalg.lstsq(design, moments[:before], rcond=None)
    assert np.abs(design @ fit - moments[:before]).max() < 1e-5 * np.abs(moments[:before]).max()
    assert np.abs(moments[:before]).max() > 0.1  # the object really loads the finger


def test_right_finger_is_the_mirrored_left_finger():
    left, right = closure_with_object(handedness=1.0), closure_with_object(handedness=-1.0)
    mirrored = as_np(left.points) * [-1.0, 1.0] + [2 * BASE[0], 0.0]
    np.testing.assert_allclose(as_np(right.points), mirrored, atol=1e-6)
    np.testing.assert_array_equal(as_np(right.in_contact), as_np(left.in_contact))


def test_stiffer_base_keeps_its_curvature_and_closes_the_tip_less():
    """stiffness_ratio = 2 (base twice as stiff as the tip, same mean) against the same object.

    The contact moment is largest at the base. A stiffer base gives less there, so the proximal
    part keeps more of its rest curvature, and the curvature the contact takes away concentrates
    just before the contact, where it turns the tangent a lot but moves the contact point little.
    The contact then sees a tangent turned further away from the object, and the free part past it
    (which keeps its rest shape) ends less closed: a smaller tip direction.
    """
    uniform, stiff_base = closure_with_object(1.0), closure_with_object(2.0)
    assert bool(stiff_base.converged) and bool(uniform.converged)
    rest = 2 * THETA / M
    near_base = slice(1, 20)  # the first fifth of the finger
    kept_uniform = as_np(uniform.turning)[near_base].mean() / rest
    kept_stiff = as_np(stiff_base.turning)[near_base].mean() / rest
    assert kept_stiff > kept_uniform + 0.01
    tip_uniform, tip_stiff = link_directions(uniform.points)[-1], link_directions(stiff_base.points)[-1]
    assert tip_stiff < tip_uniform - 0.005


def test_base_compliance_lets_the_base_turn_away_under_contact():
    clamped, compliant = closure_with_object(), closure_with_object(base_compliance=0.5)
    assert float(clamped.base_angle) == 0.0
    assert bool(compliant.converged)
    assert float(compliant.base_angle) < -0.05  # away from the object (toward -x)
    assert link_directions(compliant.points)[0] < link_directions(clamped.points)[0] - 0.05
    # The base spring balances the bending moment at the base node: psi / c = -m_0.
    moment = bending_moments(compliant, RodMechanics(base_compliance=0.5))[0]
    assert float(compliant.base_angle) / 0.5 == pytest.approx(-moment, rel=1e-6)
    free = close_rod(jnp.array(BASE), THETA, LENGTH, HALF_THICKNESS, None, mechanics=RodMechanics(base_compliance=0.5))
    assert abs(float(free.base_angle)) < 1e-9


@pytest.mark.parametrize(
    "field, kwargs",
    [
        ("stiffness_ratio", dict(stiffness_ratio=0.0)),
        ("stiffness_ratio", dict(stiffness_ratio=float("nan"))),
        ("base_compliance", dict(base_compliance=-0.1)),
        ("n_segments", dict(n_segments=40)),
        ("n_segments", dict(n_segments=96.0)),
        ("n_steps", dict(n_steps=0)),
        ("samples_per_segment", dict(samples_per_segment=0)),
        ("penetration_tol", dict(penetration_tol=0.0)),
        ("contact_tol", dict(contact_tol=-1.0)),
        ("penalty", dict(penalty=float("inf"))),
        ("max_rounds", dict(max_rounds=0)),
        ("max_iterations", dict(max_iterations=True)),
        ("solver_tol", dict(solver_tol=0.0)),
    ],
)
def test_mechanics_rejects_bad_fields_by_name(field, kwargs):
    with pytest.raises(SoftgripError, match=f"RodMechanics.{field}"):
        RodMechanics(**kwargs)


@pytest.mark.parametrize(
    "name, kwargs",
    [
        ("base", dict(base=(1.0, 2.0, 3.0))),
        ("base", dict(base=(float("nan"), 0.0))),
        ("theta_entire", dict(theta_entire=-0.1)),
        ("theta_entire", dict(theta_entire=math.pi / 2)),
        ("length", dict(length=0.0)),
        ("half_thickness", dict(half_thickness=-1.0)),
        ("handedness", dict(handedness=0.5)),
        ("sdf", dict(sdf=np.zeros((4, 2)))),
    ],
)
def test_close_rod_rejects_bad_inputs_by_name(name, kwargs):
    args = dict(base=BASE, theta_entire=THETA, length=LENGTH, half_thickness=HALF_THICKNESS, sdf=None) | kwargs
    handedness = args.pop("handedness", 1.0)
    with pytest.raises(SoftgripError, match=name):
        close_rod(**args, handedness=handedness)


def test_observed_joints_rejects_zero_links():
    closure = close_rod(jnp.array(BASE), THETA, LENGTH, HALF_THICKNESS)
    with pytest.raises(SoftgripError, match="n_links"):
        observed_joints(closure, 0)
