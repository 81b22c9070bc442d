"""Peak memory of ``softgrip_jax.score`` on large batches, against the size of its result (issue 21).

Run from the repository root (each batch size in a fresh process, so peaks do not mix):

    .venv/bin/python benchmarks/score_memory.py 1000000
    .venv/bin/python benchmarks/score_memory.py 5000000

The README planner's gripper and disc, B random poses around it, the geometric estimate. A thread
samples the process's resident set (``/proc/self/status`` VmRSS) every 5 ms during the call; the
figure is the peak above the resident set just before the call (poses already on the device,
the batch's function already compiled by a first call on the same B), divided by the bytes of the
returned ``Score``'s leaves. 1.0 would be the result alone.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(1, str(Path(__file__).resolve().parent.parent))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from softgrip_jax import FingerModel, Gripper, PolygonSDF, score  # noqa: E402
from softgrip_jax import Geometric


def rss_bytes() -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("no VmRSS in /proc/self/status (Linux only)")


def peak_during(fn):
    """(fn(), peak resident bytes while it ran)."""
    peak, done = [rss_bytes()], threading.Event()

    def sample():
        while not done.is_set():
            peak[0] = max(peak[0], rss_bytes())
            time.sleep(0.005)

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    try:
        out = jax.block_until_ready(fn())
    finally:
        done.set()
        thread.join()
    return out, max(peak[0], rss_bytes())


def main(argv: list[str] | None = None) -> str:
    from _machine import describe

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("batch", type=int, help="candidate poses B")
    args = parser.parse_args(argv)
    finger = FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=20)
    gripper = Gripper(left=finger, right=finger, base_separation=56.0)
    disc = PolygonSDF.regular(center=(0.0, 38.0), radius=15.0, n_vertices=128)
    rng = np.random.default_rng(0)
    poses = jnp.asarray(np.column_stack([rng.uniform(-10, 10, args.batch), rng.uniform(-10, 10, args.batch),
                                         rng.uniform(-0.2, 0.2, args.batch)]).astype(np.float32))
    jax.block_until_ready(score(gripper, disc, poses, estimator=Geometric()))  # compile for this B
    before = rss_bytes()
    t0 = time.perf_counter()
    result, peak = peak_during(lambda: score(gripper, disc, poses, estimator=Geometric()))
    seconds = time.perf_counter() - t0
    size = sum(leaf.nbytes for leaf in jax.tree_util.tree_leaves(result))
    line = (f"| {args.batch:,} | {size / 2**20:.0f} | {(peak - before) / 2**20:.0f} | {(peak - before) / size:.2f} "
            f"| {seconds:.1f} |")
    text = "\n".join(["Command (from the repository root):\n",
                      f"    .venv/bin/python benchmarks/score_memory.py {args.batch}\n",
                      f"Machine: {describe()}\n",
                      "| poses | result (MiB) | peak above the start (MiB) | peak / result | call (s) |",
                      "|---|---|---|---|---|", line])
    print(text)
    return text


if __name__ == "__main__":
    main()
