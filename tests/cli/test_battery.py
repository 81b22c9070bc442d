"""The reliability battery's classifier (benchmarks/reliability_battery.py): synthetic outcomes, then
deliberately broken fake commands run through the battery's own runners, then (slow) a few kinds
of the real battery that pass today."""

from __future__ import annotations

import importlib.util
import json
import os
import pickle
import signal
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def battery():
    spec = importlib.util.spec_from_file_location("reliability_battery", ROOT / "benchmarks" / "reliability_battery.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up while it runs
    spec.loader.exec_module(module)
    return module


def outcome(battery, obs, **kind):
    return battery.classify(battery.Kind("k", ["score", "--json"], **kind), obs)[0]


# -- synthetic outcomes -----------------------------------------------------------------------------


def test_a_clean_refusal_and_a_clean_success(battery) -> None:
    Obs = battery.Observation
    assert outcome(battery, Obs(2, "", "softgrip score: error: --mu nan: expected ...\n"), message="mu") == "clean"
    assert outcome(battery, Obs(0, '{"valid": true}'), expect="ok") == "clean"
    assert outcome(battery, Obs(0, '{"valid": false}'), expect="flag") == "clean"
    assert outcome(battery, Obs(2, "", "error: x\n"), expect="either") == "clean"


@pytest.mark.parametrize(("obs", "expected"), [
    (dict(code=1, stderr="boom"), "traceback"),
    (dict(code=2, stderr="Traceback (most recent call last):\n  ...\nKeyError: 'x'\n"), "traceback"),
    (dict(code=2, escaped=True), "traceback"),
    (dict(code=-11), "crash"),
    (dict(code=139), "crash"),
    (dict(code=None), "hang"),
    (dict(code=2, new_files=[("out/.out.json.1a2b.tmp", 2048)]), "partial file"),
    (dict(code=2, new_files=[("out/out.json", 0)]), "partial file"),
    (dict(code=0, stdout='{"valid": false, "frames": [', new_files=[]), "partial file"),
    (dict(code=2, bad_json=["out/out.json"]), "partial file"),
    (dict(code=2, lost=["frame/color.png"]), "data lost"),
    (dict(code=0, stdout='{"frames": [{"valid": true}]}'), "silent result"),
    (dict(code=0, valid_in_files=True), "silent result"),
    (dict(code=2, stderr="warning: scene\x1b[31m\nerror: x\n"), "unsanitised"),
    (dict(code=2, stderr="warning: a\nINJECTED line\n"), "unsanitised"),
    (dict(code=0), "wrong outcome"),
    (dict(code=2, stderr="error: the header is wrong\n"), "wrong outcome"),
])
def test_each_failure_is_named(battery, obs, expected) -> None:
    assert outcome(battery, battery.Observation(**obs), expect="flag" if "valid" in obs.get("stdout", "") or
                   obs.get("valid_in_files") else "refuse", message="mu|header" if expected != "wrong outcome"
                   or obs["code"] == 0 else "semicolon") == expected


def test_the_worst_failure_wins_and_every_problem_is_listed(battery) -> None:
    obs = battery.Observation(1, "", f"Traceback (most recent call last):\nValueError: {battery.SECRET}\n",
                              new_files=[("o/x.json", 0)], marker=True)
    kind = battery.Kind("k", ["score"], secret=battery.SECRET, marker=Path("m"))
    first, problems = battery.classify(kind, obs)
    assert first == "code executed"
    assert [p.split(":")[0] for p in problems] == ["code executed", "secret printed", "traceback", "partial file"]


def test_signals_the_battery_sent_are_expected_others_are_crashes(battery) -> None:
    kind = battery.Kind("k", ["score"], expect="signal", send=(signal.SIGTERM, 1.0))
    for code in (0, 130, 143, -signal.SIGTERM):
        assert battery.classify(kind, battery.Observation(code))[0] == "clean", code
    assert battery.classify(kind, battery.Observation(-signal.SIGSEGV))[0] == "crash"
    assert battery.classify(kind, battery.Observation(134))[0] == "crash"


def test_a_late_refusal_and_an_ignored_input_are_named(battery) -> None:
    late = battery.Kind("k", ["calibrate"], message="/sys", max_seconds=15.0)
    assert battery.classify(late, battery.Observation(2, "", "error: /sys: read-only", seconds=50.0))[0] == "wrong outcome"
    assert battery.classify(late, battery.Observation(2, "", "error: /sys: read-only", seconds=1.0))[0] == "clean"
    doc = json.dumps({"frames": [{"fingers": [{"joints_mm": [[0, 1]]}]}]})
    same = battery.Kind("d", ["estimate", "--json"], expect="ok", check=battery.same_estimate("base"))
    assert battery.classify(same, battery.Observation(0, doc), {"base": doc})[0] == "silent result"
    other = doc.replace("[0, 1]", "[0, 2]")
    assert battery.classify(same, battery.Observation(0, other), {"base": doc})[0] == "clean"


# -- broken fake commands through the battery's runners ---------------------------------------------


def run_kind(battery, tmp_path, kind):
    return battery.observe(kind, {**os.environ, "PYTHONPATH": str(ROOT)}, tmp_path, {})


def test_in_process_calls_that_raise_leave_files_or_run_a_payload(battery, tmp_path: Path) -> None:
    from softgrip_base import SoftgripError

    out = tmp_path / "out"
    out.mkdir()

    def refuse():
        raise SoftgripError("--mu nan: expected a number")

    def bug():
        return {}["missing"]

    def leave_empty():
        (out / "result.json").touch()

    def leave_temp():
        (out / ".result.json.0123.tmp").write_text("{")

    marker = tmp_path / "marker"

    def unpickle():
        pickle.loads(pickle.dumps(battery._Payload(marker)))

    for call, expected in ((refuse, "clean"), (bug, "traceback"), (leave_empty, "partial file"),
                           (leave_temp, "partial file"), (unpickle, "code executed")):
        kind = battery.Kind(call.__name__, call=call, expect="refuse" if call is refuse else "either", watch=[out],
                            marker=marker, message="mu" if call is refuse else "")
        assert run_kind(battery, tmp_path, kind)[0] == expected, call.__name__


@pytest.mark.parametrize(("script", "expected"), [
    ("import os, signal; os.kill(os.getpid(), signal.SIGSEGV)", "crash"),
    ("raise KeyError('x')", "traceback"),
    ("import sys, time; print('{\"valid\": tr', end='', flush=True); sys.exit(0)", "partial file"),
    ("import sys; print('{\"valid\": true}'); sys.exit(0)", "silent result"),
    ("import sys; sys.stderr.write('error: x\\n'); sys.exit(2)", "clean"),
    ("import time; time.sleep(30)", "hang"),
])
def test_subprocess_commands_are_classified(battery, tmp_path: Path, script: str, expected: str) -> None:
    kind = battery.Kind("fake", ["--json"], subprocess=True, program=[sys.executable, "-c", script], timeout=3.0)
    assert run_kind(battery, tmp_path, kind)[0] == expected


def test_a_closed_stdout_and_a_file_size_limit_reach_the_command(battery, tmp_path: Path) -> None:
    probe = ("import os, sys, resource; print(os.fstat(1) if False else '', end='');"
             "sys.stderr.write(f'{sys.stdout is None} {resource.getrlimit(resource.RLIMIT_FSIZE)[0]}'); sys.exit(2)")
    kind = battery.Kind("fake", [], subprocess=True, stdout="closed", fsize=64 * 1024,
                        program=[sys.executable, "-c", probe], timeout=10.0)
    _, _, obs = run_kind(battery, tmp_path, kind)
    assert obs.stderr == f"True {64 * 1024}", obs.stderr


# -- the real battery: kinds that pass today ----------------------------------------------------------


@pytest.mark.slow
def test_kinds_that_pass_today_are_clean(battery, capsys) -> None:
    code = battery.main(["--only", "-o onto", "--json"])
    report = json.loads(capsys.readouterr().out)
    assert report["kinds"] >= 4
    assert code == 0 and report["counts"]["clean"] == report["kinds"], report["results"]
