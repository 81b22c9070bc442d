"""The deformation of each contact case (paper section IV-C, eq. 9).

Each case is a ``(psi, turning)`` pair drawn by the chain of :mod:`softgrip_jax._kinematics`:

* (a) no contact: psi = 0, turning = 2 Theta / N (eqs. 1-3);
* (b) tip only: the free PCC shape rotated away from the object about P_base by
  Theta_remain = Theta - Theta_o1 (eq. 8): psi = -(Theta - Theta_o1);
* (c) tip and another area: as (b) with Theta_remain = Theta - Theta_o1 - Theta_o1o2 (eq. 9);
* (d) another area only: the first N_g1 links bend so their chord reaches Theta_o1
  (turning 2 Theta_o1 / N_g1), the other N - N_g1 links bend by Theta_remain
  (turning 2 Theta_remain / (N - N_g1)); a fractional N_g1 splits one link in proportion.

All four are computed and the case selects one, so the estimate is branch-free and vmappable.
Cases (b) and (c) rotate the whole free arc about P_base as if the base were a pin; a finger
clamped at its base unbends instead, so against a clamped closure they miss the tip by
millimetres. That is the paper's model, kept faithful here.

The estimate of one finger in stages (input checks, contact, this shape, the finished
:class:`~softgrip_jax._stage.Estimate`) is :mod:`softgrip_jax._stage`; the estimator
``Geometric()`` (:mod:`softgrip_jax._estimators`) keeps this shape.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from softgrip_jax._contact import Contact
from softgrip_jax._kinematics import pcc_turning
from softgrip_jax._model import FingerModel
from softgrip_jax._safe import safe_divide


def case_shapes(finger: FingerModel, contact: Contact) -> tuple[Float[Array, "4"], Float[Array, "4 n"]]:
    """``(psi, turning)`` of the four cases (a)-(d), stacked in :class:`ContactCase` order: psi (4,)
    rad and turning (4, N) rad; :func:`~softgrip_jax._kinematics.forward_kinematics` ``(base, psi[k],
    turning[k], L)`` draws case k.

    Example:
        >>> import jax.numpy as jnp
        >>> from softgrip_jax import ContactCase, PolygonSDF, predict_contact
        >>> f = FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=10)
        >>> import jax
        >>> c = jax.jit(predict_contact)(f, PolygonSDF.regular((20.0, 30.0), 8.0), jnp.zeros(2))
        >>> psi, turning = case_shapes(f, c)
        >>> psi.shape, turning.shape, float(psi[ContactCase.NONE])
        ((4,), (4, 10), 0.0)
    """
    n, theta = finger.n_links, finger.theta_entire
    free = pcc_turning(theta, n)
    zero = jnp.zeros_like(theta)
    remain_b = theta - contact.theta_o1  # eq. 8
    remain_c = theta - contact.theta_o1 - contact.theta_o1o2  # eq. 9
    # (d): per-link share of the first part; link k holds clip(N_g1 - k, 0, 1) of it.
    share = jnp.clip(contact.n_g1 - jnp.arange(n, dtype=theta.dtype), 0.0, 1.0)
    rate_first = safe_divide(2.0 * contact.theta_o1, contact.n_g1)
    rate_rest = safe_divide(2.0 * contact.theta_remain, n - contact.n_g1)
    turning_d = share * rate_first + (1.0 - share) * rate_rest
    psi = jnp.stack([zero, -remain_b, -remain_c, zero])
    turning = jnp.stack([free, free, free, turning_d])
    return psi, turning


def case_shape(finger: FingerModel, contact: Contact) -> tuple[Float[Array, ""], Float[Array, " n"]]:
    """``(psi, turning)`` of the contact's own case (eq. 9): psi () rad and turning (N,) rad, in
    the finger's frame; :func:`case_shapes` selected by ``contact.case``."""
    psi_all, turning_all = case_shapes(finger, contact)
    return psi_all[contact.case], turning_all[contact.case]
