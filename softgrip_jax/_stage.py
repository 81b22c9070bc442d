"""The estimate of one finger in stages, in its own frame until the last: the inputs checked,
the first contact bracketed and refined (eqs. 5-8, :mod:`softgrip_jax._contact`), the shape of its
case (eq. 9, :mod:`softgrip_jax._deformation`), then an estimator's deformation and
:func:`finish`, which places the chain in the image plane with its status.

Batched code (:mod:`softgrip_jax._batch`) runs these stages on only the fingers that need each;
:func:`geometric_stage` runs them for one finger. The equations live in the modules named above.
"""

from __future__ import annotations

import enum
from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from softgrip_jax._contact import (Bracket, Contact, ContactCase, ContactConfig, RootSearch, bracket_contact, finish_root,
                                   free_contact, refine_contact, start_root)
from softgrip_jax._deformation import case_shape
from softgrip_jax._frames import FingerFrame
from softgrip_jax._kinematics import forward_kinematics
from softgrip_jax._mechanics import (Equilibrium, MechanicsConfig, Progress, closing_start, finish_equilibrium,
                                     start_equilibrium)
from softgrip_jax._model import FingerModel
from softgrip_jax._names import code_names
from softgrip_jax._sdf import AbstractSDF

if TYPE_CHECKING:
    from softgrip_jax._estimators import AbstractEstimator


class Status(enum.IntEnum):
    """Per-estimate outcome. Only ``OK`` estimates are ``valid``."""

    OK = 0
    NON_FINITE_INPUT = 1  #: a NaN or inf base, pose or parameter; joints are NaN
    BASE_OUTSIDE_SDF = 2  #: the base lies outside the SDF's grid (outside the image); joints are NaN
    INITIAL_OVERLAP = 3  #: the object already overlaps the open finger: the pose collides (reported as case none)
    ROOT_NOT_CONVERGED = 4  #: the first-contact root finder hit its iteration cap
    MECHANICS_NOT_CONVERGED = 5  #: the mechanics equilibrium missed its tolerances within its budget
    NON_FINITE_SDF = 6  #: the object's signed distances hold a NaN or inf (an SDFGrid cell, a vertex)
    PARAMETER_OUT_OF_RANGE = 7  #: a finger parameter outside its range (Theta not in [0, pi/2), L <= 0, ...)
    COORDINATE_OUT_OF_RANGE = 8  #: the base lies farther than MAX_COORDINATE_MM from the origin; joints are NaN
    NON_FINITE_RESULT = 9  #: the estimate (or its score) came out NaN or inf although its inputs looked usable


#: Largest base coordinate (mm) an estimate accepts: 100 m. Farther, float32 cannot resolve a link
#: (its spacing there is a fraction of a millimetre and grows with the distance), so such a pose is
#: a unit or data mistake, reported as ``Status.COORDINATE_OUT_OF_RANGE``.
MAX_COORDINATE_MM = 1.0e5


def input_problem(finger: FingerModel, sdf: AbstractSDF, origin: Array, estimator: AbstractEstimator) -> Int[Array, ""]:
    """The :class:`Status` of inputs that are finite but unusable (0 if none): a base beyond
    :data:`MAX_COORDINATE_MM`, a finger parameter out of its range (checked here because under
    ``jit``/``vmap`` the model's construction cannot see the values; the ``estimator`` checks the
    parameters only it reads), or non-finite SDF data."""
    from softgrip_jax._model import THETA_MAX

    in_range = (
        (finger.theta_entire >= 0) & (finger.theta_entire < THETA_MAX) & (finger.length > 0)
        & (finger.half_thickness >= 0)
    )
    in_range = in_range & estimator.finger_in_range(finger)
    near = jnp.all(jnp.abs(origin) <= MAX_COORDINATE_MM)
    return jnp.where(~near, Status.COORDINATE_OUT_OF_RANGE,
                     jnp.where(~in_range, Status.PARAMETER_OUT_OF_RANGE,
                               jnp.where(~sdf.all_finite(), Status.NON_FINITE_SDF, Status.OK))).astype(jnp.int32)


class Estimate(eqx.Module):
    """The estimated deformation of one finger (image-plane mm unless noted).

    Attributes:
        joints: (N+1, 2) joints from the base (index 0) to the tip (index N).
        psi: base rotation of the estimated shape (rad, in the finger's frame).
        turning: (N,) turning angles of the estimated shape (rad).
        case: the :class:`ContactCase` value. For ``Mechanics()``, read from the
            equilibrium: which contact areas carry force (runs of centreline stations within
            ``MechanicsConfig.contact_tol``; see :func:`solve_equilibrium`), the tip's (reaching
            within ``ContactConfig.tip_tolerance`` links of it), another, both or none.
        contact: the :class:`Contact` prediction, with its points in image-plane mm and its
            angles in the finger's frame. Its first touch (``s1``, ``p_g1``, ``p_o1``, ``l_g1``,
            ``n_g1``, ``theta_o1``) holds for both estimators: the finger closes freely until then.
            For ``Mechanics()``, ``contact.case`` is the equilibrium's case and ``p_o2`` the
            tip's foot on the object when the tip touches; the other fields describe the
            geometric construction of Fig. 8.
        valid: the inputs were usable and the pose is collision-free at the start.
        status: a :class:`Status` value saying why not, when not valid.
        residual: mm. For ``Mechanics()`` where the finger touches, how far the last
            Gauss-Newton step of the equilibrium solve moved the joints (to first order): converged
            estimates have it at most ``MechanicsConfig.step_tol``. 0 otherwise.
        event: the estimate is at or near an event of the closing path, where it jumps or turns
            steep with the pose: the tip carried contact force while the finger closed, then slid
            off the object (the finger snapped past it); or the equilibrium is near a fold (its
            ``sensitivity`` above ``MechanicsConfig.fold_sensitivity``: the tip is about to slide
            off, or a contact to appear). A planner should treat such poses as a boundary, where
            neighbouring poses may close into a different equilibrium. False for the geometric
            estimate.
        sensitivity: mm/mm. For ``Mechanics()`` where the finger touches, how far the tip
            moves per mm the base moves (the largest over directions, by implicit differentiation
            of the equilibrium): about 1 where the shape follows the base, growing without bound
            toward a fold. 1 for a finger that touches nothing (its tip follows the base rigidly);
            0 where not computed (the geometric estimate of a touching finger).
    """

    joints: Float[Array, "joints 2"]
    psi: Float[Array, ""]
    turning: Float[Array, " n"]
    case: Int[Array, ""]
    contact: Contact
    valid: Bool[Array, ""]
    status: Int[Array, ""]
    residual: Float[Array, ""]
    event: Bool[Array, ""]
    sensitivity: Float[Array, ""]

    @property
    def case_name(self) -> str | np.ndarray:
        """``case`` by name: ``"none"``, ``"tip"``, ``"tip_and_other"`` or ``"other"`` (an array of
        names for a batch; outside ``jit``)."""
        return code_names(self.case, ContactCase)

    @property
    def status_name(self) -> str | np.ndarray:
        """``status`` by name: ``"ok"``, ``"base_outside_sdf"``, ... (:class:`Status`, lower case; an
        array of names for a batch; outside ``jit``)."""
        return code_names(self.status, Status)


class Stage(eqx.Module):
    """The geometric estimate of one finger before it is placed in the image (finger frame).

    The first stage of :func:`estimate_in_frame`; batched code runs the mechanics solve on only
    the stages that :func:`needs_mechanics` selects, then :func:`finish` each.
    """

    frame: FingerFrame  #: the finger's frame, made harmless (zero) where the input is unusable
    finite: Bool[Array, ""]
    inside: Bool[Array, ""]
    contact: Contact
    psi: Float[Array, ""]
    turning: Float[Array, " n"]
    problem: Int[Array, ""]  #: :func:`input_problem`'s status


class Search(eqx.Module):
    """A finger placed by its frame and its first contact bracketed (:func:`search_contact`).

    Batched code refines the contact of only the searches that ``need_refining``
    (:func:`refine_search`), gives the others :func:`free_contact`, and completes each with
    :func:`stage_of`.
    """

    frame: FingerFrame  #: the finger's frame, made harmless (zero) where the input is unusable
    finite: Bool[Array, ""]
    inside: Bool[Array, ""]
    bracket: Bracket
    problem: Int[Array, ""]  #: :func:`input_problem`'s status

    @property
    def need_refining(self) -> Bool[Array, ""]:
        """A usable input whose first contact lies inside (0, Theta]."""
        return self.finite & self.inside & (self.problem == Status.OK) & self.bracket.needs_root


def _distance_in(sdf: AbstractSDF, frame: FingerFrame):
    return lambda q: sdf.distance(frame.to_world(q))


def _coarse_distance_in(sdf: AbstractSDF, frame: FingerFrame):
    return lambda q: sdf.coarse_distance(frame.to_world(q))


def search_contact(
    finger: FingerModel, sdf: AbstractSDF, frame: FingerFrame, config: ContactConfig, estimator: AbstractEstimator,
    rows: tuple[int, int] | None = None,
) -> Search:
    """Check the inputs, place the finger and bracket its first contact (eq. 5) over the coarse grid,
    or over its ``rows`` (:func:`bracket_contact`)."""
    finite = (
        jnp.all(jnp.isfinite(frame.origin)) & jnp.isfinite(frame.angle)
        & jnp.isfinite(finger.theta_entire) & jnp.isfinite(finger.length) & jnp.isfinite(finger.half_thickness)
    )
    finite = finite & estimator.finger_finite(finger)
    problem = input_problem(finger, sdf, jnp.where(finite, frame.origin, 0.0), estimator)
    inside = sdf.contains(jnp.where(finite, frame.origin, 0.0))
    usable = finite & inside & (problem != Status.COORDINATE_OUT_OF_RANGE)
    # An unusable input is replaced by a harmless one so it cannot produce NaN gradients;
    # its outputs are then overwritten with NaN.
    safe_frame = FingerFrame(
        origin=jnp.where(usable, frame.origin, 0.0),
        angle=jnp.where(usable, frame.angle, 0.0),
        handedness=frame.handedness,
    )
    return Search(frame=safe_frame, finite=finite, inside=inside,
                  bracket=bracket_contact(finger, _coarse_distance_in(sdf, safe_frame), config, rows), problem=problem)


def search_further(
    finger: FingerModel, sdf: AbstractSDF, search: Search, config: ContactConfig, rows: tuple[int, int]
) -> Bracket:
    """The bracket of a search over later ``rows`` of the coarse grid (the finger was free before)."""
    return bracket_contact(finger, _coarse_distance_in(sdf, search.frame), config, rows)


def refine_search(finger: FingerModel, sdf: AbstractSDF, search: Search, config: ContactConfig,
                  root: RootSearch | None = None) -> Contact:
    """The refined contact (eqs. 5-8, Fig. 8) of a search that ``need_refining``, from its finished
    ``root`` search (None: found here)."""
    # (A lookup without a cheaper coarse one would only look up the circle's chosen samples twice.)
    return refine_contact(finger, _distance_in(sdf, search.frame), search.bracket, config, root,
                          coarse=_coarse_distance_in(sdf, search.frame) if sdf.has_coarse_lookup else None)


def start_root_search(finger: FingerModel, sdf: AbstractSDF, search: Search, config: ContactConfig) -> RootSearch:
    """The first iterations of a search's first-contact root finder (:func:`start_root`)."""
    return start_root(finger, _distance_in(sdf, search.frame), search.bracket, config)


def finish_root_search(finger: FingerModel, sdf: AbstractSDF, search: Search, config: ContactConfig,
                       root: RootSearch) -> RootSearch:
    """A search's root finder continued until it converges (:func:`finish_root`)."""
    return finish_root(finger, _distance_in(sdf, search.frame), search.bracket, config, root)


def stage_of(finger: FingerModel, search: Search, refined: Contact) -> Stage:
    """The :class:`Stage` of a search: its ``refined`` contact where it needs refining, else
    :func:`free_contact`; and the deformation of the contact's case (eq. 9)."""
    need = search.need_refining
    contact = jax.tree_util.tree_map(lambda a, b: jnp.where(need, a, b), refined, free_contact(finger, search.bracket))
    psi, turning = case_shape(finger, contact)
    return Stage(frame=search.frame, finite=search.finite, inside=search.inside, contact=contact,
                 psi=psi, turning=turning, problem=search.problem)


def geometric_stage(
    finger: FingerModel, sdf: AbstractSDF, frame: FingerFrame, config: ContactConfig, estimator: AbstractEstimator
) -> Stage:
    """Contact prediction (eqs. 5-8) and the deformation of its case (eq. 9), in the finger frame.

    One finger: the refinement is computed whether needed or not. (Not behind a ``lax.cond``: under
    ``vmap`` both sides of a branch run anyway, and JAX then broadcasts every operand of the branch,
    the SDF grid included, to the batch size: out of memory for a vmapped estimate over 100,000
    bases.) Batched code refines only where needed, with the same result.
    """
    search = search_contact(finger, sdf, frame, config, estimator)
    return stage_of(finger, search, refine_search(finger, sdf, search, config))


def needs_mechanics(stage: Stage) -> Bool[Array, ""]:
    """Whether the mechanics solve can change this estimate: a usable input that touches the object.

    Without contact the spring chain rests in its PCC shape, which is the geometric estimate of
    case (a); an unusable or colliding input is reported as such either way.
    """
    c = stage.contact
    return (stage.finite & stage.inside & (stage.problem == Status.OK) & c.touches & ~c.initial_overlap
            & c.root_converged)


def finish(finger: FingerModel, stage: Stage, equilibrium: Equilibrium | None = None) -> Estimate:
    """The :class:`Estimate` of a stage, with the mechanics ``equilibrium`` where one applies.

    ``equilibrium`` is used where :func:`needs_mechanics` holds (None: the geometric estimate).
    """
    contact, psi, turning = stage.contact, stage.psi, stage.turning
    solved = jnp.array(True)
    residual = jnp.zeros((), psi.dtype)
    event = jnp.array(False)
    sensitivity = jnp.where(contact.touches, 0.0, 1.0).astype(psi.dtype)
    if equilibrium is not None:
        eq, use = equilibrium, needs_mechanics(stage)
        psi = jnp.where(use, eq.psi, psi)
        turning = jnp.where(use, eq.turning, turning)
        solved = eq.converged | ~use
        residual = jnp.where(use, eq.residual, residual).astype(psi.dtype)
        event = use & (eq.slid_off | eq.near_fold)
        sensitivity = jnp.where(use, eq.sensitivity, sensitivity).astype(psi.dtype)
        tip_touches = use & ((eq.case == ContactCase.TIP) | (eq.case == ContactCase.TIP_AND_OTHER))
        contact = eqx.tree_at(lambda c: (c.case, c.p_o2), contact,
                              (jnp.where(use, eq.case, contact.case),
                               jnp.where(tip_touches, eq.tip_foot, contact.p_o2)))
    joints_local = forward_kinematics(jnp.zeros(2, turning.dtype), psi, turning, finger.length)
    finite, inside = stage.finite, stage.inside
    far = stage.problem == Status.COORDINATE_OUT_OF_RANGE
    usable = finite & inside & ~far
    status = jnp.where(
        ~finite, Status.NON_FINITE_INPUT,
        jnp.where(far, Status.COORDINATE_OUT_OF_RANGE,
                  jnp.where(~inside, Status.BASE_OUTSIDE_SDF,
                            jnp.where(stage.problem != Status.OK, stage.problem,
                                      jnp.where(contact.initial_overlap, Status.INITIAL_OVERLAP,
                                                jnp.where(~contact.root_converged, Status.ROOT_NOT_CONVERGED,
                                                          jnp.where(~solved, Status.MECHANICS_NOT_CONVERGED,
                                                                    Status.OK)))))),
    ).astype(jnp.int32)

    def world(q):
        return jnp.where(usable, stage.frame.to_world(q), jnp.nan)

    contact = eqx.tree_at(
        lambda c: (c.p_g1, c.p_o1, c.p_o2), contact,
        (world(contact.p_g1), world(contact.p_o1), world(contact.p_o2)),
    )
    joints = world(joints_local)
    # A safety net: nothing reported valid holds a NaN or inf (the points the case uses).
    used = jnp.where(contact.case != ContactCase.NONE, contact.p_o1, 0.0)
    used2 = jnp.where(contact.case == ContactCase.TIP_AND_OTHER, contact.p_o2, 0.0)
    sound = jnp.all(jnp.isfinite(joints)) & jnp.all(jnp.isfinite(used)) & jnp.all(jnp.isfinite(used2))
    status = jnp.where((status == Status.OK) & ~sound, Status.NON_FINITE_RESULT, status).astype(jnp.int32)
    return Estimate(
        joints=joints, psi=psi, turning=turning, case=contact.case, contact=contact,
        valid=status == Status.OK, status=status, residual=residual, event=event,
        sensitivity=sensitivity,
    )


def mechanics_of(
    finger: FingerModel, sdf: AbstractSDF, stage: Stage, mechanics: MechanicsConfig, config: ContactConfig
) -> Equilibrium:
    """The spring chain's equilibrium reached by closing from a stage's first touch (the closing path).

    A stage whose input is unusable (a NaN Theta, a base outside the SDF or too far, NaN SDF
    data) is solved on a harmless stand-in instead (:func:`stand_in`): the nominal finger, its
    shape and contact zeroed, placed far outside the object. Its equilibrium is discarded by
    :func:`finish` anyway, but solving (and differentiating) the real one would feed NaN to the
    implicit adjoint's linear solve, which then fails the whole batch's gradient. So one bad row
    never costs the others theirs; its own gradient is zero or NaN.

    It is :func:`start_mechanics` with the whole iteration budget, then
    :func:`~softgrip_jax._mechanics.finish_equilibrium`. A batch splits the same iterations
    between :func:`start_mechanics` and :func:`~softgrip_jax._mechanics.continue_equilibrium`
    (``Mechanics.deform_batch``), to the same result.
    """
    finger, stage = stand_in(finger, stage)
    progress = start_mechanics(finger, sdf, stage, mechanics, config)
    return finish_equilibrium(finger, sdf, stage.frame, progress, mechanics, config)


def stand_in(finger: FingerModel, stage: Stage) -> tuple[FingerModel, Stage]:
    """The finger and stage that :func:`mechanics_of` solves: the stage's own, or the harmless
    stand-in of an unusable one (see there)."""
    bad = ~(stage.finite & stage.inside & (stage.problem == Status.OK))
    nominal = {"length": 50.0, "theta_entire": 0.5, "half_thickness": 1.0, "stiffness_ratio": 1.0,
               "base_compliance": 0.0}
    finger = eqx.tree_at(lambda f: tuple(getattr(f, name) for name in nominal), finger,
                         tuple(jnp.where(bad, jnp.asarray(value, finger.length.dtype), getattr(finger, name))
                               for name, value in nominal.items()))

    def harmless(x):
        if not eqx.is_inexact_array(x):
            return x
        return jnp.where(bad, jnp.zeros_like(x), x)

    stage = eqx.tree_at(lambda st: (st.contact, st.psi, st.turning), stage,
                        jax.tree_util.tree_map(harmless, (stage.contact, stage.psi, stage.turning)))
    far = jnp.full_like(stage.frame.origin, 2.0 * MAX_COORDINATE_MM)
    frame = eqx.tree_at(lambda f: f.origin, stage.frame, jnp.where(bad, far, stage.frame.origin))
    return finger, eqx.tree_at(lambda st: st.frame, stage, frame)


def start_mechanics(finger: FingerModel, sdf: AbstractSDF, stage: Stage, mechanics: MechanicsConfig,
                    config: ContactConfig, steps: int | None = None) -> Progress:
    """The closing path of :func:`mechanics_of` and at most ``steps`` iterations of its solve at
    Theta (None: all of them, ``mechanics.max_steps``), for a finger and stage of :func:`stand_in`.
    No derivatives."""
    s, psi, turning = closing_start(finger, stage.contact, config)
    return start_equilibrium(finger, sdf, stage.frame, psi, turning, mechanics, config, start_actuation=s,
                             steps=steps)
