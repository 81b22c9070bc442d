"""The estimate benchmarks' scene: a 480x640 SDF grid at the D405's scale at 120 mm (0.31 mm/px) with
a 30 mm disc, a 52 mm finger, and two sets of candidate bases ("mixed" and "touching", see
bench_estimate.py). ``pkg`` is the package to build them with (``softgrip_jax``, or a baseline copy
of it in compare_estimate.py).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from softgrip_jax import Geometric

SPACING_MM = 120.0 / 385.0


def disc_grid(pkg):
    """The SDF grid (480 x 640, SPACING_MM) of a 15 mm-radius disc at the origin."""
    return pkg.SDFGrid.sample(lambda p: jnp.linalg.norm(p, axis=-1) - 15.0,
                              origin=(-320 * SPACING_MM, -240 * SPACING_MM), spacing=(SPACING_MM, SPACING_MM),
                              shape=(480, 640))


def finger(pkg, n_links: int):
    return pkg.FingerModel(length=52.0, theta_entire=0.5, half_thickness=4.0, n_links=n_links)


def mixed_bases(batch: int) -> np.ndarray:
    """(batch, 2) float32 bases spread uniformly over an 80 x 60 mm window above the disc."""
    return np.random.default_rng(0).uniform([-60.0, -70.0], [20.0, -10.0], (batch, 2)).astype(np.float32)


def touching_bases(n_links: int, batch: int) -> np.ndarray:
    """(batch, 2) float32 bases whose finger touches the disc while closing (valid, case other than
    none), picked from 20,000 mixed bases by this checkout's estimate and repeated up to ``batch``."""
    import softgrip_jax as current

    pool = mixed_bases(20_000)
    first = current.estimate_batch(finger(current, n_links), disc_grid(current), pool, estimator=Geometric())
    return np.resize(pool[np.asarray(first.valid & (first.case != 0))], (batch, 2))
