"""``SoftgripError`` lives in :mod:`softgrip_base.errors`, below the JAX core; this import path
keeps working and names the same class."""

from softgrip_base.errors import SoftgripError

__all__ = ["SoftgripError", "check_number_fields"]


def check_number_fields(module, ranges: dict[str, tuple[float, float]]) -> None:
    """Each field ``name`` of ``module`` (an equinox module's run-time settings) is a scalar number in
    ``ranges[name]`` = (low, high), both included; a :class:`SoftgripError` naming the class and the
    field otherwise. Traced values (under ``jit``) cannot be seen and are not checked."""
    import jax
    import numpy as np

    for name, (low, high) in ranges.items():
        value = getattr(module, name)
        if isinstance(value, jax.core.Tracer):
            continue
        ok = not isinstance(value, bool) and np.ndim(value) == 0
        try:
            ok = ok and low <= float(value) <= high
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise SoftgripError(f"{type(module).__name__}.{name} must be a number in [{low:g}, {high:g}], "
                                f"got {value!r}")
