"""Drawing estimates on a frame, as in the paper's Figs. 15-17, and writing PNGs atomically.

Colours follow the paper: estimated joints are blue dots joined by lines, observed positions
green dots, contact points red dots. Points are pixels (u, v) (x right, y down, pixel centres at
integers) and are drawn with sub-pixel precision and anti-aliasing. Non-finite points (an invalid
candidate's NaN joints) are skipped.

Example:
    >>> import numpy as np
    >>> image = np.zeros((120, 160, 3), np.uint8)
    >>> joints = np.array([[40.0, 10.0], [45.0, 50.0], [60.0, 90.0]])
    >>> out = draw_overlay(image, joints=[joints], contacts=np.array([[60.0, 90.0]]))
    >>> out.shape, bool(out.any()), bool(image.any())
    ((120, 160, 3), True, False)
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from softgrip_jax import SoftgripError
from softgrip_base.atomic_write import write_atomic

JOINT_RGB = (0, 0, 255)
OBSERVED_RGB = (0, 255, 0)
CONTACT_RGB = (255, 0, 0)
_SHIFT = 4  # fractional bits of cv2's sub-pixel drawing: 1/16 px


def draw_overlay(
    rgb: np.ndarray,
    joints: Sequence[np.ndarray] = (),
    observed: Sequence[np.ndarray] = (),
    contacts: np.ndarray | None = None,
    radius_px: int = 3,
    thickness_px: int = 2,
) -> np.ndarray:
    """A copy of ``rgb`` with estimates drawn on it.

    Args:
        rgb: (H, W, 3) uint8 RGB image (e.g. ``Frame.color``); not modified.
        joints: per finger, estimated joints (K, 2) px: blue dots joined by lines, base first.
        observed: per finger, observed positions (K, 2) px: green dots.
        contacts: (P, 2) contact points px: red dots; None for none.
        radius_px: dot radius (px, >= 1); contact dots are one pixel larger.
        thickness_px: line thickness (px, >= 1).

    Returns:
        (H, W, 3) uint8 RGB image.

    Raises:
        SoftgripError: a bad image, point array or size.

    Example:
        >>> image = draw_overlay(np.zeros((100, 100, 3), np.uint8), joints=[np.array([[50.0, 10.0], [50.0, 60.0]])],
        ...                      contacts=np.array([[50.0, 60.0]]))
        >>> image.shape, image[10, 50].tolist() != [0, 0, 0]
        ((100, 100, 3), True)
    """
    if not isinstance(rgb, np.ndarray) or rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise SoftgripError(f"draw_overlay: rgb must be an (H, W, 3) uint8 image, got "
                            f"{getattr(rgb, 'dtype', type(rgb).__name__)} {getattr(rgb, 'shape', '')}")
    if radius_px < 1 or thickness_px < 1:
        raise SoftgripError(f"draw_overlay: radius_px and thickness_px must be >= 1, got {radius_px}, "
                            f"{thickness_px}")
    image = rgb.copy()
    for points in joints:
        fixed, finite = _fixed_point(points, "joints")
        for k in np.flatnonzero(finite[:-1] & finite[1:]):
            cv2.line(image, fixed[k], fixed[k + 1], JOINT_RGB, thickness_px, cv2.LINE_AA, _SHIFT)
        _dots(image, fixed[finite], radius_px, JOINT_RGB)
    for points in observed:
        fixed, finite = _fixed_point(points, "observed")
        _dots(image, fixed[finite], radius_px, OBSERVED_RGB)
    if contacts is not None:
        fixed, finite = _fixed_point(contacts, "contacts")
        _dots(image, fixed[finite], radius_px + 1, CONTACT_RGB)
    return image


def save_png(path: str | os.PathLike[str], rgb: np.ndarray, *, inputs=(), force: bool = False,
             what: str = "output") -> Path:
    """Write an RGB (H, W, 3) or grey (H, W) uint8 image as a PNG, atomically; returns the path.

    The PNG is encoded in memory by OpenCV, written to a hidden temporary file next to ``path`` and
    renamed over it, so ``path`` is never a partial file. An existing regular file is replaced (its
    mode kept); ``inputs``, ``force`` and ``what`` as in ``softgrip_base.atomic_write.check_output``.

    Raises:
        SoftgripError: a bad image, or the file cannot be written (the message names it).
        OutputRefusedError: the output policy refuses ``path`` (one of ``inputs``, a folder, a
            FIFO or device, a link without ``force``, ...).

    Example:
        >>> import tempfile, numpy as np
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     print(save_png(f"{folder}/black.png", np.zeros((4, 4, 3), np.uint8)).name)
        black.png
    """
    target = Path(path)
    image = np.asarray(rgb)
    if image.dtype != np.uint8 or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise SoftgripError(f"save_png {target}: expected an (H, W, 3) RGB or (H, W) grey uint8 image, got "
                            f"{image.dtype} {image.shape}")
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image)
    if not ok:
        raise SoftgripError(f"save_png {target}: OpenCV could not encode the image")
    try:
        target = write_atomic(target, encoded.tobytes(), inputs=inputs, force=force, what=what)
    except OSError as err:
        raise SoftgripError(f"could not write {target}: {err.strerror}; check that its folder exists "
                            f"and is writable") from None
    return target


def _fixed_point(points: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """Points (K, 2) px as (K, 2) int32 in 1/16 px (cv2's ``shift``), and (K,) which are drawable
    (finite and within +/- 2^20 px; the others are left out)."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2:
        raise SoftgripError(f"draw_overlay: {what} must be (K, 2) arrays of pixels (u, v), got shape "
                            f"{points.shape}")
    drawable = (np.abs(points) < 2**20).all(axis=1)  # False for NaN and inf too
    fixed = np.zeros(points.shape, dtype=np.int32)
    fixed[drawable] = np.rint(points[drawable] * (1 << _SHIFT)).astype(np.int32)
    return fixed, drawable


def _dots(image: np.ndarray, fixed: np.ndarray, radius_px: int, rgb: tuple[int, int, int]) -> None:
    """Filled anti-aliased discs at fixed-point centres (K, 2), drawn into ``image`` in place."""
    for centre in fixed:
        cv2.circle(image, centre, radius_px << _SHIFT, rgb, cv2.FILLED, cv2.LINE_AA, _SHIFT)
