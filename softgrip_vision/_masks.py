"""Mask operations computed on the box around the mask only, with results equal to the whole
image's to the last bit (a finger or an object covers a few percent of a frame)."""

from __future__ import annotations

import cv2
import numpy as np


def box(mask: np.ndarray, margin: int) -> tuple[slice, slice] | None:
    """(rows, cols) slices of the smallest box holding ``mask``'s pixels, ``margin`` px wider on
    each side within the image; None for an empty mask."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if not len(rows):
        return None
    h, w = mask.shape
    return (slice(max(0, int(rows[0]) - margin), min(h, int(rows[-1]) + 1 + margin)),
            slice(max(0, int(cols[0]) - margin), min(w, int(cols[-1]) + 1 + margin)))


def distance_inside(mask: np.ndarray) -> np.ndarray:
    """(H, W) float32: ``cv2.distanceTransform(mask, DIST_L2, DIST_MASK_PRECISE)`` (each pixel's
    exact Euclidean distance to the nearest pixel outside the mask, 0 outside it) of a bool mask.

    Computed on the mask's box one pixel wider (a frame of pixels outside the mask), except where
    the box meets the image's edge, which is then the box's own: the nearest outside pixel of any
    pixel of the box lies in it, so the distances are the whole image's.
    """
    region = np.ascontiguousarray(mask, dtype=bool)
    out = np.zeros(region.shape, np.float32)
    where = box(region, 1)
    if where is not None:
        crop = np.ascontiguousarray(region[where])
        out[where] = cv2.distanceTransform(crop.view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return out
