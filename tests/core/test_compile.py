"""The batch functions' compile options (softgrip_jax._compile)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softgrip_jax import _compile
from softgrip_jax._compile import CPU_OPTIONS, compiler_options, tuned_jit


@pytest.fixture
def fresh_options():
    _compile._accepted_options.cache_clear()
    yield
    _compile._accepted_options.cache_clear()


def test_this_xla_accepts_the_cpu_options(fresh_options):
    # With the pinned jax on a CPU, the options are in use; a jaxlib that renamed one would
    # silently lose the speed-up, which this test reports.
    assert jax.default_backend() == "cpu"
    assert compiler_options() == CPU_OPTIONS


def test_an_option_xla_does_not_know_is_left_out_and_the_others_kept(fresh_options, monkeypatch):
    monkeypatch.setattr(_compile, "CPU_OPTIONS", {"xla_cpu_no_such_option_anywhere": 1})
    assert compiler_options() == {}
    _compile._accepted_options.cache_clear()
    known = {"xla_cpu_use_fusion_emitters": False}
    monkeypatch.setattr(_compile, "CPU_OPTIONS", {"xla_cpu_no_such_option_anywhere": 1, **known})
    assert compiler_options() == known


@pytest.fixture(params=[False, True], ids=["optimised", "most optimisations off"])
def optimisations_off(request):
    before = jax.config.read("jax_disable_most_optimizations")
    jax.config.update("jax_disable_most_optimizations", request.param)
    yield request.param
    jax.config.update("jax_disable_most_optimizations", before)


def test_an_estimator_overrides_the_options_of_its_programs_only(fresh_options, optimisations_off):
    from softgrip_jax import Geometric, Mechanics

    # Without XLA's optimisations (fast compiles), no override that compiles slower to run faster.
    fusion = {} if optimisations_off else {"xla_cpu_use_fusion_emitters": True}
    one_thread = {} if optimisations_off else {"xla_cpu_multi_thread_eigen": False}
    assert compiler_options(Geometric()) == {**CPU_OPTIONS, **fusion}
    assert compiler_options(Mechanics()) == {**CPU_OPTIONS, **fusion, **one_thread}
    assert compiler_options() == CPU_OPTIONS


def test_tuned_jit_computes_what_jit_does_and_compiles_once_per_shape():
    def f(x, n):
        return jnp.cumsum(jnp.sin(x) ** n) / (1.0 + jnp.arange(x.shape[0]))

    tuned = tuned_jit(f, static_argnames="n")
    x = jnp.linspace(0.0, 3.0, 37)
    np.testing.assert_allclose(tuned(x, n=2), jax.jit(f, static_argnames="n")(x, n=2), rtol=1e-6)
    before = tuned._cache_size()
    tuned(x + 1.0, n=2)
    assert tuned._cache_size() == before  # same shapes: no recompilation
    assert tuned.__name__ == "f"
    # Inlined inside another trace (where JAX refuses inner compile options), and differentiable.
    np.testing.assert_allclose(jax.jit(lambda y: tuned(y, n=2))(x), tuned(x, n=2), rtol=1e-6)
    grad = jax.grad(lambda y: jnp.sum(tuned(y, n=3)))(x)
    expected = jax.grad(lambda y: jnp.sum(f(y, n=3)))(x)
    np.testing.assert_allclose(grad, expected, rtol=1e-5, atol=1e-6)
