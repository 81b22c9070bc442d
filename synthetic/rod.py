"""The observed closure: a finely discretised elastic rod, independent of the estimator's model.

Accuracy is measured against this model (benchmarks/reproduce_paper.py, benchmarks/bench_mechanics_fit.py). It shares nothing with the
estimator's PCC chain or contact cases except the conventions: image plane in millimetres, x right,
y down, angles from the downward vertical and positive toward +x, direction of angle ``a`` is
``(sin a, cos a)``. The finger is computed as a left finger (curling toward +x); a right finger
reflects the object about the vertical line through its base, so both run the same code.

Model. A planar inextensible rod of length ``L`` hangs from its base point, cut into ``M`` equal
segments of length ``h = L / M``. Node ``i`` (``i = 0`` is the base) carries a turning angle
``phi_i``; segment ``i`` points at ``alpha_i = psi + phi_0 + ... + phi_i``, where ``psi`` is the
base direction (0 when clamped). Node ``i`` represents the rod over its Voronoi length
``l_0 = h / 2``, ``l_i = h``, so the elastic energy is

    E = sum_i k_i (phi_i - l_i kappa0)^2 / (2 l_i) + k_base psi^2 / 2,

with rest curvature ``kappa0 = 2 Theta / L``: the free rod is the circular arc whose base->tip chord
makes the angle ``Theta`` with the vertical (its nodes lie on that arc up to ``(kappa0 h)^2 / 24``
relative, about 0.002 mm for ``L = 100`` mm). The bending stiffness varies linearly from
``stiffness_ratio`` at the base to 1 at the tip, scaled to a mean of 1; a base spring has
``k_base = 1 / (base_compliance L)`` in the same units (``base_compliance = 1`` makes the base as
compliant as the whole rod under a uniform moment; 0 clamps the base). Energies are reported
divided by ``mean(k) / L``, so they are dimensionless.

Contact is frictionless: every node and ``samples_per_segment - 1`` points inside each segment keep
the centreline at least ``half_thickness`` from the object, measured with its signed distance.
Closing is quasi-static: the rest curvature ramps from 0 to ``kappa0`` in ``n_steps`` steps and each
step minimises the energy from the previous solution with BFGS (optimistix, float64), enforcing
contact with an augmented Lagrangian (PHR) whose multipliers carry over between steps, until both
the deepest sampled penetration and the gap at which a lifted-off point still pushes are below half
of ``penetration_tol``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float

from softgrip_jax import SoftgripError

_CHECK_SAMPLES = 8  # points per segment at which max_penetration is measured (finer than the solve)


def _require_float(name: str, value, *, lower: float, strict: bool = False, upper: float | None = None):
    """Raise a SoftgripError naming ``name`` unless ``value`` is a finite number in range."""
    if isinstance(value, jax.core.Tracer):
        return
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise SoftgripError(f"{name} must be a number, got {value!r}") from None
    below = number <= lower if strict else number < lower
    if not math.isfinite(number) or below or (upper is not None and number >= upper):
        bound = f"> {lower}" if strict else f">= {lower}"
        limit = f" and < {upper:.6g}" if upper is not None else ""
        raise SoftgripError(f"{name} must be finite and {bound}{limit}, got {value!r}")


def _require_int(name: str, value, *, lower: int):
    """Raise a SoftgripError naming ``name`` unless ``value`` is an int >= ``lower``."""
    if isinstance(value, bool) or not isinstance(value, int) or value < lower:
        raise SoftgripError(f"{name} must be an integer >= {lower}, got {value!r}")


@dataclasses.dataclass(frozen=True)
class RodMechanics:
    """Material and solver settings of the observed-closure rod.

    Attributes:
        stiffness_ratio: bending stiffness at the base over that at the tip (linear profile, 1 =
            uniform), > 0.
        base_compliance: compliance of a rotational spring at the base, relative to the bending
            compliance ``L / mean(k)`` of the whole rod; 0 clamps the base direction. >= 0.
        n_segments: number of equal rod segments M, >= 80.
        n_steps: quasi-static load steps of the rest-curvature ramp, >= 1.
        samples_per_segment: contact points per segment (its start node included), >= 1.
        penetration_tol: largest accepted penetration of the centreline inside ``half_thickness``
            of the object, mm, > 0. ``RodClosure.converged`` is False above it.
        contact_tol: a node is ``in_contact`` when within ``half_thickness + contact_tol`` of the
            object, mm, >= 0.
        penalty: augmented-Lagrangian penalty weight (dimensionless, violations in units of L), > 0.
        max_rounds: most augmented-Lagrangian rounds per load step, >= 1.
        max_iterations: most BFGS iterations per minimisation, >= 1.
        solver_tol: relative and absolute BFGS tolerance on the scaled variables and energy, > 0.
    """

    stiffness_ratio: float = 1.0
    base_compliance: float = 0.0
    n_segments: int = 96
    n_steps: int = 30
    samples_per_segment: int = 3
    penetration_tol: float = 0.02
    contact_tol: float = 0.05
    penalty: float = 1e4
    max_rounds: int = 10
    max_iterations: int = 2000
    solver_tol: float = 1e-10

    def __post_init__(self):
        _require_float("RodMechanics.stiffness_ratio", self.stiffness_ratio, lower=0.0, strict=True)
        _require_float("RodMechanics.base_compliance", self.base_compliance, lower=0.0)
        _require_int("RodMechanics.n_segments", self.n_segments, lower=80)
        _require_int("RodMechanics.n_steps", self.n_steps, lower=1)
        _require_int("RodMechanics.samples_per_segment", self.samples_per_segment, lower=1)
        _require_float("RodMechanics.penetration_tol", self.penetration_tol, lower=0.0, strict=True)
        _require_float("RodMechanics.contact_tol", self.contact_tol, lower=0.0)
        _require_float("RodMechanics.penalty", self.penalty, lower=0.0, strict=True)
        _require_int("RodMechanics.max_rounds", self.max_rounds, lower=1)
        _require_int("RodMechanics.max_iterations", self.max_iterations, lower=1)
        _require_float("RodMechanics.solver_tol", self.solver_tol, lower=0.0, strict=True)


class RodClosure(eqx.Module):
    """One finger's observed closure, in the image plane (mm).

    Attributes:
        points: (M+1, 2) rod nodes from base to tip, mm.
        turning: (M,) turning angle at each node, rad (node 0 turns from the base direction).
        base_angle: () base direction psi, rad (0 when clamped; in the finger's own frame, so
            negative means rotated away from the closing direction for either hand).
        energy: () elastic energy divided by mean(k) / L (dimensionless).
        max_penetration: () deepest point of the centreline inside ``half_thickness`` of the
            object, mm, >= 0 (checked at 8 points per segment).
        in_contact: (M+1,) nodes within ``half_thickness + contact_tol`` of the object.
        converged: () every minimisation succeeded, every load step met the augmented-Lagrangian
            tolerance within ``max_rounds``, and ``max_penetration <= penetration_tol``.
    """

    points: Float[Array, "m1 2"]
    turning: Float[Array, " m"]
    base_angle: Float[Array, ""]
    energy: Float[Array, ""]
    max_penetration: Float[Array, ""]
    in_contact: Bool[Array, " m1"]
    converged: Bool[Array, ""]


class _Scene(eqx.Module):
    """Everything a closure depends on that may vary without recompiling (float64 arrays)."""

    base: Float[Array, "2"]
    theta_entire: Float[Array, ""]
    length: Float[Array, ""]
    half_thickness: Float[Array, ""]
    handedness: Float[Array, ""]
    stiffness_ratio: Float[Array, ""]
    base_compliance: Float[Array, ""]
    sdf: Any


class _SolverSettings(NamedTuple):
    """The static part of RodMechanics: one compilation per distinct value."""

    n_segments: int
    n_steps: int
    samples_per_segment: int
    penetration_tol: float
    contact_tol: float
    penalty: float
    max_rounds: int
    max_iterations: int
    solver_tol: float


def close_rod(
    base: ArrayLike,
    theta_entire: float,
    length: float,
    half_thickness: float,
    sdf: Any = None,
    *,
    mechanics: RodMechanics = RodMechanics(),
    handedness: float = 1.0,
) -> RodClosure:
    """Close one finger quasi-statically against an object and return its equilibrium shape.

    Runs in float64 whatever the global ``jax_enable_x64`` setting; compiles once per
    ``mechanics`` solver settings (sizes and tolerances) and object structure, so scenes that differ
    in base, angle, length, thickness, stiffness profile, base compliance, hand or object vertex
    values reuse the compilation. Concrete inputs are validated; traced ones (under ``jax.vmap``) are
    not. The open finger (straight down from ``base``) should be clear of the object: the closure
    follows the contact from its first touch, and an object already overlapping the open finger is
    pushed out along its distance gradient, wherever that leads.

    Args:
        base: (2,) base point, mm.
        theta_entire: entire bending angle Theta of the free closure, rad, in [0, pi/2).
        length: rod length L, mm, > 0.
        half_thickness: half the finger thickness r, mm, >= 0.
        sdf: the object, anything with ``.distance(points[..., 2]) -> [...]`` in mm (negative
            inside), such as ``softgrip_jax.PolygonSDF``; None for no object.
        mechanics: material and solver settings.
        handedness: +1 for a left finger (curls toward +x), -1 for a right one (toward -x).

    Returns:
        The closure, float64.

    Example:
        >>> from softgrip_jax import PolygonSDF
        >>> ball = PolygonSDF.regular(center=(30.0, 45.0), radius=12.0, n_vertices=64)
        >>> closure = close_rod((0.0, 0.0), 0.8, 90.0, 5.0, ball)
        >>> bool(closure.converged), float(closure.max_penetration) < 0.02
        (True, True)
        >>> observed_joints(closure, 20).shape
        (21, 2)
    """
    _check_inputs(base, theta_entire, length, half_thickness, sdf, handedness)
    with jax.enable_x64(True):
        scene = _make_scene(base, theta_entire, length, half_thickness, sdf, mechanics, handedness)
        return _close(scene, _solver_settings(mechanics))


def rod_energy(
    turning: Float[ArrayLike, " m"],
    base_angle: float,
    base: ArrayLike,
    theta_entire: float,
    length: float,
    half_thickness: float,
    sdf: Any = None,
    *,
    mechanics: RodMechanics = RodMechanics(),
    handedness: float = 1.0,
    progress: float = 1.0,
    multipliers: Float[ArrayLike, " p"] | None = None,
) -> Float[Array, ""]:
    """The objective the quasi-static solver minimises (elastic energy plus contact term).

    Elastic energy over mean(k) / L, plus the augmented-Lagrangian contact term
    ``sum_p (max(0, lam_p + mu g_p)^2 - lam_p^2) / (2 mu)`` with ``g_p = (r - sdf(x_p)) / L`` at the
    contact points ``x_p`` (M * samples_per_segment + 1 of them, base to tip) and ``mu`` the
    penalty. Computed in the dtype of the inputs; call it under ``jax.enable_x64(True)`` for float64.

    Args:
        turning: (M,) turning angles, rad, with M = ``mechanics.n_segments``.
        base_angle: base direction psi, rad (ignored when the base is clamped).
        base, theta_entire, length, half_thickness, sdf, handedness: as for :func:`close_rod`.
        mechanics: material and solver settings.
        progress: fraction of the rest curvature applied, in [0, 1].
        multipliers: (P,) contact multipliers lam_p >= 0; zeros (a pure quadratic penalty) if None.

    Returns:
        () the objective.

    Example (the straight rod without an object stores the energy of bending back from its rest
    arc, about (2 Theta)^2 / 2 in units of mean(k) / L):
        >>> import jax.numpy as jnp
        >>> m = RodMechanics().n_segments
        >>> round(float(rod_energy(jnp.zeros(m), 0.0, jnp.zeros(2), 0.5, 52.0, 4.0)), 2)
        0.5
    """
    if jnp.shape(turning) != (mechanics.n_segments,):
        raise SoftgripError(
            f"rod_energy: turning must have shape ({mechanics.n_segments},) = (mechanics.n_segments,), "
            f"got {jnp.shape(turning)}"
        )
    scene = _make_scene(base, theta_entire, length, half_thickness, sdf, mechanics, handedness)
    settings = _solver_settings(mechanics)
    if multipliers is None:
        multipliers = jnp.zeros(_n_contact_points(settings), scene.length.dtype)
    return _objective(jnp.asarray(turning), jnp.asarray(base_angle), scene, settings, progress, multipliers)


def observed_joints(closure: RodClosure, n_links: int) -> Float[Array, "n1 2"]:
    """The paper's observed positions (eq. 10): the rod divided into ``n_links`` equal arc lengths.

    Args:
        closure: a closure with (M+1, 2) points.
        n_links: number of links N, >= 1.

    Returns:
        (N+1, 2) points at arc lengths k L / N, k = 0..N, mm (base first, tip last), in the dtype of
        ``closure.points``.

    Example: :func:`close_rod`'s example divides a closure into 20 links.
    """
    _require_int("observed_joints: n_links", n_links, lower=1)
    with jax.enable_x64(True):
        points = closure.points
        m = points.shape[-2] - 1
        station = jnp.arange(n_links + 1) * (m / n_links)
        index = jnp.clip(jnp.floor(station).astype(jnp.int32), 0, m - 1)
        frac = (station - index)[:, None]
        return points[..., index, :] + frac * (points[..., index + 1, :] - points[..., index, :])


def free_arc_points(
    base: ArrayLike,
    theta_entire: float,
    length: float,
    arc_lengths: Float[ArrayLike, "..."],
    handedness: float = 1.0,
) -> Float[Array, "... 2"]:
    """Points of the free closed finger: the circular arc of curvature 2 Theta / L from the base.

    Args:
        base: (2,) base point, mm.
        theta_entire: entire bending angle Theta, rad (chord angle of the arc of length L).
        length: finger length L, mm.
        arc_lengths: (...) arc lengths from the base, mm.
        handedness: +1 curls toward +x, -1 toward -x.

    Returns:
        (..., 2) points, mm, float64. Exact and smooth at Theta = 0 (straight finger).

    Example (the straight finger, and the tip of a closed one: the chord at Theta from the vertical):
        >>> import numpy as np
        >>> free_arc_points((0.0, 0.0), 0.0, 50.0, np.array([25.0, 50.0])).tolist()
        [[0.0, 25.0], [0.0, 50.0]]
        >>> tip = free_arc_points((0.0, 0.0), 0.5, 50.0, 50.0)
        >>> round(float(np.arctan2(tip[0], tip[1])), 6)
        0.5
    """
    with jax.enable_x64(True):
        s = jnp.asarray(arc_lengths, jnp.result_type(float))
        half_turn = theta_entire * s / length  # half the tangent angle kappa0 s / 2
        # (1 - cos a) / kappa0 = s sin(a/2) sinc(a/2) and sin(a) / kappa0 = s sinc(a), a = kappa0 s.
        across = s * jnp.sin(half_turn) * jnp.sinc(half_turn / jnp.pi)
        down = s * jnp.sinc(2 * half_turn / jnp.pi)
        return jnp.asarray(base, s.dtype) + jnp.stack([handedness * across, down], axis=-1)


# ---------------------------------------------------------------------------------------------
# The solve


@eqx.filter_jit
def _close(scene: _Scene, settings: _SolverSettings) -> RodClosure:
    """Quasi-static closure of one scene (see the module docstring)."""
    n = settings.n_segments
    scale = jnp.sqrt(_voronoi(n) / _stiffness(n, scene.stiffness_ratio))
    base_scale = jnp.sqrt(scene.base_compliance)

    def unpack(u):
        # Scaled variables make the elastic Hessian the identity: BFGS starts well conditioned.
        return u[1:] * scale, u[0] * base_scale

    def objective(u, args):
        progress, multipliers = args
        turning, base_angle = unpack(u)
        return _objective(turning, base_angle, scene, settings, progress, multipliers)

    solver = optx.BFGS(rtol=settings.solver_tol, atol=settings.solver_tol)

    def minimise(u, progress, multipliers):
        solution = optx.minimise(
            objective,
            solver,
            u,
            args=(progress, multipliers),
            max_steps=settings.max_iterations,
            throw=False,
        )
        return solution.value, solution.result == optx.RESULTS.successful

    def violation(u):
        turning, base_angle = unpack(u)
        nodes = _nodes(scene, turning, base_angle)
        points = _segment_samples(nodes, settings.samples_per_segment)
        return scene.half_thickness - _distance(scene, points)

    def load_step(carry, progress):
        u, multipliers = carry

        def unfinished(state):
            _, _, _, rounds, residual = state
            return (rounds < settings.max_rounds) & (residual > 0.5 * settings.penetration_tol)

        def augmented_lagrangian_round(state):
            u, multipliers, ok, rounds, _ = state
            u, solved = minimise(u, progress, multipliers)
            updated = jnp.maximum(0.0, multipliers + settings.penalty * violation(u) / scene.length)
            # max|max(g, -lam / mu)| in mm: penetration, and force left at points that lifted off.
            residual = jnp.max(jnp.abs(updated - multipliers)) * scene.length / settings.penalty
            return u, updated, ok & solved, rounds + 1, residual

        if scene.sdf is None:
            u, ok = minimise(u, progress, multipliers)
            return (u, multipliers), ok
        state = (u, multipliers, jnp.array(True), jnp.array(0), jnp.array(jnp.inf, u.dtype))
        u, multipliers, ok, _, residual = jax.lax.while_loop(unfinished, augmented_lagrangian_round, state)
        return (u, multipliers), ok & (residual <= 0.5 * settings.penetration_tol)

    dtype = scene.length.dtype
    start = (jnp.zeros(n + 1, dtype), jnp.zeros(_n_contact_points(settings), dtype))
    progresses = jnp.arange(1, settings.n_steps + 1, dtype=dtype) / settings.n_steps
    (u, _), solved = jax.lax.scan(load_step, start, progresses)

    turning, base_angle = unpack(u)
    nodes = _nodes(scene, turning, base_angle)
    if scene.sdf is None:
        max_penetration = jnp.zeros((), dtype)
        in_contact = jnp.zeros(n + 1, bool)
    else:
        check = _segment_samples(nodes, _CHECK_SAMPLES)
        max_penetration = jnp.maximum(0.0, jnp.max(scene.half_thickness - _distance(scene, check)))
        in_contact = _distance(scene, nodes) <= scene.half_thickness + settings.contact_tol
    return RodClosure(
        points=_mirror(scene, nodes),
        turning=turning,
        base_angle=base_angle,
        energy=_elastic_energy(turning, base_angle, scene, 1.0),
        max_penetration=max_penetration,
        in_contact=in_contact,
        converged=jnp.all(solved) & (max_penetration <= settings.penetration_tol),
    )


def _objective(turning, base_angle, scene: _Scene, settings: _SolverSettings, progress, multipliers):
    """Elastic energy plus the augmented-Lagrangian contact term (see :func:`rod_energy`)."""
    energy = _elastic_energy(turning, base_angle, scene, progress)
    if scene.sdf is None:
        return energy
    points = _segment_samples(_nodes(scene, turning, base_angle), settings.samples_per_segment)
    gap = (scene.half_thickness - _distance(scene, points)) / scene.length
    shifted = jnp.maximum(0.0, multipliers + settings.penalty * gap)
    return energy + jnp.sum(shifted**2 - multipliers**2) / (2 * settings.penalty)


def _elastic_energy(turning, base_angle, scene: _Scene, progress):
    """Bending plus base-spring energy over mean(k) / L at a fraction ``progress`` of kappa0."""
    n = turning.shape[0]
    voronoi = _voronoi(n)
    rest = 2 * scene.theta_entire * progress * voronoi  # kappa0 l_i, with lengths in units of L
    bending = jnp.sum(_stiffness(n, scene.stiffness_ratio) * (turning - rest) ** 2 / (2 * voronoi))
    compliant = scene.base_compliance > 0
    safe_compliance = jnp.where(compliant, scene.base_compliance, 1.0)
    return bending + jnp.where(compliant, base_angle**2 / (2 * safe_compliance), 0.0)


# ---------------------------------------------------------------------------------------------
# Geometry


def _voronoi(n: int) -> Float[Array, " n"]:
    """(n,) length each node represents, in units of L: half a segment at the base, else one."""
    return jnp.concatenate([jnp.array([0.5]), jnp.ones(n - 1)]) / n


def _stiffness(n: int, ratio) -> Float[Array, " n"]:
    """(n,) bending stiffness at the nodes: linear from ``ratio`` (base) to 1 (tip), mean 1."""
    position = jnp.arange(n) / n
    return 2.0 / (ratio + 1.0) * (ratio + (1.0 - ratio) * position)


def _nodes(scene: _Scene, turning, base_angle) -> Float[Array, "m1 2"]:
    """(M+1, 2) rod nodes in the left-finger frame, mm."""
    direction = base_angle + jnp.cumsum(turning)
    step = scene.length / turning.shape[0] * jnp.stack([jnp.sin(direction), jnp.cos(direction)], -1)
    return scene.base + jnp.concatenate([jnp.zeros((1, 2), step.dtype), jnp.cumsum(step, 0)])


def _segment_samples(nodes, per_segment: int) -> Float[Array, "p 2"]:
    """(M * per_segment + 1, 2) points at equal steps along the rod, base to tip."""
    t = jnp.arange(per_segment, dtype=nodes.dtype)[None, :, None] / per_segment
    inner = nodes[:-1, None, :] + t * (nodes[1:] - nodes[:-1])[:, None, :]
    return jnp.concatenate([inner.reshape(-1, 2), nodes[-1:]])


def _mirror(scene: _Scene, points):
    """Reflect left-frame points into the finger's hand (identity for the left finger)."""
    x = scene.base[0] + scene.handedness * (points[..., 0] - scene.base[0])
    return jnp.stack([x, points[..., 1]], axis=-1)


def _distance(scene: _Scene, points):
    """Signed distance (mm) from the object to left-frame points, through the hand's mirror."""
    return scene.sdf.distance(_mirror(scene, points))


def _n_contact_points(settings: _SolverSettings) -> int:
    return settings.n_segments * settings.samples_per_segment + 1


# ---------------------------------------------------------------------------------------------
# Inputs


def _make_scene(base, theta_entire, length, half_thickness, sdf, mechanics: RodMechanics, handedness):
    """Pack the traced inputs as arrays of the default float dtype."""
    dtype = jnp.result_type(float)
    scalar = lambda value: jnp.asarray(value, dtype)  # noqa: E731
    return _Scene(
        base=jnp.asarray(base, dtype),
        theta_entire=scalar(theta_entire),
        length=scalar(length),
        half_thickness=scalar(half_thickness),
        handedness=scalar(handedness),
        stiffness_ratio=scalar(mechanics.stiffness_ratio),
        base_compliance=scalar(mechanics.base_compliance),
        sdf=sdf,
    )


def _solver_settings(mechanics: RodMechanics) -> _SolverSettings:
    return _SolverSettings(*(getattr(mechanics, field) for field in _SolverSettings._fields))


def _check_inputs(base, theta_entire, length, half_thickness, sdf, handedness) -> None:
    """Validate the concrete inputs of :func:`close_rod`; traced ones pass through."""
    if not isinstance(base, jax.core.Tracer):
        point = np.asarray(base, dtype=float) if np.size(base) == 2 else None
        if point is None or point.shape != (2,) or not np.all(np.isfinite(point)):
            raise SoftgripError(f"close_rod: base must be a finite (x, y) point in mm, got {base!r}")
    _require_float("close_rod: theta_entire", theta_entire, lower=0.0, upper=math.pi / 2)
    _require_float("close_rod: length", length, lower=0.0, strict=True)
    _require_float("close_rod: half_thickness", half_thickness, lower=0.0)
    if not isinstance(handedness, jax.core.Tracer) and float(handedness) not in (1.0, -1.0):
        raise SoftgripError(f"close_rod: handedness must be +1 (left) or -1 (right), got {handedness!r}")
    if sdf is not None and not callable(getattr(sdf, "distance", None)):
        raise SoftgripError(
            f"close_rod: sdf must have a .distance(points) method (e.g. softgrip_jax.PolygonSDF) "
            f"or be None, got {type(sdf).__name__}"
        )
