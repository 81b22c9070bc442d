"""A polygon's edges indexed by cells: the same signed distance as every edge read, from OpenCV's
pointPolygonTest (an independent reference) and from a regular polygon's distances derived by hand."""

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softgrip_jax import PolygonSDF, SoftgripError, score
from softgrip_jax._polygon_cells import EXACT_DEPTH_MM, MARGIN_MM


def star(rng, n, center=(0.0, 38.0)):
    """A simple, star-shaped (concave) polygon of n vertices, radii 6-18 mm."""
    angles = np.sort(rng.uniform(0, 2 * np.pi, n))
    radii = rng.uniform(6.0, 18.0, n)
    return np.stack([center[0] + radii * np.cos(angles), center[1] + radii * np.sin(angles)], -1)


def points_around(vertices, rng, count, spread):
    """Points scattered about the outline (Gaussian, ``spread`` mm) and over the table's area."""
    near = vertices[rng.integers(0, len(vertices), count)] + rng.normal(0.0, spread, (count, 2))
    low, high = vertices.min(0) - MARGIN_MM, vertices.max(0) + MARGIN_MM
    return np.concatenate([near, rng.uniform(low, high, (count, 2))])


@pytest.mark.parametrize("shape", ["disc128", "star40", "star200"])
def test_the_cells_read_the_distance_opencv_reads(shape):
    rng = np.random.default_rng(3)
    if shape == "disc128":
        vertices = np.asarray(PolygonSDF.regular((0.0, 38.0), 15.0, 128).vertices, np.float64)
    else:
        vertices = star(rng, int(shape[4:]))
    polygon = PolygonSDF(vertices)
    assert polygon.cells is not None
    points = points_around(vertices, rng, 3000, 2.0)
    got = np.asarray(jax.jit(lambda s, p: s.distance(p))(polygon, jnp.asarray(points)), np.float64)
    contour = vertices.astype(np.float32).reshape(-1, 1, 2)
    # pointPolygonTest: positive inside; the project's: negative inside.
    want = -np.array([cv2.pointPolygonTest(contour, (float(x), float(y)), True) for x, y in points])
    exact = want > -EXACT_DEPTH_MM
    np.testing.assert_allclose(got[exact], want[exact], atol=2e-4)
    # Deeper inside, a cell may keep only its nearest candidates: never shallower, always inside.
    assert np.all(got[~exact] <= want[~exact] + 2e-4) and np.all(got[~exact] < 0)


def test_a_regular_polygon_reads_the_distances_derived_by_hand():
    # A regular 64-gon of circumradius R: along a vertex's direction the nearest point is the vertex
    # (rho - R); along an edge's middle, the edge at the apothem R cos(pi / 64) (negative inside).
    n, radius = 64, 12.0
    polygon = PolygonSDF.regular((0.0, 0.0), radius, n)
    assert polygon.cells is not None
    apothem = radius * np.cos(np.pi / n)
    rho = np.linspace(apothem - 1.5, radius + 15.0, 40)
    vertex = np.stack([rho, np.zeros_like(rho)], -1)  # vertex 0 lies on +x
    middle = rho[:, None] * np.array([np.cos(np.pi / n), np.sin(np.pi / n)])
    d_vertex = np.asarray(polygon.distance(jnp.asarray(vertex)))
    d_middle = np.asarray(polygon.distance(jnp.asarray(middle)))
    outside = rho > radius
    np.testing.assert_allclose(d_vertex[outside], rho[outside] - radius, atol=1e-5)
    np.testing.assert_allclose(d_middle, rho - apothem, atol=1e-5)


def test_beyond_the_cells_it_reads_an_upper_bound_outside():
    rng = np.random.default_rng(4)
    vertices = star(rng, 40)
    polygon = PolygonSDF(vertices)
    far = vertices.mean(0) + rng.normal(0.0, 1.0, (500, 2)) * 200.0
    far = far[np.any((far < vertices.min(0) - MARGIN_MM) | (far > vertices.max(0) + MARGIN_MM), axis=1)]
    got = np.asarray(polygon.distance(jnp.asarray(far)))
    every_edge = np.asarray(polygon.edge_distance(jnp.asarray(far)))
    assert np.all(got >= every_edge - 1e-3) and np.all(every_edge > MARGIN_MM - 1e-3)


def test_derivatives_follow_the_nearest_edge():
    rng = np.random.default_rng(5)
    vertices = star(rng, 40)
    polygon = PolygonSDF(vertices)
    every_edge = PolygonSDF(vertices, edge_cells=False)
    points = jnp.asarray(points_around(vertices, rng, 200, 3.0)[:200])
    np.testing.assert_allclose(jax.vmap(jax.grad(polygon.distance))(points),
                               jax.vmap(jax.grad(every_edge.distance))(points), atol=1e-5)
    np.testing.assert_allclose(jax.vmap(jax.hessian(polygon.distance))(points),
                               jax.vmap(jax.hessian(every_edge.distance))(points), atol=1e-4)
    # In the vertices: the index is constant, the distance to the chosen edge follows them.
    with_vertices = lambda sdf, v: jnp.sum(jnp.tanh(eqx.tree_at(lambda s: s.vertices, sdf, v).distance(points)))  # noqa: E731
    np.testing.assert_allclose(jax.grad(lambda v: with_vertices(polygon, v))(polygon.vertices),
                               jax.grad(lambda v: with_vertices(every_edge, v))(every_edge.vertices), atol=1e-5)
    # And against central differences, along one random direction of the vertices (float64 on host).
    direction = rng.normal(size=vertices.shape)
    h = 1e-3
    moved = [np.sum(np.tanh(np.asarray(PolygonSDF(vertices + s * h * direction, edge_cells=False).distance(points),
                                       np.float64))) for s in (1, -1)]
    derivative = np.sum(np.asarray(jax.grad(lambda v: with_vertices(polygon, v))(polygon.vertices)) * direction)
    assert derivative == pytest.approx((moved[0] - moved[1]) / (2 * h), rel=2e-2, abs=2e-3)


def test_which_polygons_get_an_index():
    assert PolygonSDF(np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])).cells is None  # few edges
    assert PolygonSDF.regular((0.0, 0.0), 15.0, 15).cells is None  # fewer than 16 edges: each read
    assert PolygonSDF.regular((0.0, 0.0), 15.0, 16).cells.edges.shape[1] <= 16 // 3
    dense = PolygonSDF.regular((0.0, 0.0), 15.0, 1000)  # a tenth of its edges a cell: indexed
    assert dense.cells is not None and dense.cells.edges.shape[1] < 1000 // 3
    disc = PolygonSDF.regular((0.0, 0.0), 15.0, 128)
    assert disc.cells is not None
    assert PolygonSDF(disc.vertices, edge_cells=False).cells is None
    seen = []  # from traced vertices (a polygon made inside jit), no index: every edge is read

    def inside_jit(v):
        polygon = PolygonSDF(v)
        seen.append(polygon.cells)
        return polygon.distance(jnp.zeros(2))

    assert float(jax.jit(inside_jit)(disc.vertices)) == pytest.approx(float(disc.distance(jnp.zeros(2))), abs=1e-5)
    assert seen == [None]


def test_replaced_vertices_are_refused_by_the_entry_points():
    from softgrip_jax import FingerModel, Geometric, Gripper

    finger = FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=20)
    gripper = Gripper(left=finger, right=finger, base_separation=56.0)
    disc = PolygonSDF.regular((0.0, 38.0), 15.0, 128)
    moved = eqx.tree_at(lambda s: s.vertices, disc, disc.vertices + jnp.array([5.0, 0.0]))
    with pytest.raises(SoftgripError, match="PolygonSDF\\(new_vertices\\)"):
        score(gripper, moved, jnp.zeros((1, 3)), estimator=Geometric())
    # The same values in a new array (a device transfer, a copy) are the polygon it was made for.
    copied = eqx.tree_at(lambda s: s.vertices, disc, jnp.array(np.asarray(disc.vertices)))
    assert np.isfinite(float(score(gripper, copied, jnp.zeros((1, 3)), estimator=Geometric()).score[0]))


def test_a_repeated_vertex_changes_nothing():
    rng = np.random.default_rng(6)
    vertices = star(rng, 40)
    repeated = np.insert(vertices, 7, vertices[7], axis=0)  # a zero-length edge
    points = jnp.asarray(points_around(vertices, rng, 1000, 2.0))
    np.testing.assert_allclose(PolygonSDF(repeated).distance(points), PolygonSDF(vertices).distance(points), atol=2e-5)
