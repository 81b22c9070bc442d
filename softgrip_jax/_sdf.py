"""Signed distance to the object: negative inside, in mm.

Two implementations behind one interface, :class:`AbstractSDF`:

* :class:`SDFGrid` samples a distance grid (made from a mask by a distance transform in ``softgrip_vision``)
  with a C1 bicubic (Catmull-Rom) lookup by default, bilinearly on request; outside the grid it reads
  as ``far``, never as contact.
* :class:`PolygonSDF` is the exact distance to a closed polygon, differentiable in its vertices; a
  polygon of many edges reads only the few its point can be nearest to (`_polygon_cells`).
"""

from __future__ import annotations

import abc
import math
from collections.abc import Callable
from functools import partial
from typing import ClassVar, Literal, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array, ArrayLike, Bool, Float

from softgrip_base.errors import SoftgripError
from softgrip_jax._polygon_cells import EdgeCells, cells_distance
from softgrip_jax._polygon_cells import edge_cells as make_edge_cells
from softgrip_jax._safe import safe_divide, safe_norm

#: Distance (mm) reported outside an :class:`SDFGrid`: farther than any finger can reach.
FAR_MM = 1.0e4


def _as_array(x: ArrayLike) -> Array:
    """Numpy arrays and lists as JAX arrays of floating point (JAX arrays and tracers as they are;
    integer grids become the default float type)."""
    if isinstance(x, jax.core.Tracer):
        return x
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.result_type(float))


def _as_pair(x: ArrayLike) -> Array:
    """A (2,) array from one number (the same along x and y) or two."""
    x = _as_array(x)
    return jnp.broadcast_to(x, (2,)) if jnp.ndim(x) == 0 else x


class AbstractSDF(eqx.Module):
    """A signed-distance function of the image plane (mm; negative inside the object)."""

    #: The largest piece of candidates (:data:`softgrip_jax._concurrent.PIECE_BUCKETS`) a default
    #: batch runs in against this SDF: a lookup whose intermediate arrays grow with the object
    #: (a polygon's points x edges) keeps its pieces smaller.
    largest_piece: ClassVar[int] = 4096
    #: A piece's fixed cost in candidates' worth of work against this SDF, as
    #: :func:`softgrip_jax._concurrent.bucket_piece` weighs it: a piece of one candidate takes about
    #: as long as this many candidates inside a large piece (measured by ``benchmarks/bench_defaults.py
    #: --only pieces --only sizes``).
    piece_overhead: ClassVar[int] = 256

    @abc.abstractmethod
    def distance(self, points: Float[Array, "*batch 2"]) -> Float[Array, "*batch"]:
        """Signed distance in mm at ``points`` (mm)."""

    def coarse_distance(self, points: Float[Array, "*batch 2"]) -> Float[Array, "*batch"]:
        """A cheaper approximation of :meth:`distance` (mm), for the contact sweep's coarse
        bracketing grid and the second contact's circle, where only signs are read (of the
        clearance at a few closing steps, of the distance around the circle): :meth:`distance`
        itself unless overridden. The root of the first contact and the chosen crossing on the
        circle are then placed with :meth:`distance`, so the estimate and its derivatives are those
        of :meth:`distance`."""
        return self.distance(points)

    @property
    def has_coarse_lookup(self) -> bool:
        """Whether :meth:`coarse_distance` is a lookup of its own (not :meth:`distance` itself):
        only then do the coarse sweep and the circle gain from reading it first."""
        return type(self).coarse_distance is not AbstractSDF.coarse_distance

    def contains(self, points: Float[Array, "*batch 2"]) -> Bool[Array, "*batch"]:
        """Whether ``points`` lie where the SDF has data (everywhere, unless overridden)."""
        return jnp.ones(jnp.shape(points)[:-1], dtype=bool)

    def all_finite(self) -> Bool[Array, ""]:
        """Whether the SDF's own data is finite (True unless overridden); an estimate on an SDF that
        is not gets ``Status.NON_FINITE_SDF``."""
        return jnp.array(True)

    def normal(self, point: Float[ArrayLike, "2"]) -> Float[Array, "2"]:
        """Unit gradient of the distance at one point (outward normal); zero where it vanishes."""
        return unit_gradient(self.distance, _as_array(point))

    def mass_properties(self) -> tuple[Float[Array, "2"], Float[Array, ""]]:
        """The object's area centroid (2,) mm and its largest distance from it, ``rho`` (mm): where
        grasp quality takes torques and how it scales them. A new SDF class implements this to be
        scored (the deformation estimates do not need it)."""
        raise SoftgripError(f"{type(self).__name__} has no mass_properties(): give it one (area centroid "
                            f"and largest distance from it, mm) to score grasps on it")


def unit_gradient(distance: Callable[[Array], Array], point: Float[Array, "2"]) -> Float[Array, "2"]:
    """Unit gradient of a distance function at ``point``; zero where the gradient vanishes."""
    grad = jax.grad(distance)(point)
    return safe_divide(grad, safe_norm(grad)[..., None])


#: Newton steps onto the surface after the first step along the gradient (:func:`surface_point`).
_SURFACE_STEPS = 3
#: Floor of |grad|^2 in those steps: no step is longer than 4 |distance|.
_MIN_GRADIENT_SQ = 0.25


def surface_point(distance: Callable[[Array], Array], point: Float[Array, "2"]) -> Float[Array, "2"]:
    """The point of the surface (distance 0) that ``point`` (mm) faces, in mm: a step of the distance
    against the unit gradient, then Newton steps onto the zero level, ``x - d g / |g|^2``.

    Where the distance has one nearest surface point the first step lands on it and the others do
    not move it. Beside a concave corner, where a point is equally near two walls, the sampled
    gradient averages the two walls' normals (its norm is below 1) and the first step stops short
    of the surface, out in the free space of the corner (by 0.29 of the distance at a right angle);
    the Newton steps carry it onto the surface, into the corner the finger nestles in.
    """
    def step(x, first):
        d, g = jax.value_and_grad(distance)(x)
        scale = jnp.where(first, safe_divide(jnp.ones_like(d), safe_norm(g)), 1.0 / jnp.maximum(jnp.sum(g * g), _MIN_GRADIENT_SQ))
        return x - d * scale * g, None

    # One traced copy of the distance and its gradient, looped (not unrolled): the distance of a
    # polygon is a large program, and each copy adds to the compile time of everything above it.
    firsts = jnp.arange(_SURFACE_STEPS + 1) == 0
    return jax.lax.scan(step, jnp.asarray(point), firsts)[0]


class SDFGrid(AbstractSDF):
    """Signed distances sampled on a regular grid, looked up by bicubic (Catmull-Rom) interpolation.

    The default lookup is C1: the distance and its gradient are continuous across cell edges, so an
    estimate on the grid moves continuously with the pose and its implicit derivative (which uses the
    distance's gradient and Hessian) is the derivative of the closure. It passes through the samples
    (the zero level stays where they put it) and reproduces quadratic fields exactly away from the
    grid's border cells, where ghost samples extrapolated linearly past the edge keep linear fields
    exact. A bilinear lookup (``interpolation="linear"``: four taps instead of sixteen, continuous
    but with a gradient that jumps at every cell edge) remains available.

    Attributes:
        values: (H, W) signed distances in mm; row i, column j is the point
            ``origin + (j * spacing[0], i * spacing[1])``.
        origin: (2,) position in mm of the centre of element (0, 0).
        spacing: (2,) grid step in mm along x (columns) and y (rows), > 0; a scalar is the same
            step along both.
        far: distance in mm returned outside the grid (static).
        interpolation: ``"cubic"`` (default, C1 Catmull-Rom bicubic, 4 x 4 samples) or ``"linear"``
            (bilinear, 2 x 2 samples) (static).
        cells: ((H-1) (W-1), 16) the cubic lookup's polynomial coefficients per cell, made from
            ``values`` at construction (None for ``"linear"``): a lookup reads one row of 16
            neighbouring floats instead of sixteen samples on four rows of the grid. Derived data:
            build a new grid (not ``eqx.tree_at``) to change ``values``.

    Arrays may be numpy arrays, JAX arrays or nested lists (stored as JAX arrays of the default
    float type).

    Example:
        >>> import jax.numpy as jnp
        >>> circle = PolygonSDF.regular(center=(0.0, 0.0), radius=10.0, n_vertices=64)
        >>> grid = SDFGrid.sample(circle, origin=(-20.0, -20.0), spacing=(0.5, 0.5), shape=(81, 81))
        >>> round(float(grid.distance(jnp.array([15.0, 0.0]))), 1)
        5.0

        From numpy, with one spacing for both axes:

        >>> import numpy as np
        >>> rows, cols = np.mgrid[0:41, 0:41]
        >>> values = np.hypot(cols - 20.0, rows - 20.0) - 10.0  # a disc of radius 10 mm, 1 mm cells
        >>> grid = SDFGrid(values=values, origin=np.array([-20.0, -20.0]), spacing=1.0)
        >>> round(float(grid.distance(np.array([15.0, 0.0]))), 1), grid.spacing.tolist()
        (5.0, [1.0, 1.0])
    """

    values: Float[Array, "h w"]
    origin: Float[Array, "2"]
    spacing: Float[Array, "2"]
    far: float = eqx.field(static=True)
    interpolation: str = eqx.field(static=True)  # "cubic" or "linear", checked below
    cells: Float[Array, "cells 16"] | None

    def __init__(self, values: Float[ArrayLike, "h w"], origin: Float[ArrayLike, "2"],
                 spacing: Float[ArrayLike, "2"] | float, far: float = FAR_MM, interpolation: str = "cubic"):
        self.values, self.origin, self.spacing = _as_array(values), _as_array(origin), _as_pair(spacing)
        self.far, self.interpolation = far, interpolation
        usable = interpolation == "cubic" and jnp.ndim(self.values) == 2 and min(jnp.shape(self.values)) >= 2
        # (Otherwise __check_init__ says what is wrong.)
        self.cells = catmull_rom_cells(self.values) if usable else None

    def __check_init__(self):
        if self.interpolation not in ("cubic", "linear"):
            raise SoftgripError(f"SDFGrid.interpolation must be 'cubic' or 'linear', got {self.interpolation!r}")
        if jnp.ndim(self.values) != 2 or min(jnp.shape(self.values)) < 2:
            raise SoftgripError(f"SDFGrid.values must be a 2-D grid of at least 2x2, got shape {jnp.shape(self.values)}")
        if jnp.shape(self.origin) != (2,) or jnp.shape(self.spacing) != (2,):
            raise SoftgripError("SDFGrid.origin and SDFGrid.spacing must each have shape (2,)")
        if not isinstance(self.spacing, jax.core.Tracer) and not bool(np.all(np.asarray(self.spacing) > 0)):
            raise SoftgripError(f"SDFGrid.spacing must be > 0 mm, got {np.asarray(self.spacing).tolist()}")

    @classmethod
    def sample(
        cls,
        sdf: AbstractSDF | Callable[[Array], Array],
        origin: tuple[float, float] | Array,
        spacing: tuple[float, float] | Array,
        shape: tuple[int, int],
        interpolation: Literal["cubic", "linear"] = "cubic",
    ) -> SDFGrid:
        """Sample another SDF (or any distance function of points) on a grid of ``shape`` (H, W),
        ``origin`` (2,) mm and ``spacing`` (2,) mm, looked up with ``interpolation``."""
        fn = sdf.distance if isinstance(sdf, AbstractSDF) else sdf
        origin = jnp.asarray(origin, dtype=jnp.result_type(float))
        spacing = jnp.asarray(spacing, dtype=jnp.result_type(float))
        rows, cols = jnp.meshgrid(jnp.arange(shape[0]), jnp.arange(shape[1]), indexing="ij")
        points = origin + jnp.stack([cols, rows], axis=-1) * spacing
        return cls(values=fn(points), origin=origin, spacing=spacing, interpolation=interpolation)

    def all_finite(self) -> Bool[Array, ""]:
        """Whether every cell is finite (a NaN cell would read as "no contact")."""
        return jnp.all(jnp.isfinite(self.values))

    def mass_properties(self) -> tuple[Float[Array, "2"], Float[Array, ""]]:
        """Area centroid and ``rho`` of the cells inside (distance < 0), each cell weighted by the
        fraction of it inside (its distance over the cell size, linearly); rho reaches the boundary
        beyond the farthest cells (their distance added)."""
        h, w = self.values.shape
        rows, cols = jnp.meshgrid(jnp.arange(h), jnp.arange(w), indexing="ij")
        points = self.origin + jnp.stack([cols, rows], axis=-1).astype(self.values.dtype) * self.spacing
        cell = jnp.sqrt(self.spacing[0] * self.spacing[1])
        weight = jnp.clip(0.5 - self.values / cell, 0.0, 1.0)
        total = jnp.sum(weight)
        centroid = jnp.sum(points * weight[..., None], axis=(0, 1)) / jnp.maximum(total, 1e-12)
        # The boundary lies |value| beyond a cell along its distance's gradient: out from the centroid
        # for the farthest cells.
        reach = jnp.sqrt(jnp.sum((points - centroid) ** 2, axis=-1)) - self.values
        rho = jnp.max(jnp.where(weight > 0, reach, 0.0))
        return centroid, rho

    def _grid_coordinates(self, points):
        col = (points[..., 0] - self.origin[0]) / self.spacing[0]
        row = (points[..., 1] - self.origin[1]) / self.spacing[1]
        return row, col

    def contains(self, points: Float[ArrayLike, "*batch 2"]) -> Bool[Array, "*batch"]:
        points = jnp.asarray(points)
        row, col = self._grid_coordinates(points)
        h, w = self.values.shape
        return (row >= 0) & (row <= h - 1) & (col >= 0) & (col <= w - 1)

    def distance(self, points: Float[ArrayLike, "*batch 2"]) -> Float[Array, "*batch"]:
        return self._lookup(points, self.interpolation)

    def coarse_distance(self, points: Float[ArrayLike, "*batch 2"]) -> Float[Array, "*batch"]:
        """The bilinear lookup (four samples instead of sixteen): it differs from the bicubic one
        by about h^2 |Hessian| / 8 (h the cell size), a few micrometres for an SDF's level sets at a
        finger's half-thickness from the surface, far below what the coarse sweep can resolve."""
        return self._lookup(points, "linear")

    def _lookup(self, points, interpolation: str):
        points = jnp.asarray(points)
        row, col = self._grid_coordinates(points)
        h, w = self.values.shape
        inside = (row >= 0) & (row <= h - 1) & (col >= 0) & (col <= w - 1)
        # Clamped coordinates keep the discarded branch finite (and its gradient zero).
        row = jnp.clip(jnp.where(inside, row, 0.0), 0, h - 1)
        col = jnp.clip(jnp.where(inside, col, 0.0), 0, w - 1)
        if interpolation == "cubic":
            value = _catmull_rom(cast(Array, self.cells), row, col, w)
        else:
            value = _bilinear(self.values, row, col)
        return jnp.where(inside, value, jnp.asarray(self.far, value.dtype))


def _bilinear(values: Float[Array, "h w"], row: Float[Array, "*batch"], col: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """Bilinear lookup at grid coordinates (row, col) within [0, H-1] x [0, W-1]."""
    h, w = values.shape
    # Between the four corners of the cell (the last row and column read the cell before them),
    # addressed by one flat index into the grid: on XLA:CPU this is faster over the whole estimate
    # than map_coordinates' two-dimensional gathers. The index is unsigned so that JAX does not wrap
    # negative indices (which would cost a select per corner).
    row0 = jnp.minimum(jnp.floor(row), h - 2)
    col0 = jnp.minimum(jnp.floor(col), w - 2)
    fy, fx = row - row0, col - col0
    index = row0.astype(jnp.uint32) * w + col0.astype(jnp.uint32)
    flat = values.reshape(-1)
    corner = lambda offset: flat.at[index + jnp.uint32(offset)].get(mode="promise_in_bounds")  # noqa: E731
    top = corner(0) + fx * (corner(1) - corner(0))
    bottom = corner(w) + fx * (corner(w + 1) - corner(w))
    return top + fy * (bottom - top)


#: Catmull-Rom (cubic convolution, a = -1/2) weights of the samples at -1, 0, 1, 2 of a point at
#: fraction t of the cell from 0 to 1, as polynomials: weight a is sum over k of _CATMULL_ROM[a, k] t^k.
_CATMULL_ROM = np.array([[0.0, -0.5, 1.0, -0.5], [1.0, 0.0, -2.5, 1.5], [0.0, 0.5, 2.0, -1.5], [0.0, 0.0, -0.5, 0.5]])


@jax.jit
def catmull_rom_cells(values: Float[Array, "h w"]) -> Float[Array, "cells 16"]:
    """The bicubic Catmull-Rom lookup of ``values`` as one polynomial per cell: row
    ``r (W-1) + c`` holds the coefficients ``C[k, l]`` (index ``4 k + l``) of the cell between
    rows r, r+1 and columns c, c+1, whose value at fractions (ty, tx) is sum C[k, l] ty^k tx^l.

    The 4 x 4 samples around a cell (rows r-1 ... r+2) include, beside the grid's edge, ghost
    samples extrapolated linearly past it (2 v0 - v1): a linear field stays exact and the lookup
    stays C1 up to the edge. Linear in ``values`` (so derivatives with respect to the samples
    pass through it)."""
    h, w = values.shape
    v = jnp.pad(values, 1, mode="reflect", reflect_type="odd")  # (h+2, w+2), ghosts 2 v0 - v1
    taps = [[v[a:a + h - 1, b:b + w - 1] for b in range(4)] for a in range(4)]  # rows r-1+a, columns c-1+b
    # C = M^T T M per cell, written out term by term with M's constants (its zeros dropped): one
    # elementwise pass over the grid that XLA fuses, where a stack-and-einsum made several.
    m = _CATMULL_ROM
    along_x = [[sum(float(m[b, l]) * taps[a][b] for b in range(4) if m[b, l] != 0.0) for l in range(4)]
               for a in range(4)]
    c = [sum(float(m[a, k]) * along_x[a][l] for a in range(4) if m[a, k] != 0.0) for k in range(4) for l in range(4)]
    return jnp.stack(c, axis=-1).reshape((h - 1) * (w - 1), 16)


def _cell_of(row: Array, col: Array, h: int, w: int) -> tuple[Array, Array, Array]:
    """The row of :func:`catmull_rom_cells` of the cell holding grid coordinates (row, col) within
    [0, H-1] x [0, W-1] (the last row and column read the cell before them), and the fractions
    (ty, tx) within it."""
    row0 = jnp.minimum(jnp.floor(row), h - 2)
    col0 = jnp.minimum(jnp.floor(col), w - 2)
    return row0.astype(jnp.uint32) * jnp.uint32(w - 1) + col0.astype(jnp.uint32), row - row0, col - col0


def _cell_coefficients(cells: Array, index: Array) -> list[Array]:
    """The 16 coefficients of each ``index``'s cell: sixteen gathers by flat index from one row of
    64 bytes, which XLA:CPU fuses with the polynomial (a single gather of 16-wide rows ran slower)."""
    flat = cells.reshape(-1)
    start = index * jnp.uint32(16)
    return [flat.at[start + jnp.uint32(k)].get(mode="promise_in_bounds") for k in range(16)]


def _horner(c: list[Array], t: Array) -> Array:
    return ((c[3] * t + c[2]) * t + c[1]) * t + c[0]


def _horner_slope(c: list[Array], t: Array) -> Array:
    return (3.0 * c[3] * t + 2.0 * c[2]) * t + c[1]


@partial(jax.custom_jvp, nondiff_argnums=(3,))
def _catmull_rom(cells: Float[Array, "cells 16"], row: Float[Array, "*batch"], col: Float[Array, "*batch"],
                 w: int) -> Float[Array, "*batch"]:
    """Bicubic Catmull-Rom lookup at grid coordinates (row, col) within [0, H-1] x [0, W-1] of a
    grid W samples wide, from its :func:`catmull_rom_cells`.

    Its derivative (custom JVP) is the analytic one, from the same coefficients: left to plain
    autodiff, the reverse pass ran much slower than the lookup. Higher derivatives (the Hessian the
    implicit differentiation of an equilibrium uses) differentiate that rule.
    """
    h = cells.shape[0] // (w - 1) + 1
    index, ty, tx = _cell_of(row, col, h, w)
    c = _cell_coefficients(cells, index)
    return _horner([_horner(c[4 * k:4 * k + 4], tx) for k in range(4)], ty)


def _catmull_rom_jvp(w, primals, tangents):
    cells, row, col = primals
    d_cells, d_row, d_col = tangents
    h = cells.shape[0] // (w - 1) + 1
    index, ty, tx = _cell_of(row, col, h, w)
    c = _cell_coefficients(cells, index)
    along_x = [_horner(c[4 * k:4 * k + 4], tx) for k in range(4)]  # one polynomial in ty
    value = _horner(along_x, ty)
    tangent = jnp.zeros_like(value)
    if not isinstance(d_row, SymbolicZero):
        tangent = tangent + _horner_slope(along_x, ty) * d_row
    if not isinstance(d_col, SymbolicZero):
        tangent = tangent + _horner([_horner_slope(c[4 * k:4 * k + 4], tx) for k in range(4)], ty) * d_col
    if not isinstance(d_cells, SymbolicZero):  # the lookup is linear in the coefficients
        dc = _cell_coefficients(d_cells, index)
        tangent = tangent + _horner([_horner(dc[4 * k:4 * k + 4], tx) for k in range(4)], ty)
    return value, tangent


_catmull_rom.defjvp(_catmull_rom_jvp, symbolic_zeros=True)


class PolygonSDF(AbstractSDF):
    """Exact signed distance to a closed polygon; differentiable in the points and the vertices.

    A polygon of many edges (16 or more) made from concrete vertices indexes its edges by the
    cells of a grid around it (``edge_cells``), so that a lookup reads the dozen edges that can be
    nearest to its point instead of all of them: the same distance, several times faster for the
    README's 128-gon. It is exact everywhere within 20 mm of the polygon's bounding box, except
    more than 2 mm deep inside, where a point may read deeper than it is; farther out it reads an
    upper bound of the distance (nothing touches there). Vertices replaced after construction
    (``eqx.tree_at``, an optimiser's update) no longer match the index: the lookup then reads
    every edge, exactly, at the old speed.

    Attributes:
        vertices: (V, 2) polygon corners in mm, V >= 3, in order (either orientation); the edge from
            the last vertex back to the first closes it.
        cells: the edges' cell index (:class:`softgrip_jax._polygon_cells.EdgeCells`), or None: made
            from concrete vertices with ``edge_cells=True`` when it reads fewer edges.

    Example:
        >>> import jax.numpy as jnp
        >>> square = PolygonSDF(jnp.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]]))
        >>> square.distance(jnp.array([[5.0, 5.0], [13.0, 14.0]])).tolist()
        [-5.0, 5.0]
    """

    vertices: Float[Array, "v 2"]
    cells: EdgeCells | None

    def __init__(self, vertices: Float[ArrayLike, "v 2"], edge_cells: bool = True) -> None:
        self.vertices = _as_array(vertices)
        concrete = not isinstance(self.vertices, jax.core.Tracer)
        well_formed = jnp.ndim(self.vertices) == 2 and jnp.shape(self.vertices)[1] == 2  # else __check_init__ says
        usable = edge_cells and concrete and well_formed and bool(np.all(np.isfinite(np.asarray(self.vertices))))
        self.cells = make_edge_cells(self.vertices) if usable else None

    @property
    def largest_piece(self) -> int:  # type: ignore[override]
        """Without the cell index a lookup materialises (points, edges) arrays: in pieces of 4096
        candidates they outgrow the CPU's caches and the batch runs slower than in pieces of 256
        (benchmarks/RESULTS.md); with it, as a grid's."""
        return AbstractSDF.largest_piece if self.cells is not None else 256

    @property
    def piece_overhead(self) -> int:  # type: ignore[override]
        """Without the cell index each candidate reads every edge, so a candidate costs as much as
        a piece's fixed cost does against a grid: a piece of one is worth about 16 candidates of a
        piece of 256; with it, as a grid's."""
        return AbstractSDF.piece_overhead if self.cells is not None else 16

    def check_cells(self) -> None:
        """Raise :class:`SoftgripError` when the cell index belongs to other vertices than the
        polygon's (vertices replaced after construction, by ``eqx.tree_at`` or an optimiser's
        update): its lookup would read the old polygon's candidate edges. Called by every entry
        point before tracing; free when the polygon is as constructed (the same array)."""
        cells = self.cells
        if cells is None or cells.vertices is self.vertices or isinstance(self.vertices, jax.core.Tracer):
            return
        if jnp.shape(cells.vertices) == jnp.shape(self.vertices) and np.array_equal(
                np.asarray(cells.vertices), np.asarray(self.vertices)):
            return
        raise SoftgripError("PolygonSDF: its vertices were replaced after construction (eqx.tree_at or an optimiser's "
                            "update?) and its edges' cell index belongs to the old ones: make a new "
                            "PolygonSDF(new_vertices) (or pass edge_cells=False to read every edge)")

    def __check_init__(self):
        shape = jnp.shape(self.vertices)
        if len(shape) != 2 or shape[1] != 2 or shape[0] < 3:
            raise SoftgripError(f"PolygonSDF.vertices must have shape (V, 2) with V >= 3, got {shape}")
        if not isinstance(self.vertices, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(self.vertices))):
            raise SoftgripError("PolygonSDF.vertices must be finite")

    @classmethod
    def regular(
        cls,
        center: tuple[float, float] | Float[ArrayLike, "2"],
        radius: float | Float[ArrayLike, ""],
        n_vertices: int = 128,
        angle: float | Float[ArrayLike, ""] = 0.0,
    ) -> PolygonSDF:
        """A regular polygon (a circle for large ``n_vertices``) of circumradius ``radius`` mm."""
        t = angle + 2 * jnp.pi * jnp.arange(n_vertices) / n_vertices
        center = jnp.asarray(center, dtype=jnp.result_type(float))
        return cls(center + radius * jnp.stack([jnp.cos(t), jnp.sin(t)], axis=-1))

    def all_finite(self) -> Bool[Array, ""]:
        """Whether every vertex is finite (checked at construction unless traced)."""
        return jnp.all(jnp.isfinite(self.vertices))

    def to_grid(self, cell_mm: float = 0.25, margin_mm: float = 60.0, interpolation: str = "cubic") -> SDFGrid:
        """The polygon's signed distance sampled on an :class:`SDFGrid` (exact at the grid's nodes),
        for batches: a grid lookup reads 16 samples where the polygon's reads every edge, so a batch
        of many poses runs several times faster (benchmarks/RESULTS.md), with the bicubic lookup's
        small error between the nodes (about cell_mm^2 / (8 R) mm on an arc of radius R mm).

        Args:
            cell_mm: the grid's spacing (mm), > 0.
            margin_mm: how far (mm, >= 0) the grid reaches beyond the polygon's bounding box on
                every side. Every finger base of the poses scored must lie on the grid: an estimate
                whose base is off it is invalid (``Status.BASE_OUTSIDE_SDF``), so give at least
                the distance from the object to the farthest base (a finger's length and half the
                base separation, plus how far the poses range).
            interpolation: the grid's lookup, ``"cubic"`` (C1, the default) or ``"linear"``.

        Example:
            >>> square = PolygonSDF(jnp.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]]))
            >>> grid = square.to_grid(cell_mm=0.5, margin_mm=5.0)
            >>> grid.values.shape, round(float(grid.distance(jnp.array([13.0, 5.0]))), 4)
            ((41, 41), 3.0)
        """
        for name, value, least in (("cell_mm", cell_mm, None), ("margin_mm", margin_mm, 0.0)):
            good = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
            if not good or (value <= 0 if least is None else value < least):
                raise SoftgripError(f"PolygonSDF.to_grid: {name} must be a finite number of mm "
                                    f"{'> 0' if least is None else '>= 0'}, got {value!r}")
        vertices = np.asarray(self.vertices, np.float64)
        low = vertices.min(axis=0) - margin_mm
        width, height = (int(n) + 1 for n in np.ceil((vertices.max(axis=0) + margin_mm - low) / cell_mm))
        shape = (height, width)
        if shape[0] * shape[1] > _MAX_GRID_CELLS:
            raise SoftgripError(f"PolygonSDF.to_grid: a grid of {shape[0]} x {shape[1]} cells of {cell_mm:g} mm is "
                                f"too large (more than {_MAX_GRID_CELLS:,} cells): use larger cells or a smaller margin_mm")
        # A few rows of the (H, W, 2) points at a time: all at once the lookup would hold H x W x V arrays.
        rows = jax.jit(lambda points: jax.lax.map(self.distance, points, batch_size=8))
        return SDFGrid.sample(rows, origin=(float(low[0]), float(low[1])), spacing=(cell_mm, cell_mm), shape=shape,
                              interpolation=cast(Literal["cubic", "linear"], interpolation))

    def mass_properties(self) -> tuple[Float[Array, "2"], Float[Array, ""]]:
        """Area centroid (the shoelace formula, either orientation) and ``rho``, the farthest vertex.

        Example:
            >>> import jax.numpy as jnp
            >>> c, rho = PolygonSDF(jnp.array([[0.0, 0.0], [4.0, 0.0], [4.0, 2.0], [0.0, 2.0]])).mass_properties()
            >>> c.tolist(), round(float(rho), 4)
            ([2.0, 1.0], 2.2361)
        """
        a = self.vertices
        b = jnp.roll(a, -1, axis=0)
        cross = a[:, 0] * b[:, 1] - b[:, 0] * a[:, 1]
        area = 0.5 * jnp.sum(cross)
        centroid = jnp.sum((a + b) * cross[:, None], axis=0) / (6.0 * area)
        rho = jnp.max(safe_norm(a - centroid))
        return centroid, rho

    def distance(self, points: Float[ArrayLike, "*batch 2"]) -> Float[Array, "*batch"]:
        points = jnp.asarray(points)
        if self.cells is None:
            return self.edge_distance(points)
        return cells_distance(self.cells, self.vertices, points)

    def coarse_distance(self, points: Float[ArrayLike, "*batch 2"]) -> Float[Array, "*batch"]:
        """With the cell index, the bilinear lookup of the exact distance at the cells' corners
        (four samples; it differs from :meth:`distance` by about h^2 |Hessian| / 8, h the cell size,
        micrometres at a finger's half-thickness from the outline, where only signs are read);
        beyond the cells, the clamped point's value plus the distance to it. Without it,
        :meth:`distance`."""
        if self.cells is None:
            return self.distance(points)
        points = jnp.asarray(points)
        cells = self.cells
        h, w = cells.nodes.shape
        upper = jnp.asarray([w - 1, h - 1], points.dtype)
        grid = (points - cells.origin) / cells.cell_mm
        clamped = jnp.clip(grid, 0.0, upper)
        beyond = safe_norm(grid - clamped) * cells.cell_mm
        return _bilinear(cells.nodes, clamped[..., 1], clamped[..., 0]) + beyond

    @property
    def has_coarse_lookup(self) -> bool:
        """Whether the cell index gives :meth:`coarse_distance` a bilinear lookup of its own."""
        return self.cells is not None

    def edge_distance(self, points: Float[ArrayLike, "*batch 2"]) -> Float[Array, "*batch"]:
        """:meth:`distance` read from every edge (without the cell index)."""
        return _edge_distance(self.vertices, jnp.asarray(points))


def _edge_distance(vertices: Float[Array, "v 2"], points: Float[Array, "*batch 2"]) -> Float[Array, "*batch"]:
    """Signed distance (mm) from ``points`` to the polygon of ``vertices``, every edge read."""
    a = vertices
    b = jnp.roll(a, -1, axis=0)
    ab = b - a
    p = points[..., None, :]
    ap = p - a
    t = jnp.clip(safe_divide(jnp.sum(ap * ab, -1), jnp.sum(ab * ab, -1)), 0.0, 1.0)
    d2 = jnp.sum((ap - t[..., None] * ab) ** 2, axis=-1)
    dist = _safe_sqrt(jnp.min(d2, axis=-1))
    # Even-odd rule: count edges crossed by a ray from the point toward +x.
    py, px = p[..., 1], p[..., 0]
    straddles = (a[:, 1] > py) != (b[:, 1] > py)
    x_cross = a[:, 0] + safe_divide((py - a[:, 1]) * ab[:, 0], ab[:, 1])
    inside = jnp.sum(straddles & (px < x_cross), axis=-1) % 2 == 1
    return jnp.where(inside, -dist, dist)


#: The largest grid :meth:`PolygonSDF.to_grid` makes (cells): 256 MB of float32 samples.
_MAX_GRID_CELLS = 64_000_000


def _safe_sqrt(x: Array) -> Array:
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)
