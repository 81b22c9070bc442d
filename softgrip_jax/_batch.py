"""Many candidates at once, in chunks so that memory stays bounded for any batch size."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jaxtyping import ArrayLike, Float

from softgrip_jax._contact import ContactConfig
from softgrip_jax._deformation import Estimate, estimate
from softgrip_jax._grasp import GraspEstimate, estimate_grasp
from softgrip_jax._model import FingerModel, Gripper
from softgrip_jax._sdf import AbstractSDF

#: Candidates evaluated together inside one chunk; peak memory scales with this, not the batch.
DEFAULT_CHUNK = 2048


@partial(jax.jit, static_argnames=("chunk_size",))
def _estimate_batch(finger, sdf, bases, config, chunk_size):
    return jax.lax.map(lambda b: estimate(finger, sdf, b, config), bases, batch_size=chunk_size)


@partial(jax.jit, static_argnames=("chunk_size",))
def _estimate_grasp_batch(gripper, sdf, poses, config, chunk_size):
    return jax.lax.map(lambda p: estimate_grasp(gripper, sdf, p, config), poses, batch_size=chunk_size)


def estimate_batch(
    finger: FingerModel,
    sdf: AbstractSDF,
    bases: Float[ArrayLike, "b 2"],
    config: ContactConfig = ContactConfig(),
    *,
    chunk_size: int = DEFAULT_CHUNK,
) -> Estimate:
    """:func:`estimate` for B finger bases (mm), compiled once per shape, ``chunk_size`` at a time.

    Returns an :class:`Estimate` whose every leaf has a leading axis of length B. A bad base
    (NaN, outside the SDF grid) comes back ``valid=False`` and does not affect the others.
    """
    bases = jnp.asarray(bases, finger.length.dtype)
    return _estimate_batch(finger, sdf, bases, config, min(chunk_size, max(1, bases.shape[0])))


def estimate_grasp_batch(
    gripper: Gripper,
    sdf: AbstractSDF,
    poses: Float[ArrayLike, "b 3"],
    config: ContactConfig = ContactConfig(),
    *,
    chunk_size: int = DEFAULT_CHUNK,
) -> GraspEstimate:
    """:func:`estimate_grasp` for B poses (x mm, y mm, angle rad), ``chunk_size`` at a time."""
    poses = jnp.asarray(poses, gripper.base_separation.dtype)
    return _estimate_grasp_batch(gripper, sdf, poses, config, min(chunk_size, max(1, poses.shape[0])))
