"""How much of each edge pixel a part covers, from its colour: sub-pixel edges of a mask.

A camera's pixel integrates light over its area (and the lens blurs a little more), so a pixel on
a part's edge has a colour between the part's and its neighbour's, in proportion to how much of
the pixel the part covers. A mask thresholds that away: a straight edge along the pixel grid then
lands on the nearest half pixel whatever its true position, so a finger's width comes out 25 or 26
px for a true 25.6 ("pixel phase"). :func:`edge_coverage` puts the fraction back on the mask's
boundary: for each pixel of the one-pixel band on either side of the boundary, the position of
its colour between the part's colour (the median over a ring just inside) and the surroundings'
(a ring just outside), clipped to [0, 1]; elsewhere the mask itself (1 inside, 0 outside).
Integrating this image across an edge (from a point inside, where it is 1, to just past the edge)
gives the edge's distance to a fraction of a pixel where the image has partial coverage, and
exactly the mask's edge (halfway between the last pixel centre inside and the first outside) where
it has none (point-sampled synthetic frames): ``softgrip_vision.keypoints`` reads edges so.

Example (a column edge at u = 10.3: pixel 10 is 20 % covered, the mask says not covered):
    >>> import numpy as np
    >>> color = np.zeros((20, 20, 3), np.uint8); color[:, 11:] = 200; color[:, 10] = 40
    >>> mask = np.zeros((20, 20), bool); mask[:, 11:] = True
    >>> coverage = edge_coverage(color, mask)
    >>> round(float(coverage[5, 10]), 3), float(coverage[5, 12])
    (0.2, 1.0)
    >>> round(15.0 - float(coverage[5, 8:16].sum()) + 0.5, 3)  # the edge from the coverage in a row
    10.3
"""

from __future__ import annotations

import cv2
import numpy as np

from softgrip_vision._masks import box

_RING_PX = 3  # width of the rings whose median colours are the part's and the surroundings'


def edge_coverage(color: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W) float32 in [0, 1]: the mask with its boundary band replaced by colour coverage.

    Args:
        color: (H, W, 3) the frame's colour (any numeric type).
        mask: (H, W) bool, the part.

    Returns:
        The mask as 0/1, except on the pixels 4-adjacent to the boundary (inside and outside),
        where it is the projection of the pixel's colour on the segment from the outside colour
        (0) to the inside colour (1), clipped. Where the two colours are within 10 levels of
        each other (no contrast to read), the mask itself.
    """
    full = np.asarray(mask, dtype=bool)
    out = full.astype(np.float32)
    if not full.any() or full.all():
        return out
    # All of it happens within _RING_PX of the mask: on its box that much wider (and one more
    # pixel), the same pixels in the same order as on the whole image.
    where = box(full, _RING_PX + 1)
    assert where is not None
    whole, out = out, out[where]
    inside = np.ascontiguousarray(full[where])
    color = np.asarray(color)[where]
    u8 = inside.view(np.uint8)
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    grown, shrunk = cv2.dilate(u8, cross).view(bool), cv2.erode(u8, cross).view(bool)
    band = grown & ~shrunk
    ring = np.ones((2 * _RING_PX + 1, 2 * _RING_PX + 1), np.uint8)
    inner = shrunk & ~cv2.erode(u8, ring).view(bool)
    outer = ~grown & cv2.dilate(u8, ring).view(bool)
    if not inner.any() or not outer.any():
        return whole
    pixels = np.asarray(color, np.float32)
    c_in, c_out = np.median(pixels[inner], axis=0), np.median(pixels[outer], axis=0)
    contrast = c_in - c_out
    if float(np.hypot.reduce(contrast)) < 10.0:
        return whole
    fraction = (pixels[band] - c_out) @ contrast / float(contrast @ contrast)
    out[band] = np.clip(fraction, 0.0, 1.0)  # a view of the whole image's
    return whole
