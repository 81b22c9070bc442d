"""Grasp quality from the estimated contacts: planar wrenches, Coulomb friction, Ferrari-Canny.

Beyond the paper (its future work: "evaluate the grasping stability using the proposed
estimation"). The standard rigid-body measure, as in Dex-Net's ``PointGraspMetrics3D``, in the plane:

* A contact is a point ``p`` on the object, the object's outward unit normal ``n`` there, and a
  Coulomb friction cone of coefficient ``mu`` about the force the finger can push with, ``-n``.
  In the plane the cone has two edges, each a unit force ``f = normalize(-n +- mu t)`` with the
  tangent ``t = (-n_y, n_x)``.
* Each edge force gives a planar wrench ``(f_x, f_y, tau / rho)``, with the torque
  ``tau = (p - c) x f`` about the object's area centroid ``c`` and ``rho`` the object's largest
  distance from ``c`` (so torque and force are commensurate, and the measure does not change when
  object and gripper are scaled together).
* The quality is the Ferrari-Canny epsilon, L1 version: the distance from the origin to the nearest
  facet of the convex hull of every contact's edge wrenches (the largest wrench the grasp resists
  in every direction with unit total normal force). It is 0 unless the origin lies strictly
  inside the hull; force closure is ``epsilon > 0``.

The hull is exact: its facets are found among all triples of the W wrenches (a triple is a facet
when no wrench lies beyond its plane), which for the few contacts of two fingers
(:data:`CONTACTS_PER_FINGER` each, two edges a contact) is a fixed-shape, vectorised and
differentiable computation (the minimum over facets is piecewise smooth). Wrenches of contacts that
do not touch are put at the origin: inside a hull that contains the origin they change nothing,
and outside it they make the origin a vertex, where epsilon is 0 as it should be.

Which contacts a finger makes: its centreline stations within ``r + band`` of the object (the
stations that touch, so a wrapped finger contributes several), taken as :data:`CONTACTS_PER_FINGER`
contacts: the stations are cut into that many runs along the finger and each run contributes its
most pressed station. The contact point is that station moved onto the surface along the object's
normal at the station; the normal is the distance's gradient at the station, which at a corner
is the direction the finger actually pushes along, within the corner's range of normals.
"""

from __future__ import annotations

import itertools
from typing import cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from softgrip_jax._safe import safe_divide, safe_norm, tied_min
from softgrip_jax._sdf import AbstractSDF

#: Friction coefficient of silicone rubber on common dry objects (plastic, wood, cardboard, glass):
#: measured values are 0.5-1.0; 0.5 is the conservative end, and Dex-Net's default.
DEFAULT_MU = 0.5
#: Contacts each finger contributes to the quality (static: the hull's size).
CONTACTS_PER_FINGER = 3
#: An epsilon at or below this (in the unit-force L1 measure, at most about 1) is no force closure:
#: float32 rounding of an origin on a facet.
CLOSURE_EPSILON = 1e-5


class FingerContacts(eqx.Module):
    """The contacts one finger makes on the object (image-plane mm), :data:`CONTACTS_PER_FINGER` slots.

    Attributes:
        points: (K, 2) contact points on the object's surface (mm).
        normals: (K, 2) the object's outward unit normals there.
        forces: (K, 2) contact force on the object at each point, in units of the finger's mean
            bending stiffness over its length squared (EI / L^2; a clamped straight finger's tip
            moved by d mm takes 3 d / L), from the mechanics estimate's equilibrium
            (:func:`softgrip_jax._mechanics.contact_forces`); NaN for an estimate without forces
            (the geometric one), 0 for a slot without contact.
        touching: (K,) whether the slot holds a contact.
    """

    points: Float[Array, "k 2"]
    normals: Float[Array, "k 2"]
    forces: Float[Array, "k 2"]
    touching: Bool[Array, " k"]


def object_frame(sdf: AbstractSDF) -> tuple[Float[Array, "2"], Float[Array, ""]]:
    """The object's area centroid (2,) mm and ``rho`` (mm), its largest distance from the centroid,
    from :meth:`~softgrip_jax.AbstractSDF.mass_properties`."""
    return sdf.mass_properties()


def finger_contacts(
    sdf: AbstractSDF,
    stations: Float[Array, "m 2"],
    half_thickness: Float[Array, ""],
    band: Float[Array, ""],
    k: int = CONTACTS_PER_FINGER,
    distance: Float[Array, " m"] | None = None,
) -> tuple[FingerContacts, Int[Array, " k"]]:
    """The contacts of one finger from its centreline ``stations`` (M, 2) mm, base to tip, and the
    index (k,) of the station each comes from; ``distance`` (M,): the stations' signed distances
    when the caller has them already (else looked up).

    A station touches when its distance to the object is at most ``half_thickness + band`` mm. The
    stations are cut into ``k`` runs of consecutive stations; each run's contact is its least
    clear station (the most pressed), when that one touches. Forces are NaN here (see
    :func:`softgrip_jax._mechanics.contact_forces` for the mechanics estimate's).
    """
    m = stations.shape[0]
    distance = sdf.distance(stations) if distance is None else distance
    run = (np.arange(m) * k) // m  # static: which run each station is in
    member = jnp.asarray(run[None, :] == np.arange(k)[:, None])  # (k, m)
    chosen = jnp.argmin(jnp.where(member, distance[None, :], jnp.inf), axis=1)  # (k,)
    point = stations[chosen]
    d = distance[chosen]
    normals = jax.vmap(sdf.normal)(point)
    touching = d <= half_thickness + band
    contacts = FingerContacts(points=point - d[:, None] * normals, normals=normals,
                              forces=jnp.full_like(point, jnp.nan), touching=touching)
    return contacts, chosen


def edge_wrenches(
    points: Float[ArrayLike, "c 2"],
    normals: Float[ArrayLike, "c 2"],
    touching: Bool[ArrayLike, " c"],
    mu: Float[ArrayLike, ""],
    centroid: Float[ArrayLike, "2"],
    rho: Float[ArrayLike, ""],
) -> Float[Array, "c2 3"]:
    """The (2C, 3) planar wrenches ``(f_x, f_y, tau / rho)`` of the C contacts' friction-cone edges:
    unit forces ``normalize(-n +- mu t)``, ``t = (-n_y, n_x)``, torque about ``centroid``. A
    contact that does not touch gives two zero wrenches."""
    points, normals, touching = jnp.asarray(points), jnp.asarray(normals), jnp.asarray(touching)
    mu, centroid, rho = jnp.asarray(mu, points.dtype), jnp.asarray(centroid, points.dtype), jnp.asarray(rho, points.dtype)
    tangent = jnp.stack([-normals[:, 1], normals[:, 0]], axis=-1)
    edges = jnp.stack([-normals + mu * tangent, -normals - mu * tangent], axis=1)  # (c, 2, 2)
    edges = edges / jnp.maximum(safe_norm(edges), 1e-12)[..., None]
    lever = points - centroid  # (c, 2)
    torque = lever[:, None, 0] * edges[..., 1] - lever[:, None, 1] * edges[..., 0]
    wrench = jnp.concatenate([edges, safe_divide(torque, rho)[..., None]], axis=-1)  # (c, 2, 3)
    wrench = jnp.where(touching[:, None, None], wrench, 0.0)
    return wrench.reshape(-1, 3)


def _triples(w: int) -> np.ndarray:
    return np.array(list(itertools.combinations(range(w), 3)), dtype=np.int32).reshape(-1, 3)


def epsilon_l1(wrenches: Float[Array, "w 3"], tolerance: float = 1e-6) -> Float[Array, ""]:
    """The Ferrari-Canny L1 epsilon of a set of wrenches: the distance from the origin to the nearest
    facet of their convex hull when the origin lies strictly inside, else 0.

    Exact: each triple of wrenches spans a plane; it is a facet when every wrench lies on one side
    (within ``tolerance``), and the origin's distance to the hull is the smallest of the facets'
    offsets, taken with the outward normal. W is static; the work grows as W^4 / 6.

    Example (two antipodal contacts on a disc, mu = 0.5: mu / sqrt((1 + mu^2)(2 + mu^2))):
        >>> import jax.numpy as jnp
        >>> mu = 0.5
        >>> w = edge_wrenches(jnp.array([[10.0, 0.0], [-10.0, 0.0]]), jnp.array([[1.0, 0.0], [-1.0, 0.0]]),
        ...                   jnp.array([True, True]), mu, jnp.zeros(2), 10.0)
        >>> round(float(epsilon_l1(w)), 4), round(mu / ((1 + mu**2) * (2 + mu**2)) ** 0.5, 4)
        (0.2981, 0.2981)
    """
    triples = _triples(wrenches.shape[0])
    a, b, c = (wrenches[triples[:, i]] for i in range(3))  # (T, 3) each
    normal = jnp.cross(b - a, c - a)  # not normalised: the side test needs only its direction
    size2 = jnp.sum(normal * normal, axis=-1)
    spans = size2 > 1e-18
    inverse = jax.lax.rsqrt(jnp.where(spans, size2, 1.0))
    offset = jnp.sum(normal * a, axis=-1)  # (T,)
    # (W, T): each wrench's height above each plane, times |normal|. Written out, not as a matrix
    # product: XLA:CPU runs this many tiny products under vmap about twice as slowly.
    side = _heights(wrenches, normal) - offset[None, :]
    limit = tolerance / inverse
    below = jnp.all(side <= limit, axis=0) & spans  # outward normal +normal, offset = n . a
    above = jnp.all(side >= -limit, axis=0) & spans  # outward normal -normal, offset = -n . a
    offset = offset * inverse
    inf = jnp.asarray(jnp.inf, wrenches.dtype)
    nearest = jnp.minimum(jnp.min(jnp.where(below, offset, inf)), jnp.min(jnp.where(above, -offset, inf)))
    return jnp.where(jnp.isfinite(nearest), jnp.maximum(nearest, 0.0), 0.0)


def _heights(wrenches: Float[Array, "w 3"], directions: Float[Array, "d 3"]) -> Float[Array, "w d"]:
    """``wrenches @ directions.T``, as three broadcast products."""
    return cast(Array, sum(wrenches[:, i, None] * directions[None, :, i] for i in range(3)))


def _pairs(w: int) -> np.ndarray:
    return np.array(list(itertools.combinations(range(w), 2)), dtype=np.int32).reshape(-1, 2)


def closure_margin(wrenches: Float[Array, "w 3"], active: Bool[Array, " w"]) -> Float[Array, ""]:
    """The signed Ferrari-Canny margin of the ``active`` wrenches: ``min over unit u of max_i w_i . u``.

    Inside the hull it is :func:`epsilon_l1` (the support function's minimum is the nearest facet's
    offset); outside, minus the origin's distance to the hull. It is continuous where the contacts
    move continuously, so it can be linearised across the edge of force closure, where the
    epsilon is flat at 0 (:class:`~softgrip_jax._robust.Uncertainty`'s ``linear``).

    Exact: the minimising direction is the outward normal of a facet (inside), or points from the
    origin's nearest point on the hull, which lies inside a facet, on an edge or at a vertex
    (outside). So it is the smallest support among the normals (both signs) of all triples, the
    directions away from the nearest point of all pairs' segments, and away from all single
    wrenches; every other direction's support is larger. Inactive wrenches (untouching contacts)
    take no part; with none active the margin is -1.

    Example (the antipodal pair of :func:`epsilon_l1`; one contact alone is outside closure):
        >>> import jax.numpy as jnp
        >>> w = edge_wrenches(jnp.array([[10.0, 0.0], [-10.0, 0.0]]), jnp.array([[1.0, 0.0], [-1.0, 0.0]]),
        ...                   jnp.array([True, True]), 0.5, jnp.zeros(2), 10.0)
        >>> round(float(closure_margin(w, jnp.ones(4, bool))), 4)
        0.2981
        >>> round(float(closure_margin(w, jnp.array([True, True, False, False]))), 4)  # -|(-1, 0, 0)|
        -0.8944
    """
    w = wrenches.shape[0]
    triples, pairs = _triples(w), _pairs(w)
    # Inactive wrenches become copies of an active one: the supports are unchanged, and any
    # direction's support bounds the minimum from above, so extra directions do no harm.
    wrenches = jnp.where(active[:, None], wrenches, wrenches[jnp.argmax(active)])
    a, b, c = (wrenches[triples[:, i]] for i in range(3))
    normal = jnp.cross(b - a, c - a)  # (T, 3), not normalised
    size2 = jnp.sum(normal * normal, axis=-1)
    # Only the triples (pairs, single wrenches) of active wrenches: the others' directions repeat
    # theirs, and a repeated direction would weigh twice where the minimum ties (tied_min below).
    facet_ok = (size2 > 1e-18) & jnp.all(active[triples], axis=1)
    inverse = jax.lax.rsqrt(jnp.where(facet_ok, size2, 1.0))
    # Both signs of each normal from one (W, T) table: support(n) = max, support(-n) = -min.
    height = _heights(wrenches, normal)
    facets = jnp.minimum(jnp.max(height, axis=0), -jnp.min(height, axis=0)) * inverse
    p, q = wrenches[pairs[:, 0]], wrenches[pairs[:, 1]]
    along = q - p
    t = jnp.clip(safe_divide(-jnp.sum(p * along, axis=-1), jnp.sum(along * along, axis=-1)), 0.0, 1.0)
    away = -jnp.concatenate([p + t[:, None] * along, wrenches])  # from the pairs' and vertices' nearest points
    length = safe_norm(away)
    near_ok = (length > 1e-9) & jnp.concatenate([jnp.all(active[pairs], axis=1), active])
    away = away / jnp.where(near_ok, length, 1.0)[:, None]
    near = jnp.max(_heights(wrenches, away), axis=0)
    # One minimum over both kinds of direction; a symmetric grasp's mirror-image facets tie to
    # rounding, and each counts its share of the derivative (tied_min), not whichever rounds lower.
    margin = tied_min(jnp.concatenate([jnp.where(facet_ok, facets, jnp.inf), jnp.where(near_ok, near, jnp.inf)]))
    return jnp.where(jnp.any(active) & jnp.isfinite(margin), margin, -1.0)
