"""XLA:CPU's fusion emitters against its loop emitter: compile time and speed of ``score`` and ``refine``.

Each setting runs in its own process (compile cache off): the README's gripper and disc, ``score``
of 4,096 random poses (geometric and mechanics: first call, then the best of 3) and ``refine`` of
one pose (geometric and mechanics: first call, then the median of 12 calls from 4 starts, and the
score each start ends at).

    python benchmarks/bench_emitters.py            # the two settings, twice each, interleaved
    python benchmarks/bench_emitters.py --repeats 1

Settings: ``shipped`` (each estimator's options as the package compiles them: XLA:CPU's MLIR fusion
emitters for both), ``loop`` (the same options with ``xla_cpu_use_fusion_emitters=False``: XLA:CPU's
loop emitter).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = """
import json, os, sys, time
os.environ["SOFTGRIP_JAX_CACHE"] = "0"
setting = sys.argv[1]
import jax, jax.numpy as jnp
from softgrip_jax import FingerModel, Geometric, Gripper, Mechanics, PolygonSDF, refine, score
if setting == "loop":
    for estimator_class in (Geometric, Mechanics):
        estimator_class.cpu_options = {**estimator_class.cpu_options, "xla_cpu_use_fusion_emitters": False}

finger = FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=20)
gripper = Gripper(left=finger, right=finger, base_separation=56.0)
obj = PolygonSDF.regular(center=(0.0, 38.0), radius=15.0, n_vertices=128)
poses = jax.random.uniform(jax.random.PRNGKey(0), (4096, 3), minval=jnp.array([-12.0, -12.0, -0.3]),
                           maxval=jnp.array([12.0, 12.0, 0.3]))

def timed(fn):
    t = time.perf_counter(); out = fn(); jax.block_until_ready(out); return time.perf_counter() - t, out

out = {"setting": setting}
for name, est in (("geometric", Geometric()), ("mechanics", Mechanics())):
    first, _ = timed(lambda: score(gripper, obj, poses, estimator=est).score)
    steady = min(timed(lambda: score(gripper, obj, poses, estimator=est).score)[0] for _ in range(3))
    out[f"score_{name}"] = {"first_s": round(first, 2), "steady_s": round(steady, 3)}
starts = [jnp.array(p) for p in ([1.0, 0.0, 0.0], [4.0, -3.0, 0.1], [-2.0, 1.0, -0.1], [3.0, 2.0, 0.15])]
for name, est in (("geometric", Geometric()), ("mechanics", Mechanics())):
    first, _ = timed(lambda: refine(gripper, obj, starts[0], estimator=est).pose)
    times = sorted(timed(lambda: refine(gripper, obj, s, estimator=est).pose)[0] for s in starts * 3)
    ends = [round(float(refine(gripper, obj, s, estimator=est).score.score), 3) for s in starts]
    out[f"refine_{name}"] = {"first_s": round(first, 2), "median_ms": round(1000 * times[len(times) // 2], 1),
                             "end_scores": ends}
print(json.dumps(out))
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    sys.path.insert(0, str(ROOT))
    from benchmarks._machine import describe

    print(json.dumps({"machine": describe()}))
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for _ in range(args.repeats):
        for setting in ("shipped", "loop"):
            done = subprocess.run([sys.executable, "-c", CHILD, setting], env=env, cwd=ROOT, capture_output=True,
                                  text=True, check=True)
            print(done.stdout.strip().splitlines()[-1], flush=True)


if __name__ == "__main__":
    main()
