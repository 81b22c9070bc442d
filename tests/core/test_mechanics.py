"""The mechanics estimate (spring-joint chain at equilibrium, softgrip_jax._mechanics).

Checked against eqs. 1-3 without an object, against the independent observed-closure rod
(synthetic.rod) on circles and squares touched at the tip and at another area, for
non-penetration, for the contact case (areas that carry force, not grazes), for implicit gradients against finite differences (float64), and through the
batch, grasp, score and refine functions.

Compilations dominate the time: the rod closures share one compilation (64-vertex polygons), the
estimates one jitted function per shape, and the finger is N = 20 throughout.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxtyping import TypeCheckError

from softgrip_jax import (CASE_NAMES, METHODS, ContactCase, ContactConfig, FingerFrame, FingerModel, Gripper,
                          Mechanics, MechanicsConfig, PolygonSDF, RefineStatus, SDFGrid, SoftgripError, Status, estimate,
                          estimate_batch, estimate_grasp, estimate_grasp_batch, estimate_in_frame, forward_kinematics,
                          pcc_joints, refine, score, score_pose)
from softgrip_jax._batch import where_needed
from softgrip_jax._grasp import finger_frames
from softgrip_jax._stage import finish, geometric_stage, mechanics_of
from softgrip_jax._mechanics import _derivatives, _Problem, solve_equilibrium
from softgrip_jax._sdf import AbstractSDF
from synthetic.rod import RodMechanics, close_rod, free_arc_points, observed_joints

LENGTH, THETA, HALF_THICKNESS, N = 52.0, 0.55, 4.0, 20
CONTACT_TOL = MechanicsConfig().contact_tol


def square(center, side, per_side=16):
    """An axis-aligned square as a 64-vertex polygon (the circles' vertex count: one compilation)."""
    h = side / 2
    corners = np.array([(-h, -h), (h, -h), (h, h), (-h, h)])
    t = np.arange(per_side)[:, None] / per_side
    edges = [corners[i] + t * (corners[(i + 1) % 4] - corners[i]) for i in range(4)]
    return PolygonSDF(jnp.asarray(np.concatenate(edges) + np.asarray(center)))


def circle(center, radius):
    return PolygonSDF.regular(center, radius, 64)


def placed(kind, arc_fraction, size, overlap, along):
    """An object (circle of radius ``size``, or square of half-side ``size``) on the inner side of
    the free closed finger at ``arc_fraction`` of its length, overlapping the finger's thickness by
    ``overlap`` mm there, moved ``along`` mm further along the finger's direction."""
    s = arc_fraction * LENGTH
    with jax.enable_x64(True):
        point = np.asarray(free_arc_points((0.0, 0.0), THETA, LENGTH, s))
    a = 2 * THETA * s / LENGTH  # tangent direction of the free arc
    inward, tangent = np.array([np.cos(a), -np.sin(a)]), np.array([np.sin(a), np.cos(a)])
    centre = point + inward * (HALF_THICKNESS + size - overlap) + tangent * along
    return circle(centre, size) if kind == "circle" else square(centre, 2 * size)


SCENES = {
    "circle_tip": ("circle", 1.0, 10.0, 4.0, 3.0),
    "circle_other": ("circle", 0.6, 10.0, 3.0, 0.0),
    "square_tip": ("square", 1.0, 10.0, 4.0, 6.0),
    "square_other": ("square", 0.65, 10.0, 3.0, 0.0),
}
EXPECTED_CASE = {"circle_tip": ContactCase.TIP, "circle_other": ContactCase.OTHER,
                 "square_tip": ContactCase.TIP, "square_other": ContactCase.OTHER}


def finger(stiffness_ratio=1.0, base_compliance=0.0):
    return FingerModel(LENGTH, THETA, HALF_THICKNESS, N, stiffness_ratio=stiffness_ratio,
                       base_compliance=base_compliance)


@functools.cache
def rod_joints(scene, stiffness_ratio, base_compliance):
    """The observed closure's joints at N equal arc lengths (float64 numpy)."""
    mechanics = RodMechanics(stiffness_ratio=stiffness_ratio, base_compliance=base_compliance)
    closure = close_rod((0.0, 0.0), THETA, LENGTH, HALF_THICKNESS, placed(*SCENES[scene]), mechanics=mechanics)
    assert bool(closure.converged)
    return np.asarray(observed_joints(closure, N), np.float64)


@jax.jit
def both_estimates(finger_, sdf, base):
    """The geometric and the mechanics estimate, sharing one contact prediction (half the compile
    time of two ``estimate`` calls; ``estimate_in_frame(estimator=Mechanics())`` is these stages)."""
    frame = FingerFrame(base, jnp.zeros((), base.dtype), jnp.ones((), base.dtype))
    stage = geometric_stage(finger_, sdf, frame, ContactConfig(), Mechanics())
    config = MechanicsConfig()
    mech = finish(finger_, stage, mechanics_of(finger_, sdf, stage, config, ContactConfig()))
    return finish(finger_, stage), mech, stage


def dense_centreline(joints, per_link=16):
    joints = np.asarray(joints)
    t = np.arange(per_link)[None, :, None] / per_link
    inner = joints[:-1, None, :] + t * (joints[1:] - joints[:-1])[:, None, :]
    return np.concatenate([inner.reshape(-1, 2), joints[-1:]])


def clearance(sdf, joints):
    """Smallest distance (mm) of the dense centreline of ``joints`` to the object, minus r."""
    return float(np.min(np.asarray(sdf.distance(jnp.asarray(dense_centreline(joints), jnp.float32))))) - HALF_THICKNESS


# ---------------------------------------------------------------------------------------------
# API contract


def test_finger_model_gains_stiffness_and_base_compliance_with_defaults():
    f = FingerModel(52.0, 0.5, 4.0, 10)  # the four fields, positionally
    assert float(f.stiffness_ratio) == 1.0 and float(f.base_compliance) == 0.0
    g = FingerModel(52.0, 0.5, 4.0, 10, 2.0, 0.3)
    assert float(g.stiffness_ratio) == 2.0 and float(g.base_compliance) == pytest.approx(0.3)


@pytest.mark.parametrize("field, value", [("stiffness_ratio", 0.0), ("stiffness_ratio", float("nan")),
                                          ("base_compliance", -0.1), ("base_compliance", float("inf"))])
def test_finger_model_rejects_bad_mechanics_fields_by_name(field, value):
    with pytest.raises(SoftgripError, match=f"FingerModel.{field}"):
        FingerModel(52.0, 0.5, 4.0, 10, **{field: value})


@pytest.mark.parametrize("field, value", [("max_steps", 0), ("stations_per_link", 0), ("active_rows", True),
                                          ("penalty", 0.0), ("contact_tol", -1.0), ("step_tol", float("nan")),
                                          ("max_turn", float("inf"))])
def test_mechanics_config_rejects_bad_fields_by_name(field, value):
    with pytest.raises(SoftgripError, match=f"MechanicsConfig.{field}"):
        MechanicsConfig(**{field: value})


def test_status_values_are_appended_not_renumbered():
    assert [s.value for s in Status][:6] == [0, 1, 2, 3, 4, 5]
    assert Status.MECHANICS_NOT_CONVERGED == 5 and METHODS == ("geometric", "mechanics")


def test_every_function_rejects_what_is_not_an_estimator_and_names_the_fix():
    f = finger()
    g = Gripper(left=f, right=f, base_separation=56.0)
    disc = circle((0.0, 38.0), 15.0)
    frame = FingerFrame(jnp.zeros(2), jnp.zeros(()), jnp.ones(()))
    calls = [
        lambda m: estimate(f, disc, jnp.zeros(2), estimator=m),
        lambda m: estimate_in_frame(f, disc, frame, estimator=m),
        lambda m: estimate_grasp(g, disc, jnp.zeros(3), estimator=m),
        lambda m: estimate_batch(f, disc, jnp.zeros((2, 2)), estimator=m),
        lambda m: estimate_grasp_batch(g, disc, jnp.zeros((2, 3)), estimator=m),
        lambda m: score_pose(g, disc, jnp.zeros(3), estimator=m),
        lambda m: score(g, disc, jnp.zeros((2, 3)), estimator=m),
        lambda m: refine(g, disc, jnp.zeros(3), estimator=m),
    ]
    for call in calls:
        # (Under the test run's jaxtyping hook the annotation refuses it first, naming the argument.)
        with pytest.raises((SoftgripError, TypeCheckError), match="estimator"):
            call("spring")


def test_where_needed_maps_only_the_needed_elements_and_puts_them_back():
    need = jnp.array([False, True, True, False, True, False, False, True, True, False, False])
    xs = jnp.arange(11.0)
    out = jax.jit(lambda n, x: where_needed(lambda v: (v * 2.0, v + 1.0), n, x, groups=3))(need, xs)
    np.testing.assert_array_equal(out[0], np.where(need, 2.0 * xs, 0.0))
    np.testing.assert_array_equal(out[1], np.where(need, xs + 1.0, 0.0))
    # ordered by kind (like cost together): the same answers, each in its place
    kinds = jnp.array([2, 1, 0, 0, 2, 1, 1, 0, 2, 2, 0])
    seen = []

    def fn(v):
        jax.debug.callback(lambda a: seen.append(np.asarray(a).ravel()), v)
        return v * 2.0

    out = jax.jit(lambda n, x, k: where_needed(fn, n, x, 6, k, 3))(need, xs, kinds)
    np.testing.assert_array_equal(jax.block_until_ready(out), np.where(need, 2.0 * xs, 0.0))
    # groups of two, in the order kind 0 (elements 2, 7), kind 1 (1), kind 2 (4, 8), a spare lane last
    lanes = np.concatenate(seen).tolist()
    assert [set(lanes[i:i + 2]) for i in (0, 2, 4)] == [{2.0, 7.0}, {1.0, 4.0}, {8.0}], lanes


def test_where_needed_never_maps_an_element_that_is_not_needed():
    # A group's spare lanes repeat a needed element: an element that needs nothing (one whose loop
    # would run to a large budget, say) must not hold its group's vmapped loop: fn never sees it.
    need = jnp.array([False, True, True, False, True, False, False, True, True, False, False])
    xs = jnp.where(need, jnp.arange(11.0), 1000.0)
    seen = []

    def fn(v):
        jax.debug.callback(lambda a: seen.append(np.asarray(a).ravel()), v)
        return v

    out = jax.jit(lambda n, x: where_needed(fn, n, x, groups=3))(need, xs)
    jax.block_until_ready(out)
    np.testing.assert_array_equal(out, np.where(need, xs, 0.0))
    assert seen and np.concatenate(seen).max() < 1000.0


def test_where_needed_maps_a_batch_smaller_than_its_group_as_one_group_of_its_own_size():
    # One pose (a planner's single call) must cost one lane, not a group of 256 copies of it.
    need = jnp.array([True, False, True])
    xs = jnp.arange(3.0)
    seen = []

    def fn(v):
        jax.debug.callback(lambda a: seen.append(np.asarray(a).ravel()), v)
        return v * 2.0

    out = jax.jit(lambda n, x: where_needed(fn, n, x, group_size=256))(need, xs)
    np.testing.assert_array_equal(jax.block_until_ready(out), [0.0, 0.0, 4.0])
    assert sorted(np.concatenate(seen).tolist()) == [0.0, 0.0, 2.0]  # three lanes: two needed, a spare repeating the first


# ---------------------------------------------------------------------------------------------
# (1) Without an object the equilibrium is the PCC shape of eqs. 1-3


@pytest.mark.parametrize("stiffness_ratio", [1.0, 2.0, 0.5])
def test_without_object_the_equilibrium_is_the_pcc_shape(stiffness_ratio):
    f = finger(stiffness_ratio)
    far = circle((500.0, 500.0), 10.0)
    base = jnp.array([3.0, -2.0])
    # Through the estimate (no contact: nothing to solve) ...
    _, mech, _ = both_estimates(f, far, base)
    assert bool(mech.valid) and int(mech.case) == ContactCase.NONE
    np.testing.assert_allclose(np.asarray(mech.joints), np.asarray(pcc_joints(f, base)), atol=1e-4)
    # ... and through the solver itself, from a start far from rest: the spring chain's energy is
    # lowest at the rest turning 2 Theta / N whatever the stiffness profile.
    start = 2 * THETA / N + 0.1 * jnp.sin(jnp.arange(N, dtype=jnp.float32))
    eq = solve_from(f, far, base, jnp.float32(0.0), start)
    assert bool(eq.converged) and int(eq.case) == ContactCase.NONE
    frame = FingerFrame(base, jnp.zeros(()), jnp.ones(()))
    joints = frame.to_world(forward_kinematics(jnp.zeros(2), eq.psi, eq.turning, f.length))
    np.testing.assert_allclose(np.asarray(joints), np.asarray(pcc_joints(f, base)), atol=1e-4)


@functools.partial(jax.jit, static_argnames="mechanics")
def solve_from(finger_, sdf, base, psi, turning, mechanics=MechanicsConfig()):
    frame = FingerFrame(base, jnp.zeros((), base.dtype), jnp.ones((), base.dtype))
    return solve_equilibrium(finger_, sdf, frame, psi, turning, mechanics)


def test_a_solve_that_runs_out_of_steps_is_reported():
    f = finger(2.0)
    sdf = placed(*SCENES["circle_other"])
    rest = jnp.full((N,), 2 * THETA / N)  # the free shape: deep in the object
    starved = solve_from(f, sdf, jnp.zeros(2), jnp.float32(0.0), rest, mechanics=MechanicsConfig(max_steps=1))
    assert not bool(starved.converged)
    # ... and becomes the estimate's status (the geometric failures take precedence).
    _, mech, stage = both_estimates(f, sdf, jnp.zeros(2))
    est = finish(f, stage, eqx.tree_at(lambda e: e.converged, starved, jnp.array(False)))
    assert int(est.status) == Status.MECHANICS_NOT_CONVERGED and not bool(est.valid)
    assert int(mech.status) == Status.OK


def test_a_solve_split_in_phases_is_the_uninterrupted_solve():
    """A batch solves in phases (two iterations in groups, the rest for the fingers that need more):
    start + continue give the uninterrupted solve's point, iteration count and convergence (the
    batch against single estimates: tests/core/test_closing_path.py)."""
    from softgrip_jax._batch import geometric_stages
    from softgrip_jax._mechanics import continue_equilibrium
    from softgrip_jax._stage import stand_in, start_mechanics

    f = FingerModel(LENGTH, 0.7, HALF_THICKNESS, N, stiffness_ratio=2.0)
    disc = SDFGrid.sample(PolygonSDF.regular((25.0, 45.0), 10.0, 64), (-40.0, -40.0), (0.25, 0.25), (480, 480))
    bases = jnp.asarray(np.random.default_rng(5).uniform(-12.0, 12.0, (256, 2)), jnp.float32)
    frames = jax.vmap(FingerFrame.hanging_from)(bases)
    mech, config = MechanicsConfig(), ContactConfig()

    @jax.jit
    def phases(frames):
        fingers, stages = jax.vmap(lambda st: stand_in(f, st))(geometric_stages(f, disc, frames, config, Mechanics()))
        whole = jax.vmap(lambda fi, st: start_mechanics(fi, disc, st, mech, config))(fingers, stages)
        first = jax.vmap(lambda fi, st: start_mechanics(fi, disc, st, mech, config, steps=2))(fingers, stages)
        rest = jax.vmap(lambda fi, st, p: continue_equilibrium(fi, disc, st.frame, p, mech))(fingers, stages, first)
        return whole, first, rest

    whole, first, rest = phases(frames)
    longer = np.asarray(whole.state.steps) > 2
    assert longer.sum() >= 3 and not np.asarray(first.done)[longer].any()  # the continuation is exercised
    assert np.asarray(first.done)[np.asarray(whole.state.steps) <= 2].all()
    np.testing.assert_array_equal(rest.state.steps, whole.state.steps)
    np.testing.assert_array_equal(rest.converged, whole.converged)
    np.testing.assert_allclose(rest.y, whole.y, atol=1e-6)


# ---------------------------------------------------------------------------------------------
# (2) Against the observed-closure rod, and (3) non-penetration

#: Largest joint distance (mm) allowed between the mechanics estimate and the rod. Measured: at most
#: 0.03 mm over these scenes (float32, N = 20 against the rod's 96 segments).
ROD_TOLERANCE_MM = 0.1


@pytest.mark.parametrize("stiffness_ratio, base_compliance", [(1.0, 0.0), (2.0, 0.0)])
@pytest.mark.parametrize("scene", list(SCENES))
def test_mechanics_matches_the_rod_and_beats_the_geometric_estimate_at_the_tip(scene, stiffness_ratio,
                                                                                base_compliance):
    observed = rod_joints(scene, stiffness_ratio, base_compliance)
    sdf = placed(*SCENES[scene])
    geo, mech, _ = both_estimates(finger(stiffness_ratio, base_compliance), sdf, jnp.zeros(2))
    assert bool(mech.valid) and int(mech.status) == Status.OK
    assert int(mech.case) == EXPECTED_CASE[scene], CASE_NAMES[int(mech.case)]
    error = np.linalg.norm(np.asarray(mech.joints, np.float64) - observed, axis=-1)
    geo_error = np.linalg.norm(np.asarray(geo.joints, np.float64) - observed, axis=-1)
    assert error.max() < ROD_TOLERANCE_MM, error.max()
    # The geometric estimate (eq. 9) misses the tip of the same closure by several tenths of a mm
    # or more: ten times the mechanics estimate's error at least.
    assert geo_error[-1] > 0.4 and geo_error[-1] > 10 * error[-1], (geo_error[-1], error[-1])
    # (3) No point of the estimated centreline lies inside r - contact_tol of the object.
    assert clearance(sdf, mech.joints) > -CONTACT_TOL


def test_base_compliance_matches_the_rod():
    observed = rod_joints("circle_other", 1.0, 0.3)
    _, mech, _ = both_estimates(finger(1.0, 0.3), placed(*SCENES["circle_other"]), jnp.zeros(2))
    error = np.linalg.norm(np.asarray(mech.joints, np.float64) - observed, axis=-1)
    assert error.max() < ROD_TOLERANCE_MM and float(mech.psi) < -0.03  # the base turns away
    clamped = rod_joints("circle_other", 1.0, 0.0)
    assert np.linalg.norm(observed[-1] - clamped[-1]) > 10 * error[-1]  # compliance visibly matters


# ---------------------------------------------------------------------------------------------
# The contact case: where the equilibrium carries force, by contact area


class Union(AbstractSDF):
    """Two objects (the smaller of their signed distances: exact outside both)."""

    first: AbstractSDF
    second: AbstractSDF

    def distance(self, points):
        return jnp.minimum(self.first.distance(points), self.second.distance(points))


def station_clearance(finger_, sdf, eq):
    """Each centreline station's distance to the object minus r (mm), base to tip, at ``eq``."""
    problem = _Problem(finger=finger_, sdf=sdf, frame=FingerFrame(jnp.zeros(2), jnp.zeros(()), jnp.ones(())),
                       config=MechanicsConfig())
    _, points = problem.stations(problem.variables(eq.psi, eq.turning))
    return np.asarray(problem.distance(points)) - HALF_THICKNESS


def in_tip_zone(n_stations):
    """Stations within ContactConfig.tip_tolerance links of the tip."""
    return np.arange(n_stations) / (n_stations - 1) >= 1.0 - ContactConfig().tip_tolerance / N


@pytest.mark.parametrize("gap, case", [(0.02, ContactCase.TIP), (-0.2, ContactCase.TIP_AND_OTHER)])
def test_a_second_area_counts_when_it_carries_force_not_when_it_grazes(gap, case):
    f = finger()
    tip_object = placed(*SCENES["circle_tip"])
    _, alone, _ = both_estimates(f, tip_object, jnp.zeros(2))
    assert int(alone.case) == ContactCase.TIP
    # A disc at mid-finger (joint 10, station 30), on the inner side of that equilibrium, ``gap`` mm
    # from the finger's thickness: 0.02 mm (within contact_tol, but it pushes nothing) or pressed
    # 0.2 mm into it (the chain bends around it and the tip stays on the first object).
    joints = np.asarray(alone.joints)
    along = (joints[11] - joints[9]) / np.linalg.norm(joints[11] - joints[9])
    inward = np.array([along[1], -along[0]])
    sdf = Union(tip_object, circle(joints[10] + inward * (HALF_THICKNESS + 3.0 + gap), 3.0))
    eq = solve_from(f, sdf, jnp.zeros(2), alone.psi, alone.turning)
    clear = station_clearance(f, sdf, eq)
    assert bool(eq.converged)
    assert clear[30] < CONTACT_TOL and clear[40:58].min() > CONTACT_TOL  # two areas, apart
    assert int(eq.case) == case, CASE_NAMES[int(eq.case)]


def test_one_area_across_the_edge_of_the_tip_zone_is_a_tip_contact():
    # A wide disc pressed just short of the tip: the finger lies on it over several stations, from
    # before the tip zone into it, with force on stations outside the zone. One contact area that
    # reaches the tip zone, as the rod's case counts it (benchmarks/reproduce_paper.rod_case): TIP,
    # not TIP_AND_OTHER.
    f = finger()
    sdf = placed("circle", 0.97, 20.0, 1.0, 0.0)
    _, mech, _ = both_estimates(f, sdf, jnp.zeros(2))
    eq = solve_from(f, sdf, jnp.zeros(2), mech.psi, mech.turning)
    clear = station_clearance(f, sdf, eq)
    tip_zone = in_tip_zone(clear.size)
    assert bool(eq.converged)
    assert (clear[~tip_zone] < 0).any() and (clear[tip_zone] < CONTACT_TOL).any()
    touching = np.flatnonzero(clear < CONTACT_TOL)
    assert np.all(np.diff(touching) == 1), touching  # one area
    assert int(eq.case) == ContactCase.TIP, CASE_NAMES[int(eq.case)]
    assert int(mech.case) == ContactCase.TIP
    closure = close_rod((0.0, 0.0), THETA, LENGTH, HALF_THICKNESS, sdf)
    rod = np.asarray(closure.in_contact)
    rod_tip_zone = np.arange(rod.size) / (rod.size - 1) >= 1.0 - 0.5 / N
    assert bool(closure.converged) and rod[rod_tip_zone].any() and rod[~rod_tip_zone].any()
    assert np.all(np.diff(np.flatnonzero(rod)) == 1)  # the rod's contact: one area, into the tip zone


# ---------------------------------------------------------------------------------------------
# (4) Gradients by implicit differentiation against central differences (float64)


TIGHT = MechanicsConfig(step_tol=1e-10, max_steps=80)


def mechanics_joints(p, sdf):
    """Joints of the mechanics estimate as a function of p = (Theta, stiffness ratio, base
    compliance, base x, base y), with its case and validity."""
    f = FingerModel(LENGTH, p[0], HALF_THICKNESS, N, stiffness_ratio=p[1], base_compliance=p[2])
    est = estimate(f, sdf, p[3:], estimator=Mechanics(TIGHT))
    return est.joints, est.case, est.valid


@jax.jit
def joints_jvp(p, v, sdf):
    (joints, case, valid), (tangent, _, _) = jax.jvp(lambda q: mechanics_joints(q, sdf), (p,), (v,))
    return joints, tangent, case, valid


@pytest.mark.parametrize("scene", ["circle_other", "circle_tip"])
def test_joint_gradients_match_finite_differences_through_a_contact(x64, scene):
    sdf = placed(*SCENES[scene])
    p0 = jnp.array([THETA, 2.0, 0.2, 0.0, 0.0])
    for i, h in enumerate([1e-6, 1e-6, 1e-6, 1e-5, 1e-5]):
        e = jnp.zeros(5).at[i].set(1.0)
        _, tangent, case, valid = joints_jvp(p0, e, sdf)
        assert bool(valid) and int(case) == EXPECTED_CASE[scene]
        central = (joints_jvp(p0 + h * e, e, sdf)[0] - joints_jvp(p0 - h * e, e, sdf)[0]) / (2 * h)
        scale = float(jnp.max(jnp.abs(central)))
        assert scale > 1e-3  # the joints really move
        np.testing.assert_allclose(np.asarray(tangent), np.asarray(central), rtol=1e-4, atol=1e-5 * scale,
                                   err_msg=f"parameter {i}")


# ---------------------------------------------------------------------------------------------
# (5) Batches: bad candidates are invalid and leave the others unchanged; grasp, score, refine


SQUARE = square((0.0, 30.0), 24.0)
GRID = SDFGrid.sample(SQUARE, origin=(-60.0, -40.0), spacing=(0.5, 0.5), shape=(200, 240))


def batch_bases():
    rng = np.random.default_rng(3)
    good = rng.uniform([-40.0, -25.0], [-10.0, 5.0], (64, 2))
    bases = np.concatenate([good[:10], [[np.nan, 0.0]], good[10:40], [[500.0, 0.0]], good[40:]])
    return jnp.asarray(bases, jnp.float32), np.r_[np.arange(10), np.arange(11, 41), np.arange(42, 66)]


@pytest.mark.parametrize("kind", ["polygon", "grid"])
@pytest.mark.parametrize("handedness", [1.0, -1.0])
def test_closed_form_derivatives_match_autodiff(kind, handedness):
    """The energy's gradient, Hessian, mixed derivative in the base and tip Jacobian in closed form
    (_derivatives) against nested jax.grad / jax.jacfwd of the energy, at an equilibrium pressed
    into a disc (stiffness ratio 2, a compliant base, a turned and mirrored frame)."""
    disc = PolygonSDF.regular((0.0, 38.0), 15.0, 64)
    sdf = disc if kind == "polygon" else SDFGrid.sample(disc, (-60.0, -20.0), (0.3, 0.3), (334, 400))
    finger = FingerModel(LENGTH, 0.7, HALF_THICKNESS, N, stiffness_ratio=2.0, base_compliance=0.2)
    left, right = finger_frames(Gripper(finger, finger, 56.0), jnp.array([2.0, 3.0, 0.15]))
    frame = left if handedness > 0 else right
    @jax.jit  # (eagerly, the solve takes minutes)
    def both(sdf, frame):
        eq = solve_equilibrium(finger, sdf, frame, jnp.array(0.0), jnp.full(N, 2 * 0.7 / N), MechanicsConfig())
        problem = _Problem(finger=finger, sdf=sdf, frame=frame, config=MechanicsConfig())
        y = problem.variables(eq.psi, eq.turning)
        weight = jnp.sqrt(1e4) / LENGTH
        _, index = jax.lax.top_k(HALF_THICKNESS - problem.distance(problem.stations(y)[1]), 6)

        def gradient(y, origin):
            moved = eqx.tree_at(lambda p: p.frame.origin, problem, origin)

            def energy(v):
                c = weight * jnp.maximum(HALF_THICKNESS - moved.distance(moved.stations(v)[1][index]), 0.0)
                return 0.5 * (jnp.sum(v**2) + jnp.sum(c**2))

            return jax.grad(energy)(y)

        origin = frame.origin
        tip = jax.jacfwd(lambda v: frame.to_world(problem.stations(v)[0][-1]))(y)
        references = (jax.jacfwd(gradient, 0)(y, origin), jax.jacfwd(gradient, 1)(y, origin), tip,
                      gradient(y, origin))
        return eq.penetration, _derivatives(problem, y, index), references

    penetration, d, (hessian, mixed, tip, gradient) = both(sdf, frame)
    assert float(penetration) > 0  # stations inside r: the contact terms are exercised
    for ours, reference in [(d.hessian, hessian), (d.mixed, mixed), (d.tip, tip)]:
        np.testing.assert_allclose(ours, reference, atol=1e-5 * float(jnp.max(jnp.abs(reference))))
    # The gradient nearly cancels at equilibrium: y against contact terms of lever arms up to L
    # times the penalty weight, where float32 rounding of a 16-sample grid lookup alone reaches
    # about 1e-4 (in float64 the test passes at atol 1e-4); compiled without XLA's optimisations
    # (make test) the two sums round in another order, and the tip's entry differed by 6.3e-4.
    np.testing.assert_allclose(d.gradient, gradient, atol=1e-3)


@pytest.mark.slow  # compiles the mechanics batch: about 45 s
def test_batch_marks_bad_bases_invalid_and_leaves_the_others_unchanged():
    f = finger(2.0)
    bases, good = batch_bases()
    run = functools.partial(estimate_batch, f, GRID, estimator=Mechanics(), chunk_size=32)
    out = run(bases)
    assert int(out.status[10]) == Status.NON_FINITE_INPUT and int(out.status[41]) == Status.BASE_OUTSIDE_SDF
    assert not bool(out.valid[10]) and not bool(out.valid[41]) and np.isnan(np.asarray(out.joints[10])).all()
    clean = run(bases.at[10].set(bases[0]).at[41].set(bases[0]))
    np.testing.assert_allclose(np.asarray(out.joints)[good], np.asarray(clean.joints)[good], atol=1e-4)
    np.testing.assert_array_equal(np.asarray(out.case)[good], np.asarray(clean.case)[good])
    # The batch covers the cases, solves to convergence, and no valid estimate penetrates.
    valid = np.asarray(out.valid)
    cases = set(np.asarray(out.case)[valid].tolist())
    assert {ContactCase.NONE, ContactCase.TIP, ContactCase.OTHER} <= cases, cases
    assert not (np.asarray(out.status) == Status.MECHANICS_NOT_CONVERGED).any()
    for joints in np.asarray(out.joints)[valid]:
        assert clearance(GRID, joints) > -CONTACT_TOL
    # Without contact the estimate is the PCC shape (eqs. 1-3).
    for i in np.nonzero(valid & (np.asarray(out.case) == ContactCase.NONE))[0]:
        np.testing.assert_allclose(np.asarray(out.joints[i]), np.asarray(pcc_joints(f, bases[i])), atol=1e-4)


GRIPPER = Gripper(left=finger(2.0), right=finger(2.0), base_separation=56.0)
DISC = circle((0.0, 38.0), 15.0)
POSES = jnp.array([[0.0, 0.0, 0.0], [0.0, -3.0, 0.0], [4.0, 1.0, 0.05], [0.0, -60.0, 0.0], [jnp.nan, 0.0, 0.0]])


@pytest.mark.slow  # compiles the mechanics grasp batch and score: about 50 s
def test_grasp_batch_and_score_use_the_mechanics_estimate():
    grasps = estimate_grasp_batch(GRIPPER, DISC, POSES, estimator=Mechanics())
    assert np.asarray(grasps.valid).tolist() == [True, True, True, True, False]
    for hand in (grasps.left, grasps.right):
        assert (np.asarray(hand.case)[:3] != ContactCase.NONE).all()
        for joints in np.asarray(hand.joints)[:4]:
            assert clearance(DISC, joints) > -CONTACT_TOL
    # A disc centred between the fingers: the right finger is the mirrored left one.
    mirrored = np.asarray(grasps.left.joints[0]) * [-1.0, 1.0]
    np.testing.assert_allclose(np.asarray(grasps.right.joints[0]), mirrored, atol=1e-3)

    scored = score(GRIPPER, DISC, POSES, estimator=Mechanics())
    np.testing.assert_allclose(np.asarray(scored.grasp.left.joints)[:4], np.asarray(grasps.left.joints)[:4],
                               atol=1e-4)
    assert np.asarray(scored.valid).tolist() == [True, True, True, True, False]
    assert float(scored.score[0]) > float(scored.score[3])  # closing on the disc beats missing it
    assert not bool(jnp.any(scored.penetrating))


@pytest.mark.slow
def test_refine_with_the_mechanics_estimate():
    refined = refine(GRIPPER, DISC, POSES[2], estimator=Mechanics(), max_steps=3)
    assert int(refined.status) in (RefineStatus.IMPROVED, RefineStatus.NO_IMPROVEMENT, RefineStatus.MAX_STEPS)
    assert float(refined.score.score) >= float(refined.start_score)
    assert bool(refined.score.valid)
