"""Operations whose reverse-mode derivative stays finite at their singular points.

The "double where" pattern (as in jaxlie): the unsafe branch is fed a harmless value, so the
discarded branch cannot inject NaN into the cotangent.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


def safe_norm(v: Float[Array, "*batch d"]) -> Float[Array, "*batch"]:
    """Euclidean norm over the last axis, with gradient 0 (not NaN) at the zero vector."""
    sq = jnp.sum(v * v, axis=-1)
    nonzero = sq > 0
    return jnp.where(nonzero, jnp.sqrt(jnp.where(nonzero, sq, 1.0)), 0.0)


def safe_divide(num: Array, den: Array, fallback: Array | float = 0.0, eps: float = 1e-12) -> Array:
    """``num / den``, or ``fallback`` where ``|den| <= eps``."""
    ok = jnp.abs(den) > eps
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), fallback)


def direction_angle(v: Float[Array, "*batch 2"]) -> Float[Array, "*batch"]:
    """Angle of a vector from the downward vertical, positive toward +x; 0 for the zero vector."""
    nonzero = jnp.sum(v * v, axis=-1) > 0
    x = jnp.where(nonzero, v[..., 0], 0.0)
    y = jnp.where(nonzero, v[..., 1], 1.0)
    return jnp.where(nonzero, jnp.arctan2(x, y), 0.0)


def unit_direction(angle: Float[Array, "*batch"]) -> Float[Array, "*batch 2"]:
    """The unit vector at ``angle`` from the downward vertical: ``(sin a, cos a)`` (y points down)."""
    return jnp.stack([jnp.sin(angle), jnp.cos(angle)], axis=-1)


def tied_min(x: Float[Array, " n"], rtol: float = 1e-5, atol: float = 1e-6) -> Float[Array, ""]:
    """``min(x)`` over a 1-D array, whose derivative is the mean of the derivatives of every entry
    within rounding (``atol + rtol |min|``) of the minimum.

    JAX averages the derivatives of entries that tie exactly; entries that tie by symmetry (the
    mirror images of a symmetric grasp) differ in their last bits, and ``jnp.min`` then takes one
    side's derivative alone: at a symmetric pose the derivative of a symmetric function came out
    nonzero. The value is ``jnp.min(x)`` exactly; infinite entries take no part in the derivative.
    """
    low = jnp.min(x)
    near = (x <= low + atol + rtol * jnp.abs(low)) & jnp.isfinite(x)
    weight = near / jnp.maximum(jnp.sum(near), 1)
    spread = jnp.where(near, x - jax.lax.stop_gradient(x), 0.0)  # value 0, derivative that of x
    return jax.lax.stop_gradient(low) + jnp.sum(jax.lax.stop_gradient(weight) * spread)


def tied_max(x: Float[Array, " n"], rtol: float = 1e-5, atol: float = 1e-6) -> Float[Array, ""]:
    """``max(x)`` over a 1-D array, with the derivative of :func:`tied_min` (near ties averaged)."""
    return -tied_min(-x, rtol, atol)
