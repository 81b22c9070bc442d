"""The `softgrip` command end to end on damaged inputs: exit status 2, one line on stderr naming the
input, no traceback, and an output file that already exists is left byte for byte as it was.

The frames are at most 12 x 12 pixels, too small for two fingers of min_finger_px, so no example
reaches the (compiled) estimator: each runs in milliseconds.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from softgrip_cli import main
from tests.fuzz.strategies import frame_files, json_values, mutated_profiles

DATA = Path(__file__).resolve().parents[2] / "data"
PROFILE = DATA / "sample_profile.json"
OLD_BYTES = b"an earlier result that must survive\n"
CLI = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def user_error(code: int, capsys, *named: str) -> str:
    """Assert a user error: status 2, one stderr line naming each of ``named``, nothing on stdout."""
    out, err = capsys.readouterr()
    assert code == 2, err
    assert out == "" and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    for name in named:
        assert name in err, (name, err)
    return err


@CLI
@given(files=frame_files())
def test_estimate_and_score_refuse_a_bad_or_tiny_frame(files, capsys):
    capsys.readouterr()
    with tempfile.TemporaryDirectory() as tmp:
        frame = str(files.write(Path(tmp) / "frame"))
        heatmap = Path(tmp) / "heat.png"
        heatmap.write_bytes(OLD_BYTES)
        user_error(main(["estimate", frame, "--profile", str(PROFILE), "--json"]), capsys, frame)
        user_error(main(["score", frame, "--profile", str(PROFILE), "--heatmap", str(heatmap)]), capsys, frame)
        assert heatmap.read_bytes() == OLD_BYTES


@CLI
@given(files=frame_files(), role=st.sampled_from(["closed", "open", "fit"]))
def test_calibrate_refuses_a_bad_frame_and_keeps_the_old_profile(files, role, capsys):
    capsys.readouterr()
    with tempfile.TemporaryDirectory() as tmp:
        frame = str(files.write(Path(tmp) / "frame"))
        output = Path(tmp) / "profile.json"
        output.write_bytes(OLD_BYTES)
        frames = {"closed": [frame, "--open", str(DATA / "calib_open")],
                  "open": [str(DATA / "calib_closed"), "--open", frame],
                  "fit": ["--fit", frame, str(DATA / "calib_closed")]}  # the start comes from the open frame
        user_error(main(["calibrate", *frames[role], "-o", str(output)]), capsys, frame)
        assert output.read_bytes() == OLD_BYTES and sorted(p.name for p in Path(tmp).iterdir()) == ["frame",
                                                                                                   "profile.json"]


@CLI
@given(mutation=mutated_profiles())
def test_a_bad_profile_is_named(mutation, capsys):
    capsys.readouterr()
    _, data = mutation
    with tempfile.TemporaryDirectory() as tmp:
        profile = Path(tmp) / "gripper.json"
        profile.write_text(json.dumps(data))
        missing = str(Path(tmp) / "no_frame")  # a valid profile gets as far as the frame
        err = user_error(main(["estimate", missing, "--profile", str(profile)]), capsys)
        assert str(profile) in err or missing in err


@CLI
@given(document=json_values, suffix=st.sampled_from([".json", ".csv"]))
def test_a_bad_pose_file_is_named(document, suffix, capsys):
    capsys.readouterr()
    with tempfile.TemporaryDirectory() as tmp:
        poses = Path(tmp) / f"poses{suffix}"
        text = json.dumps(document)
        poses.write_text(text if suffix == ".json" else text.replace("[", "").replace("]", "").replace(", ", ","))
        missing = str(Path(tmp) / "no_frame")  # good poses get as far as the frame
        err = user_error(main(["score", missing, "--profile", str(PROFILE), "--poses", str(poses)]), capsys)
        assert str(poses) in err or missing in err


@pytest.mark.parametrize("argv, named", [
    (["estimate", "FRAME", "--profile", "MISSING"], "MISSING"),
    (["estimate", "FRAME", "--profile", "TMP"], "TMP"),  # a folder, not a file
    (["estimate", "MISSING", "--profile", "PROFILE"], "MISSING"),
    (["estimate", "FRAME", "--profile", "PROFILE", "--overlay-dir", "PROFILE"], "PROFILE"),
    (["score", "FRAME", "--profile", "PROFILE", "--heatmap", "TMP"], "TMP"),
    (["score", "FRAME", "--profile", "PROFILE", "--grid", "0:1:0,0:1:1,0:0:1"], "--grid"),
    (["score", "FRAME", "--profile", "PROFILE", "--grid=-1e308:1e308:3,0:1:2,0:0:1"], "--grid"),
    (["score", "FRAME", "--profile", "PROFILE", "--grid", "0:1:10000000000,0:1:1,0:0:1"], "--grid"),
    (["calibrate", "CLOSED", "--open", "OPEN", "-o", "TMP"], "TMP"),
    (["calibrate", "CLOSED", "--open", "OPEN", "-o", "TMP/missing/p.json"], "TMP/missing"),
    (["calibrate", "--fit", "OPEN", "CLOSED", "OPEN", "-o", "TMP/p.json"], "--fit"),
    (["demo", "--data", "TMP", "--out", "TMP/out"], "TMP"),
    (["capture", "--out", "TMP", "--bag", "MISSING.db3"], "MISSING.db3"),
])
def test_bad_arguments_are_user_errors(argv, named, tmp_path, capsys):
    names = {"FRAME": str(DATA / "circle_open"), "PROFILE": str(PROFILE), "MISSING": str(tmp_path / "missing"),
             "TMP": str(tmp_path), "OPEN": str(DATA / "calib_open"), "CLOSED": str(DATA / "calib_closed")}

    def fill(text):
        for key in sorted(names, key=len, reverse=True):
            text = text.replace(key, names[key])
        return text

    user_error(main([fill(a) for a in argv]), capsys, fill(named))


@pytest.mark.parametrize("argv", [["estimate"], ["score", "F", "--grid", "1", "--poses", "p.csv"], ["nope"],
                                  ["calibrate", "C", "--open", "O", "-o", "p.json", "--n-links", "0"],
                                  ["calibrate", "C", "--open", "O", "-o", "p.json", "--n-links", "101"]])
def test_usage_errors_exit_2(argv, capsys):
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: softgrip") and "error: " in err and "Traceback" not in err
