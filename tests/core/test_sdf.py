"""Signed distances against independent references (OpenCV's pointPolygonTest, brute force)."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from softgrip_jax import FAR_MM, PolygonSDF, SDFGrid, SoftgripError
from softgrip_jax._sdf import surface_point, unit_gradient


def random_star_polygon(rng, n):
    """A simple (star-shaped) polygon around the origin with n vertices."""
    angles = np.sort(rng.uniform(0, 2 * np.pi, n))
    radii = rng.uniform(5, 20, n)
    return np.stack([radii * np.cos(angles), radii * np.sin(angles)], -1)


def brute_force_distance(poly, p):
    a, b = poly, np.roll(poly, -1, axis=0)
    ab, ap = b - a, p - a
    t = np.clip(np.sum(ap * ab, 1) / np.sum(ab * ab, 1), 0, 1)
    return np.min(np.linalg.norm(ap - t[:, None] * ab, axis=1))


@given(seed=st.integers(0, 2**31 - 1), n=st.sampled_from([3, 7, 16]))
def test_polygon_sdf_matches_opencv(seed, n):
    rng = np.random.default_rng(seed)
    poly = random_star_polygon(rng, n)
    points = rng.uniform(-25, 25, (64, 2))
    ours = np.asarray(PolygonSDF(jnp.asarray(poly)).distance(jnp.asarray(points)))
    contour = poly.astype(np.float32).reshape(-1, 1, 2)
    for p, d in zip(points, ours):
        unsigned = brute_force_distance(poly, p)
        inside = cv2.pointPolygonTest(contour, (float(p[0]), float(p[1])), False)
        if abs(unsigned) < 1e-3:  # on the boundary: sign is a matter of rounding
            continue
        expected = -unsigned if inside > 0 else unsigned
        assert d == pytest.approx(expected, abs=1e-3)


def test_polygon_sdf_vertex_gradient_matches_finite_differences(x64):
    poly = jnp.array([[0.0, 0.0], [12.0, 1.0], [10.0, 9.0], [2.0, 11.0]])
    point = jnp.array([14.0, 6.0])
    fn = lambda v: PolygonSDF(v).distance(point)
    grad = jax.grad(fn)(poly)
    h = 1e-6
    fd = np.zeros_like(np.asarray(poly))
    for idx in np.ndindex(*poly.shape):
        e = jnp.zeros_like(poly).at[idx].set(h)
        fd[idx] = (fn(poly + e) - fn(poly - e)) / (2 * h)
    np.testing.assert_allclose(grad, fd, atol=1e-7)
    assert np.abs(fd).sum() > 0.5  # the point's nearest edge moves with its vertices


@pytest.mark.parametrize("interpolation", ["cubic", "linear"])
def test_sdf_grid_reproduces_a_linear_field_and_is_far_outside(interpolation):
    # v = col + 10 row is linear: both lookups reproduce it, the cubic one up to the grid's edge
    # (its ghost samples past the edge are extrapolated linearly). (9, 7.5) is the last corner,
    # (6, 7.25) the middle of the first cell: 0.5 + 10 * 0.5.
    values = jnp.array([[0.0, 1.0, 2.0], [10.0, 11.0, 12.0]])
    grid = SDFGrid(values=values, origin=jnp.array([5.0, 7.0]), spacing=jnp.array([2.0, 0.5]),
                   interpolation=interpolation)
    pts = jnp.array([[5.0, 7.0], [9.0, 7.5], [6.0, 7.25], [4.9, 7.0], [5.0, 7.6], [100.0, 100.0]])
    d = np.asarray(grid.distance(pts))
    np.testing.assert_allclose(d[:3], [0.0, 12.0, 5.5], atol=1e-5)
    assert np.all(d[3:] == FAR_MM)  # outside never reads as contact
    np.testing.assert_array_equal(grid.contains(pts), [True, True, True, False, False, False])


def test_sdf_grid_sampled_circle_zero_level():
    circle = PolygonSDF.regular(center=(1.0, 2.0), radius=10.0, n_vertices=256)
    grid = SDFGrid.sample(circle, origin=(-15.0, -15.0), spacing=(0.25, 0.25), shape=(141, 141))
    angles = np.linspace(0, 2 * np.pi, 50, endpoint=False)
    on_circle = np.stack([1 + 10 * np.cos(angles), 2 + 10 * np.sin(angles)], -1)
    np.testing.assert_allclose(grid.distance(jnp.asarray(on_circle)), 0.0, atol=2e-2)
    np.testing.assert_allclose(grid.normal(jnp.array([11.0, 2.0])), [1.0, 0.0], atol=0.03)  # ~ spacing / radius


def test_sdf_constructors_reject_bad_input():
    with pytest.raises(SoftgripError, match="vertices"):
        PolygonSDF(jnp.zeros((2, 2)))
    with pytest.raises(SoftgripError, match="spacing"):
        SDFGrid(values=jnp.zeros((3, 3)), origin=jnp.zeros(2), spacing=jnp.array([1.0, 0.0]))


def test_a_polygon_on_a_grid_is_exact_at_the_nodes_and_covers_its_margin():
    poly = random_star_polygon(np.random.default_rng(3), 16)
    grid = PolygonSDF(jnp.asarray(poly, jnp.float32)).to_grid(cell_mm=0.5, margin_mm=7.0)
    low, high = poly.min(axis=0) - 7.0, poly.max(axis=0) + 7.0
    h, w = grid.values.shape
    far_corner = np.asarray(grid.origin) + np.array([w - 1, h - 1]) * np.asarray(grid.spacing)
    np.testing.assert_allclose(grid.origin, low, atol=1e-5)
    assert np.all(far_corner >= high - 1e-4) and np.all(far_corner < high + 0.5)
    # OpenCV's signed distance (positive inside) at 300 random nodes, against the grid's samples.
    rows, cols = np.random.default_rng(4).integers(0, [h, w], (300, 2)).T
    nodes = np.asarray(grid.origin) + np.stack([cols, rows], -1) * 0.5
    contour = poly.astype(np.float32).reshape(-1, 1, 2)
    expected = [-cv2.pointPolygonTest(contour, (float(x), float(y)), True) for x, y in nodes]
    np.testing.assert_allclose(np.asarray(grid.values)[rows, cols], expected, atol=1e-4)


def test_a_polygon_grid_rejects_bad_sizes():
    square = PolygonSDF(jnp.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]]))
    for kwargs, name in (({"cell_mm": 0.0}, "cell_mm"), ({"cell_mm": float("nan")}, "cell_mm"),
                         ({"margin_mm": -1.0}, "margin_mm"), ({"cell_mm": 1e-4, "margin_mm": 100.0}, "too large")):
        with pytest.raises(SoftgripError, match=name):
            square.to_grid(**kwargs)


def test_sdf_grid_from_numpy_with_a_scalar_spacing_matches_the_jax_grid():
    """numpy arrays and a scalar spacing are accepted at construction and at lookup (planners hand
    over numpy grids), and give the same distances as the JAX arrays they stand for."""
    import numpy as np

    rows, cols = np.mgrid[0:31, 0:41]
    values = np.hypot(cols * 0.5 - 10.0, rows * 0.5 - 7.5) - 4.0  # float64 numpy
    from_numpy = SDFGrid(values=values, origin=np.zeros(2), spacing=0.5)
    from_jax = SDFGrid(values=jnp.asarray(values, jnp.result_type(float)), origin=jnp.zeros(2),
                       spacing=jnp.array([0.5, 0.5]))
    assert isinstance(from_numpy.values, jax.Array) and from_numpy.spacing.shape == (2,)
    points = np.array([[10.0, 7.5], [14.0, 7.5], [3.3, 2.2], [100.0, 0.0]])
    np.testing.assert_allclose(from_numpy.distance(points), from_jax.distance(jnp.asarray(points, from_jax.values.dtype)),
                               rtol=1e-6)
    assert float(from_numpy.distance(points)[0]) == pytest.approx(-4.0, abs=1e-5)
    assert float(from_numpy.distance(points)[-1]) == from_numpy.far
    with pytest.raises(SoftgripError, match="spacing must be > 0"):
        SDFGrid(values=values, origin=np.zeros(2), spacing=0.0)


@pytest.mark.parametrize("sampled", [None, "linear", "cubic"])
def test_surface_point_lands_in_a_concave_corner_and_on_a_circle(sampled):
    # An L-shaped object whose inner corner is the origin, free space in the quadrant x, y > 0. The
    # point (3.2, 3.1) is 3.1 from the wall y = 0 and 3.2 from x = 0: its nearest surface point is
    # (3.2, 0). On a 0.5-mm grid it lies 0.2 cells from the corner's bisector, where the sampled
    # gradient blends the two walls' normals: one step along it stops short of the surface, out in
    # the corner's free space (3 (1 - 1/sqrt(2)) = 0.88 mm from (3, 3) on the bisector). The bilinear
    # gradient blends over the whole cell (0.38 mm short here); the bicubic one, whose slope is
    # continuous, over a narrower band around the bisector (0.08 mm short).
    l_shape = PolygonSDF(jnp.array([[-20.0, -20.0], [20.0, -20.0], [20.0, 0.0], [0.0, 0.0], [0.0, 20.0],
                                    [-20.0, 20.0]]))
    circle = PolygonSDF.regular(center=(0.0, 0.0), radius=10.0, n_vertices=256)
    if sampled:
        grid = dict(origin=(-30.0, -30.0), spacing=(0.5, 0.5), shape=(121, 121), interpolation=sampled)
        l_shape = SDFGrid.sample(l_shape, **grid)
        circle = SDFGrid.sample(circle, **grid)
    point = jnp.array([3.2, 3.1])
    one_step = point - l_shape.distance(point) * unit_gradient(l_shape.distance, point)
    on_surface = surface_point(l_shape.distance, point)
    assert abs(float(l_shape.distance(on_surface))) < 0.02
    if sampled:
        # the single step, out in the corner's free space
        assert float(l_shape.distance(one_step)) > (0.3 if sampled == "linear" else 0.05)
        # on the surface, in the corner's reach: not farther than the corner itself
        assert float(jnp.linalg.norm(on_surface - point)) <= float(jnp.linalg.norm(point)) + 0.02
    else:  # the exact distance has one nearest point, and the first step lands on it
        np.testing.assert_allclose(on_surface, [3.2, 0.0], atol=1e-4)
    # On a circle of radius 10 the surface point of (15 cos a, 15 sin a) is (10 cos a, 10 sin a). The
    # 256-gon's facet normals are within pi / 256 of radial, which slides the foot along the circle by
    # up to 5 pi / 256 = 0.06 mm; the grid's gradients stay within that too.
    a = 0.7
    foot = surface_point(circle.distance, jnp.array([15.0 * np.cos(a), 15.0 * np.sin(a)]))
    np.testing.assert_allclose(foot, [10.0 * np.cos(a), 10.0 * np.sin(a)], atol=0.07)
