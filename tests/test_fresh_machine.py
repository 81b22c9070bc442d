"""A new user's first run: the README's set-up in an empty virtual environment, then ``softgrip demo``.

The repository's git-tracked files (what a clone or a CI checkout has, nothing the developer left
lying around) are copied to a temporary folder; the Makefile's ``setup-demo`` target (what ``make demo`` installs:
the core, no optional backend) builds a new ``.venv`` there with the machine's base Python (not this test's virtual environment, so the new
one starts empty); then ``.venv/bin/softgrip demo`` runs from the copy, as ``make demo`` would.
Packages come from pip's usual sources (torch 2.13.0, pinned by constraints.txt, is a CPU build on
this machine's disk), so nothing of gigabytes is downloaded.

The demo uses the machine's own compilation cache (``~/.cache/softgrip-jax/jax``, which the CLI
tests' in-process demo fills earlier in the same run): it holds compiled XLA programs, not installed
code, and with it the demo takes about a minute instead of four or five of compilation.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SCENES = ("circle", "square", "star_a")  # data/*_open, the calibration pair aside
CASES = {"none", "tip", "other", "tip_and_other"}


def _base_python() -> str:
    """The Python this test's virtual environment was made from (or this one, outside a venv)."""
    base = getattr(sys, "_base_executable", None) or sys.executable
    if Path(base).resolve() == Path(sys.executable).resolve() and sys.prefix != sys.base_prefix:
        cfg = Path(sys.prefix) / "pyvenv.cfg"
        home = dict(line.split(" = ", 1) for line in cfg.read_text().splitlines() if " = " in line).get("home")
        if home:
            base = str(Path(home) / f"python{sys.version_info.major}.{sys.version_info.minor}")
    return base


def _tracked_files() -> list[str]:
    if shutil.which("git") is None or not (REPO / ".git").exists():
        pytest.skip("needs a git checkout of the repository (its tracked files are what a new user gets)")
    out = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, check=True, capture_output=True).stdout
    return [name for name in out.decode().split("\0") if name]


def _clean_env() -> dict[str, str]:
    """The machine's environment without this test's virtual environment or source paths."""
    env = {k: v for k, v in os.environ.items()
           if k not in {"VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME", "JAX_COMPILATION_CACHE_DIR", "SOFTGRIP_JAX_CACHE",
                        "XLA_FLAGS", "JAX_ENABLE_X64", "MAKEFLAGS", "MFLAGS", "MAKELEVEL"}}
    venv_bin = str(Path(sys.prefix) / "bin")
    env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep) if p != venv_bin)
    return env


@pytest.fixture
def work(tmp_path):
    """The copy's folder; its virtual environment (about 1.5 GB) is removed afterwards, as pytest
    keeps the last few runs' temporary folders."""
    folder = tmp_path / "softgrip-jax"
    yield folder
    shutil.rmtree(folder / ".venv", ignore_errors=True)


@pytest.mark.slow
def test_readme_setup_then_demo_on_a_fresh_copy(tmp_path, work):
    if shutil.which("make") is None:
        pytest.skip("needs make (the README's set-up is `make demo` / `make test`)")
    files = _tracked_files()
    for name in files:
        source = REPO / name
        if source.is_file():  # a tracked file deleted in the working tree is not part of the checkout
            (work / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, work / name)
    assert not (work / ".venv").exists()
    env = _clean_env()
    python = _base_python()

    t0 = time.perf_counter()
    setup = subprocess.run(["make", "setup-demo", f"PYTHON={python}"], cwd=work, env=env,
                           capture_output=True, text=True, timeout=900)
    t_setup = time.perf_counter() - t0
    assert setup.returncode == 0, f"make setup failed:\n{setup.stdout[-3000:]}\n{setup.stderr[-3000:]}"
    softgrip = work / ".venv" / "bin" / "softgrip"
    assert softgrip.is_file()
    # The new venv runs the copy, not this checkout.
    where = subprocess.run([str(work / ".venv" / "bin" / "python"), "-c",
                            "import softgrip_jax, softgrip_vision, softgrip_calib, softgrip_cli; print(softgrip_jax.__file__)"],
                           cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert where.returncode == 0, where.stderr
    assert Path(where.stdout.strip()).resolve().is_relative_to(work.resolve())
    # The demo's environment has none of the optional backends.
    extras = subprocess.run([str(work / ".venv" / "bin" / "python"), "-c",
                             "import importlib.util as u; print([m for m in ('torch', 'kornia', 'pyrealsense2', "
                             "'matplotlib', 'pytest') if u.find_spec(m)])"],
                            cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert extras.stdout.strip() == "[]", extras.stdout + extras.stderr

    t0 = time.perf_counter()
    demo = subprocess.run([str(softgrip), "demo", "--json"], cwd=work, env=env,
                          capture_output=True, text=True, timeout=900)
    t_demo = time.perf_counter() - t0
    print(f"fresh machine: make setup {t_setup:.0f} s, softgrip demo {t_demo:.0f} s")
    assert demo.returncode == 0, f"softgrip demo failed:\n{demo.stdout[-3000:]}\n{demo.stderr[-3000:]}"
    assert "Traceback" not in demo.stderr

    out = work / "demo-out"
    summary = json.loads((out / "summary.json").read_text())
    assert json.loads(demo.stdout) == summary  # --json prints exactly what summary.json holds
    expected = (["profile.json"] + [f"estimate_{s}.png" for s in SCENES]
                + ["heatmap_circle.png", "refined_circle.png", "summary.json"])
    assert sorted(summary["files"]) == sorted(expected)
    assert sorted(p.name for p in out.iterdir()) == sorted(expected)  # nothing else, no partial files
    for name in expected:
        if name.endswith(".png"):
            assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
            assert (out / name).stat().st_size > 10_000

    profile = json.loads((out / "profile.json").read_text())
    assert set(profile["fingers"]) == {"left", "right"}
    calibration = summary["calibration"]
    assert calibration["n_links"] == 20
    for side in ("left", "right"):
        finger = calibration["fingers"][side]
        assert 0.1 < finger["theta_entire"] < 1.5 and 20 < finger["length_mm"] < 100

    assert summary["method"] == "mechanics"  # the project default
    assert [s["scene"] for s in summary["scenes"]] == list(SCENES)
    for scene in summary["scenes"]:
        assert scene["valid"]
        for finger in scene["fingers"]:
            assert finger["case"] in CASES - {"none"}  # every sample scene closes onto its object
            assert len(finger["joints_mm"]) == 21
        for side in ("left", "right"):  # estimate vs the observed closure (eq. 10), as tests/cli checks
            errors = scene["errors_vs_observed"][side]
            assert errors["tip_mm"] < 3.0 and errors["mid_mm"] < 3.0

    score = summary["score"]
    assert score["scene"] == "circle" and score["n_valid"] > 0 and score["n_candidates"] >= score["n_valid"]
    assert score["best"]["valid"] and score["best"]["score"] is not None
    refined = summary["refine"]
    assert refined["score"] is not None and refined["score"] >= refined["start_score"] - 1e-6
    assert "demo finished" in demo.stderr
