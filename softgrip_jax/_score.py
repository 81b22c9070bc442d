"""Scoring and refining pre-touch gripper poses (the paper's future work).

A candidate is a gripper pose (x mm, y mm, angle rad). Its score ranks what a grasp engineer
would: grasps in force closure first, by their quality; then the rest, by how near they come.

* ``quality``: the Ferrari-Canny L1 epsilon of both fingers' contacts with Coulomb friction
  (:mod:`softgrip_jax._quality`): the largest planar wrench the grasp resists in every direction
  per unit of total normal force, torque scaled by the object's size ``rho``. ``force_closure`` is
  ``quality > 0``. It is comparable across objects and poses, and does not change when object and
  gripper move, turn or scale together.
* ``risk`` in [0, 1], the tie-breaker: ``1 - (1 - w_tip tip_only)(1 - w_pen penetration)(1 - w_event
  event)``, with ``tip_only`` a finger landing with its tip only (case b), ``penetration`` the
  estimated finger's depth inside the object over the flagged depth (``max_penetration`` r), and
  ``event`` a slide-off or fold of the mechanics estimate near the pose (its ``Estimate.event``).
* ``progress`` in [0, 1], for grasps without closure: how much of a grasp there is,
  ``(w_touch mean(touch) + w_wrap mean(wrap) + w_opposition max(opposition, 0)) / (w_touch + w_wrap
  + w_opposition)``; ``touch`` (each finger closes onto the object before its closure ends: 1,
  grazes it at the very end: ramps to 0, misses: 0), ``wrap`` (the fraction of the finger within
  ``contact_band`` of the object) and ``opposition`` (-n_left . n_right at the first contacts).

    score = 1 + quality (1 - risk)                 in force closure   (in [1, 2))
    score = 0.99 progress (1 - risk)               otherwise           (in [0, 0.99])

so a grasp in force closure always ranks above one without, whatever the weights. An estimate
deeper in the object than ``max_penetration`` r is flagged ``penetrating``; it and every other
invalid candidate score -inf. Every setting is an array of :class:`ScoreWeights` (friction ``mu``
included): changing one never recompiles. Within a tier the score is a continuous function of the
estimate, and its derivative in the pose is that of the estimate (implicit differentiation);
:func:`refine` climbs it by a compass search, which also crosses the jumps between tiers.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from softgrip_jax._batch import as_candidates, grasp_chunk, map_chunks, run_batch
from softgrip_jax._checks import check_gripper, check_sdf
from softgrip_jax._compile import tuned_jit
from softgrip_jax._concurrent import run_in_pieces
from softgrip_jax._contact import ContactCase, ContactConfig
from softgrip_jax._errors import SoftgripError, check_number_fields
from softgrip_jax._export import exportable
from softgrip_jax._gather import where_needed
from softgrip_jax._grasp import GraspEstimate, estimate_grasp, per_finger
from softgrip_jax._frames import across_direction
from softgrip_jax._kinematics import chain_stations
from softgrip_jax._estimators import AbstractEstimator, Mechanics, as_estimator
from softgrip_jax._mechanics import contact_forces
from softgrip_jax._model import FingerModel, Gripper
from softgrip_jax._names import code_names
from softgrip_jax._quality import (CLOSURE_EPSILON, DEFAULT_MU, FingerContacts, closure_margin, edge_wrenches,
                                   finger_contacts)
from softgrip_jax._robust import (NOISE_SIZE, OffsetSDF, Uncertainty, linear_moments, noise_deviations, perturbations,
                                  perturbed)
from softgrip_jax._safe import safe_divide, tied_max, unit_direction
from softgrip_jax._sdf import AbstractSDF
from softgrip_jax._stage import Estimate, Status
from softgrip_jax._trace import trace_once

#: Candidates near force closure whose draws are evaluated together (robust quality), and draws of
#: each evaluated together: memory holds _DRAWN_GROUP x _DRAW_BLOCK estimates, whatever K is.
_DRAWN_GROUP = 32
_DRAW_BLOCK = 16
#: The score of the best grasp without force closure is at most this (every grasp in closure scores 1 or more).
OPEN_TIER_MAX = 0.99


class ScoreWeights(eqx.Module):
    """Settings of the score, all run-time values (array leaves: changing one never recompiles).

    Attributes:
        mu: Coulomb friction coefficient between finger and object (default: silicone on common
            dry objects, :data:`~softgrip_jax._quality.DEFAULT_MU`).
        tip_only, penetration, event: weights in [0, 1] of the risks (see the module docstring).
        touch, wrap, opposition: weights (>= 0) of the progress of a grasp without closure.
        contact_band: mm beyond r within which a station counts as touching (quality) or lying
            along the object (wrap).
        max_penetration: fraction of r; an estimate deeper inside the object is flagged.
    """

    mu: float | Array = DEFAULT_MU
    tip_only: float | Array = 0.5
    penetration: float | Array = 0.5
    event: float | Array = 0.5
    touch: float | Array = 1.0
    wrap: float | Array = 1.0
    opposition: float | Array = 1.0
    contact_band: float | Array = 0.25
    max_penetration: float | Array = 0.5

    def __check_init__(self):
        checks = {"mu": (0.0, 10.0), "tip_only": (0.0, 1.0), "penetration": (0.0, 1.0), "event": (0.0, 1.0),
                  "touch": (0.0, 1e6), "wrap": (0.0, 1e6), "opposition": (0.0, 1e6), "contact_band": (0.0, 100.0),
                  "max_penetration": (0.0, 10.0)}
        check_number_fields(self, checks)
        if not isinstance(self.touch, jax.core.Tracer) and float(self.touch) + float(self.wrap) + float(self.opposition) <= 0:
            raise SoftgripError("ScoreWeights: touch, wrap and opposition must not all be 0")


class ScoreComponents(eqx.Module):
    """The terms of the score; per-finger arrays are (left, right)."""

    touch: Float[Array, "2"]
    wrap: Float[Array, "2"]
    opposition: Float[Array, ""]
    tip_only: Float[Array, "2"]
    penetration_mm: Float[Array, "2"]
    risk: Float[Array, ""]  #: in [0, 1]
    progress: Float[Array, ""]  #: in [0, 1]


class Score(eqx.Module):
    """A scored candidate: ``score`` is -inf unless ``valid`` (estimates usable, no flag).

    Attributes:
        quality: the Ferrari-Canny L1 epsilon of both fingers' contacts (0 without force closure,
            and where not valid).
        force_closure: ``quality > 0``.
        contacts: (left, right) :class:`~softgrip_jax._quality.FingerContacts`, leaves with a
            leading axis 2: the contacts the quality is computed from.
        centroid: (2,) mm, the object's area centroid (torques are about it); rho: mm, its
            largest distance from the centroid.
        quality_mean, p_closure: with an :class:`~softgrip_jax._robust.Uncertainty`, the expected
            quality and the probability of force closure over its draws, and the score in closure
            is ``1 + quality_mean (1 - risk)`` (NaN for a candidate not drawn: not valid, or
            outside closure beyond the uncertainty's ``reach``); without one, ``quality`` and 0 or 1.
        margin: the signed closure margin (:func:`~softgrip_jax._quality.closure_margin`): the
            quality in force closure, minus the wrench distance to it outside (how far a grasp
            is from closure); -1 where not valid.
    """

    score: Float[Array, ""]
    components: ScoreComponents
    grasp: GraspEstimate
    penetrating: Bool[Array, ""]
    valid: Bool[Array, ""]
    status: Int[Array, ""]  #: the first failing finger's :class:`Status`, 0 if both are OK
    quality: Float[Array, ""]
    force_closure: Bool[Array, ""]
    contacts: FingerContacts
    centroid: Float[Array, "2"]
    rho: Float[Array, ""]
    quality_mean: Float[Array, ""]
    p_closure: Float[Array, ""]
    margin: Float[Array, ""]

    @property
    def status_name(self) -> str | np.ndarray:
        """``status`` by name (:class:`Status`, lower case; an array of names for a batch; outside ``jit``)."""
        return code_names(self.status, Status)


def _finger_terms(finger: FingerModel, sdf: AbstractSDF, est: Estimate, weights: ScoreWeights, config, estimator,
                  handedness: Float[ArrayLike, ""]):
    theta = finger.theta_entire
    touches = est.case != ContactCase.NONE
    # Closing onto the object counts fully when it happens before the last tenth of the closure.
    touch = jnp.where(touches, jnp.clip(safe_divide(theta - est.contact.s1, 0.1 * theta, 1.0), 0.0, 1.0), 0.0)
    joints = jnp.where(est.valid, est.joints, 0.0)
    per_link = (estimator.config.stations_per_link if isinstance(estimator, Mechanics)
                else config.per_link(finger.n_links))
    stations, _ = chain_stations(joints, finger.length, per_link)
    distance = sdf.distance(stations)
    gap = distance - finger.half_thickness
    band = jnp.maximum(weights.contact_band, 1e-3)
    wrap = jnp.mean(jax.nn.sigmoid((band - gap) / (0.25 * band)))
    tip = jax.nn.sigmoid((est.contact.n_g1 - (finger.n_links - config.tip_tolerance)) / 0.1) * touch
    penetration = jnp.maximum(-jnp.min(gap), 0.0)
    # The outward normal at the contact, taken r off the surface at P_g1, where it is well defined
    # (exactly on a polygon's boundary the direction to the nearest point is rounding noise).
    normal = sdf.normal(jnp.where(est.valid, est.contact.p_g1, 0.0))
    contacts, station = finger_contacts(sdf, stations, finger.half_thickness, band, distance=distance)
    touching = contacts.touching & est.valid & touches
    forces = contacts.forces
    if isinstance(estimator, Mechanics):  # the equilibrium's forces, on the object (along -n)
        size = contact_forces(finger, joints, est.turning, jnp.asarray(handedness, joints.dtype), stations[station],
                              contacts.normals, station, per_link, touching)
        forces = -size[:, None] * contacts.normals
    contacts = FingerContacts(points=contacts.points, normals=contacts.normals, forces=forces, touching=touching)
    return touch, wrap, tip, penetration, normal, contacts


def score_pose(
    gripper: Gripper,
    sdf: AbstractSDF,
    pose: Float[ArrayLike, "3"],
    weights: ScoreWeights = ScoreWeights(),
    config: ContactConfig = ContactConfig(),
    *,
    estimator: AbstractEstimator | None = None,
    uncertainty: Uncertainty | None = None,
) -> Score:
    """Score one pose (x mm, y mm, angle rad). Pure; jit-, vmap- and grad-compatible.

    With ``uncertainty`` (:class:`~softgrip_jax._robust.Uncertainty`) the quality is also taken over
    its K draws (``quality_mean``, ``p_closure``), which then rank grasps in force closure.

    ``estimator`` chooses the fingers' deformation estimate, ``Mechanics(config)`` (None: the
    default, ``Mechanics()``) or ``Geometric()``, as for :func:`estimate_grasp`.

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
    check_gripper(gripper)
    check_sdf(sdf)
    estimator = as_estimator(estimator)
    if uncertainty is not None and uncertainty.linear:
        def at(z):
            sample = perturbed(gripper, weights.mu, uncertainty, z)
            s = _score_drawn(gripper, sdf, weights, config, estimator, pose, sample)
            return s.margin, s

        return _linearised(at, gripper.base_separation.dtype)
    grasp = estimate_grasp(gripper, sdf, pose, config, estimator=estimator)
    nominal = _score_grasp(gripper, sdf, grasp, weights, config, estimator)
    if uncertainty is None:
        return nominal
    quality, closure = _drawn(gripper, sdf, weights, config, estimator, uncertainty, pose)
    return _with_robust(nominal, quality, closure, _within_reach(nominal, uncertainty))


def _score_grasp(gripper: Gripper, sdf: AbstractSDF, grasp: GraspEstimate, weights: ScoreWeights, config,
                 estimator) -> Score:
    """The :class:`Score` of both fingers' estimates at one pose."""
    one = jnp.ones((), gripper.base_separation.dtype)
    left, right = per_finger(lambda finger, est, hand: _finger_terms(finger, sdf, est, weights, config, estimator, hand),
                             gripper, (grasp.left, grasp.right), (one, -one))
    touch, wrap, tip, penetration = (jnp.stack([a, b]) for a, b in zip(left[:4], right[:4]))
    opposition = -jnp.dot(left[4], right[4]) * touch[0] * touch[1]
    contacts = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), left[5], right[5])
    centroid, rho = sdf.mass_properties()
    margin = _contacts_margin(contacts, weights.mu, centroid, rho)
    closure = margin > CLOSURE_EPSILON
    quality = jnp.where(closure, margin, 0.0)
    r = jnp.stack([gripper.left.half_thickness, gripper.right.half_thickness])
    limit = weights.max_penetration * r
    # The fingers' larger risk; mirror images tie (to rounding) at a symmetric pose, where each
    # side's derivative counts half (tied_max), as the symmetric score's derivative is.
    depth = tied_max(jnp.clip(safe_divide(penetration, limit, 1.0), 0.0, 1.0))
    event = (grasp.left.event | grasp.right.event).astype(quality.dtype)
    risk = 1.0 - (1.0 - weights.tip_only * tied_max(tip)) * (1.0 - weights.penetration * depth) * (
        1.0 - weights.event * event)
    total = weights.touch + weights.wrap + weights.opposition
    progress = (weights.touch * jnp.mean(touch) + weights.wrap * jnp.mean(wrap)
                + weights.opposition * jnp.maximum(opposition, 0.0)) / total
    raw = jnp.where(closure, 1.0 + quality * (1.0 - risk), OPEN_TIER_MAX * progress * (1.0 - risk))
    penetrating = jnp.any(penetration > limit)
    sound = jnp.isfinite(raw)  # e.g. a NaN the SDF returns near the fingers: never a valid NaN score
    valid = grasp.valid & ~penetrating & sound
    status = jnp.where(grasp.left.status != 0, grasp.left.status, grasp.right.status)
    status = jnp.where((status == 0) & ~sound, Status.NON_FINITE_RESULT, status).astype(status.dtype)
    return Score(
        score=jnp.where(valid, raw, -jnp.inf),
        components=ScoreComponents(touch=touch, wrap=wrap, opposition=opposition, tip_only=tip,
                                   penetration_mm=penetration, risk=risk, progress=progress),
        grasp=grasp, penetrating=penetrating, valid=valid, status=status,
        quality=jnp.where(valid & closure, quality, 0.0), force_closure=closure & valid, contacts=contacts,
        centroid=centroid, rho=rho, quality_mean=jnp.where(valid & closure, quality, 0.0),
        p_closure=(closure & valid).astype(quality.dtype), margin=jnp.where(valid, margin, -1.0),
    )


def _contacts_margin(contacts: FingerContacts, mu, centroid, rho) -> Float[Array, ""]:
    """The signed closure margin (:func:`~softgrip_jax._quality.closure_margin`) of both fingers'
    contacts (leaves with a leading axis 2)."""
    touching = contacts.touching.reshape(-1)
    wrenches = edge_wrenches(contacts.points.reshape(-1, 2), contacts.normals.reshape(-1, 2), touching, mu,
                             centroid, rho)
    return closure_margin(wrenches, jnp.repeat(touching, 2))


def _score_drawn(gripper, sdf, weights, config, estimator, pose, sample) -> Score:
    """The :class:`Score` of one pose (3,) under one draw (:class:`~softgrip_jax._robust.Perturbations`
    without a leading axis): its gripper, object, friction and pose offset."""
    g, o, w = _draw(gripper, sdf, weights, sample)
    return _score_grasp(g, o, estimate_grasp(g, o, pose + sample.pose, config, estimator=estimator), w, config,
                        estimator)


def _drawn(gripper, sdf, weights, config, estimator, uncertainty, pose):
    """(K,) quality and force closure of one pose (3,) in each of the K draws of ``uncertainty``,
    :data:`_DRAW_BLOCK` draws at a time (so memory does not grow with K)."""
    def one(sample):
        s = _score_drawn(gripper, sdf, weights, config, estimator, pose, sample)
        return s.quality, s.force_closure

    k = uncertainty.samples
    block = min(k, _DRAW_BLOCK)
    count = -(-k // block)
    wrapped = jnp.arange(count * block) % k  # the last block is filled with the first draws, then dropped
    draws = jax.tree_util.tree_map(lambda x: x[wrapped].reshape((count, block) + x.shape[1:]),
                                   perturbations(gripper, weights.mu, uncertainty))
    quality, closure = jax.lax.map(jax.vmap(one), draws)
    return quality.reshape(-1)[:k], closure.reshape(-1)[:k]


def _within_reach(nominal: Score, uncertainty: Uncertainty) -> Bool[Array, "*b"]:
    """Which candidates are drawn: valid, and in force closure or their closure margin above
    ``-uncertainty.reach``."""
    return nominal.valid & (nominal.force_closure | (nominal.margin > -uncertainty.reach))


def _with_robust(nominal: Score, quality: Float[Array, " k"], closure: Bool[Array, " k"], drawn) -> Score:
    """``nominal`` with the expected quality and probability of closure over K draws (each draw's
    quality and closure, 0 and False where its estimate is not valid), ranked by them; NaN where
    not ``drawn`` (not known)."""
    mean = jnp.where(drawn, jnp.mean(quality, axis=0), 0.0)
    p = jnp.where(drawn, jnp.mean(closure.astype(mean.dtype), axis=0), jnp.nan)
    # (NaN only in the reported fields: in the score's untaken branch it would reach its gradient.)
    score = jnp.where(nominal.valid & nominal.force_closure, 1.0 + mean * (1.0 - nominal.components.risk),
                      nominal.score)
    return eqx.tree_at(lambda s: (s.score, s.quality_mean, s.p_closure), nominal,
                       (score, jnp.where(drawn, mean, jnp.nan), p))


def _linearised(margins, dtype) -> Score:
    """The nominal :class:`Score` (leaves of any leading shape) with ``quality_mean`` and
    ``p_closure`` from the first-order expansion of the closure margin in the standard variables z
    (:func:`~softgrip_jax._robust.linear_moments`); ``margins(z)`` gives ``(margin, Score)`` at z."""
    margin, derivative, nominal = jax.linearize(margins, jnp.zeros(NOISE_SIZE, dtype), has_aux=True)
    tangents = jax.vmap(derivative)(jnp.diag(noise_deviations(dtype)))  # (13, *b)
    mean, p = linear_moments(margin, tangents)
    score = jnp.where(nominal.valid & nominal.force_closure, 1.0 + mean * (1.0 - nominal.components.risk),
                      nominal.score)
    unknown = lambda x: jnp.where(nominal.valid, x, jnp.nan)  # noqa: E731
    return eqx.tree_at(lambda s: (s.score, s.quality_mean, s.p_closure), nominal, (score, unknown(mean), unknown(p)))


def _draw(gripper, sdf, weights, sample):
    """The gripper, object and weights of one draw of :func:`~softgrip_jax._robust.perturbations`."""
    return sample.gripper, OffsetSDF(sdf, sample.contour), eqx.tree_at(lambda w: w.mu, weights, sample.mu)


def _score_share(gripper, sdf, poses, weights, config, uncertainty, chunk_size, estimator):
    """The :class:`Score` of poses (P, 3) on one device, ``chunk_size`` at a time: in each chunk both
    fingers' estimates (the contact refined and the equilibrium solved only where a finger touches,
    :mod:`softgrip_jax._batch`), then the score of each pose; with ``uncertainty``, the same for
    each of its K draws, for the candidates in (or within its ``reach`` of) force closure."""
    def scored(g, o, w, share):
        grasps = grasp_chunk(g, o, share, config, estimator)
        return jax.vmap(lambda e: _score_grasp(g, o, e, w, config, estimator))(grasps)

    def chunk(share):
        if uncertainty is not None and uncertainty.linear:
            def at(sample):
                g, o, w = _draw(gripper, sdf, weights, sample)
                s = scored(g, o, w, share + sample.pose)
                return s.margin, s

            return _linearised(lambda z: at(perturbed(gripper, weights.mu, uncertainty, z)), share.dtype)
        nominal = scored(gripper, sdf, weights, share)
        if uncertainty is None:
            return nominal
        # Only the candidates in (or near) force closure are drawn, a group at a time: the cost
        # follows their number, not the chunk's.
        drawn = _within_reach(nominal, uncertainty)
        draw_pose = lambda pose: _drawn(gripper, sdf, weights, config, estimator, uncertainty, pose)  # noqa: E731
        quality, closure = where_needed(draw_pose, drawn, share, group_size=_DRAWN_GROUP)
        return jax.vmap(_with_robust)(nominal, quality, closure, drawn)

    return map_chunks(chunk, poses, chunk_size)


_score_one_device = exportable(tuned_jit(_score_share, static_argnames=("chunk_size", "estimator")),
                               ("chunk_size", "estimator"))


@partial(tuned_jit, static_argnames=("chunk_size", "estimator"))
def _score_sharded(gripper, sdf, poses, weights, config, uncertainty, chunk_size, estimator):
    # poses: (devices, per_device, 3); the device axis is vmapped (and sharded across the devices).
    return jax.vmap(lambda share: _score_share(gripper, sdf, share, weights, config, uncertainty, chunk_size,
                                               estimator))(poses)


def score(
    gripper: Gripper,
    sdf: AbstractSDF,
    poses: Float[ArrayLike, "b 3"],
    weights: ScoreWeights = ScoreWeights(),
    config: ContactConfig = ContactConfig(),
    *,
    chunk_size: int | None = None,
    estimator: AbstractEstimator | None = None,
    workers: int | None = None,
    uncertainty: Uncertainty | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Score:
    """Score B candidate poses (x mm, y mm, angle rad) in one compiled call.

    Poses are evaluated in pieces of a few fixed sizes chosen by B (one pose as a piece of one,
    thousands as pieces of 4096), each size compiled once, when first needed (memory does not grow
    with B). When several JAX devices are
    present (GPUs, or hosts joined by ``jax.distributed``), each device runs pieces of the same size
    with ``jax.sharding``; results agree with a single device's to float32 rounding. Returns a
    :class:`Score` whose leaves have a leading axis B; rank with ``jnp.argsort(-result.score)``.
    ``estimator`` chooses the deformation estimate, as for :func:`score_pose`; with ``Mechanics()`` (the default) the equilibrium is solved only for
    fingers that touch.

    Args:
        gripper: both fingers and the base separation W (mm, rad).
        sdf: the object (mm), in the frame's millimetre coordinates (x right, y down).
        poses: (B, 3) candidate poses: gripper centre x, y (mm) and angle (rad).
        chunk_size: poses per compiled call (a piece; static); memory grows with it, not with B.
            None (default): chosen by B, as for :func:`estimate_batch`. An int: every B runs
            through the program of that size.
        estimator: ``Geometric()`` or ``Mechanics(config)`` (None: ``Mechanics()``); equal
            estimators reuse one compiled program.
        workers: on one device, pieces run at once (None: one per CPU core on a CPU, one
            elsewhere), as for :func:`estimate_batch`.
        progress: ``progress(done, total)`` (poses) after each piece, as for :func:`estimate_batch`.
        uncertainty: robust quality (:class:`~softgrip_jax._robust.Uncertainty`): each candidate
            is also scored for its K draws of the calibration, the pose error, mu and the contour
            (the same draws for every candidate), giving ``quality_mean`` and ``p_closure``, which
            then rank the grasps in closure. Only valid candidates in force closure, or whose
            closure margin is above ``-uncertainty.reach``, are drawn (K times their time); the
            others' ``quality_mean`` and ``p_closure`` are NaN (not drawn). With
            ``linear=True``, a first-order expansion instead (see :mod:`softgrip_jax._robust`).
            None: the nominal quality only.

    Returns:
        :class:`Score` with leading axis B: ``score`` (B,) (-inf where not valid), ``components``,
        ``grasp`` (both fingers' :class:`Estimate`, joints (B, N+1, 2) mm), ``valid``, ``status``.

    Example (the README's planner: score a grid of poses, refine the best, read both fingers'
    contacts; ``tests/test_readme.py`` keeps the README's copy identical):
        >>> import jax.numpy as jnp
        >>> from softgrip_jax import FingerModel, Geometric, Gripper, PolygonSDF, enable_compilation_cache, refine, score
        >>> # Compiled programs kept on disk (a per-user folder): a new process starts in seconds.
        >>> cache_folder = enable_compilation_cache()
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
        >>> # Grasps in force closure (friction mu = ScoreWeights().mu = 0.5) rank first, by their quality.
        >>> result = score(gripper, obj, poses, estimator=Geometric())
        >>> best = int(jnp.argmax(result.score))
        >>> print(int(result.force_closure.sum()), "of", len(poses), "poses in force closure; the best:",
        ...       [round(float(v), 2) for v in poses[best]], "quality", round(float(result.quality[best]), 3),
        ...       "risk", round(float(result.components.risk[best]), 2))
        60 of 605 poses in force closure; the best: [0.0, -10.0, 0.0] quality 0.281 risk 0.5
        >>> refined = refine(gripper, obj, poses[best], estimator=Geometric())  # never worse than its start
        >>> bool(refined.score.score >= result.score[best])
        True
        >>> for side in ("left", "right"):  # why it won: both fingers of the refined pose, each an Estimate
        ...     f = getattr(refined.score.grasp, side)
        ...     print(side, f.case_name, "first contact on the object (mm):",
        ...           [round(float(v), 1) for v in f.contact.p_o1], "tip (mm):", [round(float(v), 1) for v in f.joints[-1]])
        left tip first contact on the object (mm): [-14.9, 40.0] tip (mm): [-19.2, 38.3]
        right tip first contact on the object (mm): [14.9, 40.0] tip (mm): [19.2, 38.3]
    """
    check_gripper(gripper)
    check_sdf(sdf)
    estimator = as_estimator(estimator)
    poses = as_candidates(poses, 3, gripper.base_separation.dtype, "score: poses")
    return run_batch(_score_one_device, _score_sharded, (gripper, sdf), poses, (weights, config, uncertainty),
                     chunk_size, workers, estimator, progress)


class RefineStatus(enum.IntEnum):
    IMPROVED = 0  #: the search converged at a valid pose that scores higher than the start
    NO_IMPROVEMENT = 1  #: the search converged at the start: nothing near it scores higher (pose unchanged)
    INVALID_START = 2  #: the start pose is not valid; nothing to refine
    MAX_STEPS = 3  #: the step budget ran out before the search converged: the best pose so far (never worse)


class Refined(eqx.Module):
    """Result of :func:`refine`: the pose, its :class:`Score`, the start's score, and why."""

    pose: Float[Array, "3"]
    score: Score
    start_score: Float[Array, ""]
    status: Int[Array, ""]
    solver_result: Int[Array, ""]  #: optimistix.RESULTS code: successful, or nonlinear_max_steps_reached
    steps: Int[Array, ""]  #: polls of the search (each one batched evaluation of the stencil)

    @property
    def status_name(self) -> str | np.ndarray:
        """``status`` by name: ``"improved"``, ``"no_improvement"``, ``"invalid_start"`` or
        ``"max_steps"`` (an array of names for a batch; outside ``jit``)."""
        return code_names(self.status, RefineStatus)


#: The search's stencils: offsets (across mm, approach mm, angle in units of ``angle_scale``) per
#: unit step, all evaluated in one batched call per poll; both have the same number of rows (one
#: compiled poll). Row 0 is the best pose itself at the first poll (the start), and afterwards the
#: last successful move repeated from the new best pose (a pattern move; the best pose again after
#: a failed poll).
#:
#: ``_COARSE``, at every step but the last: along the approach axis every half step up to two
#: steps (the score jumps between tiers there: an optimum at the edge of force closure lies just
#: past a plateau of the open tier, and the band of force closure along the approach axis can be
#: thinner than a step, so whole steps alone jump over it); across the gripper and in angle one
#: step; the diagonals of across with approach; and those of across with angle that turn the
#: gripper about a point ``1 / angle_scale`` mm ahead of it, toward the object (the edge of force
#: closure moves with all three, so the way up along it is often diagonal; the other diagonals of
#: across with angle turn the gripper about a point behind it, away from the object).
_COARSE = np.array([
    [0, 0, 0],
    [0, 1, 0], [0, -1, 0], [0, 2, 0], [0, -2, 0], [0, 0.5, 0], [0, -0.5, 0], [0, 1.5, 0], [0, -1.5, 0],
    [1, 0, 0], [-1, 0, 0],
    [0, 0, 1], [0, 0, -1],
    [1, 0, -1], [-1, 0, 1],
    [1, 1, 0], [-1, 1, 0], [1, -1, 0], [-1, -1, 0],
], np.float32)
#: ``_FINE``, at the last step (the one converging): the optimum lies on the curved edge of force
#: closure, where the way up combines all three axes; besides the axes, the turns about a point ahead
#: and the diagonals of across with the way back along the approach axis (toward the edge), the
#: eight corners (every axis at once), which the coarse stencil lacks.
_FINE = np.array([
    [0, 0, 0],
    [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1],
    [1, 0, -1], [-1, 0, 1],
    [1, -1, 0], [-1, -1, 0],
    [1, 1, 1], [1, 1, -1], [1, -1, 1], [1, -1, -1], [-1, 1, 1], [-1, 1, -1], [-1, -1, 1], [-1, -1, -1],
], np.float32)
#: A failed poll multiplies the step by this (the last poll at ``final_step`` itself when a step
#: would skip past it): from the default 2 mm, polls at 2, 0.5 and 0.125 mm.
_SHRINK = 0.25
#: A poll improves on the best pose when it scores more than this above it (float32 rounding of
#: the score is below 1e-6): equal scores (a plateau, or a pose scored twice) never move it.
_GAIN = 1e-6


def _offsets(pose, step, angle_scale, stencil):
    """(S, 3) pose offsets of ``stencil`` (S, 3) at ``step`` mm, in the gripper's frame at ``pose``."""
    across, down = across_direction(pose[2]), unit_direction(pose[2])
    xy = step * (stencil[:, :1] * across + stencil[:, 1:2] * down)
    return jnp.concatenate([xy, step * angle_scale * stencil[:, 2:]], axis=-1)


def _refine_one(gripper, sdf, pose, weights, config, uncertainty, max_steps, angle_scale, estimator, initial_step,
                final_step):
    """A compass search (pattern search) of the score from ``pose``: each poll scores a stencil
    around the best pose at ``step`` in one batched call (:data:`_COARSE`, or :data:`_FINE` at the
    last step), moves to its best point when that is higher, else multiplies ``step`` by
    :data:`_SHRINK`; it converges when ``step`` falls below ``final_step``."""
    dtype = pose.dtype
    coarse, fine = jnp.asarray(_COARSE, dtype), jnp.asarray(_FINE, dtype)

    def scored(poses):
        s = jax.vmap(lambda p: score_pose(gripper, sdf, p, weights, config, estimator=estimator,
                                          uncertainty=uncertainty))(poses)
        # The score travels as one flat vector per pose (one select per step, not one per leaf);
        # its integers (case and status codes) and flags are exact in the vector's float dtype.
        return jnp.where(s.valid, s.score, -jnp.inf), jax.vmap(lambda one: ravel_pytree(one)[0])(s), s

    shapes, scored = trace_once(scored, jnp.zeros((coarse.shape[0], 3), dtype))
    unflatten = ravel_pytree(jax.tree_util.tree_map(lambda leaf: jnp.zeros(leaf.shape[1:], leaf.dtype), shapes[2]))[1]
    step0 = jnp.asarray(initial_step, dtype)
    tol = jnp.asarray(final_step, dtype)
    flat_size = shapes[1].shape[1]

    def shrunk(step):  # divided by 4, but the last poll at final_step itself, not below it
        return jnp.where((step > tol) & (_SHRINK * step < tol), tol, _SHRINK * step)

    def poll(carry):
        best, value, flat, step, last, k, start_value, start_flat = carry
        stencil = jnp.where(step * _SHRINK < tol, fine, coarse)
        offsets = _offsets(best, step, angle_scale, stencil).at[0].set(last)
        values, flats, _ = scored(best + offsets)
        first = k == 0
        start_value = jnp.where(first, values[0], start_value)
        start_flat = jnp.where(first, flats[0], start_flat)
        value = jnp.where(first, values[0], value)
        flat = jnp.where(first, flats[0], flat)
        i = jnp.argmax(values)
        better = (values[i] > value + _GAIN) & jnp.isfinite(start_value)
        return (jnp.where(better, best + offsets[i], best), jnp.where(better, values[i], value),
                jnp.where(better, flats[i], flat), jnp.where(better, step, shrunk(step)),
                jnp.where(better, offsets[i], 0.0), k + 1, start_value, start_flat)

    def going(carry):
        _, _, _, step, _, k, start_value, _ = carry
        return (k == 0) | ((k < max_steps) & (step >= tol) & jnp.isfinite(start_value))

    zeros = jnp.zeros((flat_size,), shapes[1].dtype)
    carry = (pose, jnp.asarray(-jnp.inf, dtype), zeros, step0, jnp.zeros((3,), dtype), jnp.asarray(0, jnp.int32),
             jnp.asarray(-jnp.inf, dtype), zeros)
    best, value, flat, step, _, k, start_value, start_flat = jax.lax.while_loop(going, poll, carry)
    start, end = unflatten(start_flat), unflatten(flat)
    converged = step < tol
    moved = jnp.any(best != pose)
    status = jnp.where(~start.valid, RefineStatus.INVALID_START,
                       jnp.where(~converged, RefineStatus.MAX_STEPS,
                                 jnp.where(moved, RefineStatus.IMPROVED, RefineStatus.NO_IMPROVEMENT)))
    result = jnp.where(converged | ~start.valid, optx.RESULTS.successful._value,
                       optx.RESULTS.nonlinear_max_steps_reached._value)
    return Refined(pose=best, score=end, start_score=start.score, status=status.astype(jnp.int32),
                   solver_result=jnp.asarray(result, jnp.int32), steps=k)


def _refine_poses(gripper, sdf, poses, weights, config, uncertainty, max_steps, angle_scale, steps, estimator):
    # One pose (3,) is refined without vmap: a batched while_loop carries a select of its whole
    # state at every step, a larger program that is slower to compile and to load from the cache.
    initial_step, final_step = steps
    run = lambda p: _refine_one(gripper, sdf, p, weights, config, uncertainty, max_steps, angle_scale,  # noqa: E731
                                estimator, initial_step, final_step)
    return run(poses) if poses.ndim == 1 else jax.vmap(run)(poses)


_refine_batch = exportable(tuned_jit(_refine_poses, static_argnames=("max_steps", "estimator")),
                           ("max_steps", "estimator"))


#: Poses of a batch refined together by :func:`refine` (each runs its own search under ``vmap``).
REFINE_CHUNK = 16


def refine(
    gripper: Gripper,
    sdf: AbstractSDF,
    pose: Float[ArrayLike, "*b 3"],
    weights: ScoreWeights = ScoreWeights(),
    config: ContactConfig = ContactConfig(),
    *,
    max_steps: int = 32,
    angle_scale: float = 0.025,
    estimator: AbstractEstimator | None = None,
    uncertainty: Uncertainty | None = None,
    chunk_size: int = REFINE_CHUNK,
    workers: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    initial_step: float = 2.0,
    final_step: float = 0.125,
) -> Refined:
    """Improve one pose (3,) or a batch (B, 3) to the best-scoring pose near it (a local optimum of
    the score: the grasp quality in force closure, robust with ``uncertainty``, as for :func:`score`).

    A compass search (pattern search): each step (a *poll*) scores a small stencil of poses
    around the best pose so far in one batched call, ``step`` mm apart in the gripper's frame
    (``step * angle_scale`` rad in angle). It moves to the stencil's best pose when that scores
    higher, else divides ``step`` by 4 (polling at ``final_step`` itself when a division would
    skip past it), from ``initial_step`` until it falls below ``final_step`` (converged; by
    default polls at 2, 0.5 and 0.125 mm). The stencil reaches every half step up to
    two steps along the approach axis, one step across it and in angle, the diagonals of across
    with approach, and turns about a point ``1 / angle_scale`` mm ahead of the gripper (a step
    across with minus a step in angle); at the last step it takes the axes, those turns, the
    diagonals of across with the way back along the approach axis and the eight corners (all
    three axes at once) instead; each poll also repeats the last successful move. It needs no
    derivative and crosses the score's jumps between tiers (an optimum at the edge of force
    closure lies just past the open tier's plateau, across a band of force closure that can be
    thinner than a step), where a gradient method stalls. From starts within 3 mm and 0.05 rad of
    an optimum it reaches it, to 0.1 mm or 1 % of its score, unless the force closure nearest the
    start is a lower optimum's (``benchmarks/bench_refine.py``: 59 of 60 starts on three objects).

    The result never gets worse than the start (a pose moves only to a strictly higher valid score).
    ``status`` says what happened: ``IMPROVED`` (converged at a better pose), ``NO_IMPROVEMENT``
    (converged at the start, which is returned unchanged), ``MAX_STEPS`` (``max_steps`` polls
    ran out first: the best pose found, which may or may not be better; compare ``score.score``
    with ``start_score``) or ``INVALID_START``. ``estimator`` chooses the deformation estimate,
    as for :func:`score_pose`.

    One pose (3,) and a batch (B, 3) run two compiled programs of the same algorithm (a batch under
    ``vmap``); their rounding differs, so on a score with jumps a pose refined alone may end
    elsewhere than the same pose in a batch; each result keeps the guarantee above.

    A batch is refined ``chunk_size`` poses at a time by one compiled program whatever B is
    (pieces, ``workers`` at once, ``progress(done, total)`` after each, as for :func:`score`).

    Args:
        pose: (3,) or (B, 3) start poses: gripper centre x, y (mm) and angle (rad).
        max_steps: polls at most (static); each scores the stencil (19 poses) once.
        angle_scale: rad of the angle stencil per mm of ``step``.
        chunk_size: poses of a batch refined together (static).
        initial_step: the stencil's first step (mm).
        final_step: the step (mm) below which the search has converged.

    Returns:
        :class:`Refined` (leading axis B for a batch): ``pose`` (3,), its :class:`Score`,
        ``start_score``, ``status`` (a :class:`RefineStatus`), ``solver_result`` (an optimistix
        ``RESULTS`` code: successful, or max steps reached) and ``steps`` (polls).

    Example: :func:`score`'s example refines the best pose of a scored grid.
    """
    check_gripper(gripper)
    check_sdf(sdf)
    if isinstance(max_steps, bool) or not isinstance(max_steps, int) or max_steps < 1:
        raise SoftgripError(f"refine: max_steps must be a whole number of search steps >= 1, got {max_steps!r}")
    if not 0 < final_step <= initial_step:
        raise SoftgripError(f"refine: need 0 < final_step <= initial_step (mm), got final_step={final_step!r}, "
                            f"initial_step={initial_step!r}")
    estimator = as_estimator(estimator)
    poses = as_candidates(pose, 3, gripper.base_separation.dtype, "refine: pose", single=True)
    scale = jnp.asarray(angle_scale, poses.dtype)
    steps = (jnp.asarray(initial_step, poses.dtype), jnp.asarray(final_step, poses.dtype))
    if poses.ndim == 1:
        return _refine_batch(gripper, sdf, poses, weights, config, uncertainty, max_steps, scale, steps, estimator)
    return run_in_pieces(_refine_piece, (gripper, sdf), poses, (weights, config, uncertainty, scale, steps), workers,
                         chunk_size, progress, max_steps=max_steps, estimator=estimator)


def _refine_piece(gripper, sdf, poses, weights, config, uncertainty, scale, steps, *, chunk_size, max_steps,
                  estimator):
    del chunk_size  # the piece is the batch: the search runs on all its poses at once
    return _refine_batch(gripper, sdf, poses, weights, config, uncertainty, max_steps, scale, steps, estimator)
