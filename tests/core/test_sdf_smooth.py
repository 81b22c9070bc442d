"""The grid lookup is C1 (issue 31): SDFGrid's bicubic (Catmull-Rom) interpolation against
hand-derived slopes, exact polynomials, an exact disc and finite differences; the bilinear lookup
(``interpolation="linear"``) is the contrast whose slope jumps at every cell edge.

The mechanics estimate on the vision SDF of a disc (the must-show of the issue) is in the slow set
at the end: a base sweep in 0.002 mm steps moves no joint by more than 0.01 mm, and the implicit
gradient of the tip matches central differences.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softgrip_jax import SDFGrid
from softgrip_jax._sdf import unit_gradient
from softgrip_jax import Mechanics

# Catmull-Rom's slope at a sample k is the samples' central difference (v[k+1] - v[k-1]) / 2 per
# cell, the same from the cells on either side of it: the lookup is C1. The bilinear lookup's slope
# in cell k is v[k+1] - v[k], so it jumps at sample k by v[k+1] - 2 v[k] + v[k-1].


def random_grid(interpolation, shape=(9, 14), spacing=(0.3, 0.4), origin=(-1.0, 2.0), seed=0):
    values = np.random.default_rng(seed).normal(size=shape)
    return SDFGrid(values=values, origin=np.asarray(origin), spacing=np.asarray(spacing),
                   interpolation=interpolation), values


def test_the_cubic_slope_is_continuous_across_cell_edges_and_the_bilinear_slope_jumps(x64):
    # A line along x at row 4.37 crosses the cell edges at columns 1 ... 12 (both neighbours inside
    # the grid). At each edge, jax.grad just left and just right of it against the slopes above.
    row, fy = 4, 0.37
    y = 2.0 + (row + fy) * 0.4
    cols = np.arange(1, 13)
    eps = 1e-9  # cells; far below any change of the slope within a cell
    slope_x = lambda grid, x: np.asarray(jax.vmap(jax.grad(grid.distance))(jnp.asarray(  # noqa: E731
        np.column_stack([x, np.full_like(x, y)]))))[:, 0]
    left_of = lambda grid: slope_x(grid, -1.0 + (cols - eps) * 0.3)  # noqa: E731
    right_of = lambda grid: slope_x(grid, -1.0 + (cols + eps) * 0.3)  # noqa: E731

    cubic, v = random_grid("cubic")
    # Catmull-Rom weights of rows 3, 4, 5, 6 at the fraction 0.37 of the cell between rows 4 and 5
    t = fy
    wy = 0.5 * np.array([-t**3 + 2 * t**2 - t, 3 * t**3 - 5 * t**2 + 2, -3 * t**3 + 4 * t**2 + t, t**3 - t**2])
    central = (v[row - 1:row + 3, cols + 1] - v[row - 1:row + 3, cols - 1]) / 2.0  # (4 rows, edges) per cell
    expected = wy @ central / 0.3  # per mm
    np.testing.assert_allclose(left_of(cubic), expected, atol=1e-6)
    np.testing.assert_allclose(right_of(cubic), expected, atol=1e-6)

    linear, v = random_grid("linear")
    cell_slope = lambda k: ((1 - fy) * (v[row, k + 1] - v[row, k]) + fy * (v[row + 1, k + 1] - v[row + 1, k])) / 0.3  # noqa: E731
    np.testing.assert_allclose(left_of(linear), cell_slope(cols - 1), atol=1e-6)
    np.testing.assert_allclose(right_of(linear), cell_slope(cols), atol=1e-6)
    jump = np.abs(cell_slope(cols) - cell_slope(cols - 1))
    assert jump.min() > 0.05 and jump.max() > 1.0  # the bilinear normal turns at every cell edge


@pytest.mark.parametrize("h", [1e-2, 1e-3])
def test_finite_difference_slopes_across_a_cell_edge_agree_as_the_step_shrinks(x64, h):
    # One-sided differences of the distance itself (no autodiff) at the cell edges of a diagonal
    # line: their gap is O(h) for the cubic lookup (its slope is continuous, its second derivative
    # bounded) and stays at the jump of the slope for the bilinear one.
    line = lambda s: np.column_stack([-1.0 + s * 0.3, 2.0 + (0.25 + 0.61 * s) * 0.4])  # noqa: E731
    edges = np.arange(1.0, 12.0)  # the line crosses column edges at integer s
    gaps = {}
    for interpolation in ("cubic", "linear"):
        grid, _ = random_grid(interpolation)
        f = lambda s: np.asarray(grid.distance(jnp.asarray(line(s))))  # noqa: E731
        forward = (f(edges + h) - f(edges)) / h
        backward = (f(edges) - f(edges - h)) / h
        gaps[interpolation] = np.abs(forward - backward).max()
    # A cubic's second derivative is bounded by a few times the largest sample difference (about 6
    # for these unit-normal samples) per cell squared: the gap is at most about 10 h here.
    assert gaps["cubic"] < 20 * h
    assert gaps["linear"] > 0.3  # the jump of the slope, whatever the step


def test_the_cubic_lookup_reproduces_quadratics_inside_and_linear_fields_up_to_the_edge(x64):
    # Catmull-Rom weights sum to 1, reproduce k and k^2 (sum_k w_k k^2 = t^2, by hand from the
    # weights), so a tensor-product lookup is exact on x, y, x^2, x y, y^2 wherever all 4 x 4 samples
    # are real: every cell but the border ones. There a ghost sample extrapolated linearly past the
    # edge keeps linear fields exact.
    rows, cols = np.mgrid[0:8, 0:11].astype(float)
    origin, spacing = np.array([1.0, -2.0]), np.array([0.5, 0.25])
    x, y = origin[0] + cols * spacing[0], origin[1] + rows * spacing[1]
    quadratic = lambda x, y: x**2 - 3 * x * y + 2 * y**2 + x - 0.5  # noqa: E731
    linear = lambda x, y: 3 * x - 2 * y + 1  # noqa: E731
    rng = np.random.default_rng(1)
    lo, hi = origin, origin + spacing * [10, 7]
    inner = rng.uniform(lo + spacing, hi - spacing, (500, 2))
    anywhere = np.concatenate([rng.uniform(lo, hi, (500, 2)), [lo, hi, [lo[0], hi[1]], [hi[0], lo[1]]]])
    for field, points in [(quadratic, inner), (linear, anywhere)]:
        grid = SDFGrid(values=field(x, y), origin=origin, spacing=spacing)
        np.testing.assert_allclose(jax.jit(lambda p: grid.distance(p))(jnp.asarray(points)), field(*points.T),  # noqa: B023
                                   atol=1e-11)
    # ... including the Hessian the mechanics estimate's implicit derivative uses
    grid = SDFGrid(values=quadratic(x, y), origin=origin, spacing=spacing)
    hessian = jax.jit(jax.vmap(jax.hessian(lambda p: grid.distance(p))))(jnp.asarray(inner[:20]))
    np.testing.assert_allclose(hessian, np.broadcast_to([[2.0, -3.0], [-3.0, 4.0]], (20, 2, 2)), atol=1e-9)
    # A quadratic in a border cell is not reproduced (the ghost is linear): the exactness is the
    # interior's, not an accident of the field.
    border = np.array([[1.1, -1.9]])
    assert abs(float(grid.distance(jnp.asarray(border))[0]) - quadratic(*border.T)[0]) > 1e-4


def test_a_disc_at_03_mm_cells_is_read_within_1e_4_mm_and_its_normal_within_1e_3():
    # float32, as the estimates run. The exact distance |p - c| - R has second derivatives up to 1/R
    # and third up to about 1/R^2 near the boundary: bilinear errs by about h^2 / (8 R) = 1e-3 mm and
    # turns the normal by O(h / R); Catmull-Rom errs by O(h^3 / R^2).
    c, radius = np.array([1.3, 2.1]), 10.0
    exact = lambda p: jnp.linalg.norm(p - c, axis=-1) - radius  # noqa: E731
    rng = np.random.default_rng(0)
    angle, offset = rng.uniform(0, 2 * np.pi, 2000), rng.uniform(-3.0, 5.0, 2000)
    radial = np.stack([np.cos(angle), np.sin(angle)], -1)
    points = jnp.asarray(c + (radius + offset)[:, None] * radial, jnp.float32)
    errors = {}
    for interpolation in ("cubic", "linear"):
        grid = SDFGrid.sample(exact, origin=(-15.0, -15.0), spacing=(0.3, 0.3), shape=(111, 111),
                              interpolation=interpolation)
        distance_error = np.abs(np.asarray(jax.jit(lambda p: grid.distance(p))(points)) - offset).max()  # noqa: B023
        normals = np.asarray(jax.jit(jax.vmap(lambda p: unit_gradient(grid.distance, p)))(points))  # noqa: B023
        errors[interpolation] = distance_error, np.linalg.norm(normals - radial, axis=-1).max()
    assert errors["cubic"][0] < 1e-4 and errors["cubic"][1] < 1e-3, errors
    assert errors["linear"][0] > 1e-3 and errors["linear"][1] > 1e-2, errors  # the contrast


def test_jax_grad_and_hessian_of_the_cubic_lookup_match_central_differences(x64):
    grid, _ = random_grid("cubic", seed=3)
    rng = np.random.default_rng(4)
    # anywhere in the grid, the border cells included, away from cell edges by more than the step
    cells = rng.integers([0, 0], [13, 8], (200, 2)) + rng.uniform(0.05, 0.95, (200, 2))
    points = jnp.asarray(np.array([-1.0, 2.0]) + cells * [0.3, 0.4])
    h = 1e-6
    e = np.eye(2) * h
    distance = jax.jit(lambda p: grid.distance(p))
    grad = jax.jit(jax.vmap(jax.grad(grid.distance)))
    central = np.stack([(distance(points + e[i]) - distance(points - e[i])) / (2 * h) for i in range(2)], -1)
    np.testing.assert_allclose(grad(points), central, atol=1e-7)
    central2 = np.stack([(grad(points + e[i]) - grad(points - e[i])) / (2 * h) for i in range(2)], -1)
    np.testing.assert_allclose(jax.jit(jax.vmap(jax.hessian(grid.distance)))(points), central2, atol=1e-5)
    # and with respect to the grid's origin (the object's position) and samples
    point = points[7]
    by_origin = jax.grad(lambda o: SDFGrid(grid.values, o, grid.spacing).distance(point))(grid.origin)
    np.testing.assert_allclose(by_origin, -jax.grad(grid.distance)(point), atol=1e-12)
    by_values = jax.grad(lambda v: SDFGrid(v, grid.origin, grid.spacing).distance(point))(grid.values)
    assert float(jnp.sum(by_values)) == pytest.approx(1.0) and int(jnp.sum(by_values != 0)) == 16


def keys_kernel(x, a=-0.5):
    """Keys' cubic convolution kernel (1981), the textbook form of Catmull-Rom for a = -1/2."""
    x = np.abs(x)
    near = (a + 2) * x**3 - (a + 3) * x**2 + 1
    far = a * x**3 - 5 * a * x**2 + 8 * a * x - 4 * a
    return np.where(x <= 1, near, np.where(x < 2, far, 0.0))


def test_the_cubic_lookup_is_keys_cubic_convolution_of_the_samples_with_linear_ghosts(x64):
    # An independent reference for the per-cell polynomial table the lookup reads: the sum over
    # the 4 x 4 nearest samples of kernel(row distance) kernel(column distance) v, in numpy, on the
    # grid extended by one ghost sample per side extrapolated linearly (2 v0 - v1, corners
    # included: the extension applied along rows, then along columns).
    grid, v = random_grid("cubic", seed=5)
    ghost = np.concatenate([2 * v[:1] - v[1:2], v, 2 * v[-1:] - v[-2:-1]], axis=0)
    ghost = np.concatenate([2 * ghost[:, :1] - ghost[:, 1:2], ghost, 2 * ghost[:, -1:] - ghost[:, -2:-1]], axis=1)
    rng = np.random.default_rng(6)
    h, w = v.shape
    coords = rng.uniform([0, 0], [h - 1, w - 1], (500, 2))  # (row, col), the border cells included
    coords[:4] = [[0, 0], [h - 1, w - 1], [0, w - 1], [h - 1, 3.5]]  # the corners and an edge
    expected = []
    for row, col in coords:
        r0, c0 = min(int(row), h - 2), min(int(col), w - 2)
        taps_r, taps_c = np.arange(r0 - 1, r0 + 3), np.arange(c0 - 1, c0 + 3)
        weights = np.outer(keys_kernel(row - taps_r), keys_kernel(col - taps_c))
        expected.append(np.sum(weights * ghost[taps_r[:, None] + 1, taps_c[None, :] + 1]))
    points = jnp.asarray(np.array([-1.0, 2.0]) + coords[:, ::-1] * [0.3, 0.4])
    np.testing.assert_allclose(jax.jit(lambda p: grid.distance(p))(points), expected, atol=1e-12)


def test_the_cubic_lookup_jits_vmaps_over_grids_and_stays_far_outside():
    grids = [random_grid("cubic", seed=s)[0] for s in range(3)]
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *grids)
    points = jnp.array([[[0.0, 3.0], [2.0, 4.5]], [[-1.0, 2.0], [50.0, 0.0]]])  # (2, 2, 2): any batch shape
    out = jax.jit(jax.vmap(lambda g: g.distance(points)))(stacked)
    assert out.shape == (3, 2, 2)
    for i, g in enumerate(grids):
        np.testing.assert_allclose(out[i], g.distance(points), rtol=1e-6)
    assert (out[:, 1, 1] == grids[0].far).all()  # outside: far, never contact
    gradient_outside = jax.grad(grids[0].distance)(jnp.array([50.0, 0.0]))
    assert np.all(np.asarray(gradient_outside) == 0.0)


def test_interpolation_is_validated():
    from softgrip_jax import SoftgripError

    with pytest.raises(SoftgripError, match="interpolation"):
        SDFGrid(values=np.zeros((3, 3)), origin=np.zeros(2), spacing=1.0, interpolation="quadratic")


# ---------------------------------------------------------------------------------------------
# The mechanics estimate on the vision SDF of a disc (slow: three compilations of the estimate)


@pytest.mark.slow
def test_the_mechanics_estimate_on_the_vision_sdf_moves_continuously_and_its_gradient_is_the_closures():
    from benchmarks.bench_smooth_sdf import FINGER, vision_disc

    from softgrip_jax import ContactCase, MechanicsConfig, estimate, estimate_batch

    # The disc of radius 10 mm at (20, 60) that the finger's tip rests on (test_closing_path's), as
    # vision makes it from a hard mask on 0.3 mm pixels. The solve is converged tightly so that where
    # it stops (up to step_tol short, by a pose-dependent amount) does not pose as a step.
    grid = vision_disc()
    assert np.allclose(np.asarray(grid.spacing), 0.3) and grid.interpolation == "cubic"
    # (step_tol 1e-5: float32 rounding kept one pose from two such steps in a row, which the solve
    # now needs to converge)
    tight = MechanicsConfig(step_tol=1e-4, max_steps=200)
    sweep = np.column_stack([np.zeros(91), -0.18 + 0.002 * np.arange(91)])  # y in [-0.18, 0]: tip held
    regular = np.array([[0.0, -0.1], [0.0, -0.03]])
    h = 0.01
    shifted = np.concatenate([regular[:, None] + s * h * np.eye(2)[None] for s in (1, -1)], axis=1).reshape(-1, 2)
    bases = jnp.asarray(np.concatenate([sweep, regular, shifted]), jnp.float32)
    est = jax.tree_util.tree_map(np.asarray, estimate_batch(FINGER, grid, bases, estimator=Mechanics(tight)))
    assert est.valid.all() and (est.case == ContactCase.TIP).all() and not est.event.any()
    assert (est.sensitivity < tight.fold_sensitivity).all()  # regular poses, no fold nearby
    # Base steps of 0.002 mm move the tip by about sensitivity (2 to 3 here) x 0.002 mm; no joint
    # jumps. (On the bilinear lookup the same sweep has a step of 0.03 mm: the tip's normal turns
    # at each cell edge; benchmarks/bench_smooth_sdf.py.)
    joints = est.joints[:91]
    step = np.linalg.norm(np.diff(joints, axis=0), axis=-1).max(axis=-1)
    assert step.max() <= 0.01, step.max()
    # d tip / d base from implicit differentiation (the lookup's gradient and Hessian) against
    # central differences of the same estimates.
    tip = lambda b: estimate(FINGER, grid, b, estimator=Mechanics(tight)).joints[-1]  # noqa: E731
    jacobians = np.asarray(jax.jit(jax.vmap(jax.jacrev(tip)))(jnp.asarray(regular, jnp.float32)), np.float64)
    tips = est.joints[93:, -1].astype(np.float64).reshape(2, 4, 2)
    central = ((tips[:, :2] - tips[:, 2:]) / (2 * h)).transpose(0, 2, 1)  # (pose, tip axis, base axis)
    error = np.linalg.norm(jacobians - central, axis=(1, 2)) / np.linalg.norm(central, axis=(1, 2))
    assert error.max() < 0.02, (error, jacobians, central)
    assert np.linalg.norm(central, axis=(1, 2)).min() > 1.5  # a held tip, amplified: not the free finger's 1
