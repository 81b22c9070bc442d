"""Both fingers of a gripper at a pose.

A pose is ``(x, y, angle)``: the point midway between the two finger bases in image-plane mm and
the gripper's in-plane rotation in rad (0: fingers hang toward +y). The left finger's base is W/2
toward the gripper's -x, the right finger's W/2 toward +x; the right finger is the left
computation on the mirrored scene (its frame has handedness -1), never a second code path.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from softgrip_jax._checks import check_gripper, check_sdf
from softgrip_jax._contact import ContactConfig
from softgrip_jax._estimate import estimate_in_frame
from softgrip_jax._estimators import AbstractEstimator, as_estimator
from softgrip_jax._frames import FingerFrame, across_direction
from softgrip_jax._model import Gripper
from softgrip_jax._sdf import AbstractSDF
from softgrip_jax._stage import Estimate


class GraspEstimate(eqx.Module):
    """Estimates of both fingers at one pose; ``valid`` when both are."""

    left: Estimate
    right: Estimate
    valid: Bool[Array, ""]


def finger_frames(gripper: Gripper, pose: Float[ArrayLike, "3"]) -> tuple[FingerFrame, FingerFrame]:
    """The (left, right) finger frames of ``gripper`` at ``pose`` = (x mm, y mm, angle rad): the
    bases W/2 either side of the centre across the gripper's axis, the right one mirrored.

    Example:
        >>> import jax.numpy as jnp
        >>> from softgrip_jax import FingerModel, Gripper
        >>> f = FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=10)
        >>> left, right = finger_frames(Gripper(f, f, 40.0), jnp.array([0.0, 5.0, 0.0]))
        >>> left.origin.tolist(), right.origin.tolist(), float(right.handedness)
        ([-20.0, 5.0], [20.0, 5.0], -1.0)
    """
    check_gripper(gripper)
    dtype = gripper.base_separation.dtype
    pose = jnp.asarray(pose, dtype)
    center, angle = pose[:2], pose[2]
    half = 0.5 * gripper.base_separation * across_direction(angle)
    one = jnp.ones((), dtype)
    return (
        FingerFrame(origin=center - half, angle=angle, handedness=one),
        FingerFrame(origin=center + half, angle=angle, handedness=-one),
    )


def estimate_grasp(
    gripper: Gripper,
    sdf: AbstractSDF,
    pose: Float[ArrayLike, "3"],
    config: ContactConfig = ContactConfig(),
    *,
    estimator: AbstractEstimator | None = None,
) -> GraspEstimate:
    """Estimate both fingers of ``gripper`` at ``pose`` = (x mm, y mm, angle rad) against ``sdf``.

    ``estimator``: ``Mechanics(config)`` (None: the default, ``Mechanics()``; the spring chain at
    equilibrium) or ``Geometric()`` (the paper's eq. 9), as for :func:`estimate_in_frame`.

    Example:
        >>> import jax.numpy as jnp
        >>> from softgrip_jax import FingerModel, Gripper, PolygonSDF
        >>> f = FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=10)
        >>> g = Gripper(left=f, right=f, base_separation=50.0)
        >>> disc = PolygonSDF.regular((0.0, 35.0), 9.0)
        >>> import jax
        >>> from softgrip_jax import Geometric
        >>> run = jax.jit(estimate_grasp)  # compiles once per estimator; op by op is slower
        >>> est = run(g, disc, jnp.array([0.0, 0.0, 0.0]), estimator=Geometric())
        >>> [e.case_name for e in (est.left, est.right)]
        ['other', 'other']
        >>> est = run(g, disc, jnp.array([0.0, 0.0, 0.0]))  # the default: mechanics
        >>> [e.case_name for e in (est.left, est.right)]
        ['tip', 'tip']
    """
    check_gripper(gripper)
    check_sdf(sdf)
    estimator = as_estimator(estimator)
    left_frame, right_frame = finger_frames(gripper, pose)
    left, right = per_finger(lambda finger, frame: estimate_in_frame(finger, sdf, frame, config, estimator=estimator),
                             gripper, (left_frame, right_frame))
    return GraspEstimate(left=left, right=right, valid=left.valid & right.valid)


def per_finger(fn, gripper: Gripper, *pairs, in_turn: bool = False):
    """``(fn(gripper.left, *lefts), fn(gripper.right, *rights))`` for ``pairs`` of (left, right)
    arguments (pytrees of arrays).

    Fingers of one structure (the same N) go through one traced copy of ``fn``, vmapped over the
    pair (``in_turn``: looped over it): half the program of two copies, so less tracing and
    compiling for everything built on it. Fingers of different N take two copies. A batch's
    ``fn`` loops (``in_turn``): under ``vmap`` the finger's parameters would be batched, and its
    skips of the work no candidate needs (``lax.cond`` on a now batched predicate) would run both
    branches.
    """
    lefts, rights = (tuple(p[i] for p in pairs) for i in (0, 1))
    if gripper.left.n_links != gripper.right.n_links:  # (the only static field of a finger)
        return fn(gripper.left, *lefts), fn(gripper.right, *rights)
    stacked = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), (gripper.left, lefts), (gripper.right, rights))
    if in_turn:
        both = jax.lax.map(lambda pair: fn(pair[0], *pair[1]), stacked)
    else:
        both = jax.vmap(lambda finger, args: fn(finger, *args))(*stacked)
    return tuple(jax.tree_util.tree_map(lambda x, i=i: x[i], both) for i in (0, 1))
