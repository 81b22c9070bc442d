"""Properties of the estimate on random rendered scenes, for both deformation methods.

Each example renders a random object (shape, size, angle, position) with a random seed, turns the
frame into the core's SDF grid through the vision pipeline, draws a finger (Theta, L, r, N) and
BATCH bases around the object, and estimates every base with ``Geometric()`` and
``Mechanics()``. What must hold (tolerances are stated where they are used):

* valid estimates are finite; bases inside the image are never NON_FINITE or BASE_OUTSIDE_SDF;
* every link is L/N long and the chain starts at its base;
* the case agrees with the contact geometry the estimator saw (its own SDF grid):
  - geometric: case none <=> the closing finger (a brute-force sweep, finer than the estimator's)
    never comes within r of the object; tip <=> the first contact is within ``tip_tolerance``
    links of the tip; tip_and_other <=> the circle of Fig. 8 reaches the object within
    Theta_remain (eq. 8-9); the first contact point lies on the object dilated by r;
  - mechanics: the case is what the equilibrium touches (stations within r + contact_tol, at the
    tip or elsewhere), and a finger that never touched during the sweep keeps the PCC shape (none);
* the estimated centreline is not inside the object dilated by r, beyond the stated tolerances,
  where it should not be: in case none (both methods) and in every case for mechanics. The
  geometric cases (b)-(d) are the paper's rules, which do not keep the finger out of the object
  (they turn the free shape about the base), so they are not held to it.

Not a property here: "the sweep touched => the mechanics case is not none". A frictionless tip that
meets the object first can slide off it and close freely; the independent elastic-rod closure
(``synthetic.rod.close_rod``) does the same on such scenes (checked on star_a, N = 5:
the rod ends clear of the object, its tip within 0.14 mm of the mechanics estimate's).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings

from softgrip_jax import ContactCase, Status
from tests.properties._scenes import (CONFIG, MECHANICS, Drawn, dense_points, estimator, graze_tolerance, scenes,
                                      sweep_clearance)

#: Link lengths: float32 rounding of coordinates up to ~100 mm (measured: under 4e-6 mm).
LINK_TOL_MM = 1e-3
#: A threshold compared twice (in the solver and here) may differ by float32 rounding.
ROUNDING_MM = 1e-3


def _distance(drawn: Drawn, points) -> np.ndarray:
    return np.asarray(drawn.sdf.distance(jnp.asarray(points, jnp.float32)))


def _grid_step(drawn: Drawn) -> float:
    return float(np.max(np.asarray(drawn.sdf.spacing)))


def _common(drawn: Drawn, est, method: str) -> np.ndarray:
    """Finite outputs, links of L/N and the base, for valid estimates; returns the valid mask."""
    valid = np.asarray(est.valid)
    status = np.asarray(est.status)
    assert not np.isin(status, [Status.NON_FINITE_INPUT, Status.BASE_OUTSIDE_SDF]).any(), (method, status)
    joints = np.asarray(est.joints)[valid]
    assert np.isfinite(joints).all(), method
    for field in ("s1", "n_g1", "theta_o1", "p_g1", "p_o1"):
        assert np.isfinite(np.asarray(getattr(est.contact, field))[valid]).all(), (method, field)
    assert np.isfinite(np.asarray(est.turning)[valid]).all() and np.isfinite(np.asarray(est.psi)[valid]).all()
    links = np.linalg.norm(np.diff(joints, axis=1), axis=-1)
    h = float(drawn.finger.length) / drawn.finger.n_links
    assert np.abs(links - h).max(initial=0.0) <= LINK_TOL_MM, (method, np.abs(links - h).max())
    assert np.abs(joints[:, 0] - drawn.bases[valid]).max(initial=0.0) <= LINK_TOL_MM, method
    return valid


def _centreline_clearance(drawn: Drawn, joints: np.ndarray) -> np.ndarray:
    """(B,) least sdf - r over 20 points per link of each estimated chain (mm)."""
    dense = dense_points(np.where(np.isfinite(joints), joints, 0.0))
    return _distance(drawn, dense).min(axis=-1) - float(drawn.finger.half_thickness)


def _check_geometric(drawn: Drawn, est, sweep_min: np.ndarray) -> None:
    valid = _common(drawn, est, "geometric")
    finger, c = drawn.finger, est.contact
    n, r = finger.n_links, float(finger.half_thickness)
    case = np.asarray(est.case)
    touches, n_g1 = np.asarray(c.touches), np.asarray(c.n_g1)
    graze = graze_tolerance(finger) + ROUNDING_MM
    # The estimator brackets on its own stations with a parabola between them, clamped by the
    # distance's Lipschitz bound; on a grid it may call a touch up to half a grid step
    # early (and place the contact point within one grid step of the dilated boundary).
    step = _grid_step(drawn)

    none = valid & (case == ContactCase.NONE)
    assert np.array_equal(none, valid & ~touches)
    assert (sweep_min[none] >= -graze).all(), (sweep_min[none].min(), graze)  # case none: never within r
    touched = valid & touches
    assert (sweep_min[touched] <= 0.5 * step).all(), sweep_min[touched].max()  # a touch is a touch
    at_tip = n_g1 >= n - CONFIG.tip_tolerance
    assert (at_tip[valid & (case == ContactCase.TIP)]).all()
    assert (~at_tip[valid & np.isin(case, [ContactCase.OTHER, ContactCase.TIP_AND_OTHER])]).all()
    reaches = np.asarray(c.has_second) & (np.asarray(c.theta_remain) >= np.asarray(c.theta_o1o2))
    assert np.array_equal(valid & touches & ~at_tip & reaches, valid & (case == ContactCase.TIP_AND_OTHER))
    if touched.any():
        p_g1 = np.asarray(c.p_g1)[touched]
        assert np.abs(_distance(drawn, p_g1) - r).max() <= step  # P_g1: on the dilated boundary
        assert np.abs(_distance(drawn, np.asarray(c.p_o1)[touched])).max() <= step  # P_o1: on the surface
    clearance = _centreline_clearance(drawn, np.asarray(est.joints))
    assert (clearance[none] >= -graze).all(), (clearance[none].min(), graze)


def _check_mechanics(drawn: Drawn, est, geometric) -> None:
    valid = _common(drawn, est, "mechanics")
    finger = drawn.finger
    n, r, length = finger.n_links, float(finger.half_thickness), float(finger.length)
    case = np.asarray(est.case)
    joints = np.asarray(est.joints)
    # The case against the contact areas of the estimated chain (solve_equilibrium's rule): an area
    # is a run of stations within r + contact_tol, the tip's when it reaches the tip zone. A case
    # with a tip contact needs a tip area, one with another contact another area, and a chain with
    # no station that close has case none. (Which areas carry force is the solver's and is not
    # recomputed here.)
    per_link = MECHANICS.stations_per_link
    stations = dense_points(np.where(np.isfinite(joints), joints, 0.0), per_link)
    m = n * per_link + 1
    arc = np.linspace(0.0, length, m)
    gap = _distance(drawn, stations) - (r + MECHANICS.contact_tol)  # <= 0: touching
    first_tip = int(np.argmax(arc >= length * (1.0 - CONFIG.tip_tolerance / n)))
    ambiguous = (np.abs(gap) <= ROUNDING_MM).any(axis=-1)
    touching = gap <= 0
    index = np.broadcast_to(np.arange(m), touching.shape)
    next_gap = np.minimum.accumulate(np.where(touching, m, index)[..., ::-1], axis=-1)[..., ::-1]
    tip_area = touching & (next_gap > first_tip)
    has_tip, has_other = tip_area.any(axis=-1), (touching & ~tip_area).any(axis=-1)
    # (Where the closing finger never touched, no equilibrium is solved: a graze within contact_tol
    # of the free shape stays case none, checked below.)
    touched = np.asarray(est.contact.touches)
    check = valid & touched & ~ambiguous
    with_tip = (case == ContactCase.TIP) | (case == ContactCase.TIP_AND_OTHER)
    with_other = (case == ContactCase.OTHER) | (case == ContactCase.TIP_AND_OTHER)
    assert (has_tip[check & with_tip]).all(), case[check & with_tip & ~has_tip]
    assert (has_other[check & with_other]).all(), case[check & with_other & ~has_other]
    assert (case[check & ~touching.any(axis=-1)] == ContactCase.NONE).all()
    # No touch while closing: the spring chain rests in its PCC shape, the geometric case (a).
    free = valid & ~touched
    assert (case[free] == ContactCase.NONE).all()
    assert np.abs(joints[free] - np.asarray(geometric.joints)[free]).max(initial=0.0) <= LINK_TOL_MM
    # Both methods share the first touch (eqs. 5-8).
    both = valid & np.asarray(geometric.valid)
    assert np.allclose(np.asarray(est.contact.s1)[both], np.asarray(geometric.contact.s1)[both], atol=1e-5)
    # Not inside the dilated object: a converged equilibrium keeps its stations within contact_tol
    # of r; between two stations (L / (N stations_per_link) apart) the chain can cut a corner of the
    # dilated object (radius >= r) by spacing^2 / (8 r); the grid lookup adds up to half a step.
    spacing = length / (n * per_link)
    tol = MECHANICS.contact_tol + spacing**2 / (8.0 * r) + 0.5 * _grid_step(drawn) + ROUNDING_MM
    clearance = _centreline_clearance(drawn, joints)
    assert (clearance[valid] >= -tol).all(), (clearance[valid].min(), tol)
    tip_cases = valid & np.isin(case, [ContactCase.TIP, ContactCase.TIP_AND_OTHER])
    if tip_cases.any():  # the tip's foot on the object
        assert np.abs(_distance(drawn, np.asarray(est.contact.p_o2)[tip_cases])).max() <= _grid_step(drawn)


@pytest.mark.slow  # ten drawn scenes, each compiled: about 90 s
@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(scenes())
def test_estimates_are_consistent_with_the_contact_geometry(drawn: Drawn):
    bases = jnp.asarray(drawn.bases)
    geometric = estimator("geometric")(drawn.finger, drawn.sdf, bases)
    mechanics = estimator("mechanics")(drawn.finger, drawn.sdf, bases)
    sweep_min = sweep_clearance(drawn.finger, drawn.sdf, drawn.bases).min(axis=-1)
    _check_geometric(drawn, geometric, sweep_min)
    _check_mechanics(drawn, mechanics, geometric)
