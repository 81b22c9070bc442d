"""End-to-end tests of `softgrip estimate`, `softgrip score` and `softgrip demo` on the frames in data/.

Each command runs once per module (fixtures below) and the tests read its outputs; the commands run
in this process, so the compiled estimate and score functions are shared (a few compilations for
the whole file).
"""

from __future__ import annotations

import contextlib
import io
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from softgrip_cli import main
from softgrip_cli._main import EXIT_USER_ERROR
from softgrip_jax import CASE_NAMES, DEFAULT_METHOD, SoftgripError
from softgrip_jax._quality import CONTACTS_PER_FINGER, DEFAULT_MU

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "data"
PROFILE = DATA / "sample_profile.json"
SCENES = ("circle", "square", "star_a")
FRAMES = [str(DATA / f"{name}_open") for name in SCENES]
FINGER_KEYS = {"side", "valid", "status", "case", "theta_entire", "joints_px", "joints_mm", "contacts_px",
               "contacts_mm", "event", "sensitivity"}
CANDIDATE_KEYS = {"pose", "score", "quality", "force_closure", "centroid_mm", "rho_mm", "components", "valid",
                  "status", "fingers"}
#: A scored candidate's fingers: the quality's contacts, with parallel normals and forces.
SCORED_FINGER_KEYS = FINGER_KEYS | {"normals", "forces"}
#: --grasps writes the figure at its own size: 10 x 7.5 inches at 120 dpi.
GRASPS_PX = (1200, 900)
TOP = 40


def run_cli(argv: list[str]) -> tuple[int, str, str]:
    """Run `softgrip ARGV` in this process: (exit code, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


def profile_data() -> dict:
    return json.loads(PROFILE.read_text())


def frame_camera(path: str):
    """The frame's plane camera, measured the way the pipeline measures it (the profile's
    segmentation and vision settings: the gripper plane fitted to the fingers' depth)."""
    from softgrip_calib.one_frame import frame_measurement
    from softgrip_calib.profile import load_profile
    from softgrip_vision.frames import load_frame

    frame = load_frame(path)
    profile = load_profile(PROFILE)
    return frame, frame_measurement(frame, profile.segmentation_settings(), profile.measure_settings()).camera


def check_finger(finger: dict, side: str, n_links: int, scored: bool = False) -> None:
    """An estimate's finger; ``scored``: a score candidate's, whose contacts are the grasp
    quality's (up to CONTACTS_PER_FINGER, with parallel normals and forces) instead of P_o1, P_o2."""
    assert set(finger) == (SCORED_FINGER_KEYS if scored else FINGER_KEYS)
    assert finger["side"] == side
    assert finger["case"] in CASE_NAMES
    assert finger["theta_entire"] == pytest.approx(profile_data()["fingers"][side]["theta_entire"], abs=1e-5)
    for key in ("joints_px", "joints_mm"):
        joints = np.array(finger[key], dtype=float)
        assert joints.shape == (n_links + 1, 2) and np.isfinite(joints).all()
    if scored:
        count = len(finger["contacts_mm"])
        assert len(finger["contacts_px"]) == len(finger["normals"]) == count <= CONTACTS_PER_FINGER
        assert finger["forces"] is None or len(finger["forces"]) == count
        if finger["case"] == "none":
            assert count == 0
        return
    expected_contacts = {"none": 0, "tip": 1, "other": 1, "tip_and_other": 2}[finger["case"]]
    assert len(finger["contacts_px"]) == len(finger["contacts_mm"]) == expected_contacts


def check_schema(document: dict, kind: str) -> None:
    """``document`` is valid under the repository's JSON Schema ``softgrip_base/schemas/KIND.schema.json``."""
    import jsonschema

    from softgrip_vision.documents import schema

    jsonschema.Draft202012Validator(schema(kind)).validate(document)


def check_png(path: Path, width: int, height: int) -> None:
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image is not None and image.shape == (height, width, 3) and image.dtype == np.uint8


# --- estimate ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def estimated(tmp_path_factory):
    overlays = tmp_path_factory.mktemp("overlays")
    document = tmp_path_factory.mktemp("documents") / "estimates.json"
    code, out, err = run_cli(["estimate", *FRAMES, "--profile", str(PROFILE), "--json",
                              "--overlay-dir", str(overlays), "--output", str(document)])
    assert code == 0, err
    assert json.loads(document.read_text()) == json.loads(out)  # -o writes what --json prints
    return json.loads(out)["frames"], overlays, json.loads(out)


def test_estimate_json_is_one_document_valid_under_its_schema(estimated):
    *_, document = estimated
    check_schema(document, "estimate")
    assert document["format"] == "softgrip-estimate/1" and document["units"] == {"length": "mm", "angle": "rad",
                                                                                 "image": "px"}
    assert document["profile"]["path"] == str(PROFILE) and len(document["profile"]["sha256"]) == 64
    assert document["profile"]["fingers"]["left"]["n_links"] == profile_data()["fingers"]["left"]["n_links"]
    assert (document["n_frames"], document["n_estimated"], document["n_failed"]) == (len(FRAMES), len(FRAMES), 0)
    for record in document["frames"]:
        _, camera = frame_camera(record["frame"])
        assert record["plane"]["depth_mm"] == pytest.approx(camera.depth_mm, abs=1e-3)
        # The pose is the midpoint of the two bases (joint 0 of each finger).
        bases = np.array([f["joints_mm"][0] for f in record["fingers"]])
        assert [record["pose"]["x_mm"], record["pose"]["y_mm"]] == pytest.approx(bases.mean(axis=0), abs=1e-3)
    # A document that breaks the schema is refused: the test can fail.
    import jsonschema

    broken = json.loads(json.dumps(document))
    broken["frames"][0]["fingers"][0]["case"] = 2
    with pytest.raises(jsonschema.ValidationError):
        check_schema(broken, "estimate")


def test_estimate_jsonl_keeps_one_object_per_line(estimated):
    records, *_ = estimated
    code, out, err = run_cli(["estimate", FRAMES[0], "--profile", str(PROFILE), "--jsonl"])
    assert code == 0, err
    lines = out.splitlines()
    assert len(lines) == 1 and json.loads(lines[0]) == records[0]


def test_estimate_prints_one_json_object_per_frame_in_order(estimated):
    records, *_ = estimated
    n_links = profile_data()["fingers"]["left"]["n_links"]
    assert [r["frame"] for r in records] == FRAMES
    for record in records:
        assert set(record) >= {"frame", "valid", "status", "method", "n_links", "fingers", "pose", "plane"}
        assert record["valid"] is True and record["status"] == "ok"
        assert all(f["valid"] is True and f["status"] == "ok" for f in record["fingers"])
        assert record["method"] == DEFAULT_METHOD  # the sample profile records no fitted estimate
        assert record["n_links"] == n_links
        assert [f["side"] for f in record["fingers"]] == ["left", "right"]
        for finger in record["fingers"]:
            check_finger(finger, finger["side"], n_links)
        # Objects sit between the fingers: every finger touches.
        assert all(f["case"] != "none" for f in record["fingers"])


def test_estimate_pixels_and_millimetres_agree_through_the_frames_camera(estimated):
    records, *_ = estimated
    truth = json.loads((DATA / "truth.json").read_text())
    profile = profile_data()
    for record in records:
        _, camera = frame_camera(record["frame"])
        for finger in record["fingers"]:
            for px, mm in (("joints_px", "joints_mm"), ("contacts_px", "contacts_mm")):
                if finger[mm]:
                    np.testing.assert_allclose(camera.mm_to_px(finger[mm]), finger[px], atol=2e-3)
            joints = np.array(finger["joints_mm"])
            link = profile["fingers"][finger["side"]]["length"] / record["n_links"]
            np.testing.assert_allclose(np.hypot(*np.diff(joints, axis=0).T), link, rtol=1e-3)
        # Base 0 of each finger is where the renderer put it (mm in the gripper plane).
        centre = np.array(truth["gripper"]["center_mm"])
        half = np.array([truth["gripper"]["base_separation_mm"] / 2, 0.0])
        for finger, base in zip(record["fingers"], (centre - half, centre + half)):
            assert np.hypot(*(np.array(finger["joints_mm"][0]) - base)) < 0.3


def test_estimate_writes_one_overlay_per_frame(estimated):
    _, overlays, _ = estimated
    for path in FRAMES:
        check_png(overlays / f"{Path(path).name}.png", 640, 480)


def test_estimate_table_without_json():
    code, out, _ = run_cli(["estimate", FRAMES[0], "--profile", str(PROFILE)])
    assert code == 0
    assert "left" in out and "right" in out and FRAMES[0] in out and f"{DEFAULT_METHOD} estimate" in out


def test_estimate_method_mechanics_and_the_profiles_recorded_method(estimated, tmp_path):
    """--method mechanics is the spring chain at equilibrium; without --method, a profile fitted
    through the mechanics estimate (fit.estimate_method) estimates with it; --method overrides it."""
    code, out, err = run_cli(["estimate", FRAMES[0], "--profile", str(PROFILE), "--json", "--method", "geometric"])
    assert code == 0, err
    records = json.loads(out)["frames"]
    assert records[0]["method"] == "geometric"
    code, out, err = run_cli(["estimate", FRAMES[0], "--profile", str(PROFILE), "--json", "--method", "mechanics"])
    assert code == 0, err
    mechanics = json.loads(out)["frames"][0]
    assert mechanics["method"] == "mechanics"
    n_links = profile_data()["fingers"]["left"]["n_links"]
    for finger, geometric in zip(mechanics["fingers"], records[0]["fingers"]):
        check_finger(finger, finger["side"], n_links)
        assert finger["case"] != "none"
        # The same base and link lengths; a different deformation model wherever the finger touches.
        assert finger["joints_mm"][0] == pytest.approx(geometric["joints_mm"][0], abs=1e-3)
        assert np.abs(np.subtract(finger["joints_mm"], geometric["joints_mm"])).max() > 1e-3

    data = profile_data()
    data["fit"]["estimate_method"] = "mechanics"
    recorded = tmp_path / "mechanics_profile.json"
    recorded.write_text(json.dumps(data))
    code, out, err = run_cli(["estimate", FRAMES[0], "--profile", str(recorded), "--json"])
    assert code == 0, err
    assert json.loads(out)["frames"][0] == mechanics
    assert json.loads(out)["profile"]["estimate_method"] == "mechanics"
    code, out, err = run_cli(["estimate", FRAMES[0], "--profile", str(recorded), "--json", "--method", "geometric"])
    assert code == 0, err
    assert json.loads(out)["frames"][0] == records[0]


@pytest.mark.parametrize("command", [["estimate", FRAMES[0]], ["score", FRAMES[0]], ["demo"]])
def test_an_unknown_method_is_a_usage_error(command, capsys):
    extra = ["--profile", str(PROFILE)] if command[0] != "demo" else []
    with pytest.raises(SystemExit) as info:
        main([*command, *extra, "--method", "spring"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "argument --method: invalid choice: 'spring'" in err and "Traceback" not in err


# --- score ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def scored(tmp_path_factory):
    folder = tmp_path_factory.mktemp("score")
    heatmap, output = folder / "heat.png", folder / "scored.json"
    output.write_text("old")
    output.chmod(0o600)
    code, out, err = run_cli(["score", FRAMES[0], "--profile", str(PROFILE), "--json", "--heatmap", str(heatmap),
                              "--grasps", str(folder / "grasps.png"), "--top", str(TOP), "-o", str(output)])
    assert code == 0, err
    # -o holds what --json prints, written atomically over the old file, whose mode it keeps.
    assert json.loads(output.read_text()) == json.loads(out) and (output.stat().st_mode & 0o777) == 0o600
    check_schema(json.loads(out), "score")
    return json.loads(out), heatmap


def test_score_json_is_ranked_best_first(scored):
    out, _ = scored
    n_links = profile_data()["fingers"]["left"]["n_links"]
    candidates = out["candidates"]
    assert out["method"] == DEFAULT_METHOD
    assert out["format"] == "softgrip-score/2" and out["conventions"]["plane"]["depth_mm"] > 0
    assert out["profile"]["path"] == str(PROFILE)
    assert out["n_candidates"] >= len(candidates) == TOP and out["n_valid"] > 0
    for c in candidates:
        assert set(c) == CANDIDATE_KEYS
        assert set(c["pose"]) == {"x_mm", "y_mm", "angle_rad"}
        assert c["valid"] == (c["score"] is not None)
        assert isinstance(c["status"], str)
        assert set(c["components"]) >= {"touch", "wrap", "opposition", "tip_only", "penetration_mm"}
        assert [f["side"] for f in c["fingers"]] == ["left", "right"]
        for finger in c["fingers"]:
            check_finger(finger, finger["side"], n_links, scored=True)
    scores = [c["score"] for c in candidates if c["valid"]]
    assert scores == sorted(scores, reverse=True)
    # Invalid candidates (score null) only after every valid one.
    valid_flags = [c["valid"] for c in candidates]
    assert valid_flags == sorted(valid_flags, reverse=True)


def check_quality_fields(document: dict, mu: float, forces: bool) -> None:
    """The grasp quality's fields of a score document (one of the sample frames: a disc of radius
    15 mm): ``friction.mu`` is ``mu``; each valid candidate's quality is a number >= 0, in force
    closure exactly when > 0, and its score is in the tier that says (1 + ..., or below 0.99); each
    finger's contacts lie on the disc with its outward unit normals, and ``forces`` (parallel,
    finite) are given exactly when ``forces``."""
    assert document["friction"] == {"mu": mu}
    candidates = document["candidates"]
    assert any(c["valid"] and c["force_closure"] for c in candidates)
    for c in candidates:
        assert isinstance(c["force_closure"], bool)
        centroid, rho = np.array(c["centroid_mm"], float), c["rho_mm"]
        assert centroid.shape == (2,) and np.isfinite(centroid).all() and 15.0 <= rho <= 16.5
        if not c["valid"]:
            assert c["quality"] is None and c["force_closure"] is False
            continue
        assert isinstance(c["quality"], float | int) and c["quality"] >= 0.0
        assert c["force_closure"] == (c["quality"] > 0)
        assert (c["score"] >= 1.0) == c["force_closure"]
        assert 0.0 <= c["components"]["risk"] <= 1.0 and 0.0 <= c["components"]["progress"] <= 1.0
        for finger in c["fingers"]:
            points = np.array(finger["contacts_mm"], float).reshape(-1, 2)
            normals = np.array(finger["normals"], float).reshape(-1, 2)
            assert len(points) == len(normals) == len(finger["contacts_mm"])
            if not len(points):
                assert finger["forces"] in (None, [])
                continue
            np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-4)
            radial = points - centroid
            np.testing.assert_allclose(np.linalg.norm(radial, axis=1), 15.0, atol=0.8)  # on the disc
            assert (np.sum(normals * radial, axis=1) / np.linalg.norm(radial, axis=1) > 0.9).all()  # outward
            if forces:
                pushes = np.array(finger["forces"], float)
                assert pushes.shape == points.shape and np.isfinite(pushes).all()
                assert (np.sum(pushes * normals, axis=1) <= 1e-6).all()  # pushing on the object, not pulling
            else:
                assert finger["forces"] is None


def test_score_json_has_the_grasp_quality_of_the_mechanics_estimate(scored):
    document, _ = scored
    assert document["method"] == "mechanics"
    check_quality_fields(document, DEFAULT_MU, forces=True)
    _, camera = frame_camera(FRAMES[0])
    for finger in (f for c in document["candidates"] for f in c["fingers"] if f["contacts_mm"]):
        np.testing.assert_allclose(camera.mm_to_px(finger["contacts_mm"]), finger["contacts_px"], atol=2e-3)
    # A document whose lists are not parallel, or with a quality out of range, breaks the schema.
    import jsonschema

    broken = json.loads(json.dumps(document))
    broken["candidates"][0]["quality"] = -1.0
    with pytest.raises(jsonschema.ValidationError):
        check_schema(broken, "score")
    broken = json.loads(json.dumps(document))
    del broken["friction"]
    with pytest.raises(jsonschema.ValidationError):
        check_schema(broken, "score")
    # Room for robust scoring: optional quality_mean and p_closure in [0, 1].
    broken["friction"] = document["friction"]
    broken["candidates"][0].update(quality_mean=0.2, p_closure=0.9)
    check_schema(broken, "score")
    broken["candidates"][0]["p_closure"] = 1.5
    with pytest.raises(jsonschema.ValidationError):
        check_schema(broken, "score")


def test_score_mu_and_geometric_estimate_and_the_grasps_picture(tmp_path):
    """--mu is the document's friction.mu and changes the quality; the geometric estimate gives no
    forces (null); --grasps writes a PNG at the figure's size."""
    documents = {}
    for mu in ("0.8", "0"):
        grasps = tmp_path / f"grasps_{mu}.png"
        code, out, err = run_cli(["score", FRAMES[0], "--profile", str(PROFILE), "--grid=-10:10:5,-60:-40:5,0:0:1",
                                  "--top", "0", "--json", "--method", "geometric", "--mu", mu, "--grasps", str(grasps),
                                  "-q"])
        assert code == 0, err
        documents[mu] = json.loads(out)
        check_schema(documents[mu], "score")
        check_png(grasps, *GRASPS_PX)
    check_quality_fields(documents["0.8"], 0.8, forces=False)
    # Without friction two fingers' few contacts on a disc hold nothing: no force closure anywhere.
    assert documents["0"]["friction"] == {"mu": 0.0}
    assert not any(c["force_closure"] for c in documents["0"]["candidates"])


@pytest.mark.slow  # compiles the robust score of the sample profile (N = 20): a minute or more
def test_score_robust_reports_expected_quality_and_closure_probability(tmp_path):
    """--robust K: the document's "robust" lists the draws' settings; every valid candidate has
    quality_mean and p_closure in [0, 1], a grasp in closure ranks by 1 + quality_mean (1 - risk),
    and the heat map shows P(force closure)."""
    heatmap = tmp_path / "p.png"
    code, out, err = run_cli(["score", FRAMES[0], "--profile", str(PROFILE), "--grid=-10:10:5,-60:-40:5,0:0:1",
                              "--top", "0", "--json", "--method", "geometric", "--robust", "4", "--pose-sigma",
                              "1.0,0.02", "--contour-sigma", "0.3", "--heatmap", str(heatmap), "-q"])
    assert code == 0, err
    document = json.loads(out)
    check_schema(document, "score")
    robust = document["robust"]
    assert (robust["method"], robust["samples"], robust["pose_mm"], robust["pose_rad"], robust["contour_mm"]) == (
        "draws", 4, 1.0, 0.02, 0.3)
    assert robust["mu_spread"] == pytest.approx(0.2)
    valid = [c for c in document["candidates"] if c["valid"]]
    assert valid and all(0 <= c["quality_mean"] <= 1 and 0 <= c["p_closure"] <= 1 for c in valid)
    assert all(c["p_closure"] * 4 == round(c["p_closure"] * 4) for c in valid)  # a fraction of 4 draws
    for c in valid:
        if c["force_closure"]:
            expected = 1 + c["quality_mean"] * (1 - c["components"]["risk"])
            assert c["score"] == pytest.approx(expected, rel=1e-4, abs=1e-4)
    assert all(c["quality_mean"] is None and c["p_closure"] is None for c in document["candidates"] if not c["valid"])
    assert heatmap.stat().st_size > 0


def test_robust_linear_sets_the_linearisation_with_the_same_spreads():
    from argparse import Namespace

    from softgrip_cli.cmd_score import parse_robust
    from softgrip_jax import Uncertainty
    from softgrip_vision.documents import uncertainty_json

    args = Namespace(robust="linear", pose_sigma="0.8,0.02", mu_spread=None, contour_sigma="0.1")
    settings = parse_robust(args)
    assert settings == {"linear": True, "pose_mm": 0.8, "pose_rad": 0.02, "mu_spread": 0.2, "contour_mm": 0.1}
    document = uncertainty_json(Uncertainty(**settings))
    assert (document["method"], document["samples"], document["seed"], document["pose_mm"]) == ("linear", None, None, 0.8)
    drawn = parse_robust(Namespace(robust="16", pose_sigma=None, mu_spread=None, contour_sigma=None))
    assert (drawn["samples"], drawn["reach"]) == (16, math.inf)  # every valid candidate drawn
    assert parse_robust(Namespace(robust="0", pose_sigma=None, mu_spread=None, contour_sigma=None)) is None


@pytest.mark.parametrize(("argv", "flag"), [(["--pose-sigma", "1,0.01"], "--pose-sigma"),
                                            (["--robust", "4", "--pose-sigma", "1"], "--pose-sigma"),
                                            (["--robust", "4", "--mu-spread", "1.5"], "--mu-spread"),
                                            (["--robust", "-2"], "--robust"),
                                            (["--robust", "lineal"], "--robust"),
                                            (["--robust", "4", "--contour-sigma", "nan"], "--contour-sigma")])
def test_bad_robust_options_are_one_line_user_errors(argv, flag):
    code, out, err = run_cli(["score", FRAMES[0], "--profile", str(PROFILE), *argv])
    one_line_error(code, err)
    assert flag in err and out == ""


def test_score_grasps_picture_of_the_mechanics_estimate(scored):
    _, heatmap = scored
    check_png(heatmap.parent / "grasps.png", *GRASPS_PX)


@pytest.mark.parametrize("mu", ["-1", "nan", "inf", "10.5", "abc"])
def test_bad_mu_is_a_one_line_user_error(mu, tmp_path):
    code, out, err = run_cli(["score", FRAMES[0], "--profile", str(PROFILE), f"--mu={mu}", "--grasps",
                              str(tmp_path / "g.png")])
    one_line_error(code, err)
    assert "--mu" in err and out == "" and not (tmp_path / "g.png").exists()


def test_grasps_refuses_to_overwrite_an_input(tmp_path):
    import shutil

    frame = tmp_path / "circle_open"
    shutil.copytree(FRAMES[0], frame)
    before = (frame / "color.png").read_bytes()
    code, _, err = run_cli(["score", str(frame), "--profile", str(PROFILE), "--grasps", str(frame / "color.png")])
    one_line_error(code, err)
    assert "--grasps" in err and (frame / "color.png").read_bytes() == before
    code, _, err = run_cli(["score", str(frame), "--profile", str(PROFILE), "--grasps", str(tmp_path / "same.png"),
                            "--heatmap", str(tmp_path / "same.png")])
    one_line_error(code, err)
    assert "--heatmap and --grasps name the same file" in err


def test_score_heatmap_is_a_matplotlib_plot_with_a_colour_bar(scored):
    _, heatmap = scored
    assert heatmap.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = cv2.cvtColor(cv2.imread(str(heatmap)), cv2.COLOR_BGR2RGB)
    h, w = image.shape[:2]
    assert w > 640 and h > 480  # the frame plus axes, labels and a colour bar
    # viridis's ends (the colour bar and the cells) are in the picture.
    for colour in ((68, 1, 84), (253, 231, 37)):
        assert np.any(np.abs(image.astype(int) - colour).sum(axis=-1) < 40), colour


def test_heatmap_format_follows_the_extension(scored, tmp_path):
    """--heatmap x.jpg writes a JPEG; an extension matplotlib cannot write is refused before any work."""
    code, _, err = run_cli(["score", FRAMES[0], "--profile", str(PROFILE), "--grid=-5:5:3,-50:-40:3,0:0:1",
                            "--heatmap", str(tmp_path / "heat.jpg"), "-q"])
    assert code == 0, err
    assert (tmp_path / "heat.jpg").read_bytes()[:3] == b"\xff\xd8\xff"
    code, _, err = run_cli(["score", FRAMES[0], "--profile", str(PROFILE), "--heatmap", str(tmp_path / "heat.xyz")])
    assert code == 2 and ".xyz" in err and ".png" in err and not (tmp_path / "heat.xyz").exists()


def test_score_ranks_a_grasp_above_closing_on_nothing(tmp_path):
    poses = tmp_path / "poses.csv"
    poses.write_text("x_mm,y_mm,angle_rad\n# far left: both fingers close on nothing\n-60,-45,0\n0,-45,0\n")
    code, out, err = run_cli(["score", FRAMES[0], "--profile", str(PROFILE), "--poses", str(poses), "--json"])
    assert code == 0, err
    first, second = json.loads(out)["candidates"]
    assert first["pose"]["x_mm"] == 0.0 and first["score"] > second["score"]
    assert [f["case"] for f in second["fingers"]] == ["none", "none"]
    assert all(f["case"] != "none" for f in first["fingers"])


@pytest.mark.parametrize("name, text, where", [
    ("bad.csv", "x_mm,y_mm\n1,2\n1,2,3\n", "line 3"),
    ("bad.csv", "1,2\n1,two\n", "line 2"),
    ("bad.json", '[\n  [0, -45, 0],\n  {"x_mm": 1}\n]\n', "line 3"),
    ("bad.json", '{"poses": [\n [0, 1],\n [0, 1, 2, 3]\n]}', "line 3"),
    ("bad.json", '[[0, 1],\n [0, 1]', "line 2"),
    ("empty.csv", "x_mm,y_mm\n", "no poses"),
    ("poses.txt", "0,0\n", ".json or .csv"),
])
def test_bad_pose_files_name_the_file_and_line(tmp_path, name, text, where):
    path = tmp_path / name
    path.write_text(text)
    code, out, err = run_cli(["score", FRAMES[0], "--profile", str(PROFILE), "--poses", str(path)])
    assert code == 2 and out == ""
    assert str(path) in err and where in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_score_reads_poses_from_stdin_and_writes_the_document_to_stdout(scored, monkeypatch):
    """--poses - reads CSV (or JSON) from standard input; -o - writes the document to stdout."""
    best = scored[0]["candidates"][0]["pose"]
    monkeypatch.setattr("sys.stdin", io.StringIO(f"{best['x_mm']},{best['y_mm']},{best['angle_rad']}\n-60,-45,0\n"))
    code, out, err = run_cli(["score", FRAMES[0], "--profile", str(PROFILE), "--poses", "-", "-o", "-", "-q"])
    assert code == 0, err
    assert "scored" not in err and "warning" not in err  # -q: no summary, no warnings
    document = json.loads(out)
    check_schema(document, "score")
    assert document["n_candidates"] == 2
    assert document["candidates"][0]["score"] == pytest.approx(scored[0]["candidates"][0]["score"], abs=1e-4)
    monkeypatch.setattr("sys.stdin", io.StringIO('[[0, -45, 0]]'))
    code, out, err = run_cli(["score", FRAMES[0], "--profile", str(PROFILE), "--poses", "-", "--json", "-q"])
    assert code == 0 and json.loads(out)["candidates"][0]["pose"] == {"x_mm": 0.0, "y_mm": -45.0, "angle_rad": 0.0}
    monkeypatch.setattr("sys.stdin", io.StringIO("1,2,3,4\n"))
    code, _, err = run_cli(["score", FRAMES[0], "--profile", str(PROFILE), "--poses", "-"])
    assert code == 2 and "<stdin>, line 1" in err


def test_bad_grid_is_a_user_error():
    code, _, err = run_cli(["score", FRAMES[0], "--profile", str(PROFILE), "--grid", "1:2:3"])
    assert code == 2 and "--grid" in err and len(err.strip().splitlines()) == 1


# --- demo -------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out_dir = tmp_path_factory.mktemp("demo")
    code, out, err = run_cli(["demo", "--out", str(out_dir), "--json"])
    assert code == 0, err
    return json.loads(out), out_dir


@pytest.mark.slow  # the demo fixture runs the whole pipeline: about 130 s
def test_demo_json_is_symmetric_and_physical(demo):
    out, _ = demo
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


@pytest.mark.slow  # the demo fixture runs the whole pipeline: about 130 s
def test_demo_writes_its_outputs(demo):
    summary, out_dir = demo
    assert summary["method"] == DEFAULT_METHOD
    assert {s["scene"] for s in summary["scenes"]} == set(SCENES)
    for name in summary["files"]:
        assert (out_dir / name).is_file(), name
    for name in summary["files"]:
        if name.endswith(".png") and not name.startswith("heatmap_"):
            check_png(out_dir / name, 640, 480)
    heatmaps = [name for name in summary["files"] if name.startswith("heatmap_")]
    assert heatmaps  # plotted with mm axes and a colour bar: larger than the frame, RGB
    for name in heatmaps:
        image = cv2.imread(str(out_dir / name), cv2.IMREAD_UNCHANGED)
        assert image.ndim == 3 and image.shape[2] == 3 and image.shape[0] > 480 and image.shape[1] > 640
    assert json.loads((out_dir / "summary.json").read_text()) == summary
    from softgrip_calib.profile import load_profile

    profile = load_profile(out_dir / "profile.json")
    assert profile.fingers["left"].theta_entire == pytest.approx(0.55, abs=0.01)


@pytest.mark.slow  # the demo fixture runs the whole pipeline: about 130 s
def test_demo_estimates_match_the_observed_closure(demo):
    summary, _ = demo
    for scene in summary["scenes"]:
        for finger in scene["fingers"]:
            assert finger["case"] != "none"
            errors = scene["errors_vs_observed"][finger["side"]]
            # The paper's geometric cases, against an independent elastic rod: millimetres at most.
            assert errors["tip_mm"] < 3.0 and errors["mid_mm"] < 3.0


@pytest.mark.slow  # the demo fixture runs the whole pipeline: about 130 s
def test_demo_refinement_never_loses_score(demo):
    summary, _ = demo
    refined = summary["refine"]
    assert summary["score"]["best"]["valid"]
    assert refined["score"] is not None and refined["score"] >= refined["start_score"] - 1e-6
    assert refined["status"] in ("improved", "no_improvement", "max_steps")


# --- user errors ------------------------------------------------------------------------------


def one_line_error(code: int, err: str) -> None:
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_missing_frame_is_a_user_error(tmp_path):
    missing = tmp_path / "no_such_frame"
    code, out, err = run_cli(["estimate", str(missing), "--profile", str(PROFILE)])
    one_line_error(code, err)
    assert str(missing) in err and out == ""


def test_bad_profile_names_the_field(tmp_path):
    data = profile_data()
    data["fingers"]["left"]["theta_entire"] = "abc"
    bad = tmp_path / "bad_profile.json"
    bad.write_text(json.dumps(data))
    for argv in (["estimate", FRAMES[0]], ["score", FRAMES[0]]):
        code, _, err = run_cli([*argv, "--profile", str(bad)])
        one_line_error(code, err)
        assert "bad_profile.json" in err and "fingers.left.theta_entire" in err


def test_missing_profile_is_a_user_error(tmp_path):
    code, _, err = run_cli(["estimate", FRAMES[0], "--profile", str(tmp_path / "nope.json")])
    one_line_error(code, err)
    assert "nope.json" in err


@pytest.fixture(scope="module")
def frame_without_gripper(tmp_path_factory):
    from softgrip_vision.frames import save_frame
    from synthetic.render import Scene, d405_intrinsics, render

    path = tmp_path_factory.mktemp("frames") / "empty_frame"
    save_frame(render(Scene([], seed=3), d405_intrinsics()), path)
    return path


def test_unusable_frame_is_a_user_error_naming_the_frame(frame_without_gripper):
    code, _, err = run_cli(["estimate", str(frame_without_gripper), "--profile", str(PROFILE)])
    one_line_error(code, err)
    assert str(frame_without_gripper) in err and "no gripper" in err


def test_a_frame_list_goes_on_past_a_bad_frame_and_fails_at_the_end_naming_it(frame_without_gripper):
    bad = str(frame_without_gripper)
    code, out, err = run_cli(["estimate", bad, FRAMES[0], "--profile", str(PROFILE), "--json"])
    assert code == EXIT_USER_ERROR and "Traceback" not in err
    document = json.loads(out)
    check_schema(document, "estimate")
    assert (document["n_frames"], document["n_estimated"], document["n_failed"]) == (2, 1, 1)
    records = document["frames"]
    assert [r["frame"] for r in records] == [bad, FRAMES[0]]  # the good frame after the bad one is estimated
    assert records[0]["valid"] is False and records[0]["status"] == "error" and "no gripper" in records[0]["error"]
    assert records[1]["valid"] is True and len(records[1]["fingers"]) == 2
    assert f"1 of 2 frames failed: {bad}" in err.splitlines()[-1]


def test_debug_shows_the_exception(frame_without_gripper):
    with pytest.raises(SoftgripError):
        main(["--debug", "estimate", str(frame_without_gripper), "--profile", str(PROFILE)])


# --- calibrate --fit: the free closure and the per-frame report --------------------------------
# Every fit here goes through the geometric estimate, N = 20, over the sample frames' 640 x 480
# grids: one compilation (some 20 s) for all of them.

OBJECT_PAIRS = [str(DATA / f"{name}_{state}") for name in SCENES for state in ("open", "closed")]
CALIBRATION = (str(DATA / "calib_open"), str(DATA / "calib_closed"))
FRAME_KEYS = {"frame", "residual_rms_mm", "start_residual_rms_mm", "mid_error_mm", "tip_error_mm", "free_closure"}


def fit_cli(*argv: str) -> tuple[int, str, str]:
    return run_cli(["calibrate", "--fit", *OBJECT_PAIRS, "--method", "geometric", *argv])


@pytest.fixture(scope="module")
def fit_with_empty(tmp_path_factory):
    output = tmp_path_factory.mktemp("fit") / "fitted.json"
    code, out, err = fit_cli("--empty", *CALIBRATION, "--n-links", "20", "--json", "-o", str(output))
    assert code == 0, err
    return json.loads(out), err, output


@pytest.mark.slow  # its fixture runs calibrate --fit: about 40 s
def test_calibrate_fit_with_empty_reports_every_pairs_residual(fit_with_empty):
    report, err, output = fit_with_empty
    from softgrip_calib.profile import load_profile

    fit = load_profile(output).fit
    label = " + ".join(CALIBRATION)
    assert fit.frames == [f"{OBJECT_PAIRS[i]} + {OBJECT_PAIRS[i + 1]}" for i in range(0, 6, 2)] + [label]
    assert fit.free_closure == label
    rows = report["frames"]
    assert [row["frame"] for row in rows] == fit.frames
    for i, row in enumerate(rows):
        assert set(row) == FRAME_KEYS
        assert row["residual_rms_mm"] == fit.frame_residual_rms_mm[i]
        assert row["start_residual_rms_mm"] == fit.frame_start_residual_rms_mm[i]
        assert 0.0 < row["mid_error_mm"] < 2.0 and 0.0 < row["tip_error_mm"] < 2.0
        assert row["free_closure"] == (row["frame"] == label)
    # Without --profile the fit starts from the calibration pair's one-frame calibration.
    free = report["free_closure"]
    assert free["frame"] == label and free["start"] == "one-frame"
    assert free["start_residual_rms_mm"] == rows[-1]["start_residual_rms_mm"] < 0.2
    assert free["residual_rms_mm"] == rows[-1]["residual_rms_mm"]
    assert free["change_mm"] == pytest.approx(free["residual_rms_mm"] - free["start_residual_rms_mm"])
    # The geometric estimate (eq. 9) closes on objects differently from the rod that shaped these
    # frames: a Theta that suits both the objects and the free closure leaves the free closure about
    # 0.17 mm worse than the one-frame calibration, and the command says so (the mechanics estimate
    # keeps it: tests/calib/test_fit.py).
    assert free["worse"] == (free["change_mm"] > 0.1)
    assert free["worse"]
    assert f"warning: the fit made the free closure ({label}) worse" in err
    assert "L, r or the base separation are measured wrong" in err


def test_calibrate_fit_includes_a_one_frame_profiles_pair(tmp_path):
    """A one-frame calibration records its folders (here absolute): the fit includes that pair."""
    one = tmp_path / "one.json"
    code, _, err = run_cli(["calibrate", CALIBRATION[1], "--open", CALIBRATION[0], "--n-links", "20", "-o", str(one)])
    assert code == 0, err
    output = tmp_path / "fitted.json"
    code, out, err = fit_cli("--profile", str(one), "--json", "-o", str(output))
    assert code == 0, err
    label = " + ".join(CALIBRATION)
    assert f"including the free-closure pair {label} that {one} records" in err
    report = json.loads(out)
    assert report["profile"]["fit"]["free_closure"] == label
    assert [row["free_closure"] for row in report["frames"]] == [False, False, False, True]
    assert report["free_closure"]["start"] == "one-frame"


def test_calibrate_fit_text_report_with_the_sample_profile(tmp_path):
    """data/sample_profile.json names its pair relative to its folder: found next to the profile.
    The text summary lists every pair and the free closure's one-frame residual beside the fitted."""
    output = tmp_path / "fitted.json"
    code, out, err = fit_cli("--profile", str(PROFILE), "-o", str(output))
    assert code == 0, err
    pair = f"{DATA / 'calib_open'} + {DATA / 'calib_closed'}"
    assert f"including the free-closure pair {pair} that {PROFILE} records" in err
    lines = out.splitlines()
    assert "per frame pair (mm): residual RMS, mean joint error at joint N/2 and at the tip" in lines
    from softgrip_calib.profile import load_profile

    fit = load_profile(output).fit
    for label, rms in zip(fit.frames, fit.frame_residual_rms_mm):
        (line,) = [line for line in lines if line.startswith(f"  {label}: ")]
        assert f"RMS {rms:.3f}, N/2 " in line and ", tip " in line
    (free,) = [line for line in lines if line.startswith(f"  {pair}: ")]
    i = fit.frames.index(pair)
    assert free.endswith(f"; free closure: one-frame {fit.frame_start_residual_rms_mm[i]:.3f} -> fitted "
                         f"{fit.frame_residual_rms_mm[i]:.3f}")


def test_calibrate_fit_warns_when_the_profiles_pair_is_missing(tmp_path):
    moved = tmp_path / "sample_profile.json"  # the frames it names are not next to this copy
    moved.write_text(PROFILE.read_text())
    output = tmp_path / "fitted.json"
    code, out, err = fit_cli("--profile", str(moved), "--json", "-o", str(output))
    assert code == 0, err
    assert (f"warning: {moved} records its free-closure pair calib_open + calib_closed, but the folders calib_open "
            f"and calib_closed do not exist") in err
    assert "give the pair with --empty OPEN CLOSED" in err
    report = json.loads(out)
    assert report["free_closure"] is None and len(report["frames"]) == 3
    assert "free_closure" not in report["profile"]["fit"]


@pytest.mark.parametrize("profile", [False, True])
def test_calibrate_fit_refuses_an_empty_pair_with_an_object(tmp_path, profile):
    """Whether the start comes from the pair (one-frame) or from --profile, the frame is named."""
    closed = str(DATA / "circle_closed")
    extra = ["--profile", str(PROFILE)] if profile else ["--n-links", "20"]
    code, out, err = fit_cli("--empty", str(DATA / "circle_open"), closed, *extra, "-o", str(tmp_path / "p.json"))
    one_line_error(code, err)
    assert f"{closed} shows an object" in err and out == ""
    assert not (tmp_path / "p.json").exists()


def test_score_text_table_shows_quality_and_closure_probability():
    """The plain-text ranking: score, quality (0 without closure) and, robust, P(closure); '-' where
    a candidate is not valid."""
    from types import SimpleNamespace

    from softgrip_cli.cmd_score import _table

    case = np.array([1, 2, 0])
    finger = SimpleNamespace(case=case)
    result = SimpleNamespace(valid=np.array([True, True, False]), score=np.array([1.25, 0.5, -np.inf]),
                             quality=np.array([0.25, 0.0, 0.0]), p_closure=np.array([0.875, 0.125, 0.0]),
                             force_closure=np.array([True, False, False]), status=np.array([0, 0, 3]),
                             penetrating=np.array([False, False, False]),
                             grasp=SimpleNamespace(left=finger, right=finger))
    poses = np.array([[0.0, -40.0, 0.0], [1.0, -42.0, 0.1], [2.0, -44.0, 0.2]])
    scene = SimpleNamespace(path="frame_0")
    lines = _table(scene, poses, result, np.array([0, 1, 2]), 2, robust=True).splitlines()
    assert "1 in force closure" in lines[0]
    assert lines[1].split()[6:9] == ["score", "quality", "P(closure)"]
    assert lines[2].split()[4:7] == ["1.250", "0.250", "0.875"]
    assert lines[3].split()[4:7] == ["0.500", "0.000", "0.125"]
    assert lines[4].split()[4:7] == ["-", "-", "-"]
    plain = _table(scene, poses, result, np.array([0]), 2).splitlines()
    assert "P(closure)" not in plain[1] and plain[2].split()[4:6] == ["1.250", "0.250"]


# --- calibrate: the gripper plane of both frames --------------------------------------------------


def test_calibrate_records_both_planes_and_warns_when_they_disagree(tmp_path):
    """The closed frame shows the gripper 2 mm farther than the open one (the camera moved): the
    command still writes the profile, with both depths, and prints the warning naming both."""
    from benchmarks.vision_accuracy import INTRINSICS, accuracy_scenes, plane_scenes
    from synthetic.render import render
    from softgrip_vision.frames import save_frame

    scene = accuracy_scenes(2)[1]
    opened, closed = plane_scenes(scene, "round", 1.1, closed_depth_shift_mm=2.0)
    open_dir, closed_dir = save_frame(render(opened, INTRINSICS), tmp_path / "open"), \
        save_frame(render(closed, INTRINSICS), tmp_path / "closed")
    output = tmp_path / "p.json"
    code, out, err = run_cli(["calibrate", str(closed_dir), "--open", str(open_dir), "--json", "-o", str(output)])
    assert code == 0, err
    depths = json.loads(out)["profile"]["vision"]["plane_depth_mm"]
    assert depths["closed"] - depths["open"] == pytest.approx(2.0, abs=0.3) and depths["used"] == "open"
    assert f"warning: the gripper plane is {depths['open']:.2f} mm deep in" in err
    assert f"but {depths['closed']:.2f} mm in" in err
