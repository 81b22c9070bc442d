"""Object outlines for synthetic scenes: the paper's test objects and a qualitative set.

Every outline is a closed polygon in millimetres in the gripper plane, a float64 array of shape
(V, 2) with columns (x, y) in image axes (x right, y down), without a repeated closing vertex:

- centred at its area centroid (the origin, which lies inside every outline here),
- scaled so that the circle about the centroid through the farthest vertex has diameter
  ``size_mm`` (the "bounding circle"),
- counter-clockwise as seen on the image (y down), the orientation of OpenCV's outer contours:
  the shoelace sum ``sum(x_i * y_{i+1} - x_{i+1} * y_i) / 2`` is minus the area,
- rotated by ``angle`` radians about the centroid, positive as the project measures angles
  (from the downward vertical toward +x: the direction (0, 1) turns toward (1, 0)).

"Up" below means toward the finger bases (-y). The paper's objects (its Fig. 14) are ``circle``,
``square``, ``clover``, ``star_a``/``star_b`` and ``triangle_a``/``triangle_b``, where A and B are
two poses of the same object; the others fill out a qualitative set like its Fig. 17.

Example:
    >>> star = shape("star_a", size_mm=30.0)
    >>> star.shape, round(float(np.hypot(star[:, 0], star[:, 1]).max()), 6)
    ((10, 2), 15.0)
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import numpy as np

from softgrip_base import SoftgripError

_CURVE_VERTICES = 192
_CLOVER_VERTICES = 256  # a multiple of 8, so the notches between the lobes are vertices


def _directions(theta: np.ndarray) -> np.ndarray:
    """Unit vectors (n, 2) at angles theta (n,) from the downward vertical, positive toward +x.

    Increasing theta runs counter-clockwise on the image (down, right, up, left).
    """
    return np.column_stack([np.sin(theta), np.cos(theta)])


def _turn(n: int) -> np.ndarray:
    """n angles (n,) evenly covering one turn, starting at 0 (straight down)."""
    return np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)


def _regular(n: int, phase: float, radii: tuple[float, ...] = (1.0,)) -> np.ndarray:
    """Regular polygon (n * len(radii), 2) with vertices cycling through radii, the first at phase."""
    theta = phase + _turn(n * len(radii))
    r = np.resize(np.asarray(radii, dtype=np.float64), theta.shape)
    return r[:, None] * _directions(theta)


def _circle() -> np.ndarray:
    return _directions(_turn(_CURVE_VERTICES))


def _ellipse() -> np.ndarray:
    """Major axis across the fingers (x), axis ratio 0.6."""
    return _directions(_turn(_CURVE_VERTICES)) * np.array([1.0, 0.6])


def _square() -> np.ndarray:
    """Edges parallel to the image axes: a flat side faces each finger."""
    return _regular(4, math.pi / 4)


def _rounded_rect() -> np.ndarray:
    """A 1.6 : 1 rectangle (long side along x) with corners rounded to 0.2 of the short side."""
    half = np.array([1.6, 1.0])
    radius = 0.4
    corners = []
    for k in range(4):  # bottom-right, top-right, top-left, bottom-left: counter-clockwise
        theta = np.linspace(k * math.pi / 2, (k + 1) * math.pi / 2, 24)
        centre = (half - radius) * np.sign(_directions(np.array([theta.mean()]))[0])
        corners.append(centre + radius * _directions(theta))
    return np.concatenate(corners)


def _triangle_a() -> np.ndarray:
    """Equilateral triangle, a vertex up and the flat side down."""
    return _regular(3, math.pi)


def _triangle_b() -> np.ndarray:
    """Equilateral triangle, a flat side up and a vertex down (pose A turned by 60 degrees)."""
    return _regular(3, 0.0)


def _star_a() -> np.ndarray:
    """Five-pointed star with inner radius half the outer one, a point up."""
    return _regular(5, math.pi, radii=(1.0, 0.5))


def _star_b() -> np.ndarray:
    """The star of pose A turned by 36 degrees: a point down, a notch up."""
    return _regular(5, 0.0, radii=(1.0, 0.5))


def _pentagon() -> np.ndarray:
    """Regular pentagon, a vertex up."""
    return _regular(5, math.pi)


def _hexagon() -> np.ndarray:
    """Regular hexagon, flat top and bottom, a vertex toward each finger."""
    return _regular(6, math.pi / 2)


def _clover() -> np.ndarray:
    """Four-leaf clover: the union of four overlapping discs, a lobe toward each finger and up/down.

    Each disc (radius 1, centre at distance 0.9 from the origin) contains the origin, so the union
    is star-shaped about it and its radius along a ray is the farthest of the four exit distances.
    """
    u = _directions(_turn(_CLOVER_VERTICES))
    lobe_centres = 0.9 * _directions(_turn(4))
    along = u @ lobe_centres.T  # (n, 4): projection of each lobe centre on each ray
    exit_distance = along + np.sqrt(1.0 - 0.9**2 + along**2)
    return exit_distance.max(axis=1)[:, None] * u


def _arc(phi: np.ndarray, centre_x: float, radius: float, centre_y: float = 0.0) -> np.ndarray:
    """Points (n, 2) on a circle about (centre_x, centre_y), at angles phi (n,) from +x toward +y."""
    return np.column_stack([centre_x + radius * np.cos(phi), centre_y + radius * np.sin(phi)])


def _heart() -> np.ndarray:
    """A heart: a diamond with a half-disc on each upper side; a 90-degree notch up, the point down."""
    radius = math.sqrt(0.5)
    right = _arc(np.linspace(math.pi / 4, -3 * math.pi / 4, 64), 0.5, radius, centre_y=-0.5)
    left = _arc(np.linspace(-math.pi / 4, -5 * math.pi / 4, 64)[1:], -0.5, radius, centre_y=-0.5)
    return np.concatenate([[(0.0, 1.0)], right, left])


def _crescent() -> np.ndarray:
    """A unit disc minus a disc of radius 0.72 offset by 0.5 toward +x: horns toward the +x finger."""
    offset, bite = 0.5, 0.72
    x_horn = (1.0 - bite**2 + offset**2) / (2.0 * offset)
    y_horn = math.sqrt(1.0 - x_horn**2)
    phi_outer = math.atan2(y_horn, x_horn)
    phi_inner = math.atan2(y_horn, x_horn - offset)
    outer = np.linspace(phi_outer, 2.0 * math.pi - phi_outer, 160)
    inner = np.linspace(2.0 * math.pi - phi_inner, phi_inner, 130)[1:-1]
    return np.concatenate([_arc(outer, 0.0, 1.0), _arc(inner, offset, bite)])


def _cross() -> np.ndarray:
    """A plus sign spanning 2 x 2 with arms 0.6 wide, an arm toward each finger."""
    h = 0.3
    return np.array(
        [(1, -h), (1, h), (h, h), (h, 1), (-h, 1), (-h, h),
         (-1, h), (-1, -h), (-h, -h), (-h, -1), (h, -1), (h, -h)],
        dtype=np.float64,
    )  # fmt: skip


def _l_shape() -> np.ndarray:
    """An L: a stem 0.4 wide and 1 tall on the left, a foot 0.4 tall reaching 0.8 to the right."""
    return np.array(
        [(0.0, 0.0), (0.4, 0.0), (0.4, 0.6), (0.8, 0.6), (0.8, 1.0), (0.0, 1.0)],
        dtype=np.float64,
    )


def _signed_area_and_centroid(polygon: np.ndarray) -> tuple[float, np.ndarray]:
    """Shoelace signed area (negative = counter-clockwise on the image) and area centroid (2,)."""
    x, y = polygon.T
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = 0.5 * cross.sum()
    centroid = np.array([((x + xn) * cross).sum(), ((y + yn) * cross).sum()]) / (6.0 * area)
    return float(area), centroid


def _rotate(points: np.ndarray, angle: float) -> np.ndarray:
    """Rotate points (n, 2) about the origin by angle (rad), turning (0, 1) toward (1, 0)."""
    c, s = math.cos(angle), math.sin(angle)
    return points @ np.array([[c, -s], [s, c]])


def _place(outline: Callable[[], np.ndarray], size_mm: float = 30.0, angle: float = 0.0) -> np.ndarray:
    """Centre, orient, scale and rotate a raw outline; see the module docstring for the result."""
    if not (math.isfinite(size_mm) and size_mm > 0.0):
        raise SoftgripError(f"size_mm must be a positive finite number of millimetres, got {size_mm!r}")
    if not math.isfinite(angle):
        raise SoftgripError(f"angle must be a finite number of radians, got {angle!r}")
    polygon = np.asarray(outline(), dtype=np.float64)
    area, centroid = _signed_area_and_centroid(polygon)
    polygon = polygon - centroid
    if area > 0.0:
        polygon = polygon[::-1]
    polygon *= 0.5 * size_mm / np.hypot(polygon[:, 0], polygon[:, 1]).max()
    return _rotate(polygon, angle)


_OUTLINES: dict[str, Callable[[], np.ndarray]] = {
    "circle": _circle,
    "square": _square,
    "clover": _clover,
    "star_a": _star_a,
    "star_b": _star_b,
    "triangle_a": _triangle_a,
    "triangle_b": _triangle_b,
    "ellipse": _ellipse,
    "rounded_rect": _rounded_rect,
    "pentagon": _pentagon,
    "hexagon": _hexagon,
    "heart": _heart,
    "crescent": _crescent,
    "cross": _cross,
    "l_shape": _l_shape,
}

SHAPES: dict[str, Callable[..., np.ndarray]] = {
    name: functools.partial(_place, outline) for name, outline in _OUTLINES.items()
}
"""Shape name -> ``f(size_mm=30.0, angle=0.0)`` returning the outline (V, 2) in mm."""

ACCURACY_SET: tuple[str, ...] = ("circle", "square", "clover", "star_a", "triangle_a")
"""The five objects of the paper's accuracy experiment (its Table II), in its order."""


def shape(name: str, size_mm: float = 30.0, angle: float = 0.0) -> np.ndarray:
    """Outline of a named object.

    Args:
        name: a key of :data:`SHAPES`.
        size_mm: diameter (mm) of the bounding circle about the centroid.
        angle: in-plane rotation (rad) about the centroid, positive from +y toward +x.

    Returns:
        float64 (V, 2) polygon in mm, centred at the centroid, counter-clockwise on the image.

    Raises:
        SoftgripError (a ValueError): unknown name (the message lists the valid ones), or a bad
            size or angle.

    Example:
        >>> square = shape("square", 20.0)
        >>> square.shape, round(float(np.hypot(*square.T).max()), 2)  # corners 10 mm from the centre
        ((4, 2), 10.0)
    """
    try:
        make = SHAPES[name]
    except KeyError:
        raise SoftgripError(f"unknown shape {name!r}; valid names: {', '.join(SHAPES)}") from None
    return make(size_mm=size_mm, angle=angle)
