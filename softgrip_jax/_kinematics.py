"""Forward kinematics of an N-link chain and the PCC shape (eqs. 1-3).

Every shape in this package is a pair ``(psi, turning)``: ``psi`` rotates the whole finger about
its base, ``turning[k]`` is the turning angle at joint k. Link k points at

    alpha_k = psi + sum_{j<k} turning_j + turning_k / 2

and P_{k+1} = P_k + (L/N) (sin alpha_k, cos alpha_k). Piecewise constant curvature with entire
bending angle Theta is psi = 0, turning = 2 Theta / N, which gives alpha_k = Theta (2k+1)/N (eq. 3)
and joints on the arc whose chords to the base make the angles Theta k / N (eq. 2).

Every chain in the package is drawn here: :func:`forward_kinematics` (angles -> joints) and
:func:`chain_points` (angles -> joints and the stations along the links), used by the contact
sweep, the cases of eq. 9, the mechanics chain and the scores. :func:`pcc_chord_joints` is eq. 2
in closed form, for a few joints of a PCC shape without the whole chain (the contact root
finder's window).
"""

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from softgrip_jax._model import FingerModel
from softgrip_jax._safe import unit_direction


def _inclusive_cumsum(x: Float[Array, "n *rest"]) -> Float[Array, "n *rest"]:
    """Cumulative sum along the first (short) axis as a triangular matrix product.

    XLA's CPU cumsum is a reduce-window several times slower than this for chains of a few dozen
    links, and the chain is summed for every candidate and every sweep value.
    """
    n = x.shape[0]
    lower = jnp.tril(jnp.ones((n, n), x.dtype))
    return jnp.tensordot(lower, x, axes=1)


def link_angles(psi: Float[Array, ""], turning: Float[Array, " n"]) -> Float[Array, " n"]:
    """Angle alpha_k of every link from the downward vertical (rad), (N,), from the base rotation
    ``psi`` (rad) and the (N,) turning angles (rad); eq. 3 for a PCC shape.

    Example:
        >>> import jax.numpy as jnp
        >>> [round(float(a), 3) for a in link_angles(jnp.array(0.0), jnp.array([0.2, 0.2]))]  # Theta (2k+1) / N
        [0.1, 0.3]
    """
    return psi + _inclusive_cumsum(turning) - 0.5 * turning


def forward_kinematics(
    base: Float[Array, "2"],
    psi: Float[Array, ""],
    turning: Float[Array, " n"],
    length: Float[Array, ""],
) -> Float[Array, "n+1 2"]:
    """Joints P_0 (= base) ... P_N, (N+1, 2) in mm, of a chain of N = len(turning) links of length
    L/N: ``base`` (2,) mm, base rotation ``psi`` (rad), ``turning`` (N,) rad, ``length`` L mm.

    Example:
        >>> import jax.numpy as jnp
        >>> forward_kinematics(jnp.zeros(2), jnp.array(0.0), jnp.zeros(2), jnp.array(50.0)).tolist()
        [[0.0, 0.0], [0.0, 25.0], [0.0, 50.0]]
    """
    n = turning.shape[0]
    steps = (length / n) * unit_direction(link_angles(psi, turning))
    zero = jnp.zeros((1, 2), steps.dtype)
    return base + jnp.concatenate([zero, _inclusive_cumsum(steps)], axis=0)


def pcc_turning(theta: Float[Array, ""], n_links: int) -> Float[Array, " n"]:
    """Turning angles 2 Theta / N (rad), (N,), of the piecewise-constant-curvature shape (eqs. 2-3).

    Example:
        >>> import jax.numpy as jnp
        >>> pcc_turning(jnp.array(0.5), 4).tolist()
        [0.25, 0.25, 0.25, 0.25]
    """
    return jnp.full((n_links,), 2.0 * theta / n_links)


def pcc_chord_joints(
    theta: Float[Array, ""], index: Float[Array, "*k"], n_links: int, length: Float[Array, ""]
) -> Float[Array, "*k 2"]:
    """Joints P_i (mm, base at the origin) of the PCC shape with entire bending angle ``theta``
    (rad), in closed form (eq. 2): joint i lies at the chord angle theta i / N from the vertical,
    (L/N) sin(theta i / N) / sin(theta / N) from the base (i L / N as theta -> 0, by its series).
    ``index``: joint indices i as floats, any shape (*k); ``length`` L mm.

    The same joints as :func:`forward_kinematics` of ``pcc_turning(theta, N)`` to rounding, at the
    cost of the requested joints only.

    Example:
        >>> import jax.numpy as jnp
        >>> [round(v, 3) for v in pcc_chord_joints(jnp.array(0.0), jnp.array([2.0]), 2, jnp.array(50.0))[0].tolist()]
        [0.0, 50.0]
    """
    n = n_links
    chord_angle = theta * index / n
    sin_a, cos_a = jnp.sin(chord_angle), jnp.cos(chord_angle)  # shared by distance and direction
    small = jnp.abs(theta) < 1e-4
    theta_safe = jnp.where(small, 1.0, theta)
    ratio = jnp.where(small, index * (1.0 - (theta**2) * (index**2 - 1.0) / (6.0 * n**2)),
                      sin_a / jnp.sin(theta_safe / n))
    return (length / n) * ratio[..., None] * jnp.stack([sin_a, cos_a], axis=-1)


def pcc_joints(finger: FingerModel, base: Float[ArrayLike, "2"]) -> Float[Array, "joints 2"]:
    """The N+1 joints in mm of the closed, untouched finger (eqs. 1-3) hanging from ``base``.

    Example:
        >>> import jax.numpy as jnp
        >>> f = FingerModel(length=50.0, theta_entire=0.0, half_thickness=4.0, n_links=2)
        >>> pcc_joints(f, jnp.zeros(2)).tolist()
        [[0.0, 0.0], [0.0, 25.0], [0.0, 50.0]]
    """
    base = jnp.asarray(base, dtype=finger.length.dtype)
    return forward_kinematics(base, jnp.zeros_like(finger.theta_entire),
                              pcc_turning(finger.theta_entire, finger.n_links), finger.length)


def chain_stations(
    joints: Float[Array, "joints 2"], length: Float[Array, ""], per_link: int
) -> tuple[Float[Array, "m 2"], Float[Array, " m"]]:
    """Points sampled along the chain's centreline and their arc lengths from the base.

    Returns ``per_link`` equally spaced points on each link (starting at its first joint) plus
    the tip: ``m = N * per_link + 1`` points, in order from base to tip, and their arc lengths (mm).

    Example:
        >>> import jax.numpy as jnp
        >>> points, arc = chain_stations(jnp.array([[0.0, 0.0], [0.0, 10.0]]), jnp.array(10.0), 2)
        >>> points.tolist(), arc.tolist()
        ([[0.0, 0.0], [0.0, 5.0], [0.0, 10.0]], [0.0, 5.0, 10.0])
    """
    n = joints.shape[0] - 1
    t = jnp.arange(per_link, dtype=joints.dtype) / per_link
    start, step = joints[:-1], joints[1:] - joints[:-1]
    inner = start[:, None, :] + t[None, :, None] * step[:, None, :]
    points = jnp.concatenate([inner.reshape(n * per_link, 2), joints[-1:]], axis=0)
    arc = jnp.arange(n * per_link + 1, dtype=joints.dtype) * (length / (n * per_link))
    return points, arc


def chain_points(
    base: Float[Array, "2"],
    psi: Float[Array, ""],
    turning: Float[Array, " n"],
    length: Float[Array, ""],
    per_link: int,
) -> tuple[Float[Array, "n+1 2"], Float[Array, "m 2"], Float[Array, " m"]]:
    """The chain and its centreline stations: the one builder of every chain in the package.

    ``(joints, stations, arc)``: :func:`forward_kinematics`' joints (N+1, 2) mm of the shape
    ``(psi, turning)`` (rad) hanging from ``base`` (2,) mm, and :func:`chain_stations`' ``per_link``
    (static) stations per link plus the tip, (M, 2) mm with M = N per_link + 1, and their arc
    lengths (M,) mm from the base.

    Example:
        >>> import jax.numpy as jnp
        >>> joints, stations, arc = chain_points(jnp.zeros(2), jnp.array(0.0), jnp.zeros(1), jnp.array(10.0), 2)
        >>> joints.tolist(), stations.tolist(), arc.tolist()
        ([[0.0, 0.0], [0.0, 10.0]], [[0.0, 0.0], [0.0, 5.0], [0.0, 10.0]], [0.0, 5.0, 10.0])
    """
    joints = forward_kinematics(base, psi, turning, length)
    stations, arc = chain_stations(joints, length, per_link)
    return joints, stations, arc
