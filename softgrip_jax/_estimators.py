"""The deformation estimators as objects: what turns a finger's predicted contact into its shape.

Every estimate runs the same contact prediction (eqs. 5-8) and the paper's eq. 9 on it (the
:class:`~softgrip_jax._stage.Stage` of one finger, in its own frame); an estimator then says
what the finger's shape is, as solvers do in optimistix and diffrax. It is an ``equinox.Module``
with only static fields, passed as ``estimator=`` to every estimate, score, refine and calibration
function and to their jitted internals as a static argument: equal estimators (same class, equal
settings) are equal and hash alike, so they share compiled programs and exported ones.

* :class:`Geometric`: the paper's eq. 9, the deformation of the predicted contact case;
* :class:`Mechanics`: the spring-joint chain at equilibrium against the object (the paper's ref.
  [16], :mod:`softgrip_jax._mechanics`), solved along the closing path with ``config``'s settings
  wherever the finger touches. The default.

A new estimator is one subclass of :class:`AbstractEstimator`: a ``name`` and a :meth:`deform`,
optionally its own checks of the finger's parameters and a batched :meth:`deform_batch`.
:func:`as_estimator` turns an estimate's name (the command line's ``--method``, a profile's
recorded estimate) into an estimator, in one place; every function takes the estimator itself.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool

from softgrip_jax._contact import ContactConfig
from softgrip_jax._errors import SoftgripError
from softgrip_jax._gather import where_needed
from softgrip_jax._mechanics import (DEFAULT_METHOD, METHODS, MechanicsConfig, check_method, closing_start,
                                     continue_equilibrium, finish_equilibrium, path_increments)
from softgrip_jax._model import FingerModel
from softgrip_jax._sdf import AbstractSDF
from softgrip_jax._stage import Estimate, Stage, finish, mechanics_of, needs_mechanics, stand_in, start_mechanics

#: A chunk's touching candidates are solved for their equilibrium in groups of this many: under
#: vmap a group iterates until its slowest element is done (the longest closing path: groups are
#: ordered by it), so small groups keep few lanes waiting, and large ones launch fewer kernels per
#: finger (measured by benchmarks/compare_mechanics.py).
_MECHANICS_GROUP = 256

#: The solve's iterations every touching finger takes in its group (most converge in two: the
#: convergence test wants two small steps in a row), and the size of the groups in which the few
#: that need more continue to the budget, ``MechanicsConfig.max_steps``.
_FIRST_STEPS = 2
_LATE_GROUP = 16

#: The equilibria's derivatives, case and sensitivity (a fixed amount of work per finger, no loop
#: that waits on a slow lane) are computed in groups of this many: fewer, larger kernels.
_FINISH_GROUP = 512


class AbstractEstimator(eqx.Module):
    """How a finger deforms once its first contact is predicted: the interface of an estimator.

    Subclasses set the class variable ``name`` (the estimate's name in JSON documents, profiles
    and exported programs' keys) and implement :meth:`deform`. All their fields must be static
    (``eqx.field(static=True)``) and hashable: an estimator is a static argument of jitted
    functions, and equal estimators share their compiled programs.

    Everything is in the finger's frame (mm, rad; base at the origin, hanging toward +y, curling
    toward +x) until :func:`~softgrip_jax._stage.finish` places the shape in the image
    plane; :meth:`deform` returns what ``finish`` returns.
    """

    name: eqx.AbstractClassVar[str]
    #: XLA:CPU compile options of the batch programs that run this estimator, over
    #: :data:`softgrip_jax._compile.CPU_OPTIONS` (chosen by measurement: ``benchmarks/bench_emitters.py``).
    cpu_options: ClassVar[dict[str, object]] = {}

    def __check_init__(self):
        loose = [f.name for f in dataclasses.fields(self) if not f.metadata.get("static", False)]
        if loose:
            raise SoftgripError(f"{type(self).__name__}: every field of an estimator must be static "
                                f"(eqx.field(static=True)) and hashable, so that equal estimators share a "
                                f"compiled program; not static: {', '.join(loose)}")

    def finger_finite(self, finger: FingerModel) -> Bool[Array, ""]:
        """Whether the finger parameters this estimator reads beyond L, Theta and r are finite
        (else ``Status.NON_FINITE_INPUT``). Default: it reads no others."""
        return jnp.array(True)

    def finger_in_range(self, finger: FingerModel) -> Bool[Array, ""]:
        """Whether those parameters lie in their ranges (else ``Status.PARAMETER_OUT_OF_RANGE``).
        Checked at run time, since under ``jit``/``vmap`` the model's construction cannot see values."""
        return jnp.array(True)

    @abc.abstractmethod
    def deform(self, finger: FingerModel, sdf: AbstractSDF, stage: Stage, config: ContactConfig) -> Estimate:
        """The :class:`~softgrip_jax._stage.Estimate` of one finger from its ``stage``.

        Args:
            finger: the finger model (mm, rad).
            sdf: the object, in image-plane mm.
            stage: the finger's contact prediction (eqs. 5-8) and eq. 9's shape of its case
                (``stage.psi`` rad, ``stage.turning`` (N,) rad), in the finger's frame
                ``stage.frame``; see :class:`~softgrip_jax._stage.Stage`.
            config: the contact prediction's settings.

        Returns:
            the estimate, usually ``finish(finger, stage_with_its_shape)``: joints (N+1, 2) in
            image-plane mm, case, contact, validity and status.
        """

    def deform_batch(self, finger: FingerModel, sdf: AbstractSDF, stages: Stage, config: ContactConfig) -> Estimate:
        """:meth:`deform` of a chunk of stages (every leaf with a leading axis B); an estimate with
        that leading axis. Default: ``jax.vmap`` of :meth:`deform`. An estimator whose work only some
        fingers need overrides it (every element's result must not depend on the others)."""
        return jax.vmap(lambda st: self.deform(finger, sdf, st, config))(stages)


class Geometric(AbstractEstimator):
    """The paper's estimate (eq. 9): the deformation of the predicted contact case, as rules.

    Example:
        >>> import jax, jax.numpy as jnp
        >>> from softgrip_jax import FingerModel, PolygonSDF, estimate
        >>> finger = FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=10)
        >>> est = jax.jit(estimate)(finger, PolygonSDF.regular((20.0, 30.0), 8.0), jnp.zeros(2),
        ...                         estimator=Geometric())
        >>> est.case_name, est.joints.shape  # joints: (N+1, 2) mm
        ('other', (11, 2))
    """

    name: ClassVar[str] = "geometric"
    #: XLA's fusion emitters: the geometric batch programs run faster with them and compile about as fast.
    cpu_options: ClassVar[dict[str, object]] = {"xla_cpu_use_fusion_emitters": True}

    def deform(self, finger: FingerModel, sdf: AbstractSDF, stage: Stage, config: ContactConfig) -> Estimate:
        return finish(finger, stage)


class Mechanics(AbstractEstimator):
    """The spring-joint chain at equilibrium against the object (the paper's ref. [16]), reached by
    closing from the first touch, with the solver settings ``config``
    (:class:`~softgrip_jax.MechanicsConfig`). A finger that touches nothing keeps its PCC shape.

    It reads the finger's ``stiffness_ratio`` (> 0) and ``base_compliance`` (>= 0). Batched, it
    solves only the fingers that touch, in groups of 256 ordered by their closing path's increments
    (the few whose solve needs more than two iterations continue in groups of 16).

    Example:
        >>> import jax, jax.numpy as jnp
        >>> from softgrip_jax import FingerModel, MechanicsConfig, PolygonSDF, estimate
        >>> finger = FingerModel(52.0, 0.55, 4.0, 20, stiffness_ratio=2.0)
        >>> disc = PolygonSDF.regular((24.0, 30.0), 10.0, 64)
        >>> est = jax.jit(estimate)(finger, disc, jnp.zeros(2), estimator=Mechanics(MechanicsConfig(max_steps=8)))
        >>> est.case_name, bool(est.valid)
        ('other', True)
        >>> Mechanics(MechanicsConfig(max_steps=8)) == Mechanics(MechanicsConfig(max_steps=8))
        True
    """

    name: ClassVar[str] = "mechanics"
    #: XLA's fusion emitters and no intra-op threads: the batch programs run faster with both, for a
    #: longer first compile (:mod:`softgrip_jax._compile`).
    cpu_options: ClassVar[dict[str, object]] = {"xla_cpu_multi_thread_eigen": False,
                                                "xla_cpu_use_fusion_emitters": True}
    config: MechanicsConfig = eqx.field(static=True, default=MechanicsConfig())

    def __check_init__(self):
        if not isinstance(self.config, MechanicsConfig):
            raise SoftgripError(f"Mechanics(config) takes a softgrip_jax.MechanicsConfig, got "
                                f"{type(self.config).__name__}")

    def finger_finite(self, finger: FingerModel) -> Bool[Array, ""]:
        return jnp.isfinite(finger.stiffness_ratio) & jnp.isfinite(finger.base_compliance)

    def finger_in_range(self, finger: FingerModel) -> Bool[Array, ""]:
        return (finger.stiffness_ratio > 0) & (finger.base_compliance >= 0)

    def deform(self, finger: FingerModel, sdf: AbstractSDF, stage: Stage, config: ContactConfig) -> Estimate:
        return finish(finger, stage, mechanics_of(finger, sdf, stage, self.config, config))

    def deform_batch(self, finger: FingerModel, sdf: AbstractSDF, stages: Stage, config: ContactConfig) -> Estimate:
        need = jax.vmap(needs_mechanics)(stages)
        # Ordered by the closing path's increments, so that short paths do not wait on long ones.
        increments = jax.vmap(lambda st: path_increments(finger, closing_start(finger, st.contact, config)[0],
                                                         self.config))(stages)
        # The closing path and the solve's first iterations in groups; the few fingers whose solve
        # goes on past them continue in small groups of their own (under vmap a group iterates until
        # its slowest element is done); then every solved finger's equilibrium and derivatives.
        mech = self.config
        solved = jax.vmap(lambda st: stand_in(finger, st))(stages)  # (fingers, stages), once
        progress = where_needed(lambda fs: start_mechanics(fs[0], sdf, fs[1], mech, config, _FIRST_STEPS), need,
                                solved, kinds=increments, n_kinds=mech.path_steps + 1, group_size=_MECHANICS_GROUP)
        late = need & ~progress.done
        later = where_needed(lambda fsp: continue_equilibrium(fsp[0], sdf, fsp[1].frame, fsp[2], mech), late,
                             (*solved, progress), group_size=_LATE_GROUP)
        progress = jax.tree_util.tree_map(lambda a, b: jnp.where(late.reshape(late.shape + (1,) * (a.ndim - 1)), a, b),
                                          later, progress)
        eq = where_needed(lambda fsp: finish_equilibrium(fsp[0], sdf, fsp[1].frame, fsp[2], mech, config), need,
                          (*solved, progress), group_size=_FINISH_GROUP)
        return jax.vmap(lambda st, e: finish(finger, st, e))(stages, eq)


def as_estimator(estimator: object = None, method: object = None, mechanics: object = None) -> AbstractEstimator:
    """The estimator a function was given (``estimator`` itself, checked), or the one a name
    gives (``method="geometric"``: :class:`Geometric`; ``method="mechanics"``:
    ``Mechanics(mechanics)``, as the command line's ``--method`` and a profile name them), else the
    default (``DEFAULT_METHOD``, "mechanics": ``Mechanics(mechanics or MechanicsConfig())``).

    It takes any values and checks them itself (it is where a user's arguments arrive).
    ``mechanics`` alone (no ``method``) sets the default's solver settings; with
    ``method="geometric"`` it is ignored. Raises :class:`SoftgripError` when ``estimator`` is given
    together with ``method`` or ``mechanics``, when ``estimator`` is not an
    :class:`AbstractEstimator` (a name says which one to pass), or when ``method`` names no
    estimate.

    Example:
        >>> as_estimator(method="geometric") == Geometric(), as_estimator() == Mechanics()
        (True, True)
    """
    if estimator is not None:
        if method is not None or mechanics is not None:
            given = " and ".join(f"{k}=" for k, v in (("method", method), ("mechanics", mechanics)) if v is not None)
            raise SoftgripError(f"give either estimator= or the older {given}, not both "
                                f"(e.g. estimator=Mechanics(MechanicsConfig(...)))")
        if isinstance(estimator, str) and estimator in METHODS:
            raise SoftgripError(f"estimator={estimator!r}: pass the estimator itself, "
                                f"{'Geometric()' if estimator == 'geometric' else 'Mechanics()'} (softgrip_jax), "
                                f"or as_estimator(method={estimator!r})")
        if not isinstance(estimator, AbstractEstimator):
            raise SoftgripError(f"estimator must be a softgrip_jax estimator (Geometric(), Mechanics(config), or "
                                f"another AbstractEstimator), got {type(estimator).__name__}")
        return estimator
    if mechanics is not None and not isinstance(mechanics, MechanicsConfig):
        raise SoftgripError(f"mechanics must be a softgrip_jax.MechanicsConfig, got {type(mechanics).__name__}")
    name = DEFAULT_METHOD if method is None else method
    check_method(name)
    if name == "geometric":
        return Geometric()
    return Mechanics(MechanicsConfig() if mechanics is None else mechanics)


#: The estimator every function and command uses unless told otherwise (``DEFAULT_METHOD`` by name).
DEFAULT_ESTIMATOR: AbstractEstimator = as_estimator()
