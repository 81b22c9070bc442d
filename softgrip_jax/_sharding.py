"""A batch split evenly across every JAX device: several GPUs, or hosts joined by ``jax.distributed``.

With more than one device in ``jax.devices()``, the batch functions place their candidates on a
one-axis :class:`jax.sharding.Mesh` named ``"candidates"`` with a ``NamedSharding`` (no ``pmap``):
each device scans its share in chunks. Every candidate is computed independently, so results are
those of one device. When the devices belong to several processes (``jax.distributed``), each
process passes the same batch and every process receives the whole result (replicated), readable
with numpy as on one device.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from softgrip_jax._concurrent import join_pieces, piece_size, split_pieces

AXIS = "candidates"


def device_mesh() -> Mesh | None:
    """The mesh over ``jax.devices()`` (every process's devices), or None for a single device."""
    devices = jax.devices()
    return Mesh(np.array(devices), (AXIS,)) if len(devices) > 1 else None


def run_sharded(fn, mesh: Mesh, before: tuple, xs: jax.Array | np.ndarray, after: tuple, chunk_size: int | None,
                progress: Callable[[int, int], None] | None = None, **static):
    """``fn(*before, shares, *after, chunk_size=..., **static)`` for a jitted ``fn`` that maps a
    (devices, chunk_size, ...) array of candidates to outputs with those two leading axes, in rounds
    of one ``chunk_size`` piece per device of ``mesh`` (None: the bucket that
    :func:`~softgrip_jax._concurrent.bucket_piece` chooses; a few programs whatever B is; the last
    round padded). Returns outputs with ``xs``'s leading axis; ``progress(done, total)`` after each
    round."""
    b = xs.shape[0]
    n_dev = mesh.devices.size
    size = piece_size(chunk_size, b, n_dev)
    pieces = split_pieces(xs, size)
    pieces += [pieces[-1]] * (-len(pieces) % n_dev)  # whole rounds (the extra pieces' rows are dropped)
    replicated = NamedSharding(mesh, PartitionSpec())
    outputs = []
    for r in range(0, len(pieces), n_dev):
        shares = np.stack(pieces[r:r + n_dev])
        # Across processes, device_put takes each process's (identical) batch and keeps its devices' shares.
        shares = jax.device_put(shares, NamedSharding(mesh, PartitionSpec(AXIS)))
        out = fn(*before, shares, *after, chunk_size=size, **static)
        if jax.process_count() > 1:  # each process gets the whole result, not only its own devices' rows
            out = _replicated(out, replicated)
        outputs += [jax.tree_util.tree_map(lambda x, i=i: x[i], out) for i in range(n_dev)]
        if progress is not None:
            progress(min(b, (r + n_dev) * size), b)
    return join_pieces(outputs, b)


@partial(jax.jit, static_argnums=(1,))
def _replicated(out, replicated):
    return jax.lax.with_sharding_constraint(out, replicated)
