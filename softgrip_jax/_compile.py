"""How the batch functions are compiled: ``jax.jit`` with XLA:CPU options where they apply.

Two XLA:CPU compile options make the estimate faster (the figures are in benchmarks/RESULTS.md,
issue 2), with results equal to within float rounding (joints within 3e-4 mm, the same cases):

* ``xla_cpu_prefer_vector_width=512``: LLVM may use 512-bit vectors where the CPU has them (a
  preference: on a CPU without AVX-512 the code is the same as without it);
* ``xla_cpu_experimental_ynn_fusion_type=""``: no YNNPACK fusions. XLA:CPU hands the estimate's
  many short reductions (over 5, 12 or 21 stations per candidate) to YNNPACK, which is slower on
  them than XLA's own loops.

They are applied only on a CPU backend, and only if this jaxlib accepts them (the second is
experimental and may be renamed): otherwise the functions compile with XLA's defaults.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from softgrip_jax._concurrent import is_traced

#: Compile options for XLA:CPU (see the module docstring).
CPU_OPTIONS: dict[str, object] = {"xla_cpu_prefer_vector_width": 512, "xla_cpu_experimental_ynn_fusion_type": ""}


@functools.cache
def compiler_options() -> dict[str, object]:
    """:data:`CPU_OPTIONS` on a CPU backend whose XLA accepts them; ``{}`` otherwise."""
    if jax.default_backend() != "cpu":
        return {}
    try:
        jax.jit(lambda x: x + 1, compiler_options=CPU_OPTIONS).lower(jnp.zeros(())).compile()
    except jax.errors.JaxRuntimeError:  # an option this XLA does not know
        return {}
    return dict(CPU_OPTIONS)


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
