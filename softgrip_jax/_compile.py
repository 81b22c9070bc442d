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

Options are chosen per program: an estimator may override them for the batch programs that run
it (``AbstractEstimator.cpu_options``). ``Geometric()`` and ``Mechanics()`` compile with the fusion
emitters: their batch programs run faster with them, for a longer first compile (both measured by
``benchmarks/bench_emitters.py``). ``Mechanics()`` also turns off XLA's intra-op threads
(``xla_cpu_multi_thread_eigen=False``): a CPU batch already runs one piece per core
(:mod:`softgrip_jax._concurrent`), and the solve's small kernels, split across the cores, waited on
each other more than they gained.

They are applied only on a CPU backend, and each only if this jaxlib accepts it (the second is
experimental and may be renamed): the others still apply.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp

from softgrip_jax._concurrent import is_traced

#: Compile options for XLA:CPU (see the module docstring).
CPU_OPTIONS: dict[str, object] = {"xla_cpu_prefer_vector_width": 512, "xla_cpu_experimental_ynn_fusion_type": "",
                                  "xla_cpu_use_fusion_emitters": False}


def compiler_options(estimator: object = None) -> dict[str, object]:
    """:data:`CPU_OPTIONS`, with the ``cpu_options`` overrides of ``estimator`` (if it has them),
    on a CPU backend: those its XLA accepts; ``{}`` on any other backend. With JAX's
    ``jax_disable_most_optimizations`` (fast compiles of slow programs, as the fast test set runs)
    the overrides are left out: the fusion emitters that ``Geometric()`` chooses run faster but
    compile slower."""
    overrides = getattr(estimator, "cpu_options", None) or {}
    if jax.config.read("jax_disable_most_optimizations"):  # compile fast, run slow: no option that trades the other way
        overrides = {}
    return dict(_accepted_options(tuple(sorted({**CPU_OPTIONS, **overrides}.items()))))


@functools.cache
def _accepted_options(items: tuple[tuple[str, object], ...]) -> tuple[tuple[str, object], ...]:
    if jax.default_backend() != "cpu":
        return ()
    if _accepted(dict(items)):
        return items
    return tuple((name, value) for name, value in items if _accepted({name: value}))


def _accepted(options: dict[str, object]) -> bool:
    try:
        jax.jit(lambda x: x + 1, compiler_options=options).lower(jnp.zeros(())).compile()
    except jax.errors.JaxRuntimeError:  # an option this XLA does not know
        return False
    return True


class tuned_jit:  # noqa: N801 - used as a decorator, like jax.jit
    """``jax.jit(fn, **jit_kwargs)`` compiled with :func:`compiler_options` of the call's
    ``estimator=`` keyword argument (if any).

    The backend is looked up at the first call, not at import. Attributes of the jitted function
    (``lower``, ``_cache_size``, ...) are those of ``jax.jit``'s. Inside another traced function
    (``jit``, ``grad``), where JAX refuses compile options on the inner function, it is an ordinary
    ``jax.jit``, inlined into the outer one whose compile options apply.
    """

    def __init__(self, fn, **jit_kwargs):
        functools.update_wrapper(self, fn)
        self._fn, self._jit_kwargs = fn, jit_kwargs
        self._tuned: dict[tuple, Any] = {}  # one jax.jit per set of compile options
        self._plain = None

    def _get(self, estimator: object = None):
        options = compiler_options(estimator)
        key = tuple(sorted(options.items()))
        if key not in self._tuned:
            self._tuned[key] = jax.jit(self._fn, compiler_options=options or None, **self._jit_kwargs)
        return self._tuned[key]

    def __call__(self, *args, **kwargs):
        if is_traced((args, kwargs)):  # inside another trace: not the tuned jit, which JAX would refuse
            return self._plain_jit()(*args, **kwargs)
        try:
            return self._get(kwargs.get("estimator"))(*args, **kwargs)
        except ValueError as err:  # "`compiler_options` can only be passed to top-level `jax.jit`"
            if "compiler_options" not in str(err):  # (a trace whose operands are all constants)
                raise
        return self._plain_jit()(*args, **kwargs)

    def _plain_jit(self):
        if self._plain is None:
            self._plain = jax.jit(self._fn, **self._jit_kwargs)
        return self._plain

    def _cache_size(self) -> int:
        """Programs compiled, over every set of compile options (``jax.jit``'s count, summed)."""
        return sum(jitted._cache_size() for jitted in self._tuned.values())

    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(self._get(), name)
