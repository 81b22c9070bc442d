"""The `softgrip` command: demo output, user errors without tracebacks, --debug."""

import json

import numpy as np
import pytest

from softgrip_cli import main


def test_demo_json_is_symmetric_and_physical(capsys):
    assert main(["demo", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    by_scene = {}
    for r in out["results"]:
        by_scene.setdefault(r["scene"], {})[r["side"]] = r
    centred = by_scene["circle between the fingers"]
    assert centred["left"]["case"] == centred["right"]["case"] != "none"
    # A centred object and a symmetric gripper: the right finger mirrors the left.
    left, right = np.array(centred["left"]["joints_mm"]), np.array(centred["right"]["joints_mm"])
    np.testing.assert_allclose(left * [-1, 1], right, atol=0.02)
    # Every link keeps its length L / N = 5.2 mm.
    np.testing.assert_allclose(np.linalg.norm(np.diff(left, axis=0), axis=1), 5.2, atol=0.02)
    far = by_scene["no object in reach"]
    assert far["left"]["case"] == far["right"]["case"] == "none"
    # The contact lies on the 15 mm circle centred at (0, 38).
    assert np.hypot(*np.subtract(centred["left"]["contact_mm"], [0.0, 38.0])) == pytest.approx(15.0, abs=0.05)


def test_user_error_prints_one_line_and_exits_2(tmp_path, capsys):
    missing = tmp_path / "nope.db3"
    assert main(["capture", "--out", str(tmp_path / "out"), "--bag", str(missing)]) == 2
    err = capsys.readouterr().err
    assert "nope.db3" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_debug_shows_the_exception(tmp_path):
    from softgrip_jax import SoftgripError

    with pytest.raises(SoftgripError):
        main(["--debug", "capture", "--out", str(tmp_path / "out"), "--bag", str(tmp_path / "nope.db3")])
