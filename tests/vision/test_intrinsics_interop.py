"""Intrinsics from other tools (a 3x3 K, Open3D, ROS CameraInfo) and lens distortion honoured
with OpenCV."""

from __future__ import annotations

import json
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from softgrip_vision.frames import Frame, FrameError, Intrinsics, load_frame, save_frame, undistort_frame

K = np.array([[612.5, 0.0, 321.25], [0.0, 611.0, 242.75], [0.0, 0.0, 1.0]])
DIST = np.array([0.11, -0.23, 0.0012, -0.0007, 0.05])


def _project(points_3d: np.ndarray, dist) -> np.ndarray:
    out, _ = cv2.projectPoints(points_3d, np.zeros(3), np.zeros(3), K, dist)
    return out.reshape(-1, 2)


def _rays(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-0.4, 0.4, (n, 2))
    return np.concatenate([xy, np.ones((n, 1))], axis=1) * rng.uniform(0.2, 0.6, (n, 1))


def test_from_matrix_round_trip_against_opencv_projection_with_distortion() -> None:
    intr = Intrinsics.from_matrix(K, 640, 480, 0.0001, dist=DIST)
    assert (intr.fx, intr.fy, intr.ppx, intr.ppy) == (612.5, 611.0, 321.25, 242.75)
    assert intr.model == "brown_conrady" and intr.coeffs == tuple(DIST)
    np.testing.assert_array_equal(intr.matrix, K)
    points = _rays(200)
    distorted = _project(points, DIST)  # where the real lens images them
    ideal = _project(points, None)  # where a pinhole camera with the same K would
    np.testing.assert_allclose(intr.undistort_points(distorted), ideal, atol=1e-3)
    assert np.abs(distorted - ideal).max() > 2.0  # the test has distortion to undo
    # Without coefficients: the pinhole, points unchanged.
    plain = Intrinsics.from_matrix(K, 640, 480)
    assert plain.model == "none" and not plain.distorted
    np.testing.assert_array_equal(plain.undistort_points(distorted), distorted)


def test_rational_and_fisheye_models_are_undone() -> None:
    points = _rays(100, seed=1)
    rational = np.array([0.1, -0.05, 0.001, 0.0005, 0.01, 0.02, -0.01, 0.005])
    intr = Intrinsics.from_matrix(K, 640, 480, dist=rational)
    assert intr.model == "rational_polynomial"
    np.testing.assert_allclose(intr.undistort_points(_project(points, rational)), _project(points, None), atol=1e-3)
    fish = np.array([0.05, -0.01, 0.002, -0.0005])
    fisheye = Intrinsics.from_matrix(K, 640, 480, dist=fish, model="kannala_brandt4")
    rays = (points[:, :2] / points[:, 2:]).reshape(-1, 1, 2)
    seen = cv2.fisheye.distortPoints(rays, K, fish).reshape(-1, 2)
    np.testing.assert_allclose(fisheye.undistort_points(seen), _project(points, None), atol=1e-3)


def test_inverse_brown_conrady_maps_distorted_to_undistorted() -> None:
    """RealSense's inverse model: the polynomial applied to the distorted ray gives the ideal one."""
    intr = Intrinsics.from_matrix(K, 640, 480, dist=DIST, model="inverse_brown_conrady")
    observed = _project(_rays(50, seed=2), None)  # any pixels
    rays = cv2.undistortPoints(observed.reshape(-1, 1, 2), K, None).reshape(-1, 2)
    expected = _project(np.concatenate([rays, np.ones((len(rays), 1))], axis=1), DIST)
    np.testing.assert_allclose(intr.undistort_points(observed), expected, atol=1e-9)


def test_from_open3d_object_or_fields_and_its_inverted_depth_scale() -> None:
    o3d_like = SimpleNamespace(width=640, height=480, intrinsic_matrix=K)
    a = Intrinsics.from_open3d(o3d_like, depth_scale=0.001)
    b = Intrinsics.from_open3d(width=640, height=480, intrinsic_matrix=K.tolist())
    assert a == b == Intrinsics.from_matrix(K, 640, 480, 0.001)
    with pytest.raises(FrameError, match=r"Open3D's depth units per metre.*depth_scale=0.001"):
        Intrinsics.from_open3d(o3d_like, depth_scale=1000.0)
    with pytest.raises(FrameError, match="needs a PinholeCameraIntrinsic"):
        Intrinsics.from_open3d(width=640)


@pytest.mark.parametrize("spelling", ["ros1", "ros2"])
def test_from_camera_info(spelling: str) -> None:
    k, d = ("K", "D") if spelling == "ros1" else ("k", "d")
    info = {"width": 640, "height": 480, "distortion_model": "plumb_bob", d: DIST.tolist(), k: K.ravel().tolist()}
    intr = Intrinsics.from_camera_info(info, depth_scale=0.0001)
    assert intr == Intrinsics.from_matrix(K, 640, 480, 0.0001, dist=DIST)
    zero = Intrinsics.from_camera_info({**info, d: [0.0] * 5})
    assert zero.model == "none"
    with pytest.raises(FrameError, match="distortion_model 'fancy' is not supported"):
        Intrinsics.from_camera_info({**info, "distortion_model": "fancy"})
    with pytest.raises(FrameError, match="9 numbers"):
        Intrinsics.from_camera_info({**info, k: [1, 2, 3]})


def test_bad_matrices_and_coefficients_are_refused() -> None:
    with pytest.raises(FrameError, match="no skew"):
        Intrinsics.from_matrix([[600, 1, 320], [0, 600, 240], [0, 0, 1]], 640, 480)
    with pytest.raises(FrameError, match="3x3"):
        Intrinsics.from_matrix(np.eye(2), 640, 480)
    with pytest.raises(FrameError, match="takes 4 or 5 coefficients, got 3"):
        Intrinsics.from_matrix(K, 640, 480, dist=[0.1, 0.2, 0.3])
    with pytest.raises(FrameError, match="model 'none'"):
        Intrinsics(640, 480, 600.0, 600.0, 320.0, 240.0, 0.001, "none", (0.1, 0, 0, 0, 0))


def test_distortion_is_stored_with_the_frame_and_undone_on_the_image(tmp_path) -> None:
    w, h = 160, 120
    k = np.array([[150.0, 0.0, 80.0], [0.0, 150.0, 60.0], [0.0, 0.0, 1.0]])
    dist = np.array([-0.6, 0.2, 0.0, 0.0, 0.0])
    intr = Intrinsics.from_matrix(k, w, h, 0.001, dist=dist)
    # A white dot at an ideal pixel, drawn where the lens images it.
    ideal = np.array([[130.0, 100.0]])
    ray = cv2.undistortPoints(ideal.reshape(1, 1, 2), k, None).reshape(1, 2)
    seen, _ = cv2.projectPoints(np.array([[*ray[0], 1.0]]), np.zeros(3), np.zeros(3), k, dist)
    color = np.zeros((h, w, 3), np.uint8)
    cv2.circle(color, tuple(int(round(c)) for c in seen.ravel()), 2, (255, 255, 255), -1)
    frame = Frame(color=color, depth=np.full((h, w), 500, np.uint16), intrinsics=intr)
    folder = save_frame(frame, tmp_path / "f")
    assert json.loads((folder / "intrinsics.json").read_text())["coeffs"] == dist.tolist()
    loaded = load_frame(folder)
    assert loaded.intrinsics == intr
    plain = undistort_frame(loaded)
    assert plain.intrinsics.model == "none" and plain.intrinsics.fx == 150.0
    ys, xs = np.nonzero(plain.color[..., 0] > 128)
    assert abs(xs.mean() - ideal[0, 0]) < 1.0 and abs(ys.mean() - ideal[0, 1]) < 1.0
    assert np.abs(seen.ravel() - ideal.ravel()).max() > 3.0  # the dot moved
    assert undistort_frame(plain) is plain


# --- issue 33: RealSense intrinsics, CameraInfo message objects, Open3D's wrong object -------------

RS_FIELDS = dict(width=640, height=480, fx=612.5, fy=611.0, ppx=321.25, ppy=242.75)


def test_from_realsense_stand_in_maps_distortion_names() -> None:
    class Distortion:  # pybind11 enums: .name, and str() is "distortion.<name>"
        name = "inverse_brown_conrady"

    for model in (Distortion(), "distortion.inverse_brown_conrady"):
        intr = Intrinsics.from_realsense(SimpleNamespace(**RS_FIELDS, model=model, coeffs=list(DIST)), 0.0001)
        assert intr.model == "inverse_brown_conrady" and intr.coeffs == tuple(DIST)
        assert (intr.fx, intr.ppy, intr.width, intr.depth_scale) == (612.5, 242.75, 640, 0.0001)
    plain = Intrinsics.from_realsense(SimpleNamespace(**RS_FIELDS, model="distortion.brown_conrady", coeffs=[0.0] * 5))
    assert plain.model == "none" and plain.coeffs == ()
    fisheye = Intrinsics.from_realsense(SimpleNamespace(**RS_FIELDS, model="distortion.kannala_brandt4",
                                                        coeffs=[0.1, 0.01, 0.0, 0.001, 0.0]))
    assert fisheye.model == "kannala_brandt4" and len(fisheye.coeffs) == 4
    # float32 values at their shortest decimals, as librealsense reports them
    assert Intrinsics.from_realsense(SimpleNamespace(**{**RS_FIELDS, "fx": float(np.float32(612.3))},
                                                     model="distortion.none", coeffs=[0.0] * 5)).fx == 612.3


def test_from_realsense_refuses_ftheta_and_wrong_objects() -> None:
    with pytest.raises(FrameError, match="distortion model 'ftheta'"):
        Intrinsics.from_realsense(SimpleNamespace(**RS_FIELDS, model="distortion.ftheta", coeffs=[0.5, 0, 0, 0, 0]))
    with pytest.raises(FrameError, match="from_realsense: got a dict without .*rs.intrinsics"):
        Intrinsics.from_realsense({"fx": 600.0})


def test_from_realsense_with_real_rs_intrinsics() -> None:
    from softgrip_vision.realsense import CameraError, import_realsense

    try:
        rs = import_realsense()
    except CameraError:
        pytest.skip("pyrealsense2 does not import here")
    rs_intr = rs.intrinsics()
    rs_intr.width, rs_intr.height = 640, 480
    rs_intr.fx, rs_intr.fy, rs_intr.ppx, rs_intr.ppy = 612.5, 611.0, 321.25, 242.75
    rs_intr.model = rs.distortion.brown_conrady
    rs_intr.coeffs = [0.125, -0.25, 0.001, -0.0005, 0.0625]
    intr = Intrinsics.from_realsense(rs_intr)
    assert intr.model == "brown_conrady"
    assert intr.coeffs == (0.125, -0.25, 0.001, -0.0005, 0.0625)
    assert (intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy) == (640, 480, 612.5, 611.0, 321.25, 242.75)


def test_camera_info_message_objects_ros1_and_ros2() -> None:
    k = [612.5, 0.0, 321.25, 0.0, 611.0, 242.75, 0.0, 0.0, 1.0]
    ros1 = SimpleNamespace(width=640, height=480, distortion_model="plumb_bob", D=list(DIST), K=tuple(k),
                           R=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], P=[0.0] * 12)
    ros2 = SimpleNamespace(width=640, height=480, distortion_model="plumb_bob", d=np.array(DIST), k=np.array(k))
    for message in (ros1, ros2):
        intr = Intrinsics.from_camera_info(message)
        assert intr.model == "brown_conrady" and intr.coeffs == tuple(DIST)
        np.testing.assert_array_equal(intr.matrix, K)
    with pytest.raises(FrameError, match="CameraInfo: got a str; pass a sensor_msgs/CameraInfo message"):
        Intrinsics.from_camera_info("camera_info.yaml")


def test_from_open3d_wrong_object_names_the_expected_type() -> None:
    with pytest.raises(FrameError, match="from_open3d: intrinsic is a ndarray without width, height, "
                                         "intrinsic_matrix; pass an open3d.camera.PinholeCameraIntrinsic"):
        Intrinsics.from_open3d(K)
