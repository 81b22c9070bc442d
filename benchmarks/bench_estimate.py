"""Throughput, latency, compile time and peak memory of the geometric estimate (issue 2).

Run from the repository root:

    .venv/bin/python benchmarks/bench_estimate.py            # full table (a few minutes)
    .venv/bin/python benchmarks/bench_estimate.py --quick    # tiny configuration (CI smoke test)

Each (N, batch) configuration runs in a fresh subprocess so that its peak resident memory is its
own. The scene is a 480x640 SDF grid at the D405's scale at 120 mm (0.31 mm/px) with a 30 mm
circle. Two sets of candidate bases:

* ``mixed``: spread uniformly over a 80 x 60 mm window above the circle, so that all four contact
  cases occur, and so do fingers that close freely (case none) or start inside the object
  (invalid: ``INITIAL_OVERLAP``); those need only the contact search, not its refinement.
* ``touching``: only bases whose finger first touches the circle while closing (valid, case other
  than none), picked from a larger uniform draw by an untimed first pass and repeated up to the
  batch size: every candidate needs the full estimate (contact search, root finder, second
  contact and deformation).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path
from softgrip_jax import Geometric

sys.path.insert(0, str(Path(__file__).resolve().parent))
# Measure this checkout's package, not whichever one the interpreter has installed (editable).
sys.path.insert(1, str(Path(__file__).resolve().parents[1]))


def run_one(n_links: int, batch: int, chunk: int, repeats: int, scene: str) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    import softgrip_jax
    from _scene import disc_grid, mixed_bases, touching_bases
    from _scene import finger as make_finger
    from softgrip_jax import estimate_batch

    grid = jax.block_until_ready(disc_grid(softgrip_jax))
    finger = make_finger(softgrip_jax, n_links)
    bases = mixed_bases(batch) if scene == "mixed" else touching_bases(n_links, batch)
    bases = jnp.asarray(bases)
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss

    t0 = time.perf_counter()
    out = jax.block_until_ready(estimate_batch(finger, grid, bases, chunk_size=chunk, estimator=Geometric()))
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats if batch > 1 else 50 * repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(estimate_batch(finger, grid, bases, chunk_size=chunk, estimator=Geometric()))
        times.append(time.perf_counter() - t0)
    # Throughput: the best call. Latency (one candidate): the median of many calls, as a caller sees it.
    steady = min(times) if batch > 1 else float(np.median(times))
    valid = np.asarray(out.valid)
    cases = np.bincount(np.asarray(out.case)[valid], minlength=4).tolist() + [int(np.sum(~valid))]
    return {
        "scene": scene, "n_links": n_links, "batch": batch, "chunk": min(chunk, batch), "compile_s": first - steady,
        "steady_s": steady, "per_second": batch / steady, "latency_ms": 1e3 * steady / batch if batch == 1 else None,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "rss_before_mb": rss_before / 1024, "cases": cases,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="tiny configuration for CI")
    parser.add_argument("--chunk", type=int, default=4096)
    parser.add_argument("--one", nargs=3, metavar=("SCENE", "N", "BATCH"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        scene, n, b = args.one[0], int(args.one[1]), int(args.one[2])
        print(json.dumps(run_one(n, b, args.chunk, repeats=1 if args.quick else 3, scene=scene)))
        return

    from _machine import describe

    links = [2] if args.quick else [2, 10, 20]
    batches = [1, 100] if args.quick else [1, 1_000, 100_000]
    command = "python benchmarks/bench_estimate.py" + (" --quick" if args.quick else "")
    print(f"`{command}` on {describe()}; chunk {args.chunk}\n")
    print("| bases | N | batch | candidate-fingers/s | latency (ms) | compile (s) | peak RSS (MB) "
          "| valid none/tip/tip+other/other, invalid |")
    print("|---|---|---|---|---|---|---|---|")
    for scene, n, b in [(scene, n, b) for scene in ("mixed", "touching") for n in links for b in batches]:
        cmd = [sys.executable, __file__, "--one", scene, str(n), str(b), "--chunk", str(args.chunk)]
        if args.quick:
            cmd.append("--quick")
        r = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.splitlines()[-1])
        latency = f"{r['latency_ms']:.3f}" if r["latency_ms"] is not None else "-"
        counts = r["cases"]
        print(f"| {scene} | {n} | {b:,} | {r['per_second']:,.0f} | {latency} | {r['compile_s']:.1f} | "
              f"{r['peak_rss_mb']:.0f} | {'/'.join(map(str, counts[:4]))}, {counts[4]} |", flush=True)


if __name__ == "__main__":
    main()
