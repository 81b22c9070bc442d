"""Grasp quality (softgrip_jax._quality): planar friction-cone wrenches and the Ferrari-Canny L1 epsilon.

References, none of them the code under test: cases derived by hand (two antipodal contacts on a
disc; Nguyen's two-contact closure condition), scipy's Qhull (``scipy.spatial.ConvexHull``) on the
same wrenches, the shoelace centroid, finite differences for the gradient, and the linear cantilever
(a tip force F = 3 EI delta / L^3) for the mechanics estimate's contact force.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import ConvexHull, QhullError

from softgrip_jax import FingerModel, Geometric, Gripper, Mechanics, PolygonSDF, SDFGrid, ScoreWeights, score
from softgrip_jax._quality import edge_wrenches, epsilon_l1, finger_contacts


def scipy_epsilon(wrenches: np.ndarray) -> float:
    """The L1 epsilon from Qhull's facets: min over facets of the origin's depth, 0 unless inside."""
    try:
        hull = ConvexHull(wrenches)
    except QhullError:  # flat or degenerate: the origin cannot be strictly inside
        return 0.0
    depth = -hull.equations[:, 3]  # n . x + offset <= 0 inside, |n| = 1
    return float(max(depth.min(), 0.0))


def antipodal(mu: float) -> float:
    """Two antipodal contacts on a disc of radius rho about the centroid: by hand, the four edge
    wrenches (-+1, +-mu, +-mu) / sqrt(1 + mu^2) form a tetrahedron whose facets all lie
    mu / sqrt((1 + mu^2)(2 + mu^2)) from the origin."""
    return mu / math.sqrt((1 + mu**2) * (2 + mu**2))


@pytest.mark.parametrize("mu", [0.1, 0.3, 0.5, 1.0, 2.0])
@pytest.mark.parametrize("radius", [5.0, 40.0])
def test_antipodal_contacts_on_a_disc_by_hand(mu, radius) -> None:
    points = jnp.array([[radius, 0.0], [-radius, 0.0]]) + jnp.array([3.0, -7.0])
    normals = jnp.array([[1.0, 0.0], [-1.0, 0.0]])
    w = edge_wrenches(points, normals, jnp.array([True, True]), mu, jnp.array([3.0, -7.0]), radius)
    assert float(epsilon_l1(w)) == pytest.approx(antipodal(mu), rel=1e-5)


@pytest.mark.parametrize(("half_angle", "closure"), [(0.40, True), (0.45, True), (0.48, False), (0.6, False)])
def test_two_contacts_close_when_their_line_lies_inside_both_cones(half_angle, closure) -> None:
    """Nguyen: two frictional point contacts are in force closure iff the line through them lies
    strictly inside both friction cones. On a circle, the chord from angle 0 to angle pi - 2 a makes
    the angle a with the normal at both ends; mu = 0.5 gives the cone's half-angle atan(0.5) = 0.4636."""
    mu = 0.5
    b = math.pi - 2 * half_angle
    points = 10.0 * jnp.array([[1.0, 0.0], [math.cos(b), math.sin(b)]])
    normals = points / 10.0
    w = edge_wrenches(points, normals, jnp.array([True, True]), mu, jnp.zeros(2), 10.0)
    eps = float(epsilon_l1(w))
    assert (eps > 1e-4) == closure
    assert eps == pytest.approx(scipy_epsilon(np.asarray(w, np.float64)), abs=2e-6)


def test_a_contact_that_does_not_touch_changes_nothing_inside_and_opens_the_rest() -> None:
    points = jnp.array([[10.0, 0.0], [-10.0, 0.0], [0.0, 10.0]])
    normals = jnp.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0]])
    two = epsilon_l1(edge_wrenches(points[:2], normals[:2], jnp.array([True, True]), 0.5, jnp.zeros(2), 10.0))
    three_off = epsilon_l1(edge_wrenches(points, normals, jnp.array([True, True, False]), 0.5, jnp.zeros(2), 10.0))
    assert float(three_off) == pytest.approx(float(two), rel=1e-6)
    one = epsilon_l1(edge_wrenches(points, normals, jnp.array([True, False, False]), 0.5, jnp.zeros(2), 10.0))
    assert float(one) == 0.0
    assert float(epsilon_l1(jnp.zeros((6, 3)))) == 0.0


def test_epsilon_equals_qhull_on_random_wrench_sets() -> None:
    """1,000 random sets of 12 wrenches (6 contacts, random normals, points, mu, some not touching):
    the exact triple enumeration against Qhull, in float64 for the comparison's sake and in
    float32 as scored."""
    rng = np.random.default_rng(7)
    run = jax.jit(jax.vmap(lambda p, n, t, mu: epsilon_l1(edge_wrenches(p, n, t, mu, jnp.zeros(2), 12.0))))
    angle = rng.uniform(0, 2 * np.pi, (1000, 6))
    points = 12.0 * np.stack([np.cos(angle), np.sin(angle)], -1) * rng.uniform(0.5, 1.0, (1000, 6, 1))
    normals = np.stack([np.cos(angle), np.sin(angle)], -1)
    normals = normals + rng.normal(0, 0.3, normals.shape)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    touching = rng.uniform(size=(1000, 6)) < 0.8
    mu = rng.uniform(0.1, 1.2, 1000)
    ours = np.asarray(run(jnp.asarray(points, jnp.float32), jnp.asarray(normals, jnp.float32), jnp.asarray(touching),
                          jnp.asarray(mu, jnp.float32)))
    wrenches = np.asarray(jax.vmap(lambda p, n, t, m: edge_wrenches(p, n, t, m, jnp.zeros(2), 12.0))(
        jnp.asarray(points), jnp.asarray(normals), jnp.asarray(touching), jnp.asarray(mu)), np.float64)
    reference = np.array([scipy_epsilon(w) for w in wrenches])
    assert (reference > 0).sum() > 300 and (reference == 0).sum() > 100  # both kinds are exercised
    closed = reference > 1e-3
    np.testing.assert_allclose(ours[closed], reference[closed], rtol=0.01)
    assert np.all(ours[reference == 0] < 1e-4)


def test_epsilon_is_invariant_to_the_order_of_the_contacts() -> None:
    rng = np.random.default_rng(3)
    angle = rng.uniform(0, 2 * np.pi, 5)
    points = 10.0 * np.stack([np.cos(angle), np.sin(angle)], -1)
    normals = points / 10.0
    touching = np.ones(5, bool)
    base = float(epsilon_l1(edge_wrenches(jnp.asarray(points), jnp.asarray(normals), touching, 0.7, jnp.zeros(2), 10.0)))
    order = rng.permutation(5)
    again = float(epsilon_l1(edge_wrenches(jnp.asarray(points[order]), jnp.asarray(normals[order]), touching, 0.7,
                                           jnp.zeros(2), 10.0)))
    assert again == pytest.approx(base, rel=1e-6)


def test_gradient_of_epsilon_matches_finite_differences() -> None:
    with jax.enable_x64(True):
        normals_angle = jnp.array([0.1, math.pi - 0.2, 1.7], jnp.float64)

        def eps(shift):
            a = normals_angle + shift
            n = jnp.stack([jnp.cos(a), jnp.sin(a)], -1)
            return epsilon_l1(edge_wrenches(10.0 * n, n, jnp.array([True, True, True]), 0.6, jnp.zeros(2), 10.0))

        shift = jnp.zeros(3, jnp.float64)
        grad = jax.grad(eps)(shift)
        h = 1e-6
        numeric = jnp.array([(eps(shift.at[i].add(h)) - eps(shift.at[i].add(-h))) / (2 * h) for i in range(3)])
        assert float(eps(shift)) > 0.05
        np.testing.assert_allclose(np.asarray(grad), np.asarray(numeric), rtol=1e-4, atol=1e-8)


def test_mass_properties_of_a_polygon_and_of_its_grid() -> None:
    # An L-shaped hexagon: the shoelace centroid by hand, (area-weighted rectangles 4x1 and 1x3).
    ell = PolygonSDF(jnp.array([[0.0, 0.0], [4.0, 0.0], [4.0, 1.0], [1.0, 1.0], [1.0, 3.0], [0.0, 3.0]]))
    centroid, rho = ell.mass_properties()
    # rectangles [0,4]x[0,1] (area 4, centre (2, .5)) and [0,1]x[1,3] (area 2, centre (.5, 2))
    expected = (4 * np.array([2.0, 0.5]) + 2 * np.array([0.5, 2.0])) / 6
    np.testing.assert_allclose(np.asarray(centroid), expected, atol=1e-6)
    assert float(rho) == pytest.approx(np.max(np.linalg.norm(np.asarray(ell.vertices) - expected, axis=1)), rel=1e-6)
    disc = PolygonSDF.regular((3.0, -2.0), 10.0, 256)
    grid = SDFGrid.sample(disc, origin=(-12.0, -17.0), spacing=(0.25, 0.25), shape=(121, 121))
    c, r = grid.mass_properties()
    np.testing.assert_allclose(np.asarray(c), [3.0, -2.0], atol=0.02)
    assert float(r) == pytest.approx(10.0, abs=0.25)


def test_finger_contacts_on_a_disc() -> None:
    """Stations along a straight line tangent to a disc (offset r + 0.1): the run holding the
    tangent point touches, its contact point lies on the circle and its normal is radial."""
    disc = PolygonSDF.regular((0.0, 0.0), 10.0, 512)
    y = jnp.linspace(-30.0, 30.0, 61)
    stations = jnp.stack([jnp.full_like(y, 13.1), y], -1)  # r = 3: 0.1 mm clear at y = 0
    c, station = finger_contacts(disc, stations, jnp.asarray(3.0), jnp.asarray(0.25))
    assert int(station[1]) == 30
    assert c.touching.tolist() == [False, True, False]
    np.testing.assert_allclose(np.asarray(c.points[1]), [10.0, 0.0], atol=2e-3)
    np.testing.assert_allclose(np.asarray(c.normals[1]), [1.0, 0.0], atol=1e-3)
    assert np.all(np.isnan(np.asarray(c.forces)))  # no forces without the mechanics estimate
    tight, _ = finger_contacts(disc, stations, jnp.asarray(3.0), jnp.asarray(0.05))
    assert not bool(jnp.any(tight.touching))


@pytest.mark.parametrize("side", [0, 1], ids=["left", "right"])
def test_mechanics_contact_force_against_the_linear_cantilever(side) -> None:
    """A nearly straight finger (Theta = 0.02 rad) closing onto a flat wall that stops its tip
    delta = 0.3 mm short of its free closure: a cantilever with a tip load, F = 3 EI delta / L^3,
    i.e. 3 delta / L in units of EI / L^2, along the wall's normal (frictionless). The right finger
    (mirrored) against a wall on its side: the same force, mirrored."""
    length, theta, r = 52.0, 0.02, 1.0
    finger = FingerModel(length=length, theta_entire=theta, half_thickness=r, n_links=20)
    gripper = Gripper(left=finger, right=finger, base_separation=200.0)
    free_tip_x = length * math.sin(theta) ** 2 / theta  # PCC: chord L sin(Theta)/Theta at the angle Theta
    delta = 0.3
    face = -100.0 + free_tip_x + r - delta  # the left finger's base is at x = -100
    wall = np.array([[face, 0.0], [face + 60.0, 0.0], [face + 60.0, 200.0], [face, 200.0]])
    if side == 1:
        wall[:, 0] = -wall[:, 0]
    result = score(gripper, PolygonSDF(jnp.asarray(wall)), jnp.array([[0.0, 0.0, 0.0]]), estimator=Mechanics())
    touching = np.asarray(result.contacts.touching[0, side])
    forces = np.asarray(result.contacts.forces[0, side])
    assert touching[-1] and not np.asarray(result.contacts.touching[0, 1 - side]).any()
    total = forces[touching].sum(axis=0)
    expected = 3 * delta / length * (1 if side == 0 else -1)  # on the wall: along its inward normal
    assert total[0] == pytest.approx(expected, rel=0.03)
    assert abs(total[1]) < 0.02 * abs(expected)
    # The geometric estimate has no forces.
    geometric = score(gripper, PolygonSDF(jnp.asarray(wall)), jnp.array([[0.0, 0.0, 0.0]]), estimator=Geometric())
    assert np.all(np.isnan(np.asarray(geometric.contacts.forces)))


@pytest.mark.parametrize("direction", [0.1, 0.785, 1.4])
def test_a_contact_on_a_corner_takes_the_normal_the_finger_pushes_along(direction) -> None:
    """At a square's corner the object has a range of normals (from one face's to the other's). A
    finger station r + 0.05 mm off the corner along a direction within that range touches it along
    that very direction: the contact point is the corner and the normal points at the station."""
    square = PolygonSDF(jnp.array([[-10.0, -10.0], [10.0, -10.0], [10.0, 10.0], [-10.0, 10.0]]))
    corner = jnp.array([10.0, 10.0])
    unit = jnp.array([math.cos(direction), math.sin(direction)])  # between +x (0) and +y (pi/2)
    station = corner + 3.05 * unit
    stations = jnp.stack([station + 20.0 * unit + jnp.array([-60.0, 0.0]), station, station + 20.0 * unit])
    c, _ = finger_contacts(square, stations, jnp.asarray(3.0), jnp.asarray(0.25))
    assert c.touching.tolist() == [False, True, False]
    np.testing.assert_allclose(np.asarray(c.normals[1]), np.asarray(unit), atol=1e-4)
    np.testing.assert_allclose(np.asarray(c.points[1]), np.asarray(corner), atol=1e-3)


def test_closure_margin_is_the_epsilon_inside_and_minus_the_distance_outside() -> None:
    """Against independent references: Qhull's facets where the origin is inside the hull, the
    origin's distance to the hull from scipy's SLSQP (min |sum l_i w_i|, l on the simplex) outside."""
    from scipy.optimize import minimize
    from scipy.spatial import ConvexHull

    from softgrip_jax._quality import closure_margin

    rng = np.random.default_rng(11)
    inside = outside = 0
    for _ in range(60):
        w = (rng.normal(size=(12, 3)) + rng.normal(size=3) * rng.uniform(0.0, 2.0)).astype(np.float32)
        active = rng.uniform(size=12) < 0.8
        active[:3] = True
        p = w[active].astype(np.float64)
        k = len(p)
        fit = minimize(lambda lam: np.sum((lam @ p) ** 2), np.full(k, 1.0 / k), method="SLSQP", bounds=[(0, 1)] * k,
                       constraints=[{"type": "eq", "fun": lambda lam: lam.sum() - 1.0}],
                       options={"ftol": 1e-14, "maxiter": 500})
        distance = float(np.sqrt(fit.fun))
        if distance > 1e-4:
            reference, outside = -distance, outside + 1
        else:
            reference, inside = float(np.min(-ConvexHull(p).equations[:, 3])), inside + 1
        got = float(closure_margin(jnp.asarray(w), jnp.asarray(active)))
        assert got == pytest.approx(reference, abs=1e-4, rel=1e-3)
        if reference > 0:
            assert got == pytest.approx(float(epsilon_l1(jnp.asarray(np.where(active[:, None], w, 0.0)))), abs=1e-5)
    assert inside >= 5 and outside >= 5
