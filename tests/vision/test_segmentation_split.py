"""Splitting one gripper region into two fingers (softgrip_vision.segmentation): fingertips that touch or
overlap by a few pixels in the closed frame, and the gripper's body (a palm bar) joining the finger
bases, found at the region's neck or at a centre-line hint; a single finger is never split; and the
one-frame calibration through a closed frame whose tips touch."""

from __future__ import annotations

import math

import numpy as np
import pytest

from softgrip_calib.one_frame import one_frame_from_frames
from softgrip_vision.segmentation import SegmentationError, segment, segment_batch
from synthetic.render import (
    LABEL_FIRST_FINGER,
    LABEL_PALM,
    Scene,
    d405_intrinsics,
    mm_to_px,
    render,
    render_labels,
)
from synthetic.rod import free_arc_points
from synthetic.scenes import gripper_centrelines

INTR = d405_intrinsics()
PLANE_MM = 120.0
MM_PER_PX = PLANE_MM / INTR.fx  # at the gripper plane
LENGTH, HALF_THICKNESS = 52.0, 4.0
CENTER = (2.3, -45.0)  # mm; the gripper's centre line falls between pixel centres


def arc(theta: float) -> np.ndarray:
    """(129, 2) mm: a free closed finger's centreline (the circular arc of eq. 1-3) from its base."""
    return np.asarray(free_arc_points((0.0, 0.0), theta, LENGTH, np.linspace(0.0, LENGTH, 129)))


def touching(theta_left: float, theta_right: float, overlap_px: float, center=CENTER) -> list[np.ndarray]:
    """[left, right] closed centrelines whose tips' caps overlap by ``overlap_px`` (0: tangent): the
    bases are moved together until the tips are 2 r - overlap apart."""
    left, right = arc(theta_left), arc(theta_right)
    gap = 2.0 * HALF_THICKNESS - overlap_px * MM_PER_PX
    dy = left[-1, 1] - right[-1, 1]
    separation = left[-1, 0] + right[-1, 0] + math.sqrt(gap ** 2 - dy ** 2)
    return gripper_centrelines(center, separation, LENGTH, left_shape=left, right_shape=right)


def truth_column(center=CENTER) -> float:
    """The image column (px) of the bases' midpoint."""
    return float(mm_to_px(np.asarray(center), INTR, PLANE_MM)[0])


def finger_iou(mask: np.ndarray, labels: np.ndarray, k: int) -> float:
    """IoU of a finger mask with finger k's true pixels; the palm (body) pixels a finger mask
    carries above its base are not counted (keypoints find the base where the finger leaves it)."""
    mask = mask & (labels != LABEL_PALM)
    truth = labels == LABEL_FIRST_FINGER + k
    return float((mask & truth).sum() / (mask | truth).sum())


def check_split(seg, labels: np.ndarray) -> None:
    assert finger_iou(seg.left_finger, labels, 0) >= 0.97
    assert finger_iou(seg.right_finger, labels, 1) >= 0.97
    assert not (seg.left_finger & seg.right_finger).any()
    columns = np.arange(labels.shape[1])
    assert (columns[seg.left_finger.any(axis=0)] < seg.center_column).all()
    assert (columns[seg.right_finger.any(axis=0)] >= seg.center_column).all()


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("palm", [False, True], ids=["no_palm", "palm"])
@pytest.mark.parametrize("overlap_px", [0, 1, 3])
def test_touching_tips_are_split_at_the_neck(overlap_px: int, palm: bool, seed: int) -> None:
    scene = Scene(touching(0.55, 0.55, overlap_px), half_thickness=HALF_THICKNESS, palm=palm, seed=seed)
    frame, labels = render(scene, INTR), render_labels(scene, INTR)
    seg = segment(frame)
    assert seg.split == "neck"  # one gripper region: the fingers touch (and the palm joins them)
    assert seg.center_column == pytest.approx(truth_column(), abs=1.5)
    check_split(seg, labels)


@pytest.mark.parametrize("palm", [False, True], ids=["no_palm", "palm"])
@pytest.mark.parametrize("overlap_px", [0, 1, 3])
def test_touching_tips_are_split_at_the_hint(overlap_px: int, palm: bool) -> None:
    scene = Scene(touching(0.55, 0.55, overlap_px), half_thickness=HALF_THICKNESS, palm=palm, seed=3)
    frame, labels = render(scene, INTR), render_labels(scene, INTR)
    hint = truth_column() + 0.4  # as another frame might put it
    seg = segment(frame, center_hint=hint)
    assert seg.split == "center_hint" and seg.center_column == hint
    check_split(seg, labels)


def test_palm_joining_open_fingers_is_split_in_its_middle() -> None:
    scene = Scene(gripper_centrelines(CENTER, 60.0, LENGTH, 64), half_thickness=HALF_THICKNESS, palm=True)
    frame, labels = render(scene, INTR), render_labels(scene, INTR)
    seg = segment(frame)
    assert seg.split == "neck"
    assert seg.center_column == pytest.approx(truth_column(), abs=1.5)
    check_split(seg, labels)
    palm = labels == LABEL_PALM
    assert (seg.fingers[palm]).mean() > 0.98  # the body's halves stay with their fingers


def test_separate_fingers_ignore_the_hint() -> None:
    scene = Scene(gripper_centrelines(CENTER, 60.0, LENGTH, 64), half_thickness=HALF_THICKNESS)
    seg = segment(render(scene, INTR), center_hint=100.0)
    assert seg.split == "components"
    assert seg.center_column == pytest.approx(truth_column(), abs=1.0)


@pytest.mark.parametrize("palm", [False, True], ids=["no_palm", "palm"])
@pytest.mark.parametrize("theta", [0.0, 0.3, 0.55, 0.9, 1.6])
def test_a_single_finger_is_never_split(theta: float, palm: bool) -> None:
    # 1.6 rad curls the finger into a U: its bottom is a finger-thick neck low in the region.
    finger = gripper_centrelines(CENTER, 60.0, LENGTH, left_shape=arc(theta))[0]
    frame = render(Scene([finger], half_thickness=HALF_THICKNESS, palm=palm), INTR)
    with pytest.raises(SegmentationError, match="only one finger found.*both fingers are in view"):
        segment(frame)
    with pytest.raises(SegmentationError, match="only one finger found.*center_hint"):
        segment(frame, center_hint=truth_column())  # the whole region is on one side


def test_a_hint_through_a_fingertip_falls_back_to_the_neck() -> None:
    scene = Scene(touching(0.55, 0.55, 1), half_thickness=HALF_THICKNESS, seed=8)
    frame, labels = render(scene, INTR), render_labels(scene, INTR)
    seg = segment(frame, center_hint=truth_column() + 12.0)  # a finger width off: inside the right tip
    assert seg.split == "neck" and seg.center_column == pytest.approx(truth_column(), abs=1.5)
    check_split(seg, labels)


def test_center_hints_of_a_batch() -> None:
    frames = [render(Scene(touching(0.55, 0.55, 1), half_thickness=HALF_THICKNESS, seed=s), INTR) for s in (4, 5)]
    segs = segment_batch(frames, center_hints=[None, truth_column()])
    assert [s.split for s in segs] == ["neck", "center_hint"]
    with pytest.raises(SegmentationError, match="one column .* per frame: got 1 for 2"):
        segment_batch(frames, center_hints=[None])
    with pytest.raises(SegmentationError, match=r"center_hints\[1\] must be a finite image column"):
        segment_batch(frames, center_hints=[None, math.nan])


@pytest.mark.parametrize(("thetas", "palm"), [((0.55, 0.55), False), ((0.55, 0.55), True),
                                             ((0.55, 0.45), False)], ids=["equal", "equal_palm", "unequal"])
def test_one_frame_calibration_with_touching_tips(thetas: tuple[float, float], palm: bool) -> None:
    # Unequal Theta: the tips meet off the open frame's centre line, whose column would cut through
    # a fingertip, so the closed frame is cut at its neck. The body is 12 mm tall here: keypoints
    # recognise a body wider than the finger (a 6 mm bar around 8 mm thick fingers reads as neither
    # a body nor a finger end).
    body = {"palm": palm, "palm_height_mm": 12.0}
    closed = Scene(touching(*thetas, overlap_px=1), half_thickness=HALF_THICKNESS, seed=6, **body)
    separation = closed.fingers[1][0, 0] - closed.fingers[0][0, 0]
    opened = Scene(gripper_centrelines(CENTER, separation, LENGTH, 64), half_thickness=HALF_THICKNESS,
                   seed=7, **body)
    closed_frame, open_frame = render(closed, INTR), render(opened, INTR)
    assert segment(closed_frame).split == "neck"  # the closed frame's fingers form one region
    hint = segment(open_frame).center_column
    assert segment(closed_frame, center_hint=hint).split == ("center_hint" if thetas[0] == thetas[1] else "neck")
    profile = one_frame_from_frames(closed_frame, open_frame, 10)
    np.testing.assert_allclose([profile.fingers[s].theta_entire for s in ("left", "right")], thetas, atol=0.01)
