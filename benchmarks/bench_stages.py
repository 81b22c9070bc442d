"""Where a chunk of the geometric batch spends its time, stage by stage.

Run from the repository root:

    .venv/bin/python benchmarks/bench_stages.py

The scene of ``../shared/speedcheck.py``: a 20 mm disc on an SDFGrid of 0.25 mm cells, N = 20,
L 52 mm, Theta 0.7, r 4 mm, one piece of 4,096 bases uniform in a 24 x 24 mm square, one thread of
work per stage (each stage jitted alone, XLA's fusion emitters on, best of 5). Prints microseconds
per finger. (The lookups' own cost and how many each call makes: ``bench_limits.py``.)
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(1, str(Path(__file__).resolve().parent))

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _machine import describe  # noqa: E402

import softgrip_jax as sg  # noqa: E402
from softgrip_jax._batch import finger_chunk  # noqa: E402
from softgrip_jax._contact import ContactConfig, sweep_parts  # noqa: E402
from softgrip_jax._frames import FingerFrame  # noqa: E402
from softgrip_jax._gather import where_needed  # noqa: E402
from softgrip_jax._stage import (finish_root_search, refine_search, search_contact, search_further,  # noqa: E402
                                 start_root_search)


def best(fn, *args, k=5):
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(k):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return min(times)


def main():
    print(describe())
    finger = sg.FingerModel(length=52.0, theta_entire=0.7, half_thickness=4.0, n_links=20)
    xs = np.arange(-40.0, 80.0, 0.25)
    x, y = np.meshgrid(xs, xs, indexing="xy")
    sdf = sg.SDFGrid(values=jnp.asarray((np.hypot(x - 25.0, y - 45.0) - 10.0).astype(np.float32)),
                     origin=jnp.array([-40.0, -40.0]), spacing=jnp.array([0.25, 0.25]))
    rng = np.random.default_rng(0)
    n = 4096
    frames = jax.vmap(FingerFrame.hanging_from)(jnp.asarray(rng.uniform(-12.0, 12.0, (n, 2)).astype(np.float32)))
    config, est = ContactConfig(), sg.Geometric()
    jit = lambda f: jax.jit(f, compiler_options=dict(est.cpu_options))  # noqa: E731
    first, second = sweep_parts(config)

    part1 = jit(lambda fr: jax.vmap(lambda f: search_contact(finger, sdf, f, config, est, first))(fr))
    s1 = part1(frames)

    def further(s):
        free = ~s.bracket.touches
        later = where_needed(lambda q: search_further(finger, sdf, q, config, second), free, s)
        return eqx.tree_at(lambda q: q.bracket, s, jax.tree_util.tree_map(lambda a, b: jnp.where(free, a, b),
                                                                         later, s.bracket))

    part2 = jit(further)
    searches = part2(s1)
    need = jax.vmap(lambda s: s.need_refining)(searches)
    start = jit(lambda s, m: where_needed(lambda q: start_root_search(finger, sdf, q, config), m, s))
    roots = start(searches, need)
    late = need & ~jax.vmap(lambda r: r.converged(config))(roots)
    finish = jit(lambda sr, m: where_needed(lambda q: finish_root_search(finger, sdf, q[0], config, q[1]), m, sr,
                                            group_size=32))
    post = jit(lambda sr, m: where_needed(lambda q: refine_search(finger, sdf, q[0], config, q[1]), m, sr))
    whole = jit(lambda fr: finger_chunk(finger, sdf, fr, config, est))
    print(f"{n} bases: {int(need.sum())} touch inside the sweep, {int(late.sum())} need more than the shared root steps")
    rows = [("bracket, first half of the sweep (all)", part1, (frames,)),
            ("bracket, second half (the still free)", part2, (s1,)),
            ("root, shared steps (touching)", start, (searches, need)),
            ("root, the rest (unconverged)", finish, ((searches, roots), late)),
            ("contact chain, second contact, surface points (touching)", post, ((searches, roots), need)),
            ("whole chunk (finger_chunk)", whole, (frames,))]
    for name, fn, args in rows:
        print(f"  {name}: {best(fn, *args) / n * 1e6:.2f} us/finger")


if __name__ == "__main__":
    main()
