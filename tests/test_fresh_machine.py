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


# ---------------------------------------------------------------------------------------------
# The built wheel alone: what `pip install softgrip-jax` gives a user outside any checkout.

RUNTIME_PACKAGES = ("softgrip_base", "softgrip_jax", "softgrip_vision", "softgrip_calib", "softgrip_cli")


def _readme_python_blocks() -> list[str]:
    """The README's ```python blocks, as the README holds them now."""
    import re

    text = (REPO / "README.md").read_text(encoding="utf-8")
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def _build_wheel(source: Path, out: Path) -> Path:
    """``pip wheel`` of ``source`` (the git-tracked files, copied) into ``out``; the wheel's path."""
    built = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                            "--disable-pip-version-check", "-q", "-w", str(out), str(source)],
                           cwd=source, capture_output=True, text=True, timeout=600)
    assert built.returncode == 0, built.stdout[-3000:] + built.stderr[-3000:]
    wheels = list(out.glob("softgrip_jax-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0]


def _copy_tracked(to: Path) -> None:
    for name in _tracked_files():
        source = REPO / name
        if source.is_file():
            (to / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, to / name)


@pytest.mark.slow
def test_the_wheel_holds_schemas_sample_frames_and_py_typed(tmp_path):
    import zipfile

    source = tmp_path / "src"
    _copy_tracked(source)
    wheel = _build_wheel(source, tmp_path / "dist")
    names = set(zipfile.ZipFile(wheel).namelist())
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert tops == set(RUNTIME_PACKAGES)  # no `synthetic`, `tests`, `data` or `schemas` at the top level
    for package in RUNTIME_PACKAGES:
        assert f"{package}/py.typed" in names
    for kind in ("estimate", "score", "intrinsics", "profile"):
        assert f"softgrip_base/schemas/{kind}.schema.json" in names
    frames = ["calib", "circle", "square", "star_a"]
    for frame in frames:
        for state in ("open", "closed"):
            for part in ("color.png", "depth.png", "intrinsics.json"):
                assert f"softgrip_vision/sample_data/{frame}_{state}/{part}" in names
    assert "softgrip_vision/sample_data/sample_profile.json" in names
    assert "softgrip_vision/sample_data/truth.json" not in names


@pytest.mark.slow
def test_a_fresh_venv_with_only_the_wheel_runs_the_demo_and_the_readme_examples(tmp_path):
    """A new venv (the machine's base Python, no system site-packages) with the built wheel and mypy,
    nothing else of this checkout: ``softgrip demo`` and every README Python block run from a folder
    outside the checkout, and mypy (default settings) finds no error in the blocks or in a file that
    imports every public module."""
    source = tmp_path / "src"
    _copy_tracked(source)
    wheel = _build_wheel(source, tmp_path / "dist")
    env = _clean_env()
    venv = tmp_path / "venv"
    made = subprocess.run([_base_python(), "-m", "venv", str(venv)], env=env, capture_output=True, text=True,
                          timeout=300)
    assert made.returncode == 0, made.stderr
    python = str(venv / "bin" / "python")
    try:
        t0 = time.perf_counter()
        install = subprocess.run([python, "-m", "pip", "install", "--quiet", "--disable-pip-version-check",
                                  "--no-compile", "-c", str(source / "constraints.txt"), str(wheel), "mypy"],
                                 env=env, capture_output=True, text=True, timeout=900)
        t_install = time.perf_counter() - t0
        assert install.returncode == 0, install.stdout[-3000:] + install.stderr[-3000:]
        run = tmp_path / "elsewhere"  # not the checkout, not the copy: the installed wheel is all there is
        run.mkdir()
        where = subprocess.run([python, "-c", "import softgrip_vision, softgrip_vision.samples as s; "
                                "print(softgrip_vision.__file__); print(s.sample_data_dir())"],
                               cwd=run, env=env, capture_output=True, text=True, timeout=120)
        assert where.returncode == 0, where.stderr
        package_file, data_dir = where.stdout.split()
        assert Path(package_file).resolve().is_relative_to(venv.resolve())
        assert Path(data_dir).resolve().is_relative_to(venv.resolve()) and Path(data_dir).name == "sample_data"

        t0 = time.perf_counter()
        demo = subprocess.run([str(venv / "bin" / "softgrip"), "demo", "--json", "--out", "demo-out"], cwd=run,
                              env=env, capture_output=True, text=True, timeout=900)
        t_demo = time.perf_counter() - t0
        print(f"wheel alone: install {t_install:.0f} s, softgrip demo {t_demo:.0f} s")
        assert demo.returncode == 0, f"softgrip demo failed:\n{demo.stdout[-3000:]}\n{demo.stderr[-3000:]}"
        assert "Traceback" not in demo.stderr
        summary = json.loads(demo.stdout)
        assert Path(summary["data"]).resolve() == Path(data_dir).resolve()
        assert [s["scene"] for s in summary["scenes"]] == list(SCENES)
        assert all(s["valid"] for s in summary["scenes"])
        assert (run / "demo-out" / "summary.json").is_file()

        blocks = _readme_python_blocks()
        assert blocks, "the README has Python examples"
        files = []
        t0 = time.perf_counter()
        for i, block in enumerate(blocks):
            path = run / f"readme_example_{i}.py"
            path.write_text(block, encoding="utf-8")
            files.append(path.name)
            ran = subprocess.run([python, path.name], cwd=run, env=env, capture_output=True, text=True,
                                 timeout=900)
            assert ran.returncode == 0, f"README block {i} failed:\n{block}\n{ran.stderr[-3000:]}"
            # What it prints is what the README shows, as `# ` comments.
            shown = {line[2:].strip() for line in block.splitlines() if line.startswith("# ")}
            for line in ran.stdout.splitlines():
                assert line.strip() in shown, f"README block {i} printed {line!r}, which the README does not show"
        t_examples = time.perf_counter() - t0

        # Every public module (no leading underscore) imported, so that mypy reads them all from the wheel.
        modules = subprocess.run([python, "-c", "import importlib.util, pkgutil\n"
                                  f"for p in {RUNTIME_PACKAGES!r}:\n"
                                  "    print(p)\n"
                                  "    path = importlib.util.find_spec(p).submodule_search_locations\n"
                                  "    for m in pkgutil.iter_modules(path):\n"
                                  "        if not m.name.startswith('_') and not m.ispkg: print(p + '.' + m.name)\n"],
                                 cwd=run, env=env, capture_output=True, text=True, timeout=120)
        assert modules.returncode == 0, modules.stderr
        public = [m for m in modules.stdout.split() if m != "softgrip_vision.sample_data"]
        assert "softgrip_vision.scene" in public and "softgrip_calib.profile" in public
        (run / "public_api.py").write_text("".join(f"import {m}\n" for m in public), encoding="utf-8")
        t0 = time.perf_counter()
        checked = subprocess.run([python, "-m", "mypy", "--no-incremental", "public_api.py", *files], cwd=run,
                                 env=env, capture_output=True, text=True, timeout=900)
        t_mypy = time.perf_counter() - t0
        assert checked.returncode == 0, f"mypy:\n{checked.stdout[-5000:]}{checked.stderr[-2000:]}"
        assert "Success: no issues found" in checked.stdout
        print(f"wheel alone: {len(blocks)} README blocks {t_examples:.0f} s, mypy {t_mypy:.0f} s")
    finally:
        shutil.rmtree(venv, ignore_errors=True)  # about 1 GB
