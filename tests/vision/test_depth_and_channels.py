"""Float depth in metres, and colour images with swapped channels."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from softgrip_vision.frames import Frame, FrameError, load_frame
from softgrip_vision.plausibility import check_channel_order
from softgrip_vision.segmentation import segment

DATA = Path(__file__).resolve().parents[2] / "data"


@pytest.fixture(scope="module")
def circle():
    return load_frame(DATA / "circle_open")


def test_float_metres_give_the_same_frame_as_depth_units(circle):
    scale = circle.intrinsics.depth_scale
    metres = circle.depth.astype(np.float32) * np.float32(scale)
    metres[circle.depth == 0] = np.nan  # no reading, as Open3D and ROS 32FC1 write it
    frame = Frame(circle.color, metres, circle.intrinsics)
    assert frame.depth.dtype == np.uint16
    np.testing.assert_array_equal(frame.depth, circle.depth)
    np.testing.assert_array_equal(np.isnan(frame.depth_mm), np.isnan(circle.depth_mm))


def test_float_depth_without_readings_and_below_zero_is_no_reading(circle):
    metres = np.full(circle.depth.shape, 0.12, np.float64)
    metres[:2, :2] = [[np.inf, -0.5], [0.0, np.nan]]
    frame = Frame(circle.color, metres, circle.intrinsics)
    assert frame.depth[:2, :2].tolist() == [[0, 0], [0, 0]]
    assert int(frame.depth[5, 5]) == round(0.12 / circle.intrinsics.depth_scale)


def test_float_millimetres_are_refused_with_the_fix(circle):
    millimetres = circle.depth.astype(np.float32) * np.float32(circle.intrinsics.depth_scale * 1000)
    with pytest.raises(FrameError, match=r"millimetres\? Divide it by 1000"):
        Frame(circle.color, millimetres, circle.intrinsics)


def test_float_depth_beyond_the_scale_names_a_depth_scale_that_holds_it(circle):
    metres = np.full(circle.depth.shape, 7.5, np.float32)  # 7.5 m: more than 65535 units of 0.1 mm
    with pytest.raises(FrameError, match=r"depth_scale of at least 0.000114"):
        Frame(circle.color, metres, circle.intrinsics)


def test_swapped_channels_are_caught_where_a_region_s_colour_is_known(circle):
    obj = segment(circle).object
    assert obj.any()
    known = circle.color[obj].mean(axis=0)  # the object's colour as captured (RGB)
    assert abs(known[0] - known[2]) > 30  # a coloured object: the check can tell the orders apart
    check_channel_order(circle.color, obj, known)
    bgr = np.ascontiguousarray(circle.color[..., ::-1])
    with pytest.raises(FrameError, match=r"swapped \(BGR\).*COLOR_BGR2RGB"):
        check_channel_order(bgr, obj, known, source="camera")
    # Segmentation does not depend on the order (saturation and value only).
    np.testing.assert_array_equal(segment(Frame(bgr, circle.depth, circle.intrinsics)).object, obj)


def test_a_grey_region_says_nothing_about_the_order(circle):
    grey = np.full((4, 4, 3), 128, np.uint8)
    check_channel_order(grey, np.ones((4, 4), bool), (200, 20, 20))  # far from red, but not swapped
    check_channel_order(grey, np.zeros((4, 4), bool), (200, 20, 20))  # nothing to compare


def folder_with_float_depth(tmp_path, circle, name, metres):
    """A copy of the circle frame's colour and intrinsics with ``metres`` written as ``name``."""
    import shutil

    import cv2

    folder = tmp_path / "frame"
    folder.mkdir()
    for keep in ("color.png", "intrinsics.json"):
        shutil.copy(DATA / "circle_open" / keep, folder / keep)
    if name.endswith(".npy"):
        np.save(folder / name, metres)
    else:
        assert cv2.imwrite(str(folder / name), metres)
    return folder


@pytest.mark.parametrize("name, dtype", [("depth.npy", np.float64), ("depth.npy", np.float32),
                                         ("depth.tiff", np.float32)])
def test_a_folder_with_float_depth_in_metres_loads_as_the_same_frame(tmp_path, circle, name, dtype):
    metres = (circle.depth * circle.intrinsics.depth_scale).astype(dtype)
    metres[circle.depth == 0] = np.nan
    frame = load_frame(folder_with_float_depth(tmp_path, circle, name, metres))
    np.testing.assert_array_equal(frame.depth, circle.depth)
    np.testing.assert_array_equal(frame.color, circle.color)


def test_float_depth_files_are_checked_and_named(tmp_path, circle):
    metres = (circle.depth * circle.intrinsics.depth_scale).astype(np.float32)
    folder = folder_with_float_depth(tmp_path, circle, "depth.npy", metres * 1000.0)  # millimetres
    with pytest.raises(FrameError, match=r"depth\.npy.*millimetres"):
        load_frame(folder)
    np.save(folder / "depth.npy", circle.depth)  # integer units belong in depth.png
    with pytest.raises(FrameError, match=r"depth\.npy must hold floating-point depth in metres.*depth\.png"):
        load_frame(folder)
    np.save(folder / "depth.npy", metres[:, :-1])
    with pytest.raises(FrameError, match=r"depth\.npy is 639x480.*registered"):
        load_frame(folder)
    (folder / "depth.npy").write_bytes(b"not numpy")
    with pytest.raises(FrameError, match=r"depth\.npy is not a readable numpy array"):
        load_frame(folder)
    np.save(folder / "depth.npy", metres)
    (folder / "depth.png").write_bytes((DATA / "circle_open" / "depth.png").read_bytes())
    with pytest.raises(FrameError, match=r"depth\.png and depth\.npy.*keep one"):
        load_frame(folder)
