"""``score`` on the README's planner scene: the 128-vertex ``PolygonSDF`` disc against the same disc
sampled on an ``SDFGrid`` of 0.25 mm cells, in one process (rates and the largest score difference).

    .venv/bin/python benchmarks/bench_polygon_grid.py [poses]      # default 2,000 poses
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("SOFTGRIP_JAX_CACHE", "0")

import jax  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe  # noqa: E402

import softgrip_jax as sg  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 2000
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    print(f"commit {commit}; {describe()}; {n:,} poses")
    finger = sg.FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=20)
    gripper = sg.Gripper(left=finger, right=finger, base_separation=56.0)
    polygon = sg.PolygonSDF.regular(center=(0.0, 38.0), radius=15.0, n_vertices=128)
    grid = jax.block_until_ready(polygon.to_grid())
    rng = np.random.default_rng(1)
    poses = np.c_[rng.uniform(-10.0, 10.0, (n, 2)), rng.uniform(-0.2, 0.2, n)].astype(np.float32)
    print("| estimator | PolygonSDF (poses/s) | to_grid() (poses/s) | ratio | score difference: median, max |")
    print("|---|---|---|---|---|")
    for name, est in (("Geometric()", sg.Geometric()), ("default (Mechanics())", None)):
        rates, scores = [], []
        for sdf in (polygon, grid):
            call = lambda sdf=sdf, est=est: sg.score(gripper, sdf, poses, estimator=est).score  # noqa: E731
            jax.block_until_ready(call())
            t0 = time.perf_counter()
            scores.append(np.asarray(jax.block_until_ready(call())))
            rates.append(n / (time.perf_counter() - t0))
        both = np.isfinite(scores[0]) & np.isfinite(scores[1])
        d = np.abs(scores[0] - scores[1])[both]
        print(f"| {name} | {rates[0]:,.0f} | {rates[1]:,.0f} | {rates[1] / rates[0]:.1f} | {np.median(d):.1e}, "
              f"{d.max():.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
