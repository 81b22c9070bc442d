"""A planner's process calling with ever new batch sizes: what each call costs, and what it leaves.

    python benchmarks/bench_batch_sizes.py [--sizes 100,300,...] [--random-calls 1000] [--quick]

One process, the compilation cache off (so that nothing is hidden): for the core ``softgrip_jax.score``
(the README planner's gripper and a 30 mm disc) and for ``Scene.score`` (the sample frame
``data/circle_open`` with ``data/sample_profile.json``), each estimator (``Geometric()``,
``Mechanics()``) is called once per batch size in the order given, then again (steady). Reported
per call: the time, the steady time of the same size, and the call against its size-proportional
steady cost (the steady time per pose at the largest size, times B). The issue's criterion: after
the first call per estimator, no call above 3x. Then ``--random-calls`` calls of random sizes
(1 .. 3,000, geometric) count the programs compiled (``jax.log_compiles``) and the process's memory
maps (/proc/self/maps) before and after.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("SOFTGRIP_JAX_CACHE", "0")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
import numpy as np  # noqa: E402

from benchmarks._machine import CompileCounter, describe  # noqa: E402


def memory_maps() -> int:
    with open("/proc/self/maps") as f:
        return sum(1 for _ in f)


def random_poses(rng, b: int) -> np.ndarray:
    return rng.uniform([-10.0, -10.0, -0.2], [10.0, 10.0, 0.2], (b, 3)).astype(np.float32)


def core_caller():
    from softgrip_jax import FingerModel, Gripper, PolygonSDF, score

    finger = FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=20)
    gripper = Gripper(left=finger, right=finger, base_separation=56.0)
    disc = PolygonSDF.regular(center=(0.0, 38.0), radius=15.0, n_vertices=128)
    return lambda poses, estimator: jax.block_until_ready(score(gripper, disc, poses, estimator=estimator).score)


def scene_caller():
    from softgrip_calib.profile import load_profile
    from softgrip_vision.scene import frame_scene

    scene = frame_scene(ROOT / "data" / "circle_open", load_profile(ROOT / "data" / "sample_profile.json"))
    centre = np.asarray(scene.pose, np.float32)
    return lambda poses, estimator: scene.score(poses + centre, estimator=estimator).score


def timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def sizes_table(name: str, call, sizes: list[int], estimators: dict) -> list[str]:
    rng = np.random.default_rng(0)
    rows = []
    for label, estimator in estimators.items():
        poses = {b: random_poses(rng, b) for b in sizes}
        first = [timed(lambda b=b: call(poses[b], estimator)) for b in sizes]
        steady = [min(timed(lambda b=b: call(poses[b], estimator)) for _ in range(2)) for b in sizes]
        per_pose = steady[-1] / sizes[-1]
        for i, b in enumerate(sizes):
            proportional = per_pose * b
            rows.append(f"| {name} | {label} | {b:,} | {first[i]:.2f} | {steady[i]:.3f} | "
                        f"{first[i] / steady[i]:.2f} | {first[i] / proportional:.2f}"
                        f"{' (first call: compiles)' if i == 0 else ''} |")
            print(rows[-1], flush=True)
    return rows


def random_sizes(call, calls: int) -> str:
    from softgrip_jax import Geometric

    rng = np.random.default_rng(1)
    counter = CompileCounter()
    logger = logging.getLogger("jax")
    call(random_poses(rng, 5), Geometric())  # warm: the piece program and every helper compiled
    before, start = memory_maps(), time.perf_counter()
    with jax.log_compiles(True):
        logger.addHandler(counter)
        try:
            for b in rng.integers(1, 3001, calls):
                call(random_poses(rng, int(b)), Geometric())
        finally:
            logger.removeHandler(counter)
    return (f"{calls:,} calls of random sizes 1 .. 3,000 (core score, geometric): {counter.count} programs "
            f"compiled, memory maps {before:,} -> {memory_maps():,} (+{memory_maps() - before:,}), "
            f"{time.perf_counter() - start:.0f} s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="100,300,1000,2500,3000,5000,7000,10000")
    parser.add_argument("--random-calls", type=int, default=1000)
    parser.add_argument("--quick", action="store_true", help="sizes 100,300,1000 and 50 random calls")
    parser.add_argument("--only", choices=("core", "scene", "random"), action="append")
    args = parser.parse_args()
    sizes = [100, 300, 1000] if args.quick else [int(s) for s in args.sizes.split(",")]
    calls = 50 if args.quick else args.random_calls
    only = set(args.only or ("core", "scene", "random"))

    from softgrip_jax import Geometric, Mechanics

    estimators = {"geometric": Geometric(), "mechanics": Mechanics()}
    print(f"Command: python benchmarks/bench_batch_sizes.py {' '.join(sys.argv[1:])}".rstrip())
    print(f"Machine: {describe()}\n")
    print("| entry point | estimator | B | call (s) | steady (s) | call / steady | call / size-proportional steady |")
    print("|---|---|---|---|---|---|---|")
    if "core" in only:
        sizes_table("core score", core_caller(), sizes, estimators)
    if "scene" in only:
        sizes_table("Scene.score", scene_caller(), sizes, estimators)
    if "random" in only:
        print("\n" + random_sizes(core_caller(), calls))


if __name__ == "__main__":
    main()
