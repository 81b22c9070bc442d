"""Results -> pictures drawn with OpenCV on the frame itself: per-frame overlays (as in the paper's
Figs. 15-17) and captions. Plots people read (heat maps with mm axes and a colour bar) are drawn
with matplotlib in :mod:`softgrip_vision.plots`."""

from __future__ import annotations

import cv2
import numpy as np

from softgrip_base.input_guard import ascii_text
from softgrip_vision.documents import SIDES, finger_contacts_mm


def grasp_overlay(rgb: np.ndarray, grasp, camera, observed_px=(), label: str | None = None) -> np.ndarray:
    """``rgb`` with both fingers' estimated joints (blue), contacts (red) and observed positions
    (green, (K, 2) px each) drawn as in the paper's Figs. 15-17, with white halos so they read on
    any background, and an optional caption."""
    from softgrip_vision.overlay import draw_overlay

    joints = [camera.mm_to_px(np.asarray(getattr(grasp, side).joints, np.float64)) for side in SIDES]
    contacts = np.concatenate([camera.mm_to_px(finger_contacts_mm(getattr(grasp, side))) for side in SIDES])
    image = rgb.copy()
    for points in joints:
        finite = np.isfinite(points).all(axis=1)
        if finite.sum() >= 2:
            cv2.polylines(image, [np.rint(points[finite] * 16).astype(np.int32)], False, (255, 255, 255), 5,
                          cv2.LINE_AA, 4)
    for point in contacts:
        if np.isfinite(point).all():
            cv2.circle(image, tuple(np.rint(point * 16).astype(int)), 7 * 16, (255, 255, 255), -1, cv2.LINE_AA, 4)
    if len(observed_px):  # observed first, so that the estimate is drawn over it
        image = draw_overlay(image, observed=list(observed_px), radius_px=5)
    image = draw_overlay(image, joints=joints, contacts=contacts, radius_px=3, thickness_px=2)
    if label:
        caption(image, label, (8, 8))
    return image


def caption(image: np.ndarray, text: str, origin: tuple[int, int], scale: float = 0.45,
            bottom: bool = False) -> None:
    """Write lines of ``text`` in white on a dark box, in place: ``origin`` is the box's top-left
    corner (px), or its bottom-left corner with ``bottom=True``. OpenCV's Hershey fonts draw ASCII
    only (and crash on some other text): each line is drawn as :func:`~softgrip_base.input_guard.ascii_text`
    makes it, other characters escaped (``\\xe9``)."""
    lines = [ascii_text(line) for line in text.splitlines()] or [""]
    font, thick = cv2.FONT_HERSHEY_SIMPLEX, 1
    sizes = [cv2.getTextSize(line, font, scale, thick)[0] for line in lines]
    step = max(h for _, h in sizes) + 6
    width = max(w for w, _ in sizes) + 8
    x, y = origin
    if bottom:
        y = max(0, y - step * len(lines) - 4)
    box = image[y:y + step * len(lines) + 4, x:x + width]
    box[:] = (0.35 * box).astype(np.uint8)
    for k, line in enumerate(lines):
        cv2.putText(image, line, (x + 4, y + step * (k + 1) - 2), font, scale, (255, 255, 255), thick, cv2.LINE_AA)
