"""Mechanics throughput on a planner's touching grid (issue 30), against the geometric estimate.

Run from the repository root:

    .venv/bin/python benchmarks/bench_touching_grid.py                 # both SDF kinds, table
    .venv/bin/python benchmarks/bench_touching_grid.py --save ref.npz  # also keep the joints
    .venv/bin/python benchmarks/bench_touching_grid.py --compare ref.npz  # largest joint change

The scene: a two-finger gripper (L = 52 mm, Theta 0.55, r = 4 mm, N = 20, bases 56 mm apart)
over a 15 mm-radius disc at (0, 38) mm, as an exact 128-gon (``PolygonSDF``) and as the
``SDFGrid`` vision would produce of it (0.3 mm cells), and a grid of gripper poses x, y in
+-10 mm and angle in +-0.2 rad, where most fingers touch the disc while closing (unlike
bench_mechanics.py's scene, where many candidates start in collision). ``estimate_grasp_batch``
with ``Geometric()`` and ``Mechanics()`` is timed after a warm-up, alternating between them and
keeping the best of ``--repeats`` runs, so that load from other processes biases neither.
``--variants`` also times ``Mechanics`` with other solver settings, to attribute its cost.
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

from softgrip_jax import (FingerModel, Geometric, Gripper, Mechanics, MechanicsConfig, PolygonSDF,  # noqa: E402
                          SDFGrid, Status, estimate_grasp_batch)

#: Solver settings timed with ``--variants`` (the differences attribute the default's cost).
VARIANTS = {
    "one-increment path": MechanicsConfig(path_step=10.0, path_iterations=1),
    "path_iterations=1": MechanicsConfig(path_iterations=1),
    "max_steps=8": MechanicsConfig(max_steps=8),
    "active_rows=4": MechanicsConfig(active_rows=4),
}


def gripper() -> Gripper:
    finger = FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=20)
    return Gripper(left=finger, right=finger, base_separation=56.0)


def objects() -> dict:
    """The disc as an exact polygon and as a 0.3 mm SDF grid covering the fingers' reach."""
    disc = PolygonSDF.regular((0.0, 38.0), 15.0, 128)
    grid = SDFGrid.sample(disc, origin=(-60.0, -20.0), spacing=(0.3, 0.3), shape=(334, 400))
    return {"PolygonSDF (128-gon)": disc, "SDFGrid (0.3 mm)": jax.block_until_ready(grid)}


def pose_grid(n_xy: int, n_angle: int) -> jax.Array:
    """(n_xy^2 n_angle, 3) poses: x, y in +-10 mm, angle in +-0.2 rad."""
    xy = np.linspace(-10.0, 10.0, n_xy)
    angle = np.linspace(-0.2, 0.2, n_angle)
    x, y, a = np.meshgrid(xy, xy, angle, indexing="ij")
    return jnp.asarray(np.stack([x.ravel(), y.ravel(), a.ravel()], axis=-1), jnp.float32)


def timed(estimators: dict, g: Gripper, sdf, poses, repeats: int) -> tuple[dict, dict]:
    """Best wall time (s) of each estimator over ``repeats`` alternating runs, and its output."""
    def run(est):
        return jax.block_until_ready(estimate_grasp_batch(g, sdf, poses, estimator=est))

    outputs = {k: run(e) for k, e in estimators.items()}  # warm-up (compilation)
    best = {k: float("inf") for k in estimators}
    for _ in range(repeats):
        for k, e in estimators.items():
            t0 = time.perf_counter()
            run(e)
            best[k] = min(best[k], time.perf_counter() - t0)
    return best, outputs


def joints_of(out) -> np.ndarray:
    """(B, 2, N+1, 2) joints of both fingers."""
    return np.stack([np.asarray(out.left.joints), np.asarray(out.right.joints)], axis=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--grid", type=int, nargs=2, default=(21, 11), metavar=("N_XY", "N_ANGLE"))
    parser.add_argument("--variants", action="store_true", help="also time Mechanics with other settings")
    parser.add_argument("--save", help="write the mechanics joints of every pose to this .npz")
    parser.add_argument("--compare", help="largest joint change (mm) against a --save file")
    args = parser.parse_args()
    from _machine import describe

    poses = pose_grid(*args.grid)
    g = gripper()
    print(f"`python benchmarks/bench_touching_grid.py{' --variants' if args.variants else ''}` on {describe()}; "
          f"{poses.shape[0]} poses ({2 * poses.shape[0]} fingers), best of {args.repeats}\n")
    print("| object | touching | estimate | fingers/s | vs geometric | not converged |")
    print("|---|---|---|---|---|---|")
    saved = {}
    for name, sdf in objects().items():
        estimators = {"geometric": Geometric(), "mechanics": Mechanics()}
        estimators.update({f"mechanics, {k}": Mechanics(c) for k, c in (VARIANTS.items() if args.variants else ())})
        best, outputs = timed(estimators, g, sdf, poses, args.repeats)
        geo = outputs["geometric"]
        touches = np.concatenate([np.asarray(geo.left.contact.touches & geo.left.valid),
                                  np.asarray(geo.right.contact.touches & geo.right.valid)])
        fingers = 2 * poses.shape[0]
        for k in estimators:
            status = np.concatenate([np.asarray(outputs[k].left.status), np.asarray(outputs[k].right.status)])
            rate = fingers / best[k]
            print(f"| {name} | {touches.mean():.1%} | {k} | {rate:,.0f} | {best['geometric'] / best[k]:.3f} | "
                  f"{int((status == Status.MECHANICS_NOT_CONVERGED).sum())} |", flush=True)
        saved[name] = joints_of(outputs["mechanics"])
    if args.save:
        np.savez(args.save, **saved)
    if args.compare:
        ref = np.load(args.compare)
        for name, joints in saved.items():
            change = np.linalg.norm(joints - ref[name], axis=-1)
            both = np.isfinite(change)
            print(f"\n{name}: largest joint change against {args.compare}: {change[both].max():.2e} mm "
                  f"(over {both.any(axis=(1, 2)).sum()} poses; 99.9th percentile {np.quantile(change[both], 0.999):.2e})")


if __name__ == "__main__":
    main()
