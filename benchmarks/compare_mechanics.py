"""The mechanics estimate of this checkout against a baseline copy, on four objects: speed and what changed.

The baseline is a copy of ``softgrip_jax`` renamed ``softgrip_jax_base`` in ``--base-dir``, made as
``compare_estimate.py``'s docstring says. Run from the repository root:

    .venv/bin/python benchmarks/compare_mechanics.py --base-dir /tmp/sg_base --batch 4000

Objects: a 20 mm disc, an 18 mm square, a triangle and a five-lobed clover (radius 10 +- 3 mm),
each an SDFGrid of 0.25 mm cells sampled from its exact distance; one finger of N = 20 (L 52 mm,
Theta 0.7 rad, r 4 mm), ``--batch`` bases uniform in a 24 x 24 mm square; ``estimate_batch`` at
defaults (the default estimator, Mechanics()). The two versions alternate (best of 2 each). Prints,
per object: both rates and their ratio; among the fingers both versions converge on, the largest
joint difference and how many differ by more than 0.01 mm; how many change case, event or status;
and how many each version leaves not converged (``MECHANICS_NOT_CONVERGED``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def polygon_sdf(x, y, corners):
    """Exact signed distance (mm) of the points (x, y) to the polygon ``corners`` (V, 2), in numpy."""
    p = np.stack([x.ravel(), y.ravel()], axis=1)
    d = np.full(len(p), np.inf)
    inside = np.zeros(len(p), bool)
    for a, b in zip(corners, np.roll(corners, -1, axis=0)):
        ab = b - a
        t = np.clip(((p - a) @ ab) / (ab @ ab), 0.0, 1.0)
        d = np.minimum(d, np.hypot(*(p - a - t[:, None] * ab).T))
        straddles = (a[1] > p[:, 1]) != (b[1] > p[:, 1])
        with np.errstate(divide="ignore", invalid="ignore"):
            inside ^= straddles & (p[:, 0] < a[0] + (p[:, 1] - a[1]) * ab[0] / ab[1])
    return np.where(inside, -d, d).reshape(x.shape)


def objects():
    xs = np.arange(-40.0, 80.0, 0.25)
    x, y = np.meshgrid(xs, xs, indexing="xy")
    cx, cy = 25.0, 45.0
    t = np.linspace(0.0, 2 * np.pi, 400, endpoint=False)
    lobes = 10.0 + 3.0 * np.cos(5 * t)
    return {
        "disc": np.hypot(x - cx, y - cy) - 10.0,
        "square": polygon_sdf(x, y, np.array([[cx - 9, cy - 9], [cx + 9, cy - 9], [cx + 9, cy + 9], [cx - 9, cy + 9]])),
        "triangle": polygon_sdf(x, y, np.array([[cx, cy - 11], [cx + 11, cy + 8], [cx - 11, cy + 8]])),
        "clover": polygon_sdf(x, y, np.stack([cx + lobes * np.cos(t), cy + lobes * np.sin(t)], axis=1)),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base-dir", default="/tmp/sg_base")
    parser.add_argument("--batch", type=int, default=4000)
    args = parser.parse_args()
    sys.path.insert(1, args.base_dir)
    import softgrip_jax as new
    import softgrip_jax_base as base

    bases = np.random.default_rng(0).uniform(-12.0, 12.0, (args.batch, 2)).astype(np.float32)

    def prepared(pkg, values):
        finger = pkg.FingerModel(length=52.0, theta_entire=0.7, half_thickness=4.0, n_links=20)
        sdf = pkg.SDFGrid(values=jnp.asarray(values.astype(np.float32)), origin=jnp.array([-40.0, -40.0]),
                          spacing=jnp.array([0.25, 0.25]))
        run = lambda: pkg.estimate_batch(finger, sdf, bases)  # noqa: E731
        return run, jax.block_until_ready(run())

    not_converged = int(new.Status.MECHANICS_NOT_CONVERGED)
    for name, values in objects().items():
        (run_new, a), (run_base, b) = prepared(new, values), prepared(base, values)
        times: dict[str, list[float]] = {"new": [], "base": []}
        for _ in range(2):
            for key, run in (("new", run_new), ("base", run_base)):
                t = time.perf_counter()
                jax.block_until_ready(run().joints)
                times[key].append(time.perf_counter() - t)
        rate_new, rate_base = (len(bases) / min(times[k]) for k in ("new", "base"))
        sa, sb = np.asarray(a.status), np.asarray(b.status)
        both = (sa == 0) & (sb == 0)
        dev = np.abs(np.asarray(a.joints) - np.asarray(b.joints)).max(axis=(1, 2))[both]
        changed = {k: int(np.sum(np.asarray(getattr(a, k)) != np.asarray(getattr(b, k))))
                   for k in ("case", "event", "status")}
        print(f"{name}: {rate_new:,.0f} / {rate_base:,.0f} fingers/s = {rate_new / rate_base:.2f}x | converged in both: "
              f"largest difference {dev.max():.4f} mm, {int(np.sum(dev > 0.01))} over 0.01 mm | changed: "
              f"{changed['case']} case, {changed['event']} event, {changed['status']} status | not converged: "
              f"{int(np.sum(sa == not_converged))} / {int(np.sum(sb == not_converged))}", flush=True)


if __name__ == "__main__":
    main()
