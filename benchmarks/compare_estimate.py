"""Back-to-back throughput of estimate_batch: this checkout against a baseline copy of the package.

The baseline is a copy of ``softgrip_jax`` renamed ``softgrip_jax_base`` (imports rewritten) in the
directory given by ``--base-dir``, e.g.::

    git archive cfcecf0 softgrip_jax | tar -x -C /tmp/sg_base
    (cd /tmp/sg_base && mv softgrip_jax softgrip_jax_base &&
     sed -i 's/softgrip_jax\\./softgrip_jax_base./g; s/from softgrip_jax import/from softgrip_jax_base import/g' \\
        softgrip_jax_base/*.py)
    python benchmarks/compare_estimate.py --base-dir /tmp/sg_base --n 20 --batch 100000
    python benchmarks/compare_estimate.py --base-dir /tmp/sg_base --n 20 --batch 20000 --touching
    python benchmarks/compare_estimate.py --one-part --n 20 --batch 32768   # no baseline copy needed

``--one-part`` compares this checkout with itself run as one computation (``workers=1``) instead of
a baseline copy: the gain of the concurrent parts of ``softgrip_jax._concurrent``.

Same scene as bench_estimate.py; the two versions alternate so that machine load hits both alike.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import sys
import time

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

# This checkout's package, not whichever one the interpreter has installed.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(1, str(Path(__file__).resolve().parent))
from _scene import disc_grid, finger, mixed_bases, touching_bases  # noqa: E402


def chosen(pkg, method: str) -> dict:
    """The keyword that selects the estimate ``method`` ("geometric" or "mechanics") in ``pkg``'s version:
    ``estimator=`` (today), ``method=`` (older), or none (before the mechanics estimate)."""
    parameters = inspect.signature(pkg.estimate_batch).parameters
    if "estimator" in parameters:
        return {"estimator": pkg.Geometric() if method == "geometric" else pkg.Mechanics()}
    return {"method": method} if "method" in parameters else {}


def scene(pkg, n_links, batch, touching):
    bases = touching_bases(n_links, batch) if touching else mixed_bases(batch)
    return finger(pkg, n_links), jax.block_until_ready(disc_grid(pkg)), jnp.asarray(bases)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--base-dir", default="/tmp/sg_base")
    parser.add_argument("--n", type=int, default=20)
    parser.add_argument("--batch", type=int, default=100_000)
    parser.add_argument("--chunk", type=int, default=4096)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-base", action="store_true")
    parser.add_argument("--method", default="geometric", choices=("geometric", "mechanics"))
    parser.add_argument("--one-part", action="store_true",
                        help="the baseline is this checkout with workers=1 (one computation)")
    parser.add_argument("--touching", action="store_true",
                        help="only bases whose finger touches while closing (bench_estimate.py's 'touching')")
    args = parser.parse_args()
    sys.path.insert(0, args.base_dir)
    versions = {"new": importlib.import_module("softgrip_jax")}
    if args.one_part:
        versions["base"] = versions["new"]
    elif not args.no_base:
        versions["base"] = importlib.import_module("softgrip_jax_base")

    def options(k, p):
        method = chosen(p, args.method)
        return {**method, **({"workers": 1} if args.one_part and k == "base" else {})}
    setups = {k: scene(p, args.n, args.batch, args.touching) for k, p in versions.items()}
    outs, best, cpu = {}, {k: np.inf for k in versions}, {k: np.inf for k in versions}
    for k, p in versions.items():
        f, g, b = setups[k]
        t0 = time.perf_counter()
        outs[k] = jax.block_until_ready(p.estimate_batch(f, g, b, chunk_size=args.chunk, **options(k, p)))
        print(f"{k}: first call {time.perf_counter() - t0:.1f} s", flush=True)
    for _ in range(args.repeats):
        for k, p in versions.items():
            f, g, b = setups[k]
            t0, c0 = time.perf_counter(), time.process_time()
            jax.block_until_ready(p.estimate_batch(f, g, b, chunk_size=args.chunk, **options(k, p)))
            best[k] = min(best[k], time.perf_counter() - t0)
            cpu[k] = min(cpu[k], time.process_time() - c0)
    for k in versions:
        print(f"{k}: {args.batch / best[k]:,.0f} candidate-fingers/s (best {best[k]:.3f} s, cpu {cpu[k]:.3f} s)")
    if "base" in versions:
        print(f"speed-up new/base: {best['base'] / best['new']:.2f}x wall, {cpu['base'] / cpu['new']:.2f}x cpu")
        a, b = outs["new"], outs["base"]
        case_a, case_b = np.asarray(a.case), np.asarray(b.case)
        print("cases new", np.bincount(case_a, minlength=4).tolist(), "base", np.bincount(case_b, minlength=4).tolist(),
              "differ:", int(np.sum(case_a != case_b)))
        same = (case_a == case_b) & np.asarray(a.valid) & np.asarray(b.valid)
        dj = np.abs(np.asarray(a.joints) - np.asarray(b.joints)).max(axis=(1, 2))[same]
        ds = np.abs(np.asarray(a.contact.s1) - np.asarray(b.contact.s1))[same]
        print(f"same-case valid: max |joints diff| {dj.max():.2e} mm (99.9%: {np.quantile(dj, 0.999):.2e}), "
              f"max |s1 diff| {ds.max():.2e}; status differ: {int(np.sum(np.asarray(a.status) != np.asarray(b.status)))}")


if __name__ == "__main__":
    main()
