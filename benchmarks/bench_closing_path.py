"""The mechanics estimate along the closing path (issue 20): accuracy against the rod, smoothness
in the pose, batch independence, convergence and throughput, printed as markdown.

Run from the repository root (one heavy process; about ten minutes on two cores):

    .venv/bin/python benchmarks/bench_closing_path.py
    .venv/bin/python benchmarks/bench_closing_path.py --quick     # smaller grids and batches

Tables:

1. Against the rod (``synthetic.rod``, 96 segments, closed by its own 60-step continuation)
   on true geometry, over a grid of finger bases around a disc where the tip slides off (Theta
   0.7 and 0.8), a square and a non-convex L shape: agreement of the contact pattern (touches at
   all, tip touches) and joint errors (mm).
2. Base sweeps in x and y, 0.002 mm steps over +-0.2 mm: the largest tip jump between neighbours
   that are both valid, unflagged and of one case, and ``jax.grad`` of the tip against central
   differences at h = 0.004 and 0.05 mm.
3. Batch independence: the largest joint change of any element between its batch and the same
   element in shuffled batches with NaN, far-away and colliding elements and other sizes.
4. Share of touching poses not converged over random bases, per scene.
5. Throughput at N = 20 (candidate-fingers per second after compilation, best of repeats), the
   geometric and the mechanics estimate, and the mechanics estimate with a one-increment path
   (the path-following cost is the difference).
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

from _machine import describe  # noqa: E402
from bench_mechanics import speed_scene  # noqa: E402
from softgrip_jax import (ContactCase, ContactConfig, FingerModel, MechanicsConfig, PolygonSDF, Status, estimate,  # noqa: E402
                          estimate_batch)
from synthetic.rod import RodMechanics, close_rod, observed_joints  # noqa: E402
from synthetic.smooth import DiscSDF  # noqa: E402
from synthetic.shapes import shape  # noqa: E402
from softgrip_jax import Mechanics
from softgrip_jax import as_estimator

L, R, N = 52.0, 4.0, 20
VERBOSE = False

SCENES = {  # name: (polygon vertices (V, 2) mm, Theta, stiffness ratio)
    "disc r10 at (20, 60), Theta 0.7 (tip slides off)": (np.asarray(PolygonSDF.regular((20.0, 60.0), 10.0, 64).vertices),
                                                       0.7, 2.0),
    "disc r10 at (24, 44), Theta 0.8": (np.asarray(PolygonSDF.regular((24.0, 44.0), 10.0, 64).vertices), 0.8, 1.0),
    "square 20 at (22, 48), Theta 0.7": (shape("square", 20.0, 0.3) + [22.0, 48.0], 0.7, 1.0),
    "L shape 30 at (22, 50), Theta 0.7 (non-convex)": (shape("l_shape", 30.0, 0.4) + [22.0, 50.0], 0.7, 1.0),
}


def rod_pattern(in_contact: np.ndarray, n_links: int) -> tuple[bool, bool]:
    """(touches, tip touches) of a rod closure's nodes (M+1,) within contact_tol of the object, by
    the estimate's rule: a tip contact is a touching node in the tip zone, the last
    ``ContactConfig.tip_tolerance`` of the N links."""
    arc = np.linspace(0.0, 1.0, in_contact.size)
    zone = arc >= 1.0 - ContactConfig().tip_tolerance / n_links
    return bool(in_contact.any()), bool(in_contact[zone].any())


def against_rod(quick: bool) -> list[str]:
    offsets = np.linspace(-8.0, 8.0, 3 if quick else 7)
    run = jax.jit(estimate)
    rows = ["| scene | fingers | contact pattern agrees | mean joint error (mm) | worst finger (mm) | flagged events |",
            "|---|---|---|---|---|---|"]
    totals = []
    for name, (vertices, theta, ratio) in SCENES.items():
        sdf = PolygonSDF(jnp.asarray(vertices, jnp.float32))
        finger = FingerModel(L, theta, R, N, stiffness_ratio=ratio)
        agree, errors, worst, events, count = 0, [], 0.0, 0, 0
        for dx in offsets:
            for dy in offsets:
                base = (float(dx), float(dy))
                est = run(finger, sdf, jnp.asarray(base, jnp.float32), estimator=Mechanics())
                if int(est.status) == Status.INITIAL_OVERLAP:
                    continue
                closure = close_rod(base, theta, L, R, sdf, mechanics=RodMechanics(stiffness_ratio=ratio, n_steps=60))
                observed = np.asarray(observed_joints(closure, N))
                error = np.linalg.norm(np.asarray(est.joints) - observed, axis=-1)
                case = int(est.case)
                mine = (case != ContactCase.NONE, case in (ContactCase.TIP, ContactCase.TIP_AND_OTHER))
                # The rod's pattern, by the estimate's rule: any node within contact_tol; a tip
                # contact when a run of such nodes reaches the tip zone (the last tip_tolerance links).
                touches, tip = rod_pattern(np.asarray(closure.in_contact), N)
                agree += int(mine == (touches, tip) and bool(est.valid))
                errors.append(error.mean())
                worst = max(worst, float(error.max()))
                if VERBOSE and (mine != (touches, tip) or error.max() > 0.3):
                    print(f"  {name} base {base}: case {case} event {bool(est.event)} valid {bool(est.valid)} rod {(touches, tip)} "
                          f"worst {error.max():.3f} mm, mean {error.mean():.3f}", flush=True)
                events += int(est.event)
                count += 1
        totals.append((agree, count, errors, worst))
        rows.append(f"| {name} | {count} | {agree}/{count} | {np.mean(errors):.3f} | {worst:.3f} | {events} |")
    agree = sum(t[0] for t in totals)
    count = sum(t[1] for t in totals)
    mean = np.mean([e for t in totals for e in t[2]])
    rows.append(f"| all | {count} | {agree}/{count} ({100 * agree / count:.1f} %) | {mean:.3f} | "
                f"{max(t[3] for t in totals):.3f} | |")
    return rows


SWEEP_OBJECTS = {  # name: the object (the disc, exact and as a 256-gon)
    "disc r10 at (20, 60), exact (smooth)": DiscSDF((20.0, 60.0), 10.0),
    "disc r10 at (20, 60), 256-gon": PolygonSDF.regular((20.0, 60.0), 10.0, 256),
}
SWEEP_CENTRES = [(0.0, 0.0), (0.0, -0.16), (-3.46, 1.50), (2.0, 0.0), (4.0, 3.0), (10.0, -3.0)]


def sweeps(quick: bool) -> list[str]:
    finger = FingerModel(L, 0.7, R, N)
    steps = np.arange(-0.2, 0.2 + 1e-9, 0.002 if not quick else 0.01)
    rows = ["| object | base | sweep | poses | touching | flagged | max tip jump, unflagged, one case (mm) | "
            "d tip_x / d base: grad, central h=0.004, h=0.05 |", "|---|---|---|---|---|---|---|---|"]
    for name, sdf in SWEEP_OBJECTS.items():
        tip_x = jax.jit(lambda b, sdf=sdf: estimate(finger, sdf, b, estimator=Mechanics()).joints[-1, 0])
        grad = jax.jit(jax.grad(lambda b, sdf=sdf: estimate(finger, sdf, b, estimator=Mechanics()).joints[-1, 0]))
        for centre in SWEEP_CENTRES:
            for axis in (0, 1):
                bases = np.tile(np.asarray(centre, np.float32), (steps.size, 1))
                bases[:, axis] += steps
                est = estimate_batch(finger, sdf, jnp.asarray(bases), estimator=Mechanics())
                tips = np.asarray(est.joints[:, -1])
                jump = np.linalg.norm(np.diff(tips, axis=0), axis=-1)
                ok = np.asarray(est.valid) & ~np.asarray(est.event)
                same = np.asarray(est.case)[1:] == np.asarray(est.case)[:-1]
                plain = ok[1:] & ok[:-1] & same
                e = np.zeros(2, np.float32)
                e[axis] = 1.0
                c = jnp.asarray(centre, jnp.float32)
                g = float(grad(c)[axis])
                central = [float((tip_x(c + h * e) - tip_x(c - h * e)) / (2 * h)) for h in (0.004, 0.05)]
                centre_flagged = bool(estimate(finger, sdf, c, estimator=Mechanics()).event)
                rows.append(f"| {name} | {centre} | {'xy'[axis]} | {steps.size} | "
                            f"{int(np.asarray(est.contact.touches).sum())} | {int(np.asarray(est.event).sum())} | "
                            f"{jump[plain].max() if plain.any() else float('nan'):.5f} | "
                            f"{g:.3f}, {central[0]:.3f}, {central[1]:.3f}{' (flagged)' if centre_flagged else ''} |")
    return rows


def independence(quick: bool) -> tuple[list[str], list[str]]:
    batch = 2000 if quick else 10000
    rng = np.random.default_rng(7)
    rows = ["| scene | batch | compositions | max joint change (mm) | valid / case flips |", "|---|---|---|---|---|"]
    conv = ["| scene | random bases | touching while closing | not converged | root not converged | events |", "|---|---|---|---|---|---|"]
    for name, (vertices, theta, ratio) in SCENES.items():
        sdf = PolygonSDF(jnp.asarray(vertices, jnp.float32))
        finger = FingerModel(L, theta, R, N, stiffness_ratio=ratio)
        bases = rng.uniform(-10.0, 10.0, (batch, 2)).astype(np.float32)
        ref = jax.tree_util.tree_map(np.asarray, estimate_batch(finger, sdf, jnp.asarray(bases), estimator=Mechanics()))
        status = ref.status
        touching = int((ref.valid & ref.contact.touches).sum())  # the closing finger met the object
        conv.append(f"| {name} | {batch} | {touching} | {int((status == Status.MECHANICS_NOT_CONVERGED).sum())} | "
                    f"{int((status == Status.ROOT_NOT_CONVERGED).sum())} | {int(ref.event.sum())} |")
        worst, flips = 0.0, 0
        for k, size in enumerate([batch, batch // 3, 37]):
            idx = rng.permutation(batch)[:size]
            other = bases[idx].copy()
            other[k::7] = [[np.nan, 0.0], [500.0, 0.0], [1e4, 1e4]][k]
            out = jax.tree_util.tree_map(np.asarray, estimate_batch(finger, sdf, jnp.asarray(other), estimator=Mechanics()))
            keep = np.ones(size, bool)
            keep[k::7] = False
            a, b = ref.joints[idx][keep], out.joints[keep]
            both = ~np.isnan(a) & ~np.isnan(b)
            worst = max(worst, float(np.abs(a - b)[both].max()))
            flips += int((ref.valid[idx][keep] != out.valid[keep]).sum() + (ref.case[idx][keep] != out.case[keep]).sum())
        rows.append(f"| {name} | {batch} | 3 (sizes {batch}, {batch // 3}, 37; shuffled; NaN / far elements) | "
                    f"{worst:.2e} | {flips} |")
    return rows, conv


def throughput(quick: bool, repeats: int = 3) -> list[str]:
    batch = 2000 if quick else 20000
    grid, finger, bases = speed_scene(batch)
    configs = {"geometric": ("geometric", MechanicsConfig()), "mechanics (closing path)": ("mechanics", MechanicsConfig()),
               "mechanics, one-increment path": ("mechanics", MechanicsConfig(path_step=10.0, path_iterations=1))}

    def go(method, mech):
        chosen = as_estimator(method=method, mechanics=mech)
        return jax.block_until_ready(estimate_batch(finger, grid, bases, estimator=chosen))

    first = {}
    for k, c in configs.items():
        t0 = time.perf_counter()
        go(*c)
        first[k] = time.perf_counter() - t0
    best = {k: float("inf") for k in configs}
    for _ in range(repeats):
        for k, c in configs.items():
            t0 = time.perf_counter()
            go(*c)
            best[k] = min(best[k], time.perf_counter() - t0)
    rows = ["| estimate | batch | candidate-fingers/s | compile (s) |", "|---|---|---|---|"]
    for k in configs:
        rows.append(f"| {k} | {batch} | {batch / best[k]:,.0f} | {first[k] - best[k]:.1f} |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--only", choices=["rod", "sweeps", "batch", "speed"], action="append")
    parser.add_argument("--verbose", action="store_true", help="name every finger that disagrees with the rod")
    args = parser.parse_args()
    global VERBOSE
    VERBOSE = args.verbose
    parts = args.only or ["rod", "sweeps", "batch", "speed"]
    print(f"Machine: {describe()}\n")
    if "speed" in parts:
        print("\n".join(throughput(args.quick)), "\n", flush=True)
    if "batch" in parts:
        rows, conv = independence(args.quick)
        print("\n".join(rows), "\n\n" + "\n".join(conv), "\n", flush=True)
    if "sweeps" in parts:
        print("\n".join(sweeps(args.quick)), "\n", flush=True)
    if "rod" in parts:
        print("\n".join(against_rod(args.quick)), flush=True)


if __name__ == "__main__":
    main()
