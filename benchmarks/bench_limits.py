"""How close the default batch path comes to the cost of its own object lookups.

Run from the repository root:

    .venv/bin/python benchmarks/bench_limits.py

Counts, at run time, how many points each batch call looks up in the object (a counting wrapper
around the SDF: a host callback adds the number of points of every lookup that runs, so a loop's
iterations and the groups that ``where_needed`` skips are counted as they run; a gradient or Hessian
at a point counts as one lookup), then times one lookup in bulk (2^20 points) on each object.
(Coarse lookups, a grid's bilinear ones for the contact sweep's bracketing, are counted apart.)
Lookups x bulk cost is a floor on the call's time: the arithmetic around the lookups (the chain's
kinematics, the solver's linear algebra, the score's hull) comes on top. Prints, per call, the
lookups per candidate, that floor, the measured time and their ratio.

Scenes: the speedcheck's (a 20 mm disc on an SDFGrid of 0.25 mm cells, N = 20, L 52 mm, Theta
0.7 rad, r 4 mm, 4,096 bases uniform in a 24 x 24 mm square) for ``estimate_batch``; the README's
planner scene (a 128-vertex PolygonSDF disc, the README's gripper, 4,096 poses in its ranges) for
``score``, on the polygon and on its ``to_grid()``. Defaults throughout.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(1, str(Path(__file__).resolve().parent))

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _machine import best_of, describe  # noqa: E402

import softgrip_jax as sg  # noqa: E402
from softgrip_jax._compile import compiler_options  # noqa: E402


class CountingSDF(sg.AbstractSDF):
    """``inner`` whose every lookup reports its number of points to ``tally`` (a host callback), its
    coarse lookups (where ``inner`` has them) to ``coarse_tally``."""

    inner: sg.AbstractSDF
    tally: Callable = eqx.field(static=True)
    coarse_tally: Callable = eqx.field(static=True)

    def distance(self, points):
        points = jnp.asarray(points)
        return self.inner.distance(points) + _reported(self.tally, points)

    def coarse_distance(self, points):
        points = jnp.asarray(points)
        return self.inner.coarse_distance(points) + _reported(self.coarse_tally, points)

    @property
    def has_coarse_lookup(self):
        return self.inner.has_coarse_lookup

    def contains(self, points):
        return self.inner.contains(points)

    def all_finite(self):
        return self.inner.all_finite()

    def mass_properties(self):
        return self.inner.mass_properties()


@jax.custom_jvp
def _zero_of(points, report):
    return report


@_zero_of.defjvp
def _zero_of_jvp(primals, tangents):
    points, report = primals
    return report, jnp.zeros_like(report)


def _reported(tally, points):
    """Zeros of the lookup's shape, from a host callback that counts its points."""
    shape = jax.ShapeDtypeStruct(points.shape[:-1], points.dtype)
    report = jax.pure_callback(tally, shape, jax.lax.stop_gradient(points), vmap_method="expand_dims")
    return _zero_of(points, report)


def bulk_ns(sdf, low, high, rng, coarse=False):
    """One lookup's cost (ns) in bulk, at 2^20 random points in the box [low, high]: the fastest of
    a few layouts (4,096 or 65,536 points at a time, or all at once but on a polygon, whose
    (points, edges) arrays would not fit in memory) and of the batch programs' compile options.
    ``coarse``: of its coarse lookup (``coarse_distance``)."""
    times = []
    for chunk in (4096, 65536) + (() if isinstance(sdf, sg.PolygonSDF) else (1 << 20,)):
        points = jnp.asarray(rng.uniform(low, high, ((1 << 20) // chunk, chunk, 2)).astype(np.float32))
        for est in (sg.Geometric(), sg.Mechanics()):
            lookup = (lambda s, p: s.coarse_distance(p)) if coarse else (lambda s, p: s.distance(p))
            run = jax.jit(lambda s, p, lookup=lookup: jax.lax.map(lambda q: lookup(s, q), p),
                          compiler_options=compiler_options(est) or None)
            times.append(best_of(lambda run=run, points=points: run(sdf, points), 5, warm=True) / (1 << 20) * 1e9)
    return min(times)


def main():
    print(describe())
    rng = np.random.default_rng(0)
    count = [0, 0]  # lookups, coarse lookups

    def tally(points, which=0):
        count[which] += int(np.prod(points.shape[:-1]))
        return np.zeros(points.shape[:-1], points.dtype)

    def lookups(call, sdf, n):
        """Lookups and coarse lookups per candidate of ``call(counting sdf)`` (one run after a
        compiling one)."""
        counting = CountingSDF(inner=sdf, tally=tally, coarse_tally=lambda p: tally(p, 1))
        jax.block_until_ready(call(counting))
        count[:] = [0, 0]
        jax.block_until_ready(call(counting))
        return count[0] / n, count[1] / n

    finger = sg.FingerModel(length=52.0, theta_entire=0.7, half_thickness=4.0, n_links=20)
    xs = np.arange(-40.0, 80.0, 0.25)
    x, y = np.meshgrid(xs, xs, indexing="xy")
    grid = sg.SDFGrid(values=jnp.asarray((np.hypot(x - 25.0, y - 45.0) - 10.0).astype(np.float32)),
                      origin=jnp.array([-40.0, -40.0]), spacing=jnp.array([0.25, 0.25]))
    n = 4096
    bases = rng.uniform(-12.0, 12.0, (n, 2)).astype(np.float32)
    grid_ns = bulk_ns(grid, -39.0, 79.0, rng), bulk_ns(grid, -39.0, 79.0, rng, coarse=True)
    print(f"one SDFGrid lookup in bulk: bicubic {grid_ns[0]:.1f} ns, its coarse (bilinear) {grid_ns[1]:.1f} ns")
    rows = []
    for est in (sg.Geometric(), sg.Mechanics()):
        call = lambda sdf, est=est: sg.estimate_batch(finger, sdf, bases, estimator=est).joints  # noqa: E731
        rows.append((f"estimate_batch, speedcheck grid, {type(est).__name__}()", lookups(call, grid, n), grid_ns,
                     best_of(lambda: call(grid), 3, warm=True) / n))

    readme = sg.FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=20)
    gripper = sg.Gripper(left=readme, right=readme, base_separation=56.0)
    polygon = sg.PolygonSDF.regular(center=(0.0, 38.0), radius=15.0, n_vertices=128)
    polygon_grid = polygon.to_grid()
    poses = np.c_[rng.uniform(-10.0, 10.0, (n, 2)), rng.uniform(-0.2, 0.2, n)].astype(np.float32)
    # (With its cell index the polygon's coarse lookup is bilinear on corner samples; without, its lookup.)
    polygon_ns = bulk_ns(polygon, -60.0, 100.0, rng), bulk_ns(polygon, -60.0, 100.0, rng, coarse=True)
    polygon_grid_ns = bulk_ns(polygon_grid, -60.0, 100.0, rng), bulk_ns(polygon_grid, -60.0, 100.0, rng, coarse=True)
    print(f"one 128-edge PolygonSDF lookup in bulk: {polygon_ns[0]:.1f} ns, coarse {polygon_ns[1]:.1f} ns; "
          f"its to_grid(): {polygon_grid_ns[0]:.1f} ns, coarse {polygon_grid_ns[1]:.1f} ns")
    for name, sdf, ns in (("PolygonSDF", polygon, polygon_ns), ("to_grid()", polygon_grid, polygon_grid_ns)):
        for est in (sg.Geometric(), sg.Mechanics()):
            m = n if isinstance(est, sg.Geometric) else n // 4
            call = lambda s, est=est, m=m: sg.score(gripper, s, poses[:m], estimator=est).score  # noqa: E731
            rows.append((f"score, README scene, {name}, {type(est).__name__}()", lookups(call, sdf, m), ns,
                         best_of(lambda: call(sdf), 3, warm=True) / m))

    print("| call (defaults) | lookups per candidate (+ coarse) | floor: lookups x bulk cost | measured | "
          "floor / measured |")
    print("|---|---|---|---|---|")
    for name, (fine, coarse), (fine_ns, coarse_ns), seconds in rows:
        floor = (fine * fine_ns + coarse * coarse_ns) * 1e-9
        print(f"| {name} | {fine:,.0f} (+ {coarse:,.0f}) | {floor * 1e6:.2f} us | {seconds * 1e6:.2f} us | "
              f"{floor / seconds:.2f} |")


if __name__ == "__main__":
    main()
