"""The mechanics estimate on a grid SDF as the pose moves (issue 31): is it continuous, and is its
gradient the derivative of the closure? Printed as markdown.

Run from the repository root (one process; several minutes on two cores, mostly compilation):

    .venv/bin/python benchmarks/bench_smooth_sdf.py            # sweeps and gradients
    .venv/bin/python benchmarks/bench_smooth_sdf.py --speed    # also the touching grid's throughput

The scene: one finger (L = 52 mm, Theta 0.7, r = 4 mm, N = 20) and a disc of radius 10 mm at
(20, 60) mm whose tip rests on it (``tests/core/test_closing_path.py``'s). The objects: the exact
disc (``synthetic.smooth.DiscSDF``), and the ``SDFGrid`` vision makes of it
(``softgrip_vision.object_sdf.object_sdf`` of the disc's hard mask, rasterised at the pixel centres of a
D405-like camera whose pixels are 0.3 mm in the plane), looked up bilinearly
(``interpolation="linear"``) and bicubically (the default).

1. Base sweeps in 0.002 mm steps, one in y (x = 0, y in [-0.2, 0.1]) and one in x
   (x in [2.0, 2.3], y = 0), 151 poses each, in one ``estimate_batch`` call: the largest joint
   step between neighbours that are both valid, unflagged (no ``event``) and of one case, with
   the default ``MechanicsConfig`` and with the solve converged tightly (``step_tol`` 1e-5 instead
   of 0.01 mm, where it stops short by a pose-dependent amount that adds to the steps).
2. ``jax.jacrev`` of the tip (2,) with respect to the base (2,) against central differences
   (h = 0.01 mm) at four poses on the sweeps, converged tightly: the largest relative error
   ||J - J_central|| / ||J_central|| (Frobenius).
3. ``--speed``: ``estimate_grasp_batch`` throughput on ``bench_touching_grid.py``'s touching grid
   (4,851 poses over a 15 mm disc as a 0.3 mm ``SDFGrid``), bilinear against bicubic lookup, best of
   ``--repeats`` runs of the four combinations in turn.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from _machine import describe  # noqa: E402
from softgrip_jax import FingerModel, Mechanics, MechanicsConfig, SDFGrid, estimate, estimate_batch  # noqa: E402
from synthetic.render import d405_intrinsics  # noqa: E402
from synthetic.smooth import DiscSDF  # noqa: E402
from softgrip_vision.geometry import PlaneCamera  # noqa: E402
from softgrip_vision.object_sdf import object_sdf  # noqa: E402

FINGER = FingerModel(52.0, 0.7, 4.0, 20)
CENTRE, RADIUS, CELL_MM = (20.0, 60.0), 10.0, 0.3
STEP = 0.002
SWEEPS = {  # name: (start (2,), axis); 151 poses in STEP steps along the axis
    "y from (0, -0.2)": ((0.0, -0.2), 1),
    "x from (2.0, 0)": ((2.0, 0.0), 0),
}
POSES = 151
GRADIENT_POSES = ((0.0, -0.1), (0.0, 0.05), (2.1, 0.0), (2.25, 0.0))
TIGHT = MechanicsConfig(step_tol=1e-5, max_steps=200)


def vision_disc(cell_mm: float = CELL_MM, centre=CENTRE, radius: float = RADIUS) -> SDFGrid:
    """The SDFGrid of the disc made by vision from its hard mask (pixel centres inside the disc)
    seen by a 640 x 480 D405-like camera whose pixels are ``cell_mm`` mm in the plane."""
    intrinsics = d405_intrinsics()
    camera = PlaneCamera(intrinsics, cell_mm * intrinsics.fx)
    v, u = np.indices((intrinsics.height, intrinsics.width))
    points = camera.px_to_mm(np.stack([u, v], -1).reshape(-1, 2).astype(float))
    mask = (np.hypot(*(points - np.asarray(centre)).T) <= radius).reshape(v.shape)
    return object_sdf(mask, camera)


def objects() -> dict:
    grid = vision_disc()
    return {"exact disc": DiscSDF(CENTRE, RADIUS),
            "SDFGrid, bilinear": SDFGrid(grid.values, grid.origin, grid.spacing, interpolation="linear"),
            "SDFGrid, bicubic": grid}


def sweep_bases() -> np.ndarray:
    """(len(SWEEPS) * POSES, 2) bases, the sweeps one after the other."""
    parts = []
    for start, axis in SWEEPS.values():
        bases = np.tile(np.asarray(start, np.float32), (POSES, 1))
        bases[:, axis] += STEP * np.arange(POSES)
        parts.append(bases)
    return np.concatenate(parts).astype(np.float32)


def worst_steps(est) -> list[tuple[float, int, int, set]]:
    """Per sweep: the largest joint step (mm) between valid, unflagged neighbours of one case, how
    many such neighbours, how many poses flagged, and the cases seen."""
    out = []
    for k in range(len(SWEEPS)):
        part = slice(k * POSES, (k + 1) * POSES)
        joints, case = np.asarray(est.joints[part]), np.asarray(est.case[part])
        ok = np.asarray(est.valid[part]) & ~np.asarray(est.event[part])
        pairs = ok[1:] & ok[:-1] & (case[1:] == case[:-1])
        step = np.linalg.norm(np.diff(joints, axis=0), axis=-1).max(axis=-1)
        out.append((float(step[pairs].max()) if pairs.any() else float("nan"), int(pairs.sum()),
                    int(np.asarray(est.event[part]).sum()), set(case.tolist())))
    return out


def tight_sweeps_and_gradients(sdf, bases: jax.Array) -> tuple[list, float, list[float]]:
    """:func:`worst_steps` of the sweeps converged tightly, the largest relative error of the
    implicit Jacobian d tip / d base against central differences over GRADIENT_POSES (the shifted
    bases estimated in the sweeps' batch), and the central Jacobians' norms."""
    h = 0.01
    poses = np.asarray(GRADIENT_POSES, np.float32)
    shifts = np.concatenate([poses[:, None, :] + s * h * np.eye(2)[None] for s in (1, -1)], axis=1).reshape(-1, 2)
    est = estimate_batch(FINGER, sdf, jnp.concatenate([bases, jnp.asarray(shifts, jnp.float32)]), estimator=Mechanics(TIGHT))
    n = bases.shape[0]
    sweeps = worst_steps(jax.tree_util.tree_map(lambda x: x[:n], est))
    tips = np.asarray(est.joints[n:, -1], np.float64).reshape(len(poses), 4, 2)
    central = ((tips[:, :2] - tips[:, 2:]) / (2 * h)).transpose(0, 2, 1)  # (P, tip axis, base axis)
    tip = lambda b: estimate(FINGER, sdf, b, estimator=Mechanics(TIGHT)).joints[-1]  # noqa: E731
    jacobians = np.asarray(jax.jit(jax.vmap(jax.jacrev(tip)))(jnp.asarray(poses)), np.float64)
    norms = np.linalg.norm(central, axis=(1, 2))
    return sweeps, float((np.linalg.norm(jacobians - central, axis=(1, 2)) / norms).max()), norms.tolist()


def speed(repeats: int) -> list[str]:
    """Fingers per second of the geometric and the mechanics estimate on the touching grid, with the
    bilinear and the bicubic lookup, timed alternately (best of ``repeats``) so that load from other
    processes biases neither."""
    import time

    from bench_touching_grid import gripper, pose_grid

    from softgrip_jax import Geometric, Mechanics, PolygonSDF, estimate_grasp_batch

    disc = PolygonSDF.regular((0.0, 38.0), 15.0, 128)
    poses, g = pose_grid(21, 11), gripper()
    grids = {k: jax.block_until_ready(SDFGrid.sample(disc, origin=(-60.0, -20.0), spacing=(0.3, 0.3), shape=(334, 400),
                                                     interpolation=k)) for k in ("linear", "cubic")}
    runs = {(k, e): (lambda k=k, est=est: jax.block_until_ready(estimate_grasp_batch(g, grids[k], poses, estimator=est)))
            for e, est in (("geometric", Geometric()), ("mechanics", Mechanics())) for k in grids}
    for run in runs.values():  # compilation
        run()
    best = dict.fromkeys(runs, float("inf"))
    for _ in range(repeats):
        for key, run in runs.items():
            t0 = time.perf_counter()
            run()
            best[key] = min(best[key], time.perf_counter() - t0)
    rows = ["| estimate | bilinear fingers/s | bicubic fingers/s | bicubic time / bilinear time |", "|---|---|---|---|"]
    for e in ("geometric", "mechanics"):
        lin, cub = best[("linear", e)], best[("cubic", e)]
        rows.append(f"| {e} | {2 * poses.shape[0] / lin:,.0f} | {2 * poses.shape[0] / cub:,.0f} | {cub / lin:.2f} |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--speed", action="store_true", help="also time the touching grid, bilinear vs bicubic")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(f"`python benchmarks/bench_smooth_sdf.py{' --speed' if args.speed else ''}` on {describe()}\n")
    print(f"Base sweeps in {STEP} mm steps ({POSES} poses each); d tip / d base against central differences "
          f"(h = 0.01 mm) at {len(GRADIENT_POSES)} poses {list(GRADIENT_POSES)}.\n")
    print("| object | sweep | cases | flagged | neighbours | worst joint step (mm) | converged tightly: "
          "flagged, neighbours, worst joint step (mm) |")
    print("|---|---|---|---|---|---|---|")
    bases = jnp.asarray(sweep_bases())
    gradients = {}
    for name, sdf in objects().items():
        default = worst_steps(estimate_batch(FINGER, sdf, bases, estimator=Mechanics()))
        tight, *gradients[name] = tight_sweeps_and_gradients(sdf, bases)
        for sweep, (worst, pairs, flagged, cases), (t_worst, t_pairs, t_flagged, _) in zip(SWEEPS, default, tight):
            print(f"| {name} | {sweep} | {sorted(cases)} | {flagged} | {pairs} | {worst:.4f} | "
                  f"{t_flagged}, {t_pairs}, {t_worst:.4f} |", flush=True)
    print("\n| object | d tip / d base: largest relative error against central differences | "
          "norm of the central Jacobians |")
    print("|---|---|---|")
    for name, (error, norms) in gradients.items():
        print(f"| {name} | {error:.2%} | {', '.join(f'{n:.2f}' for n in norms)} |")
    if args.speed:
        print(f"\nTouching grid (bench_touching_grid.py's scene), best of {args.repeats}:\n")
        print("\n".join(speed(args.repeats)))


if __name__ == "__main__":
    main()
