"""Robust grasp quality: what calibration, the arm and vision do not know, sampled (Dex-Net's idea).

A candidate's quality (:mod:`softgrip_jax._quality`) holds for the nominal gripper, pose, friction
and object. Each of them is uncertain: the calibration's standard errors of each finger's Theta, L,
stiffness ratio and base compliance (``calibrate --fit`` reports them), the arm's pose error, the
friction coefficient, and the object contour that vision hands over (an outline grown or shrunk by a
few tenths of a millimetre). :class:`Uncertainty` says how much; :func:`perturbations` draws K
perturbations of all of them at once. The same K draws serve every candidate (common random
numbers, from a fixed ``seed``), so the ranking of two candidates is not decided by noise, and a
batch's results do not depend on its size or order. The expected quality ``quality_mean`` (0 for a
draw without force closure) and the probability of force closure ``p_closure`` are the means over
the K draws.

Or linearised (``Uncertainty(linear=True)``): every uncertain input is a standard variable z_j
(:data:`NOISE_SIZE` of them: :func:`perturbed` maps them to the inputs), and the signed closure
margin m (:func:`~softgrip_jax._quality.closure_margin`: the epsilon inside force closure, minus
the distance to it outside) is expanded to first order, m ~ m0 + sum_j (dm/dz_j) z_j: normal with
sigma^2 = sum_j (dm/dz_j)^2 Var z_j. Then (:func:`linear_moments`)

    p_closure = Phi(m0 / sigma),    quality_mean = E[max(m, 0)] = m0 Phi(m0 / sigma) + sigma phi(m0 / sigma).

One forward-mode derivative per input instead of K estimates; it is as good as the margin is
smooth over the spread of the inputs (a finger that starts or stops touching within it is not seen).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.scipy.stats import norm
from jaxtyping import Array, ArrayLike, Bool, Float

from softgrip_jax._errors import SoftgripError, check_number_fields
from softgrip_jax._model import FingerModel, Gripper
from softgrip_jax._sdf import AbstractSDF


#: :class:`Uncertainty`'s default ``reach`` (closure margin, in the quality's unit-force wrench
#: measure): draw the grasps in force closure only.
DEFAULT_REACH = 0.0


class Uncertainty(eqx.Module):
    """How uncertain each input of a grasp is (standard deviations unless noted; all run-time values
    but ``samples``).

    Attributes:
        samples: K perturbations per candidate (static: the shape of the computation).
        pose_mm: the arm's position error along x and y (mm).
        pose_rad: the arm's in-plane angle error (rad).
        mu_spread: the friction coefficient is drawn uniformly from ``mu (1 +- mu_spread)``.
        theta: each finger's Theta (rad), e.g. the fit's standard error ``left.theta_entire``.
        length: each finger's L (mm).
        stiffness_ratio: each finger's stiffness ratio (drawn as ``exp(N(0, s))`` times it:
            stays > 0).
        base_compliance: each finger's base compliance (kept >= 0).
        contour_mm: the object outline grown (> 0) or shrunk by this much (mm).
        seed: the draws' seed; the same seed gives the same draws for every candidate and call.
        reach: which candidates are drawn: those in force closure, and those whose nominal
            closure margin (``Score.margin``) is above ``-reach``; the others' ``quality_mean`` and
            ``p_closure`` are NaN (not drawn). The draws' cost follows the drawn candidates. 0 (the
            default): the grasps in closure, which robust quality ranks; ``inf``: every valid
            candidate. The margin does not see a contact that appears within the spread, so a
            grasp far outside closure by it may still close in some draws.
        linear: (static) instead of K draws, the first-order expansion of the closure margin
            (see the module docstring); ``samples`` and ``seed`` are then unused.
    """

    samples: int = eqx.field(static=True, default=16)
    pose_mm: float | Array = 0.5
    pose_rad: float | Array = 0.01
    mu_spread: float | Array = 0.2
    theta: float | Array = 0.0
    length: float | Array = 0.0
    stiffness_ratio: float | Array = 0.0
    base_compliance: float | Array = 0.0
    contour_mm: float | Array = 0.0
    seed: int | Array = 0
    reach: float | Array = DEFAULT_REACH
    linear: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        if not isinstance(self.linear, bool):
            raise SoftgripError(f"Uncertainty.linear must be True or False, got {self.linear!r}")
        if isinstance(self.samples, bool) or not isinstance(self.samples, int) or not 1 <= self.samples <= 4096:
            raise SoftgripError(f"Uncertainty.samples must be an integer in [1, 4096], got {self.samples!r}")
        check_number_fields(self, {"pose_mm": (0.0, 1e3), "pose_rad": (0.0, 1.0), "mu_spread": (0.0, 0.999),
                                   "theta": (0.0, 1.0), "length": (0.0, 1e3), "stiffness_ratio": (0.0, 10.0),
                                   "base_compliance": (0.0, 1e3), "contour_mm": (0.0, 1e3),
                                   "reach": (0.0, math.inf)})


    @classmethod
    def from_fit(cls, standard_errors: Mapping[str, float], gripper: Gripper, **settings) -> Uncertainty:
        """The calibration's part from a fit's standard errors (a profile's ``fit.standard_errors``:
        ``"left.theta_entire"`` rad, ``"right.stiffness_ratio"``, ``"left.base_compliance"``, ...),
        the larger of the two fingers' for each; ``settings`` give the other fields (and override).

        Example:
            >>> from softgrip_jax import FingerModel, Gripper
            >>> f = FingerModel(length=52.0, theta_entire=0.5, half_thickness=4.0, n_links=10, stiffness_ratio=2.0)
            >>> u = Uncertainty.from_fit({"left.theta_entire": 0.004, "right.theta_entire": 0.006,
            ...                           "left.stiffness_ratio": 0.2}, Gripper(f, f, 56.0), pose_mm=1.0)
            >>> round(u.theta, 4), round(u.stiffness_ratio, 4), u.pose_mm
            (0.006, 0.1, 1.0)
        """
        def largest(name: str, relative: bool = False) -> float:
            values = []
            for side in ("left", "right"):
                se = standard_errors.get(f"{side}.{name}")
                if se is None:
                    continue
                se = float(se)
                if not math.isfinite(se) or se < 0:
                    raise SoftgripError(f"standard error of {side}.{name} must be a finite number >= 0, got {se!r}")
                if relative:  # the ratio is drawn multiplicatively: its relative error
                    se /= float(getattr(gripper, side).stiffness_ratio)
                values.append(se)
            return max(values, default=0.0)

        fields = {"theta": largest("theta_entire"), "stiffness_ratio": largest("stiffness_ratio", relative=True),
                  "base_compliance": largest("base_compliance")}
        return cls(**{**fields, **settings})


class OffsetSDF(AbstractSDF):
    """An object grown by ``offset`` mm (shrunk when negative): its distance minus the offset."""

    base: AbstractSDF
    offset: Float[Array, ""]

    def distance(self, points: Float[Array, "*batch 2"]) -> Float[Array, "*batch"]:
        return self.base.distance(points) - self.offset

    def coarse_distance(self, points: Float[Array, "*batch 2"]) -> Float[Array, "*batch"]:
        return self.base.coarse_distance(points) - self.offset

    @property
    def has_coarse_lookup(self) -> bool:
        return self.base.has_coarse_lookup

    @property
    def largest_piece(self) -> int:  # type: ignore[override]
        return self.base.largest_piece

    @property
    def piece_overhead(self) -> int:  # type: ignore[override]
        return self.base.piece_overhead

    def contains(self, points: Float[Array, "*batch 2"]) -> Bool[Array, "*batch"]:
        return self.base.contains(points)

    def all_finite(self) -> Bool[Array, ""]:
        return self.base.all_finite() & jnp.isfinite(self.offset)

    def mass_properties(self) -> tuple[Float[Array, "2"], Float[Array, ""]]:
        centroid, rho = self.base.mass_properties()
        return centroid, rho + self.offset


#: The standard variables z of one draw: each finger's Theta, L, stiffness ratio and base compliance
#: (left 0-3, right 4-7), the pose's x, y and angle (8-10) and the contour (11), all N(0, 1); the
#: friction (12), uniform in [-1, 1].
NOISE_SIZE = 13
_UNIFORM = 12


class Perturbations(eqx.Module):
    """Draws of everything uncertain: leaves with a leading axis K (or none, for one draw)."""

    gripper: Gripper
    pose: Float[Array, "*k 3"]  #: added to the candidate's pose (mm, mm, rad)
    mu: Float[Array, "*k"]
    contour: Float[Array, "*k"]  #: mm the object is grown by


def _finger(finger: FingerModel, u: Uncertainty, noise: Float[Array, "4"]) -> FingerModel:
    return eqx.tree_at(
        lambda f: (f.theta_entire, f.length, f.stiffness_ratio, f.base_compliance), finger,
        (jnp.maximum(finger.theta_entire + u.theta * noise[0], 0.0),
         jnp.maximum(finger.length + u.length * noise[1], 1e-3),
         finger.stiffness_ratio * jnp.exp(u.stiffness_ratio * noise[2]),
         jnp.maximum(finger.base_compliance + u.base_compliance * noise[3], 0.0)))


def perturbed(gripper: Gripper, mu: Float[ArrayLike, ""], u: Uncertainty, z: Float[Array, "13"]) -> Perturbations:
    """The inputs of one draw from its standard variables ``z`` (:data:`NOISE_SIZE`,); z = 0 gives
    the nominal gripper, mu, a zero pose offset and contour."""
    dtype = gripper.base_separation.dtype
    pose = z[8:11] * jnp.stack([jnp.asarray(u.pose_mm, dtype)] * 2 + [jnp.asarray(u.pose_rad, dtype)])
    return Perturbations(
        gripper=Gripper(left=_finger(gripper.left, u, z[0:4]), right=_finger(gripper.right, u, z[4:8]),
                        base_separation=gripper.base_separation),
        pose=pose, mu=jnp.asarray(mu, dtype) * (1.0 + u.mu_spread * z[_UNIFORM]), contour=u.contour_mm * z[11])


def noise_deviations(dtype) -> Float[Array, "13"]:
    """The standard deviation of each standard variable z_j: 1, and 1 / sqrt(3) for the uniform one."""
    return jnp.ones(NOISE_SIZE, dtype).at[_UNIFORM].set(1.0 / math.sqrt(3.0))


def perturbations(gripper: Gripper, mu: Float[ArrayLike, ""], u: Uncertainty) -> Perturbations:
    """K = ``u.samples`` draws (common random numbers from ``u.seed``) of the gripper's calibration,
    the pose error, mu and the contour offset around the nominal ``gripper`` and ``mu``."""
    dtype = gripper.base_separation.dtype
    key = jax.random.key(jnp.asarray(u.seed, jnp.uint32))
    normal = jax.random.normal(key, (u.samples, NOISE_SIZE - 1), dtype)
    uniform = jax.random.uniform(jax.random.fold_in(key, 1), (u.samples, 1), dtype, -1.0, 1.0)
    return jax.vmap(lambda z: perturbed(gripper, mu, u, z))(jnp.concatenate([normal, uniform], axis=1))


def linear_moments(margin: Float[Array, "*b"],
                   tangents: Float[Array, "j *b"]) -> tuple[Float[Array, "*b"], Float[Array, "*b"]]:
    """``(quality_mean, p_closure)`` of a normal margin with mean ``margin`` and the standard
    deviation of the ``tangents`` (J, ...) (dm/dz_j times z_j's deviation, stacked on axis 0).

    Example (the margin one standard deviation above 0: P = Phi(1)):
        >>> import jax.numpy as jnp
        >>> q, p = linear_moments(jnp.array(0.1), jnp.array([0.06, 0.08]))
        >>> round(float(p), 4), round(float(q), 4)
        (0.8413, 0.1083)
    """
    sigma = jnp.sqrt(jnp.sum(tangents**2, axis=0))
    spread = sigma > 1e-12
    t = margin / jnp.where(spread, sigma, 1.0)
    p = jnp.where(spread, norm.cdf(t), (margin > 0).astype(margin.dtype))
    mean = jnp.where(spread, margin * norm.cdf(t) + sigma * norm.pdf(t),
                     jnp.maximum(margin, 0.0))
    return mean, p
