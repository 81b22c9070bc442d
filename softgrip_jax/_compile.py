"""How the batch functions are compiled: ``jax.jit`` with XLA:CPU options where they apply.

Three XLA:CPU compile options (the figures are in benchmarks/RESULTS.md), with results equal to
within float rounding:

* ``xla_cpu_prefer_vector_width=512``: LLVM may use 512-bit vectors where the CPU has them (a
  preference: on a CPU without AVX-512 the code is the same as without it);
* ``xla_cpu_experimental_ynn_fusion_type=""``: no YNNPACK fusions. XLA:CPU hands the estimate's
  many short reductions (over 5, 12 or 21 stations per candidate) to YNNPACK, which is slower on
  them than XLA's own loops;
* ``xla_cpu_use_fusion_emitters=False``: XLA:CPU's loop emitter instead of its MLIR fusion
  emitters. The estimate is hundreds of small kernels, and the fusion emitters pay a fixed cost
  per kernel at compile time: with the loop emitter a new process compiles ``score`` and ``refine``
  in about two thirds of the time; ``score`` runs as fast or faster, ``estimate_batch`` a few
  percent slower, and ``refine``'s single-pose kernels tens of percent slower (a few ms to tens of
  ms per call): a trade for a start-up shorter by many seconds (``benchmarks/bench_emitters.py``
  measures both).

They are applied only on a CPU backend, and each only if this jaxlib accepts it (the second is
experimental and may be renamed): the others still apply.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from softgrip_jax._concurrent import is_traced

#: Compile options for XLA:CPU (see the module docstring).
CPU_OPTIONS: dict[str, object] = {"xla_cpu_prefer_vector_width": 512, "xla_cpu_experimental_ynn_fusion_type": "",
                                  "xla_cpu_use_fusion_emitters": False}


@functools.cache
def compiler_options() -> dict[str, object]:
    """:data:`CPU_OPTIONS` on a CPU backend, those its XLA accepts; ``{}`` on any other backend."""
    if jax.default_backend() != "cpu":
        return {}
    if _accepted(CPU_OPTIONS):
        return dict(CPU_OPTIONS)
    return {name: value for name, value in CPU_OPTIONS.items() if _accepted({name: value})}


def _accepted(options: dict[str, object]) -> bool:
    try:
        jax.jit(lambda x: x + 1, compiler_options=options).lower(jnp.zeros(())).compile()
    except jax.errors.JaxRuntimeError:  # an option this XLA does not know
        return False
    return True


class tuned_jit:  # noqa: N801 - used as a decorator, like jax.jit
    """``jax.jit(fn, **jit_kwargs)`` compiled with :func:`compiler_options`.

    The backend is looked up at the first call, not at import. Attributes of the jitted function
    (``lower``, ``_cache_size``, ...) are those of ``jax.jit``'s. Inside another traced function
    (``jit``, ``grad``), where JAX refuses compile options on the inner function, it is an ordinary
    ``jax.jit``, inlined into the outer one whose compile options apply.
    """

    def __init__(self, fn, **jit_kwargs):
        functools.update_wrapper(self, fn)
        self._fn, self._jit_kwargs = fn, jit_kwargs
        self._tuned = self._plain = None

    def _get(self):
        if self._tuned is None:
            self._tuned = jax.jit(self._fn, compiler_options=compiler_options() or None, **self._jit_kwargs)
        return self._tuned

    def __call__(self, *args, **kwargs):
        if is_traced((args, kwargs)):  # inside another trace: not the tuned jit, which JAX would refuse
            return self._plain_jit()(*args, **kwargs)
        try:
            return self._get()(*args, **kwargs)
        except ValueError as err:  # "`compiler_options` can only be passed to top-level `jax.jit`"
            if "compiler_options" not in str(err):  # (a trace whose operands are all constants)
                raise
        return self._plain_jit()(*args, **kwargs)

    def _plain_jit(self):
        if self._plain is None:
            self._plain = jax.jit(self._fn, **self._jit_kwargs)
        return self._plain

    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(self._get(), name)
