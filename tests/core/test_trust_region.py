"""The mechanics solve's trust region (softgrip_jax._mechanics.ChainGaussNewton.step).

Fingers whose tip slides over a corner (a star's point, a square's corner) lose the
plain Gauss-Newton iteration: past the fold its model is poor and the steps wander, raising the
energy tenfold, until the budget is spent (``mechanics_not_converged``). With the trust region the
solve descends the energy and lands where the independent rod's quasi-static closure lands
(synthetic.rod: a finer rod, BFGS with an augmented Lagrangian, its object exact).
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from softgrip_jax import FingerModel, MechanicsConfig, PolygonSDF, Status, estimate_batch
from softgrip_jax._mechanics import _STRETCH_MAX, ChainGaussNewton, _initial_state, _Problem, _residual_fn
from softgrip_jax._frames import FingerFrame
from synthetic.rod import close_rod, observed_joints
from synthetic.shapes import shape

LENGTH, HALF_THICKNESS, N = 52.0, 4.0, 20


def outline(name):
    """The shape, 30 mm across, turned 0.3 rad, centred at (25, 45) mm."""
    return shape(name, 30.0, 0.3) + np.array([25.0, 45.0])


def sampled(polygon):
    """The polygon on a 0.4 mm grid (the image's SDF stands in for it)."""
    return PolygonSDF(vertices=jnp.asarray(polygon, jnp.float32)).to_grid(cell_mm=0.4)


# (shape, Theta, base mm): each one the plain iteration left not converged (checked once, on the
# tree before the trust region); their closures are ordinary, the rod converges on every one.
LOST = [
    ("square", 0.8, (7.7141, 12.3405)),
    ("star_a", 0.8, (-0.5871, 9.2437)),
    ("rounded_rect", 0.55, (5.2308, -4.1025)),
]


@pytest.mark.parametrize("name, theta, base", LOST, ids=[case[0] for case in LOST])
def test_a_finger_sliding_over_a_corner_converges_where_the_rod_closes(name, theta, base):
    polygon = outline(name)
    finger = FingerModel(length=LENGTH, theta_entire=theta, half_thickness=HALF_THICKNESS, n_links=N)
    est = estimate_batch(finger, sampled(polygon), np.array([base], np.float32))
    closure = close_rod(base, theta, LENGTH, HALF_THICKNESS, PolygonSDF(vertices=jnp.asarray(polygon)))
    assert bool(closure.converged)
    assert int(est.status[0]) == Status.OK
    rod_tip = np.asarray(observed_joints(closure, N))[-1]
    assert np.linalg.norm(np.asarray(est.joints[0, -1]) - rod_tip) < 0.1


def test_a_step_that_raises_the_energy_is_undone_and_the_region_shrinks():
    """Hand-made state: the anchor's energy is E(anchor), the model predicted a fall of 1, and the
    current point (the step's end; the object far away) has a higher energy than the anchor. The step goes back to the
    anchor, keeps its energy and shrinks the region to a quarter of the step's reach; a step whose
    energy fell as predicted is kept and leaves the region as it was."""
    finger = FingerModel(length=LENGTH, theta_entire=0.6, half_thickness=HALF_THICKNESS, n_links=N)
    problem = _Problem(finger=finger, sdf=PolygonSDF.regular((90.0, 30.0), 10.0, 64),
                       frame=FingerFrame.hanging_from(jnp.zeros(2)), config=MechanicsConfig())
    solver = ChainGaussNewton(rtol=0.05, atol=0.01)
    anchor = jnp.zeros(N + 1)
    worse = anchor.at[3].set(2.0)  # springs stretched: energy 2.0 above the anchor's 0
    region = lambda s: (s.anchor_energy, s.predicted, s.reach, s.shift)  # noqa: E731
    state = eqx.tree_at(region, _initial_state(anchor, problem.n_stations),
                        tuple(jnp.asarray(v) for v in (0.0, 1.0, 4.0, 1.0)))
    y, after, _ = solver.step(_residual_fn, worse, problem, {}, state, None)
    assert np.array_equal(np.asarray(y), np.asarray(anchor))
    assert float(after.anchor_energy) == 0.0
    assert float(after.stretch) == pytest.approx(1.0)  # 0.25 of the reach 4
    assert not np.isfinite(float(after.moved))  # a rejected step never counts toward convergence

    fell = eqx.tree_at(lambda s: s.anchor_energy, state, jnp.asarray(2.5))  # fell by 0.5 of 1 predicted
    y, after, _ = solver.step(_residual_fn, worse, problem, {}, fell, None)
    assert not np.array_equal(np.asarray(y), np.asarray(anchor))
    assert float(after.anchor_energy) == pytest.approx(2.0)
    assert float(after.stretch) == _STRETCH_MAX
