"""Evaluate a function only on the elements of a batch that need it, a fixed-size group at a time.

The batch functions (:mod:`softgrip_jax._batch`) and the batched estimators
(:mod:`softgrip_jax._estimators`) use it so that the cost of a step that only some candidates need
(the contact's root finder, the mechanics solve) follows the number of those candidates rather than
the batch size.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool

from softgrip_jax._trace import trace_once

#: A chunk's needed candidates are mapped in groups of ceil(chunk / _SOLVE_GROUPS) by default.
_SOLVE_GROUPS = 8


def where_needed(fn, need: Bool[Array, " b"] | Bool[np.ndarray, " b"], inputs, groups: int = _SOLVE_GROUPS,
                 kinds=None, n_kinds: int = 1, group_size: int | None = None):
    """``jax.vmap(fn)(inputs)`` evaluated only where ``need`` holds (elsewhere: zeros).

    The needed elements are gathered to the front and mapped a group at a time; groups with
    nothing to do are skipped (``lax.cond``), so the cost follows the number of needed elements
    (a group's spare lanes repeat one of its needed elements, so they never outlast it).
    ``kinds`` (optional, (b,) integers in [0, ``n_kinds``)): the needed elements are ordered by
    kind first, so that elements of like cost (say, as many loop iterations) share their groups.
    Differentiable (gathers, ``lax.map`` and ``lax.cond``).
    """
    b = need.shape[0]
    if group_size is None:
        groups = max(1, min(groups, b))  # a small batch (one candidate) is one group, not eight
        size = -(-b // groups)
    else:  # (a batch smaller than a group is one group of its own size: one pose computes one lane)
        size = max(1, min(group_size, b))
        groups = -(-b // size)
    # Needed first, each part in its original order: every element's place from two running
    # counts (cheaper than an argsort on XLA:CPU).
    count = jnp.sum(need)
    if kinds is None or n_kinds <= 1:
        rank = jnp.cumsum(need) - 1
    else:  # by kind, then in order: a running count per kind after the counts of the kinds before
        of_kind = need[:, None] & (jnp.clip(kinds, 0, n_kinds - 1)[:, None] == jnp.arange(n_kinds)[None, :])
        running = jnp.cumsum(of_kind, axis=0)
        before = jnp.cumsum(running[-1]) - running[-1]
        rank = jnp.sum(jnp.where(of_kind, running - 1 + before[None, :], 0), axis=1)
    place = jnp.where(need, rank, count + jnp.cumsum(~need) - 1)
    order = jnp.zeros(b, place.dtype).at[place].set(jnp.arange(b, dtype=place.dtype), unique_indices=True)
    padded = jnp.concatenate([order, jnp.zeros(groups * size - b, order.dtype)])
    wanted = jnp.arange(groups * size) < count
    take = lambda idx: jax.tree_util.tree_map(lambda x: x[idx], inputs)  # noqa: E731
    out_shape, mapped = trace_once(jax.vmap(fn), take(padded[:size]))

    def group(g):
        idx = jax.lax.dynamic_slice_in_dim(padded, g * size, size)
        work = jax.lax.dynamic_slice_in_dim(wanted, g * size, size)
        # The group's spare lanes repeat its first (needed) element: an element that needs nothing
        # can be one whose loops would run to their budget (a collision, a base far off), and
        # under vmap the whole group would wait on it; its answer is discarded anyway.
        idx = jnp.where(work, idx, idx[0])
        return jax.lax.cond(
            jnp.any(work),
            lambda: mapped(take(idx)),
            lambda: jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), out_shape),
        )

    out = jax.lax.map(group, jnp.arange(groups))

    def restore(x):
        x = x.reshape((groups * size,) + x.shape[2:])[place]
        return jnp.where(need.reshape((b,) + (1,) * (x.ndim - 1)), x, jnp.zeros((), x.dtype))

    return jax.tree_util.tree_map(restore, out)
