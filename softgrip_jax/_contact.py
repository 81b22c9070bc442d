"""Contact prediction (paper section IV-B, eqs. 5-8) as a sweep over the object's SDF.

The finger closes from straight (s = 0) to its calibrated shape (s = Theta). At closing progress s
it is the PCC chain with turning angles 2 s / N (or, with ``sweep="rigid"``, the straight finger
rotated about its base by s: the paper's "same angle beta for every link"). In both readings s is
the angle of the base-tip chord. The clearance

    g(s) = min over centreline stations of (sdf(station) - r)

is positive while the finger is free. The first contact s1 is the smallest root of g: bracketed on
a coarse grid of s values (one vectorised SDF lookup), then refined by Newton's method kept inside
that bracket (:class:`BracketedNewton`, an optimistix root finder), so that derivatives of s1 come from the implicit
function theorem. Batched code takes the first :data:`ROOT_STEPS_TOGETHER` iterations for every
touching finger at once (:func:`start_root`) and continues only the few not converged
(:func:`finish_root`). Then (eqs. 6-8):

* P_g1: the touching point of the finger (nearest the base), L_g1 its arc length, N_g1 = L_g1 N / L;
* P_o1: P_g1 moved onto the object surface along the SDF's normal;
* angles are measured between centreline points against the object dilated by r (the paper's
  finger is a line; see the comment in :func:`predict_contact_local`);
* N_g1 within half a link of N: contact at the tip only (case b);
* otherwise the circle of radius L_g2 = L - L_g1 around P_g1 is intersected with the dilated
  object boundary; the crossing with the largest y is where the tip would touch (P_o2 is its
  foot on the surface); Theta_o1 and Theta_o1o2 are the angles of P_base->P_g1 and of P_g1->that
  crossing from the vertical, Theta_remain = Theta - Theta_o1 (eq. 8); the tip
  reaches P_o2 (case c) if Theta_remain >= Theta_o1o2, else only the other area touches (case d).

All coordinates here are in the finger's frame: base at ``base``, hanging toward +y, curling
toward +x (see :mod:`softgrip_jax._frames` for other placements).
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from softgrip_base.errors import SoftgripError
from softgrip_jax._kinematics import chain_points, pcc_chord_joints, pcc_joints, pcc_turning
from softgrip_jax._model import FingerModel
from softgrip_jax._safe import direction_angle, safe_divide, unit_direction
from softgrip_jax._sdf import AbstractSDF, surface_point


class ContactCase(enum.IntEnum):
    """The four contact cases of the paper's Fig. 6."""

    NONE = 0  #: (a) no contact
    TIP = 1  #: (b) contact only at the tip
    TIP_AND_OTHER = 2  #: (c) contact at the tip and another area
    OTHER = 3  #: (d) contact at an area other than the tip


#: Names of the cases, indexed by :class:`ContactCase` value (the JSON and CLI spelling).
CASE_NAMES: tuple[str, ...] = ("none", "tip", "tip_and_other", "other")


class ContactConfig(eqx.Module):
    """How the contact sweep is discretised (all static: changing one recompiles).

    Attributes:
        sweep: ``"pcc"`` (default) closes the finger along its PCC shapes; ``"rigid"`` rotates the
            straight finger about its base (the paper's Fig. 7 read literally).
        n_sweep: values of s on the coarse bracketing grid over [0, Theta]. The tip travels about
            L Theta / (n_sweep - 1) between two of them; the finger (2r thick) could only pass
            through an object between grid values if that travel exceeded 2r plus the object's
            thickness, and a graze shallower than about travel^2 / (8 r) can be missed. The default
            12 keeps the travel under 2r for a 52 mm finger with r = 4 mm at any Theta < pi/2
            (7.4 mm at most; at Theta = 0.5 it is 2.4 mm, and grazes under 0.2 mm can be missed).
        n_stations: centreline sample points at least, base to tip: every link gets
            ceil((n_stations - 1) / N) equally spaced points (plus the tip), so that the sampling
            is about as fine for any N. Between stations the distance is refined by a parabola.
        n_circle: samples of the second-contact circle (Fig. 8).
        root_atol: tolerance of the first-contact root, on s (rad) and on g (mm).
        root_max_steps: iteration cap of the root finder.
        tip_tolerance: N_g1 within this many links of N counts as the tip (case b).
    """

    sweep: Literal["pcc", "rigid"] = eqx.field(static=True, default="pcc")
    n_sweep: int = eqx.field(static=True, default=12)
    n_stations: int = eqx.field(static=True, default=21)
    n_circle: int = eqx.field(static=True, default=64)
    root_atol: float = eqx.field(static=True, default=1e-4)
    root_max_steps: int = eqx.field(static=True, default=16)
    tip_tolerance: float = eqx.field(static=True, default=0.5)

    def __check_init__(self):
        if self.sweep not in ("pcc", "rigid"):
            raise SoftgripError(f"ContactConfig.sweep must be 'pcc' or 'rigid', got {self.sweep!r}")
        for name, low in (("n_sweep", 2), ("n_stations", 2), ("n_circle", 8), ("root_max_steps", 1)):
            value = getattr(self, name)
            if not isinstance(value, int) or value < low:
                raise SoftgripError(f"ContactConfig.{name} must be an integer >= {low}, got {value!r}")

    def per_link(self, n_links: int) -> int:
        """Stations on each link for a chain of ``n_links`` links."""
        return max(1, -(-(self.n_stations - 1) // n_links))


class Contact(eqx.Module):
    """Predicted contact of one finger (finger-frame coordinates, mm and rad).

    Fields that a case does not define (for example P_o2 without a second contact) hold finite
    placeholder values; read them through ``case``. Without a first contact inside (0, Theta]
    (case none, and an object that overlaps the open finger, reported as case none with
    ``initial_overlap``) they describe the closed finger's tip (:func:`free_contact`).
    """

    case: Int[Array, ""]  #: a :class:`ContactCase` value
    touches: Bool[Array, ""]  #: any contact in [0, Theta]
    s1: Float[Array, ""]  #: closing progress (chord angle, rad) at first contact; Theta if none
    p_g1: Float[Array, "2"]  #: first contact point on the finger centreline (mm)
    p_o1: Float[Array, "2"]  #: first contact point on the object surface (mm)
    p_o2: Float[Array, "2"]  #: second contact point on the object surface (mm), if any
    has_second: Bool[Array, ""]  #: the circle of Fig. 8 crosses the object boundary
    l_g1: Float[Array, ""]  #: arc length from the base to P_g1 (eq. 6, mm)
    n_g1: Float[Array, ""]  #: L_g1 / L * N (eq. 7), fractional
    theta_o1: Float[Array, ""]  #: angle of P_base -> P_g1 from the vertical (rad)
    theta_o1o2: Float[Array, ""]  #: angle of P_g1 -> the tip's second contact from the vertical (rad)
    theta_remain: Float[Array, ""]  #: Theta - Theta_o1 (eq. 8, rad)
    initial_overlap: Bool[Array, ""]  #: the object already overlaps the open finger (s = 0)
    root_converged: Bool[Array, ""]  #: the root finder met its tolerance


def sweep_shape(
    finger: FingerModel, s: Float[Array, ""], sweep: Literal["pcc", "rigid"] = "pcc"
) -> tuple[Float[Array, ""], Float[Array, " n"]]:
    """``(psi, turning)`` of the finger at closing progress ``s`` (its base-tip chord angle, rad):
    the base rotation (rad) and the (N,) turning angles (rad), for :func:`forward_kinematics`.

    Example:
        >>> import jax.numpy as jnp
        >>> f = FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=2)
        >>> psi, turning = sweep_shape(f, jnp.array(0.3))            # PCC: psi 0, turning 2 s / N
        >>> float(psi), [round(float(t), 3) for t in turning]
        (0.0, [0.3, 0.3])
        >>> psi, turning = sweep_shape(f, jnp.array(0.3), "rigid")   # the straight finger, rotated by s
        >>> round(float(psi), 3), turning.tolist()
        (0.3, [0.0, 0.0])
    """
    if sweep == "pcc":
        return jnp.zeros_like(s), pcc_turning(s, finger.n_links)
    return s, jnp.zeros((finger.n_links,), dtype=jnp.result_type(s))


def _sweep_chain(finger, base, s, config):
    """Joints (N+1, 2) mm, stations (M, 2) mm and their arc lengths (M,) mm of the finger at
    closing progress ``s`` (rad), drawn by :func:`~softgrip_jax._kinematics.chain_points`."""
    return chain_points(base, *sweep_shape(finger, s, config.sweep), finger.length, config.per_link(finger.n_links))


def _interior_vertices(
    d: Float[Array, "*batch m"], spacing: Float[Array, ""]
) -> tuple[Float[Array, "*batch m-2"], Float[Array, "*batch m-2"]]:
    """Minimum of the parabola through each interior station's distance and its neighbours'.

    Stations sample the centreline a few per link (``spacing`` mm apart); the true minimum distance
    usually lies between two of them. Returns (value, offset in station spacings, within
    [-1/2, 1/2]) for stations 1 ... m-2; a non-convex triple keeps its own value. A distance is
    1-Lipschitz, so no value is allowed below ``d - spacing / 2``: this keeps a discontinuity (an
    SDF grid's border) from posing as a deep minimum. Computed on slices, without shifted copies of
    ``d``: the bracket evaluates it on n_sweep x stations values per candidate.
    """
    d_prev, d_mid, d_next = d[..., :-2], d[..., 1:-1], d[..., 2:]
    slope = 0.5 * (d_next - d_prev)
    curvature = d_prev - 2.0 * d_mid + d_next
    convex = curvature > 0
    offset = jnp.where(convex, jnp.clip(-slope / jnp.where(convex, curvature, 1.0), -0.5, 0.5), 0.0)
    value = d_mid + slope * offset + 0.5 * curvature * offset**2
    return jnp.maximum(value, d_mid - 0.5 * spacing), offset


def _parabola_vertices(
    d: Float[Array, "*batch m"], spacing: Float[Array, ""]
) -> tuple[Float[Array, "*batch m"], Float[Array, "*batch m"]]:
    """:func:`_interior_vertices` for every station: the two end stations keep their own value."""
    if d.shape[-1] < 3:
        return d, jnp.zeros_like(d)
    value, offset = _interior_vertices(d, spacing)
    ends = jnp.zeros_like(d[..., :1])
    return (jnp.concatenate([d[..., :1], value, d[..., -1:]], axis=-1),
            jnp.concatenate([ends, offset, ends], axis=-1))


def _chain_clearance(distances: Float[Array, "*batch m"], spacing, r: Float[Array, ""]) -> Float[Array, "*batch"]:
    """g: the smallest centreline clearance (mm), refined between stations ``spacing`` mm apart
    (the minimum of :func:`_parabola_vertices`, without concatenating its ends)."""
    d = distances
    ends = jnp.minimum(d[..., 0], d[..., -1])
    if d.shape[-1] < 3:
        return ends - r
    return jnp.minimum(jnp.min(_interior_vertices(d, spacing)[0], axis=-1), ends) - r


def _station_spacing(finger, config):
    return finger.length / (finger.n_links * config.per_link(finger.n_links))


#: Stations around the first-touching one that the root finder watches.
_ROOT_WINDOW = 5

#: Clearance (mm) the root finder's function keeps at least at the bracket's lower end
#: (:func:`refine_contact`).
_END_MARGIN_MM = 1e-6


def _window_stations(finger, base, s, config, first):
    """The ``_ROOT_WINDOW`` stations from index ``first`` at closing progress ``s``, in closed form.

    Joints of the PCC sweep lie on a circle through the base (eq. 2,
    :func:`~softgrip_jax._kinematics.pcc_chord_joints`): joint i is at chord angle s i / N and
    distance (L/N) sin(s i / N) / sin(s / N); of the rigid sweep, at i L / N along the direction s.
    The same stations as :func:`_sweep_chain`'s to rounding, but only the joints the window needs
    are computed: the root finder evaluates this (and its derivative in s) at every iteration, for
    every touching candidate, where drawing the whole chain would cost N joints for five stations.
    """
    n, per_link = finger.n_links, config.per_link(finger.n_links)
    index = first + jnp.arange(_ROOT_WINDOW)
    if per_link == 1:  # the stations are joints: no link ends to interpolate between
        ends = index.astype(s.dtype)
    else:
        link = jnp.minimum(index // per_link, n - 1)
        frac = ((index - link * per_link) / per_link).astype(s.dtype)
        ends = jnp.stack([link, link + 1]).astype(s.dtype)  # (2, window) joint indices
    if config.sweep == "pcc":
        joints = base + pcc_chord_joints(s, ends, n, finger.length)
    else:
        joints = base + (finger.length / n) * ends[..., None] * unit_direction(s)
    if per_link == 1:
        return joints
    return joints[0] + frac[:, None] * (joints[1] - joints[0])


def _window_clearance(finger, dist, base, s, config, first):
    """g restricted to a window of stations (mm)."""
    d = dist(_window_stations(finger, base, s, config, first))
    return _chain_clearance(d, _station_spacing(finger, config), finger.half_thickness)


def _point_at_arc_length(joints, length, l):
    """The centreline point (mm) at arc length ``l`` along a chain of straight links."""
    n = joints.shape[0] - 1
    u = jnp.clip(l / length * n, 0.0, n)
    k = jnp.clip(jnp.floor(u).astype(jnp.int32), 0, n - 1)
    t = u - k
    return joints[k] + t * (joints[k + 1] - joints[k])


def _second_contact(dist, centre, radius, n_circle, coarse=None):
    """Crossings of the circle (``centre``, ``radius``) with the zero level of ``dist`` (Fig. 8).

    Returns (has_crossing, crossing point, angle of centre -> crossing): the crossing with the
    largest y, i.e. the direction nearest the downward vertical. ``coarse`` (optional): a cheaper
    lookup (SDFGrid's bilinear one) that finds the crossings on the ``n_circle`` samples; the two
    samples around the chosen one are then looked up with ``dist``, which places it.
    """
    dtype = centre.dtype
    step = 2.0 * jnp.pi / n_circle
    phi = (jnp.arange(n_circle, dtype=dtype) - n_circle // 2) * step  # [-pi, pi)
    points = centre + radius * unit_direction(phi)
    d = (dist if coarse is None else coarse)(points)
    d_next = jnp.roll(d, -1)
    crossing = (d > 0) != (d_next > 0)

    def angle_between(d, d_next, phi):
        angle = phi + jnp.clip(safe_divide(d, d - d_next, 0.5), 0.0, 1.0) * step
        return jnp.where(angle >= jnp.pi, angle - 2.0 * jnp.pi, angle)

    angle = angle_between(d, d_next, phi)
    # Nearest the downward vertical: the largest cos(angle), i.e. the smallest |angle| in [-pi, pi)
    # (compared without computing the 64 cosines).
    ranking = jnp.where(crossing, -jnp.abs(angle), -jnp.inf)
    best = jnp.argmax(ranking)
    has = jnp.any(crossing)
    chosen = angle[best]
    if coarse is not None:
        ends = dist(points[jnp.stack([best, (best + 1) % n_circle])])
        chosen = angle_between(ends[0], ends[1], phi[best])
    theta_o1o2 = jnp.where(has, chosen, 0.0)
    return has, centre + radius * unit_direction(theta_o1o2), theta_o1o2


def predict_contact(
    finger: FingerModel,
    sdf: AbstractSDF,
    base: Float[ArrayLike, "2"],
    config: ContactConfig = ContactConfig(),
) -> Contact:
    """Predict where the finger hanging from ``base`` first touches the object, and its case.

    Args:
        finger: the calibrated finger.
        sdf: the object's signed distance (mm), in the same coordinates as ``base``.
        base: (2,) finger base in mm. The finger hangs toward +y and curls toward +x.
        config: sweep discretisation.

    Returns:
        A :class:`Contact` (mm, rad). Pure, jit-, vmap- and grad-compatible.

    Example:
        >>> import jax.numpy as jnp
        >>> from softgrip_jax import CASE_NAMES, PolygonSDF
        >>> f = FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=10)
        >>> import jax  # jitted, the call compiles once: faster than running op by op
        >>> c = jax.jit(predict_contact)(f, PolygonSDF.regular((20.0, 30.0), 8.0), jnp.zeros(2))
        >>> CASE_NAMES[int(c.case)], bool(c.touches), round(float(c.n_g1), 1)  # N_g1: links to P_g1
        ('other', True, 7.6)
    """
    from softgrip_jax._checks import check_finger, check_sdf

    check_finger(finger)
    check_sdf(sdf)
    base = jnp.asarray(base, finger.length.dtype)
    contact = predict_contact_local(finger, lambda q: sdf.distance(q + base), config,
                                    coarse=(lambda q: sdf.coarse_distance(q + base)) if sdf.has_coarse_lookup else None)
    return eqx.tree_at(lambda c: (c.p_g1, c.p_o1, c.p_o2), contact,
                       (contact.p_g1 + base, contact.p_o1 + base, contact.p_o2 + base))


def predict_contact_local(
    finger: FingerModel,
    dist: Callable[[Float[Array, "*batch 2"]], Float[Array, "*batch"]],
    config: ContactConfig = ContactConfig(),
    coarse: Callable[[Float[Array, "*batch 2"]], Float[Array, "*batch"]] | None = None,
) -> Contact:
    """:func:`predict_contact` in the finger's own frame: base at the origin, ``dist`` the object's
    signed distance as a function of finger-frame points (mm); ``coarse`` a cheaper approximation
    of it for the coarse bracketing grid and the second contact's circle
    (:meth:`~softgrip_jax._sdf.AbstractSDF.coarse_distance`; None: ``dist``).

    The scene enters only through ``dist``, so a finger placed by a frame (translated, rotated or
    mirrored) closes over that frame instead of carrying it inside the SDF: the SDF, usually a large
    grid, then stays one unbatched operand however many candidates are batched.

    Example:
        >>> import jax.numpy as jnp
        >>> from softgrip_jax import PolygonSDF
        >>> f = FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=10)
        >>> disc = PolygonSDF.regular((20.0, 30.0), 8.0)
        >>> import jax
        >>> c = jax.jit(lambda f: predict_contact_local(f, lambda q: disc.distance(q + jnp.array([0.0, 0.0]))))(f)
        >>> round(float(c.s1), 3) < 0.5  # the chord angle at first touch, before Theta
        True
    """
    bracket = bracket_contact(finger, dist if coarse is None else coarse, config)
    refined = refine_contact(finger, dist, bracket, config, coarse=coarse)
    free = free_contact(finger, bracket)
    return jax.tree_util.tree_map(lambda a, b: jnp.where(bracket.needs_root, a, b), refined, free)


class Bracket(eqx.Module):
    """The coarse first-contact search of one finger (finger frame): where the root lies.

    The first stage of :func:`predict_contact_local`; batched code refines (:func:`refine_contact`)
    only the fingers whose bracket ``needs_root`` and gives the others :func:`free_contact`.
    """

    touches: Bool[Array, ""]  #: some grid value of s in [0, Theta] has the finger touching
    initial_overlap: Bool[Array, ""]  #: it touches already at s = 0
    lower: Float[Array, ""]  #: the grid value of s before the first touching one (rad)
    upper: Float[Array, ""]  #: the first touching grid value (rad)
    start: Float[Array, ""]  #: the root finder's start inside [lower, upper] (rad)
    first: Int[Array, ""]  #: the first of the root window's stations

    @property
    def needs_root(self) -> Bool[Array, ""]:
        """A first contact lies inside (0, Theta]: it is refined by :func:`refine_contact`."""
        return self.touches & ~self.initial_overlap


def sweep_parts(config: ContactConfig) -> tuple[tuple[int, int], tuple[int, int]] | None:
    """The two parts of the coarse grid that batched code brackets one after the other: values
    0 ... h-1, then h-1 ... n_sweep-1 for only the fingers still free after the first part (the
    part after starts on the last free value, so that it can bracket a touch on its first new
    value). ``None`` for a grid too short to be worth splitting."""
    n = config.n_sweep
    if n < 6:
        return None
    h = n // 2
    return (0, h), (h - 1, n)


def bracket_contact(
    finger: FingerModel,
    dist: Callable[[Float[Array, "*batch 2"]], Float[Array, "*batch"]],
    config: ContactConfig = ContactConfig(),
    rows: tuple[int, int] | None = None,
) -> Bracket:
    """The clearance g at every value of s on the coarse grid (one vectorised lookup of
    n_sweep x stations points) and the first grid interval where it reaches zero (eq. 5).

    ``rows`` (static): ``(first, stop)`` looks only at the grid values first ... stop-1 (all of
    them by default). Batched code brackets the first part of :func:`sweep_parts` for every finger
    and the second only for those still free, with the same result as one bracket over the whole
    grid for about 3/4 of the lookups. A part that starts after s = 0 takes its first value as free
    (the part before found it so) and brackets nothing before it.
    """
    dtype = finger.length.dtype
    base = jnp.zeros(2, dtype)
    theta, r = finger.theta_entire, finger.half_thickness
    spacing = _station_spacing(finger, config)
    s_grid = theta * jnp.linspace(0.0, 1.0, config.n_sweep, dtype=dtype)
    first_row, stop = rows or (0, config.n_sweep)
    s_rows = s_grid[first_row:stop]
    points = jax.vmap(lambda s: _sweep_chain(finger, base, s, config)[1])(s_rows)
    d_grid = dist(points)  # (rows, stations)
    hit = _chain_clearance(d_grid, spacing, r) <= 0
    if first_row > 0:
        hit = hit.at[0].set(False)
    touches = jnp.any(hit)
    j = jnp.argmax(hit)
    initial_overlap = hit[0]
    need_root = touches & ~initial_overlap
    lower = s_rows[jnp.maximum(j - 1, 0)]
    if first_row > 0:  # without a touch, the bracket of the whole grid: [0, 1)
        lower = jnp.where(touches, lower, s_grid[0])
    upper = jnp.where(need_root, s_rows[j], lower + 1.0)

    # Which station touches first inside the bracket: the earliest linear crossing. The root
    # finder then watches only a window around it, starting from that crossing.
    v_lo, v_hi = _parabola_vertices(d_grid[jnp.stack([jnp.maximum(j - 1, 0), j])], spacing)[0] - r
    crossing = jnp.where(v_hi <= 0, jnp.clip(safe_divide(v_lo, v_lo - v_hi, 0.0), 0.0, 1.0), jnp.inf)
    centre = jnp.argmin(crossing)
    n_stations = d_grid.shape[-1]
    first = jnp.clip(centre - _ROOT_WINDOW // 2, 0, max(n_stations - _ROOT_WINDOW, 0))
    # (The fraction is made finite before use: an inf in the discarded branch would still turn
    # the gradient into NaN.)
    fraction = jnp.where(need_root, jnp.min(jnp.where(jnp.isfinite(crossing), crossing, 1.0)), 0.5)
    start = lower + fraction * (upper - lower)
    return Bracket(touches=touches, initial_overlap=initial_overlap, lower=lower, upper=upper, start=start,
                   first=first)


def free_contact(finger: FingerModel, bracket: Bracket) -> Contact:
    """The :class:`Contact` of a finger whose bracket does not need a root: it closes freely
    (case none), or the object overlaps it from the start (``initial_overlap``; reported as case
    none too, since the pose collides and no deformation is predicted).

    The contact fields, undefined for these, describe the closed finger's tip: s1 = Theta
    (0 for an initial overlap), P_g1 = P_o1 = P_o2 = the tip, L_g1 = L, N_g1 = N.
    """
    theta, n = finger.theta_entire, finger.n_links
    tip = pcc_joints(finger, jnp.zeros(2, theta.dtype))[-1]
    theta_o1 = direction_angle(tip)
    false = jnp.zeros((), bool)
    return Contact(
        case=jnp.asarray(ContactCase.NONE, jnp.int32), touches=bracket.touches,
        s1=jnp.where(bracket.initial_overlap, 0.0, theta), p_g1=tip, p_o1=tip, p_o2=tip, has_second=false,
        l_g1=finger.length, n_g1=jnp.asarray(n, theta.dtype), theta_o1=theta_o1, theta_o1o2=jnp.zeros_like(theta),
        theta_remain=theta - theta_o1, initial_overlap=bracket.initial_overlap, root_converged=~false,
    )


class _BracketState(eqx.Module):
    lower: Float[Array, ""]
    upper: Float[Array, ""]
    diff: Float[Array, ""]
    value: Float[Array, ""]


class BracketedNewton(optx.AbstractRootFinder):
    """Newton's method kept inside a bracket (the safeguard of Numerical Recipes' ``rtsafe``), for
    a scalar function positive at ``options["lower"]`` and not positive at ``options["upper"]``.

    Each evaluation's sign shrinks the bracket; a Newton step that would leave it (the clearance
    g(s) is not monotone: it dips below zero and rises again when the sweep passes a corner) is
    replaced by the bracket's midpoint, so the iterates never leave a bracket that holds a root.
    Converged when the last step and |f| are both within ``atol``. ``options["diff"]`` and
    ``options["value"]`` (optional; inf by default): the last step and |f| of a search continued
    from where it stopped (one that had converged takes no step).
    """

    atol: float  # type: ignore[misc]  # optimistix's abstract fields read to mypy as having defaults
    rtol: float = 0.0
    norm: Callable = jnp.abs

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        inf = jnp.asarray(jnp.inf, f_struct.dtype)
        return _BracketState(lower=jnp.asarray(options["lower"], f_struct.dtype),
                             upper=jnp.asarray(options["upper"], f_struct.dtype),
                             diff=jnp.asarray(options.get("diff", inf), f_struct.dtype),
                             value=jnp.asarray(options.get("value", inf), f_struct.dtype))

    def step(self, fn, y, args, options, state, tags):
        value, slope, aux = jax.jvp(lambda s: fn(s, args), (y,), (jnp.ones_like(y),), has_aux=True)
        free = value > 0
        lower = jnp.where(free, y, state.lower)
        upper = jnp.where(free, state.upper, y)
        newton = y - value / jnp.where(slope == 0, 1.0, slope)
        # (Inclusive: at a root found to float precision the step rounds onto the bracket's end.)
        inside = (slope != 0) & (newton >= lower) & (newton <= upper)
        new = jnp.where(value == 0, y, jnp.where(inside, newton, 0.5 * (lower + upper)))
        return new, _BracketState(lower=lower, upper=upper, diff=new - y, value=jnp.abs(value)), aux

    def terminate(self, fn, y, args, options, state, tags):
        return (jnp.abs(state.diff) <= self.atol) & (state.value <= self.atol), optx.RESULTS.successful

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}


#: Root-finder iterations that every touching finger of a batch takes together (frozen once
#: converged), before the few that have not converged yet go on alone (:func:`finish_root`): under
#: ``vmap`` a loop runs until its slowest lane is done, and one finger in thousands that needs the
#: whole budget (Newton bouncing off a corner, then bisection) made every finger of its group wait.
ROOT_STEPS_TOGETHER = 2


class RootSearch(eqx.Module):
    """The first-contact root finder of one finger: its iterate, its bracket and the tilt of the
    function it solves (:func:`root_function`)."""

    s: Float[Array, ""]  #: the iterate (rad)
    lower: Float[Array, ""]  #: the bracket: the clearance is positive at ``lower``...
    upper: Float[Array, ""]  #: ...and not positive at ``upper`` (rad)
    diff: Float[Array, ""]  #: the last step (rad; inf before the first)
    value: Float[Array, ""]  #: |clearance| at the iterate before the last step (mm; inf before the first)
    lift: Float[Array, ""]  #: the tilt (mm) at the bracket's lower end...
    drop: Float[Array, ""]  #: ...and at its upper end

    def converged(self, config: ContactConfig) -> Bool[Array, ""]:
        """The last step and the clearance are both within ``config.root_atol``."""
        return (jnp.abs(self.diff) <= config.root_atol) & (self.value <= config.root_atol)


def root_function(finger: FingerModel, dist, bracket: Bracket, config: ContactConfig, search: RootSearch):
    """The clearance of the root window as a function of s (mm), tilted to change sign across the bracket.

    The bracket may come from a coarser lookup than ``dist`` (SDFGrid's bilinear one): where the
    two disagree at the bracket's ends (a graze of micrometres, or a window of stations whose
    clearance differs from the whole chain's) the clearance solved for is tilted by the straight
    line that makes it positive at ``lower`` and not positive at ``upper``, as the root finder
    needs. Where they agree, as almost everywhere, the tilt is exactly zero. Where there is no
    bracket, it is a harmless stand-in (root at the start, slope -1), so that the implicit
    derivative stays finite.
    """
    base = jnp.zeros(2, finger.length.dtype)
    lower, upper = bracket.lower, bracket.upper

    def fn(s):
        along = safe_divide(s - lower, upper - lower, 0.0)
        real = (_window_clearance(finger, dist, base, s, config, bracket.first)
                + search.lift - along * (search.lift + search.drop))
        return jnp.where(bracket.needs_root, real, bracket.start - s)

    return fn


def start_root(finger: FingerModel, dist, bracket: Bracket, config: ContactConfig,
               steps: int = ROOT_STEPS_TOGETHER) -> RootSearch:
    """The root search of one finger after its first ``steps`` iterations of :class:`BracketedNewton`
    (an iterate that has converged stays where it is)."""
    base = jnp.zeros(2, finger.length.dtype)
    g_lower = _window_clearance(finger, dist, base, bracket.lower, config, bracket.first)
    g_upper = _window_clearance(finger, dist, base, bracket.upper, config, bracket.first)
    inf = jnp.asarray(jnp.inf, g_lower.dtype)
    search = RootSearch(s=bracket.start, lower=bracket.lower, upper=bracket.upper, diff=inf, value=inf,
                        lift=jnp.maximum(_END_MARGIN_MM - g_lower, 0.0), drop=jnp.maximum(g_upper, 0.0))
    fn = root_function(finger, dist, bracket, config, search)
    solver = BracketedNewton(atol=config.root_atol)

    def iteration(_, search):
        state = _BracketState(lower=search.lower, upper=search.upper, diff=search.diff, value=search.value)
        s, state, _ = solver.step(lambda s, _: (fn(s), None), search.s, None, {}, state, frozenset())
        stepped = RootSearch(s=s, lower=state.lower, upper=state.upper, diff=state.diff, value=state.value,
                             lift=search.lift, drop=search.drop)
        done = search.converged(config)
        return jax.tree_util.tree_map(lambda old, new: jnp.where(done, old, new), search, stepped)

    # (A loop of a fixed count, not unrolled: its body is compiled once, and it runs as fast.)
    return jax.lax.fori_loop(0, min(steps, config.root_max_steps), iteration, search)


def finish_root(finger: FingerModel, dist, bracket: Bracket, config: ContactConfig, search: RootSearch,
                steps_taken: int = ROOT_STEPS_TOGETHER) -> RootSearch:
    """The root search continued (optimistix's root finder, from the iterate and the bracket it has
    reached) until it converges or the budget ``config.root_max_steps`` is spent."""
    remaining = config.root_max_steps - min(steps_taken, config.root_max_steps)
    if remaining <= 0:
        return search
    fn = root_function(finger, dist, bracket, config, search)

    def solve(fn_, s0):
        solution = optx.root_find(
            lambda s, _: fn_(s), BracketedNewton(atol=config.root_atol), s0,
            options=dict(lower=search.lower, upper=search.upper, diff=search.diff, value=search.value),
            throw=False, max_steps=remaining,
        )
        # The flag as a float: custom_root gives its auxiliary outputs zero tangents of their own dtype.
        return solution.value, (solution.result == optx.RESULTS.successful).astype(s0.dtype)

    # Differentiated (refine_contact takes no derivative through the search, but a JVP traced
    # through it is traced all the same), optimistix's adjoint would solve the 1x1 tangent system
    # with lineax, whose checks are host callbacks, and a program with host callbacks never enters
    # the persistent compilation cache: JAX's custom_root with a division instead.
    value, ok = jax.lax.custom_root(fn, search.s, solve, lambda g, y: y / g(jnp.ones_like(y)), has_aux=True)
    ok = ok > 0.5
    tiny = jnp.zeros_like(search.s)
    # (The solver's last step and value are within atol exactly when it succeeded.)
    return eqx.tree_at(lambda r: (r.s, r.diff, r.value), search,
                       (value, jnp.where(ok, tiny, jnp.inf), jnp.where(ok, tiny, jnp.inf)))


def refine_contact(
    finger: FingerModel,
    dist: Callable[[Float[Array, "*batch 2"]], Float[Array, "*batch"]],
    bracket: Bracket,
    config: ContactConfig = ContactConfig(),
    search: RootSearch | None = None,
    coarse: Callable[[Float[Array, "*batch 2"]], Float[Array, "*batch"]] | None = None,
) -> Contact:
    """The first contact s1 inside the bracket (a bracketed Newton root finder), where the finger
    touches (eqs. 6-7), its angles (eq. 8) and the second contact (Fig. 8): the :class:`Contact`
    of a finger whose ``bracket.needs_root``. (For any other bracket it returns finite values
    without meaning, so that it can be evaluated, and differentiated, everywhere.)

    ``search``: the finished root search (:func:`start_root`, then :func:`finish_root` where it
    has not converged), as batched code computes it; None: computed here. ``coarse``: a cheaper
    lookup that finds the second contact's crossings on the circle (None: ``dist``).
    """
    if search is None:
        search = start_root(finger, dist, bracket, config)
        # (Not behind a lax.cond on its convergence: under vmap that cond would become a select
        # over copies of every operand, the object's grid included, one per finger. A search that
        # has converged takes no step in finish_root.)
        search = finish_root(finger, dist, bracket, config, search)
    dtype = finger.length.dtype
    base = jnp.zeros(2, dtype)
    theta = finger.theta_entire
    n, r, length = finger.n_links, finger.half_thickness, finger.length
    need_root, touches, initial_overlap = bracket.needs_root, bracket.touches, bracket.initial_overlap

    # Gradients through s1 by the implicit function theorem, ds1 = -dg / (dg/ds), with JAX's own
    # custom_root around the root already found (its "solve" returns it): optimistix's adjoint
    # solves the (here 1x1) tangent system with lineax, whose checks are host callbacks under
    # reverse mode, and a program with host callbacks never enters the persistent compilation cache.
    fn = root_function(finger, dist, bracket, config, search)
    root = jax.lax.custom_root(fn, jax.lax.stop_gradient(search.s), lambda _, s: s,
                               lambda g, y: y / g(jnp.ones_like(y)))
    root_converged = search.converged(config) | ~need_root
    s1 = jnp.where(need_root, root, jnp.where(initial_overlap, 0.0, theta))

    # First contact point on the finger (eq. 6-7): the station nearest the base among those
    # touching at s1, refined between stations.
    joints, stations, arc = _sweep_chain(finger, base, s1, config)
    d = dist(stations)
    vertex, offset = _parabola_vertices(d, _station_spacing(finger, config))
    # Touching regions are local minima of the distance along the finger; of those that touch
    # (to within 1e-3 L), take the one nearest the base, as the paper takes the overlapping pixel
    # nearest P_base.
    d_prev = jnp.concatenate([jnp.full((1,), jnp.inf, d.dtype), d[:-1]])
    d_next = jnp.concatenate([d[1:], jnp.full((1,), jnp.inf, d.dtype)])
    local_min = (d <= d_prev) & (d < d_next)
    near = local_min & (vertex <= jnp.min(vertex) + 1e-3 * length)
    k = jnp.where(jnp.any(near), jnp.argmax(near), jnp.argmin(vertex))
    l_g1 = jnp.clip(arc[k] + offset[k] * (arc[1] - arc[0]), 0.0, length)
    p_g1 = _point_at_arc_length(joints, length, l_g1)
    n_g1 = l_g1 / length * n

    # The paper's finger is a line and its angles are measured to the contact itself. For a finger
    # of half-thickness r the same construction runs on the centreline against the object dilated
    # by r (distance - r): Theta_o1 aims at P_g1, and the circle of Fig. 8 is centred there and
    # crosses the dilated boundary. Aiming at the surface point P_o1 instead would put every
    # estimated centreline r deep into the object. P_o1 and P_o2 are reported on the true surface.
    theta_o1 = direction_angle(p_g1 - base)
    theta_remain = theta - theta_o1  # eq. 8

    # Second contact (Fig. 8).
    dilated = lambda q: dist(q) - r
    coarse_dilated = None if coarse is None else (lambda q: coarse(q) - r)
    has_second, p_g2, theta_o1o2 = _second_contact(dilated, p_g1, length - l_g1, config.n_circle, coarse_dilated)
    p_o1, p_o2 = jax.vmap(lambda q: surface_point(dist, q))(jnp.stack([p_g1, p_g2]))  # one traced copy

    at_tip = n_g1 >= n - config.tip_tolerance
    case = jnp.where(
        ~touches,
        ContactCase.NONE,
        jnp.where(
            at_tip,
            ContactCase.TIP,
            jnp.where(has_second & (theta_remain >= theta_o1o2), ContactCase.TIP_AND_OTHER, ContactCase.OTHER),
        ),
    ).astype(jnp.int32)
    return Contact(
        case=case, touches=touches, s1=s1, p_g1=p_g1, p_o1=p_o1, p_o2=p_o2, has_second=has_second,
        l_g1=l_g1, n_g1=n_g1, theta_o1=theta_o1, theta_o1o2=theta_o1o2, theta_remain=theta_remain,
        initial_overlap=initial_overlap, root_converged=root_converged,
    )
