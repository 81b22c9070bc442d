"""First contact against geometry derived by hand and against a dense sweep written with numpy."""

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from softgrip_jax import ContactCase, ContactConfig, FingerModel, PolygonSDF, SDFGrid
from softgrip_jax import predict_contact as _predict_contact

predict_contact = eqx.filter_jit(_predict_contact)

L, R_FINGER = 50.0, 3.0


def circle(center, radius):
    return PolygonSDF.regular(center, radius, n_vertices=720)


@pytest.mark.parametrize("center, radius", [((14.0, 30.0), 6.0), ((20.0, 25.0), 10.0)])
def test_rigid_sweep_first_contact_is_the_tangent_angle(center, radius):
    """A straight finger rotating about its base touches a circle when its line is tangent.

    Distance from the centre C to the finger's line at angle s is cx cos s - cy sin s
    = rho cos(s + phi0); it equals R + r at s1 = acos((R + r) / rho) - phi0.
    """
    cx, cy = center
    rho, phi0 = math.hypot(cx, cy), math.atan2(cy, cx)
    s1 = math.acos((radius + R_FINGER) / rho) - phi0
    u = np.array([math.sin(s1), math.cos(s1)])
    foot = (cx * u[0] + cy * u[1]) * u  # closest point of the line to C
    assert 0 < np.linalg.norm(foot) < L  # the tangent point lies on the finger, not beyond the tip
    p_o1 = np.array(center) + radius * (foot - center) / np.linalg.norm(foot - center)

    finger = FingerModel(length=L, theta_entire=0.9, half_thickness=R_FINGER, n_links=10)
    c = predict_contact(finger, circle(center, radius), jnp.zeros(2), ContactConfig(sweep="rigid"))
    assert bool(c.touches) and not bool(c.initial_overlap)
    assert float(c.s1) == pytest.approx(s1, abs=1e-3)
    # The same circle sampled on a grid of 0.25 mm (the fast path for batches): the same contact.
    on_grid = predict_contact(finger, circle(center, radius).to_grid(margin_mm=32.0), jnp.zeros(2),
                              ContactConfig(sweep="rigid"))
    assert float(on_grid.s1) == pytest.approx(s1, abs=1e-3)
    assert float(on_grid.s1) == pytest.approx(float(c.s1), abs=1e-4)
    np.testing.assert_allclose(on_grid.p_o1, c.p_o1, atol=0.01)
    np.testing.assert_allclose(c.p_g1, foot, atol=0.1)
    np.testing.assert_allclose(c.p_o1, p_o1, atol=0.1)
    assert float(c.l_g1) == pytest.approx(np.linalg.norm(foot), abs=0.1)  # eq. 6
    assert float(c.n_g1) == pytest.approx(np.linalg.norm(foot) / L * 10, abs=0.02)  # eq. 7
    # Theta_o1 is the angle of P_base -> P_g1 (the centreline against the object dilated by r).
    assert float(c.theta_o1) == pytest.approx(math.atan2(foot[0], foot[1]), abs=2e-3)


def dense_first_contact(distance, theta, n, length, r, base=(0.0, 0.0), n_s=4001, per_link=200, between=None):
    """Independent brute force: chains of eq. 2 from ``base``, links sampled densely, the object's
    exact ``distance`` (numpy, points (M, 2) -> (M,) mm), at ``n_s`` values of s over ``between``
    (lo, hi) rad (default (0, theta)), lo excluded. Returns (s1 rad, the first point touching,
    its arc length from the base mm), or None when nothing touches up to ``theta``."""
    i = np.arange(n + 1)
    t = np.linspace(0, 1, per_link, endpoint=False)
    lo, hi = between or (0.0, theta)
    for s in np.linspace(lo, hi, n_s)[1:]:
        chord = (length / n) * np.sin(s * i / n) / np.sin(s / n)
        joints = np.stack([chord * np.sin(s * i / n), chord * np.cos(s * i / n)], -1) + np.asarray(base)
        pts = (joints[:-1, None] + t[None, :, None] * (joints[1:] - joints[:-1])[:, None]).reshape(-1, 2)
        pts = np.concatenate([pts, joints[-1:]])
        gap = distance(pts) - r
        if gap.min() <= 0:
            k = int(np.argmin(gap))
            return s, pts[k], k / (per_link * n) * length
    return None


@pytest.mark.parametrize("n, tol_s, tol_mm", [(10, 1e-3, 0.05), (20, 2e-3, 0.08)])  # 2.5 mm station spacing
@pytest.mark.parametrize("sdf_kind", ["polygon", "grid"])
@pytest.mark.parametrize("center, radius", [((16.0, 32.0), 7.0), ((9.0, 20.0), 4.0), ((36.0, 42.0), 9.0)])
def test_pcc_sweep_first_contact_matches_dense_sweep(sdf_kind, center, radius, n, tol_s, tol_mm):
    theta = 0.8
    expected = dense_first_contact(lambda p: np.linalg.norm(p - np.array(center), axis=1) - radius, theta, n, L,
                                   R_FINGER)
    assert expected is not None
    s1, p_g1, l_g1 = expected
    sdf = circle(center, radius)
    if sdf_kind == "grid":
        exact = lambda p: jnp.linalg.norm(p - jnp.asarray(center), axis=-1) - radius
        sdf = SDFGrid.sample(exact, origin=(-20.0, -10.0), spacing=(0.2, 0.2), shape=(400, 400))
    finger = FingerModel(length=L, theta_entire=theta, half_thickness=R_FINGER, n_links=n)
    c = predict_contact(finger, sdf, jnp.zeros(2))
    assert float(c.s1) == pytest.approx(s1, abs=tol_s)
    np.testing.assert_allclose(c.p_g1, p_g1, atol=tol_mm)
    assert float(c.l_g1) == pytest.approx(l_g1, abs=tol_mm)


def polygon_distance(points, vertices):
    """Unsigned distance (mm) from points (P, 2) to a polygon's edges, by numpy (outside points)."""
    a, b = vertices, np.roll(vertices, -1, axis=0)
    ap = points[:, None, :] - a[None]
    t = np.clip(np.sum(ap * (b - a), -1) / np.sum((b - a) ** 2, -1), 0.0, 1.0)
    return np.min(np.linalg.norm(ap - t[..., None] * (b - a), axis=-1), axis=1)


def square_near_the_finger():
    from synthetic.shapes import shape

    return shape("square", 20.0, 0.3) + np.array([22.0, 48.0])


@pytest.mark.parametrize("vertices, theta, base", [
    # The sweep passes a square's corner: within one interval of the coarse grid the clearance
    # falls below zero and rises again, and a plain Newton step from the interval's far end left
    # it (ROOT_NOT_CONVERGED for about 1 in 500 random bases near this square).
    (square_near_the_finger(), 0.7, (-7.378, -7.336)),
    (square_near_the_finger(), 0.7, (-3.602, -9.166)),
    (square_near_the_finger(), 0.7, (-9.952, -5.649)),
    # A root met to float precision: the last Newton step rounds onto the bracket's end, which
    # must count as inside it (it was replaced by a bisection and ran out of steps).
    (np.asarray(PolygonSDF.regular((24.0, 44.0), 10.0, 64).vertices), 0.8, (1.8815513, -3.2346227)),
])
def test_the_first_contact_root_converges_inside_its_bracket(vertices, theta, base):
    finger = FingerModel(length=52.0, theta_entire=theta, half_thickness=4.0, n_links=20)
    c = predict_contact(finger, PolygonSDF(jnp.asarray(vertices, jnp.float32)), jnp.asarray(base, jnp.float32))
    assert bool(c.touches) and bool(c.root_converged)
    # The polygon's unsigned distance: the finger is outside it until the first touch.
    distance = lambda p: polygon_distance(p, np.asarray(vertices, np.float64))  # noqa: E731
    # Two levels (s steps of theta / 1400, then of theta / 1400^2 in the step that touches first): a
    # touch the coarse level misses can only move the reference later, failing the test, not passing it.
    coarse = dense_first_contact(distance, theta, 20, 52.0, 4.0, base=base, n_s=1401, per_link=50)
    step = theta / 1400
    expected = dense_first_contact(distance, theta, 20, 52.0, 4.0, base=base, n_s=1401, per_link=50,
                                   between=(coarse[0] - step, coarse[0]))
    assert float(c.s1) == pytest.approx(expected[0], abs=2e-3)


def test_no_object_in_reach_is_case_a():
    finger = FingerModel(length=L, theta_entire=0.5, half_thickness=R_FINGER, n_links=10)
    base = jnp.array([3.0, -2.0])
    c = predict_contact(finger, circle((60.0, 25.0), 5.0), base)
    assert not bool(c.touches) and int(c.case) == ContactCase.NONE
    assert float(c.s1) == pytest.approx(0.5)
    # Undefined contact fields describe the closed finger's tip: N links of L/N on a circle (eqs.
    # 1-3), so at (L/N) sin(T) / sin(T/N) from the base along the chord angle T.
    tip = np.array(base) + L / 10 * np.sin(0.5) / np.sin(0.05) * np.array([np.sin(0.5), np.cos(0.5)])
    np.testing.assert_allclose(c.p_g1, tip, atol=1e-3)
    np.testing.assert_allclose(c.p_o2, tip, atol=1e-3)
    assert float(c.n_g1) == 10.0 and not bool(c.has_second)


def test_object_overlapping_the_open_finger_is_flagged():
    finger = FingerModel(length=L, theta_entire=0.5, half_thickness=R_FINGER, n_links=10)
    c = predict_contact(finger, circle((2.0, 25.0), 4.0), jnp.zeros(2))
    assert bool(c.initial_overlap) and float(c.s1) == 0.0
    assert int(c.case) == ContactCase.NONE  # the pose collides: no deformation is predicted


@pytest.mark.parametrize("n_links, sweep", [(10, "pcc"), (20, "pcc"), (4, "rigid")])
def test_bracket_in_two_parts_equals_the_whole_grid(n_links, sweep):
    # Batched code brackets the grid's first part for every finger and its second part only for
    # the fingers still free: every field must be the one-pass bracket's (the grid values to
    # rounding: XLA computes the sines of 6 and of 12 rows in differently vectorised loops).
    import jax

    from softgrip_jax._contact import bracket_contact, sweep_parts

    config = ContactConfig(sweep=sweep)
    first, second = sweep_parts(config)
    assert first == (0, 6) and second == (5, 12)
    assert sweep_parts(ContactConfig(n_sweep=5)) is None  # too short to split
    finger = FingerModel(length=L, theta_entire=0.6, half_thickness=R_FINGER, n_links=n_links)
    disc = circle((20.0, 30.0), 8.0)
    xs, ys = np.meshgrid(np.linspace(-45.0, 15.0, 31), np.linspace(-25.0, 10.0, 15))
    bases = jnp.asarray(np.stack([xs.ravel(), ys.ravel()], axis=1), jnp.float32)

    def parts(base):
        dist = lambda q: disc.distance(q + base)  # noqa: E731
        whole = bracket_contact(finger, dist, config)
        early = bracket_contact(finger, dist, config, first)
        late = bracket_contact(finger, dist, config, second)
        joined = jax.tree_util.tree_map(lambda a, b: jnp.where(early.touches, a, b), early, late)
        return whole, joined, early.touches

    whole, joined, early = jax.jit(jax.vmap(parts))(bases)
    for name in ("touches", "initial_overlap", "first"):
        np.testing.assert_array_equal(getattr(joined, name), getattr(whole, name), err_msg=name)
    for name in ("lower", "upper", "start"):
        np.testing.assert_allclose(getattr(joined, name), getattr(whole, name), rtol=0, atol=1e-6, err_msg=name)
    # The scene exercises both parts: touches in the first, only in the second, and none.
    late_only = np.asarray(whole.touches & ~early)
    assert np.asarray(early).sum() > 20 and late_only.sum() > 20 and (~np.asarray(whole.touches)).sum() > 20


class _CubicEverywhere(SDFGrid):
    """The same grid, its coarse sweep read with the bicubic lookup too (the reference)."""

    def coarse_distance(self, points):
        return self.distance(points)


def test_a_bilinear_coarse_sweep_finds_the_contact_the_bicubic_one_does():
    # A grid sampled coarsely (1 mm cells) from a disc, so that the two lookups differ by more than
    # they do on a camera's grid; 400 bases around it, touching, grazing and missing.
    exact = lambda p: jnp.linalg.norm(p - jnp.asarray([20.0, 34.0]), axis=-1) - 9.0  # noqa: E731
    grid = SDFGrid.sample(exact, origin=(-40.0, -30.0), spacing=(1.0, 1.0), shape=(110, 110))
    reference = _CubicEverywhere(grid.values, grid.origin, grid.spacing)
    finger = FingerModel(length=52.0, theta_entire=0.8, half_thickness=4.0, n_links=20)
    bases = np.random.default_rng(3).uniform([-14.0, -12.0], [8.0, 8.0], (400, 2)).astype(np.float32)
    import jax

    run = jax.jit(jax.vmap(lambda sdf, b: _predict_contact(finger, sdf, b), in_axes=(None, 0)))
    fast, ref = run(grid, jnp.asarray(bases)), run(reference, jnp.asarray(bases))
    assert bool(jnp.all(fast.root_converged))
    assert 100 < int(jnp.sum(ref.touches & ~ref.initial_overlap)) < 390  # both kinds are present
    same = np.asarray(fast.touches == ref.touches) & np.asarray(fast.initial_overlap == ref.initial_overlap)
    assert same.mean() >= 0.99  # a graze of micrometres may flip; nothing else
    both = same & np.asarray(ref.touches & ~ref.initial_overlap)
    np.testing.assert_allclose(np.asarray(fast.s1)[both], np.asarray(ref.s1)[both], atol=2e-4)
    np.testing.assert_array_equal(np.asarray(fast.case)[both], np.asarray(ref.case)[both])
    # The second contact's circle is scanned with the bilinear lookup and its chosen crossing
    # placed with the bicubic one: the same crossing, at the same angle.
    # (A circle tangent to the object within the two lookups' difference may gain or lose its
    # crossing, as a graze may flip the touch: on this deliberately coarse grid, 1 % at most.)
    assert (np.asarray(fast.has_second) == np.asarray(ref.has_second))[both].mean() >= 0.99
    second = both & np.asarray(ref.has_second) & np.asarray(fast.has_second)
    assert second.sum() > 50
    # Where the two lookups put a crossing on either side of a sample, the fine placement is
    # clipped to the coarse interval's end: within 5 mrad on this grid of 1 mm cells (the lookups'
    # difference, and so this, shrinks with the cell's square), and nearly always far closer.
    gap = np.abs(np.asarray(fast.theta_o1o2) - np.asarray(ref.theta_o1o2))[second]
    assert gap.max() <= 5e-3 and np.median(gap) <= 1e-5


def test_the_root_converges_when_the_bracket_end_is_still_free():
    # A bracket whose upper end the coarse lookup saw touching and the fine one sees free (here
    # made by hand: the upper end moved just short of the true root): the root finder's function
    # is tilted to cross zero inside the bracket, converges, and lands at that end.
    from softgrip_jax._contact import bracket_contact, refine_contact

    finger = FingerModel(length=L, theta_entire=0.8, half_thickness=R_FINGER, n_links=10)
    disc = circle((16.0, 32.0), 7.0)
    true = predict_contact(finger, disc, jnp.zeros(2))
    bracket = bracket_contact(finger, disc.distance)
    short = eqx.tree_at(lambda b: (b.upper, b.start), bracket, (true.s1 - 1e-3, true.s1 - 2e-3))
    c = eqx.filter_jit(refine_contact)(finger, disc.distance, short)
    assert bool(c.root_converged)
    assert float(short.lower) <= float(c.s1) <= float(short.upper) + 1e-6
    assert float(c.s1) == pytest.approx(float(short.upper), abs=2e-4)


def test_fingers_whose_root_takes_longer_reach_the_root_brent_finds():
    # The batch runs the first ROOT_STEPS_TOGETHER root iterations for every touching finger at
    # once and continues only the unconverged ones (finish_root). Those must end where an
    # independent solver (scipy's Brent method, in float64 on the same function) puts the root.
    import jax
    from scipy.optimize import brentq

    from softgrip_jax._contact import (ROOT_STEPS_TOGETHER, bracket_contact, finish_root, root_function,
                                       start_root)

    xs = np.arange(-40.0, 80.0, 0.25)
    x, y = np.meshgrid(xs, xs, indexing="xy")
    grid = SDFGrid(values=jnp.asarray((np.hypot(x - 25.0, y - 45.0) - 10.0).astype(np.float32)),
                   origin=jnp.array([-40.0, -40.0]), spacing=jnp.array([0.25, 0.25]))
    finger = FingerModel(length=52.0, theta_entire=0.7, half_thickness=4.0, n_links=20)
    config = ContactConfig()
    bases = jnp.asarray(np.random.default_rng(0).uniform(-12.0, 12.0, (400, 2)).astype(np.float32))

    def solve(base):
        dist = lambda q: grid.distance(q + base)  # noqa: E731
        bracket = bracket_contact(finger, lambda q: grid.coarse_distance(q + base), config)
        started = start_root(finger, dist, bracket, config)
        finished = finish_root(finger, dist, bracket, config, started)
        return bracket, started, finished

    brackets, started, finished = jax.jit(jax.vmap(solve))(bases)
    need = np.asarray(jax.vmap(lambda b: b.needs_root)(brackets))
    late = np.flatnonzero(need & ~np.asarray(jax.vmap(lambda r: r.converged(config))(started)))
    assert len(late) >= 5  # fingers that the shared steps leave unconverged exist here
    assert bool(jnp.all(jax.vmap(lambda r: r.converged(config))(finished)[need]))
    for i in late[:10]:
        take = lambda t: jax.tree_util.tree_map(lambda a: a[i], t)  # noqa: E731
        bracket, search = take(brackets), take(finished)
        fn = jax.jit(root_function(finger, lambda q: grid.distance(q + bases[i]), bracket, config, search))
        g = lambda s: float(fn(jnp.float32(s)))  # noqa: E731
        assert g(float(bracket.lower)) > 0 >= g(float(bracket.upper))  # the bracket holds a sign change
        reference = brentq(g, float(bracket.lower), float(bracket.upper), xtol=1e-7)
        # (A non-monotone clearance can hold several roots: then the solver's must be one of them.)
        assert abs(float(search.s) - reference) <= 2 * config.root_atol or abs(g(float(search.s))) <= config.root_atol
    assert ROOT_STEPS_TOGETHER < config.root_max_steps
