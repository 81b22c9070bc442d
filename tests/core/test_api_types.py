"""The public entry points given the wrong type of object (None, a numpy array or a list for the
SDF; a profile's dict, a path or the profile itself for the gripper) raise SoftgripError naming the
argument, what it got and what to pass: never an AttributeError or TypeError from deep inside.
The checks run in Python before tracing, so they hold under jax.jit too; no test compiles.

The test run checks annotations at run time (jaxtyping's import hook, pyproject's addopts), which
refuses these calls with its own TypeCheckError before the function body runs; the tests call the
functions without that wrapper (``inspect.unwrap``), as a user's program runs them, and one test
runs a call in a plain interpreter."""

from __future__ import annotations

import inspect
import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import softgrip_jax as sg
from softgrip_calib.profile import ProfileError, check_profile, load_profile, save_profile, to_gripper
from tests.cli.test_commands import DATA, PROFILE

ROOT = DATA.parent


class _Plain:
    """softgrip_jax's functions without the test run's type-checking wrapper."""

    def __getattr__(self, name):
        return inspect.unwrap(getattr(sg, name))


api = _Plain()
FINGER = sg.FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=6)
GRIPPER = sg.Gripper(FINGER, FINGER, 50.0)
DISC = sg.PolygonSDF.regular((0.0, 35.0), 9.0, n_vertices=16)
POSE = jnp.zeros(3)
BASE = jnp.zeros(2)
PROFILE_DICT = json.loads(PROFILE.read_text())

BAD_SDFS = [(None, "got None"), (np.zeros((4, 4)), "got a numpy array of shape (4, 4)"), ([1.0, 2.0], "got a list")]

SDF_ENTRY_POINTS = {
    "estimate": lambda sdf: api.estimate(FINGER, sdf, BASE),
    "estimate_in_frame": lambda sdf: api.estimate_in_frame(FINGER, sdf, sg.FingerFrame.hanging_from(BASE)),
    "estimate_batch": lambda sdf: api.estimate_batch(FINGER, sdf, BASE[None]),
    "estimate_grasp": lambda sdf: api.estimate_grasp(GRIPPER, sdf, POSE),
    "estimate_grasp_batch": lambda sdf: api.estimate_grasp_batch(GRIPPER, sdf, POSE[None]),
    "predict_contact": lambda sdf: api.predict_contact(FINGER, sdf, BASE),
    "score": lambda sdf: api.score(GRIPPER, sdf, POSE[None]),
    "score_pose": lambda sdf: api.score_pose(GRIPPER, sdf, POSE),
    "refine": lambda sdf: api.refine(GRIPPER, sdf, POSE),
}

GRIPPER_ENTRY_POINTS = {
    "estimate_grasp": lambda g: api.estimate_grasp(g, DISC, POSE),
    "estimate_grasp_batch": lambda g: api.estimate_grasp_batch(g, DISC, POSE[None]),
    "score": lambda g: api.score(g, DISC, POSE[None]),
    "score_pose": lambda g: api.score_pose(g, DISC, POSE),
    "refine": lambda g: api.refine(g, DISC, POSE),
    "finger_frames": lambda g: api.finger_frames(g, POSE),
}


@pytest.mark.parametrize("entry", sorted(SDF_ENTRY_POINTS))
@pytest.mark.parametrize(("bad", "got"), BAD_SDFS, ids=["None", "ndarray", "list"])
def test_a_wrong_sdf_names_the_argument_and_what_to_pass(entry: str, bad, got: str) -> None:
    with pytest.raises(sg.SoftgripError) as info:
        SDF_ENTRY_POINTS[entry](bad)
    message = str(info.value)
    assert message.startswith(f"sdf: {got};"), message
    assert "SDFGrid" in message and "PolygonSDF" in message and "\n" not in message


@pytest.mark.parametrize("entry", sorted(GRIPPER_ENTRY_POINTS))
def test_a_profile_dict_as_the_gripper_says_how_to_make_one(entry: str) -> None:
    with pytest.raises(sg.SoftgripError, match=r"^gripper: got a dict with keys .*load_profile\(path\)\.gripper\(\)"):
        GRIPPER_ENTRY_POINTS[entry](PROFILE_DICT)


def test_a_profile_object_as_the_gripper_says_to_take_its_gripper() -> None:
    with pytest.raises(sg.SoftgripError, match=r"got a CalibrationProfile \(a calibration profile\); pass its "
                                               r"\.gripper\(\)"):
        api.score(load_profile(PROFILE), DISC, POSE[None])


@pytest.mark.parametrize("bad", [None, {"length": 50.0}, GRIPPER])
def test_a_wrong_finger_names_the_argument(bad) -> None:
    with pytest.raises(sg.SoftgripError, match=r"^finger: got .*; pass a softgrip_jax\.FingerModel"):
        api.estimate(bad, DISC, BASE)


def test_the_checks_hold_under_jit_and_let_good_arguments_trace() -> None:
    with pytest.raises(sg.SoftgripError, match="^sdf: got None"):
        jax.jit(api.estimate)(FINGER, None, BASE)
    with pytest.raises(sg.SoftgripError, match="^sdf: got an array of shape"):  # traced: an array, not an SDF
        jax.jit(api.predict_contact)(FINGER, jnp.zeros((4, 4)), BASE)
    shape = jax.eval_shape(api.predict_contact, FINGER, DISC, BASE)  # traced, not compiled
    assert shape.p_o1.shape == (2,)


@pytest.mark.parametrize(("bad", "fix"), [
    (PROFILE_DICT, "CalibrationProfile.from_dict(d)"),
    (str(PROFILE), "load_profile(path)"),
    (PROFILE, "load_profile(path)"),
    (None, "load_profile(path)"),
])
def test_profile_functions_given_a_dict_or_path_say_how_to_load_it(bad, fix: str, tmp_path) -> None:
    for call in (lambda: to_gripper(bad), lambda: save_profile(bad, tmp_path / "p.json"), lambda: check_profile(bad)):
        with pytest.raises(ProfileError) as info:
            call()
        assert str(info.value).startswith("profile: got ") and fix in str(info.value), info.value
    assert not (tmp_path / "p.json").exists()


def test_frame_scene_given_a_profile_dict_says_how_to_load_it() -> None:
    from softgrip_vision.scene import FrameSceneError, frame_scene

    with pytest.raises(FrameSceneError, match=r"^profile: got a dict with keys .*load_profile\(path\)"):
        frame_scene(DATA / "circle_open", PROFILE_DICT)


def test_a_plain_interpreter_gets_the_softgrip_error_too() -> None:
    code = ("import json, softgrip_jax as sg, jax.numpy as jnp\n"
            "disc = sg.PolygonSDF.regular((0.0, 35.0), 9.0)\n"
            f"profile = json.load(open({str(PROFILE)!r}))\n"
            "try:\n"
            "    sg.score(profile, disc, jnp.zeros((1, 3)))\n"
            "except sg.SoftgripError as err:\n"
            "    print(str(err).split(';')[0])\n")
    run = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert run.stdout.startswith("gripper: got a dict with keys 'version'"), run.stdout + run.stderr
