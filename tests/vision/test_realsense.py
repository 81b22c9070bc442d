"""RealSense recordings written with a software device and read back; the capture command."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pytest

import softgrip_vision.realsense as realsense
from softgrip_cli import cmd_capture
from softgrip_vision.frames import Frame, FrameError, Intrinsics, load_frame
from softgrip_vision.realsense import (
    CameraError,
    capture_from_camera,
    capture_from_recording,
    import_realsense,
    list_devices,
    write_recording,
)

W, H = 64, 48
# float32-exact except depth_scale, which must come back as the same shortest decimal
INTRINSICS = Intrinsics(width=W, height=H, fx=385.25, fy=384.5, ppx=31.75, ppy=23.5,
                        depth_scale=0.00025)


def random_frames(n: int, seed: int = 0) -> list[Frame]:
    rng = np.random.default_rng(seed)
    return [Frame(color=rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
                  depth=rng.integers(0, 65536, (H, W), dtype=np.uint16),
                  intrinsics=INTRINSICS) for _ in range(n)]


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Frame]]:
    frames = random_frames(3)
    path = write_recording(tmp_path_factory.mktemp("rec") / "scene.db3", frames)
    return path, frames


def assert_same(loaded: Frame, expected: Frame) -> None:
    np.testing.assert_array_equal(loaded.color, expected.color)
    np.testing.assert_array_equal(loaded.depth, expected.depth)
    assert loaded.intrinsics == expected.intrinsics


# --- recordings --------------------------------------------------------------------------------


def test_recording_plays_back_bit_exact(recording: tuple[Path, list[Frame]],
                                        tmp_path: Path) -> None:
    path, frames = recording
    paths = capture_from_recording(path, tmp_path / "out")
    assert paths == [tmp_path / "out" / f"frame_{i:04d}" for i in range(3)]
    for folder, frame in zip(paths, frames):
        assert_same(load_frame(folder), frame)


def test_recording_records_device_name_and_depth_scale(
        recording: tuple[Path, list[Frame]]) -> None:
    rs = import_realsense()
    device = rs.context().load_device(str(recording[0]))
    assert device.get_info(rs.camera_info.name) == "softgrip synthetic"
    assert device.first_depth_sensor().get_depth_scale() == pytest.approx(0.00025, rel=1e-6)


def test_count_takes_the_first_frames(recording: tuple[Path, list[Frame]],
                                      tmp_path: Path) -> None:
    path, frames = recording
    paths = capture_from_recording(path, tmp_path, count=2)
    assert len(paths) == 2
    for folder, frame in zip(paths, frames[:2]):
        assert_same(load_frame(folder), frame)


def test_capturing_twice_adds_frames_and_keeps_the_old_ones(
        recording: tuple[Path, list[Frame]], tmp_path: Path) -> None:
    path, frames = recording
    first = capture_from_recording(path, tmp_path, count=1)
    before = (first[0] / "depth.png").read_bytes()
    second = capture_from_recording(path, tmp_path, count=2)
    assert [p.name for p in first + second] == ["frame_0000", "frame_0001", "frame_0002"]
    assert (first[0] / "depth.png").read_bytes() == before
    assert_same(load_frame(second[1]), frames[1])


def test_single_frame_recording(tmp_path: Path) -> None:
    frames = random_frames(1, seed=5)
    path = write_recording(tmp_path / "one.db3", frames)
    [folder] = capture_from_recording(path, tmp_path / "out")
    assert_same(load_frame(folder), frames[0])


def test_frames_without_depth_readings_are_skipped_with_a_warning(tmp_path: Path) -> None:
    frames = random_frames(3, seed=7)
    blind = random_frames(1, seed=8)[0]
    object.__setattr__(blind, "depth", np.zeros((H, W), np.uint16))  # as a camera can send
    path = write_recording(tmp_path / "blind.db3", [frames[0], blind, frames[2]])
    with pytest.warns(UserWarning, match="skipped depth frame 1: it has no depth readings"):
        paths = capture_from_recording(path, tmp_path / "out")
    assert len(paths) == 2
    assert_same(load_frame(paths[0]), frames[0])
    assert_same(load_frame(paths[1]), frames[2])


def test_unregistered_depth_goes_through_rs_align(tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """Force the rs.align path: with identity geometry, flat depth stays flat where it lands."""
    frame = random_frames(1)[0]
    flat = Frame(frame.color, np.full((H, W), 1000, np.uint16), INTRINSICS)
    path = write_recording(tmp_path / "flat.db3", [flat])
    rs = import_realsense()
    monkeypatch.setattr(realsense, "_registration", lambda *_: rs.align(rs.stream.color))
    [folder] = capture_from_recording(path, tmp_path / "out")
    depth = load_frame(folder).depth
    assert set(np.unique(depth)) <= {0, 1000}
    assert (depth == 1000).mean() > 0.9


def test_write_recording_refuses_bad_targets_and_frames(
        recording: tuple[Path, list[Frame]], tmp_path: Path) -> None:
    path, frames = recording
    size = path.stat().st_size
    with pytest.raises(CameraError, match="already exists") as info:
        write_recording(path, frames)
    assert str(path) in str(info.value) and path.stat().st_size == size
    with pytest.raises(CameraError, match=r"\.db3") as info:
        write_recording(tmp_path / "scene.bag", frames)
    assert "scene.bag" in str(info.value)
    with pytest.raises(FrameError, match="at least one frame"):
        write_recording(tmp_path / "empty.db3", [])
    other = Frame(frames[0].color, frames[0].depth,
                  Intrinsics(W, H, 300.0, 300.0, 32.0, 24.0, 0.001))
    with pytest.raises(FrameError, match=r"frames\[1\] has intrinsics"):
        write_recording(tmp_path / "mixed.db3", [frames[0], other])
    assert list(tmp_path.iterdir()) == []  # nothing left behind


@pytest.mark.parametrize("name", ["missing.db3", "missing.bag"])
def test_missing_recording(tmp_path: Path, name: str) -> None:
    with pytest.raises(CameraError, match="does not exist") as info:
        capture_from_recording(tmp_path / name, tmp_path / "out")
    assert str(tmp_path / name) in str(info.value)


def test_wrong_extension(tmp_path: Path) -> None:
    video = tmp_path / "scene.mp4"
    video.write_bytes(b"\x00" * 100)
    with pytest.raises(CameraError, match=r"expected a \.db3") as info:
        capture_from_recording(video, tmp_path / "out")
    assert str(video) in str(info.value)


@pytest.mark.parametrize("name, content", [
    ("garbage.db3", b"not a database" * 100),
    ("garbage.bag", b"not a bag"),
    ("empty.db3", b""),
])
def test_unreadable_recording(tmp_path: Path, name: str, content: bytes) -> None:
    bad = tmp_path / name
    bad.write_bytes(content)
    with pytest.raises(CameraError, match="not a readable RealSense recording") as info:
        capture_from_recording(bad, tmp_path / "out")
    assert str(bad) in str(info.value)
    assert not (tmp_path / "out").exists()


def test_truncated_recording(recording: tuple[Path, list[Frame]], tmp_path: Path) -> None:
    truncated = tmp_path / "truncated.db3"
    truncated.write_bytes(recording[0].read_bytes()[:20000])
    with pytest.raises(CameraError) as info:
        capture_from_recording(truncated, tmp_path / "out")
    assert str(truncated) in str(info.value)


def test_bad_count(recording: tuple[Path, list[Frame]], tmp_path: Path) -> None:
    with pytest.raises(CameraError, match="count must be an integer >= 1"):
        capture_from_recording(recording[0], tmp_path, count=0)


# --- import and camera -------------------------------------------------------------------------


def test_missing_pyrealsense2_says_how_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)
    with pytest.raises(CameraError) as info:
        import_realsense()
    assert "pip install 'softgrip-jax[realsense]'" in str(info.value)
    assert "libusb-1.0-0" in str(info.value)


def test_camera_settings_are_checked_first(tmp_path: Path) -> None:
    with pytest.raises(CameraError, match="count must be an integer >= 1"):
        capture_from_camera(tmp_path, count=0)
    with pytest.raises(CameraError, match="width must be an integer >= 1"):
        capture_from_camera(tmp_path, width=-640)


@pytest.mark.skipif("list_devices()", reason="a RealSense camera is connected")
def test_no_camera(tmp_path: Path) -> None:
    with pytest.raises(CameraError, match="no RealSense camera found"):
        capture_from_camera(tmp_path / "out")
    assert not (tmp_path / "out").exists()


# --- softgrip capture --------------------------------------------------------------------------


def capture_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="softgrip")
    cmd_capture.add_parser(parser.add_subparsers(dest="command", required=True))
    return parser


def test_cli_capture_from_recording_json(recording: tuple[Path, list[Frame]], tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    path, frames = recording
    args = capture_parser().parse_args(
        ["capture", "--bag", str(path), "--out", str(tmp_path / "out"), "--json"])
    assert args.func(args) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == {"frames": [str(tmp_path / "out" / f"frame_{i:04d}") for i in range(3)]}
    for folder, frame in zip(printed["frames"], frames):
        assert_same(load_frame(folder), frame)


def test_cli_capture_prints_one_folder_per_line(recording: tuple[Path, list[Frame]],
                                                tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    args = capture_parser().parse_args(
        ["capture", "--bag", str(recording[0]), "--out", str(tmp_path), "--count", "2"])
    assert args.func(args) == 0
    assert capsys.readouterr().out.splitlines() == [str(tmp_path / "frame_0000"),
                                                    str(tmp_path / "frame_0001")]


def test_cli_refuses_camera_options_with_a_recording(recording: tuple[Path, list[Frame]],
                                                     tmp_path: Path) -> None:
    args = capture_parser().parse_args(
        ["capture", "--bag", str(recording[0]), "--out", str(tmp_path), "--width", "848"])
    with pytest.raises(CameraError, match="--width apply to a camera"):
        args.func(args)


def test_cli_missing_recording_is_a_user_error(tmp_path: Path) -> None:
    args = capture_parser().parse_args(
        ["capture", "--bag", str(tmp_path / "nope.db3"), "--out", str(tmp_path)])
    with pytest.raises(CameraError, match="nope.db3"):
        args.func(args)


@pytest.mark.parametrize("argv", [
    ["capture"],  # --out is required
    ["capture", "--out", "x", "--count", "0"],
    ["capture", "--out", "x", "--fps", "fast"],
])
def test_cli_rejects_bad_arguments(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        capture_parser().parse_args(argv)
    assert info.value.code == 2
    assert "softgrip capture" in capsys.readouterr().err


def test_cli_help_has_examples(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        capture_parser().parse_args(["capture", "--help"])
    text = capsys.readouterr().out
    assert "examples:" in text and "--bag scene.db3" in text and "frame_0000" in text


def test_capture_keeps_the_lens_distortion(tmp_path: Path) -> None:
    """The colour stream's distortion model and coefficients survive recording and capture."""
    distorted = Intrinsics(width=W, height=H, fx=385.25, fy=384.5, ppx=31.75, ppy=23.5, depth_scale=0.00025,
                           model="inverse_brown_conrady", coeffs=(0.125, -0.25, 0.0009765625, -0.001953125, 0.0625))
    rng = np.random.default_rng(7)
    frame = Frame(color=rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
                  depth=rng.integers(1, 65536, (H, W), dtype=np.uint16), intrinsics=distorted)
    path = write_recording(tmp_path / "lens.db3", [frame])
    [folder] = capture_from_recording(path, tmp_path / "out")
    loaded = load_frame(folder)
    assert loaded.intrinsics == distorted
    assert json.loads((folder / "intrinsics.json").read_text())["model"] == "inverse_brown_conrady"
