"""Segmentation (softgrip_vision.segmentation): masks against the renderer's ground-truth labels, both
backends against each other, every setting, and one test per bad input."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from benchmarks.vision_accuracy import accuracy_scenes, measure
from softgrip_jax import SoftgripError
from softgrip_vision.frames import Frame
from softgrip_vision.segmentation import (SegmentationError, SegmentationSettings, segment, segment_batch,
                                          segment_object)
from synthetic.render import (
    LABEL_FIRST_FINGER,
    LABEL_OBJECT,
    Scene,
    d405_intrinsics,
    mm_to_px,
    render,
    render_labels,
)
from synthetic.rod import free_arc_points
from synthetic.scenes import gripper_centrelines
from synthetic.shapes import shape

INTR = d405_intrinsics()
PLANE_MM = 120.0
SCENES = accuracy_scenes(20)


def open_fingers(center=(0.0, -40.0), separation=60.0) -> list[np.ndarray]:
    return gripper_centrelines(center, separation, 52.0, 64)


def closed_fingers(theta: float, separation: float, center=(0.0, -45.0)) -> list[np.ndarray]:
    arc = np.asarray(free_arc_points((0.0, 0.0), theta, 52.0, np.linspace(0.0, 52.0, 129)))
    return gripper_centrelines(center, separation, 52.0, left_shape=arc, right_shape=arc)


def rendered(scene: Scene) -> tuple[Frame, np.ndarray]:
    return render(scene, INTR), render_labels(scene, INTR)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


# --- accuracy ---------------------------------------------------------------------------------


@pytest.mark.parametrize("scene", SCENES, ids=lambda s: f"scene{s.index}")
def test_both_fingers_are_always_found(scene) -> None:
    assert measure(scene).fingers_found == 4  # two fingers, open and closed, each matching the truth


@pytest.mark.parametrize("seed", [0, 1])
def test_masks_match_the_ground_truth(seed: int) -> None:
    scene = Scene(open_fingers(), object_polygon=shape("star_a", 28.0) + (0.0, 5.0), seed=seed)
    frame, labels = rendered(scene)
    seg = segment(frame)
    assert iou(seg.left_finger, labels == LABEL_FIRST_FINGER) > 0.98
    assert iou(seg.right_finger, labels == LABEL_FIRST_FINGER + 1) > 0.98
    assert iou(seg.object, labels == LABEL_OBJECT) > 0.98
    assert not (seg.left_finger & seg.right_finger).any()
    assert (seg.fingers <= seg.gripper).all()
    base_u = mm_to_px(np.array([[-30.0, 0.0], [30.0, 0.0]]), INTR, PLANE_MM)[:, 0]
    assert base_u[0] < seg.center_column < base_u[1]


def test_no_object_is_an_empty_mask_not_an_error() -> None:
    seg = segment(render(Scene(open_fingers(), object_polygon=None), INTR))
    assert not seg.object.any()
    assert seg.left_finger.any() and seg.right_finger.any()


def test_depth_holes_are_filled_and_their_colour_decides() -> None:
    scene = Scene(open_fingers(), object_polygon=shape("circle") + (0.0, 8.0), n_depth_holes=60, seed=4)
    frame, labels = rendered(scene)
    holes = frame.depth == 0
    fingers = labels >= LABEL_FIRST_FINGER
    assert (holes & fingers).sum() > 300  # many holes, on the fingers and at their edges
    filled = segment(frame)
    assert filled.fingers[holes & fingers].mean() > 0.98
    assert filled.object[holes & (labels == LABEL_OBJECT)].mean() > 0.98
    assert not filled.gripper[holes & (labels == 0)].any()  # background holes stay background
    unfilled = segment(frame, SegmentationSettings(hole_fill_px=0))
    assert not unfilled.gripper[holes].any()


def test_automatic_background_cut_off_lies_between_plane_and_background() -> None:
    frame = render(Scene(open_fingers(), object_polygon=shape("square") + (0.0, 8.0)), INTR)
    seg = segment(frame)
    assert PLANE_MM + 5 < seg.background_cutoff_mm < 400.0 - 20
    assert segment(frame, SegmentationSettings(background_depth_mm=200.0)).background_cutoff_mm == 200.0


def test_no_background_in_view_means_no_cut_off() -> None:
    frame, labels = rendered(Scene(open_fingers(), background_depth_mm=140.0))
    seg = segment(frame)
    assert math.isinf(seg.background_cutoff_mm)
    assert iou(seg.left_finger, labels == LABEL_FIRST_FINGER) > 0.98  # the dark background is not gripper


def test_center_column_separates_touching_fingers() -> None:
    # Closed at Theta = 0.6, the tips' caps overlap by 1 mm: one gripper component.
    tip_x = 52.0 * math.sin(0.6) ** 2 / 0.6
    frame, labels = rendered(Scene(closed_fingers(0.6, 2 * tip_x + 7.0)))
    assert segment(frame).split == "neck"  # found in the frame without the setting
    column = float(mm_to_px(np.zeros(2), INTR, PLANE_MM)[0])
    seg = segment(frame, SegmentationSettings(center_column=column))
    assert seg.center_column == column and seg.split == "center_column"
    assert np.nonzero(seg.left_finger)[1].max() < column <= np.nonzero(seg.right_finger)[1].min()
    assert iou(seg.left_finger, labels == LABEL_FIRST_FINGER) > 0.95


def test_region_of_interest_leaves_the_gripper_body_out() -> None:
    scene = Scene(open_fingers(), palm=True)
    frame = render(scene, INTR)
    assert segment(frame).split == "neck"  # the palm joins the fingers: cut in the middle of it
    base_row = int(math.ceil(mm_to_px(scene.fingers[0][0], INTR, PLANE_MM)[1]))
    seg = segment(frame, SegmentationSettings(roi=(0, base_row, INTR.width, INTR.height)))
    assert np.nonzero(seg.left_finger)[0].min() == base_row
    assert not seg.gripper[:base_row].any()


# --- backends ---------------------------------------------------------------------------------


def test_kornia_and_opencv_backends_agree() -> None:
    small = d405_intrinsics(320, 240)  # kornia is slow on a CPU; the same scenes at half size
    frames = [
        render(Scene(open_fingers(), object_polygon=shape("star_b", 26.0) + (1.0, 6.0), seed=1), small),
        render(Scene(closed_fingers(0.7, 84.0), n_depth_holes=20, seed=2), small),
        render(Scene(open_fingers((5.0, -35.0), 70.0), object_polygon=shape("clover") + (5.0, 12.0),
                     color_noise_sigma=6.0, seed=3), small),
    ]
    settings = SegmentationSettings(hole_fill_px=7, object_open_px=3, min_finger_px=50)  # every morphology on
    by_opencv = segment_batch(frames, settings, backend="opencv")
    by_kornia = segment_batch(frames, settings, backend="kornia", device="cpu")
    assert by_opencv[0].object.any() and by_opencv[1].left_finger.any()
    for a, b in zip(by_opencv, by_kornia, strict=True):
        for name in ("gripper", "left_finger", "right_finger", "object"):
            assert np.mean(getattr(a, name) != getattr(b, name)) < 0.005, name  # < 0.5 % of pixels
        assert a.background_cutoff_mm == b.background_cutoff_mm
        assert a.center_column == pytest.approx(b.center_column, abs=0.5)


def test_kornia_backend_needs_frames_of_one_size() -> None:
    small = d405_intrinsics(320, 240)
    frames = [render(Scene(open_fingers()), INTR), render(Scene(open_fingers()), small)]
    with pytest.raises(SegmentationError, match="one size"):
        segment_batch(frames, backend="kornia")


def test_unknown_backend() -> None:
    with pytest.raises(SegmentationError, match="'opencv' or 'kornia'"):
        segment_batch([render(Scene(open_fingers()), INTR)], backend="cuda")


# --- settings ---------------------------------------------------------------------------------


@pytest.mark.parametrize(("field", "value"), [
    ("background_depth_mm", -5.0),
    ("background_depth_mm", math.nan),
    ("gripper_max_saturation", 1.5),
    ("gripper_min_value", "0.5"),
    ("object_min_saturation", 0.1),  # below gripper_max_saturation
    ("object_min_value", -0.1),
    ("hole_fill_px", 4),
    ("gripper_open_px", -3),
    ("object_open_px", 2.0),
    ("min_finger_px", 0),
    ("min_object_px", True),
    ("center_column", -1.0),
    ("roi", (10, 10, 5, 20)),
    ("roi", (0, 0, 10)),
])
def test_bad_settings_name_the_field(field: str, value: object) -> None:
    with pytest.raises(SegmentationError, match=field):
        SegmentationSettings(**{field: value})


def test_settings_round_trip_through_json() -> None:
    settings = SegmentationSettings(background_depth_mm=250.0, gripper_max_saturation=0.2, hole_fill_px=11,
                                    center_column=321.5, roi=(0, 40, 640, 480))
    restored = SegmentationSettings.from_dict(json.loads(json.dumps(settings.to_dict())))
    assert restored == settings
    assert SegmentationSettings.from_dict({}) == SegmentationSettings()


def test_settings_from_dict_refuses_unknown_and_bad_fields() -> None:
    with pytest.raises(SegmentationError, match="profile.json: unknown segmentation setting.*gripper_max_sat"):
        SegmentationSettings.from_dict({"gripper_max_sat": 0.2}, source="profile.json")
    with pytest.raises(SegmentationError, match="profile.json: .*min_finger_px"):
        SegmentationSettings.from_dict({"min_finger_px": -1}, source="profile.json")
    with pytest.raises(SegmentationError, match="JSON object"):
        SegmentationSettings.from_dict([1, 2], source="profile.json")


def test_segmentation_error_is_a_softgrip_error() -> None:
    assert issubclass(SegmentationError, SoftgripError) and issubclass(SegmentationError, ValueError)


# --- bad input --------------------------------------------------------------------------------


def test_no_gripper_in_the_frame() -> None:
    frame = render(Scene([], object_polygon=shape("circle")), INTR)
    with pytest.raises(SegmentationError, match="no gripper found.*gripper_max_saturation.*lit"):
        segment(frame)


def test_one_finger_only() -> None:
    frame = render(Scene(open_fingers()[:1]), INTR)
    with pytest.raises(SegmentationError, match="only one finger found.*both fingers are in view"):
        segment(frame)


def test_one_finger_only_with_a_center_column_names_the_missing_side() -> None:
    frame = render(Scene(open_fingers()[:1]), INTR)
    with pytest.raises(SegmentationError, match="right of center_column=320"):
        segment(frame, SegmentationSettings(center_column=320.0))


def test_no_depth_in_the_gripper_region() -> None:
    frame, labels = rendered(Scene(open_fingers(), object_polygon=shape("circle") + (0.0, 8.0)))
    depth = frame.depth.copy()
    depth[labels >= LABEL_FIRST_FINGER] = 0
    no_depth = Frame(color=frame.color, depth=depth, intrinsics=frame.intrinsics)
    with pytest.raises(SegmentationError, match="no depth in the gripper region.*depth range"):
        segment(no_depth)


def test_gripper_beyond_the_background_cut_off() -> None:
    frame = render(Scene(open_fingers()), INTR)
    with pytest.raises(SegmentationError, match="cut-off of 100 mm.*background_depth_mm above 120"):
        segment(frame, SegmentationSettings(background_depth_mm=100.0))


def test_dark_gripper_says_check_lighting() -> None:
    frame = render(Scene(open_fingers(), gripper_rgb=(90, 90, 88), background_rgb=(40, 40, 40)), INTR)
    with pytest.raises(SegmentationError, match="no gripper found.*gripper_min_value"):
        segment(frame)
    assert segment(frame, SegmentationSettings(gripper_min_value=0.25)).left_finger.any()


def test_region_of_interest_outside_the_frame() -> None:
    with pytest.raises(SegmentationError, match="roi.*outside the 640x480 frame"):
        segment(render(Scene(open_fingers()), INTR), SegmentationSettings(roi=(700, 0, 800, 10)))


def test_center_column_outside_the_frame() -> None:
    with pytest.raises(SegmentationError, match="center_column=900 is outside the frame"):
        segment(render(Scene(open_fingers()), INTR), SegmentationSettings(center_column=900.0))


def test_a_batch_names_the_frame_that_failed() -> None:
    good = render(Scene(open_fingers()), INTR)
    bad = render(Scene(open_fingers()[:1]), INTR)
    with pytest.raises(SegmentationError, match="^frame 1: only one finger"):
        segment_batch([good, bad])


def _ring_frame(hole_depth: int, hole_rgb: tuple[int, int, int]) -> tuple[Frame, np.ndarray]:
    """A 60 x 60 frame: a red square (object colour, 120 mm deep) with a 20 px hole of ``hole_depth``
    (0: no reading) and ``hole_rgb``, on a grey background 400 mm deep; and the square's mask."""
    from softgrip_vision.frames import Intrinsics

    color = np.full((60, 60, 3), 90, np.uint8)
    depth = np.full((60, 60), 400, np.uint16)
    square = np.zeros((60, 60), bool)
    square[10:50, 10:50] = True
    color[square], depth[square] = (200, 30, 30), 120
    hole = np.zeros_like(square)
    hole[20:40, 20:40] = True
    color[hole], depth[hole] = hole_rgb, hole_depth
    return Frame(color=color, depth=depth, intrinsics=Intrinsics(60, 60, 60.0, 60.0, 30.0, 30.0, 0.001)), square


@pytest.mark.parametrize("hole_depth, hole_rgb, filled", [
    (0, (200, 30, 30), True),     # no reading, the object's colour: a dropout on the object
    (400, (200, 30, 30), False),  # a reading of the background behind: a real hole (a ring)
    (0, (90, 90, 90), False),     # no reading, the background's grey: not the object's colour
], ids=["dropout", "ring with background behind", "grey hole without reading"])
def test_a_hole_the_object_encloses_is_filled_only_without_reading_and_in_its_colour(hole_depth, hole_rgb, filled):
    # The 20 px hole's middle is 10 px from a reading, beyond hole_fill_px=15's reach (7 px).
    frame, square = _ring_frame(hole_depth, hole_rgb)
    obj = segment_object(frame, SegmentationSettings(background_depth_mm=300.0)).object
    assert obj.sum() == (1600 if filled else 1200), obj.sum()
    assert not (obj & ~square).any()
