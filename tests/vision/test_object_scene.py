"""softgrip_vision.object_scene: a scene from a frame of the object alone and the arm's pose of the gripper.

The pose is checked against hand-derived geometry (a plane's depth on the optical axis, the
gripper origin and its right base back in camera coordinates) and against the other way to the same
scene: a frame of the same set-up with the gripper in view, measured by frame_scene. The object's
SDF and segment_object's mask are checked against the rendered disc under the renderer's other
conditions: lighting, depth noise and holes, and a gripper partly in view.
"""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import numpy as np
import pytest

from softgrip_calib.profile import load_profile
import softgrip_vision.object_scene as object_scene_module
from softgrip_vision.object_scene import gripper_plane, object_scene
from softgrip_vision.scene import FrameSceneError, frame_scene
from softgrip_vision.segmentation import segment_object
from synthetic.render import (LABEL_FIRST_FINGER, LABEL_OBJECT, Scene, d405_intrinsics, mm_to_px, plane_points_3d,
                              plane_rotation, render, render_labels)
from synthetic.scenes import gripper_centrelines

DATA = Path(__file__).resolve().parents[2] / "data"
PROFILE = load_profile(DATA / "sample_profile.json")
INTRINSICS = d405_intrinsics()
ANGLES = np.linspace(0.0, 2.0 * np.pi, 96, endpoint=False)
DISC = np.stack([14.0 * np.cos(ANGLES), 12.0 + 14.0 * np.sin(ANGLES)], axis=-1)  # mm in the gripper plane


def _transform(rotation: np.ndarray, origin: np.ndarray) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = rotation, origin
    return t


def _rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("tilt", [(0.0, 0.0), (12.0, -8.0)])
@pytest.mark.parametrize("turn", [0.0, 0.15])
def test_the_pose_puts_the_gripper_origin_and_its_right_base_back_where_the_transform_says(tilt, turn):
    # The gripper's frame: x along the base line, y along the fingers, z the plane's normal.
    rotation = plane_rotation(tilt) @ _rot_z(-turn)
    origin = np.array([6.0, -35.0, 140.0])
    camera, pose = gripper_plane(INTRINSICS, _transform(rotation, origin))
    normal = rotation[:, 2]
    # On paper: the plane n . p = n . origin meets the optical axis (0, 0, Z) at Z = n . origin / n_z.
    assert camera.depth_mm == pytest.approx(normal @ origin / normal[2], abs=1e-9)
    np.testing.assert_allclose(camera.normal, normal, atol=1e-12)
    np.testing.assert_allclose(camera.points_3d(pose[:2]), origin, atol=1e-9)
    # The right finger's base, W/2 along the gripper's x axis, is W/2 along the pose's "across".
    half = 28.0
    across = np.array([math.cos(pose[2]), -math.sin(pose[2])])
    np.testing.assert_allclose(camera.points_3d(pose[:2] + half * across), origin + half * rotation[:, 0], atol=1e-9)
    if tilt == (0.0, 0.0):  # facing the camera, the turn about the optical axis is the pose's angle
        assert pose[2] == pytest.approx(turn, abs=1e-12)


@pytest.mark.parametrize("tilt", [(0.0, 0.0), (10.0, 6.0)])
def test_an_object_only_frame_and_the_arms_pose_give_the_scene_a_frame_with_the_gripper_gives(tilt):
    centre = np.array([0.0, -40.0])
    fingers = gripper_centrelines(tuple(centre), PROFILE.base_separation, PROFILE.fingers["left"].length)
    common = dict(half_thickness=PROFILE.fingers["left"].half_thickness, object_polygon=DISC, tilt_deg=tilt)
    with_gripper = frame_scene(render(Scene(fingers, **common), INTRINSICS), PROFILE, warn=lambda _: None)
    rotation = plane_rotation(tilt)
    origin = plane_points_3d(Scene(fingers, **common), centre)
    alone = object_scene(render(Scene([], **common), INTRINSICS), PROFILE, _transform(rotation, origin),
                         warn=lambda _: None)
    # The same plane and pose as measured from the fingers (to the measurement's accuracy) ...
    assert alone.camera.depth_mm == pytest.approx(with_gripper.camera.depth_mm, abs=0.5)
    np.testing.assert_allclose(alone.pose[:2], with_gripper.pose[:2], atol=0.5)
    assert alone.pose[2] == pytest.approx(with_gripper.pose[2], abs=0.01)
    # ... and the same object: distances near its outline agree (the grids differ in size only).
    a = np.linspace(0.0, 2.0 * np.pi, 24, endpoint=False)
    ring = plane_points_3d(Scene(fingers, **common), np.stack([20.0 * np.cos(a), 12.0 + 20.0 * np.sin(a)], -1))
    ex, ey, _ = alone.camera.axes  # the ring in the scene's plane coordinates
    probes = np.stack([(ring - [0.0, 0.0, alone.camera.depth_mm]) @ axis for axis in (ex, ey)], axis=-1)
    far = np.asarray(alone.sdf.distance(probes))
    near = np.asarray(with_gripper.sdf.distance(probes))
    np.testing.assert_allclose(far, near, atol=0.3)
    np.testing.assert_allclose(far, 6.0, atol=0.5)  # 20 mm from the centre of a 14 mm disc
    assert not alone.segmentation.fingers.any() and alone.segmentation.split == "none"


def test_the_grid_reaches_fingers_that_hang_from_above_the_image():
    # The gripper 95 mm above the optical axis: its bases are above the image's top edge (about 72 mm up).
    origin = np.array([0.0, -95.0, 120.0])
    scene = object_scene(render(Scene([], object_polygon=DISC + [0.0, -40.0]), INTRINSICS), PROFILE,
                         _transform(np.eye(3), origin), warn=lambda _: None)
    top_edge_mm = scene.camera.px_to_mm([0.0, -0.5])[1]
    assert scene.bases_mm[:, 1].max() < top_edge_mm  # the bases are out of view ...
    grid_top = float(scene.sdf.origin[1])
    assert grid_top < scene.bases_mm[:, 1].min() - PROFILE.fingers["left"].length  # ... but on the grid
    distance = float(scene.sdf.distance(np.asarray(scene.bases_mm[0])))
    assert distance > 20.0  # free space there, not an object


def test_arm_poses_near_the_view_share_one_grid_shape_whose_values_are_the_images_own():
    # Tens of mm apart and a few mm deeper or nearer: one grid shape, so the scoring programs (and
    # here a jitted lookup) compile once; on the image's pixels the padded grid holds exactly what
    # object_sdf gives on the image alone, and beyond it the distance to the disc.
    import jax

    from softgrip_vision.coverage import edge_coverage
    from softgrip_vision.geometry import face_offset_mm
    from softgrip_vision.object_sdf import object_sdf

    frame = render(Scene([], object_polygon=DISC), INTRINSICS)
    lookup = jax.jit(lambda sdf, points: sdf.distance(points))
    shapes = set()
    for origin in ([0.0, -40.0, 120.0], [28.0, -12.0, 117.0], [-30.0, -75.0, 123.5]):
        scene = object_scene(frame, PROFILE, _transform(np.eye(3), np.array(origin)), warn=lambda _: None)
        shapes.add(scene.sdf.values.shape)
        lookup(scene.sdf, np.zeros((4, 2), np.float32)).block_until_ready()
        mask = scene.segmentation.object
        alone = object_sdf(mask, scene.camera.parallel(face_offset_mm(scene.frame, mask, scene.camera)),
                           coverage=edge_coverage(scene.frame.color, mask))
        np.testing.assert_allclose(np.asarray(scene.sdf.spacing), np.asarray(alone.spacing), rtol=1e-6)
        col, row = np.rint((np.asarray(alone.origin) - np.asarray(scene.sdf.origin))
                           / np.asarray(alone.spacing)).astype(int)
        assert row > 0 and col > 0  # padded on every side
        # (to float32 rounding: the far field's arithmetic runs in float32 on grids whose spacings
        # differ in the seventh digit)
        np.testing.assert_allclose(np.asarray(scene.sdf.values)[row:row + 480, col:col + 640],
                                   np.asarray(alone.values), rtol=1e-6, atol=1e-6)
        # Past the image (the bases hang above it in the last pose): the distance to the disc, mm.
        beyond = np.array([[0.0, float(alone.origin[1]) - 20.0], [float(alone.origin[0]) - 20.0, 12.0]])
        np.testing.assert_allclose(np.asarray(scene.sdf.distance(beyond)),
                                   np.hypot(beyond[:, 0], beyond[:, 1] - 12.0) - 14.0, atol=0.3)
    assert len(shapes) == 1 and all(min(s) > 640 for s in shapes), shapes
    assert lookup._cache_size() == 1


@pytest.mark.parametrize("pose, match", [
    (np.eye(3), "4 x 4"),
    (np.full((4, 4), np.nan), "4 x 4"),
    ("identity", "4 x 4"),
    (_transform(2.0 * np.eye(3), [0.0, 0.0, 120.0]), "not rigid"),
    (_transform(np.diag([1.0, 1.0, -1.0]), [0.0, 0.0, 120.0]), "not rigid"),  # a reflection
    (_transform(np.eye(3), [0.0, 0.0, -120.0]), "not in front of the camera"),
    (_transform(np.diag([-1.0, 1.0, -1.0]), [0.0, 0.0, 120.0]), "from its back"),
    (_transform(plane_rotation((0.0, 85.0)), [0.0, 0.0, 120.0]), "edge on"),
])
def test_a_pose_that_cannot_be_the_grippers_is_refused_with_the_reason(pose, match):
    with pytest.raises(FrameSceneError, match=match):
        gripper_plane(INTRINSICS, pose)


def test_a_pose_far_outside_the_view_names_the_unit_mistake_and_bad_inputs_name_themselves():
    frame = render(Scene([], object_polygon=DISC), INTRINSICS)
    metres = _transform(np.eye(3), [0.0, -0.04, 0.12])  # metres, not mm: 0.12 mm deep
    with pytest.raises(FrameSceneError, match="not metres"):
        object_scene(frame, PROFILE, metres)
    with pytest.raises(FrameSceneError, match="check that gripper_pose is in mm"):  # 5 m away in x
        object_scene(frame, PROFILE, _transform(np.eye(3), [5000.0, -40.0, 120.0]))
    notes: list[str] = []
    object_scene(frame, PROFILE, _transform(np.eye(3), [0.0, -40.0, 60.0]), warn=notes.append)
    assert any("farther than a finger is long" in note for note in notes)  # the object 60 mm behind the plane
    with pytest.raises(FrameSceneError, match="margin_mm"):
        object_scene(frame, PROFILE, _transform(np.eye(3), [0.0, -40.0, 120.0]), margin_mm=-1.0)
    with pytest.raises(FrameSceneError, match="profile"):
        object_scene(frame, {"fingers": {}}, _transform(np.eye(3), [0.0, -40.0, 120.0]))


def test_an_object_cut_by_the_image_border_is_warned_about():
    notes: list[str] = []
    big = np.stack([40.0 * np.cos(ANGLES), 90.0 + 40.0 * np.sin(ANGLES)], axis=-1)  # runs off the bottom
    object_scene(render(Scene([], object_polygon=big), INTRINSICS), PROFILE,
                 _transform(np.eye(3), [0.0, -40.0, 120.0]), warn=notes.append)
    assert any("runs off the image" in note for note in notes)


# ---------------------------------------------------------------------------------------------
# The renderer's other assumptions, swept on the object-only path: lighting, depth noise and holes,
# a gripper partly in view. The truth is the rendered disc DISC (centre (0, 12) mm, radius 14 mm).

ARM_POSE = _transform(np.eye(3), [0.0, -40.0, 120.0])  # the gripper facing the camera, 40 mm above the disc
RING = np.linspace(0.0, 2.0 * np.pi, 48, endpoint=False)


def _disc_ring(radius_mm: float) -> np.ndarray:
    """(48, 2) mm: points radius_mm from DISC's centre, in the renderer's plane coordinates."""
    return np.stack([radius_mm * np.cos(RING), 12.0 + radius_mm * np.sin(RING)], axis=-1)


def _contrast(factor: float):
    """The colour image's contrast scaled by ``factor`` about mid-grey (128), as a flat-looking camera gives."""
    def apply(frame):
        color = np.clip(np.rint(128.0 + factor * (frame.color.astype(np.float64) - 128.0)), 0, 255)
        return dataclasses.replace(frame, color=color.astype(np.uint8))
    return apply


def _depth_hole(radius_px: float, centre_mm=(0.0, 12.0)):
    """Zero depth (no reading) on a disc of radius_px pixels about centre_mm in the plane 120 mm deep."""
    def apply(frame):
        u0, v0 = mm_to_px(np.array([centre_mm]), INTRINSICS, 120.0)[0]
        v, u = np.indices(frame.depth.shape)
        depth = frame.depth.copy()
        depth[(u - u0) ** 2 + (v - v0) ** 2 <= radius_px ** 2] = 0
        return dataclasses.replace(frame, depth=depth)
    return apply


def _no_object(frame):
    """The frame with the object's pixels replaced by the background's (colour and depth of a corner)."""
    labels = render_labels(Scene([], object_polygon=DISC), INTRINSICS)
    color, depth = frame.color.copy(), frame.depth.copy()
    color[labels == LABEL_OBJECT], depth[labels == LABEL_OBJECT] = frame.color[0, 0], frame.depth[0, 0]
    return dataclasses.replace(frame, color=color, depth=depth)


def _object_only(post=None, settings=None, margin_mm=object_scene_module.DEFAULT_MARGIN_MM, **scene_kw):
    """Render DISC with ``scene_kw`` (no gripper unless ``fingers`` is given), apply ``post`` to the
    frame, and return (frame, render Scene, object_scene's scene, its warnings)."""
    rendered = Scene(scene_kw.pop("fingers", []), object_polygon=DISC, **scene_kw)
    frame = render(rendered, INTRINSICS)
    frame = post(frame) if post is not None else frame
    notes: list[str] = []
    scene = object_scene(frame, PROFILE, ARM_POSE, margin_mm=margin_mm, settings=settings, warn=notes.append)
    return frame, rendered, scene, notes


def _assert_the_disc_is_recovered(scene, rendered) -> None:
    """The scene's SDF (mm) against the true disc: ~0 on its outline, +6 mm 6 mm outside, -7 mm 7 mm
    inside (a false free-space pocket inside would show there), and free space at the finger bases."""
    offset = rendered.object_depth_offset_mm
    def probes(radius_mm):  # the renderer's plane points -> the scene's plane coordinates (mm)
        points = plane_points_3d(rendered, _disc_ring(radius_mm), offset) - offset * np.asarray(scene.camera.normal)
        ex, ey, _ = scene.camera.axes
        return np.stack([(points - [0.0, 0.0, scene.camera.depth_mm]) @ axis for axis in (ex, ey)], axis=-1)
    on = np.abs(np.asarray(scene.sdf.distance(probes(14.0))))
    assert on.mean() < 0.1 and on.max() < 0.3, (on.mean(), on.max())
    np.testing.assert_allclose(np.asarray(scene.sdf.distance(probes(20.0))), 6.0, atol=0.25)
    np.testing.assert_allclose(np.asarray(scene.sdf.distance(probes(7.0))), -7.0, atol=0.3)
    assert np.asarray(scene.sdf.distance(np.asarray(scene.bases_mm))).min() > 20.0


def _assert_segment_object_finds_the_disc(frame, rendered) -> None:
    """segment_object's object mask against the renderer's labels: intersection over union >= 0.99,
    and no finger pixel taken for the object."""
    seg = segment_object(frame, PROFILE.segmentation_settings())
    labels = render_labels(rendered, INTRINSICS)
    truth = labels == LABEL_OBJECT
    iou = (seg.object & truth).sum() / (seg.object | truth).sum()
    assert iou >= 0.99, iou
    assert not (seg.object & (labels >= LABEL_FIRST_FINGER)).any()


LIGHTING = {
    "dim (gain 0.3)": dict(light_gain=0.3),
    "dark (gain 0.5)": dict(light_gain=0.5),
    "bright (gain 1.6)": dict(light_gain=1.6),
    "overexposed (gain 2.5)": dict(light_gain=2.5),
    "uneven, darker right": dict(light_gradient=-0.5),
    "uneven, brighter right": dict(light_gradient=0.9),
    "low contrast 0.6": dict(post=_contrast(0.6)),
    "low contrast 0.4": dict(post=_contrast(0.4)),
}


@pytest.mark.parametrize("lighting", LIGHTING.values(), ids=LIGHTING.keys())
def test_the_object_alone_is_recovered_under_the_lighting_a_camera_may_see(lighting):
    frame, rendered, scene, notes = _object_only(**lighting)
    _assert_the_disc_is_recovered(scene, rendered)
    _assert_segment_object_finds_the_disc(frame, rendered)
    assert notes == []


@pytest.mark.parametrize("lighting, reading", [
    (dict(light_gain=0.15), "value"), (dict(post=_contrast(0.25)), "saturation")],
    ids=["too dark (gain 0.15)", "washed out (contrast 0.25)"])
def test_an_object_the_colour_thresholds_miss_is_warned_about_with_its_colour(lighting, reading):
    # The depth shows the disc in front of the background; its colour falls below a threshold. The
    # scene has no object (what the thresholds say), and the warning gives the region's colour.
    frame, rendered, scene, notes = _object_only(**lighting)
    assert not scene.has_object
    assert len(notes) == 1 and "neither object- nor gripper-coloured" in notes[0], notes
    median = float(re.search(r"median saturation ([0-9.]+), value ([0-9.]+)", notes[0]).group(
        1 if reading == "saturation" else 2))
    limit = getattr(PROFILE.segmentation_settings(), f"object_min_{reading}")
    assert median < limit, (median, limit)  # the threshold it names is the one the object misses
    # The region named is the disc: its pixel count within 10 % of the rendered disc's.
    count = int(re.search(r"a region of (\d+) px", notes[0]).group(1))
    truth = int((render_labels(rendered, INTRINSICS) == LABEL_OBJECT).sum())
    assert abs(count - truth) < 0.1 * truth, (count, truth)


def test_a_frame_without_an_object_is_not_warned_about():
    frame, rendered, scene, notes = _object_only(post=_no_object)
    assert not scene.has_object and notes == []


@pytest.mark.parametrize("sigma_mm", [0.0, 1.0, 2.0, 4.0])
def test_depth_noise_leaves_the_object_and_its_face_depth(sigma_mm):
    # The face 5 mm behind the gripper plane: taking it at the plane instead would shrink the disc by
    # 14 * 5 / 125 = 0.56 mm, beyond the outline's tolerance, so the face's depth is read despite the noise.
    frame, rendered, scene, notes = _object_only(depth_noise_sigma_mm=sigma_mm, object_depth_offset_mm=5.0, seed=2)
    _assert_the_disc_is_recovered(scene, rendered)
    _assert_segment_object_finds_the_disc(frame, rendered)
    assert notes == []


HOLES = {
    "20 small holes": dict(n_depth_holes=20, seed=3),
    "150 small holes": dict(n_depth_holes=150, seed=3),
    "a 5 px hole inside": dict(post=_depth_hole(5.0)),
}
HOLE_FILL_REASON = (
    "no-reading pixels farther than about hole_fill_px / 2 (7 px by default) from a depth reading are "
    "left out of the object mask whatever their colour, so a large depth hole {} the object's SDF")
UNFILLED_HOLES = {
    # Holes the object encloses are filled by colour (segmentation.fill_enclosed_holes); one that
    # opens onto the background is not: its colour there is the background's, which may pass for the
    # object's (a stereo camera's occlusion shadow beside an object on a coloured table).
    "a 20 px hole inside": dict(post=_depth_hole(20.0)),
    "a 30 px hole inside": dict(post=_depth_hole(30.0)),
    "a 15 px hole on the edge": pytest.param(dict(post=_depth_hole(15.0, (14.0, 12.0))), marks=pytest.mark.xfail(
        strict=True, reason=HOLE_FILL_REASON.format("on the outline bites into"))),
}


@pytest.mark.parametrize("holes", [*HOLES.values(), *UNFILLED_HOLES.values()], ids=[*HOLES, *UNFILLED_HOLES])
def test_depth_holes_on_the_object_leave_its_outline_and_inside(holes):
    frame, rendered, scene, notes = _object_only(**holes)
    _assert_the_disc_is_recovered(scene, rendered)
    assert notes == []


def test_an_object_without_depth_readings_is_warned_about_not_taken_from_colour_alone():
    _, rendered, scene, notes = _object_only(post=_depth_hole(80.0))
    assert not scene.has_object
    assert len(notes) == 1 and "object-coloured region" in notes[0] and "no depth readings" in notes[0], notes


def test_a_hole_fill_as_large_as_the_depth_hole_recovers_the_object():
    # The documented remedy for the xfailed case above: hole_fill_px spanning the hole.
    settings = dataclasses.replace(PROFILE.segmentation_settings(), hole_fill_px=31)
    _, rendered, scene, notes = _object_only(post=_depth_hole(15.0, (14.0, 12.0)), settings=settings)
    _assert_the_disc_is_recovered(scene, rendered)
    assert notes == []


GRIPPER_IN_VIEW = {
    "fingertips from the top edge": dict(fingers=gripper_centrelines((0.0, -110.0), 64.0, 52.0)),
    "fingers and palm, dimmed": dict(fingers=gripper_centrelines((0.0, -75.0), 64.0, 52.0), palm=True,
                                     light_gain=0.6),
    "a finger from the left edge": dict(fingers=[np.array([[-120.0, 30.0], [-40.0, 30.0]])], half_thickness=5.0),
}


@pytest.mark.parametrize("margin_mm", [0.0, 60.0])
@pytest.mark.parametrize("gripper", GRIPPER_IN_VIEW.values(), ids=GRIPPER_IN_VIEW.keys())
def test_a_gripper_partly_in_view_is_not_taken_for_the_object(gripper, margin_mm):
    frame, rendered, scene, notes = _object_only(margin_mm=margin_mm, **gripper)
    _assert_the_disc_is_recovered(scene, rendered)
    _assert_segment_object_finds_the_disc(frame, rendered)
    assert notes == []
    assert not scene.segmentation.fingers.any()  # the object-only path never looks for fingers


def test_a_gripper_in_view_that_hides_part_of_the_object_is_warned_about():
    finger = np.array([[-60.0, -80.0], [-5.0, 15.0]])  # ends over the disc's left half, in front of it
    _, rendered, scene, notes = _object_only(fingers=[finger], half_thickness=4.0)
    assert any("may hide some of it" in note for note in notes), notes
    labels = render_labels(rendered, INTRINSICS)
    on_finger = labels >= LABEL_FIRST_FINGER
    assert on_finger.any() and not (scene.segmentation.object & on_finger).any()
    # Where the finger covers the disc, the visible outline follows the finger's edge: some points
    # 7 mm inside the true disc read outside the object (what the warning is about).
    hidden = np.asarray(scene.sdf.distance(_disc_ring(7.0)))
    assert hidden.max() > 0.0
