"""Objects with a smooth boundary, for tests and benchmarks of the mechanics estimate.

A polygon's exact distance (``PolygonSDF``) has flat facets: a frictionless fingertip pressed on
one rests only where the facets' rounded joins (radius r, after dilation by the finger's
half-thickness) face its force, and crosses each flat facet in one jump as the base moves. Those
jumps are the polygon's, not the solver's; :class:`DiscSDF` has none.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from softgrip_jax import AbstractSDF


class DiscSDF(AbstractSDF):
    """Exact signed distance (mm) to a disc of ``radius`` (mm) about ``centre`` (2,) mm."""

    centre: Float[Array, "2"]
    radius: Float[Array, ""]

    def __init__(self, centre, radius):
        self.centre = jnp.asarray(centre, jnp.float32)
        self.radius = jnp.asarray(radius, jnp.float32)

    def distance(self, points: Float[Array, "*batch 2"]) -> Float[Array, "*batch"]:
        offset = points - self.centre
        # the floor keeps the gradient finite at the centre
        return jnp.sqrt(jnp.sum(offset * offset, axis=-1) + 1e-12) - self.radius

    def mass_properties(self):
        """The disc's centre and radius (mm)."""
        return self.centre, self.radius


__all__ = ["DiscSDF"]
