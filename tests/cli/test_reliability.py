"""Bad input at the command line: each kind is a one-line error (exit 2) naming the field or file,
nothing an input or a device is overwritten, nothing is lost silently. Only cheap refusals here (no
compilation): the estimates behind them are tested in test_commands."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.cli.test_commands import DATA, PROFILE, run_cli

ROOT = Path(__file__).resolve().parents[2]


def frame_copy(tmp_path: Path, name: str = "circle_open", **intrinsics) -> Path:
    folder = tmp_path / name
    shutil.copytree(DATA / name, folder)
    data = json.loads((folder / "intrinsics.json").read_text())
    data.update(intrinsics)
    (folder / "intrinsics.json").write_text(json.dumps(data))
    return folder


def one_line_error(code: int, err: str, *needles: str) -> None:
    assert code == 2 and "Traceback" not in err, err
    assert all(n in err for n in needles), err


def test_calibrate_never_writes_onto_its_own_frame(tmp_path: Path) -> None:
    opened = frame_copy(tmp_path)
    before = (opened / "intrinsics.json").read_bytes()
    code, _, err = run_cli(["calibrate", str(DATA / "calib_closed"), "--open", str(opened),
                            "-o", str(opened / "intrinsics.json"), "--force"])
    one_line_error(code, err, "inputs")
    assert (opened / "intrinsics.json").read_bytes() == before


def test_score_never_writes_its_heatmap_onto_a_fifo_or_its_image(tmp_path: Path) -> None:
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    code, _, err = run_cli(["score", str(DATA / "circle_open"), "--profile", str(PROFILE), "--heatmap", str(fifo)])
    one_line_error(code, err, "FIFO")
    frame = frame_copy(tmp_path)
    before = (frame / "color.png").read_bytes()
    code, _, err = run_cli(["score", str(frame), "--profile", str(PROFILE), "-o", str(frame / "color.png")])
    one_line_error(code, err, "inputs")
    assert (frame / "color.png").read_bytes() == before


@pytest.mark.parametrize(("field", "value", "named"), [
    ("depth_scale", 1000, "try depth_scale = 0.001"),  # Open3D's convention inverted
    ("depth_scale", 1e-9, "depth_scale"),
    ("fx", 1e300, "fx = 1e+300"),
    ("fx", 1e-300, "fx = 1e-300"),
    ("fy", 2000.0, "differ"),
    ("ppx", 1e9, "ppx"),
])
def test_implausible_intrinsics_name_the_field_and_the_fix(tmp_path: Path, field: str, value, named: str) -> None:
    frame = frame_copy(tmp_path, **{field: value})
    code, _, err = run_cli(["estimate", str(frame), "--profile", str(PROFILE)])
    one_line_error(code, err, str(frame), named)


def test_a_depth_image_out_of_range_is_refused(tmp_path: Path) -> None:
    import cv2

    frame = frame_copy(tmp_path)
    depth = cv2.imread(str(frame / "depth.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(frame / "depth.png"), np.full_like(depth, 65535))  # 6.5 m at the sample's 0.0001
    code, _, err = run_cli(["estimate", str(frame), "--profile", str(PROFILE)])
    one_line_error(code, err, "gripper lies", "depth_scale")


def test_a_png_header_claiming_a_huge_image_is_refused_before_decoding(tmp_path: Path) -> None:
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    frame = frame_copy(tmp_path)
    (frame / "color.png").write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 60000, 60000, 8, 2,
                                                                                         0, 0, 0))
                                      + chunk(b"IDAT", zlib.compress(b"\0" * 100)) + chunk(b"IEND", b""))
    code, _, err = run_cli(["estimate", str(frame), "--profile", str(PROFILE)])
    one_line_error(code, err, "60000x60000", "color.png")


def test_a_fit_pair_given_closed_open_is_refused(tmp_path: Path) -> None:
    code, _, err = run_cli(["calibrate", "--fit", str(DATA / "circle_closed"), str(DATA / "circle_open"),
                            "-o", str(tmp_path / "p.json"), "--method", "geometric"])
    one_line_error(code, err, "swapped", "OPEN CLOSED")
    assert not (tmp_path / "p.json").exists()


def test_a_large_json_pose_file_parses_at_csv_speed_and_a_bad_entry_is_named_by_line(tmp_path: Path) -> None:
    from softgrip_cli.cmd_score import PoseInputError, read_poses

    poses = np.random.default_rng(0).uniform(-50, 50, (100_000, 3)).round(3)
    path = tmp_path / "poses.json"
    path.write_text(json.dumps(poses.tolist()))
    start = time.perf_counter()
    np.testing.assert_allclose(read_poses(str(path)), poses)
    assert time.perf_counter() - start < 5.0  # item by item with line numbers it took tens of seconds
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps([[1, 2, 3], [4, True, 6]], indent=1))
    with pytest.raises(PoseInputError, match=r"bad.json, line 7: pose values must be finite numbers"):
        read_poses(str(bad))


def _mapped(pid: int, name: str) -> bool:
    try:
        return name in Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return False


@pytest.mark.parametrize("when", ["numpy loaded", "0.3 s"])
def test_ctrl_c_while_starting_exits_130_without_a_traceback(when: str, sigint_delivered) -> None:
    """Ctrl-C inside the command's imports of numpy, JAX and OpenCV. Not earlier: a SIGINT while
    the interpreter itself starts (before any of the command's code, ``init_import_site``) is
    Python's own fatal error, whatever the command does."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    process = subprocess.Popen([sys.executable, "-m", "softgrip_cli", "estimate", str(DATA / "circle_open"),
                                "--profile", str(PROFILE)], stderr=subprocess.PIPE, stdout=subprocess.PIPE, env=env,
                               cwd=ROOT)
    if when == "numpy loaded":
        deadline = time.monotonic() + 60.0
        while not _mapped(process.pid, "numpy") and process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.002)
    else:
        time.sleep(0.3)
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 130 and b"Traceback" not in err, err


def test_a_damaged_recording_names_the_lost_frames_and_fails_unless_allowed(tmp_path: Path) -> None:
    realsense = pytest.importorskip("softgrip_vision.realsense")
    try:
        realsense.import_realsense()
    except Exception as err:  # pragma: no cover - no pyrealsense2 here
        pytest.skip(f"pyrealsense2 unavailable: {err}")
    from softgrip_vision.frames import load_frame

    frames = [load_frame(DATA / name) for name in ("circle_open", "square_open", "star_a_open")]
    recording = realsense.write_recording(tmp_path / "scene.db3", frames)
    data = bytearray(recording.read_bytes())
    data[len(data) // 2:len(data) // 2 + 16] = np.random.default_rng(1).integers(0, 256, 16, np.uint8).tobytes()
    recording.write_bytes(bytes(data))
    assert realsense.recording_depth_frames(recording) == [0, 1, 2]
    code, out, err = run_cli(["capture", "--bag", str(recording), "--out", str(tmp_path / "out"), "--json"])
    one_line_error(code, err, "lost", "--allow-partial")
    report = json.loads(out)
    assert report["complete"] is False and report["lost_frame_numbers"]
    assert len(report["frames"]) + len(report["lost_frame_numbers"]) == 3
    code, out, err = run_cli(["capture", "--bag", str(recording), "--out", str(tmp_path / "again"), "--allow-partial"])
    assert code == 0 and "warning" in err and "lost" in err
