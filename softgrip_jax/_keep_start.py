"""A quasi-Newton minimiser that also keeps what the objective gave at the start.

:func:`~softgrip_jax.refine` compares the pose the minimiser ends at with the start pose, and
returns the start's full score when the end is no better. Scoring the start apart from the
minimiser would put another copy of the score in the compiled program; the minimiser already
evaluates the objective at the start in its first step (the first step of optimistix's
quasi-Newton minimisers evaluates at ``y0`` and is always accepted), so this wrapper keeps that
evaluation's auxiliary output in its state.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, PyTree


class KeepStartState(eqx.Module):
    """The wrapped minimiser's state, and the auxiliary output of its first evaluation (at ``y0``;
    zeros until that evaluation)."""

    inner: Any
    start_aux: PyTree


class KeepStart(optx.AbstractMinimiser):
    """``inner`` (an optimistix quasi-Newton minimiser such as ``optx.BFGS``), unchanged, with the
    auxiliary output at ``y0`` kept in ``solution.state.start_aux``; ``solution.state.inner.aux``
    is the auxiliary output at ``solution.value`` (the last accepted point).

    Needs ``max_steps >= 1`` (no step, no evaluation).
    """

    inner: optx.AbstractQuasiNewton
    rtol: float
    atol: float
    norm: Callable[[PyTree], Array] = eqx.field(static=True)

    def __init__(self, inner: optx.AbstractQuasiNewton):
        self.inner = inner
        self.rtol, self.atol, self.norm = inner.rtol, inner.atol, inner.norm  # its tolerances and norm

    def init(self, fn, y, args, options, f_struct, aux_struct, tags) -> KeepStartState:
        zeros = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), aux_struct)
        return KeepStartState(self.inner.init(fn, y, args, options, f_struct, aux_struct, tags), zeros)

    def step(self, fn, y, args, options, state: KeepStartState, tags):
        first: Bool[Array, ""] = state.inner.first_step
        y, inner, aux = self.inner.step(fn, y, args, options, state.inner, tags)
        # After the first step the inner state's aux is the evaluation at y0 (accepted).
        start = jax.tree_util.tree_map(lambda new, old: jnp.where(first, new, old), inner.aux, state.start_aux)
        return y, KeepStartState(inner, start), aux

    def terminate(self, fn, y, args, options, state: KeepStartState, tags):
        return self.inner.terminate(fn, y, args, options, state.inner, tags)

    def postprocess(self, fn, y, aux, args, options, state: KeepStartState, tags, result):
        return self.inner.postprocess(fn, y, aux, args, options, state.inner, tags, result)
