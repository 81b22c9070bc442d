"""KeepStart: optimistix's BFGS unchanged, plus the objective's auxiliary output at the start and
at the returned point, checked on functions whose values are known by hand."""

import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from softgrip_jax._keep_start import KeepStart


def quadratic(y, _):
    value = jnp.sum((y - jnp.array([3.0, -1.0])) ** 2)
    return value, {"y": y, "f": value}


def rosenbrock(y, _):
    value = (1.0 - y[0]) ** 2 + 100.0 * (y[1] - y[0] ** 2) ** 2
    return value, {"y": y, "f": value}


def test_start_and_end_of_a_quadratic():
    y0 = jnp.array([0.0, 0.0])
    sol = optx.minimise(quadratic, KeepStart(optx.BFGS(rtol=1e-6, atol=1e-6)), y0, has_aux=True, max_steps=50)
    start, end = sol.state.start_aux, sol.state.inner.aux
    np.testing.assert_allclose(start["y"], [0.0, 0.0])
    assert float(start["f"]) == pytest.approx(10.0)  # 3**2 + 1**2
    np.testing.assert_allclose(sol.value, [3.0, -1.0], atol=1e-4)
    np.testing.assert_allclose(end["y"], sol.value)
    assert float(end["f"]) == pytest.approx(0.0, abs=1e-7)


@pytest.mark.parametrize("max_steps", [1, 2, 3, 7])
def test_end_aux_is_that_of_the_returned_point_when_stopped_early(max_steps):
    # Stopped mid-way, the returned point is the last accepted one; its aux must match it (optimistix's
    # own solution.aux lags one accepted step behind), and the start's aux is the objective at y0.
    y0 = jnp.array([-1.2, 1.0])
    sol = optx.minimise(rosenbrock, KeepStart(optx.BFGS(rtol=1e-8, atol=1e-8)), y0, has_aux=True,
                        max_steps=max_steps, throw=False)
    np.testing.assert_allclose(sol.state.start_aux["y"], y0)
    assert float(sol.state.start_aux["f"]) == pytest.approx(24.2, rel=1e-6)  # 2.2**2 + 100 * 0.44**2
    np.testing.assert_allclose(sol.state.inner.aux["y"], sol.value)
    assert float(sol.state.inner.aux["f"]) == pytest.approx(float(rosenbrock(sol.value, None)[0]), rel=1e-6)
    assert float(sol.state.inner.aux["f"]) <= float(sol.state.start_aux["f"])  # accepted steps never go up


def test_same_path_as_bfgs_alone():
    y0 = jnp.array([-1.2, 1.0])
    plain = optx.minimise(rosenbrock, optx.BFGS(rtol=1e-6, atol=1e-6), y0, has_aux=True, max_steps=200)
    kept = optx.minimise(rosenbrock, KeepStart(optx.BFGS(rtol=1e-6, atol=1e-6)), y0, has_aux=True, max_steps=200)
    np.testing.assert_array_equal(kept.value, plain.value)
    assert int(kept.stats["num_steps"]) == int(plain.stats["num_steps"])
    np.testing.assert_allclose(kept.value, [1.0, 1.0], atol=1e-3)
