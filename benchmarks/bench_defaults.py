"""The batch path at default settings, as a planner gets it without options (issue 42's figures).

Run from the repository root (the compilation cache off, one process, about 5 minutes):

    .venv/bin/python benchmarks/bench_defaults.py            # every row
    .venv/bin/python benchmarks/bench_defaults.py --only estimate --only sizes

Rows (every call at its defaults: no ``chunk_size``, no ``workers``, default interpolation):

* ``estimate``: ``estimate_batch`` on a 20 mm disc as an ``SDFGrid`` (0.25 mm cells), one finger of
  N = 20 (L 52 mm, Theta 0.7 rad, r 4 mm), 100,000 bases uniform in a 24 x 24 mm square (most
  fingers touch): candidate-fingers/s with ``Geometric()`` and (20,000 bases) the default
  estimator, best of 3 after a compiling call; one ``estimate`` under ``jax.jit``, median of 101.
  The scene of ``../shared/speedcheck.py``.
* ``planner``: ``score`` on the README's planner scene (its gripper, ``PolygonSDF.regular`` disc of
  128 vertices, and the same disc sampled by ``PolygonSDF.to_grid()``), 10,000 random poses around
  the disc: poses/s with each estimator; one pose, warm (median of 21 calls of ``score`` on a (1, 3)
  batch); robust K = 16 on 1,000 poses.
* ``pieces``: ``estimate_batch`` (Geometric(), the ``estimate`` scene, 16,384 bases) with each
  fixed ``chunk_size`` of ``PIECE_BUCKETS``: candidate-fingers/s, and the time of one piece per
  worker, from which the fixed cost per piece that ``bucket_piece`` weighs is read.
* ``sizes``: one process's calls of ``score`` (Geometric(), the README scene) with batch sizes
  1 ... 10,000: the piece size chosen, the time of the call once its piece size has compiled,
  and poses/s: what the bucketed pieces cost a planner calling with any batch size.

Prints Markdown rows for benchmarks/RESULTS.md, headed by the tree's commit and the machine.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("SOFTGRIP_JAX_CACHE", "0")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import best_of, describe  # noqa: E402

import softgrip_jax as sg  # noqa: E402
from softgrip_jax._concurrent import bucket_piece, worker_count  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def first_and_best(fn, k=3):
    t = time.perf_counter()
    jax.block_until_ready(fn())
    return time.perf_counter() - t, best_of(fn, k)


def estimate_scene():
    finger = sg.FingerModel(length=52.0, theta_entire=0.7, half_thickness=4.0, n_links=20)
    xs = np.arange(-40.0, 80.0, 0.25)
    x, y = np.meshgrid(xs, xs, indexing="xy")
    disc = (np.hypot(x - 25.0, y - 45.0) - 10.0).astype(np.float32)
    sdf = sg.SDFGrid(values=jnp.asarray(disc), origin=jnp.array([-40.0, -40.0]), spacing=jnp.array([0.25, 0.25]))
    bases = np.random.default_rng(0).uniform(-12.0, 12.0, (100_000, 2)).astype(np.float32)
    return finger, sdf, bases


def estimate_rows():
    finger, sdf, bases = estimate_scene()
    first, t = first_and_best(lambda: sg.estimate_batch(finger, sdf, bases, estimator=sg.Geometric()))
    geo = len(bases) / t
    print(f"| estimate_batch, Geometric(), 100,000 bases | {geo:,.0f} candidate-fingers/s | first call {first:.1f} s |")
    one = jax.jit(lambda b: sg.estimate(finger, sdf, b, estimator=sg.Geometric()))
    jax.block_until_ready(one(bases[0]))
    latency = sorted(best_of(lambda i=i: one(bases[i]), 1) for i in range(1, 102))[50] * 1e3
    print(f"| one estimate under jax.jit, Geometric() | {latency:.2f} ms (median of 101) | |")
    mb = bases[:20_000]
    first, t = first_and_best(lambda: sg.estimate_batch(finger, sdf, mb))
    mech = len(mb) / t
    print(f"| estimate_batch, default estimator (Mechanics()), 20,000 bases | {mech:,.0f} candidate-fingers/s "
          f"= {mech / geo:.3f} of geometric | first call {first:.1f} s |")


def readme_scene():
    finger = sg.FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=20)
    gripper = sg.Gripper(left=finger, right=finger, base_separation=56.0)
    obj = sg.PolygonSDF.regular(center=(0.0, 38.0), radius=15.0, n_vertices=128)
    rng = np.random.default_rng(1)
    poses = np.c_[rng.uniform(-10.0, 10.0, (10_000, 2)), rng.uniform(-0.2, 0.2, 10_000)].astype(np.float32)
    return gripper, obj, poses


def planner_rows():
    gripper, polygon, poses = readme_scene()
    t0 = time.perf_counter()
    grid = jax.block_until_ready(polygon.to_grid())
    made = time.perf_counter() - t0
    print(f"| `PolygonSDF.to_grid()` of the README disc ({grid.values.shape[0]} x {grid.values.shape[1]} cells) | "
          f"{made * 1e3:,.0f} ms | first call, compiles included |")
    for obj_name, obj in (("PolygonSDF", polygon), ("to_grid()", grid)):
        for name, est in (("Geometric()", sg.Geometric()), ("default (Mechanics())", None)):
            first, t = first_and_best(lambda est=est, obj=obj: sg.score(gripper, obj, poses, estimator=est).score, k=2)
            one = [best_of(lambda i=i, est=est, obj=obj: sg.score(gripper, obj, poses[i:i + 1], estimator=est).score, 1)
                   for i in range(21)]
            print(f"| score, README scene, {obj_name}, {name}, 10,000 poses | {len(poses) / t:,.0f} poses/s | first call "
                  f"{first:.1f} s; one pose warm {sorted(one)[10] * 1e3:.1f} ms (median of 21) |")
        robust = poses[:1000]
        for name, est in (("Geometric()", sg.Geometric()), ("default (Mechanics())", None)):
            first, t = first_and_best(lambda est=est, obj=obj: sg.score(gripper, obj, robust, estimator=est,
                                                                        uncertainty=sg.Uncertainty(samples=16)).score, k=2)
            print(f"| score, README scene, {obj_name}, {name}, robust K = 16, 1,000 poses | {len(robust) / t:,.0f} "
                  f"poses/s | first call {first:.1f} s |")


def piece_rows():
    from softgrip_jax._concurrent import PIECE_BUCKETS

    finger, sdf, bases = estimate_scene()
    bases = bases[:16_384]
    print("| piece size | candidate-fingers/s | one piece per worker (ms) |")
    print("|---|---|---|")
    for size in PIECE_BUCKETS:
        run = lambda size=size, b=bases: sg.estimate_batch(finger, sdf, b, estimator=sg.Geometric(), chunk_size=size)  # noqa: E731
        jax.block_until_ready(run())
        sample = bases[:size * worker_count(None)]
        one = best_of(lambda size=size: sg.estimate_batch(finger, sdf, sample, estimator=sg.Geometric(),
                                                          chunk_size=size), 5)
        t = best_of(run, 2 if size > 8 else 1)
        print(f"| {size} | {len(bases) / t:,.0f} | {one * 1e3:.2f} |")


def size_rows():
    gripper, obj, poses = readme_scene()
    workers = worker_count(None)
    print("| B | piece size | call (ms) | poses/s |")
    print("|---|---|---|---|")
    for b in (1, 2, 5, 20, 100, 300, 605, 1000, 3000, 10_000):
        call = lambda b=b: sg.score(gripper, obj, poses[:b], estimator=sg.Geometric()).score  # noqa: E731
        jax.block_until_ready(call())  # compiles the piece size the first time it is needed
        t = best_of(call, 3)
        size = bucket_piece(b, workers, largest=obj.largest_piece, overhead=obj.piece_overhead)
        print(f"| {b:,} | {size} | {t * 1e3:.1f} | {b / t:,.0f} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", action="append", choices=("estimate", "planner", "pieces", "sizes"),
                    help="run only these rows (repeatable; default: all)")
    args = ap.parse_args()
    only = set(args.only or ("estimate", "planner", "pieces", "sizes"))
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True,
                           text=True).stdout.strip()
    print(f"commit {commit}{' (with uncommitted changes)' if dirty else ''}; {describe()}")
    if only & {"estimate", "planner"}:
        print("| call (defaults) | rate | notes |")
        print("|---|---|---|")
    if "estimate" in only:
        estimate_rows()
    if "planner" in only:
        planner_rows()
    if "pieces" in only:
        piece_rows()
    if "sizes" in only:
        size_rows()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
