"""Frame folders: round trip, never overwriting, atomic writes, and one test per bad input."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import softgrip_vision.frames as frames_module
from softgrip_base.errors import SoftgripError
from softgrip_vision.frames import (
    COLOR_FILE,
    DEPTH_FILE,
    INTRINSICS_FILE,
    Frame,
    FrameError,
    Intrinsics,
    load_frame,
    next_frame_dir,
    save_frame,
)

W, H = 40, 30


def make_frame(seed: int = 0, width: int = W, height: int = H) -> Frame:
    rng = np.random.default_rng(seed)
    intrinsics = Intrinsics(width=width, height=height, fx=385.25, fy=384.5, ppx=19.75,
                            ppy=14.5, depth_scale=0.001)
    color = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    depth = rng.integers(0, 65536, (height, width), dtype=np.uint16)
    depth[0, 0] = 0  # a pixel with no reading
    depth[0, 1] = 1
    return Frame(color=color, depth=depth, intrinsics=intrinsics)


@pytest.fixture
def saved(tmp_path: Path) -> Path:
    return save_frame(make_frame(), tmp_path / "frame_0000")


def assert_frame_error(path: Path, *names: str) -> None:
    with pytest.raises(FrameError) as info:
        load_frame(path)
    for name in names:
        assert name in str(info.value)


# --- round trip -------------------------------------------------------------------------------


def test_round_trip_is_bit_exact(saved: Path) -> None:
    frame = make_frame()
    loaded = load_frame(saved)
    assert loaded.color.dtype == np.uint8 and loaded.depth.dtype == np.uint16
    np.testing.assert_array_equal(loaded.color, frame.color)
    np.testing.assert_array_equal(loaded.depth, frame.depth)
    assert loaded.intrinsics == frame.intrinsics


def test_color_is_stored_as_a_normal_png(tmp_path: Path) -> None:
    """A red frame must look red to any PNG reader (OpenCV reads BGR)."""
    frame = make_frame()
    red = np.zeros_like(frame.color)
    red[..., 0] = 255
    path = save_frame(Frame(red, frame.depth, frame.intrinsics), tmp_path / "red")
    bgr = cv2.imread(str(path / COLOR_FILE), cv2.IMREAD_UNCHANGED)
    assert (bgr[..., 2] == 255).all() and (bgr[..., :2] == 0).all()
    assert load_frame(path).color[0, 0].tolist() == [255, 0, 0]


def test_intrinsics_json_uses_pyrealsense2_names(saved: Path) -> None:
    data = json.loads((saved / INTRINSICS_FILE).read_text())
    assert data == {"width": W, "height": H, "fx": 385.25, "fy": 384.5, "ppx": 19.75,
                    "ppy": 14.5, "depth_scale": 0.001}


def test_depth_mm_is_millimetres_with_nan_for_no_reading() -> None:
    frame = make_frame()
    depth_mm = frame.depth_mm
    assert depth_mm.dtype == np.float32 and depth_mm.shape == (H, W)
    assert math.isnan(depth_mm[0, 0])
    assert depth_mm[0, 1] == pytest.approx(1.0)
    valid = frame.depth > 0
    np.testing.assert_allclose(depth_mm[valid], frame.depth[valid] * 1.0, rtol=1e-6)


@settings(max_examples=25, deadline=None)
@given(
    width=st.integers(1, 5000), height=st.integers(1, 5000),
    fx=st.floats(1e-3, 1e5), fy=st.floats(1e-3, 1e5),
    ppx=st.floats(-1e4, 1e4), ppy=st.floats(-1e4, 1e4), depth_scale=st.floats(1e-6, 1.0),
)
def test_intrinsics_dict_round_trip(width: int, height: int, fx: float, fy: float, ppx: float,
                                    ppy: float, depth_scale: float) -> None:
    intrinsics = Intrinsics(width, height, fx, fy, ppx, ppy, depth_scale)
    text = json.dumps(intrinsics.to_dict())
    assert Intrinsics.from_dict(json.loads(text)) == intrinsics


# --- never overwrite, atomic ------------------------------------------------------------------


def test_save_refuses_an_existing_folder_and_leaves_it_alone(saved: Path) -> None:
    before = {p.name: p.read_bytes() for p in saved.iterdir()}
    with pytest.raises(FrameError, match="already exists") as info:
        save_frame(make_frame(seed=1), saved)
    assert str(saved) in str(info.value)
    assert {p.name: p.read_bytes() for p in saved.iterdir()} == before


def test_save_refuses_an_existing_file(tmp_path: Path) -> None:
    target = tmp_path / "taken"
    target.write_text("mine")
    with pytest.raises(FrameError, match="already exists"):
        save_frame(make_frame(), target)
    assert target.read_text() == "mine"


def test_save_refuses_an_empty_existing_folder(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(FrameError, match="already exists"):
        save_frame(make_frame(), tmp_path / "empty")
    assert list((tmp_path / "empty").iterdir()) == []


def test_failed_write_leaves_no_partial_folder(tmp_path: Path,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    real_write = frames_module._write_file

    def failing_write(path: Path, data: bytes) -> None:
        if path.name == DEPTH_FILE:
            raise OSError(28, "No space left on device")
        real_write(path, data)

    monkeypatch.setattr(frames_module, "_write_file", failing_write)
    target = tmp_path / "frame_0000"
    with pytest.raises(FrameError, match="No space left") as info:
        save_frame(make_frame(), target)
    assert str(target) in str(info.value)
    assert list(tmp_path.iterdir()) == []  # neither the frame nor its temporary sibling


def test_save_creates_missing_parents(tmp_path: Path) -> None:
    path = save_frame(make_frame(), tmp_path / "a" / "b" / "frame_0000")
    assert sorted(p.name for p in path.iterdir()) == sorted([COLOR_FILE, DEPTH_FILE,
                                                             INTRINSICS_FILE])


def test_next_frame_dir_gives_the_first_free_name(tmp_path: Path) -> None:
    assert next_frame_dir(tmp_path) == tmp_path / "frame_0000"
    assert next_frame_dir(tmp_path / "missing") == tmp_path / "missing" / "frame_0000"
    (tmp_path / "frame_0000").mkdir()
    (tmp_path / "frame_0001").mkdir()
    (tmp_path / "frame_0003").mkdir()
    assert next_frame_dir(tmp_path) == tmp_path / "frame_0002"
    assert next_frame_dir(tmp_path, prefix="closed") == tmp_path / "closed_0000"


# --- bad input: folder and files ---------------------------------------------------------------


def test_frame_error_is_a_softgrip_error() -> None:
    assert issubclass(FrameError, SoftgripError) and issubclass(FrameError, ValueError)


def test_missing_folder(tmp_path: Path) -> None:
    assert_frame_error(tmp_path / "nope", str(tmp_path / "nope"), "does not exist")


def test_folder_is_a_file(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("x")
    assert_frame_error(tmp_path / "file", str(tmp_path / "file"), "not a folder")


@pytest.mark.parametrize("name", [COLOR_FILE, DEPTH_FILE, INTRINSICS_FILE])
def test_missing_file(saved: Path, name: str) -> None:
    (saved / name).unlink()
    assert_frame_error(saved, str(saved / name), "missing")


@pytest.mark.parametrize("name", [COLOR_FILE, DEPTH_FILE])
def test_corrupt_png(saved: Path, name: str) -> None:
    (saved / name).write_bytes((saved / name).read_bytes()[:60])  # truncated
    assert_frame_error(saved, str(saved / name), "not a readable PNG")


@pytest.mark.parametrize("name", [COLOR_FILE, DEPTH_FILE])
def test_png_that_is_not_an_image(saved: Path, name: str) -> None:
    (saved / name).write_text("hello")
    assert_frame_error(saved, str(saved / name), "not a readable PNG")


def test_corrupt_json(saved: Path) -> None:
    (saved / INTRINSICS_FILE).write_text('{"width": 40,')
    assert_frame_error(saved, str(saved / INTRINSICS_FILE), "not valid JSON")


def test_binary_json(saved: Path) -> None:
    (saved / INTRINSICS_FILE).write_bytes(b"\xff\xfe\x00garbage")
    assert_frame_error(saved, str(saved / INTRINSICS_FILE), "not valid JSON")


@pytest.mark.parametrize(
    "image, described",
    [
        (np.zeros((H, W), np.uint8), "1 channel"),
        (np.zeros((H, W, 4), np.uint8), "4 channel"),
        (np.zeros((H, W, 3), np.uint16), "16-bit"),
    ],
    ids=["gray", "bgra", "16-bit"],
)
def test_color_not_8bit_3channel(saved: Path, image: np.ndarray, described: str) -> None:
    cv2.imwrite(str(saved / COLOR_FILE), image)
    assert_frame_error(saved, str(saved / COLOR_FILE), "8-bit", "3 channels", described)


def test_depth_8bit(saved: Path) -> None:
    cv2.imwrite(str(saved / DEPTH_FILE), np.full((H, W), 7, np.uint8))
    assert_frame_error(saved, str(saved / DEPTH_FILE), "must be 16-bit", "depth_scale")


def test_depth_8bit_colour_visualisation(saved: Path) -> None:
    cv2.imwrite(str(saved / DEPTH_FILE), np.full((H, W, 3), 7, np.uint8))
    assert_frame_error(saved, str(saved / DEPTH_FILE), "must be 16-bit")


def test_depth_with_channels(saved: Path) -> None:
    cv2.imwrite(str(saved / DEPTH_FILE), np.full((H, W, 3), 7, np.uint16))
    assert_frame_error(saved, str(saved / DEPTH_FILE), "single-channel")


def test_color_and_depth_sizes_differ(saved: Path) -> None:
    cv2.imwrite(str(saved / DEPTH_FILE), np.full((H, W + 2), 500, np.uint16))
    assert_frame_error(saved, str(saved / COLOR_FILE), str(saved / DEPTH_FILE),
                       f"{W}x{H}", f"{W + 2}x{H}")


def test_intrinsics_size_mismatch(saved: Path) -> None:
    data = json.loads((saved / INTRINSICS_FILE).read_text())
    data["width"] = 640
    (saved / INTRINSICS_FILE).write_text(json.dumps(data))
    assert_frame_error(saved, str(saved / INTRINSICS_FILE), f"640x{H}", f"{W}x{H}")


def test_all_zero_depth(saved: Path) -> None:
    cv2.imwrite(str(saved / DEPTH_FILE), np.zeros((H, W), np.uint16))
    assert_frame_error(saved, str(saved / DEPTH_FILE), "no depth readings")


# --- bad input: intrinsics ---------------------------------------------------------------------


@pytest.mark.parametrize(
    "key, value, says",
    [
        ("fx", float("nan"), "fx must be a finite number"),
        ("fy", float("inf"), "fy must be a finite number"),
        ("ppx", float("-inf"), "ppx must be a finite number"),
        ("fx", -385.0, "fx must be positive"),
        ("depth_scale", 0, "depth_scale must be positive"),
        ("width", 0, "width must be a positive integer"),
        ("height", 30.5, "height must be an integer"),
        ("fy", "385", "fy must be a number"),
        ("ppy", True, "ppy must be a number"),
        ("depth_scale", None, "depth_scale must be a number"),
    ],
)
def test_invalid_intrinsics(saved: Path, key: str, value: object, says: str) -> None:
    data = json.loads((saved / INTRINSICS_FILE).read_text())
    data[key] = value
    (saved / INTRINSICS_FILE).write_text(json.dumps(data))  # writes NaN / Infinity for floats
    assert_frame_error(saved, str(saved / INTRINSICS_FILE), says)


def test_intrinsics_missing_key(saved: Path) -> None:
    data = json.loads((saved / INTRINSICS_FILE).read_text())
    del data["ppy"], data["depth_scale"]
    (saved / INTRINSICS_FILE).write_text(json.dumps(data))
    assert_frame_error(saved, str(saved / INTRINSICS_FILE), "missing key(s) ppy, depth_scale")


def test_intrinsics_not_an_object(saved: Path) -> None:
    (saved / INTRINSICS_FILE).write_text("[1, 2, 3]")
    assert_frame_error(saved, str(saved / INTRINSICS_FILE), "JSON object")


def test_intrinsics_constructor_validates() -> None:
    with pytest.raises(FrameError, match="fx must be positive"):
        Intrinsics(W, H, 0.0, 1.0, 0.0, 0.0, 0.001)
    with pytest.raises(FrameError, match="width must be a positive integer"):
        Intrinsics(True, H, 1.0, 1.0, 0.0, 0.0, 0.001)


# --- bad input: arrays -------------------------------------------------------------------------


def test_frame_validates_arrays() -> None:
    frame = make_frame()
    with pytest.raises(FrameError, match="color must be an 8-bit colour image"):
        Frame(frame.color.astype(np.float32), frame.depth, frame.intrinsics)
    with pytest.raises(FrameError, match="depth is 8-bit"):
        Frame(frame.color, frame.depth.astype(np.uint8), frame.intrinsics)
    with pytest.raises(FrameError, match="depth must be a 16-bit single-channel"):
        Frame(frame.color, frame.depth.astype(np.int32), frame.intrinsics)
    with pytest.raises(FrameError, match="intrinsics says"):
        Frame(frame.color[:-1], frame.depth[:-1], frame.intrinsics)
    with pytest.raises(FrameError, match="no depth readings"):
        Frame(frame.color, np.zeros_like(frame.depth), frame.intrinsics)
    with pytest.raises(FrameError, match="must be an Intrinsics"):
        Frame(frame.color, frame.depth, frame.intrinsics.to_dict())
