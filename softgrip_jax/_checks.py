"""Argument types of the public entry points, checked in Python before anything is traced.

A wrong type (``None`` or a numpy array where an SDF goes, a profile's plain dict where a gripper
goes) would otherwise fail deep inside as an ``AttributeError`` or ``TypeError``. Each check is an
``isinstance`` test on the Python object: under ``jax.jit`` an equinox module keeps its class (its
array leaves become tracers), so the checks cost nothing at run time and never touch the device
(but for a polygon whose vertices are no longer the array its edge index was made with: those are
compared by value once).
"""

from __future__ import annotations

from typing import Any

from softgrip_base.errors import SoftgripError

_SDF_HINT = ("pass a softgrip_jax.SDFGrid or PolygonSDF: from a camera frame softgrip_vision.object_sdf.object_sdf(mask, "
             "camera) or softgrip_vision.scene.frame_scene(...).sdf, from numbers SDFGrid(values, origin, spacing) or "
             "PolygonSDF(vertices)")
_FINGER_HINT = "pass a softgrip_jax.FingerModel(length, theta_entire, half_thickness, n_links) (mm, rad)"
_GRIPPER_HINT = ("pass a softgrip_jax.Gripper(left, right, base_separation); from a calibration profile: "
                 "softgrip_calib.profile.load_profile(path).gripper(), or CalibrationProfile.from_dict(d).gripper() for a "
                 "dict read from one")


def describe(value: Any) -> str:
    """A few words on what ``value`` is, for a message: ``None``, ``a numpy array of shape (3, 3)``,
    ``a dict with keys 'fingers', ...``, ``a list``, ``a str``."""
    if value is None:
        return "None"
    shape = getattr(value, "shape", None)
    if shape is not None and hasattr(value, "dtype"):
        kind = "a numpy array" if type(value).__module__ == "numpy" else "an array"
        return f"{kind} of shape {tuple(shape)}"
    if isinstance(value, dict):
        keys = ", ".join(repr(k) for k in list(value)[:4])
        return f"a dict with keys {keys}{', ...' if len(value) > 4 else ''}" if value else "an empty dict"
    name = type(value).__name__
    return f"{'an' if name[:1].lower() in 'aeiou' else 'a'} {name}"


def check_sdf(sdf: Any, name: str = "sdf") -> None:
    """Raise :class:`SoftgripError` unless ``sdf`` is a :class:`~softgrip_jax.AbstractSDF`."""
    from softgrip_jax._sdf import AbstractSDF, PolygonSDF

    if not isinstance(sdf, AbstractSDF):
        raise SoftgripError(f"{name}: got {describe(sdf)}; {_SDF_HINT}")
    if isinstance(sdf, PolygonSDF):
        sdf.check_cells()


def check_finger(finger: Any, name: str = "finger") -> None:
    """Raise :class:`SoftgripError` unless ``finger`` is a :class:`~softgrip_jax.FingerModel`."""
    from softgrip_jax._model import FingerModel

    if not isinstance(finger, FingerModel):
        raise SoftgripError(f"{name}: got {describe(finger)}; {_FINGER_HINT}")


def check_gripper(gripper: Any, name: str = "gripper") -> None:
    """Raise :class:`SoftgripError` unless ``gripper`` is a :class:`~softgrip_jax.Gripper`
    (a calibration profile, as a ``CalibrationProfile`` or its dict, is named with the fix)."""
    from softgrip_jax._model import Gripper

    if isinstance(gripper, Gripper):
        return
    if callable(getattr(gripper, "gripper", None)):  # a CalibrationProfile
        raise SoftgripError(f"{name}: got {describe(gripper)} (a calibration profile); pass its .gripper()")
    raise SoftgripError(f"{name}: got {describe(gripper)}; {_GRIPPER_HINT}")
