"""Where the geometric estimate's time goes: XLA:CPU kernels by name, from a ``jax.profiler`` trace.

Run from the repository root:

    .venv/bin/python benchmarks/profile_estimate.py            # 8,192 bases, N = 20, top 30 kernels
    .venv/bin/python benchmarks/profile_estimate.py --batch 2048 --n 10 --top 50
    .venv/bin/python benchmarks/profile_estimate.py --touching --batch 16384 --vary   # cost of each stage
    .venv/bin/python benchmarks/profile_estimate.py --touching --batch 100000 --parts 1,2,4   # part counts
    .venv/bin/python benchmarks/profile_estimate.py --touching --batch 100000 --chunks 2048,4096   # chunk sizes

Same scene as bench_estimate.py. Prints the throughput of the traced configuration, then each kernel's
total time over the traced call, how often it ran, its output shape and the JAX operation it came
from (kernel names are XLA's fusion names, e.g. ``bitcast_gather_fusion.26``). Kernel times are
summed over XLA's worker threads, so they add up to more than the wall time.
"""

from __future__ import annotations

import argparse
import collections
import re
import sys
import tempfile
import time
from pathlib import Path
from softgrip_jax import Geometric

# Profile this checkout's package, not whichever one the interpreter has installed.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(1, str(Path(__file__).resolve().parent))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch", type=int, default=8192)
    parser.add_argument("--n", type=int, default=20, help="links per finger")
    parser.add_argument("--chunk", type=int, default=4096)
    parser.add_argument("--top", type=int, default=30, help="kernels to list")
    parser.add_argument("--touching", action="store_true",
                        help="only bases whose finger touches while closing (bench_estimate.py's 'touching')")
    parser.add_argument("--workers", type=int, default=1,
                        help="concurrent parts (default 1: one computation, whose kernels the trace lists)")
    parser.add_argument("--vary", action="store_true",
                        help="instead of the trace: time per finger with stages cut down (root finder capped at one "
                             "Newton step, 8 second-contact samples, a 10x looser root tolerance), alternating, "
                             "median of 5")
    parser.add_argument("--chunks", default=None,
                        help="instead of the trace: throughput with these chunk sizes (e.g. 2048,4096) and the default "
                             "parts, alternating in this process, median of 5")
    parser.add_argument("--parts", default=None,
                        help="instead of the trace: throughput with these concurrent part counts (e.g. 1,2,4), "
                             "alternating in this process, median of 5")
    args = parser.parse_args()

    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax.profiler import ProfileData

    import softgrip_jax
    from _scene import disc_grid, finger, mixed_bases, touching_bases
    from softgrip_jax import ContactConfig, estimate_batch

    grid = disc_grid(softgrip_jax)
    finger = finger(softgrip_jax, args.n)
    bases = touching_bases(args.n, args.batch) if args.touching else mixed_bases(args.batch)
    bases = jnp.asarray(bases)

    def run(b, config=ContactConfig(), workers=args.workers, chunk=args.chunk):
        return estimate_batch(finger, grid, b, config, chunk_size=chunk, estimator=Geometric(), workers=workers)

    def alternate(label, variants):
        """Median throughput of each variant (keyword arguments of ``run``), alternating, 5 rounds."""
        times = {name: [] for name in variants}
        for kwargs in variants.values():
            jax.block_until_ready(run(bases, **kwargs))
        for _ in range(5):
            for name, kwargs in variants.items():
                t0 = time.perf_counter()
                jax.block_until_ready(run(bases, **kwargs))
                times[name].append(time.perf_counter() - t0)
        for name, t in times.items():
            print(f"{label(name)}: {args.batch / np.median(t):10,.0f} candidate-fingers/s")

    if args.parts:
        alternate(lambda c: f"{c} part(s)", {int(c): dict(workers=int(c)) for c in args.parts.split(",")})
        return
    if args.chunks:
        alternate(lambda c: f"chunk {c}", {int(c): dict(workers=None, chunk=int(c)) for c in args.chunks.split(",")})
        return

    if args.vary:
        configs = {"default": ContactConfig(), "root finder capped at 1 step": ContactConfig(root_max_steps=1),
                   "8 second-contact samples": ContactConfig(n_circle=8),
                   "root tolerance 1e-3": ContactConfig(root_atol=1e-3)}
        times = {name: [] for name in configs}
        for config in configs.values():
            jax.block_until_ready(run(bases, config))
        for _ in range(5):
            for name, config in configs.items():
                t0 = time.perf_counter()
                jax.block_until_ready(run(bases, config))
                times[name].append(time.perf_counter() - t0)
        for name, t in times.items():
            print(f"{name:30s} {np.median(t) / args.batch * 1e6:6.2f} us per finger")
        return

    jax.block_until_ready(run(bases))
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        jax.block_until_ready(run(bases))
        best = min(best, time.perf_counter() - t0)
    print(f"{args.batch / best:,.0f} candidate-fingers/s (N = {args.n}, batch {args.batch}, best of 3)")

    with tempfile.TemporaryDirectory() as folder:
        with jax.profiler.trace(folder):
            jax.block_until_ready(run(bases))
        trace = next(Path(folder).rglob("*.xplane.pb"))
        profile = ProfileData.from_file(str(trace))
    total, count = collections.Counter(), collections.Counter()
    for plane in profile.planes:
        for line in plane.lines:
            if not line.name.startswith("tf_XLAEigen"):  # XLA:CPU's worker threads
                continue
            for event in line.events:
                if not event.name.startswith(("ThunkExecutor", "while")):
                    total[event.name] += event.duration_ns
                    count[event.name] += 1
    hlo = jax.jit(run).lower(bases).compile().as_text()
    print(f"kernels: {sum(total.values()) / 1e6:.1f} ms summed over threads\n")
    print(f"{'ms':>8} {'runs':>5}  {'kernel':40s} {'output':30s} operation")
    for name, ns in total.most_common(args.top):
        found = re.search(r"%" + re.escape(name) + r" = (.*?) fusion\(.*?op_name=\"([^\"]*)\"", hlo)
        shape, op = (re.sub(r"\{[^}]*\}", "", found.group(1)), found.group(2).split("/")[-1]) if found else ("?", "?")
        print(f"{ns / 1e6:8.2f} {count[name]:5d}  {name:40s} {shape:30s} {op}")


if __name__ == "__main__":
    main()
