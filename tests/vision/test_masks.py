"""softgrip_vision._masks and the mask operations computed on the mask's box: bit-for-bit the
whole image's, for masks inside the image and touching its edges."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from softgrip_vision._masks import box
from softgrip_vision.coverage import _RING_PX, edge_coverage


def _blob(shape, centre, radius, rng):
    v, u = np.indices(shape)
    wobble = 1.0 + 0.2 * np.sin(3.0 * np.arctan2(v - centre[1], u - centre[0]) + rng.uniform(0, 6))
    return np.hypot(u - centre[0], v - centre[1]) <= radius * wobble


MASKS = {
    "inside": ((60, 80), (40.0, 30.0), 12.0),
    "touching the left and top edges": ((60, 80), (2.0, 1.0), 15.0),
    "touching the right and bottom edges": ((60, 80), (78.0, 58.0), 15.0),
    "wider than the image": ((60, 80), (40.0, 30.0), 45.0),
}


def test_the_box_is_the_masks_own_grown_within_the_image():
    mask = np.zeros((10, 12), bool)
    assert box(mask, 3) is None
    mask[4:6, 1:3] = True
    assert box(mask, 2) == (slice(2, 8), slice(0, 5))


def _whole_image_coverage(color, mask):
    """edge_coverage as computed on the whole image (the reference)."""
    inside = np.asarray(mask, dtype=bool)
    out = inside.astype(np.float32)
    u8 = inside.view(np.uint8)
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    grown, shrunk = cv2.dilate(u8, cross).view(bool), cv2.erode(u8, cross).view(bool)
    band = grown & ~shrunk
    ring = np.ones((2 * _RING_PX + 1, 2 * _RING_PX + 1), np.uint8)
    inner = shrunk & ~cv2.erode(u8, ring).view(bool)
    outer = ~grown & cv2.dilate(u8, ring).view(bool)
    pixels = np.asarray(color, np.float32)
    c_in, c_out = np.median(pixels[inner], axis=0), np.median(pixels[outer], axis=0)
    contrast = c_in - c_out
    out[band] = np.clip((pixels[band] - c_out) @ contrast / float(contrast @ contrast), 0.0, 1.0)
    return out


@pytest.mark.parametrize("shape, centre, radius", list(MASKS.values())[:3], ids=list(MASKS)[:3])
def test_edge_coverage_on_the_box_is_the_whole_images(shape, centre, radius):
    rng = np.random.default_rng(1)
    mask = _blob(shape, centre, radius, rng)
    color = np.where(mask[..., None], [200, 40, 30], [20, 20, 20]).astype(np.float64)
    color = np.clip(cv2.GaussianBlur(color, (0, 0), 0.8) + rng.normal(0.0, 3.0, color.shape), 0, 255)
    color = color.astype(np.uint8)
    expected = _whole_image_coverage(color, mask)
    assert ((expected > 0.0) & (expected < 1.0)).any()  # the band holds fractions
    np.testing.assert_array_equal(edge_coverage(color, mask), expected)
