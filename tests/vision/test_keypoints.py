"""Finger keypoints (softgrip_vision.keypoints) against the renderer's ground truth, pixels <-> millimetres
(softgrip_vision.geometry), and drawing them (softgrip_vision.overlay).

Ground truth is the scene geometry in mm projected with the renderer's own ``mm_to_px`` at the
scene's plane depth; the pipeline estimates the plane depth from the noisy depth image.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from benchmarks.vision_accuracy import REQUIREMENTS, accuracy_scenes, measure
from softgrip_vision.frames import Frame, FrameError, Intrinsics
from softgrip_vision.geometry import PlaneCamera, plane_depth_mm
from softgrip_vision.keypoints import (
    KeypointError,
    finger_keypoints,
    finger_length,
    gripper_keypoints,
    resample_polyline,
    theta_from_closed,
)
from softgrip_vision.overlay import CONTACT_RGB, JOINT_RGB, OBSERVED_RGB, draw_overlay, save_png
from softgrip_vision.segmentation import SegmentationSettings, segment
from synthetic.render import LABEL_FIRST_FINGER, Scene, d405_intrinsics, mm_to_px, render, render_labels
from synthetic.rod import free_arc_points
from synthetic.scenes import gripper_centrelines

INTR = d405_intrinsics()
PLANE_MM = 120.0
CAMERA = PlaneCamera(INTR, PLANE_MM)
LENGTH, HALF_THICKNESS = 52.0, 4.0
SCENES = accuracy_scenes(20)


def closed_scene(theta: float, separation: float, **kwargs) -> Scene:
    arc = np.asarray(free_arc_points((0.0, 0.0), theta, LENGTH, np.linspace(0.0, LENGTH, 257)))
    return Scene(gripper_centrelines((0.0, -45.0), separation, LENGTH, left_shape=arc, right_shape=arc),
                 half_thickness=HALF_THICKNESS, **kwargs)


def to_px(points_mm: np.ndarray, intrinsics: Intrinsics = INTR) -> np.ndarray:
    return mm_to_px(points_mm, intrinsics, PLANE_MM)


# --- accuracy on the rendered scenes ----------------------------------------------------------


@pytest.mark.parametrize("scene", SCENES, ids=lambda s: f"scene{s.index}-theta{s.theta:.2f}")
def test_keypoints_meet_the_required_accuracy(scene) -> None:
    errors = measure(scene)
    assert errors.base_px <= REQUIREMENTS["base_px"]
    assert errors.tip_px <= REQUIREMENTS["tip_px"]
    assert errors.theta_rad <= REQUIREMENTS["theta_rad"]
    assert errors.length_pct <= REQUIREMENTS["length_pct"]
    assert errors.observed_px <= 1.5  # the observed positions follow the true arc, too
    assert errors.half_thickness_mm <= 0.25


def test_the_scene_set_spans_theta_and_objects() -> None:
    thetas = [s.theta for s in SCENES]
    assert min(thetas) < 0.33 and max(thetas) > 0.77
    assert len({s.object_name for s in SCENES}) >= 15 and None in {s.object_name for s in SCENES}


def test_a_finger_curled_past_horizontal() -> None:
    # Theta = 1.2: the tip's direction is 2.4 rad from the downward vertical, so the lower part of the
    # finger runs sideways and then upward: several centreline points per image row.
    scene = closed_scene(1.2, 110.0)
    labels = render_labels(scene, INTR)
    for k, side in enumerate(("left", "right")):
        finger = finger_keypoints(labels == LABEL_FIRST_FINGER + k, CAMERA, side)
        true_line = scene.fingers[k]
        assert np.hypot(*(finger.base_px - to_px(true_line[0]))) < 1.0
        assert np.hypot(*(finger.tip_px - to_px(true_line[-1]))) < 1.0
        assert finger.theta == pytest.approx(1.2, abs=0.01)
        assert finger.arc_length_mm == pytest.approx(LENGTH, rel=0.01)
        tail = finger.centreline_px[-20:, 1]
        assert tail[-1] < tail.max() - 2.0  # the tip end rises again


def test_holes_in_the_mask_do_not_move_the_keypoints() -> None:
    labels = render_labels(closed_scene(0.6, 90.0), INTR)
    mask = labels == LABEL_FIRST_FINGER
    whole = finger_keypoints(mask, CAMERA, "left")
    holed = mask.copy()
    rows, cols = np.nonzero(mask)
    middle = len(rows) // 2
    holed[rows[middle] - 3:rows[middle] + 3, cols[middle] - 3:cols[middle] + 3] = False
    with_hole = finger_keypoints(holed, CAMERA, "left")
    assert np.allclose(with_hole.base_px, whole.base_px) and np.allclose(with_hole.tip_px, whole.tip_px)
    assert with_hole.half_thickness_px == pytest.approx(whole.half_thickness_px)


def test_specks_outside_the_finger_are_ignored() -> None:
    labels = render_labels(closed_scene(0.5, 90.0), INTR)
    mask = labels == LABEL_FIRST_FINGER
    clean = finger_keypoints(mask, CAMERA, "left")
    specked = mask.copy()
    specked[5:8, 5:8] = True  # above the finger: would be the "topmost pixel"
    assert np.allclose(finger_keypoints(specked, CAMERA, "left").base_px, clean.base_px)


def test_a_flat_cut_base_is_the_middle_of_the_top_edge() -> None:
    scene = Scene(gripper_centrelines((0.0, -40.0), 60.0, LENGTH), half_thickness=HALF_THICKNESS, palm=True)
    frame = render(scene, INTR)
    base_row = int(math.ceil(to_px(scene.fingers[0][0])[1]))
    seg = segment(frame, SegmentationSettings(roi=(0, base_row, INTR.width, INTR.height)))
    camera = PlaneCamera.from_frame(frame, seg.fingers)
    for finger, line in zip(gripper_keypoints(seg, camera, rounded_base=False), scene.fingers):
        assert np.hypot(*(finger.base_px - to_px(line[0]))) < 1.5
        assert np.hypot(*(finger.tip_px - to_px(line[-1]))) < 1.5


def test_theta_is_measured_in_millimetres_when_pixels_are_not_square() -> None:
    # 5 % anisotropy; a D405's fx and fy differ by well under 1 %.
    tall = Intrinsics(width=640, height=480, fx=385.0, fy=405.0, ppx=321.6, ppy=238.9, depth_scale=1e-4)
    scene = closed_scene(0.7, 90.0)
    frame = render(scene, tall)
    seg = segment(frame)
    camera = PlaneCamera.from_frame(frame, seg.fingers)
    assert camera.spacing_mm[0] != pytest.approx(camera.spacing_mm[1], rel=0.05)
    for finger in gripper_keypoints(seg, camera):
        assert finger.theta == pytest.approx(0.7, abs=0.01)
        in_px = theta_from_closed(finger.base_px, finger.tip_px, finger.side)
        assert abs(in_px - 0.7) > 3 * abs(finger.theta - 0.7)  # pixels are off by the aspect ratio


def test_right_finger_is_mirrored() -> None:
    labels = render_labels(closed_scene(0.5, 90.0), INTR)
    left = finger_keypoints(labels == LABEL_FIRST_FINGER, CAMERA, "left")
    right = finger_keypoints(labels == LABEL_FIRST_FINGER + 1, CAMERA, "right")
    assert left.tip_px[0] > left.base_px[0] and right.tip_px[0] < right.base_px[0]
    assert left.theta == pytest.approx(right.theta, abs=0.005) == pytest.approx(0.5, abs=0.01)


def test_millimetre_views_go_through_the_camera() -> None:
    labels = render_labels(closed_scene(0.5, 90.0), INTR)
    finger = finger_keypoints(labels == LABEL_FIRST_FINGER, CAMERA, "left")
    assert np.allclose(finger.base_mm, CAMERA.px_to_mm(finger.base_px))
    assert np.allclose(finger.centreline_mm, CAMERA.px_to_mm(finger.centreline_px))
    assert finger.half_thickness_mm == pytest.approx(HALF_THICKNESS, abs=0.15)
    observed = finger.observed_mm(4)
    assert observed.shape == (5, 2)
    assert np.allclose(observed[[0, -1]], [finger.base_mm, finger.tip_mm])
    assert np.allclose(finger.observed_px(4), CAMERA.mm_to_px(observed))
    assert finger.length_mm == pytest.approx(finger_length(finger.base_mm, finger.tip_mm))


# --- eqs. 4 and 5, resampling -----------------------------------------------------------------


def test_eq4_and_eq5_by_hand() -> None:
    assert theta_from_closed((10.0, 0.0), (13.0, 3.0), "left") == pytest.approx(math.pi / 4)
    assert theta_from_closed((10.0, 0.0), (7.0, 3.0 * math.sqrt(3.0)), "right") == pytest.approx(math.pi / 6)
    assert theta_from_closed((0.0, 0.0), (-1.0, 5.0), "left") == pytest.approx(-math.atan(0.2))
    assert finger_length((1.0, 2.0), (4.0, 6.0)) == 5.0


def test_eq4_needs_the_tip_below_the_base() -> None:
    with pytest.raises(KeypointError, match="not below its base.*closed gripper without an object"):
        theta_from_closed((0.0, 10.0), (5.0, 10.0))


def test_bad_side() -> None:
    with pytest.raises(KeypointError, match="'left' or 'right'"):
        theta_from_closed((0.0, 0.0), (1.0, 1.0), "middle")


def test_resample_polyline_divides_the_arc_length_equally() -> None:
    corner = np.array([[0.0, 0.0], [0.0, 3.0], [4.0, 3.0]])  # length 7, bend at 3
    points = resample_polyline(corner, 7)
    assert np.allclose(points, [[0, 0], [0, 1], [0, 2], [0, 3], [1, 3], [2, 3], [3, 3], [4, 3]])
    assert np.allclose(resample_polyline(corner, 2), [[0, 0], [0.5, 3], [4, 3]])
    assert np.allclose(resample_polyline(corner, 1), [[0, 0], [4, 3]])


@pytest.mark.parametrize(("points", "n"), [(np.zeros((1, 2)), 3), (np.zeros((4, 3)), 3), (np.zeros((4, 2)), 0)])
def test_resample_polyline_rejects_bad_input(points: np.ndarray, n: int) -> None:
    with pytest.raises(KeypointError, match="resample_polyline"):
        resample_polyline(points, n)


# --- bad masks --------------------------------------------------------------------------------


def test_empty_mask() -> None:
    with pytest.raises(KeypointError, match="left finger's mask is empty"):
        finger_keypoints(np.zeros((480, 640), bool), CAMERA, "left")


def test_a_blob_too_short_to_have_two_ends() -> None:
    blob = cv2.circle(np.zeros((480, 640), np.uint8), (300, 200), 15, 1, cv2.FILLED).astype(bool)
    with pytest.raises(KeypointError, match="too short.*whole finger in view"):
        finger_keypoints(blob, CAMERA, "right")


def test_a_finger_cut_by_the_image_border() -> None:
    scene = Scene(gripper_centrelines((0.0, 30.0), 60.0, LENGTH), half_thickness=HALF_THICKNESS)
    labels = render_labels(scene, INTR)
    assert (labels[-1] == LABEL_FIRST_FINGER).any()  # the left finger runs off the bottom
    with pytest.raises(KeypointError, match="left finger's tip is cut off by the image border"):
        finger_keypoints(labels == LABEL_FIRST_FINGER, CAMERA, "left")


# --- pixels <-> millimetres -------------------------------------------------------------------


def test_plane_camera_round_trip_and_formula() -> None:
    camera = PlaneCamera(Intrinsics(width=640, height=480, fx=400.0, fy=380.0, ppx=318.0, ppy=242.0,
                                    depth_scale=1e-4), 125.0)
    uv = np.array([[0.0, 0.0], [318.0, 242.0], [639.0, 479.0]])
    xy = camera.px_to_mm(uv)
    assert np.allclose(xy[0], [-318.0 * 125.0 / 400.0, -242.0 * 125.0 / 380.0])
    assert np.allclose(xy[1], 0.0)
    assert np.allclose(camera.mm_to_px(xy), uv)
    assert np.allclose(camera.spacing_mm, [125.0 / 400.0, 125.0 / 380.0])
    assert np.allclose(camera.origin_mm, xy[0])
    assert camera.mm_per_px == pytest.approx(125.0 / math.sqrt(400.0 * 380.0))


def test_plane_depth_is_the_median_of_the_gripper_readings() -> None:
    scene = Scene(gripper_centrelines((0.0, -40.0), 60.0, LENGTH), plane_depth_mm=117.3, n_depth_holes=8)
    frame = render(scene, INTR)
    fingers = render_labels(scene, INTR) >= LABEL_FIRST_FINGER
    assert plane_depth_mm(frame, fingers) == pytest.approx(117.3, abs=0.05)


def test_plane_depth_without_readings() -> None:
    frame = render(Scene(gripper_centrelines((0.0, -40.0), 60.0, LENGTH)), INTR)
    fingers = render_labels(Scene(gripper_centrelines((0.0, -40.0), 60.0, LENGTH)), INTR) >= LABEL_FIRST_FINGER
    depth = frame.depth.copy()
    depth[fingers] = 0
    with pytest.raises(FrameError, match="no depth reading in the gripper region"):
        plane_depth_mm(Frame(frame.color, depth, frame.intrinsics), fingers)
    with pytest.raises(FrameError, match="mask of the gripper region is 10x10"):
        plane_depth_mm(frame, np.ones((10, 10), bool))


@pytest.mark.parametrize("depth", [0.0, -1.0, math.inf])
def test_plane_camera_rejects_bad_depth(depth: float) -> None:
    with pytest.raises(FrameError, match="depth_mm"):
        PlaneCamera(INTR, depth)


# --- overlay ----------------------------------------------------------------------------------


def test_overlay_draws_joints_observed_and_contacts_in_their_colours(tmp_path: Path) -> None:
    image = np.full((120, 160, 3), 128, np.uint8)
    joints = np.array([[20.0, 10.0], [20.0, 60.0], [np.nan, np.nan], [60.0, 100.0]])
    observed = np.array([[100.0, 20.0], [-50.0, 5.0]])  # the second is off the image
    out = draw_overlay(image, joints=[joints], observed=[observed], contacts=np.array([[140.0, 100.0]]))
    assert (image == 128).all()  # the input is not modified
    assert tuple(out[10, 20]) == JOINT_RGB and tuple(out[35, 20]) == JOINT_RGB  # dot, and line between
    assert tuple(out[80, 40]) == (128, 128, 128)  # no line through the NaN joint
    assert tuple(out[20, 100]) == OBSERVED_RGB and tuple(out[100, 140]) == CONTACT_RGB
    path = save_png(tmp_path / "overlay.png", out)
    assert np.array_equal(cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB), out)
    save_png(path, image)  # replaces
    assert (cv2.imread(str(path)) == 128).all()
    assert [p.name for p in tmp_path.iterdir()] == ["overlay.png"]  # no temporary file left


def test_overlay_rejects_bad_input(tmp_path: Path) -> None:
    with pytest.raises(Exception, match="uint8"):
        draw_overlay(np.zeros((10, 10), np.float32))
    with pytest.raises(Exception, match=r"\(K, 2\)"):
        draw_overlay(np.zeros((10, 10, 3), np.uint8), joints=[np.zeros(4)])
    with pytest.raises(Exception, match="could not write.*missing"):
        save_png(tmp_path / "missing" / "x.png", np.zeros((4, 4, 3), np.uint8))


def test_bilinear_sampling_of_more_points_than_opencv_remap_takes_at_once() -> None:
    """A painted-over frame once asked for more than 2**15 samples, beyond cv2.remap's limit on a
    map's rows: sampling goes in blocks, and agrees with scipy's map_coordinates (an independent
    bilinear interpolation) inside the image."""
    from scipy.ndimage import map_coordinates

    from softgrip_vision.keypoints import _bilinear

    image = np.random.default_rng(0).random((50, 60)).astype(np.float32)
    points = np.random.default_rng(1).uniform(-2.0, 62.0, (100_000, 2))  # (u, v) px
    values = _bilinear(image, points)
    reference = map_coordinates(image.astype(np.float64), [points[:, 1], points[:, 0]], order=1, mode="constant")
    inside = (points[:, 0] > 0.5) & (points[:, 0] < 58.5) & (points[:, 1] > 0.5) & (points[:, 1] < 48.5)
    assert values.shape == (100_000,)
    np.testing.assert_allclose(values[inside], reference[inside], atol=1e-4)
    assert _bilinear(image, points.reshape(1000, 100, 2)).shape == (1000, 100)


# A bent finger cut flat at its base (where it leaves the gripper's body): the base keypoint and
# Theta (eq. 4) read back from closed frames whose truth is known, across Theta. The cut's centre
# was once found from a quadratic centre curve followed 2.5 r past its stretch and from lines along
# the finger's direction 2.5 r in, which on a bent finger miss the centre (a circle's next term) and
# leave through a side: the base came out up to 1.5 px toward the tip and Theta too large by 2-12
# mrad, growing with Theta.


def _closed_flat_base(theta: float, centre_x: float, section: str) -> Scene:
    arc = np.asarray(free_arc_points((0.0, 0.0), theta, LENGTH, np.linspace(0.0, LENGTH, 257)))
    return Scene(gripper_centrelines(np.array([centre_x, -40.0]), 76.0, LENGTH, 64, left_shape=arc,
                                     right_shape=arc),
                 half_thickness=HALF_THICKNESS, plane_depth_mm=PLANE_MM, base_end="flat", finger_section=section,
                 supersample=3, seed=3)


@pytest.mark.parametrize("theta", [0.4, 0.8])
def test_a_bent_fingers_flat_base_is_found_at_the_cuts_centre(theta):
    scene = _closed_flat_base(theta, 0.0, "flat")
    frame = render(scene, INTR)
    seg = segment(frame)
    keypoints = gripper_keypoints(seg, PlaneCamera.from_frame(frame, seg.fingers), color=frame.color)
    for k, finger in zip(keypoints, scene.fingers):
        assert k.base_end == "flat"
        truth = mm_to_px(finger[:1], INTR, PLANE_MM)[0]
        assert np.hypot(*(k.base_px - truth)) < 0.3  # px (was 0.8 at Theta 0.4, 1.7 at 0.8)


@pytest.mark.slow  # six frame pairs through one-frame calibration: about 45 s (the base's own test above is fast)
def test_theta_from_flat_based_fingers_has_no_bias_growing_with_theta():
    from softgrip_calib.one_frame import one_frame_from_frames

    errors = {}
    for theta in (0.4, 0.65, 0.8):
        for centre_x, section in ((-25.0, "round"), (25.0, "flat")):  # the gripper about 80 px off centre
            closed = _closed_flat_base(theta, centre_x, section)
            opened = Scene(gripper_centrelines(np.array([centre_x, -40.0]), 76.0, LENGTH, 64),
                           half_thickness=HALF_THICKNESS, plane_depth_mm=PLANE_MM, base_end="flat",
                           finger_section=section, supersample=3, seed=4)
            profile = one_frame_from_frames(render(closed, INTR), render(opened, INTR), 20)
            errors.setdefault(theta, []).extend(profile.fingers[s].theta_entire - theta for s in ("left", "right"))
    worst = max(abs(e) for v in errors.values() for e in v)
    mean = {theta: float(np.mean(v)) for theta, v in errors.items()}
    assert worst < 0.003, errors  # rad, the goal for one frame pair (was up to 0.012)
    assert abs(mean[0.8] - mean[0.4]) < 0.0015, mean  # no trend with Theta (was +0.007)
    assert max(abs(m) for m in mean.values()) < 0.0015, mean
