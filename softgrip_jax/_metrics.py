"""Evaluation against observed shapes (paper section V-A)."""

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from softgrip_jax._safe import safe_norm


def joint_errors(
    estimated: Float[ArrayLike, "*batch joints 2"], observed: Float[ArrayLike, "*batch joints 2"]
) -> Float[Array, "*batch joints"]:
    """Eq. 10: distance epsilon_i (mm) between estimated and observed joint i, for every joint.

    Example:
        >>> import jax.numpy as jnp
        >>> joint_errors(jnp.array([[0.0, 0.0], [3.0, 4.0]]), jnp.zeros((2, 2))).tolist()
        [0.0, 5.0]
    """
    estimated, observed = jnp.asarray(estimated), jnp.asarray(observed)
    if estimated.shape != observed.shape:
        from softgrip_base.errors import SoftgripError

        raise SoftgripError(
            f"joint_errors: estimated joints {estimated.shape} and observed joints {observed.shape} "
            "must have the same shape (N+1 joints of 2 coordinates)"
        )
    return safe_norm(estimated - observed)
