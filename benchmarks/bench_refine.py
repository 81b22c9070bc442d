"""Does ``refine`` reach the optimum near its start, and how long does one pose take (issue 42)?

Run from the repository root (the compilation cache off, one process, a few minutes):

    .venv/bin/python benchmarks/bench_refine.py                 # the table and the timings
    .venv/bin/python benchmarks/bench_refine.py --only timing   # the timings only

Three objects in front of the README's gripper (N = 20, L 52 mm, Theta 0.55 rad, W 56 mm):

* ``disc``: the README's disc, ``PolygonSDF.regular((0, 38), 15, 128)``;
* ``rectangle``: a 26 x 20 mm ``PolygonSDF`` rectangle centred at (0, 38);
* ``grid``: an ellipse (semi-axes 13 x 10 mm, centre (0, 38)) sampled as an ``SDFGrid`` of 0.25 mm cells.

Each object and the gripper are mirror-symmetric about x = 0, so the centred poses (x = 0,
angle 0) form a line through a local optimum: a dense scan along the approach axis (y, every
0.05 mm, one ``score`` call) finds it and is the reference. From 20 starts within 3 mm (x, y)
and 0.05 rad of it (5 on the line, 3 mm and 1 mm short, at it, 1 mm and 3 mm past, and 15
random ones, seeded), ``refine`` (``Geometric()``, its defaults otherwise) runs pose by pose; a
start *reaches* the optimum when it ends within 0.1 mm of it or scores at least 99 % of it.

Timings: one pose refined warm (a compiled call before; the median of 11 starts), with
``Geometric()`` and with the default estimator (``Mechanics()``), on the disc.

Prints Markdown for benchmarks/RESULTS.md, headed by the tree's commit and the machine.
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
from _machine import describe  # noqa: E402

import softgrip_jax as sg  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FINGER = sg.FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=20)
GRIPPER = sg.Gripper(left=FINGER, right=FINGER, base_separation=56.0)
SCAN = np.arange(-25.0, 20.0, 0.05)  # y (mm) of the centred poses scanned
REACH_MM, REACH_SCORE = 0.1, 0.99


def objects() -> dict[str, sg.AbstractSDF]:
    disc = sg.PolygonSDF.regular(center=(0.0, 38.0), radius=15.0, n_vertices=128)
    rectangle = sg.PolygonSDF(jnp.array([[-13.0, 28.0], [13.0, 28.0], [13.0, 48.0], [-13.0, 48.0]]))
    t = 2 * np.pi * np.arange(256) / 256
    ellipse = sg.PolygonSDF(jnp.asarray(np.c_[13.0 * np.cos(t), 38.0 + 10.0 * np.sin(t)], jnp.float32))
    grid = sg.SDFGrid.sample(ellipse, origin=(-40.0, -40.0), spacing=(0.25, 0.25), shape=(441, 321))
    return {"disc": disc, "rectangle": rectangle, "grid": grid}


def scan_optimum(sdf) -> tuple[float, float]:
    """(y, score) of the best centred pose of the scan."""
    poses = np.c_[np.zeros_like(SCAN), SCAN, np.zeros_like(SCAN)].astype(np.float32)
    s = np.asarray(sg.score(GRIPPER, sdf, poses, estimator=sg.Geometric()).score)
    i = int(np.argmax(s))
    return float(SCAN[i]), float(s[i])


def starts(y_opt: float) -> np.ndarray:
    """(20, 3): 5 on the centred line (dy -3, -1, 0, 1, 3 mm), 15 random within 3 mm and 0.05 rad."""
    rng = np.random.default_rng(42)
    line = np.array([[0.0, y_opt + dy, 0.0] for dy in (-3.0, -1.0, 0.0, 1.0, 3.0)])
    r = 3.0 * np.sqrt(rng.uniform(0.0, 1.0, 15))
    phi = rng.uniform(0.0, 2 * np.pi, 15)
    rand = np.c_[r * np.cos(phi), y_opt + r * np.sin(phi), rng.uniform(-0.05, 0.05, 15)]
    return np.concatenate([line, rand]).astype(np.float32)


def fmt(p) -> str:
    return f"({p[0]:+.2f}, {p[1]:+.2f}, {p[2]:+.3f})"


def table() -> None:
    print("| object | start (x, y, angle) | end (x, y, angle) | start score | end score | scan optimum (y, score) "
          "| from optimum (mm) | steps | status | reached |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    summary = []
    for name, sdf in objects().items():
        y_opt, s_opt = scan_optimum(sdf)
        reached = 0
        for start in starts(y_opt):
            r = sg.refine(GRIPPER, sdf, start, estimator=sg.Geometric())
            end = np.asarray(r.pose)
            off = float(np.hypot(end[0], end[1] - y_opt))
            score = float(r.score.score)
            ok = off <= REACH_MM or score >= REACH_SCORE * s_opt
            reached += ok
            print(f"| {name} | {fmt(start)} | {fmt(end)} | {float(r.start_score):.4f} | {score:.4f} | "
                  f"({y_opt:+.2f}, {s_opt:.4f}) | {off:.2f} | {int(r.steps)} | {r.status_name} | "
                  f"{'yes' if ok else 'NO'} |")
        summary.append(f"{name}: {reached} of 20")
    print(f"\nreached (within {REACH_MM} mm or {REACH_SCORE:.0%} of the scan optimum's score): " + "; ".join(summary))


def timing() -> None:
    disc = objects()["disc"]
    y_opt, _ = scan_optimum(disc)
    poses = starts(y_opt)
    print("| refine, one pose, README disc | warm (median of 11) | first call |")
    print("|---|---|---|")
    for name, est in (("Geometric()", sg.Geometric()), ("default (Mechanics())", None)):
        t = time.perf_counter()
        jax.block_until_ready(sg.refine(GRIPPER, disc, poses[0], estimator=est).pose)
        first = time.perf_counter() - t
        times = []
        for p in poses[1:12]:
            t = time.perf_counter()
            jax.block_until_ready(sg.refine(GRIPPER, disc, p, estimator=est).pose)
            times.append(time.perf_counter() - t)
        times.sort()
        print(f"| {name} | {times[5] * 1e3:.1f} ms (range {times[0] * 1e3:.1f}-{times[-1] * 1e3:.1f}) | {first:.1f} s |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", action="append", choices=("table", "timing"),
                    help="run only these parts (repeatable; default: both)")
    args = ap.parse_args()
    only = set(args.only or ("table", "timing"))
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True,
                           text=True).stdout.strip()
    print(f"commit {commit}{' (with uncommitted changes)' if dirty else ''}; {describe()}")
    if "table" in only:
        table()
    if "timing" in only:
        timing()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
