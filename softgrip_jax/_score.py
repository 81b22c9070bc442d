"""Scoring and refining pre-touch gripper poses (the paper's future work).

A candidate is a gripper pose (x mm, y mm, angle rad). Its score combines what a planner needs to
rank pre-touch poses from both fingers' estimates:

* ``touch``: each finger closes onto the object before its closure ends (1), grazes it at the very
  end (ramps to 0), or misses it (0);
* ``wrap``: the fraction of each estimated finger that lies along the object surface (centreline
  within ``contact_band`` mm of the object plus r);
* ``opposition``: -n_left . n_right for the outward object normals at the two first contacts:
  1 when the fingers squeeze from opposite sides, 0 when either finger misses;
* ``tip_only``: a finger landing with its tip only (case b) on an edge, which a planner avoids;
* ``penetration_mm``: how deep the estimated finger (centreline + r) lies inside the object. The
  paper's wrapping cases press a soft finger's skin into the object by a millimetre or so; an
  estimate deeper than ``max_penetration`` times r is flagged ``penetrating`` and ranks last.

score = w_touch mean(touch) + w_wrap mean(wrap) + w_opposition opposition
        - w_tip_only mean(tip_only) - w_penetration mean(penetration_mm).

Every term is a continuous function of the estimate, so the score can be differentiated in the pose
and refined by an optimistix minimiser.
"""

from __future__ import annotations

import enum
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from softgrip_jax._batch import as_candidates, grasp_chunk, map_chunks, run_batch
from softgrip_jax._compile import tuned_jit
from softgrip_jax._contact import ContactCase, ContactConfig
from softgrip_jax._export import exportable
from softgrip_jax._grasp import GraspEstimate, estimate_grasp
from softgrip_jax._kinematics import chain_stations
from softgrip_jax._estimators import AbstractEstimator, as_estimator
from softgrip_jax._mechanics import MechanicsConfig
from softgrip_jax._model import FingerModel, Gripper
from softgrip_jax._safe import safe_divide
from softgrip_jax._sdf import AbstractSDF
from softgrip_jax._stage import Estimate, Status


class ScoreWeights(eqx.Module):
    """Weights and thresholds of the score (all static; mm where a length)."""

    touch: float = eqx.field(static=True, default=1.0)
    wrap: float = eqx.field(static=True, default=2.0)
    opposition: float = eqx.field(static=True, default=1.0)
    tip_only: float = eqx.field(static=True, default=1.5)
    penetration: float = eqx.field(static=True, default=1.0)  #: per mm
    contact_band: float = eqx.field(static=True, default=1.0)  #: mm beyond r that counts as "along"
    max_penetration: float = eqx.field(static=True, default=0.5)  #: fraction of r; deeper is flagged


class ScoreComponents(eqx.Module):
    """The terms of the score; per-finger arrays are (left, right)."""

    touch: Float[Array, "2"]
    wrap: Float[Array, "2"]
    opposition: Float[Array, ""]
    tip_only: Float[Array, "2"]
    penetration_mm: Float[Array, "2"]


class Score(eqx.Module):
    """A scored candidate: ``score`` is -inf unless ``valid`` (estimates usable, no flag)."""

    score: Float[Array, ""]
    components: ScoreComponents
    grasp: GraspEstimate
    penetrating: Bool[Array, ""]
    valid: Bool[Array, ""]
    status: Int[Array, ""]  #: the first failing finger's :class:`Status`, 0 if both are OK


def _finger_terms(finger: FingerModel, sdf: AbstractSDF, est: Estimate, weights: ScoreWeights, config):
    theta = finger.theta_entire
    touches = est.case != ContactCase.NONE
    # Closing onto the object counts fully when it happens before the last tenth of the closure.
    touch = jnp.where(touches, jnp.clip(safe_divide(theta - est.contact.s1, 0.1 * theta, 1.0), 0.0, 1.0), 0.0)
    joints = jnp.where(est.valid, est.joints, 0.0)
    stations, _ = chain_stations(joints, finger.length, config.per_link(finger.n_links))
    gap = sdf.distance(stations) - finger.half_thickness
    wrap = jnp.mean(jax.nn.sigmoid((weights.contact_band - gap) / (0.25 * weights.contact_band)))
    tip = jax.nn.sigmoid((est.contact.n_g1 - (finger.n_links - config.tip_tolerance)) / 0.1) * touch
    penetration = jnp.maximum(-jnp.min(gap), 0.0)
    # The outward normal at the contact, taken r off the surface at P_g1, where it is well defined
    # (exactly on a polygon's boundary the direction to the nearest point is rounding noise).
    normal = sdf.normal(jnp.where(est.valid, est.contact.p_g1, 0.0))
    return touch, wrap, tip, penetration, normal


def score_pose(
    gripper: Gripper,
    sdf: AbstractSDF,
    pose: Float[ArrayLike, "3"],
    weights: ScoreWeights = ScoreWeights(),
    config: ContactConfig = ContactConfig(),
    *,
    estimator: AbstractEstimator | None = None,
    method: str | None = None,
    mechanics: MechanicsConfig | None = None,
) -> Score:
    """Score one pose (x mm, y mm, angle rad). Pure; jit-, vmap- and grad-compatible.

    ``estimator`` chooses the fingers' deformation estimate, ``Mechanics(config)`` (None: the
    default, ``Mechanics()``) or ``Geometric()``, as for :func:`estimate_grasp` (or the older
    ``method=``, static under ``jit``, and ``mechanics=``).

    Example:
        >>> import jax.numpy as jnp
        >>> from softgrip_jax import FingerModel, Geometric, Gripper, PolygonSDF
        >>> f = FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=10)
        >>> g = Gripper(left=f, right=f, base_separation=56.0)
        >>> disc = PolygonSDF.regular((0.0, 38.0), 15.0, 128)
        >>> import jax
        >>> run = jax.jit(score_pose)  # compiles once per estimator; op by op is slower
        >>> centred = run(g, disc, jnp.array([0.0, 0.0, 0.0]), estimator=Geometric())
        >>> missing = run(g, disc, jnp.array([0.0, -60.0, 0.0]), estimator=Geometric())
        >>> bool(centred.score > missing.score)
        True
    """
    estimator = as_estimator(estimator, method, mechanics)
    grasp = estimate_grasp(gripper, sdf, pose, config, estimator=estimator)
    return _score_grasp(gripper, sdf, grasp, weights, config)


def _score_grasp(gripper: Gripper, sdf: AbstractSDF, grasp: GraspEstimate, weights: ScoreWeights, config) -> Score:
    """The :class:`Score` of both fingers' estimates at one pose."""
    left = _finger_terms(gripper.left, sdf, grasp.left, weights, config)
    right = _finger_terms(gripper.right, sdf, grasp.right, weights, config)
    touch, wrap, tip, penetration = (jnp.stack([a, b]) for a, b in zip(left[:4], right[:4]))
    opposition = -jnp.dot(left[4], right[4]) * touch[0] * touch[1]
    raw = (weights.touch * jnp.mean(touch) + weights.wrap * jnp.mean(wrap) + weights.opposition * opposition
           - weights.tip_only * jnp.mean(tip) - weights.penetration * jnp.mean(penetration))
    r = jnp.stack([gripper.left.half_thickness, gripper.right.half_thickness])
    penetrating = jnp.any(penetration > weights.max_penetration * r)
    sound = jnp.isfinite(raw)  # e.g. a NaN the SDF returns near the fingers: never a valid NaN score
    valid = grasp.valid & ~penetrating & sound
    status = jnp.where(grasp.left.status != 0, grasp.left.status, grasp.right.status)
    status = jnp.where((status == 0) & ~sound, Status.NON_FINITE_RESULT, status).astype(status.dtype)
    return Score(
        score=jnp.where(valid, raw, -jnp.inf),
        components=ScoreComponents(touch=touch, wrap=wrap, opposition=opposition, tip_only=tip,
                                   penetration_mm=penetration),
        grasp=grasp, penetrating=penetrating, valid=valid, status=status,
    )


def _score_share(gripper, sdf, poses, weights, config, chunk_size, estimator):
    """The :class:`Score` of poses (P, 3) on one device, ``chunk_size`` at a time: in each chunk both
    fingers' estimates (the contact refined and the equilibrium solved only where a finger touches,
    :mod:`softgrip_jax._batch`), then the score of each pose."""
    def chunk(share):
        grasps = grasp_chunk(gripper, sdf, share, config, estimator)
        return jax.vmap(lambda g: _score_grasp(gripper, sdf, g, weights, config))(grasps)

    return map_chunks(chunk, poses, chunk_size)


_score_one_device = exportable(tuned_jit(_score_share, static_argnames=("chunk_size", "estimator")),
                               ("chunk_size", "estimator"))


@partial(tuned_jit, static_argnames=("chunk_size", "estimator"))
def _score_sharded(gripper, sdf, poses, weights, config, chunk_size, estimator):
    # poses: (devices, per_device, 3); the device axis is vmapped (and sharded across the devices).
    return jax.vmap(lambda share: _score_share(gripper, sdf, share, weights, config, chunk_size, estimator))(poses)


def score(
    gripper: Gripper,
    sdf: AbstractSDF,
    poses: Float[ArrayLike, "b 3"],
    weights: ScoreWeights = ScoreWeights(),
    config: ContactConfig = ContactConfig(),
    *,
    chunk_size: int = 2048,
    estimator: AbstractEstimator | None = None,
    method: str | None = None,
    mechanics: MechanicsConfig | None = None,
    workers: int | None = None,
) -> Score:
    """Score B candidate poses (x mm, y mm, angle rad) in one compiled call.

    Poses are evaluated ``chunk_size`` at a time (memory does not grow with B). When several JAX
    devices are present (GPUs, or hosts joined by ``jax.distributed``), the batch is split evenly
    across them with ``jax.sharding``; results are identical to a single device's. Returns a
    :class:`Score` whose leaves have a leading axis B; rank with ``jnp.argsort(-result.score)``.
    ``estimator`` (or the older ``method`` / ``mechanics``) chooses the deformation estimate, as for
    :func:`score_pose`; with ``Mechanics()`` (the default) the equilibrium is solved only for
    fingers that touch.

    Args:
        gripper: both fingers and the base separation W (mm, rad).
        sdf: the object (mm), in the frame's millimetre coordinates (x right, y down).
        poses: (B, 3) candidate poses: gripper centre x, y (mm) and angle (rad).
        chunk_size: poses evaluated together (static); memory grows with it, not with B.
        estimator: ``Geometric()`` or ``Mechanics(config)`` (None: ``Mechanics()``); equal
            estimators reuse one compiled program.
        workers: on one device, concurrent parts the batch is split into (None: one per CPU core
            on a CPU, one elsewhere), as for :func:`estimate_batch`; results do not depend on it.

    Returns:
        :class:`Score` with leading axis B: ``score`` (B,) (-inf where not valid), ``components``,
        ``grasp`` (both fingers' :class:`Estimate`, joints (B, N+1, 2) mm), ``valid``, ``status``.

    Example (the README's planner: score a grid of poses, refine the best, read both fingers'
    contacts; ``tests/test_readme.py`` keeps the README's copy identical):
        >>> import jax.numpy as jnp
        >>> from softgrip_jax import CASE_NAMES, FingerModel, Geometric, Gripper, PolygonSDF, refine, score
        >>> finger = FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=20)  # mm, rad
        >>> gripper = Gripper(left=finger, right=finger, base_separation=56.0)  # mm
        >>> obj = PolygonSDF.regular(center=(0.0, 38.0), radius=15.0, n_vertices=128)  # a 30 mm disc
        >>> # Candidate poses (B, 3): gripper centre x, y in mm (y grows downward: the fingers hang
        >>> # toward +y) and the gripper's angle in rad.
        >>> x, y, angle = jnp.meshgrid(jnp.linspace(-10.0, 10.0, 11), jnp.linspace(-10.0, 10.0, 11),
        ...                            jnp.linspace(-0.2, 0.2, 5), indexing="ij")
        >>> poses = jnp.stack([x.ravel(), y.ravel(), angle.ravel()], axis=-1)  # (605, 3)
        >>> # One compiled call; invalid candidates score -inf. The geometric estimate is the fastest
        >>> # for a coarse grid; without estimator=, score and refine use the mechanics estimate, Mechanics().
        >>> result = score(gripper, obj, poses, estimator=Geometric())
        >>> best = int(jnp.argmax(result.score))
        >>> refined = refine(gripper, obj, poses[best], estimator=Geometric())  # never worse than its start
        >>> bool(refined.score.score >= result.score[best])
        True
        >>> for side in ("left", "right"):  # both fingers of the refined pose, each an Estimate
        ...     f = getattr(refined.score.grasp, side)
        ...     print(side, CASE_NAMES[int(f.case)], "first contact on the object (mm):",
        ...           [round(float(v), 1) for v in f.contact.p_o1], "tip (mm):", [round(float(v), 1) for v in f.joints[-1]])
        left other first contact on the object (mm): [-10.1, 49.1] tip (mm): [-4.5, 56.6]
        right other first contact on the object (mm): [13.9, 43.7] tip (mm): [11.5, 53.4]
    """
    estimator = as_estimator(estimator, method, mechanics)
    poses = as_candidates(poses, 3, gripper.base_separation.dtype, "score: poses")
    return run_batch(_score_one_device, _score_sharded, (gripper, sdf), poses, (weights, config), chunk_size,
                     workers, estimator)


class RefineStatus(enum.IntEnum):
    IMPROVED = 0  #: the refined pose scores higher and is valid
    NO_IMPROVEMENT = 1  #: the start was kept: the minimiser found nothing better that stays valid
    INVALID_START = 2  #: the start pose is not valid; nothing to refine


class Refined(eqx.Module):
    """Result of :func:`refine`: the pose, its :class:`Score`, the start's score, and why."""

    pose: Float[Array, "3"]
    score: Score
    start_score: Float[Array, ""]
    status: Int[Array, ""]
    solver_result: Int[Array, ""]  #: optimistix.RESULTS code of the minimiser, as an integer
    steps: Int[Array, ""]


def _refine_one(gripper, sdf, pose, weights, config, max_steps, angle_scale, estimator):
    scale = jnp.array([1.0, 1.0, angle_scale], pose.dtype)
    score_at = lambda p: score_pose(gripper, sdf, p, weights, config, estimator=estimator)  # noqa: E731

    def objective(z, _):
        s = score_at(z * scale)
        raw = jnp.where(s.valid, s.score, 0.0)
        # Leaving the valid set costs more than any score can gain.
        return -raw + 10.0 * (1.0 - s.valid.astype(pose.dtype))

    solution = optx.minimise(objective, optx.BFGS(rtol=1e-4, atol=1e-4), pose / scale, throw=False,
                             max_steps=max_steps)
    candidate = solution.value * scale
    # The start and the end scored by one traced copy of the score (lax.map), not two: the score
    # is most of the program, and of its compile time.
    both = jax.lax.map(score_at, jnp.stack([pose, candidate]))
    start, refined = (jax.tree_util.tree_map(lambda x, i=i: x[i], both) for i in (0, 1))
    better = refined.valid & (refined.score > start.score)
    keep = lambda new, old: jnp.where(better, new, old)
    return Refined(
        pose=keep(candidate, pose),
        score=jax.tree_util.tree_map(keep, refined, start),
        start_score=start.score,
        status=jnp.where(~start.valid, RefineStatus.INVALID_START,
                         jnp.where(better, RefineStatus.IMPROVED, RefineStatus.NO_IMPROVEMENT)).astype(jnp.int32),
        solver_result=jnp.asarray(solution.result._value, jnp.int32),
        steps=jnp.asarray(solution.stats["num_steps"], jnp.int32),
    )


def _refine_poses(gripper, sdf, poses, weights, config, max_steps, angle_scale, estimator):
    # One pose (3,) is refined without vmap: a batched while_loop carries a select of its whole
    # state at every step and runs both branches of each cond, a larger program that is slower to
    # compile and to load from the cache.
    if poses.ndim == 1:
        return _refine_one(gripper, sdf, poses, weights, config, max_steps, angle_scale, estimator)
    return jax.vmap(lambda p: _refine_one(gripper, sdf, p, weights, config, max_steps, angle_scale, estimator))(poses)


_refine_batch = exportable(tuned_jit(_refine_poses, static_argnames=("max_steps", "estimator")),
                           ("max_steps", "estimator"))


def refine(
    gripper: Gripper,
    sdf: AbstractSDF,
    pose: Float[ArrayLike, "*b 3"],
    weights: ScoreWeights = ScoreWeights(),
    config: ContactConfig = ContactConfig(),
    *,
    max_steps: int = 40,
    angle_scale: float = 0.05,
    estimator: AbstractEstimator | None = None,
    method: str | None = None,
    mechanics: MechanicsConfig | None = None,
) -> Refined:
    """Improve one pose (3,) or a batch (B, 3) by gradient ascent of the score (optimistix BFGS).

    The result never gets worse: when the minimiser ends at a pose that scores lower or is not
    valid, the start pose is returned with ``status = NO_IMPROVEMENT``. ``angle_scale`` (rad per
    unit of the minimiser's variable) balances millimetres against radians. ``estimator`` (or the
    older ``method`` / ``mechanics``) chooses the deformation estimate, as for :func:`score_pose`;
    the mechanics estimate's gradient in the pose comes from implicit differentiation.

    One pose (3,) and a batch (B, 3) run two compiled programs of the same algorithm (a batch under
    ``vmap``). Their rounding differs, and where BFGS wanders on a non-smooth score (contact cases
    changing, the edge of the valid set) a pose refined alone may end elsewhere than the same pose
    in a batch; each result keeps the guarantee above.

    Args:
        pose: (3,) or (B, 3) start poses: gripper centre x, y (mm) and angle (rad).
        max_steps: BFGS iterations at most (static).

    Returns:
        :class:`Refined` (leading axis B for a batch): ``pose`` (3,), its :class:`Score`,
        ``start_score``, ``status`` (a :class:`RefineStatus`), the minimiser's result and steps.

    Example: :func:`score`'s example refines the best pose of a scored grid.
    """
    estimator = as_estimator(estimator, method, mechanics)
    poses = as_candidates(pose, 3, gripper.base_separation.dtype, "refine: pose", single=True)
    return _refine_batch(gripper, sdf, poses, weights, config, max_steps, jnp.asarray(angle_scale, poses.dtype),
                         estimator)
