"""softgrip_vision.object_scene: a scene from a frame of the object alone and the arm's pose of the gripper.

The pose is checked against hand-derived geometry (a plane's depth on the optical axis, the
gripper origin and its right base back in camera coordinates) and against the other way to the same
scene: a frame of the same set-up with the gripper in view, measured by frame_scene.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from softgrip_calib.profile import load_profile
from softgrip_vision.object_scene import gripper_plane, object_scene
from softgrip_vision.scene import FrameSceneError, frame_scene
from synthetic.render import Scene, d405_intrinsics, plane_points_3d, plane_rotation, render
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
