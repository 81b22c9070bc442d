"""A batch split evenly across every JAX device: several GPUs, or hosts joined by ``jax.distributed``.

With more than one device in ``jax.devices()``, the batch functions place their candidates on a
one-axis :class:`jax.sharding.Mesh` named ``"candidates"`` with a ``NamedSharding`` (no ``pmap``):
each device scans its share in chunks. Every candidate is computed independently, so results are
those of one device. When the devices belong to several processes (``jax.distributed``), each
process passes the same batch and every process receives the whole result (replicated), readable
with numpy as on one device.
"""

from __future__ import annotations

from functools import partial

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from softgrip_jax._concurrent import balanced_chunk, pad_rows

AXIS = "candidates"


def device_mesh() -> Mesh | None:
    """The mesh over ``jax.devices()`` (every process's devices), or None for a single device."""
    devices = jax.devices()
    return Mesh(np.array(devices), (AXIS,)) if len(devices) > 1 else None


def run_sharded(fn, mesh: Mesh, before: tuple, xs: jax.Array, after: tuple, chunk_size: int, **static):
    """``fn(*before, shares, *after, chunk_size=..., **static)`` for a jitted ``fn`` that maps a
    (devices, per_device, ...) array of candidates to outputs with those two leading axes; the
    shares are placed one per device of ``mesh``. Returns outputs with ``xs``'s leading axis."""
    b = xs.shape[0]
    n_dev = mesh.devices.size
    per_device = max(1, -(-b // n_dev))
    shares = pad_rows(xs, n_dev * per_device).reshape((n_dev, per_device) + xs.shape[1:])
    # Across processes, device_put takes each process's (identical) batch and keeps its devices' shares.
    shares = jax.device_put(shares, NamedSharding(mesh, PartitionSpec(AXIS)))
    out = fn(*before, shares, *after, chunk_size=balanced_chunk(per_device, chunk_size), **static)
    if jax.process_count() > 1:  # each process gets the whole result, not only its own devices' rows
        return _joined_replicated(out, b, NamedSharding(mesh, PartitionSpec()))
    return _join(out, b)


def _join(out, b):
    return jax.tree_util.tree_map(lambda x: x.reshape((x.shape[0] * x.shape[1],) + x.shape[2:])[:b], out)


@partial(jax.jit, static_argnums=(1, 2))
def _joined_replicated(out, b, replicated):
    return jax.lax.with_sharding_constraint(_join(out, b), replicated)
