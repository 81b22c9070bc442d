"""Candidates per second through the planner API's `score` (issue 5), after compilation.

Run from the repository root:

    .venv/bin/python benchmarks/bench_score.py

Scene: a 480x640 SDF grid at 0.31 mm/px with a 30 mm disc; a 52 mm, N = 20 gripper with bases 64 mm
apart; grids of poses (x, y, angle) around the disc. One candidate is both fingers.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe  # noqa: E402

from softgrip_jax import FingerModel, Gripper, SDFGrid, score  # noqa: E402
from softgrip_jax import Geometric


def grid_poses(n: int) -> np.ndarray:
    side = int(round((n / 5) ** 0.5))
    xs, ys, angles = np.linspace(-20, 20, side), np.linspace(-70, -20, n // (5 * side)), np.linspace(-0.2, 0.2, 5)
    return np.stack(np.meshgrid(xs, ys, angles, indexing="ij"), -1).reshape(-1, 3).astype(np.float32)


def main() -> None:
    spacing = 120.0 / 385.0
    sdf = SDFGrid.sample(lambda p: jnp.linalg.norm(p, axis=-1) - 15.0, origin=(-320 * spacing, -240 * spacing),
                         spacing=(spacing, spacing), shape=(480, 640))
    finger = FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=20)
    gripper = Gripper(left=finger, right=finger, base_separation=64.0)
    print(f"`python benchmarks/bench_score.py` on {describe()}\n")
    print("| poses | candidates/s (both fingers) | compile (s) | valid |")
    print("|---|---|---|---|")
    for n in (1_000, 100_000):
        poses = jnp.asarray(grid_poses(n))
        t0 = time.perf_counter()
        jax.block_until_ready(score(gripper, sdf, poses, estimator=Geometric()))
        first = time.perf_counter() - t0
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            out = jax.block_until_ready(score(gripper, sdf, poses, estimator=Geometric()))
            times.append(time.perf_counter() - t0)
        best = min(times)
        print(f"| {poses.shape[0]:,} | {poses.shape[0] / best:,.0f} | {first - best:.1f} | "
              f"{int(np.sum(np.asarray(out.valid)))} |", flush=True)


if __name__ == "__main__":
    main()
