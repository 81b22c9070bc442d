"""Forward kinematics of an N-link chain and the PCC shape (eqs. 1-3).

Every shape in this package is a pair ``(psi, turning)``: ``psi`` rotates the whole finger about
its base, ``turning[k]`` is the turning angle at joint k. Link k points at

    alpha_k = psi + sum_{j<k} turning_j + turning_k / 2

and P_{k+1} = P_k + (L/N) (sin alpha_k, cos alpha_k). Piecewise constant curvature with entire
bending angle Theta is psi = 0, turning = 2 Theta / N, which gives alpha_k = Theta (2k+1)/N (eq. 3)
and joints on the arc whose chords to the base make the angles Theta k / N (eq. 2).
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
