"""Every file a person names goes through one guard (softgrip_base.input_guard): regular files only,
a size limit per kind, no secret echoed, CSV as spreadsheets save it, every message escaped, no
traceback or crash for odd names. Each CLI run here fails (or reads) before any compilation."""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from softgrip_base import input_guard
from softgrip_cli.cmd_score import PoseInputError, read_poses
from tests.cli.test_commands import DATA, PROFILE, run_cli

ROOT = Path(__file__).resolve().parents[2]
FRAME = DATA / "circle_open"
SECRET = "s3cr3t-Pa55word-4242"
POSES = np.array([[0.0, -40.0, 0.1], [1.5, -41.0, 0.0], [-2.0, -39.5, -0.2]])


@contextlib.contextmanager
def deadline(seconds: int = 20):
    """Fail instead of hanging (a FIFO read that blocks)."""
    def expire(signum, frame):
        raise TimeoutError(f"blocked for {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def refused(argv: list[str], *needles: str) -> str:
    """Run the CLI; assert exit 2, one line without a traceback naming every needle; the message."""
    with deadline():
        code, out, err = run_cli(argv)
    assert code == 2, (code, err)
    assert "Traceback" not in err and err.count("\n") == 1 and err.startswith("softgrip "), err
    assert all(n in err for n in needles), (needles, err)
    assert SECRET not in out + err
    return err


def score(poses: str | Path) -> list[str]:
    return ["score", str(FRAME), "--profile", str(PROFILE), "--poses", str(poses)]


def estimate(frame: str | Path, *extra: str) -> list[str]:
    return ["estimate", str(frame), "--profile", str(PROFILE), *extra]


def frame_copy(tmp_path: Path, name: str = "frame") -> Path:
    folder = tmp_path / name
    shutil.copytree(FRAME, folder)
    return folder


# ---------------------------------------------------------------------------------------------
# 1. Regular files only, size limits


@pytest.mark.parametrize("flag", ["--poses", "--profile"])
def test_a_fifo_is_refused_without_blocking(tmp_path: Path, flag: str) -> None:
    fifo = tmp_path / ("in.csv" if flag == "--poses" else "in.json")
    os.mkfifo(fifo)
    argv = score(fifo) if flag == "--poses" else estimate(FRAME)[:2] + ["--profile", str(fifo)]
    refused(argv, str(fifo), "FIFO")


def test_a_device_is_refused_without_reading_it(tmp_path: Path) -> None:
    zero = tmp_path / "zero.csv"
    zero.symlink_to("/dev/zero")
    refused(score(zero), str(zero), "a device")
    refused(["estimate", str(FRAME), "--profile", "/dev/zero"], "/dev/zero", "a device")


def test_a_folder_is_refused_as_a_pose_file(tmp_path: Path) -> None:
    folder = tmp_path / "poses.json"
    folder.mkdir()
    refused(score(folder), str(folder), "a folder")


@pytest.mark.parametrize("name", ["color.png", "intrinsics.json"])
def test_a_frame_file_that_is_a_fifo_or_device_is_refused(tmp_path: Path, name: str) -> None:
    frame = frame_copy(tmp_path)
    (frame / name).unlink()
    os.mkfifo(frame / name)
    refused(estimate(frame), str(frame / name), "FIFO")
    (frame / name).unlink()
    (frame / name).symlink_to("/dev/zero")
    refused(estimate(frame), str(frame / name), "a device")


def test_files_over_their_kind_s_limit_are_refused(tmp_path: Path, monkeypatch) -> None:
    poses = tmp_path / "poses.csv"
    poses.write_text("x_mm,y_mm\n" + "0,-40\n" * 100)
    monkeypatch.setattr(input_guard, "MAX_POSE_BYTES", 200)
    refused(score(poses), str(poses), "more than such a file can be (200 bytes)")
    monkeypatch.setattr(input_guard, "MAX_PROFILE_BYTES", 1000)
    refused(estimate(FRAME), str(PROFILE), "more than such a file can be (1000 bytes)")
    monkeypatch.undo()
    import softgrip_vision.frames

    monkeypatch.setattr(softgrip_vision.frames, "MAX_FILE_BYTES", 1000)
    refused(estimate(FRAME), str(FRAME / "color.png"), "more than such a file can be (1000 bytes)")


def test_standard_input_is_size_limited(monkeypatch) -> None:
    monkeypatch.setattr(input_guard, "MAX_POSE_BYTES", 100)
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(b"0,-40\n" * 50)))
    with pytest.raises(PoseInputError, match="standard input.*more than"):
        read_poses("-")
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(b"\xef\xbb\xbf0,-40,0.1\n1.5,-41,0\n")))
    np.testing.assert_array_equal(read_poses("-"), POSES[:2])


def test_a_recording_that_is_a_fifo_or_a_long_name_is_refused(tmp_path: Path) -> None:
    fifo = tmp_path / "rec.db3"
    os.mkfifo(fifo)
    refused(["capture", "--bag", str(fifo), "--out", str(tmp_path / "out")], str(fifo), "FIFO")
    refused(["capture", "--bag", str(tmp_path / ("a" * 300 + ".db3")), "--out", str(tmp_path / "out")],
            "ENAMETOOLONG")
    assert not (tmp_path / "out").exists()


def test_read_user_file_reads_at_most_the_limit_plus_one(tmp_path: Path) -> None:
    small = tmp_path / "small"
    small.write_bytes(b"12345")
    assert input_guard.read_user_file(small, what="x", max_bytes=5, error=ValueError) == b"12345"
    with pytest.raises(ValueError, match="small is 5 bytes, more than such a file can be .4 bytes."):
        input_guard.read_user_file(small, what="x", max_bytes=4, error=ValueError)
    with pytest.raises(ValueError, match="missing.*: nowhere"):
        input_guard.read_user_file(tmp_path / "missing", what="x", max_bytes=4, error=ValueError, missing="nowhere")


# ---------------------------------------------------------------------------------------------
# 2. No secret echoed


def test_a_link_to_a_secret_file_is_named_not_quoted(tmp_path: Path) -> None:
    shadow = tmp_path / "shadow"
    shadow.write_text(f"root:{SECRET}:19000:0:99999:7:::\ndaemon:*:19000:0:99999:7:::\n")
    link = tmp_path / "poses.csv"
    link.symlink_to(shadow)
    refused(score(link), str(link), "line 1", "not a pose file")


@pytest.mark.parametrize("text", [
    f'["{SECRET}", "another"]',
    f'{{"token": "{SECRET}"}}',
    f'{{"{SECRET}": 1}}',
    f'[[0, -40], {{"password": "{SECRET}"}}, "{SECRET}", "x"]',
])
def test_a_json_file_of_other_data_is_not_quoted(tmp_path: Path, text: str) -> None:
    poses = tmp_path / "poses.json"
    poses.write_text(text)
    refused(score(poses), str(poses))


def test_a_pose_file_with_one_bad_row_is_quoted(tmp_path: Path) -> None:
    poses = tmp_path / "poses.csv"
    poses.write_text("0,-40\n1,-41\nfoo,3\n2,-42\n")
    refused(score(poses), f"{poses}, line 3", "'foo,3'")


@pytest.mark.parametrize("text", [f'{{"token": "{SECRET}"}}', f'["{SECRET}"]', f"password={SECRET}\n"])
def test_a_profile_of_other_data_is_not_quoted(tmp_path: Path, text: str) -> None:
    profile = tmp_path / "profile.json"
    profile.write_text(text)
    refused(["estimate", str(FRAME), "--profile", str(profile)], str(profile))


def test_intrinsics_of_other_data_are_not_quoted(tmp_path: Path) -> None:
    frame = frame_copy(tmp_path)
    (frame / "intrinsics.json").write_text(json.dumps({"api_key": SECRET, "user": SECRET}))
    refused(estimate(frame), str(frame / "intrinsics.json"), "not camera intrinsics")


# ---------------------------------------------------------------------------------------------
# 3. CSV as people save it


@pytest.mark.parametrize(("name", "data"), [
    ("plain", b"x_mm,y_mm,angle_rad\n0,-40,0.1\n1.5,-41,0\n-2,-39.5,-0.2\n"),
    ("excel BOM", b"\xef\xbb\xbfx_mm,y_mm,angle_rad\r\n0,-40,0.1\r\n1.5,-41,0\r\n-2,-39.5,-0.2\r\n"),
    ("semicolons", b"x_mm;y_mm;angle_rad\n0;-40;0.1\n1.5;-41;0\n-2;-39.5;-0.2\n"),
    ("tabs", b"0\t-40\t0.1\n1.5\t-41\t0\n-2\t-39.5\t-0.2\n"),
    ("BOM and semicolons", b"\xef\xbb\xbf0;-40;0.1\r\n1.5;-41;0\r\n-2;-39.5;-0.2\r\n"),
])
def test_csv_as_spreadsheets_save_it_gives_the_same_poses(tmp_path: Path, name: str, data: bytes) -> None:
    path = tmp_path / "poses.csv"
    path.write_bytes(data)
    np.testing.assert_array_equal(read_poses(str(path)), POSES)


@pytest.mark.parametrize("text", ["x_mm;y_mm;angle_rad\n0,5;-40,2;0,1\n", "0,5;-40,2\n", "0,5\t-40,2\n",
                                  '"0,5","-40,2"\n'])
def test_a_decimal_comma_is_refused_never_misread(tmp_path: Path, text: str) -> None:
    path = tmp_path / "poses.csv"
    path.write_text(text)
    err = refused(score(path), str(path), "decimal comma", "0.5")
    assert "header" not in err


def test_a_file_not_utf8_is_named_without_its_bytes(tmp_path: Path) -> None:
    path = tmp_path / "poses.csv"
    path.write_bytes(b"0,-40\n\xff\xfe" + SECRET.encode() + b"\n")
    refused(score(path), str(path), "not UTF-8", "offset 6")


# ---------------------------------------------------------------------------------------------
# 4. Every message escaped


NASTY = "frame\x1b[31m\nred\r\udcff\x07"


def test_warnings_notes_and_errors_are_escaped(capsys) -> None:
    from softgrip_cli import _pipeline
    from softgrip_cli.cmd_calibrate import _print_warning as calibrate_warning
    from softgrip_cli.cmd_capture import _print_warning as capture_warning

    _pipeline.configure_output()
    _pipeline.warn(f"{NASTY}: skipped")
    _pipeline.note(f"{NASTY}: 1 frame")
    capture_warning(UserWarning(NASTY), UserWarning, "f", 1)
    calibrate_warning(UserWarning(NASTY), UserWarning, "f", 1)
    out, err = capsys.readouterr()
    assert out == ""
    lines = err.split("\n")
    assert len(lines) == 5 and lines[-1] == "", err
    for line in lines[:-1]:
        assert "\\x1b[31m\\nred\\r\\udcff\\x07" in line, line
        assert all(c.isprintable() for c in line), line


def test_an_error_about_a_nasty_folder_name_is_one_escaped_line(tmp_path: Path) -> None:
    folder = tmp_path / "frame\x1b[2J\nx"
    err = refused(estimate(folder), "frame\\x1b[2J\\nx", "does not exist")
    assert "\x1b" not in err


# ---------------------------------------------------------------------------------------------
# 5. ASCII streams, invalid UTF-8 names


def _python(code: str, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": str(ROOT), **env})


def test_ascii_streams_never_raise_on_other_characters() -> None:
    code = ("from softgrip_cli._main import safe_streams; import sys; safe_streams(); "
            "print('fr\\u20acme \\udcff'); print('gr\\u00fc\\u00dfe', file=sys.stderr)")
    done = _python(code, LC_ALL="C", PYTHONIOENCODING="ascii")
    assert done.returncode == 0, done.stderr
    assert done.stdout == b"fr\\u20acme \\udcff\n" and done.stderr == b"gr\\xfc\\xdfe\n"


@pytest.mark.slow  # a new process that imports JAX: about 10 s on the 2-core machine
def test_a_cli_error_about_a_non_ascii_name_with_ascii_streams() -> None:
    done = subprocess.run([sys.executable, "-m", "softgrip_cli", "score", "fr\u20acme-nowhere", "--profile",
                           str(PROFILE), "--poses", "p\u00f6ses.csv"], cwd=ROOT, capture_output=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": str(ROOT), "LC_ALL": "C", "PYTHONIOENCODING": "ascii"})
    assert done.returncode == 2 and b"Traceback" not in done.stderr, done.stderr
    assert b"p\\xf6ses.csv" in done.stderr and b"no such pose file" in done.stderr


# ---------------------------------------------------------------------------------------------
# 6. Names too long


def test_a_name_over_255_characters_is_one_clean_error(tmp_path: Path) -> None:
    long = "a" * 300
    before = sorted(os.listdir(tmp_path))
    refused(estimate(tmp_path / long), long, "ENAMETOOLONG")
    refused(["estimate", str(FRAME), "--profile", str(tmp_path / f"{long}.json")], "ENAMETOOLONG")
    refused(score(tmp_path / f"{long}.csv"), "ENAMETOOLONG")
    refused(estimate(FRAME, "-o", str(tmp_path / f"{long}.json")), "-o", "ENAMETOOLONG")
    refused(estimate(FRAME, "--overlay-dir", str(tmp_path / long)), "ENAMETOOLONG")
    assert sorted(os.listdir(tmp_path)) == before  # no file left


# ---------------------------------------------------------------------------------------------
# 7. Text drawn by OpenCV


def test_a_caption_with_invalid_utf8_bytes_draws_ascii_instead_of_crashing() -> None:
    # In a subprocess: before the fix, cv2.putText crashed the interpreter (exit 139) on this text.
    code = ("import numpy as np; from softgrip_cli._pictures import caption; "
            "image = np.zeros((60, 400, 3), np.uint8); "
            "caption(image, 'bad\\udcff\\x1b[31m caf\\u00e9\\nline 2', (4, 4)); print(int(image.max()))")
    done = _python(code)
    assert done.returncode == 0, done.stderr
    assert int(done.stdout) == 255  # the text was drawn


def test_plot_titles_take_names_literally() -> None:
    from softgrip_vision.plots import _plain

    assert _plain("a$x^2$\nb\udcff") == "a\\$x^2\\$\\nb\\udcff"


# ---------------------------------------------------------------------------------------------
# 8. The right cause named


@pytest.mark.parametrize("how", ["one channel", "three equal channels"])
def test_a_greyscale_colour_image_is_named_as_such(tmp_path: Path, how: str) -> None:
    frame = frame_copy(tmp_path)
    grey = cv2.cvtColor(cv2.imread(str(frame / "color.png")), cv2.COLOR_BGR2GRAY)
    cv2.imwrite(str(frame / "color.png"), grey if how == "one channel" else cv2.merge([grey] * 3))
    err = refused(estimate(frame), str(frame), "color.png", "greyscale", "colour")
    assert "gripper's body" not in err
