"""Synthetic scenes: object outlines, gripper layouts and the RGB-D renderer.

Rendered masks are checked against an independent rasterisation (OpenCV's pointPolygonTest on
pixel centres) and shape properties against independent formulas (OpenCV moments, segment
intersection), not against the code under test.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from softgrip_vision.frames import load_frame, save_frame
from synthetic.render import (
    LABEL_BACKGROUND,
    LABEL_FIRST_FINGER,
    LABEL_OBJECT,
    LABEL_PALM,
    Scene,
    d405_intrinsics,
    mm_to_px,
    px_to_mm,
    render,
    render_labels,
)
from synthetic.scenes import gripper_centrelines
from synthetic.shapes import ACCURACY_SET, SHAPES, shape

INTR = d405_intrinsics()
PLANE_MM = 120.0
HALF_THICKNESS_MM = 4.0
OBJECT_OFFSET_MM = (1.3, 10.7)  # object centroid, deliberately off the pixel grid and the axis
CURVED = {"circle": 0, "ellipse": 0, "rounded_rect": 0, "clover": 4, "heart": 2, "crescent": 2}  # corners


def _fingers() -> list[np.ndarray]:
    return gripper_centrelines((0.0, -40.0), 50.0, 52.0, 64)


def _scene(name: str | None = "star_a", **kwargs) -> Scene:
    polygon = None if name is None else shape(name) + OBJECT_OFFSET_MM
    return Scene(_fingers(), half_thickness=HALF_THICKNESS_MM, object_polygon=polygon, **kwargs)


def _to_px(points_mm: np.ndarray) -> np.ndarray:
    """Pinhole projection at the plane depth, written out independently of render.mm_to_px."""
    return np.column_stack([
        INTR.fx * points_mm[:, 0] / PLANE_MM + INTR.ppx,
        INTR.fy * points_mm[:, 1] / PLANE_MM + INTR.ppy,
    ])


def _saturation(color: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(color, cv2.COLOR_RGB2HSV)[..., 1]


def _shoelace(polygon: np.ndarray) -> float:
    x, y = polygon.T
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab, ap = b - a, p - a
    t = np.clip(np.sum(ap * ab, -1) / np.maximum(np.sum(ab * ab, -1), 1e-300), 0.0, 1.0)
    return np.linalg.norm(ap - t[..., None] * ab, axis=-1)


def _non_adjacent_edges_clear(polygon: np.ndarray) -> float:
    """Smallest distance between two non-adjacent edges; 0 if any two of them cross or touch."""
    v = len(polygon)
    a, b = polygon, np.roll(polygon, -1, axis=0)
    i, j = np.triu_indices(v, k=2)
    keep = (j - i) % v != v - 1  # the first and last edges are adjacent too
    i, j = i[keep], j[keep]
    if i.size == 0:
        return math.inf

    def orient(p, q, r):
        pq, pr = q - p, r - p
        return pq[..., 0] * pr[..., 1] - pq[..., 1] * pr[..., 0]

    crossing = (orient(a[i], b[i], a[j]) * orient(a[i], b[i], b[j]) < 0) & (
        orient(a[j], b[j], a[i]) * orient(a[j], b[j], b[i]) < 0
    )
    if crossing.any():
        return 0.0
    return float(np.min([
        _point_segment_distance(a[i], a[j], b[j]).min(),
        _point_segment_distance(b[i], a[j], b[j]).min(),
        _point_segment_distance(a[j], a[i], b[i]).min(),
        _point_segment_distance(b[j], a[i], b[i]).min(),
    ]))


def _hausdorff(p: np.ndarray, q: np.ndarray) -> float:
    d = np.linalg.norm(p[:, None, :] - q[None, :, :], axis=-1)
    return float(max(d.min(axis=1).max(), d.min(axis=0).max()))


# --- shapes ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(SHAPES))
@pytest.mark.parametrize(("size_mm", "angle"), [(30.0, 0.0), (17.5, 0.7)])
def test_shape_is_a_simple_centred_ccw_polygon_of_the_requested_size(name, size_mm, angle):
    polygon = shape(name, size_mm=size_mm, angle=angle)
    assert polygon.dtype == np.float64 and polygon.ndim == 2 and polygon.shape[1] == 2
    assert polygon.shape[0] >= 3 and np.isfinite(polygon).all()
    edge = np.linalg.norm(np.roll(polygon, -1, axis=0) - polygon, axis=1)
    assert edge.min() > 1e-6 * size_mm  # no repeated vertex, closing one included
    area = _shoelace(polygon)
    assert area < 0.0  # counter-clockwise on the image (y down), like OpenCV's outer contours
    moments = cv2.moments(polygon.astype(np.float32))
    assert moments["m00"] == pytest.approx(-area, rel=1e-5)
    centroid = np.array([moments["m10"], moments["m01"]]) / moments["m00"]
    np.testing.assert_allclose(centroid, 0.0, atol=1e-4 * size_mm)
    assert np.linalg.norm(polygon, axis=1).max() == pytest.approx(size_mm / 2, rel=1e-12)
    assert _non_adjacent_edges_clear(polygon) > 1e-3 * size_mm


@pytest.mark.parametrize(("name", "corners"), CURVED.items())
def test_curved_shapes_are_smooth_between_their_corners(name, corners):
    polygon = shape(name, size_mm=30.0)
    edges = np.roll(polygon, -1, axis=0) - polygon
    heading = np.arctan2(edges[:, 1], edges[:, 0])
    turn = np.angle(np.exp(1j * (np.roll(heading, -1) - heading)))  # at each vertex, rad
    assert polygon.shape[0] >= 96
    assert np.count_nonzero(np.abs(turn) > math.radians(8.0)) == corners  # curves are dense


@pytest.mark.parametrize(
    ("name", "area_over_r2"),
    [
        ("circle", math.pi),
        ("square", 2.0),
        ("triangle_a", 3 * math.sqrt(3) / 4),
        ("hexagon", 3 * math.sqrt(3) / 2),
        ("pentagon", 5 / 2 * math.sin(2 * math.pi / 5)),
    ],
)
def test_shape_areas_match_geometry(name, area_over_r2):
    r = 12.0
    assert -_shoelace(shape(name, size_mm=2 * r)) == pytest.approx(area_over_r2 * r**2, rel=2e-3)


def test_unknown_shape_names_the_valid_ones():
    with pytest.raises(ValueError, match="unknown shape 'moon'.*circle.*triangle_b.*l_shape"):
        shape("moon")


@pytest.mark.parametrize("size_mm", [0.0, -3.0, math.nan, math.inf])
def test_bad_size_is_refused(size_mm):
    with pytest.raises(ValueError, match="size_mm"):
        shape("circle", size_mm=size_mm)


def test_registry_and_accuracy_set():
    assert {"circle", "square", "clover", "star_a", "star_b", "triangle_a", "triangle_b"} <= set(SHAPES)
    assert len(SHAPES) >= 13
    assert ACCURACY_SET == ("circle", "square", "clover", "star_a", "triangle_a")
    np.testing.assert_array_equal(SHAPES["heart"](size_mm=20.0, angle=0.3), shape("heart", 20.0, 0.3))


@pytest.mark.parametrize(("pose_a", "pose_b", "turn"), [("star_a", "star_b", math.pi / 5),
                                                        ("triangle_a", "triangle_b", math.pi / 3)])
def test_poses_a_and_b_are_one_object_in_two_poses(pose_a, pose_b, turn):
    a, b = shape(pose_a), shape(pose_b)
    assert _hausdorff(a, b) > 3.0  # mm: clearly different outlines
    assert _shoelace(a) == pytest.approx(_shoelace(b))
    assert _hausdorff(shape(pose_a, angle=turn), b) < 1e-9  # the same object, turned
    assert a[:, 1].min() == pytest.approx(-15.0)  # pose A: a vertex points up (-y), at the bases
    assert b[:, 1].max() == pytest.approx(15.0)  # pose B: a vertex points down


def test_positive_angle_turns_down_toward_plus_x():
    a = 0.4
    turned = shape("triangle_b", size_mm=30.0, angle=a)  # triangle_b has a vertex at (0, 15)
    apex = turned[np.argmax(turned @ np.array([math.sin(a), math.cos(a)]))]
    np.testing.assert_allclose(apex, [15 * math.sin(a), 15 * math.cos(a)], atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(
    name=st.sampled_from(sorted(SHAPES)),
    size_mm=st.floats(1.0, 200.0),
    angle=st.floats(-2 * math.pi, 2 * math.pi),
)
def test_rotation_is_rigid_about_the_centroid(name, size_mm, angle):
    base, turned = shape(name, size_mm), shape(name, size_mm, angle)
    c, s = math.cos(angle), math.sin(angle)
    expected = np.column_stack([c * base[:, 0] + s * base[:, 1], -s * base[:, 0] + c * base[:, 1]])
    np.testing.assert_allclose(turned, expected, atol=1e-9 * size_mm)


# --- camera model ---------------------------------------------------------------------------------


def test_d405_intrinsics_are_realistic():
    assert (INTR.width, INTR.height, INTR.depth_scale) == (640, 480, 1e-4)
    assert INTR.fx == INTR.fy == pytest.approx(385.0)
    assert abs(INTR.ppx - 320) < 4 and abs(INTR.ppy - 240) < 4
    big = d405_intrinsics(1280, 960)
    assert big.fx == pytest.approx(2 * INTR.fx) and big.ppx == pytest.approx(2 * INTR.ppx)


@settings(max_examples=50, deadline=None)
@given(
    x=st.floats(-100, 100), y=st.floats(-100, 100), depth_mm=st.floats(50.0, 1000.0),
)
def test_mm_px_round_trip(x, y, depth_mm):
    p = np.array([[x, y]])
    px = mm_to_px(p, INTR, depth_mm)
    np.testing.assert_allclose(px, [[INTR.fx * x / depth_mm + INTR.ppx, INTR.fy * y / depth_mm + INTR.ppy]])
    np.testing.assert_allclose(px_to_mm(px, INTR, depth_mm), p, atol=1e-9)


def test_mm_px_broadcast_per_point_depths():
    points = np.array([[[10.0, -5.0], [0.0, 0.0]]])  # (1, 2, 2)
    depths = np.array([[100.0, 200.0]])
    px = mm_to_px(points, INTR, depths)
    assert px.shape == (1, 2, 2)
    np.testing.assert_allclose(px[0, 1], [INTR.ppx, INTR.ppy])
    np.testing.assert_allclose(px_to_mm(px, INTR, depths), points)


# --- rendering ------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_object_mask_matches_an_independent_rasterisation(name):
    scene = _scene(name, n_depth_holes=0)
    frame = render(scene, INTR)
    mask = _saturation(frame.color) > 128
    polygon_px = _to_px(scene.object_polygon)

    lo = np.floor(polygon_px.min(axis=0)).astype(int) - 3
    hi = np.ceil(polygon_px.max(axis=0)).astype(int) + 3
    contour = polygon_px.astype(np.float32).reshape(-1, 1, 2)
    signed = np.array([
        [cv2.pointPolygonTest(contour, (float(u), float(v)), True) for u in range(lo[0], hi[0])]
        for v in range(lo[1], hi[1])
    ])  # > 0 inside, px from the outline
    window = mask[lo[1]:hi[1], lo[0]:hi[0]]
    assert mask.sum() == window.sum()  # nothing saturated away from the object
    assert window[signed > 1.0].all()  # within 1 px of the outline
    assert not window[signed < -1.0].any()
    # The documented rule: a pixel is the object's exactly when its centre is inside the outline.
    assert window[signed > 1e-3].all()
    assert not window[signed < -1e-3].any()
    area_px = -_shoelace(polygon_px)
    assert abs(window.sum() - area_px) < 0.5 * cv2.arcLength(contour, closed=True)


def test_labels_are_the_painted_masks():
    scene = _scene("clover", n_depth_holes=0, palm=True)
    frame, labels = render(scene, INTR), render_labels(scene, INTR)
    assert labels.dtype == np.uint8 and labels.shape == (INTR.height, INTR.width)
    assert set(np.unique(labels)) == {LABEL_BACKGROUND, LABEL_OBJECT, LABEL_PALM,
                                      LABEL_FIRST_FINGER, LABEL_FIRST_FINGER + 1}
    np.testing.assert_array_equal(_saturation(frame.color) > 128, labels == LABEL_OBJECT)


def test_fingers_cover_their_centrelines_with_the_right_width():
    scene = _scene(None, n_depth_holes=0)
    frame, labels = render(scene, INTR), render_labels(scene, INTR)
    hsv = cv2.cvtColor(frame.color, cv2.COLOR_RGB2HSV)
    for k, finger in enumerate(scene.fingers):
        u, v = np.rint(_to_px(finger)).astype(int).T
        assert (labels[v, u] == LABEL_FIRST_FINGER + k).all()
        assert (hsv[v, u, 1] < 40).all() and (hsv[v, u, 2] > 180).all()  # light, unsaturated
        row = int(np.rint(_to_px(finger[len(finger) // 2 : len(finger) // 2 + 1])[0, 1]))
        width_px = np.count_nonzero(labels[row] == LABEL_FIRST_FINGER + k)
        assert abs(width_px - 2 * HALF_THICKNESS_MM * INTR.fx / PLANE_MM) <= 1.0
    background = labels == LABEL_BACKGROUND
    assert hsv[background, 2].mean() < 0.6 * hsv[~background, 2].mean()  # darker
    assert np.percentile(hsv[background, 1], 99) < 60  # unsaturated


def test_finger_tip_ends_where_the_centreline_ends():
    scene = _scene(None, n_depth_holes=0)
    labels = render_labels(scene, INTR)
    tip = _to_px(scene.fingers[0][-1:])[0]
    below_tip_px = HALF_THICKNESS_MM * INTR.fy / PLANE_MM
    column = int(np.rint(tip[0]))
    rows = np.nonzero(labels[:, column] == LABEL_FIRST_FINGER)[0]
    assert abs(rows.max() - (tip[1] + below_tip_px)) <= 1.0


def test_depth_reads_plane_object_and_background():
    scene = _scene("square", n_depth_holes=0, object_depth_offset_mm=3.0)
    frame, labels = render(scene, INTR), render_labels(scene, INTR)
    depth_mm = frame.depth.astype(np.float64) * INTR.depth_scale * 1000.0
    gripper = depth_mm[labels >= LABEL_FIRST_FINGER]
    assert gripper.mean() == pytest.approx(PLANE_MM, abs=0.03)
    assert 0.25 < gripper.std() < 0.35
    assert np.abs(gripper - PLANE_MM).max() < 6 * 0.3
    assert depth_mm[labels == LABEL_OBJECT].mean() == pytest.approx(PLANE_MM + 3.0, abs=0.05)
    assert depth_mm[labels == LABEL_BACKGROUND].mean() == pytest.approx(400.0, abs=0.2)
    assert frame.depth.min() > 0


def test_holes_are_small_zero_blobs_on_the_foreground_and_change_nothing_else():
    with_holes = render(_scene("circle", n_depth_holes=5, seed=7), INTR)
    without = render(_scene("circle", n_depth_holes=0, seed=7), INTR)
    labels = render_labels(_scene("circle"), INTR)
    holes = with_holes.depth == 0
    assert not (without.depth == 0).any()
    assert holes.any()
    np.testing.assert_array_equal(with_holes.color, without.color)
    np.testing.assert_array_equal(with_holes.depth[~holes], without.depth[~holes])
    n, components, stats, _ = cv2.connectedComponentsWithStats(holes.astype(np.uint8), connectivity=8)
    assert 1 <= n - 1 <= 5
    assert stats[1:, cv2.CC_STAT_AREA].max() <= math.pi * 4.5**2
    for c in range(1, n):
        assert (labels[components == c] != LABEL_BACKGROUND).any()


def test_render_is_deterministic_for_a_seed():
    a, b = render(_scene(seed=3), INTR), render(_scene(seed=3), INTR)
    c = render(_scene(seed=4), INTR)
    np.testing.assert_array_equal(a.color, b.color)
    np.testing.assert_array_equal(a.depth, b.depth)
    assert not np.array_equal(a.color, c.color) and not np.array_equal(a.depth, c.depth)


def test_noise_free_render_is_exact():
    scene = _scene("triangle_b", n_depth_holes=0, color_noise_sigma=0.0, depth_noise_sigma_mm=0.0)
    frame, labels = render(scene, INTR), render_labels(scene, INTR)
    assert (frame.color[labels == LABEL_OBJECT] == scene.object_rgb).all()
    assert (frame.depth[labels >= LABEL_FIRST_FINGER] == 1200).all()  # 120 mm in 0.1 mm units


def test_palm_joins_the_bases_just_above_them():
    between_bases = np.array([[0.0, -40.0 - 3.0]])  # mm: midway, 3 mm above the bases
    u, v = np.rint(_to_px(between_bases)[0]).astype(int)
    with_palm = render_labels(_scene(None, palm=True), INTR)
    assert with_palm[v, u] == LABEL_PALM
    assert render_labels(_scene(None), INTR)[v, u] == LABEL_BACKGROUND
    above = np.rint(_to_px(np.array([[0.0, -40.0 - 7.0]]))[0]).astype(int)
    assert with_palm[above[1], above[0]] == LABEL_BACKGROUND


def test_frame_survives_save_and_load(tmp_path):
    frame = render(_scene("heart"), INTR)
    loaded = load_frame(save_frame(frame, tmp_path / "frame"))
    np.testing.assert_array_equal(loaded.color, frame.color)
    np.testing.assert_array_equal(loaded.depth, frame.depth)
    assert loaded.intrinsics == INTR


def test_scene_checks_its_fields():
    with pytest.raises(ValueError, match=r"fingers\[1\]"):
        Scene([np.zeros((5, 2)), np.zeros((1, 2))])
    with pytest.raises(ValueError, match="object_polygon"):
        Scene(_fingers(), object_polygon=np.array([[0.0, np.nan], [1, 0], [0, 1]]))
    with pytest.raises(ValueError, match="background_depth_mm"):
        Scene(_fingers(), background_depth_mm=100.0)
    with pytest.raises(ValueError, match="object_rgb"):
        Scene(_fingers(), object_rgb=(300, 0, 0))
    with pytest.raises(ValueError, match="palm"):
        Scene([], palm=True)
    with pytest.raises(ValueError, match="depth_scale"):
        render(Scene(_fingers(), background_depth_mm=7000.0), INTR)


def test_no_gripper_no_object_renders_background():
    labels = render_labels(Scene([]), INTR)
    assert (labels == LABEL_BACKGROUND).all()
    assert render(Scene([], n_depth_holes=2), INTR).depth.min() == 0


# --- gripper layout -------------------------------------------------------------------------------


def test_open_gripper_has_straight_fingers_at_the_bases():
    left, right = gripper_centrelines((5.0, -30.0), 40.0, 52.0, 27)
    assert left.shape == right.shape == (27, 2)
    np.testing.assert_allclose(left[:, 0], -15.0)
    np.testing.assert_allclose(right[:, 0], 25.0)
    np.testing.assert_allclose(left[:, 1], np.linspace(-30.0, 22.0, 27))
    np.testing.assert_allclose(right[:, 1], left[:, 1])


def test_closed_shapes_are_placed_and_the_right_one_mirrored():
    curl = np.array([[0.0, 0.0], [2.0, 20.0], [8.0, 38.0], [18.0, 48.0]])  # curls toward +x
    left, right = gripper_centrelines((0.0, 0.0), 50.0, 52.0, 64, left_shape=curl, right_shape=curl)
    np.testing.assert_allclose(left, curl + (-25.0, 0.0))
    np.testing.assert_allclose(right, curl * (-1.0, 1.0) + (25.0, 0.0))
    assert right[-1, 0] < 25.0  # the right finger curls toward the centre (-x)


def test_a_shape_must_start_at_its_base():
    with pytest.raises(ValueError, match="left_shape must start at its base"):
        gripper_centrelines((0.0, 0.0), 50.0, 52.0, 64, left_shape=np.array([[1.0, 0.0], [1.0, 10.0]]))
    with pytest.raises(ValueError, match="right_shape"):
        gripper_centrelines((0.0, 0.0), 50.0, 52.0, 64, right_shape=np.zeros((1, 2)))
