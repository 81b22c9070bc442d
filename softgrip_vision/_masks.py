"""The box around a mask, where mask operations that reach only a few pixels from it can run (a
finger or an object covers a few percent of a frame).

Not OpenCV's distance transform: its DIST_MASK_PRECISE values differ in the last bit between an
image and a crop of it (a faster square root on some rows), so it runs on the whole image."""

from __future__ import annotations

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
