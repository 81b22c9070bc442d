"""Layouts of a two-finger gripper for synthetic scenes.

Coordinates are millimetres in the gripper plane (x right, y down, see ``synthetic.render``).
A finger centreline is an open polyline (K, 2), base first. The left finger curls toward +x when
the gripper closes (the project's core convention); the right finger is its mirror image.
"""

from __future__ import annotations

import numpy as np

from softgrip_base import SoftgripError


def _finger(base: np.ndarray, offsets: np.ndarray, mirror: bool, what: str) -> np.ndarray:
    """Place a centreline given as offsets (K, 2) from its base, mirrored about x if asked."""
    offsets = np.asarray(offsets, dtype=np.float64)
    if offsets.ndim != 2 or offsets.shape[1] != 2 or offsets.shape[0] < 2:
        raise SoftgripError(
            f"{what} must be a (K, 2) array of mm offsets from the base, K >= 2, got shape {offsets.shape}"
        )
    if not np.isfinite(offsets).all():
        raise SoftgripError(f"{what} contains non-finite coordinates")
    if not np.allclose(offsets[0], 0.0, atol=1e-9):
        raise SoftgripError(
            f"{what} must start at its base (0, 0), got {offsets[0].tolist()}; subtract the base first"
        )
    return base + offsets * (-1.0 if mirror else 1.0, 1.0)


def gripper_centrelines(
    center_xy_mm: tuple[float, float],
    base_separation_mm: float,
    length_mm: float,
    n_points: int = 64,
    left_shape: np.ndarray | None = None,
    right_shape: np.ndarray | None = None,
) -> list[np.ndarray]:
    """Centrelines of a two-finger gripper, [left, right], for ``render.Scene.fingers``.

    The finger bases sit at ``center_xy_mm`` +/- (base_separation_mm / 2, 0). A finger without a
    shape is open: straight down (+y) from its base, ``length_mm`` long, ``n_points`` evenly spaced.
    A shape gives a deformed (e.g. closed) finger as offsets (K, 2) in mm from its base, first row
    (0, 0), drawn as a LEFT finger (curling toward +x); the right one is mirrored about its base's
    vertical. So a symmetric closure passes the same array for both. Centrelines that are already
    placed (e.g. ``rod.close_rod(...).points`` of each hand) go straight into ``Scene.fingers``.

    Args:
        center_xy_mm: gripper centre between the finger bases (mm, (2,)).
        base_separation_mm: distance W between the bases (mm, > 0).
        length_mm: length of an open finger (mm, > 0).
        n_points: points on an open finger's centreline (>= 2).
        left_shape, right_shape: optional offsets (K, 2) from the base, left-finger convention.

    Returns:
        Two float64 arrays (K, 2) in mm, base first.

    Example:
        >>> left, right = gripper_centrelines((0.0, -40.0), 50.0, 52.0, 3)
        >>> left.tolist(), right[-1].tolist()
        ([[-25.0, -40.0], [-25.0, -14.0], [-25.0, 12.0]], [25.0, 12.0])
    """
    if not base_separation_mm > 0.0 or not length_mm > 0.0 or int(n_points) < 2:
        raise SoftgripError(
            f"need base_separation_mm > 0, length_mm > 0 and n_points >= 2, got "
            f"{base_separation_mm}, {length_mm}, {n_points}"
        )
    center = np.asarray(center_xy_mm, dtype=np.float64).reshape(2)
    half = np.array([0.5 * base_separation_mm, 0.0])
    straight = np.column_stack([np.zeros(int(n_points)), np.linspace(0.0, length_mm, int(n_points))])
    return [
        _finger(center - half, straight if left_shape is None else left_shape, False, "left_shape"),
        _finger(center + half, straight if right_shape is None else right_shape, True, "right_shape"),
    ]
