"""The mechanics estimate: the N-link chain with spring joints at equilibrium.

Model. The finger is the chain of :mod:`softgrip_jax._kinematics`: base P_0, base direction psi, turning angles
delta_k (link k, of length h = L/N, points at psi + sum_{j<k} delta_j + delta_k / 2). Link k is the
chord of a short arc that turns by delta_k, so its curvature is delta_k / h and its bending energy
k_k (delta_k - delta0)^2 / (2 h), with the rest turning delta0 = 2 Theta / N of the calibrated,
untouched closure (eqs. 1-3): without an object the equilibrium *is* the PCC shape, whatever the
stiffness. Energies are in units of mean(k) / L (dimensionless, as the observed-closure rod
reports them):

    E = sum_k k_k N (delta_k - delta0)^2 / 2  +  psi^2 / (2 c)  +  contact.

The bending stiffness k_k = 2 / (rho + 1) (rho + (1 - rho) s_k / L), sampled at the link middles
s_k = (k + 1/2) h, is linear along the finger, ``stiffness_ratio`` rho times stiffer at the base
than at the tip, with mean 1. The base spring has compliance ``base_compliance`` c in units of the
whole finger's bending compliance L / mean(k) (c = 1: the base turns as much under a moment as the
whole finger bends); c = 0 clamps the base (psi = 0). These are the parametrisations of the
observed-closure rod (``synthetic.rod``, a test-support package of the source tree), so a
calibration against it can recover rho and c; both are ``FingerModel`` fields and the estimate is
differentiable in them.

Contact is frictionless and quasi-static: a penalty mu / 2 (max(0, r - d) / L)^2 on each of
``stations_per_link`` centreline stations per link and the tip, with d the object's signed distance
(mm) and r the half-thickness. A station then sinks about (contact force) L / mu into the finger's
thickness: 0.005 to 0.03 mm at the default mu = 1e4.

Solve. Least squares in the scaled variables z_k = sqrt(k_k N) (delta_k - delta0) and
u = psi / sqrt(c + 1e-8) (the floor keeps a clamped base differentiable in c): residuals
(z, u, sqrt(mu) max(0, r - d) / L), half of whose squared norm is E, and whose spring block has the
identity as its Jacobian. A Gauss-Newton step then needs only the rows of the few stations in
contact: with the K = ``active_rows`` least clear stations, the Woodbury identity turns the
(N+1) x (N+1) system into a K x K one per candidate (exact while at most K stations touch; a convex
object touches a clamped elastic chain at a few points). Around that core, the step keeps stations
that touch in the model (within 0.05 mm) as "end on the surface", drops those the model would pull
out of the object, corrects the step for the contacts' curvature (below), stops short where a
station outside the model would enter the object, halves a step that undoes the previous one, and
turns no angle by more than ``max_turn``. It is an optimistix
least-squares solver (:class:`ChainGaussNewton`), so ``optimistix.least_squares`` supplies the
iteration budget (``max_steps``), a per-candidate result (``throw=False``: a candidate that misses
its tolerances gets ``Status.MECHANICS_NOT_CONVERGED``) and derivatives by implicit
differentiation of the optimality condition: the equilibrium's derivatives in Theta, L, r, rho, c,
the base pose and the object never go through the iterations.

The Gauss-Newton model leaves out the curvature of the contact terms (the object's curvature under
a pressed station, and the force turning the links it acts through). Near a fold of the
equilibrium (a held tip about to slide off a convex object) that curvature cancels most of the
springs' stiffness in one direction, the tip's slide along the surface, and the model's step there
is a small fraction of the way to the equilibrium; just past the fold, where the held equilibrium
has ceased to exist but the energy still falls only slowly along the slide, the bare model crawls
through that slow region for more steps than the budget holds, and a pose just before a slide-off
came out not converged. So each step minimises the model with that curvature added, by a few
conjugate-gradient iterations preconditioned with the Gauss-Newton model (whose first iterate is
the Gauss-Newton step stretched by the curvature along it), truncated where the curvature turns
negative (past the fold: the step then goes a bounded multiple of the Gauss-Newton step along the
slide, and the solve reaches the equilibrium after the slide-off). Where the contacts do not bend
the energy this is the Gauss-Newton step. The fixed point and the equilibrium are unchanged; the
convergence test reads the corrected step, the distance to the equilibrium with the curvature
included. The closing path's increments (below) take the plain Gauss-Newton step: they only carry
the shape along its branch to the next increment, and the correction costs about as much as the
rest of a step; the solve at Theta, which decides convergence, takes the corrected one. From the
converged point one full Newton step, with the energy's whole Hessian, finishes the solve where it
is small and lowers the energy (:func:`_polish`): what the few conjugate
directions leave out would otherwise stop the solve short by a pose-dependent amount.

The trust region. Past a fold, and where a tip slides over a corner (a star's point, a polygon's
corner), even the corrected model is poor a short way from where it was made: its steps raised
the energy tenfold and more, and the solve wandered between far-apart shapes until its budget was
spent (``mechanics_not_converged``). So the solve at Theta keeps the energy falling: each step's
energy is compared with the reduction the model predicted for it (the penalty's hinge linearised
over the step's K stations, plus the curvature term), one iteration late, when the energy at the
step's end comes with the next step; a step that achieved less than _ACCEPT of its prediction is
undone and the region (the curvature correction's stretch, in Gauss-Newton steps) shrinks to a
quarter of that step, one that achieved more than three quarters lets it grow back, up to
_STRETCH_MAX (Nocedal & Wright, *Numerical Optimization*, Algorithm 4.1, with Steihaug's
conjugate gradients). Steps within ``step_tol`` are kept whatever their energy (float32 rounding
of the stiff penalty). An undone step spends an iteration of the budget and never counts toward
convergence. Where every step is accepted, as on an ordinary contact, the solve is the plain one.

The closing path. A contact problem of this kind has several equilibria (a tip held on the object,
or the finger pressed along its middle after the tip slid past); the estimate is the one the finger
reaches by closing. Model and assumptions: the actuation is ramped quasi-statically from the open
finger (0) to Theta, the rest turning 2 s / N following the actuation s; contact is frictionless
(the tip slides along the surface); inertia is neglected (a snap-through lands in the equilibrium
the next increments find from the shape before it). Until the first touch s1 (the contact sweep,
eqs. 5-8) the chain closes freely through its PCC shapes, so the path costs nothing there and
starts at the PCC shape of s1 (:func:`closing_start`); from there the actuation rises to Theta in
at most ``path_steps`` increments of at most ``path_step`` rad, each followed by
``path_iterations`` Gauss-Newton steps warm-started from the last shape
(:func:`follow_closing_path`), and the least-squares solve above finishes at Theta. The path
carries no derivative: the equilibrium's derivatives come from implicit differentiation at Theta.
When the tip carried force along the path but does not at the end, the tip slid off the object
(``Equilibrium.slid_off``, the estimate's ``event``): near such poses the equilibrium may jump with
the pose. Near a fold of the equilibrium (a held tip about to slide off) the estimate is still
continuous but steep: :func:`tip_sensitivity` measures how far the tip moves per mm of base motion
(implicit differentiation with the energy's full Hessian, whose curvature terms the Gauss-Newton
model leaves out), and ``Equilibrium.near_fold`` flags it above ``fold_sensitivity``. Where the
finger does not touch the object at all, the equilibrium is the PCC shape and batched code skips
the solve (:mod:`softgrip_jax._batch`).

Batch independence: the path's increments and the solve's iterations are per-element loops
(``lax.while_loop`` under ``vmap`` holds each finished element), so an element's estimate does
not depend on which other elements share its batch.

Beyond the paper: the paper's own first modelling approach, the spring-joint chain of its ref.
[16], at equilibrium against the object with a stiffness profile and a base spring, in place of
the geometric rules of eq. 9. Against a clamped elastic rod it lands within hundredths of a
millimetre where eq. 9's cases (b) and (c) miss the tip by a millimetre or so.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from softgrip_jax._contact import Contact, ContactCase, ContactConfig
from softgrip_jax._errors import SoftgripError
from softgrip_jax._frames import FingerFrame
from softgrip_jax._kinematics import chain_points, pcc_turning
from softgrip_jax._model import FingerModel
from softgrip_jax._sdf import AbstractSDF, surface_point

#: The deformation estimates, by name (the ``method`` argument of the estimate functions).
METHODS: tuple[str, ...] = ("geometric", "mechanics")

#: The estimate every function and command uses when ``method`` is not given: the one the accuracy
#: harness shows is more accurate at an acceptable speed (benchmarks/RESULTS.md, issue 7).
DEFAULT_METHOD: str = "mechanics"

#: Compliance floor: keeps psi = sqrt(c + floor) u differentiable at a clamped base (c = 0), where
#: it lets the base turn by 1e-8 of the base moment (nanoradians).
_COMPLIANCE_FLOOR = 1e-8

#: mm: a station this close to the object keeps its row in the Newton step (see _newton_step).
_GLUE_MM = 0.05

#: The curvature-corrected step goes at most this many times as far as the Gauss-Newton step
#: (in the norm of its model), in at most _CG_ITERATIONS conjugate directions (see _with_curvature).
_STRETCH_MAX = 16.0
_CG_ITERATIONS = 3

#: The trust region (see ChainGaussNewton.step): a step is kept when the energy falls by at least
#: _ACCEPT of the reduction the model predicted, or changes by no more than _ENERGY_NOISE of itself
#: (float32 rounding near the equilibrium); the region shrinks to no less than _STRETCH_MIN
#: Gauss-Newton steps.
_ACCEPT = 0.1
_ENERGY_NOISE = 1e-6
_STRETCH_MIN = 1e-3


def check_method(method: object, where: str = "method") -> None:
    """Raise a :class:`SoftgripError` unless ``method`` names an estimate."""
    if not isinstance(method, str) or method not in METHODS:
        raise SoftgripError(f"{where} must be one of {', '.join(repr(m) for m in METHODS)}, got {method!r}")


class MechanicsConfig(eqx.Module):
    """Settings of the mechanics estimate's solver (all static: changing one recompiles).

    Attributes:
        max_steps: Gauss-Newton iterations at most (a step the trust region undoes counts). A
            candidate that has not met ``step_tol`` and ``contact_tol`` by then gets
            ``Status.MECHANICS_NOT_CONVERGED``.
        stations_per_link: centreline stations per link that may not enter the object (plus the
            tip); the chain may cut a sharp corner between two stations by up to about
            (L / (N stations_per_link))^2 / (8 r).
        penalty: contact penalty weight mu (dimensionless; penetration in units of L). A station
            sinks about force * L / mu mm into the finger's thickness.
        active_rows: the least clear stations that enter each Newton step (K); the step is exact
            while at most K stations touch at once.
        contact_tol: mm. Stations within r + contact_tol of the object form the contact areas
            (runs of consecutive stations); an area touches when one of its stations carries
            contact force, and the case says which areas touch (see :func:`solve_equilibrium`).
            An equilibrium deeper than contact_tol inside r is not converged.
        step_tol: mm. Converged when two steps in a row (before they are shortened) move no joint
            by more than this (to first order).
        max_turn: rad. A step changes no turning angle (or psi) by more than this.
        path_step: rad. The closing path raises the actuation from first touch to Theta in
            increments of at most this (fewer steps where less actuation remains after the touch).
        path_steps: the most increments of the closing path (a longer remainder takes larger ones).
        path_iterations: Gauss-Newton iterations at each increment of the closing path.
        fold_sensitivity: mm/mm. An equilibrium whose tip moves more than this per mm of base
            motion is near a fold (the tip about to slide off, a contact about to appear) and is
            flagged as an event (see ``Estimate.event``); an ordinary contact moves the tip about
            as far as the base.

    Example:
        >>> import jax.numpy as jnp
        >>> from softgrip_jax import FingerModel, Mechanics, PolygonSDF, estimate
        >>> finger = FingerModel(52.0, 0.55, 4.0, 20, stiffness_ratio=2.0)
        >>> disc = PolygonSDF.regular((24.0, 30.0), 10.0, 64)
        >>> import jax
        >>> run = jax.jit(estimate)  # compiles once per estimator; op by op is slower
        >>> est = run(finger, disc, jnp.zeros(2), estimator=Mechanics(MechanicsConfig(max_steps=8)))
        >>> est.case_name, bool(est.valid)
        ('other', True)
    """

    max_steps: int = eqx.field(static=True, default=24)
    stations_per_link: int = eqx.field(static=True, default=3)
    penalty: float = eqx.field(static=True, default=1e4)
    active_rows: int = eqx.field(static=True, default=6)
    contact_tol: float = eqx.field(static=True, default=0.05)
    step_tol: float = eqx.field(static=True, default=0.01)
    max_turn: float = eqx.field(static=True, default=0.3)
    path_step: float = eqx.field(static=True, default=0.1)
    path_steps: int = eqx.field(static=True, default=8)
    path_iterations: int = eqx.field(static=True, default=2)
    fold_sensitivity: float = eqx.field(static=True, default=5.0)

    def __check_init__(self):
        for name, low in (("max_steps", 1), ("stations_per_link", 1), ("active_rows", 1), ("path_steps", 1),
                          ("path_iterations", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise SoftgripError(f"MechanicsConfig.{name} must be an integer >= {low}, got {value!r}")
        for name in ("penalty", "contact_tol", "step_tol", "max_turn", "path_step", "fold_sensitivity"):
            value = getattr(self, name)
            ok = isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0 and value < float("inf")
            if not ok:
                raise SoftgripError(f"MechanicsConfig.{name} must be a finite number > 0, got {value!r}")


# ---------------------------------------------------------------------------------------------
# The model


def link_stiffness(finger: FingerModel) -> Float[Array, " n"]:
    """Bending stiffness of each link at its middle, in units of the mean: linear along the finger,
    ``stiffness_ratio`` times stiffer at the base than at the tip, mean 1.

    Example:
        >>> from softgrip_jax import FingerModel
        >>> [round(float(k), 3) for k in link_stiffness(FingerModel(52.0, 0.5, 4.0, 4, stiffness_ratio=3.0))]
        [1.375, 1.125, 0.875, 0.625]
    """
    n, rho = finger.n_links, finger.stiffness_ratio
    position = (jnp.arange(n, dtype=finger.length.dtype) + 0.5) / n
    return 2.0 / (rho + 1.0) * (rho + (1.0 - rho) * position)


class _Problem(eqx.Module):
    """One finger's equilibrium problem, in its own frame (base at the origin)."""

    finger: FingerModel
    sdf: AbstractSDF
    frame: FingerFrame
    config: MechanicsConfig = eqx.field(static=True)

    def distance(self, q):
        return self.sdf.distance(self.frame.to_world(q))

    @property
    def n_stations(self) -> int:
        """M = N stations_per_link + 1 centreline stations (see :meth:`stations`)."""
        return self.finger.n_links * self.config.stations_per_link + 1

    def scales(self):
        """(N,) d delta / d z and () d psi / d u."""
        f = self.finger
        per_link = jax.lax.rsqrt(link_stiffness(f) * f.n_links)
        return per_link, jnp.sqrt(f.base_compliance + _COMPLIANCE_FLOOR)

    def shape(self, y):
        """``(psi, turning)`` of the variables y = (z_0 .. z_{N-1}, u)."""
        f = self.finger
        per_link, base = self.scales()
        rest = pcc_turning(f.theta_entire, f.n_links)
        return base * y[-1], rest + per_link * y[:-1]

    def variables(self, psi, turning):
        """Inverse of :meth:`shape`."""
        f = self.finger
        per_link, base = self.scales()
        rest = pcc_turning(f.theta_entire, f.n_links)
        return jnp.concatenate([(turning - rest) / per_link, (psi / base)[None]])

    def stations(self, y):
        """Joints (N+1, 2) and centreline stations (M, 2), M = N stations_per_link + 1, in mm, in
        the finger's frame: the chain of :func:`~softgrip_jax._kinematics.chain_points`."""
        psi, turning = self.shape(y)
        joints, points, _ = chain_points(jnp.zeros(2, turning.dtype), psi, turning, self.finger.length,
                                         self.config.stations_per_link)
        return joints, points

    def residuals(self, y, _args=None):
        """(z, u, sqrt(mu) max(0, r - d) / L): half its squared norm is the energy."""
        f = self.finger
        _, points = self.stations(y)
        weight = jnp.sqrt(jnp.asarray(self.config.penalty, y.dtype)) / f.length
        contact = weight * jnp.maximum(f.half_thickness - self.distance(points), 0.0)
        return jnp.concatenate([y, contact])


# Small products written as broadcast, multiply and sum: under ``vmap`` XLA:CPU runs a batched
# ``dot`` of tiny matrices (K x N+1 with K = 6) as one small matrix product per element, while the
# same product as elementwise arithmetic fuses with its neighbours and vectorises across the batch
# (benchmarks/RESULTS.md, "The mechanics' batch programs").


def _matvec(a: Float[Array, "k n"], x: Float[Array, " n"]) -> Float[Array, " k"]:
    """a @ x."""
    return jnp.sum(a * x[None, :], axis=-1)


def _rmatvec(a: Float[Array, "k n"], v: Float[Array, " k"]) -> Float[Array, " n"]:
    """a.T @ v."""
    return jnp.sum(a * v[:, None], axis=0)


def _inner(x: Float[Array, " n"], y: Float[Array, " n"]) -> Float[Array, ""]:
    """x . y."""
    return jnp.sum(x * y)


def _gram(a: Float[Array, "k n"]) -> Float[Array, "k k"]:
    """a @ a.T."""
    return jnp.sum(a[:, None, :] * a[None, :, :], axis=-1)


def _residual_fn(y, problem: _Problem):
    return problem.residuals(y)


def _cross(a, b):
    """a_x b_y - a_y b_x, broadcasting."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _cholesky(s: Float[Array, "k k"]) -> list:
    """The lower Cholesky factor of a small symmetric positive-definite s, unrolled (fuses under
    vmap), as nested lists of scalars for :func:`_cholesky_solve`."""
    k = s.shape[0]
    low: list[list[Any]] = [[None] * k for _ in range(k)]
    for j in range(k):
        diag = s[j, j] - sum((low[j][p] ** 2 for p in range(j)), jnp.zeros((), s.dtype))
        low[j][j] = jnp.sqrt(jnp.maximum(diag, 1e-12))
        for i in range(j + 1, k):
            off = s[i, j] - sum((low[i][p] * low[j][p] for p in range(j)), jnp.zeros((), s.dtype))
            low[i][j] = off / low[j][j]
    return low


def _cholesky_solve(low: list, b: Float[Array, " k"]) -> Float[Array, " k"]:
    """Solve s x = b with the factor of :func:`_cholesky`."""
    k = len(low)
    fwd: list[Array] = []
    for i in range(k):
        fwd.append((b[i] - sum((low[i][p] * fwd[p] for p in range(i)), jnp.zeros((), b.dtype))) / low[i][i])
    x: list[Any] = [None] * k
    for i in reversed(range(k)):
        x[i] = (fwd[i] - sum((low[p][i] * x[p] for p in range(i + 1, k)), jnp.zeros((), b.dtype))) / low[i][i]
    return jnp.stack(x)


def _spd_solve(s: Float[Array, "k k"], b: Float[Array, " k"]) -> Float[Array, " k"]:
    """Solve s x = b for a small symmetric positive-definite s, unrolled (fuses under vmap)."""
    return _cholesky_solve(_cholesky(s), b)


def _turning_rows(g: Float[Array, "k 2"], p: Float[Array, "k 2"], joints: Float[Array, "joints 2"],
                  station: Int[Array, " k"], per_link: int) -> Float[Array, "k n"]:
    """d distance / d delta_j (K, N) of K stations ``p`` (mm; indices ``station`` among ``per_link``
    per link plus the tip) whose distance has the gradient ``g``: turning link j moves everything
    past its middle M_j about M_j (its own stations about its start, by half), so a point moves by
    (p - centre) turned by 90 degrees and its distance by the cross product of g with that."""
    n = joints.shape[0] - 1
    link = jnp.minimum(station // per_link, n - 1)
    mids = 0.5 * (joints[:-1] + joints[1:])
    j = jnp.arange(n)
    own = 0.5 * _cross(g, p - joints[link])
    past = _cross(g, p)[:, None] - _cross(g[:, None, :], mids[None, :, :])
    return jnp.where(j[None, :] < link[:, None], past, jnp.where(j[None, :] == link[:, None], own[:, None], 0.0))


def _curvature_operator(problem: _Problem, joints, index, p, g, force) -> Callable:
    """x -> C x: the contact terms' curvature (the Hessian's part the Gauss-Newton model leaves out,
    see :func:`_derivatives`) applied to x (scaled variables, (N+1,)), for the K stations ``index``
    at ``p`` (K, 2) with distance gradients ``g`` (K, 2) and ``force`` (K,) = w c_k, zero outside r.

    C = sum_k force_k (alpha^T diag(cover_k (g_k . V)) alpha - J_k^T Hd_k J_k), with phi = alpha x
    the links' turns, J_k x the station's first-order displacement (its links' turns, each about
    the link's start, swept over the links up to it) and J_k^T v by :func:`_turning_rows`.
    """
    n, per_link = problem.finger.n_links, problem.config.stations_per_link
    dtype = joints.dtype
    per_link_scale, base_scale = problem.scales()
    link = jnp.minimum(index // per_link, n - 1)
    fraction = (index - link * per_link).astype(dtype) / per_link
    i = jnp.arange(n)[None, :]
    cover = jnp.where(i < link[:, None], 1.0, jnp.where(i == link[:, None], fraction[:, None], 0.0))  # (K, N)
    links = joints[1:] - joints[:-1]  # (N, 2)
    bend = jnp.sum(force[:, None] * cover * (g @ links.T), axis=0)  # (N,)
    hess_d = jax.vmap(jax.hessian(problem.distance))(p)  # (K, 2, 2)

    def apply(x):
        turn = x[:-1] * per_link_scale
        phi = x[-1] * base_scale + jnp.cumsum(turn) - 0.5 * turn  # psi, the turns before, half its own
        swept = cover @ (phi[:, None] * links)  # (K, 2)
        u = jnp.stack([swept[:, 1], -swept[:, 0]], axis=-1)  # turned by 90 degrees: J_k x
        v = force[:, None] * jnp.einsum("kij,kj->ki", hess_d, u)
        back = jnp.sum(_turning_rows(v, p, joints, index, per_link), axis=0) * per_link_scale
        pull = jnp.sum(_cross(v, p)) * base_scale
        b = bend * phi  # alpha^T b: link j's turn moves phi_i for i > j fully, its own by half
        ahead = jnp.cumsum(b[::-1])[::-1] - 0.5 * b
        return jnp.concatenate([ahead * per_link_scale - back, (jnp.sum(b) * base_scale - pull)[None]])

    return apply


def _with_curvature(problem: _Problem, joints, index, p, g, force, a, low, step, stretch):
    """The Gauss-Newton ``step`` corrected for the contact terms' curvature (see _newton_step).

    The step s minimises the model G . x + x^T B x / 2 with B = I + A^T A (``a``: the step's rows),
    so G = -B s. This minimises G . x + x^T (B + C) x / 2 instead, C the contact terms' curvature
    (:func:`_curvature_operator`), by conjugate gradients preconditioned with B (whose inverse the
    Woodbury identity gives, as for the step): from 0, the first iterate is s stretched by the
    model's curvature along it, and each of the _CG_ITERATIONS adds one direction. B^-1 C is small
    but in the few directions where the contacts' curvature matters (a held tip's slide along the
    surface), so a few suffice. Where the model curves down along a direction (past a fold, where
    the held equilibrium has ceased to exist) or its minimum lies beyond ``stretch`` times s (in
    the B-norm: the trust region, at most _STRETCH_MAX), the iterate goes that far along the
    direction and stops (Steihaug's truncated conjugate gradients). ``low``: the Cholesky factor of
    I + A A^T (:func:`_cholesky`), the step's own.

    Returns (x, x.Bx, x.(B + C)x, s.Bs): the step and its curvatures in the two models, and the
    Gauss-Newton step's. Where the
    contacts' curvature turns the step away from descent (G . x >= 0, possible past a fold), x is
    s, shortened to the region.
    """
    curvature = _curvature_operator(problem, joints, index, p, g, force)

    def b_times(x):
        return x + _rmatvec(a, _matvec(a, x))

    def b_solve(r):
        return r - _rmatvec(a, _cholesky_solve(low, _matvec(a, r)))

    bs = b_times(step)
    sbs = _inner(step, bs)
    radius2 = stretch**2 * sbs
    tiny = jnp.asarray(1e-30, step.dtype)
    x, bx = jnp.zeros_like(step), jnp.zeros_like(step)
    r, d, rz = bs, step, sbs
    running = sbs > tiny
    # Along the iterates: b . x (b = Bs = -G), x.(B + C)x (H x = b - r), and s.(B + C)s.
    descent, xhx, shs = jnp.zeros((), step.dtype), jnp.zeros((), step.dtype), jnp.zeros((), step.dtype)
    for iteration in range(_CG_ITERATIONS):
        bd = b_times(d)
        hd = bd + curvature(d)
        dhd, dbd, xbd, xbx = _inner(d, hd), _inner(d, bd), _inner(x, bd), _inner(x, bx)
        if iteration == 0:
            shs = dhd
        alpha = rz / jnp.where(dhd > 0, dhd, 1.0)
        # Where the model curves down along d, or its minimum along d lies beyond the radius: to
        # the radius along d (the root tau >= 0 of |x + tau d|_B^2 = radius^2), and stop.
        beyond = (dhd <= 0) | (xbx + 2 * alpha * xbd + alpha**2 * dbd > radius2)
        dbd_safe = jnp.maximum(dbd, tiny)
        tau = (-xbd + jnp.sqrt(jnp.maximum(xbd**2 + dbd_safe * (radius2 - xbx), 0.0))) / dbd_safe
        move = jnp.where(running, jnp.where(beyond, tau, alpha), 0.0)
        xhx = xhx + 2.0 * move * (_inner(d, bs) - _inner(d, r)) + move**2 * dhd
        descent = descent + move * _inner(d, bs)
        x, bx = x + move * d, bx + move * bd
        r = r - move * hd
        z = b_solve(r)
        rz_next = _inner(r, z)
        running = running & ~beyond & (rz_next > 1e-12 * sbs)
        d = z + (rz_next / jnp.maximum(rz, tiny)) * d
        rz = rz_next
    short = jnp.minimum(stretch, 1.0)
    away = descent <= 0
    return (jnp.where(away, short * step, x), jnp.where(away, short**2 * sbs, _inner(x, bx)),
            jnp.where(away, short**2 * shs, xhx), sbs)


class _Step(eqx.Module):
    """One step of :func:`_newton_step` and what the solver reads of it."""

    step: Float[Array, " n1"]  #: the step in y
    moved: Float[Array, ""]  #: mm: largest joint displacement of the full (unshortened) step, to first order
    penetration: Float[Array, ""]  #: mm: the deepest station inside r at y (>= 0)
    pushed: Bool[Array, " m"]  #: stations carrying contact force in the model after the full step
    energy: Float[Array, ""]  #: the energy at y
    predicted: Float[Array, ""]  #: the energy's reduction the model predicts for the step
    reach: Float[Array, ""]  #: the step's length in Gauss-Newton steps (in the model's norm)
    shift: Float[Array, ""]  #: mm: largest joint displacement of the step taken, to first order


def _newton_step(problem: _Problem, y, previous, curvature: bool = True, stretch=_STRETCH_MAX) -> _Step:
    """The Gauss-Newton step at y, corrected for the contacts' curvature within ``stretch`` times
    the Gauss-Newton step (unless ``curvature`` is False, as on the closing path), and diagnostics
    (see the module docstring and :class:`_Step`)."""
    f, config = problem.finger, problem.config
    n, per_link = f.n_links, config.stations_per_link
    dtype = y.dtype
    joints, points = problem.stations(y)
    m = points.shape[0]
    violation = f.half_thickness - problem.distance(points)
    weight = jnp.sqrt(jnp.asarray(config.penalty, dtype)) / f.length

    # The K least clear stations (the most penetrating first), their distance gradients, and their
    # rows of the Jacobian of the contact residuals: moving delta_j turns everything past the
    # middle M_j of link j by the same angle (link j itself by half of it, about its start); psi
    # turns everything about the base. A point p then moves by (p - centre) turned by 90 degrees,
    # and its distance by the cross product of the gradient with that.
    k = min(config.active_rows, m)
    depth, index = jax.lax.top_k(violation, k)
    p = points[index]
    g = jax.vmap(jax.grad(problem.distance))(p)
    mids = 0.5 * (joints[:-1] + joints[1:])
    rows = _turning_rows(g, p, joints, index, per_link)
    per_link_scale, base_scale = problem.scales()
    a_k = -weight * jnp.concatenate([rows * per_link_scale[None, :], (_cross(g, p) * base_scale)[:, None]], axis=1)

    # The Gauss-Newton step minimises |y + step|^2 + |c + A step|^2 over the rows of the stations
    # that penetrate or touch (within _GLUE_MM outside): those touching enter with their signed
    # distance, as the constraint "end on the surface"; otherwise the step would not see them and
    # drive them straight in, and a contact rolling along the finger would advance one station per
    # step. Its model residuals (the contact forces over the weight) solve the K x K system
    # (I + A A^T) lam = c - A y, and step = -y - A^T lam (the Woodbury identity, in the form that
    # does not cancel large terms in float32). Stations with lam < 0 would be pulled out of the
    # object, which no contact can do: they are dropped and the step recomputed.
    signed = weight * depth

    # The products with A, once: a round's system is their rows and columns of the stations kept.
    gram = _gram(a_k)
    rhs = signed - _matvec(a_k, y)

    def solve(rows_on):
        both = rows_on[:, None] & rows_on[None, :]
        low = _cholesky(jnp.eye(k, dtype=dtype) + jnp.where(both, gram, 0.0))
        lam = jnp.where(rows_on, _cholesky_solve(low, jnp.where(rows_on, rhs, 0.0)), 0.0)
        return -y - _rmatvec(a_k, lam), lam, low

    # Dropping one station changes the others' multipliers, and a glued station outside the
    # object can turn negative only after another is dropped: were it kept, the step's fixed point
    # would hold it there by a pull, which stops the chain short of the true equilibrium (a tip
    # on a face it meets nearly parallel ended 0.2 mm along the face from it). So drop until no
    # multiplier is negative: at most K rounds, as each drops at least one row or changes nothing.
    # A round that drops nothing is a fixed point, so the loop stops there (usually after one or
    # two rounds) with the rows K rounds would give.
    def drop_pulling(carry):
        rounds, rows_on, _ = carry
        _, lam, _ = solve(rows_on)
        kept = rows_on & (lam >= 0)
        return rounds + 1, kept, jnp.any(kept != rows_on)

    _, modelled, _ = jax.lax.while_loop(lambda c: (c[0] < k) & c[2], drop_pulling,
                                        (jnp.array(0, jnp.int32), depth > -_GLUE_MM, jnp.array(True)))
    step, lam, low = solve(modelled)
    # The stations that carry contact force after the step (the model's residuals, positive: pushed
    # by the object), for the contact case (see solve_equilibrium).
    pushed = jnp.any((index[:, None] == jnp.arange(m)[None, :]) & (modelled & (lam > 0))[:, None], axis=0)
    # The contacts' curvature, which the model leaves out, matters near a fold (module docstring).
    if curvature:
        step, xbx, xhx, sbs = _with_curvature(problem, joints, index, p, g, weight * weight * jnp.maximum(depth, 0.0),
                                              jnp.where(modelled[:, None], a_k, 0.0), low, step, stretch)

    # Trust region on the angles.
    turns = jnp.concatenate([step[:-1] * per_link_scale, (step[-1] * base_scale)[None]])
    step = step * jnp.minimum(1.0, config.max_turn / jnp.maximum(jnp.max(jnp.abs(turns)), 1e-30))

    # The step does not see the other stations and would drive them through the object and back:
    # shorten it so that the first of them that it drives into the object stops on the surface
    # (to first order), where the next step sees it. The candidates are the K least clear stations.
    approach = _matvec(a_k, step) / weight  # mm of penetration per unit step
    free = ~modelled & (depth < 0) & (approach > 0)
    entry = jnp.where(free, -depth / jnp.where(free, approach, 1.0), 1.0)
    alpha = jnp.clip(jnp.min(entry), 0.0, 1.0)
    # A step that undoes most of the previous one is an active set flipping between two states
    # (a station glued, then dropped): halving it lets the pair settle between them.
    reverses = _inner(step, previous) < -0.5 * jnp.sqrt(_inner(step, step) * _inner(previous, previous))
    alpha = jnp.where(reverses, 0.5, 1.0) * alpha
    # How far the full step would move the joints, to first order (a turn d_j at link j moves
    # joint i > j by d_j (P_i - M_j) turned by 90 degrees, d psi moves it by d psi P_i turned): the
    # distance to the model's equilibrium, which a shortened step would understate.
    turn = step[:-1] * per_link_scale
    dpsi = step[-1] * base_scale
    before = jnp.concatenate([jnp.zeros((1,), dtype), jnp.cumsum(turn)])  # sum_{j<i} d_j
    moment = jnp.concatenate([jnp.zeros((1, 2), dtype), jnp.cumsum(turn[:, None] * mids, axis=0)])
    lever = joints * (before + dpsi)[:, None] - moment  # (N+1, 2), turned by 90 degrees below
    moved = jnp.sqrt(jnp.max(jnp.sum(lever**2, axis=-1)))
    penetration = jnp.maximum(jnp.max(violation), 0.0)
    taken = alpha * step
    if not curvature:  # the closing path reads only the step and the contacts
        nothing = jnp.zeros((), dtype)
        return _Step(step=taken, moved=moved, penetration=penetration, pushed=pushed, energy=nothing,
                     predicted=nothing, reach=nothing, shift=nothing)
    # The energy at y, and the model's value after the step taken (the hinge model of the K
    # stations, plus the contacts' curvature term): what the trust region compares.
    inside = jnp.maximum(violation, 0.0)
    energy = 0.5 * (_inner(y, y) + weight * weight * jnp.sum(inside * inside))
    after = y + taken
    hinge = jnp.maximum(signed + alpha * weight * approach, 0.0)
    model = 0.5 * (_inner(after, after) + jnp.sum(hinge * hinge) + alpha**2 * (xhx - xbx))
    reach = alpha * jnp.sqrt(xbx / jnp.maximum(sbs, 1e-30))
    return _Step(step=taken, moved=moved, penetration=penetration, pushed=pushed, energy=energy,
                 predicted=energy - model, reach=reach, shift=alpha * moved)


class _SolverState(eqx.Module):
    """The solve's iterations (see :class:`ChainGaussNewton`): the last step's diagnostics and the
    trust region's anchor (the last accepted point), its energy, the reduction the model predicted
    for the step taken from it, and the region's size in Gauss-Newton steps."""

    previous: Float[Array, " n1"]
    moved: Float[Array, ""]
    moved_before: Float[Array, ""]
    penetration: Float[Array, ""]
    pushed: Bool[Array, " m"]
    steps: Int[Array, ""]
    anchor: Float[Array, " n1"]
    anchor_energy: Float[Array, ""]
    predicted: Float[Array, ""]
    reach: Float[Array, ""]
    shift: Float[Array, ""]
    stretch: Float[Array, ""]


def _initial_state(y: Float[Array, " n1"], n_stations: int) -> _SolverState:
    inf = jnp.asarray(jnp.inf, y.dtype)
    return _SolverState(previous=jnp.zeros_like(y), moved=inf, moved_before=inf, penetration=inf,
                        pushed=jnp.zeros(n_stations, bool), steps=jnp.array(0), anchor=y, anchor_energy=inf,
                        predicted=inf, reach=jnp.asarray(_STRETCH_MAX, y.dtype), shift=inf,
                        stretch=jnp.asarray(_STRETCH_MAX, y.dtype))


class ChainGaussNewton(optx.AbstractLeastSquaresSolver):
    """Gauss-Newton for the spring chain's least squares (see the module docstring).

    Specific to this problem: it reads the chain from ``args`` (a ``_Problem``) to build the step
    from the structure of the residuals, while ``fn`` (the residuals) is what optimistix
    differentiates implicitly.
    """

    rtol: float
    atol: float
    norm: Callable = optx.max_norm
    #: Iterations in all, counted in the state across calls that resume it (``options["state"]``).
    max_steps: int = eqx.field(static=True, default=MechanicsConfig().max_steps)

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        if options and "state" in options:  # resuming a solve under way (see Progress)
            return options["state"]
        return _initial_state(y, args.n_stations)

    def step(self, fn, y, args, options, state, tags):
        # The trust region, checked one iteration late (the energy at y comes with the step from
        # y): a step whose energy fell by less than _ACCEPT of the model's prediction is undone and
        # the region shrunk, so that the solve descends the energy (past a fold, where the
        # contacts' curvature leaves the model poor, it would otherwise wander). Where the steps
        # are accepted, as on an ordinary contact, the solve is the plain one.
        here = _newton_step(args, y, state.previous, stretch=state.stretch)
        fell = state.anchor_energy - here.energy
        noise = _ENERGY_NOISE * jnp.abs(state.anchor_energy)
        ratio = fell / jnp.maximum(state.predicted, 1e-30)
        # (A step within the tolerance is kept whatever its energy: there the energy's changes are
        # float32 rounding of the stiff penalty, and the region is for the steps that travel.)
        small = (state.shift <= self.atol) | (jnp.abs(fell) <= noise)
        accept = ~jnp.isfinite(state.anchor_energy) | (ratio >= _ACCEPT) | small
        stretch = jnp.where(ratio < 0.25, 0.25 * state.reach,
                            jnp.where(ratio > 0.75, jnp.maximum(state.stretch, 2.0 * state.reach), state.stretch))
        stretch = jnp.where(small, state.stretch, stretch)
        stretch = jnp.clip(stretch, _STRETCH_MIN, _STRETCH_MAX)
        inf = jnp.asarray(jnp.inf, y.dtype)
        zero = jnp.zeros_like(y)
        state = _SolverState(
            previous=jnp.where(accept, here.step, zero), moved=jnp.where(accept, here.moved, inf),
            moved_before=jnp.where(accept, state.moved, inf), penetration=here.penetration,
            pushed=here.pushed, steps=state.steps + 1, anchor=jnp.where(accept, y, state.anchor),
            anchor_energy=jnp.where(accept, here.energy, state.anchor_energy),
            predicted=jnp.where(accept, here.predicted, state.predicted), reach=jnp.where(accept, here.reach, state.reach),
            shift=jnp.where(accept, here.shift, state.shift), stretch=stretch)
        return jnp.where(accept, y + here.step, state.anchor), state, None

    def terminate(self, fn, y, args, options, state, tags):
        # Two steps in a row within tolerance: a single small step can be an accident of a kink in
        # the object's distance gradient (a bilinear SDFGrid's cell edges), whose other side the
        # next step sees; near a fold, such a point lay a few tenths of a millimetre from any
        # equilibrium.
        done = (state.moved <= self.atol) & (state.moved_before <= self.atol) & (state.penetration <= self.rtol)
        spent = state.steps >= self.max_steps
        # (The result must read successful while the solve goes on: optimistix stops on any other.)
        return done | spent, optx.RESULTS.where(spent & ~done, optx.RESULTS.nonlinear_max_steps_reached,
                                                optx.RESULTS.successful)

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}


class Progress(eqx.Module):
    """A solve of the equilibrium under way (no derivatives): where its iterations stand.

    The solve runs in phases (:func:`start_equilibrium`, :func:`continue_equilibrium`,
    :func:`finish_equilibrium`) so that a batch can take the few slow elements on in small groups
    of their own instead of holding every group to its slowest element; the phases one after the
    other are one uninterrupted solve.
    """

    y: Float[Array, " n1"]  #: the scaled variables (see :class:`_Problem`)
    state: _SolverState
    done: Bool[Array, ""]  #: the solve stopped: converged, or failed on a non-finite value
    converged: Bool[Array, ""]
    tip_pressed: Bool[Array, ""]  #: the tip carried contact force along the closing path


def _iterate(problem: _Problem, y, state: _SolverState, steps: int, mechanics: MechanicsConfig):
    """At most ``steps`` more iterations of :class:`ChainGaussNewton` from ``y`` and its ``state``:
    ``(y, state, done, converged)``."""
    solver = ChainGaussNewton(rtol=mechanics.contact_tol, atol=mechanics.step_tol, max_steps=mechanics.max_steps)
    solution: optx.Solution = optx.least_squares(_residual_fn, solver, y, args=problem, options={"state": state},
                                                 max_steps=steps, throw=False)
    converged = solution.result == optx.RESULTS.successful
    # Stopped: converged, failed (a non-finite value), or the whole budget spent.
    done = (solution.result != optx.RESULTS.nonlinear_max_steps_reached) | (solution.state.steps >= mechanics.max_steps)
    return solution.value, solution.state, done, converged


def start_equilibrium(
    finger: FingerModel,
    sdf: AbstractSDF,
    frame: FingerFrame,
    start_psi: Float[Array, ""],
    start_turning: Float[Array, " n"],
    mechanics: MechanicsConfig = MechanicsConfig(),
    config: ContactConfig = ContactConfig(),
    *,
    start_actuation: Float[Array, ""] | None = None,
    steps: int | None = None,
) -> Progress:
    """The first phase of :func:`solve_equilibrium` (same arguments): the closing path, if
    ``start_actuation`` is given, then at most ``steps`` iterations of the solve at Theta (None:
    the whole budget, ``mechanics.max_steps``). No derivatives."""
    finger, sdf, frame, start_psi, start_turning, start_actuation = jax.lax.stop_gradient(
        (finger, sdf, frame, start_psi, start_turning, start_actuation))
    problem = _Problem(finger=finger, sdf=sdf, frame=frame, config=mechanics)
    tip_pressed = jnp.array(False)
    if start_actuation is not None:
        start_psi, start_turning, tip_pressed = follow_closing_path(problem, start_actuation, start_psi,
                                                                    start_turning, config)
    y0 = problem.variables(start_psi, start_turning)
    state = _initial_state(y0, problem.n_stations)
    budget = mechanics.max_steps if steps is None else min(steps, mechanics.max_steps)
    y, state, done, converged = _iterate(problem, y0, state, budget, mechanics)
    return Progress(y=y, state=state, done=done, converged=converged, tip_pressed=tip_pressed)


def continue_equilibrium(finger: FingerModel, sdf: AbstractSDF, frame: FingerFrame, progress: Progress,
                         mechanics: MechanicsConfig = MechanicsConfig()) -> Progress:
    """The solve of :func:`start_equilibrium` continued to its whole budget, ``mechanics.max_steps``
    iterations in all (none where it is ``done``). No derivatives."""
    finger, sdf, frame, progress = jax.lax.stop_gradient((finger, sdf, frame, progress))
    problem = _Problem(finger=finger, sdf=sdf, frame=frame, config=mechanics)
    # (optimistix's budget counts this call's steps, the solver's the state's: all of them.)
    y, state, done, converged = _iterate(problem, progress.y, progress.state, mechanics.max_steps, mechanics)
    return Progress(y=y, state=state, done=done, converged=converged, tip_pressed=progress.tip_pressed)


def closing_start(
    finger: FingerModel, contact: Contact, config: ContactConfig = ContactConfig()
) -> tuple[Float[Array, ""], Float[Array, ""], Float[Array, " n"]]:
    """Where the closing path leaves the free closure: ``(s, psi, turning)``, the actuation (rad)
    and the chain's shape (rad; psi (), turning (N,)) at first touch.

    Until the first touch the chain closes freely through its PCC shapes (eqs. 1-3), so the path
    starts at the PCC shape of ``contact.s1``. A rigid contact sweep (``config.sweep="rigid"``)
    measures its s1 on other shapes: the path then starts from the open finger (s = 0).
    """
    s = contact.s1 if config.sweep == "pcc" else jnp.zeros_like(contact.s1)
    s = jnp.clip(s, 0.0, finger.theta_entire)
    return s, jnp.zeros_like(s), pcc_turning(s, finger.n_links)


def path_increments(finger: FingerModel, s_start: Float[Array, ""], mechanics: MechanicsConfig) -> Int[Array, ""]:
    """How many increments the closing path takes from actuation ``s_start`` (rad) to Theta."""
    remain = jnp.maximum(finger.theta_entire - s_start, 0.0)
    return jnp.clip(jnp.ceil(remain / mechanics.path_step), 1, mechanics.path_steps).astype(jnp.int32)


class _PathState(eqx.Module):
    step: Int[Array, ""]
    y: Float[Array, " n1"]
    previous: Float[Array, " n1"]
    tip_pressed: Bool[Array, ""]


def _at_actuation(problem: _Problem, s) -> _Problem:
    """The same problem with the rest turning of actuation ``s`` (rad) in place of Theta's."""
    return eqx.tree_at(lambda p: p.finger.theta_entire, problem, s)


def _tip_zone(problem: _Problem, config: ContactConfig) -> Bool[Array, " m"]:
    """(M,) the stations within ``config.tip_tolerance`` links of the tip."""
    f = problem.finger
    arc = jnp.linspace(0.0, 1.0, problem.n_stations, dtype=f.length.dtype)
    return arc >= 1.0 - config.tip_tolerance / f.n_links


def follow_closing_path(
    problem: _Problem, s_start: Float[Array, ""], psi: Float[Array, ""], turning: Float[Array, " n"],
    config: ContactConfig = ContactConfig(),
) -> tuple[Float[Array, ""], Float[Array, " n"], Bool[Array, ""]]:
    """Close the chain quasi-statically from actuation ``s_start`` (rad) and shape ``(psi, turning)``
    to Theta: the rest turning ramps in ``n = clip(ceil((Theta - s_start) / path_step), 1,
    path_steps)`` equal increments, each followed by ``path_iterations`` plain Gauss-Newton steps
    (:func:`_newton_step`) warm-started from the last shape, contact frictionless.

    Returns the shape at Theta (psi () and turning (N,), rad; not yet converged: the caller's
    least-squares solve finishes it) and whether the tip carried contact force at some increment.

    Every element of a batch runs its own n increments: under ``vmap`` the loop runs for the
    longest path and holds each finished element (``lax.while_loop``'s per-element select), so
    no element's answer depends on the others.
    """
    mech = problem.config
    theta = problem.finger.theta_entire
    remain = jnp.maximum(theta - s_start, 0.0)
    count = path_increments(problem.finger, s_start, mech)
    tip_zone = _tip_zone(problem, config)

    def increment(state: _PathState) -> _PathState:
        s_before = s_start + remain * state.step / count
        s_after = jnp.where(state.step + 1 >= count, theta, s_start + remain * (state.step + 1) / count)
        shape = _at_actuation(problem, s_before).shape(state.y)
        here = _at_actuation(problem, s_after)
        y = here.variables(*shape)

        def iteration(_, carry):
            y, previous, pressed = carry
            taken = _newton_step(here, y, previous, curvature=False)
            return y + taken.step, taken.step, pressed | jnp.any(taken.pushed & tip_zone)

        y, previous, pressed = jax.lax.fori_loop(0, mech.path_iterations, iteration,
                                                 (y, state.previous, state.tip_pressed))
        return _PathState(step=state.step + 1, y=y, previous=previous, tip_pressed=pressed)

    start = _at_actuation(problem, s_start).variables(psi, turning)
    state = _PathState(step=jnp.array(0, jnp.int32), y=start, previous=jnp.zeros_like(start),
                       tip_pressed=jnp.array(False))
    state = jax.lax.while_loop(lambda st: st.step < count, increment, state)
    psi, turning = problem.shape(state.y)
    return psi, turning, state.tip_pressed


def tip_sensitivity(problem: _Problem, y: Float[Array, " n1"]) -> Float[Array, ""]:
    """How far the equilibrium's tip moves per mm the base moves, at most over directions (mm/mm).

    By the implicit function theorem at the equilibrium y (the energy's gradient G(y, base) = 0):
    dy/dbase = -H^-1 dG/dbase with H the energy's full Hessian (curvature of the contact terms
    included, unlike the Gauss-Newton model). A finger whose shape follows the base has a value near
    1; near a fold of the equilibrium (where the tip is about to slide off, or a contact area to
    appear) H turns singular and the value grows without bound. Diagnostic only: it carries no
    derivative.
    """
    return _second_order(problem, y)[0]


def _angle_map(problem: _Problem, dtype) -> Float[Array, "n n1"]:
    """(N, N+1) d phi_i / d y_j: how each link's direction phi_i (psi + sum_{j<i} delta_j +
    delta_i / 2) turns with the scaled variables y (turning j < i fully, link i's own by half, psi
    all of them). Constant: the chain's angles are linear in y."""
    n = problem.finger.n_links
    per_link, base = problem.scales()
    i, j = jnp.arange(n)[:, None], jnp.arange(n)[None, :]
    share = jnp.where(j < i, 1.0, jnp.where(j == i, 0.5, 0.0)).astype(dtype)
    return jnp.concatenate([share * per_link[None, :], jnp.broadcast_to(base, (n, 1)).astype(dtype)], axis=1)


class _Curvature(eqx.Module):
    """The energy's first and second derivatives at a shape (see :func:`_derivatives`)."""

    gradient: Float[Array, " n1"]  #: dE/dy
    hessian: Float[Array, "n1 n1"]  #: d2E/dy2
    mixed: Float[Array, "n1 2"]  #: d2E/dy d(base), the base moved in the image plane (mm)
    tip: Float[Array, "2 n1"]  #: d(tip)/dy in the image plane (mm)


def _station_jacobians(problem: _Problem, joints, index: Int[Array, " k"]):
    """For the stations ``index`` (K,): the link vectors V (K, N, 2) mm up to each (the own link's
    by the station's fraction of it; zero beyond), and dP_k/dy (K, 2, N+1) mm.

    A station is the sum of the link vectors before it; turning link i's direction phi_i by a
    small angle turns V_i by 90 degrees (and twice, negates it). With alpha = d phi / d y
    (:func:`_angle_map`), V alpha is dP/dy turned back by 90 degrees.
    """
    n, per_link = problem.finger.n_links, problem.config.stations_per_link
    dtype = joints.dtype
    link = jnp.minimum(index // per_link, n - 1)
    fraction = (index - link * per_link).astype(dtype) / per_link  # the tip: link N-1, fraction 1
    i = jnp.arange(n)[None, :]
    covered = jnp.where(i < link[:, None], 1.0, jnp.where(i == link[:, None], fraction[:, None], 0.0))
    vectors = covered[:, :, None] * (joints[1:] - joints[:-1])[None]
    turned = jnp.einsum("kni,nj->kij", vectors, _angle_map(problem, dtype))
    return vectors, jnp.stack([turned[:, 1], -turned[:, 0]], axis=1)


def _derivatives(problem: _Problem, y: Float[Array, " n1"], index: Int[Array, " k"]) -> _Curvature:
    """The energy's derivatives at y with the contact terms of the stations ``index`` (the others
    must lie outside r), in closed form (what nested ``jax.jacfwd`` / ``jax.grad`` of the energy
    give, at a fraction of their cost).

    The penalty c_k = w max(0, r - d(P_k)) of a station inside r (d < r) adds c_k a_k to the
    gradient, with a_k = -w J_k^T g (J_k = dP_k/dy, g and Hd the distance's gradient and Hessian at
    P_k, finger frame), and a_k a_k^T + c_k w (alpha^T diag(g . V) alpha - J_k^T Hd J_k) to the
    Hessian (g . d2P_k/dy2 = -alpha^T diag(g . V) alpha, see :func:`_station_jacobians`). Moving the
    base by b in the image plane moves the object by -R^T b in the finger frame (R: the frame's
    axes), hence the mixed term -w (a_k g^T + c_k J_k^T Hd) R^T.
    """
    f = problem.finger
    dtype = y.dtype
    joints, points = problem.stations(y)
    vectors, jac = _station_jacobians(problem, joints, index)
    p = points[index]
    grad_d = jax.vmap(jax.grad(problem.distance))(p)
    hess_d = jax.vmap(jax.hessian(problem.distance))(p)
    weight = jnp.sqrt(jnp.asarray(problem.config.penalty, dtype)) / f.length
    sink = f.half_thickness - problem.distance(p)
    inside = sink > 0
    c = jnp.where(inside, weight * sink, 0.0)  # (K,)
    a = jnp.where(inside[:, None], -weight * jnp.einsum("kij,ki->kj", jac, grad_d), 0.0)  # (K, N+1)
    alpha = _angle_map(problem, dtype)
    bend = jnp.einsum("k,kni,ki->n", weight * c, vectors, grad_d)  # (N,)
    stretch = jnp.einsum("k,kia,kib,kbc->ac", weight * c, jac, hess_d, jac)
    hessian = jnp.eye(y.shape[0], dtype=dtype) + a.T @ a + alpha.T @ (bend[:, None] * alpha) - stretch
    axes = jax.jacfwd(problem.frame.to_world)(joints[-1])  # (2, 2): R, finger frame to image plane
    hd_jac = jnp.einsum("kij,kja->kia", hess_d, jac)  # (K, 2, N+1)
    mixed = -weight * (a.T @ grad_d + jnp.einsum("k,kia->ai", c, hd_jac)) @ axes.T
    tip = axes @ _station_jacobians(problem, joints, jnp.array([problem.n_stations - 1]))[1][0]
    return _Curvature(gradient=y + a.T @ c, hessian=hessian, mixed=mixed, tip=tip)


def _second_order(
    problem: _Problem, y: Float[Array, " n1"]
) -> tuple[Float[Array, ""], Float[Array, " n1"], Float[Array, " n1"]]:
    """From one Hessian H of the energy at y: the tip's sensitivity (:func:`tip_sensitivity`,
    mm/mm), the full Newton step -H^-1 G (scaled variables, (N+1,)) and the gradient G ((N+1,)).
    No derivatives."""
    problem, y = jax.lax.stop_gradient((problem, y))
    f = problem.finger
    # Only stations inside r add to the energy and its derivatives: the K least clear stations (the
    # Newton step's rows) hold them all wherever the step is exact.
    _, index = jax.lax.top_k(f.half_thickness - problem.distance(problem.stations(y)[1]),
                             min(problem.config.active_rows, problem.n_stations))
    d = _derivatives(problem, y, index)
    solved = -_gauss_jordan(d.hessian, jnp.concatenate([d.mixed, d.gradient[:, None]], axis=1))
    dy, newton = solved[:, :2], solved[:, 2]
    d_tip = jnp.eye(2, dtype=y.dtype) + d.tip @ dy  # (2, 2): the base carries the tip along
    # largest singular value of the 2 x 2 matrix, closed form
    gram = d_tip.T @ d_tip
    half_trace = 0.5 * jnp.trace(gram)
    det = gram[0, 0] * gram[1, 1] - gram[0, 1] * gram[1, 0]  # (not jnp.linalg.det: an LU custom call)
    gap = jnp.sqrt(jnp.maximum(half_trace**2 - det, 0.0))
    value = jnp.sqrt(half_trace + gap)
    return jnp.where(jnp.isfinite(value), value, jnp.inf), newton, d.gradient


def _gauss_jordan(a: Float[Array, "n n"], b: Float[Array, "n k"]) -> Float[Array, "n k"]:
    """Solve a x = b for a symmetric a, without pivoting (stable for a positive definite one, as
    the Hessian of a stable equilibrium is), in a ``fori_loop`` of plain array operations. With
    ``jnp.linalg.solve`` (LAPACK, a custom call) in its place, a batched estimate split by
    ``run_in_parts`` hung: both threads waiting in ``block_until_ready``, no CPU used. A vanishing
    pivot (a fold) gives inf."""
    n = a.shape[0]
    rows = jnp.arange(n)

    def eliminate(k, m):
        pivot = m[k, k]
        row = m[k] / pivot
        return jnp.where((rows == k)[:, None], row[None, :], m - m[:, k][:, None] * row[None, :])

    return jax.lax.fori_loop(0, n, eliminate, jnp.concatenate([a, b], axis=1))[:, n:]


def _polish(problem: _Problem, y, newton, gradient, converged) -> Float[Array, " n1"]:
    """The full Newton step taken from the converged solver point, or zeros (N+1,).

    The solver's steps see the contact terms' curvature only along a few conjugate directions
    (:func:`_with_curvature`). Near a fold, in the soft direction (a held tip's slide along the
    surface), the solve can then still stop a fraction of ``step_tol`` short, by a different
    amount at neighbouring poses: steps in the estimate as the pose moves. One Newton step with
    the full Hessian (the one the sensitivity needs) removes most of that. It is taken only from
    a converged point, where it is small (no joint moves more than 10 ``step_tol``: the same
    contacts), descends and lowers the energy.
    """
    def energy(v):
        return 0.5 * jnp.sum(problem.residuals(v) ** 2)

    trial = y + newton
    shift = jnp.max(jnp.linalg.norm(problem.stations(trial)[0] - problem.stations(y)[0], axis=-1))
    take = (converged & jnp.all(jnp.isfinite(newton)) & (shift <= 10.0 * problem.config.step_tol)
            & (jnp.dot(gradient, newton) < 0) & (energy(trial) <= energy(y) * (1.0 + 1e-6)))
    return jnp.where(take, newton, 0.0)


def contact_forces(
    finger: FingerModel,
    joints: Float[Array, "joints 2"],
    turning: Float[Array, " n"],
    handedness: Float[Array, ""],
    points: Float[Array, "k 2"],
    normals: Float[Array, "k 2"],
    station: Int[Array, " k"],
    per_link: int,
    touching: Bool[Array, " k"],
) -> Float[Array, " k"]:
    """Contact force magnitudes (K,) of an equilibrium, in units of EI / L^2 (mean bending stiffness
    over L^2), at K contact stations, from the springs' moments: frictionless contact pushes each
    station along the object's outward normal, and at equilibrium each link's spring moment
    ``k_j N (delta_j - delta0)`` (EI / L) equals the moment of the forces beyond it,
    ``sum_c lambda_c d(distance_c)/d delta_j``. Solved for lambda >= 0 by least squares over the N
    links (the contacts' rows as in :func:`_newton_step`), then ``f = lambda L``.

    Independent of the penalty's sink depth (hundredths of a micrometre, which a converged solve
    does not resolve): the moments are what the solve converges.

    Args:
        joints: (N+1, 2) mm, image plane; turning: (N,) rad, the finger's own frame; handedness: +1
            for a finger curling toward its frame's +x (left), -1 mirrored (right).
        points: (K, 2) mm, the contact stations on the centreline; normals: (K, 2) the object's
            outward unit normals there; station: (K,) their indices among the ``per_link`` (static)
            stations per link plus the tip.
    """
    n = finger.n_links
    # A mirrored finger turns the other way in the image.
    rows = handedness * _turning_rows(normals, points, joints, station, per_link)
    rows = jnp.where(touching[:, None], rows, 0.0)
    moments = link_stiffness(finger) * n * (turning - pcc_turning(finger.theta_entire, n))
    k = points.shape[0]
    gram = rows @ rows.T + 1e-9 * jnp.trace(rows @ rows.T) * jnp.eye(k, dtype=rows.dtype) + 1e-30 * jnp.eye(k)
    lam = jnp.linalg.solve(gram, rows @ moments)
    # A slot that would pull: drop it and solve again (a few contacts: two rounds suffice in practice).
    for _ in range(2):
        keep = touching & (lam > 0)
        r = jnp.where(keep[:, None], rows, 0.0)
        g = r @ r.T + jnp.diag(jnp.where(keep, 0.0, 1.0)) + 1e-9 * jnp.trace(r @ r.T) * jnp.eye(k, dtype=rows.dtype)
        lam = jnp.where(keep, jnp.linalg.solve(g, r @ moments), 0.0)
    return jnp.maximum(lam, 0.0) * finger.length


class Equilibrium(eqx.Module):
    """The spring chain at equilibrium, in the finger's frame."""

    psi: Float[Array, ""]
    turning: Float[Array, " n"]
    case: Int[Array, ""]
    converged: Bool[Array, ""]
    penetration: Float[Array, ""]  #: deepest station inside r (mm)
    tip_foot: Float[Array, "2"]  #: the tip moved onto the object surface (mm, finger frame)
    steps: Int[Array, ""]
    residual: Float[Array, ""]  #: the last Gauss-Newton step's largest joint displacement (mm)
    slid_off: Bool[Array, ""]  #: the tip carried force along the closing path, but not at its end
    sensitivity: Float[Array, ""]  #: tip displacement per base displacement, largest (mm/mm)
    near_fold: Bool[Array, ""]  #: sensitivity above ``MechanicsConfig.fold_sensitivity``


def solve_equilibrium(
    finger: FingerModel,
    sdf: AbstractSDF,
    frame: FingerFrame,
    start_psi: Float[Array, ""],
    start_turning: Float[Array, " n"],
    mechanics: MechanicsConfig = MechanicsConfig(),
    config: ContactConfig = ContactConfig(),
    *,
    start_actuation: Float[Array, ""] | None = None,
) -> Equilibrium:
    """Equilibrium of the spring chain placed by ``frame`` against ``sdf``, from a start shape.

    ``start_psi, start_turning`` (finger frame) start the solve and carry no derivative: the
    equilibrium's derivatives come from implicit differentiation. With ``start_actuation`` (rad)
    they are the shape at that actuation and the chain first closes along the path to Theta
    (:func:`follow_closing_path`; :func:`closing_start` gives the estimate's start); without it
    the solve starts at Theta directly.

    The case says where the equilibrium carries contact force: a station carries force where it
    lies inside r (the penalty pushes it) or the solver's last step modelled a positive multiplier
    for it (the chain pushes it into the object); a station merely within ``contact_tol`` of the
    object does not. Each force belongs to a contact area, the run of consecutive stations within
    ``contact_tol`` around it: the tip's when that run reaches the last ``config.tip_tolerance``
    links, another area's otherwise. So a graze is no contact, and a single area that straddles
    the edge of the tip zone is a tip contact, as the observed-closure rod's case counts areas.
    """
    progress = start_equilibrium(finger, sdf, frame, start_psi, start_turning, mechanics, config,
                                 start_actuation=start_actuation)
    return finish_equilibrium(finger, sdf, frame, progress, mechanics, config)


def finish_equilibrium(finger: FingerModel, sdf: AbstractSDF, frame: FingerFrame, progress: Progress,
                       mechanics: MechanicsConfig = MechanicsConfig(),
                       config: ContactConfig = ContactConfig()) -> Equilibrium:
    """The :class:`Equilibrium` of a finished solve (:func:`start_equilibrium`, then
    :func:`continue_equilibrium` where it was not ``done``), with the equilibrium's derivatives in
    the finger, the object and the frame.

    Those come by the implicit function theorem on the optimality condition of the least squares
    (the gradient of 0.5 |r|^2 vanishes), with JAX's ``custom_root`` around the solve already done
    and a dense solve of its Jacobian (the chain's few variables), rather than optimistix's adjoint:
    that one solves the tangent system with lineax, whose checks are host callbacks under reverse
    mode unless ``EQX_ON_ERROR`` was set before equinox was imported; a program with host callbacks
    never enters the persistent compilation cache.
    """
    problem = _Problem(finger=finger, sdf=sdf, frame=frame, config=mechanics)
    progress = jax.lax.stop_gradient(progress)

    def optimality(y):
        return jax.grad(lambda z: 0.5 * jnp.sum(_residual_fn(z, problem) ** 2))(y)

    def solved(_, start):  # the solve is done: custom_root only supplies the derivatives
        return start

    def tangent_solve(linear, rhs):
        return jnp.linalg.solve(jax.jacfwd(linear)(rhs), rhs)

    y = jax.lax.custom_root(optimality, progress.y, solved, tangent_solve)
    state = progress.state
    pushed, moved, steps, converged, tip_pressed = (state.pushed, state.moved, state.steps, progress.converged,
                                                    progress.tip_pressed)
    sensitivity, newton, gradient = _second_order(problem, y)
    y = y + jax.lax.stop_gradient(_polish(problem, y, newton, gradient, converged))
    psi, turning = problem.shape(y)
    joints, points = problem.stations(y)
    arc = jnp.linspace(0.0, 1.0, points.shape[0], dtype=points.dtype) * finger.length
    d = problem.distance(points)
    r, length, n = finger.half_thickness, finger.length, finger.n_links
    # The case (see the docstring): stations that carry force, by the contact area they lie in.
    pressed = pushed | (d < r)
    touching = (d <= r + mechanics.contact_tol) | pressed
    at_tip = arc >= length * (1.0 - config.tip_tolerance / n)
    station = jnp.arange(d.shape[0])
    first_tip = jnp.argmax(at_tip)  # the tip zone is the tail of the stations
    next_gap = jax.lax.cummin(jnp.where(touching, d.shape[0], station), reverse=True)
    tip_area = touching & (next_gap > first_tip)
    tip = jnp.any(pressed & tip_area)
    other = jnp.any(pressed & ~tip_area)
    case = jnp.where(tip, jnp.where(other, ContactCase.TIP_AND_OTHER, ContactCase.TIP),
                     jnp.where(other, ContactCase.OTHER, ContactCase.NONE)).astype(jnp.int32)
    tip_point = joints[-1]
    tip_foot = surface_point(problem.distance, tip_point)
    penetration = jnp.maximum(jnp.max(r - d), 0.0)
    return Equilibrium(
        psi=psi, turning=turning, case=case, converged=converged,
        penetration=penetration, tip_foot=tip_foot, steps=steps,
        residual=moved, slid_off=tip_pressed & ~tip, sensitivity=sensitivity,
        near_fold=sensitivity > mechanics.fold_sensitivity,
    )
