"""The `softgrip` command: demo output, user errors without tracebacks, --debug."""

import json

import numpy as np
import pytest

from softgrip_cli import main


def test_demo_json_is_symmetric_and_physical(tmp_path, capsys):
    assert main(["demo", "--json", "--out", str(tmp_path)]) == 0
    out = json.loads(capsys.readouterr().out)
    by_scene = {s["scene"]: {f["side"]: f for f in s["fingers"]} for s in out["scenes"]}
    centred = by_scene["circle"]  # data/: a 30 mm circle centred between the fingers, at (0, -20) mm
    assert centred["left"]["case"] == centred["right"]["case"] != "none"
    # A centred object and a (calibrated, nearly) symmetric gripper: the right finger mirrors the left
    # about the gripper's centre line x = 0, to within what the vision measures.
    left, right = np.array(centred["left"]["joints_mm"]), np.array(centred["right"]["joints_mm"])
    np.testing.assert_allclose(left * [-1, 1], right, atol=0.6)
    # Every link keeps its length L / N.
    n = out["calibration"]["n_links"]
    length = out["calibration"]["fingers"]["left"]["length_mm"]
    np.testing.assert_allclose(np.linalg.norm(np.diff(left, axis=0), axis=1), length / n, rtol=1e-3)
    # The contact lies on the 15 mm circle centred at (0, -20).
    assert np.hypot(*np.subtract(centred["left"]["contacts_mm"][0], [0.0, -20.0])) == pytest.approx(15.0, abs=0.3)


def test_user_error_prints_one_line_and_exits_2(tmp_path, capsys):
    missing = tmp_path / "nope.db3"
    assert main(["capture", "--out", str(tmp_path / "out"), "--bag", str(missing)]) == 2
    err = capsys.readouterr().err
    assert "nope.db3" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_debug_shows_the_exception(tmp_path):
    from softgrip_jax import SoftgripError

    with pytest.raises(SoftgripError):
        main(["--debug", "capture", "--out", str(tmp_path / "out"), "--bag", str(tmp_path / "nope.db3")])


def test_closed_output_pipe_exits_141_without_a_traceback(tmp_path, capsys, monkeypatch):
    from softgrip_cli import cmd_capture

    def reader_went_away(args):
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(cmd_capture, "run", reader_went_away)
    assert main(["capture", "--out", str(tmp_path / "out")]) == 141
    assert "Traceback" not in capsys.readouterr().err
