"""No holes before a slide-off (issue 31): base sweeps through the poses where a held tip slides off
a disc, and the mechanics throughput on a planner's touching grid, this checkout against a baseline
copy of the package in one run, printed as markdown.

The baseline is a copy of ``softgrip_jax`` renamed ``softgrip_jax_base`` in ``--base-dir`` (as for
compare_estimate.py), e.g. the commit before the change::

    git archive ac0b5a3 softgrip_jax | tar -x -C /tmp/sg_base
    (cd /tmp/sg_base && mv softgrip_jax softgrip_jax_base &&
     sed -i 's/softgrip_jax\\./softgrip_jax_base./g; s/from softgrip_jax import/from softgrip_jax_base import/g' \\
        softgrip_jax_base/*.py)
    python benchmarks/bench_slide_off.py --base-dir /tmp/sg_base
    python benchmarks/bench_slide_off.py                 # this checkout only

Tables:

1. Sweeps: the issue's disc (radius 10 mm at (20, 60) mm, Theta 0.7, N = 20, uniform stiffness),
   exact (``synthetic.smooth.DiscSDF``) and as an ``SDFGrid`` of 0.3 mm cells sampled from it;
   the base moved by 0.002 mm over +-0.2 mm in x and in y around three bases where the held tip
   slides off: 6 x 201 = 1,206 poses per object. Not converged, events (slid off / near a fold),
   the solver's iterations after the closing path (mean, largest), and the largest distance of a
   converged shape from the energy's stationary point (one Newton step of the energy by autodiff,
   tests/core/test_closing_path.py; poses right at the fold, where the Hessian is singular, left
   out and counted).
2. Throughput: ``estimate_grasp_batch`` with ``Mechanics()`` on bench_touching_grid.py's scene
   (21 x 21 x 11 poses, two fingers each, both SDF kinds), best of ``--repeats`` runs alternating
   between the versions, and the ratio.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(1, str(Path(__file__).resolve().parent))
sys.path.insert(2, str(ROOT / "tests" / "core"))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from _machine import describe  # noqa: E402
from softgrip_jax import Mechanics

STEPS = np.arange(-0.2, 0.2 + 1e-9, 0.002)
CENTRES = [(0.0, 0.0), (0.0, -0.16), (-3.46, 1.50)]


def sweep_bases() -> np.ndarray:
    out = []
    for centre in CENTRES:
        for axis in (0, 1):
            b = np.tile(np.asarray(centre, np.float32), (STEPS.size, 1))
            b[:, axis] += STEPS
            out.append(b)
    return np.concatenate(out).astype(np.float32)


def objects(pkg) -> dict:
    """The exact disc (``synthetic.smooth.DiscSDF``'s distance, as a ``pkg.AbstractSDF``) and its
    SDFGrid."""
    class Disc(pkg.AbstractSDF):
        def distance(self, points):
            offset = points - jnp.asarray([20.0, 60.0], jnp.float32)
            return jnp.sqrt(jnp.sum(offset * offset, axis=-1) + 1e-12) - 10.0

        def mass_properties(self):
            return jnp.asarray([20.0, 60.0], jnp.float32), jnp.asarray(10.0, jnp.float32)

    disc = Disc()
    return {"exact disc": disc,
            "SDFGrid, 0.3 mm cells": pkg.SDFGrid.sample(disc, (-20.0, -20.0), (0.3, 0.3), (367, 234))}


def solve_steps(pkg, finger, sdf, bases):
    """The solver's iterations after the closing path, per pose (the Equilibrium's ``steps``)."""
    stage_mod = importlib.import_module(pkg.__name__ + "._stage")
    est_mod = importlib.import_module(pkg.__name__ + "._estimators")
    frames_mod = importlib.import_module(pkg.__name__ + "._frames")
    contact_mod = importlib.import_module(pkg.__name__ + "._contact")
    mech_mod = importlib.import_module(pkg.__name__ + "._mechanics")
    estimator = est_mod.as_estimator(method="mechanics")
    config = contact_mod.ContactConfig()

    def one(base):
        frame = frames_mod.FingerFrame.hanging_from(base)
        stage = stage_mod.geometric_stage(finger, sdf, frame, config, estimator)
        eq = stage_mod.mechanics_of(finger, sdf, stage, mech_mod.MechanicsConfig(), config)
        return jnp.where(stage_mod.needs_mechanics(stage), eq.steps, -1)

    return np.asarray(jax.jit(jax.vmap(one))(jnp.asarray(bases)))


def sweeps(versions: dict) -> list[str]:
    from test_closing_path import newton_distance

    rows = ["| version | object | poses | not converged | events (slid off or near a fold) | solver iterations, "
            "mean / largest | largest distance from an equilibrium (mm), poses at the fold |",
            "|---|---|---|---|---|---|---|"]
    bases = sweep_bases()
    for label, pkg in versions.items():
        finger = pkg.FingerModel(52.0, 0.7, 4.0, 20)
        for name, sdf in objects(pkg).items():
            est = jax.tree_util.tree_map(np.asarray, pkg.estimate_batch(finger, sdf, jnp.asarray(bases),
                                                                        estimator=Mechanics()))
            steps = solve_steps(pkg, finger, sdf, bases)
            steps = steps[steps >= 0]
            bad = est.status == pkg.Status.MECHANICS_NOT_CONVERGED
            distance, minimum, _ = newton_distance(finger, sdf, bases, est.psi, est.turning)
            keep = ~bad & minimum
            rows.append(f"| {label} | {name} | {bases.shape[0]} | {int(bad.sum())} | {int(est.event.sum())} | "
                        f"{steps.mean():.1f} / {steps.max()} | {distance[keep].max():.4f}, "
                        f"{int((~bad & ~minimum).sum())} |")
            print(rows[-1], flush=True)
    return rows


def throughput(versions: dict, repeats: int) -> list[str]:
    from bench_touching_grid import pose_grid

    poses = pose_grid(21, 11)
    setups = {}
    for label, pkg in versions.items():
        finger = pkg.FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=20)
        g = pkg.Gripper(left=finger, right=finger, base_separation=56.0)
        disc = pkg.PolygonSDF.regular((0.0, 38.0), 15.0, 128)
        grid = pkg.SDFGrid.sample(disc, origin=(-60.0, -20.0), spacing=(0.3, 0.3), shape=(334, 400))
        setups[label] = (pkg, g, {"PolygonSDF (128-gon)": disc, "SDFGrid (0.3 mm)": grid})
    rows = ["| object | " + " | ".join(f"{k} fingers/s" for k in versions) + " | ratio | not converged |",
            "|---|" + "---|" * len(versions) + "---|---|"]
    for name in ("PolygonSDF (128-gon)", "SDFGrid (0.3 mm)"):
        def run(label):
            pkg, g, objs = setups[label]
            return jax.block_until_ready(pkg.estimate_grasp_batch(g, objs[name], poses, estimator=pkg.Mechanics()))

        outputs = {k: run(k) for k in versions}  # warm-up (compilation)
        best = {k: float("inf") for k in versions}
        for _ in range(repeats):
            for k in versions:
                t0 = time.perf_counter()
                run(k)
                best[k] = min(best[k], time.perf_counter() - t0)
        fingers = 2 * poses.shape[0]
        rates = {k: fingers / best[k] for k in versions}
        labels = list(versions)
        ratio = rates[labels[-1]] / rates[labels[0]] if len(labels) > 1 else 1.0
        nc = []
        for k in versions:
            pkg = setups[k][0]
            status = np.concatenate([np.asarray(outputs[k].left.status), np.asarray(outputs[k].right.status)])
            nc.append(str(int((status == pkg.Status.MECHANICS_NOT_CONVERGED).sum())))
        rows.append(f"| {name} | " + " | ".join(f"{rates[k]:,.0f}" for k in versions) + f" | {ratio:.3f} | "
                    + " / ".join(nc) + " |")
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--base-dir", help="directory holding a baseline copy softgrip_jax_base")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--only", choices=["sweeps", "speed"], action="append")
    args = parser.parse_args()
    versions = {}
    if args.base_dir:
        sys.path.insert(0, args.base_dir)
        versions["before"] = importlib.import_module("softgrip_jax_base")
    versions["after" if args.base_dir else "this checkout"] = importlib.import_module("softgrip_jax")
    parts = args.only or ["sweeps", "speed"]
    print(f"Machine: {describe()}\n", flush=True)
    if "speed" in parts:
        print("\n".join(throughput(versions, args.repeats)), "\n", flush=True)
    if "sweeps" in parts:
        print("\n".join(sweeps(versions)), flush=True)


if __name__ == "__main__":
    main()
