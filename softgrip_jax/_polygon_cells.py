"""A polygon's edges indexed by the cells of a grid, so that a distance lookup reads a few edges.

:class:`softgrip_jax.PolygonSDF`'s exact lookup reads every edge of the polygon for every point
(the README's 128-gon: 128 segment distances a point). :class:`EdgeCells` lists, for each square
cell of a grid laid over the polygon, the edges that can be the nearest one to some point of the
cell, and the lookup reads only those: the same distance, exactly, from a dozen edges.

Which edges a cell keeps: for a cell of centre ``c`` and half-diagonal ``h``, the edge nearest to a
point ``p`` of the cell is at most ``d_min(c) + h`` from ``p`` (``d_min(c)`` the nearest edge's
distance from ``c``), hence at most ``d_min(c) + 2 h`` from ``c`` (triangle inequality). A cell
keeping every edge within ``d_min(c) + 2 h`` of its centre therefore holds the nearest edge of each
of its points. Every edge that crosses the cell is within ``h`` of its centre, so it is kept too,
and the sign (inside or not, the even-odd rule) follows from the centre's, flipped once for each
kept edge the segment from the centre to the point crosses.

A cell deep inside the polygon (more than :data:`EXACT_DEPTH_MM` from the outline; near the middle of
a disc every edge is about as far) may hold more candidates than the table's width ``K``: it keeps
its ``K`` nearest, and a point there reads at least as deep as it is (the sign is right). Points
beyond the grid (``margin_mm`` around the polygon's bounding box) read their nearest cell's edges:
an upper bound of the distance, outside the polygon, where no finger is near it.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from softgrip_jax._safe import safe_divide

#: Inside the polygon, the depth (mm) to which every cell is exact; deeper cells may be truncated.
EXACT_DEPTH_MM = 2.0
#: How far (mm) the grid reaches beyond the polygon's bounding box.
MARGIN_MM = 20.0
#: A polygon with fewer edges is looked up edge by edge (the table would read as many).
MIN_EDGES = 16
#: The table is kept only when a cell reads at most this fraction of the edges: a gathered edge
#: costs about what three edges read in a row do.
MAX_FRACTION = 1 / 3
#: The most cells a table has (memory: cells x K edge indices).
MAX_CELLS = 1 << 17
#: The most cell-edge distances made for a table (its construction time).
MAX_WORK = 1 << 23
#: Slack (mm) on which edges a cell keeps: a float32 point a rounding error outside its cell is
#: still covered.
_SLACK_MM = 1e-3
#: Where a cell's unused candidate slots point (mm): no point of the grid is near it.
_FAR_MM = 1.0e6


class EdgeCells(eqx.Module):
    """The candidate edges of each cell of a square grid (see the module's docstring).

    Attributes:
        edges: (H * W, K) indices of the candidate edges of each cell (edge ``i`` runs from vertex
            ``i`` to ``i + 1``; cell (row, col) is row ``row * W + col``), -1 where a cell has
            fewer than K.
        ends: (H * W, 5, K) the candidates' start vertex a (x, y), their vector b - a (x, y) and
            1 / |b - a|^2 (mm, 1/mm^2), copied from the vertices for a fast scan; a cell with fewer
            than K repeats a point far away.
        inside: (H, W) whether each cell's centre is inside the polygon (the even-odd rule).
        origin: (2,) the corner (mm) of cell (0, 0); cell (row, col) spans
            ``origin + (col, row) * cell_mm`` to ``origin + (col + 1, row + 1) * cell_mm``.
        cell_mm: the cells' side (mm).
        nodes: (H + 1, W + 1) the exact signed distance (mm) at the cells' corners, for a bilinear
            coarse lookup.
        vertices: (V, 2) the vertices the table was made for (mm), the polygon's own array.
    """

    edges: Int[Array, "c k"]
    ends: Float[Array, "c 5 k"]
    inside: Bool[Array, "h w"]
    origin: Float[Array, "2"]
    cell_mm: float = eqx.field(static=True)
    nodes: Float[Array, "h1 w1"]
    vertices: Float[Array, "v 2"]


def edge_cells(polygon: Float[Array, "v 2"]) -> EdgeCells | None:
    """The cell table of a polygon's (V, 2) concrete vertices (mm), or None when reading every edge
    is as cheap (few edges, or edges so dense that a cell keeps more than a third of them). The
    table keeps ``polygon`` itself (the same array) as the vertices it belongs to."""
    vertices = np.asarray(polygon, np.float64)
    n = len(vertices)
    if n < MIN_EDGES:
        return None
    a, b = vertices, np.roll(vertices, -1, axis=0)
    lengths = np.hypot(*(b - a).T)
    low = vertices.min(axis=0) - MARGIN_MM
    span = vertices.max(axis=0) + MARGIN_MM - low
    # Cells about the edges' length keep a handful of edges near the outline (larger ones keep more
    # of the far field's); fewer, larger cells when the grid, or the work of making it, would be
    # too large.
    cell = float(np.clip(0.7 * np.median(lengths), 0.25, 1.0))
    cell = max(cell, math.sqrt(span[0] * span[1] / MAX_CELLS), math.sqrt(span[0] * span[1] * n / MAX_WORK))
    width, height = (int(k) for k in np.ceil(span / cell))
    cols, rows = np.meshgrid(np.arange(width), np.arange(height))
    centres = low + (np.stack([cols, rows], axis=-1).reshape(-1, 2) + 0.5) * cell
    half_diagonal = cell * math.sqrt(0.5)

    candidates, nearest = [], []
    for start in range(0, len(centres), 4096):  # (cells, V) distances a block at a time
        d = _segment_distances(centres[start:start + 4096], a, b)
        d_min = d.min(axis=1, keepdims=True)
        keep = d <= d_min + 2 * half_diagonal + _SLACK_MM
        order = np.argsort(np.where(keep, d, np.inf), axis=1, kind="stable")
        candidates.append((order, keep.sum(axis=1)))
        nearest.append(d_min[:, 0])
    d_min = np.concatenate(nearest)
    order = np.concatenate([o for o, _ in candidates])
    counts = np.concatenate([c for _, c in candidates])
    inside = _even_odd(centres, a, b)
    corners = low + np.stack(np.meshgrid(np.arange(width + 1), np.arange(height + 1)), axis=-1).reshape(-1, 2) * cell
    nodes = np.concatenate([_segment_distances(corners[i:i + 4096], a, b).min(axis=1)
                            for i in range(0, len(corners), 4096)])
    nodes = np.where(_even_odd(corners, a, b), -nodes, nodes).reshape(height + 1, width + 1)
    must_be_exact = ~inside | (d_min <= EXACT_DEPTH_MM + half_diagonal)
    k = int(counts[must_be_exact].max())
    if k > MAX_FRACTION * n:
        return None
    table = np.where(np.arange(k) < np.minimum(counts, k)[:, None], order[:, :k], -1)
    ab = b - a
    squared = np.sum(ab * ab, axis=1)
    inverse = np.divide(1.0, squared, out=np.zeros_like(squared), where=squared > 0)  # a repeated vertex: t = 0
    edge_rows = np.stack([a[:, 0], a[:, 1], ab[:, 0], ab[:, 1], inverse])
    far = np.array([_FAR_MM, _FAR_MM, 0.0, 0.0, 0.0])[:, None]
    ends = np.where(table[:, None, :] >= 0, edge_rows[:, np.maximum(table, 0)].transpose(1, 0, 2), far)
    dtype = jnp.result_type(float)
    return EdgeCells(edges=jnp.asarray(table, jnp.int16 if n < 2 ** 15 else jnp.int32), ends=jnp.asarray(ends, dtype),
                     inside=jnp.asarray(inside.reshape(height, width)), origin=jnp.asarray(low, dtype), cell_mm=cell,
                     nodes=jnp.asarray(nodes, dtype), vertices=polygon)


def _segment_distances(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P, V) distances (mm) from each of (P, 2) points to each segment a[i] -> b[i]."""
    ab = b - a
    ap = points[:, None, :] - a
    t = np.clip(np.einsum("pvi,vi->pv", ap, ab) / np.maximum(np.einsum("vi,vi->v", ab, ab), 1e-300), 0.0, 1.0)
    return np.hypot(*np.moveaxis(ap - t[..., None] * ab, -1, 0))


def _even_odd(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P,) whether each of (P, 2) points is inside the polygon of edges a[i] -> b[i] (a ray
    toward +x crosses an odd number of edges; as :meth:`PolygonSDF.distance` decides it)."""
    inside = np.zeros(len(points), bool)
    for start in range(0, len(points), 4096):
        p = points[start:start + 4096, None, :]
        straddles = (a[:, 1] > p[..., 1]) != (b[:, 1] > p[..., 1])
        with np.errstate(divide="ignore", invalid="ignore"):
            x_cross = a[:, 0] + (p[..., 1] - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
        inside[start:start + 4096] = np.sum(straddles & (p[..., 0] < x_cross), axis=1) % 2 == 1
    return inside


def cells_distance(table: EdgeCells, vertices: Float[Array, "v 2"], points: Float[Array, "*batch 2"]
                   ) -> Float[Array, "*batch"]:
    """Signed distance (mm) from ``points`` to the polygon of ``vertices`` read from its cells'
    candidate edges (differentiable in the points and the vertices; the table is constant).

    The nearest candidate and the sign are found on the table's copies, without derivatives; the
    distance to that one edge is then taken again from ``vertices``, so that gradients and
    Hessians follow one edge, not K."""
    h, w = table.inside.shape
    p = jax.lax.stop_gradient(points)
    cell = (p - table.origin) / table.cell_mm
    ij = jnp.floor(cell).astype(jnp.int32)
    col, row = jnp.clip(ij[..., 0], 0, w - 1), jnp.clip(ij[..., 1], 0, h - 1)
    on_table = (col == ij[..., 0]) & (row == ij[..., 1])
    flat = (row * w + col).astype(jnp.uint32)
    ends = table.ends.at[flat].get(mode="promise_in_bounds")  # (*batch, 5, K)
    ax, ay, abx, aby, inverse = (ends[..., i, :] for i in range(5))
    apx, apy = p[..., :1] - ax, p[..., 1:] - ay
    t = jnp.clip((apx * abx + apy * aby) * inverse, 0.0, 1.0)
    nearest = jnp.argmin((apx - t * abx) ** 2 + (apy - t * aby) ** 2, axis=-1)
    # Even-odd from the cell's centre: each candidate the segment centre -> point crosses flips it.
    cx, cy = (table.origin[i] + (index.astype(p.dtype) + 0.5) * table.cell_mm for i, index in ((0, col), (1, row)))
    pcx, pcy = (p[..., 0] - cx)[..., None], (p[..., 1] - cy)[..., None]
    acx, acy = ax - cx[..., None], ay - cy[..., None]
    a_side = pcx * acy - pcy * acx > 0
    b_side = pcx * (acy + aby) - pcy * (acx + abx) > 0
    c_side = abx * -acy - aby * -acx > 0
    p_side = abx * apy - aby * apx > 0
    crossings = jnp.sum((a_side != b_side) & (c_side != p_side), axis=-1)
    inside = on_table & (table.inside.reshape(-1).at[flat].get(mode="promise_in_bounds") != (crossings % 2 == 1))
    edge = jnp.take_along_axis(table.edges.at[flat].get(mode="promise_in_bounds"), nearest[..., None], axis=-1)[..., 0]
    # The chosen edge and its two neighbours: where two edges tie at their shared vertex, the scan's
    # rounding (which differs between a batch's lanes) may choose either; the least of the three
    # reads the same whichever it chose, so an element's answer does not depend on its batch.
    n = vertices.shape[0]
    edges = (edge.astype(jnp.int32)[..., None] + jnp.arange(-1, 2, dtype=jnp.int32)) % n
    a = vertices[edges]
    b = vertices[(edges + 1) % n]
    ab, ap = b - a, points[..., None, :] - a
    s = jnp.clip(safe_divide(jnp.sum(ap * ab, -1), jnp.sum(ab * ab, -1)), 0.0, 1.0)
    d2 = jnp.min(jnp.sum((ap - s[..., None] * ab) ** 2, axis=-1), axis=-1)
    positive = d2 > 0
    dist = jnp.where(positive, jnp.sqrt(jnp.where(positive, d2, 1.0)), 0.0)
    return jnp.where(inside, -dist, dist)


def _cross(u: Array, v: Array) -> Array:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]
