"""Argument types shared by the commands."""

import argparse


def positive_int(text: str) -> int:
    """An argparse type: a whole number >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def __getattr__(name: str):
    """``DEFAULT_METHOD``: the estimate the commands use when neither ``--method`` nor the profile
    (``fit.estimate_method``, the estimate it was fitted through) says which, the core's default set
    in one place; ``METHOD_CHOICES``: the choices of ``--method``. Read from the core on first use,
    so that a command without ``--method`` (capture) does not import JAX."""
    if name in ("DEFAULT_METHOD", "METHOD_CHOICES"):
        import softgrip_jax

        return softgrip_jax.DEFAULT_METHOD if name == "DEFAULT_METHOD" else softgrip_jax.METHODS
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def add_method_argument(parser: argparse.ArgumentParser, from_profile: bool = True,
                        profile_text: str = "the profile") -> None:
    """Add ``--method geometric|mechanics`` (default None: decided by :func:`resolve_estimator`).
    ``from_profile``: the command reads a profile (``profile_text`` in the help) whose recorded
    estimate is the default."""
    from softgrip_jax import DEFAULT_METHOD, METHODS as METHOD_CHOICES

    default = (f"the estimate {profile_text} was fitted with (its fit.estimate_method), else {DEFAULT_METHOD}"
               if from_profile else DEFAULT_METHOD)
    parser.add_argument("--method", choices=METHOD_CHOICES, default=None,
                        help="the deformation estimate: geometric (the paper's eq. 9) or mechanics (the "
                             f"spring-joint chain at equilibrium); default: {default}")


def resolve_method(method: str | None, profile=None) -> str:
    """``--method`` if given, else the estimate ``profile`` was fitted through, else DEFAULT_METHOD."""
    if method is not None:
        return method
    from softgrip_jax import DEFAULT_METHOD

    recorded = getattr(getattr(profile, "fit", None), "estimate_method", None)
    return recorded or DEFAULT_METHOD


def resolve_estimator(method: str | None, profile=None):
    """The estimator object every command uses (a ``softgrip_jax.AbstractEstimator``): the one named by
    ``--method``, else by the estimate ``profile`` was fitted through, else the default
    (:func:`resolve_method`). The one place where a command turns a name into an estimator; its
    ``name`` is what the JSON documents and profiles record."""
    from softgrip_jax import as_estimator

    return as_estimator(method=resolve_method(method, profile))
