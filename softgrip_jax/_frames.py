"""Finger frames: where a finger hangs in the image plane.

The core computes one finger that hangs straight down (+y) from its base and curls toward +x.
A finger at another place, a rotated gripper, or a right finger (which curls toward -x) is the same
computation on the scene expressed in the finger's own frame; the right finger's frame is mirrored
about the gripper's centre line. Distances are unchanged by these rigid motions
and reflections, so the object's SDF read through ``frame.to_world`` is again a signed distance.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from softgrip_jax._safe import unit_direction


def across_direction(angle: Float[Array, "*batch"]) -> Float[Array, "*batch 2"]:
    """The unit vector across a gripper at ``angle`` (rad from the downward vertical): "down",
    ``(sin a, cos a)``, turned by +90 degrees, ``(cos a, -sin a)``. A left finger closes along it, and
    the finger bases sit either side of the gripper's centre along it."""
    down = unit_direction(angle)
    return jnp.stack([down[..., 1], -down[..., 0]], axis=-1)


class FingerFrame(eqx.Module):
    """A finger's frame in the image plane.

    Attributes:
        origin: (2,) the finger base in mm (image-plane coordinates).
        angle: gripper rotation in rad: the finger's "down" is the direction at this angle from the
            image's downward vertical, positive toward +x.
        handedness: +1 for a finger curling toward its frame's +x (left finger), -1 for its
            mirror image (right finger).
    """

    origin: Float[Array, "2"]
    angle: Float[Array, ""]
    handedness: Float[Array, ""]

    @classmethod
    def hanging_from(cls, base: Float[Array, "2"]) -> "FingerFrame":
        """The frame of a left finger hanging straight down from ``base`` (mm): no gripper rotation."""
        return cls(origin=base, angle=jnp.zeros((), base.dtype), handedness=jnp.ones((), base.dtype))

    def _axes(self):
        return self.handedness * across_direction(self.angle), unit_direction(self.angle)

    def to_world(self, q: Float[Array, "*batch 2"]) -> Float[Array, "*batch 2"]:
        """Finger-frame points (mm) to image-plane points (mm)."""
        ex, ey = self._axes()
        x = ex[0] * q[..., 0] + ey[0] * q[..., 1] + self.origin[0]
        y = ex[1] * q[..., 0] + ey[1] * q[..., 1] + self.origin[1]
        # The barrier makes XLA compute the points once. Without it XLA:CPU fuses this sum into
        # each of the SDF lookup's four gathers and recomputes it (and whatever produced ``q``)
        # there; written as a matrix product instead, it becomes a batched dot of 2x3 matrices,
        # which XLA:CPU runs slower than this over the whole estimate (benchmarks/RESULTS.md).
        return jax.lax.optimization_barrier(jnp.stack([x, y], axis=-1))

    def to_local(self, p: Float[Array, "*batch 2"]) -> Float[Array, "*batch 2"]:
        """Image-plane points (mm) to finger-frame points (mm)."""
        ex, ey = self._axes()
        d = p - self.origin
        return jnp.stack([d @ ex, d @ ey], axis=-1)
