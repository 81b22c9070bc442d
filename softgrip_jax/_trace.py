"""A function traced once, for loops that need its output shapes before its body is traced.

``lax.fori_loop`` with an output buffer and ``lax.cond`` with a branch of zeros need the shapes of
a function's output before the loop or the branch is traced; ``jax.eval_shape`` of the bare
function gets them by tracing it, and the loop body then traces it again. Nested (a chunk loop
around groups of the contact's root finder), every level doubled the tracing, most of a new
process's start-up.
"""

from __future__ import annotations

import jax


def trace_once(fn, *example):
    """``(shapes, same_fn)``: ``fn``'s output shapes (``ShapeDtypeStruct`` leaves) for arguments
    shaped like ``example``, and ``fn`` as an inlined ``jax.jit``, whose trace for those shapes
    JAX keeps: called again inside the loop with arguments of ``example``'s shapes, dtypes and
    weak types, it is not traced again, and its operations are inlined into the caller (the
    same program as calling ``fn``)."""
    same_fn = jax.jit(fn, inline=True)
    return jax.eval_shape(same_fn, *example), same_fn
