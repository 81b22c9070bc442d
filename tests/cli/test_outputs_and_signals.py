"""Every output complete or absent: after SIGTERM, SIGHUP or Ctrl-C, on a full disk, with standard
output closed or full; output folders that take no file refused before any work; environment
variables that used to give tracebacks (JAX_PLATFORMS, JAX_DEBUG_NANS/INFS, EQX_ON_ERROR).

Most cases run ``softgrip capture`` with its work replaced by a stand-in (``FAKE`` below) in a
subprocess: capture imports neither JAX nor OpenCV, so each run takes about a second, and the
stand-in decides exactly when a signal arrives or what it writes. The one end-to-end run of a real
score under SIGTERM is marked slow.
"""

from __future__ import annotations

import contextlib
import errno
import io
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from softgrip_base.atomic_write import GuardedStdout, StdoutError, atomic_open, probe_folder, write_atomic
from softgrip_base import OutputRefusedError
from tests.cli.test_commands import DATA, PROFILE

ROOT = Path(__file__).resolve().parents[2]

#: A `softgrip` whose commands do what argv[1] says instead of their work (a script, run in a subprocess).
FAKE = r'''
import json, os, signal, sys, time
from softgrip_cli import _main

behaviour, rest = sys.argv[1], sys.argv[2:]

def work(args):
    if behaviour.startswith("write-then-"):  # an -o file being written when the signal comes
        from softgrip_base.atomic_write import atomic_open
        with atomic_open(args.out / "out.json", what="-o") as handle:
            handle.write(b"x" * 1_000_000)
            os.kill(os.getpid(), getattr(signal, behaviour.split("-")[-1]))
            for _ in range(500):
                time.sleep(0.01)
    elif behaviour.startswith("print-then-"):  # a JSON document half printed when the signal comes
        sys.stdout.write(json.dumps({"candidates": ["x" * 100] * 1000}))
        os.kill(os.getpid(), getattr(signal, behaviour.split("-")[-1]))
        for _ in range(500):
            time.sleep(0.01)
    elif behaviour == "print":
        print(json.dumps({"candidates": ["x" * 100] * 1000}))
    elif behaviour == "nan":  # a computation whose invalid value is NaN by design
        import jax, jax.numpy as jnp
        print(float(jax.jit(jnp.log)(-1.0)), os.environ["EQX_ON_ERROR"])
    return 0

original = _main.build_parser
def build_parser(only=None):
    parser = original(only)
    for action in parser._subparsers._group_actions:
        for command in action.choices.values():
            command.set_defaults(func=work)
    return parser
_main.build_parser = build_parser
sys.exit(_main.main(rest))
'''


def run_fake(tmp_path: Path, behaviour: str, argv: list[str], env: dict | None = None, **kwargs):
    script = tmp_path / "fake_softgrip.py"
    script.write_text(FAKE)
    environment = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    return subprocess.run([sys.executable, str(script), behaviour, *argv], cwd=ROOT, env=environment,
                          capture_output=kwargs.pop("capture_output", True), timeout=180, **kwargs)


def capture_argv(folder: Path) -> list[str]:
    return ["capture", "--bag", str(folder / "rec.db3"), "-o", str(folder)]


def one_error_line(stderr: bytes, *needles: str) -> str:
    text = stderr.decode()
    assert "Traceback" not in text, text
    lines = [line for line in text.splitlines() if line.strip()]
    assert len(lines) == 1, text
    assert all(needle in lines[0] for needle in needles), text
    return lines[0]


# ---------------------------------------------------------------------------------------------
# Signals


@pytest.mark.parametrize("name", ["SIGTERM", "SIGHUP", "SIGINT"])
def test_a_signal_while_an_output_is_written_leaves_no_temporary_file(tmp_path: Path, name: str,
                                                                      sigint_delivered) -> None:
    out = tmp_path / "out"
    out.mkdir()
    run = run_fake(tmp_path, f"write-then-{name}", capture_argv(out))
    signum = getattr(signal, name)
    assert run.returncode == 128 + signum, run.stderr
    one_error_line(run.stderr, "interrupted" if name == "SIGINT" else "terminated")
    assert sorted(os.listdir(out)) == [], "a temporary or partial file was left"


def test_a_signal_while_a_document_is_printed_leaves_a_redirected_stdout_as_it_was(tmp_path: Path) -> None:
    target = tmp_path / "results.json"
    target.write_bytes(b"earlier line\n")
    with open(target, "ab") as stdout:  # >> results.json
        run = run_fake(tmp_path, "print-then-SIGTERM", capture_argv(tmp_path), capture_output=False,
                       stdout=stdout, stderr=subprocess.PIPE)
    assert run.returncode == 143
    one_error_line(run.stderr, "terminated")
    assert target.read_bytes() == b"earlier line\n"


def test_sigterm_while_starting_exits_143_without_a_traceback() -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    process = subprocess.Popen([sys.executable, "-m", "softgrip_cli", "estimate", str(DATA / "circle_open"),
                                "--profile", str(PROFILE)], stderr=subprocess.PIPE, stdout=subprocess.PIPE, env=env,
                               cwd=ROOT)
    time.sleep(0.5)
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 143, err
    one_error_line(err, "terminated")


@pytest.mark.slow
def test_sigterm_during_a_real_score_leaves_no_temporary_file(tmp_path: Path) -> None:
    """The report's reproducer: ``score -o out.json`` over a large grid, SIGTERM while the document
    is being written (the moment its hidden temporary file appears)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    process = subprocess.Popen([sys.executable, "-m", "softgrip_cli", "score", str(DATA / "circle_open"), "--profile",
                                str(PROFILE), "--method", "geometric", "--grid=-10:10:20,-60:-30:20,-0.1:0.1:10",
                                "--top", "0", "-o", str(tmp_path / "out.json")], stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, env=env, cwd=ROOT, text=True)
    deadline = time.monotonic() + 900
    while process.poll() is None and time.monotonic() < deadline:
        if any(name.endswith(".tmp") for name in os.listdir(tmp_path)):
            process.send_signal(signal.SIGTERM)
            break
        time.sleep(0.01)
    _, err = process.communicate(timeout=300)
    assert process.returncode == 143, err
    assert "Traceback" not in err and err.strip().splitlines()[-1] == "terminated", err  # a summary may come first
    assert os.listdir(tmp_path) == []


# ---------------------------------------------------------------------------------------------
# Standard output


def test_stdout_on_a_full_device_is_one_error_line_and_exit_2(tmp_path: Path) -> None:
    with open("/dev/full", "wb") as full:
        run = run_fake(tmp_path, "print", capture_argv(tmp_path), capture_output=False, stdout=full,
                       stderr=subprocess.PIPE)
        version = subprocess.run([sys.executable, "-m", "softgrip_cli", "--version"], cwd=ROOT, stdout=full,
                                 stderr=subprocess.PIPE, env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=120)
    assert run.returncode == 2
    one_error_line(run.stderr, "standard output", "No space left on device")
    assert version.returncode == 2
    one_error_line(version.stderr, "standard output")


def test_closed_stdout_is_refused_before_any_work(tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    run = run_fake(tmp_path, "write-then-SIGTERM", capture_argv(out), capture_output=False,
                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, preexec_fn=lambda: os.close(1))
    assert run.returncode == 2
    one_error_line(run.stderr, "standard output is closed", "redirect")
    assert os.listdir(out) == []  # the work (which would write out.json) never ran


def test_closed_stderr_never_puts_diagnostics_into_stdout(tmp_path: Path) -> None:
    run = subprocess.run([sys.executable, "-m", "softgrip_cli", "capture", "--bag", str(tmp_path / "none.db3"), "-o",
                          str(tmp_path / "out")], cwd=ROOT, capture_output=True, timeout=120,
                         env={**os.environ, "PYTHONPATH": str(ROOT)}, preexec_fn=lambda: os.close(2))
    assert run.returncode == 2 and run.stdout == b"", run.stdout


def test_guarded_stdout_turns_a_failed_write_into_stdout_error() -> None:
    class Full(io.StringIO):
        def write(self, text):
            raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(StdoutError, match="No space left on device"):
        GuardedStdout(Full()).write("{}")

    class Gone(io.StringIO):
        def flush(self):
            raise BrokenPipeError(errno.EPIPE, "Broken pipe")

    with pytest.raises(BrokenPipeError):  # a reader gone stays what it was (exit 141, not an error)
        GuardedStdout(Gone()).flush()


# ---------------------------------------------------------------------------------------------
# A full disk under -o


@pytest.fixture
def disk_full_after(monkeypatch):
    """Files opened by ``atomic_open`` (its hidden ``.tmp`` files) take 100 bytes, then fail with
    ENOSPC, as a full file system does."""
    real_fdopen = os.fdopen

    class FullFile:
        def __init__(self, handle):
            self.handle, self.written = handle, 0

        def write(self, data):
            self.written += len(data)
            if self.written > 100:
                raise OSError(errno.ENOSPC, "No space left on device")
            return self.handle.write(data)

        def __getattr__(self, name):
            return getattr(self.handle, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.handle.close()

    def fdopen(fd, *args, **kwargs):
        handle = real_fdopen(fd, *args, **kwargs)
        name = os.path.basename(os.readlink(f"/proc/self/fd/{fd}"))
        return FullFile(handle) if name.startswith(".") and name.endswith(".tmp") else handle

    monkeypatch.setattr(os, "fdopen", fdopen)


def test_a_full_disk_while_writing_leaves_neither_file_nor_temporary(tmp_path: Path, disk_full_after) -> None:
    target = tmp_path / "out.json"
    with pytest.raises(OSError, match="No space"):
        write_atomic(target, b"x" * 1000)
    with pytest.raises(OSError, match="No space"):
        with atomic_open(target) as handle:
            for _ in range(10):
                handle.write(b"y" * 50)
    assert os.listdir(tmp_path) == []


def test_calibrate_on_a_full_disk_exits_2_and_leaves_no_file(tmp_path: Path, disk_full_after) -> None:
    from tests.cli.test_commands import run_cli

    code, _, err = run_cli(["calibrate", str(DATA / "calib_closed"), "--open", str(DATA / "calib_open"), "-o",
                            str(tmp_path / "p.json")])
    assert code == 2 and "Traceback" not in err, err
    assert "p.json" in err and "No space left on device" in err, err
    assert os.listdir(tmp_path) == []


# ---------------------------------------------------------------------------------------------
# Output folders that take no file: refused before any work


@pytest.fixture
def read_only_folder(tmp_path: Path, monkeypatch) -> Path:
    """A folder in which no file can be created, even by root (as a read-only mount): creating a
    file there fails with EROFS. (Tests run as root here, where mode 0555 would not stop a write.)"""
    folder = tmp_path / "ro"
    folder.mkdir()
    real_open = os.open

    def refusing_open(path, flags, *args, **kwargs):
        if Path(os.fspath(path)).parent == folder and flags & os.O_CREAT:
            raise OSError(errno.EROFS, "Read-only file system", os.fspath(path))
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", refusing_open)
    return folder


def test_probe_folder_finds_a_folder_that_takes_no_file(read_only_folder: Path) -> None:
    with pytest.raises(OutputRefusedError, match=r"-o x: cannot create a file in the folder .*ro \(Read-only"):
        probe_folder(read_only_folder, what="-o x")
    probe_folder(read_only_folder.parent)  # its parent does
    probe_folder(read_only_folder.parent / "new" / "deeper")  # not there yet: where it would be made
    assert sorted(os.listdir(read_only_folder.parent)) == ["ro"]


def test_probe_folder_as_root_on_a_folder_the_kernel_refuses() -> None:
    """Without monkeypatching: /sys refuses new files even to root (where os.access says yes)."""
    folder = Path("/sys/kernel")
    try:
        fd = os.open(folder / ".softgrip-test", os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError:
        pass
    else:  # pragma: no cover - a system where /sys takes files
        os.close(fd)
        os.unlink(folder / ".softgrip-test")
        pytest.skip("/sys/kernel takes new files here")
    with pytest.raises(OutputRefusedError, match="cannot create a file"):
        probe_folder(folder, what="-o")


def _never(*args, **kwargs):
    raise AssertionError("the work started before the output folder was checked")


@pytest.mark.parametrize(("argv", "work"), [
    (["calibrate", "--fit", str(DATA / "calib_closed"), "--open", str(DATA / "calib_open"), "-o", "{ro}/p.json"],
     ("softgrip_cli.cmd_calibrate", "_fit")),
    (["calibrate", str(DATA / "calib_closed"), "--open", str(DATA / "calib_open"), "-o", "{ro}/p.json"],
     ("softgrip_cli.cmd_calibrate", "_one_frame")),
    (["score", str(DATA / "circle_open"), "--profile", str(PROFILE), "-o", "{ro}/s.json"],
     ("softgrip_cli._pipeline", "frame_scene")),
    (["estimate", str(DATA / "circle_open"), "--profile", str(PROFILE), "-o", "{ro}/e.json"],
     ("softgrip_cli._pipeline", "frame_scene")),
    (["estimate", str(DATA / "circle_open"), "--profile", str(PROFILE), "--overlay-dir", "{ro}"],
     ("softgrip_cli._pipeline", "frame_scene")),
    (["demo", "-o", "{ro}"], ("softgrip_cli.cmd_demo", "_calibrate")),
])
def test_an_output_folder_that_takes_no_file_is_refused_before_any_work(read_only_folder: Path, monkeypatch,
                                                                        argv: list[str], work) -> None:
    import importlib

    from tests.cli.test_commands import run_cli

    monkeypatch.setattr(importlib.import_module(work[0]), work[1], _never)
    code, _, err = run_cli([word.replace("{ro}", str(read_only_folder)) for word in argv])
    assert code == 2 and "Traceback" not in err, err
    assert "cannot create a file" in err and str(read_only_folder) in err, err


# ---------------------------------------------------------------------------------------------
# Environment variables


def test_jax_platforms_naming_an_absent_platform_is_one_line(tmp_path: Path) -> None:
    run = run_fake(tmp_path, "nan", ["estimate", str(DATA / "circle_open"), "--profile", str(PROFILE)],
                   env={"JAX_PLATFORMS": "cuda"})
    assert run.returncode == 2
    one_error_line(run.stderr, "JAX_PLATFORMS='cuda'", "JAX_PLATFORMS=cpu")


def test_xla_flags_with_a_flag_xla_does_not_know_is_one_line_not_an_abort(tmp_path: Path) -> None:
    # XLA aborts the process (SIGABRT, a fatal log line) on an unknown flag when the backend starts.
    run = run_fake(tmp_path, "nan", ["estimate", str(DATA / "circle_open"), "--profile", str(PROFILE)],
                   env={"XLA_FLAGS": "--xla_no_such_flag=1"})
    assert run.returncode == 2, run.stderr
    one_error_line(run.stderr, "XLA_FLAGS='--xla_no_such_flag=1'", "Unknown flag")


@pytest.mark.parametrize(("name", "value", "named"), [
    ("EQX_ON_ERROR", "foo", "raise, nan, breakpoint, off"),
    ("EQX_ON_ERROR_BREAKPOINT_FRAMES", "many", "whole number"),
    ("EQX_ON_ERROR", "breakpoint", "EQX_ON_ERROR=raise"),
])
def test_an_equinox_variable_equinox_rejects_is_one_line(tmp_path: Path, name: str, value: str, named: str) -> None:
    run = run_fake(tmp_path, "nan", ["estimate", str(DATA / "circle_open"), "--profile", str(PROFILE)],
                   env={name: value})
    assert run.returncode == 2
    one_error_line(run.stderr, f"{name}={value!r}", named)


def test_jax_debug_nans_and_infs_are_turned_off_with_one_warning_each(tmp_path: Path) -> None:
    run = run_fake(tmp_path, "nan", ["estimate", str(DATA / "circle_open"), "--profile", str(PROFILE)],
                   env={"JAX_DEBUG_NANS": "1", "JAX_DEBUG_INFS": "true", "EQX_ON_ERROR": "raise"})
    assert run.returncode == 0, run.stderr
    assert run.stdout.decode().split() == ["nan", "raise"]  # computed; the user's EQX_ON_ERROR kept
    lines = run.stderr.decode().splitlines()
    assert len(lines) == 2 and "Traceback" not in run.stderr.decode(), lines
    assert "JAX_DEBUG_NANS=1 is ignored" in lines[0] and "JAX_DEBUG_INFS=true is ignored" in lines[1], lines


def test_check_jax_environment_restores_the_settings_it_changed() -> None:
    import jax

    from softgrip_cli._main import check_jax_environment, restore_jax_settings

    warnings: list[str] = []
    with contextlib.ExitStack() as stack:
        stack.callback(jax.config.update, "jax_debug_nans", jax.config.jax_debug_nans)
        jax.config.update("jax_debug_nans", True)
        changed = check_jax_environment(warnings.append)
        assert not jax.config.jax_debug_nans and len(warnings) == 1 and "NaN" in warnings[0]
        restore_jax_settings(changed)
        assert jax.config.jax_debug_nans
