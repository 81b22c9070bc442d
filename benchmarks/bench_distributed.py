"""``estimate_batch`` and ``score`` in one process against the same batch split over several
processes joined by ``jax.distributed`` on this machine (loopback, gloo CPU collectives, one CPU
device per process).

    python benchmarks/bench_distributed.py                       # 1 and 2 processes
    python benchmarks/bench_distributed.py --processes 2 --batch 20000 --repeats 3 --json

Each run is a set of new processes; each times its calls after a first (compiling) call, with
``block_until_ready``, and checks that its result equals the single process's (the first run's,
saved to a temporary file). One process uses its default ``workers`` (one part per core).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _worker(args) -> None:
    import jax
    args.processes = args.processes[0]
    if args.processes > 1:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(coordinator_address=f"127.0.0.1:{args.port}", num_processes=args.processes,
                                   process_id=args.rank)
    import numpy as np

    from softgrip_jax import FingerModel, Gripper, PolygonSDF, estimate_batch, score
    finger = FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=20)
    gripper = Gripper(left=finger, right=finger, base_separation=56.0)
    disc = PolygonSDF.regular((0.0, 38.0), 15.0, 128)
    rng = np.random.default_rng(0)
    bases = rng.uniform([-40.0, -10.0], [10.0, 10.0], (args.batch, 2)).astype(np.float32)
    poses = rng.uniform([-20.0, -20.0, -0.2], [20.0, 20.0, 0.2], (args.batch // 2, 3)).astype(np.float32)
    calls = {"estimate_batch": lambda: estimate_batch(finger, disc, bases, method=args.method),
             "score": lambda: score(gripper, disc, poses, method=args.method)}
    out = {"processes": jax.process_count(), "devices": len(jax.devices())}
    results = {}
    for name, call in calls.items():
        start = time.perf_counter()
        results[name] = jax.block_until_ready(call())
        out[f"{name}_first_s"] = time.perf_counter() - start
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            jax.block_until_ready(call())
            times.append(time.perf_counter() - start)
        out[f"{name}_s"] = min(times)
    arrays = {"joints": np.asarray(results["estimate_batch"].joints), "score": np.asarray(results["score"].score)}
    reference = Path(args.reference)
    if args.rank == 0 and not reference.exists():
        np.savez(reference, **arrays)
    elif reference.exists():
        ref = np.load(reference)
        out["max_joint_diff_mm"] = float(np.nanmax(np.abs(ref["joints"] - arrays["joints"])))
        finite = np.isfinite(ref["score"]) & np.isfinite(arrays["score"])
        out["valid_mismatches"] = int(np.sum(np.isfinite(ref["score"]) != np.isfinite(arrays["score"])))
        out["max_score_diff"] = float(np.max(np.abs(ref["score"][finite] - arrays["score"][finite]), initial=0.0))
    if args.processes > 1:
        jax.distributed.shutdown()
    if args.rank == 0:
        print(json.dumps(out))


def _run(processes: int, args, reference: str) -> dict:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)
    cmd = [sys.executable, __file__, "--worker", "--processes", str(processes), "--port", str(port), "--batch",
           str(args.batch), "--repeats", str(args.repeats), "--method", args.method, "--reference", reference]
    procs = [subprocess.Popen(cmd + ["--rank", str(r)], env=env, stdout=subprocess.PIPE, text=True)
             for r in range(processes)]
    outs = [p.communicate()[0] for p in procs]
    if any(p.returncode for p in procs):
        raise SystemExit(f"a process failed with {processes} processes")
    return json.loads(outs[0].strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--processes", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--batch", type=int, default=20000, help="finger bases; score gets half as many poses")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--method", default="geometric")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--rank", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--reference", default="", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        return _worker(args)
    from benchmarks._machine import describe
    with tempfile.TemporaryDirectory() as tmp:
        reference = os.path.join(tmp, "one_process.npz")
        rows = [_run(n, args, reference) for n in sorted(args.processes)]
    if args.json:
        print(json.dumps({"machine": describe(), "rows": rows}, indent=2))
        return
    print(describe())
    for row in rows:
        print(json.dumps(row))


if __name__ == "__main__":
    main()
