"""Throughput and accuracy of the mechanics estimate (issue 7) against the geometric one.

Run from the repository root:

    .venv/bin/python benchmarks/bench_mechanics.py            # full tables (a few minutes)
    .venv/bin/python benchmarks/bench_mechanics.py --quick    # batch 1k only, two budgets

Two tables, printed as markdown:

1. Throughput of ``estimate_batch`` at N = 20 (candidate-fingers per second, after compilation;
   compile time separately), ``Geometric()`` and ``Mechanics()`` in the same run, on
   the scene of ``bench_estimate.py``: a 480x640 SDF grid at the D405's scale at 120 mm (0.31
   mm/px) with a 30 mm circle, candidate bases spread so that all four contact cases occur (and
   many candidates start in collision, as in a planner's raw sample). Timings alternate between
   the methods and keep the best of several repeats, so that load from other processes biases
   neither. At 10k the mechanics rows vary the iteration budget ``MechanicsConfig.max_steps``
   (a candidate that misses its tolerances within it is ``MECHANICS_NOT_CONVERGED``).
2. Accuracy against the observed-closure rod (``synthetic.rod``: 96 segments, its own
   stiffness profile) on circles and squares touched at the tip and at another area, stiffness
   ratio 1 and 2: joint errors (mm) of the mechanics estimate for each iteration budget, and of
   the geometric estimate, on the same scenes.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from softgrip_jax import (CASE_NAMES, FingerModel, MechanicsConfig, PolygonSDF, SDFGrid, Status,  # noqa: E402
                          estimate_batch)
from softgrip_jax import Geometric, Mechanics
from softgrip_jax import as_estimator

N_LINKS = 20


# ---------------------------------------------------------------------------------------------
# Throughput (the scene of bench_estimate.py)


def speed_scene(batch: int):
    spacing = 120.0 / 385.0
    grid = SDFGrid.sample(lambda p: jnp.linalg.norm(p, axis=-1) - 15.0, origin=(-320 * spacing, -240 * spacing),
                          spacing=(spacing, spacing), shape=(480, 640))
    finger = FingerModel(length=52.0, theta_entire=0.5, half_thickness=4.0, n_links=N_LINKS)
    rng = np.random.default_rng(0)
    bases = jnp.asarray(rng.uniform([-60.0, -70.0], [20.0, -10.0], (batch, 2)).astype(np.float32))
    return jax.block_until_ready(grid), finger, bases


def throughput(batch: int, budgets: list[int], repeats: int) -> list[dict]:
    grid, finger, bases = speed_scene(batch)
    configs = [("geometric", None)] + [("mechanics", MechanicsConfig(max_steps=s)) for s in budgets]

    def run(method, mechanics):
        estimator = as_estimator(method=method, mechanics=mechanics)
        return jax.block_until_ready(estimate_batch(finger, grid, bases, estimator=estimator))

    first, outputs = {}, {}
    for c in configs:
        t0 = time.perf_counter()
        outputs[c] = run(*c)
        first[c] = time.perf_counter() - t0
    best = {c: float("inf") for c in configs}
    for _ in range(repeats):
        for c in configs:
            t0 = time.perf_counter()
            run(*c)
            best[c] = min(best[c], time.perf_counter() - t0)
    rows = []
    for c in configs:
        out = outputs[c]
        status = np.asarray(out.status)
        rows.append({
            "method": c[0], "max_steps": None if c[1] is None else c[1].max_steps, "batch": batch,
            "per_second": batch / best[c], "compile_s": first[c] - best[c],
            "valid": int((status == Status.OK).sum()),
            "not_converged": int((status == Status.MECHANICS_NOT_CONVERGED).sum()),
            "cases": np.bincount(np.asarray(out.case)[status == Status.OK], minlength=4).tolist(),
        })
    return rows


# ---------------------------------------------------------------------------------------------
# Accuracy against the rod (the scenes of tests/core/test_mechanics.py)

LENGTH, THETA, HALF_THICKNESS = 52.0, 0.55, 4.0
SCENES = {  # kind, arc fraction, size (radius or half side, mm), overlap (mm), shift along the finger (mm)
    "circle, tip": ("circle", 1.0, 10.0, 4.0, 3.0),
    "circle, other area": ("circle", 0.6, 10.0, 3.0, 0.0),
    "square, tip": ("square", 1.0, 10.0, 4.0, 6.0),
    "square, other area": ("square", 0.65, 10.0, 3.0, 0.0),
}


def placed(kind, arc_fraction, size, overlap, along):
    """A 64-vertex object on the inner side of the free closed finger (see test_mechanics.py)."""
    from synthetic.rod import free_arc_points

    s = arc_fraction * LENGTH
    with jax.enable_x64(True):
        point = np.asarray(free_arc_points((0.0, 0.0), THETA, LENGTH, s))
    a = 2 * THETA * s / LENGTH
    centre = (point + np.array([np.cos(a), -np.sin(a)]) * (HALF_THICKNESS + size - overlap)
              + np.array([np.sin(a), np.cos(a)]) * along)
    if kind == "circle":
        return PolygonSDF.regular(centre, size, 64)
    corners = np.array([(-size, -size), (size, -size), (size, size), (-size, size)])
    t = np.arange(16)[:, None] / 16
    return PolygonSDF(jnp.asarray(np.concatenate([corners[i] + t * (corners[(i + 1) % 4] - corners[i])
                                                  for i in range(4)]) + centre))


def accuracy(budgets: list[int], ratios: list[float]) -> list[dict]:
    from softgrip_jax import estimate
    from synthetic.rod import RodMechanics, close_rod, observed_joints

    estimates = {}
    for s in budgets:
        config = MechanicsConfig(max_steps=s)
        estimates[s] = jax.jit(lambda f, sdf, c=config: estimate(f, sdf, jnp.zeros(2), estimator=Mechanics(c)))
    geometric = jax.jit(lambda f, sdf: estimate(f, sdf, jnp.zeros(2), estimator=Geometric()))
    rows = []
    for ratio in ratios:
        for name, spec in SCENES.items():
            sdf = placed(*spec)
            closure = close_rod((0.0, 0.0), THETA, LENGTH, HALF_THICKNESS, sdf,
                                mechanics=RodMechanics(stiffness_ratio=ratio))
            observed = np.asarray(observed_joints(closure, N_LINKS), np.float64)
            finger = FingerModel(LENGTH, THETA, HALF_THICKNESS, N_LINKS, stiffness_ratio=ratio)
            row = {"scene": name, "ratio": ratio}
            for key, fn in [("geometric", geometric)] + list(estimates.items()):
                est = fn(finger, sdf)
                error = np.linalg.norm(np.asarray(est.joints, np.float64) - observed, axis=-1)
                row[key] = (float(error.mean()), float(error[-1]), CASE_NAMES[int(est.case)], int(est.status))
            rows.append(row)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="batch 1k, budgets 1 and 4 on the rod, stiffness ratio 1")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--speed-only", type=int, metavar="BATCH",
                        help="only the throughput table, at this batch and the default budget")
    args = parser.parse_args()
    from _machine import describe

    default = MechanicsConfig().max_steps
    # (batch, iteration budgets): the default budget at 1k, the budget's cost at 10k.
    plan = [(1_000, [default])] if args.quick else [(1_000, [default]), (10_000, [2, 4, 8, default, 16])]
    if args.speed_only:
        plan = [(args.speed_only, [default])]
    budgets = [1, 4] if args.quick else [1, 2, 4, 8, 16]
    command = ("python benchmarks/bench_mechanics.py" + (" --quick" if args.quick else "")
               + (f" --speed-only {args.speed_only}" if args.speed_only else ""))
    print(f"`{command}` on {describe()}\n")
    print(f"### Throughput of estimate_batch, N = {N_LINKS} (same run, alternating; default max_steps = {default})\n")
    print("| batch | method | max_steps | candidate-fingers/s | vs geometric | compile (s) | valid | not converged |"
          " valid cases none/tip/tip+other/other |")
    print("|---|---|---|---|---|---|---|---|---|")
    for batch, steps in plan:
        rows = throughput(batch, steps, args.repeats)
        geometric = rows[0]["per_second"]
        for r in rows:
            budget = "-" if r["max_steps"] is None else r["max_steps"]
            print(f"| {batch:,} | {r['method']} | {budget} | {r['per_second']:,.0f} | "
                  f"{r['per_second'] / geometric:.2f} | {r['compile_s']:.1f} | {r['valid']} | "
                  f"{r['not_converged'] if r['max_steps'] else '-'} | {'/'.join(map(str, r['cases']))} |", flush=True)
    if args.speed_only:
        return

    ratios = [1.0] if args.quick else [1.0, 2.0]
    print(f"\n### Joint error against the rod (mm: mean over the {N_LINKS + 1} joints / at the tip), by iteration "
          "budget\n")
    header = "| scene | stiffness ratio | geometric | " + " | ".join(f"mechanics, {s} steps" for s in budgets) + " |"
    print(header)
    print("|" + "---|" * (3 + len(budgets)))
    rows = accuracy(budgets, ratios)
    for r in rows:
        cells = []
        for key in ["geometric"] + budgets:
            mean, tip, case, status = r[key]
            flag = "" if status == Status.OK else f" ({Status(status).name.lower()})"
            cells.append(f"{mean:.3f} / {tip:.3f} {case}{flag}")
        print(f"| {r['scene']} | {r['ratio']:g} | " + " | ".join(cells) + " |", flush=True)
    worst = {key: max(r[key][0] for r in rows) for key in ["geometric"] + budgets}
    print("\nWorst mean error (mm): " + ", ".join(
        f"{'geometric' if k == 'geometric' else f'{k} steps'} {v:.3f}" for k, v in worst.items()))


if __name__ == "__main__":
    main()
