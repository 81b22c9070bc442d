"""The calibrated gripper: one ``FingerModel`` per finger and the base separation."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, ArrayLike

from softgrip_base.errors import SoftgripError

#: Largest accepted entire bending angle (rad). At pi/2 the PCC arc is a semicircle whose
#: base-tip chord is horizontal and eq. 4 (an arctangent) can no longer measure it.
THETA_MAX = math.pi / 2

#: Largest number of links N a finger model accepts. The estimate's work and memory grow with N
#: (some arrays with its square: N = 10**6 asked for terabytes); the paper uses 10-20 and a
#: calibration profile at most 100.
MAX_N_LINKS = 1000


def _concrete(x) -> np.ndarray | None:
    """The value of ``x`` as numpy, or None while it is being traced (jit, vmap, grad)."""
    if isinstance(x, jax.core.Tracer):
        return None
    return np.asarray(x)


def _as_float(x: ArrayLike) -> Array:
    if isinstance(x, jax.core.Tracer):
        return x
    return jnp.asarray(x, dtype=jnp.result_type(float))


class FingerModel(eqx.Module):
    """One soft finger as the paper models it (eqs. 1-3): length, entire bending angle, N links.

    Attributes:
        length: finger length L in mm (eq. 5), > 0.
        theta_entire: entire bending angle Theta in rad (eq. 4), in [0, pi/2): the angle between
            the vertical and the base-tip chord of the closed, untouched finger.
        half_thickness: half of the finger's thickness r in mm, >= 0; "in contact" means that the
            centreline is within r of the object.
        n_links: number N of rigid links (static), 1 to :data:`MAX_N_LINKS`.
        stiffness_ratio: bending stiffness at the base over that at the tip, > 0 (default 1: uniform).
            The profile is linear along the finger with mean 1; only the mechanics estimate uses it.
        base_compliance: compliance of a rotational spring at the base, >= 0, in units of the whole
            finger's bending compliance L / mean(k); 0 (default) clamps the base. Only the
            mechanics estimate uses it.

    Construction with concrete values rejects bad ones with a :class:`SoftgripError` naming the field.

    Example:
        >>> finger = FingerModel(length=52.0, theta_entire=0.5, half_thickness=4.0, n_links=20)
        >>> finger.n_links
        20
    """

    length: Float[Array, ""] = eqx.field(converter=_as_float)
    theta_entire: Float[Array, ""] = eqx.field(converter=_as_float)
    half_thickness: Float[Array, ""] = eqx.field(converter=_as_float)
    n_links: int = eqx.field(static=True)
    stiffness_ratio: Float[Array, ""] = eqx.field(converter=_as_float, default=1.0)
    base_compliance: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)

    if TYPE_CHECKING:  # the signature the converters accept (type checkers do not apply them)
        def __init__(self, length: Float[ArrayLike, ""], theta_entire: Float[ArrayLike, ""],
                     half_thickness: Float[ArrayLike, ""], n_links: int,
                     stiffness_ratio: Float[ArrayLike, ""] = 1.0,
                     base_compliance: Float[ArrayLike, ""] = 0.0) -> None: ...

    def __check_init__(self):
        if not isinstance(self.n_links, (int, np.integer)) or isinstance(self.n_links, bool) or self.n_links < 1:
            raise SoftgripError(f"FingerModel.n_links must be an integer >= 1, got {self.n_links!r}")
        if self.n_links > MAX_N_LINKS:
            raise SoftgripError(f"FingerModel.n_links must be at most {MAX_N_LINKS} (the paper uses 10-20), got "
                                f"{self.n_links}")
        checks = (
            ("length", lambda v: np.isfinite(v) and v > 0, "a finite length in mm > 0"),
            ("theta_entire", lambda v: np.isfinite(v) and 0 <= v < THETA_MAX,
             "a finite angle in radians in [0, pi/2)"),
            ("half_thickness", lambda v: np.isfinite(v) and v >= 0, "a finite half-thickness in mm >= 0"),
            ("stiffness_ratio", lambda v: np.isfinite(v) and v > 0, "a finite base-to-tip stiffness ratio > 0"),
            ("base_compliance", lambda v: np.isfinite(v) and v >= 0,
             "a finite base compliance >= 0 (0 clamps the base)"),
        )
        for name, ok, expected in checks:
            value = _concrete(getattr(self, name))
            if value is None:
                continue
            if value.shape != ():
                raise SoftgripError(f"FingerModel.{name} must be a scalar, got shape {value.shape}")
            if not ok(float(value)):
                raise SoftgripError(f"FingerModel.{name} must be {expected}, got {float(value)!r}")

    @property
    def link_length(self) -> Float[Array, ""]:
        """L / N in mm (eq. 1)."""
        return self.length / self.n_links


class Gripper(eqx.Module):
    """A two-finger gripper: a left finger curling toward +x, a right one curling toward -x.

    Attributes:
        left, right: the calibrated fingers (each has its own Theta).
        base_separation: distance W in mm between the two finger bases, > 0.

    Example:
        >>> f = FingerModel(length=52.0, theta_entire=0.5, half_thickness=4.0, n_links=10)
        >>> Gripper(left=f, right=f, base_separation=60.0).base_separation.item()
        60.0
    """

    left: FingerModel
    right: FingerModel
    base_separation: Float[Array, ""] = eqx.field(converter=_as_float)

    if TYPE_CHECKING:  # the signature the converter accepts (type checkers do not apply it)
        def __init__(self, left: FingerModel, right: FingerModel,
                     base_separation: Float[ArrayLike, ""]) -> None: ...

    def __check_init__(self):
        value = _concrete(self.base_separation)
        if value is not None and (value.shape != () or not np.isfinite(value) or value <= 0):
            raise SoftgripError(
                f"Gripper.base_separation must be a finite distance in mm > 0, got {value!r}"
            )
