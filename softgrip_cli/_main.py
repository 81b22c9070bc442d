"""Argument parsing, error reporting and exit codes of the ``softgrip`` command."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

# Exit codes: 0 success, 1 unexpected failure (a bug: traceback shown), 2 user error (bad input,
# message only; also standard output closed or full), 130 interrupted (Ctrl-C), 143 terminated
# (SIGTERM; 129 SIGHUP), 141 output pipe closed early (as `yes | head` gives).
EXIT_USER_ERROR = 2
EXIT_BROKEN_PIPE = 141
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143


#: The commands in the order of ``softgrip --help``, each the name of its module ``softgrip_cli.cmd_<name>``.
COMMANDS = ("demo", "calibrate", "estimate", "score", "capture")


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The ``softgrip`` parser with every command, or with the command ``only`` alone: the other
    commands' modules are then not imported (so ``softgrip capture`` does not import JAX)."""
    import importlib

    names = COMMANDS if only is None else (only,)
    modules = [importlib.import_module(f"softgrip_cli.cmd_{name}") for name in names]
    parser = argparse.ArgumentParser(
        prog="softgrip",
        description="Pre-touch deformation estimation of a soft gripper from one RGB-D frame.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {version()}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks of user errors too")
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="print results and errors only (no warnings, progress or summaries on stderr)")
    parser.add_argument("-v", "--verbose", action="store_true",
                        help="print details on stderr too (each frame's measured pose, object and plane)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module in modules:
        module.add_parser(sub)
    for command in sub.choices.values():  # -q and -v after the command too (softgrip estimate ... -q)
        command.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                             help="as softgrip -q: results and errors only on stdout and stderr")
        command.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                             help="as softgrip -v: details on stderr too")
    return parser


def version() -> str:
    """The installed distribution's version (the source tree's pyproject when not installed)."""
    from importlib.metadata import PackageNotFoundError, version as _version

    try:
        return _version("softgrip-jax")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree without installing
        return "unknown"


def one_line(text: str) -> str:
    """``text`` with line breaks and other unprintable characters (from file names, JSON keys, ...)
    escaped as in a Python string literal, so that an error message stays on one line
    (:func:`softgrip_base.input_guard.one_line`, which every message printed goes through)."""
    from softgrip_base.input_guard import one_line as _one_line

    return _one_line(text)


def safe_streams() -> None:
    """Make standard output and error unable to fail on a character their encoding lacks (an ASCII
    terminal with ``LC_ALL=C PYTHONIOENCODING=ascii``, a file name with bytes that were not UTF-8):
    such characters are written as backslash escapes (``\\xe9``) instead of raising
    ``UnicodeEncodeError``. JSON on stdout is ASCII anyway (``json.dumps`` escapes the rest).
    Streams that are not text files (captured, replaced) are left as they are."""
    for stream in (sys.stdout, sys.stderr):
        if getattr(stream, "errors", None) not in ("strict", "surrogateescape"):
            continue
        try:
            if hasattr(stream, "reconfigure"):  # a text file (io.TextIOWrapper)
                stream.reconfigure(errors="backslashreplace")
        except (AttributeError, OSError, ValueError):
            pass


def _command_named(argv: Sequence[str]) -> str | None:
    """The command ``argv`` names (its first word that is not an option), if it is one of
    :data:`COMMANDS`; None otherwise (``softgrip --help``, a misspelt command: the full parser)."""
    words = [word for word in argv if not word.startswith("-")]
    return words[0] if words and words[0] in COMMANDS else None


#: The signals that stop a command as Ctrl-C does: every output complete or absent, one line on
#: stderr, exit 128 + the signal's number (130 SIGINT, 143 SIGTERM, 129 SIGHUP).
STOP_SIGNALS = ("SIGINT", "SIGTERM", "SIGHUP")

#: The values equinox accepts in ``EQX_ON_ERROR`` (it raises a ValueError at import otherwise).
EQX_ON_ERROR_VALUES = ("raise", "nan", "breakpoint", "off")


class Terminated(BaseException):
    """SIGTERM or SIGHUP, raised in the main thread as Python raises KeyboardInterrupt for SIGINT:
    the ``with`` blocks and ``finally`` clauses on the way out run, so an output being written
    (``softgrip_base.atomic_write.atomic_open``) removes its temporary file. Derives from
    BaseException, as KeyboardInterrupt does: ``except Exception`` does not swallow it."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _stop_message(signum: int) -> bytes:
    import signal

    return b"interrupted\n" if signum == signal.SIGINT else b"terminated\n"


def _stopped_while_starting(signum, frame) -> None:
    """Ctrl-C, SIGTERM or SIGHUP while JAX and OpenCV are imported: nothing is written yet, so
    leave at once. (An exception raised in the middle of an extension module's import can leave it
    half set up, and the interpreter then crashes on the way out.)"""
    os.write(2, _stop_message(signum))
    os._exit(128 + signum)


def _raise_terminated(signum, frame) -> None:
    """SIGTERM or SIGHUP while a command runs: :class:`Terminated` in the main thread."""
    raise Terminated(signum)


def _set_handlers(handler, names=STOP_SIGNALS) -> dict:
    """Install ``handler`` for the signals ``names`` (those this platform has, and not ignored by
    whoever started us, e.g. ``nohup`` ignores SIGHUP) and return {signal: previous handler}; empty
    when not called from the main thread (signals are then not ours to handle)."""
    import signal

    previous = {}
    for name in names:
        signum = getattr(signal, name, None)
        if signum is None:
            continue
        try:
            if signal.getsignal(signum) == signal.SIG_IGN:
                continue
            previous[signum] = signal.signal(signum, handler)
        except ValueError:  # not the main thread
            return previous
    return previous


def _restore_handlers(previous: dict) -> None:
    import signal

    for signum, handler in previous.items():
        signal.signal(signum, handler if handler is not None else signal.SIG_DFL)


def _protect_stderr() -> None:
    """Standard error closed (``2>&-``): point file descriptor 2 at ``/dev/null``. Otherwise the
    next file opened (an output's temporary file) would get descriptor 2, and whatever a library
    writes to stderr would land in it; and ``print(file=sys.stderr)`` with no ``sys.stderr`` would
    print diagnostics into the results on stdout."""
    try:
        os.fstat(2)
    except OSError:
        try:
            null = os.open(os.devnull, os.O_WRONLY)
            if null != 2:
                os.dup2(null, 2)
                os.close(null)
        except OSError:  # pragma: no cover - no /dev/null
            return
    if sys.stderr is None:
        sys.stderr = open(2, "w", closefd=False)  # noqa: SIM115 - the process's own stderr, never closed


def _stdout_closed_message() -> str | None:
    """Why standard output cannot take the results, before any work: closed (``>&-``; Python
    then has no ``sys.stdout``) or not open for writing. None when it is usable (or not a file
    descriptor at all, e.g. captured)."""
    import errno

    if sys.stdout is None:
        return "standard output is closed (>&-); softgrip writes its results there: redirect it instead " \
               "(> FILE, or > /dev/null to discard them)"
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):
        return None
    try:
        os.fstat(fd)
    except OSError as err:
        if err.errno == errno.EBADF:
            return "standard output is closed (>&-); softgrip writes its results there: redirect it instead " \
                   "(> FILE, or > /dev/null to discard them)"
    return None


def check_equinox_environment() -> None:
    """Refuse, with one line naming the variable, an ``EQX_ON_ERROR`` or
    ``EQX_ON_ERROR_BREAKPOINT_FRAMES`` that equinox would reject with a traceback when imported."""
    from softgrip_base import SoftgripError

    value = os.environ.get("EQX_ON_ERROR")
    if value is not None and value not in EQX_ON_ERROR_VALUES:
        raise SoftgripError(f"the environment variable EQX_ON_ERROR={one_line(value)!r} is not one of equinox's "
                            f"values ({', '.join(EQX_ON_ERROR_VALUES)}): unset it or set "
                            f"one of them")
    if value == "breakpoint":
        # equinox then stops in a debugger inside the compiled solves, which softgrip runs as exported
        # programs: they cannot hold the debugger's host callback.
        raise SoftgripError("the environment variable EQX_ON_ERROR='breakpoint' (equinox's interactive debugger) "
                            "is not supported by the softgrip command, whose solvers run as compiled exported "
                            "programs: unset it, or set EQX_ON_ERROR=raise to stop on "
                            "the first failed check")
    frames = os.environ.get("EQX_ON_ERROR_BREAKPOINT_FRAMES")
    if frames is not None:
        try:
            int(frames)
        except ValueError:
            raise SoftgripError(f"the environment variable EQX_ON_ERROR_BREAKPOINT_FRAMES={one_line(frames)!r} is "
                                f"not a whole number: unset it or set a number of frames, e.g. 1") from None


def _check_xla_flags(error: type[Exception]) -> None:
    """Start JAX's backend in a child process under this environment; raise ``error`` naming
    ``XLA_FLAGS`` if XLA aborts it (an unknown or malformed flag)."""
    import subprocess

    try:
        child = subprocess.run([sys.executable, "-c", "import jax; jax.devices()"], capture_output=True,
                               text=True, errors="replace", timeout=300)
    except (OSError, subprocess.TimeoutExpired):
        return  # could not tell: the command goes on as before
    if child.returncode == 0:
        return
    lines = [line for line in child.stderr.splitlines() if "flag" in line.lower()] or child.stderr.splitlines()[-1:]
    said = one_line(lines[0].split("] ", 1)[-1]) if lines else f"exit {child.returncode}"
    raise error(f"the environment variable XLA_FLAGS={one_line(os.environ['XLA_FLAGS'])!r} stops XLA from "
                f"starting ({said}); remove the flag XLA does not know, or unset XLA_FLAGS")


def check_jax_environment(warn) -> dict:
    """Make JAX usable by a command whatever the environment says, before its first computation.

    * ``JAX_PLATFORMS`` (or ``JAX_PLATFORM_NAME``) naming a platform this machine lacks (``cuda``
      on a CPU machine): a SoftgripError naming the variable, its value and the fix.
    * ``JAX_DEBUG_NANS`` / ``JAX_DEBUG_INFS``: turned off for this command, with one warning
      (through ``warn``) naming the variable: invalid candidates are NaN and -inf by design, and
      would make JAX raise FloatingPointError.

    * ``XLA_FLAGS`` with a flag XLA does not know: XLA aborts the whole process when JAX starts its
      backend, so a command given ``XLA_FLAGS`` first starts JAX in a child process (a second or
      two) and, if that dies, is a SoftgripError quoting XLA's complaint and naming the variable.

    Returns the JAX settings changed, {name: previous value}, for :func:`restore_jax_settings`.
    """
    from softgrip_base import SoftgripError

    if os.environ.get("XLA_FLAGS", "").strip():
        _check_xla_flags(SoftgripError)
    import jax

    try:
        jax.devices()
    except (RuntimeError, AssertionError) as err:
        for name in ("JAX_PLATFORMS", "JAX_PLATFORM_NAME"):
            value = os.environ.get(name)
            if value:
                raise SoftgripError(f"the environment variable {name}={one_line(value)!r} names a platform JAX "
                                    f"cannot use on this machine; unset it (JAX then picks what is there) or set "
                                    f"{name}=cpu") from None
        raise err
    changed = {}
    for option, variable in (("jax_debug_nans", "JAX_DEBUG_NANS"), ("jax_debug_infs", "JAX_DEBUG_INFS")):
        if getattr(jax.config, option):
            changed[option] = True
            jax.config.update(option, False)
            given = os.environ.get(variable)
            source = f"{variable}={one_line(given)}" if given is not None else option
            warn(f"{source} is ignored for this command: invalid candidates are NaN or -inf by design (they come "
                 f"back valid: false), which JAX's {'NaN' if option.endswith('nans') else 'inf'} checks would "
                 f"stop on")
    return changed


def restore_jax_settings(changed: dict) -> None:
    """Undo :func:`check_jax_environment`'s changes (``main`` runs in-process too, e.g. in tests)."""
    if changed:
        import jax

        for option, value in changed.items():
            jax.config.update(option, value)


def main(argv: Sequence[str] | None = None) -> int:
    # Ctrl-C, SIGTERM and SIGHUP at any moment, also while JAX and OpenCV are being imported (the
    # first second or so), end with "interrupted" / "terminated" and exit 128 + the signal's number,
    # never a traceback, and leave no output partial or temporary file behind. This module imports
    # nothing heavy at its top, so that the handlers below cover those imports.
    import signal

    from softgrip_base.atomic_write import GuardedStdout, StdoutError

    _protect_stderr()
    closed = _stdout_closed_message()
    if closed is not None:  # before any work: the results would be lost
        print(f"softgrip: error: {closed}", file=sys.stderr)
        return EXIT_USER_ERROR
    safe_streams()
    # Every write to stdout through a guard: a full disk or an I/O error is one line and exit 2, and
    # an interrupted command's output is made absent (GuardedStdout.discard), never left partial.
    stdout = sys.stdout = GuardedStdout(sys.stdout)
    original = _set_handlers(_stopped_while_starting)
    jax_changed: dict = {}
    try:
        from softgrip_base import OutputRefusedError, SoftgripError

        words = sys.argv[1:] if argv is None else list(argv)
        named = _command_named(words)
        if named != "capture":  # every other command imports equinox, which reads them once
            try:
                check_equinox_environment()  # before equinox is imported: its own error is a traceback
            except SoftgripError as err:
                print(f"softgrip{'' if named is None else ' ' + named}: error: {one_line(str(err))}",
                      file=sys.stderr)
                return EXIT_USER_ERROR
        parser = build_parser(only=named)
        try:
            args = parser.parse_args(words)
        except StdoutError as err:  # --help or --version onto a full disk
            stdout.discard()
            print(f"softgrip: error: {one_line(str(err))}", file=sys.stderr)
            return EXIT_USER_ERROR
        uses_jax = getattr(args, "uses_jax", True)  # every command but capture
        if uses_jax:
            from softgrip_cli import _pipeline  # imported here, under the handlers above
        import warnings

        try:
            # From here Ctrl-C is a KeyboardInterrupt and SIGTERM / SIGHUP a Terminated: the outputs
            # being written clean up after them.
            for signum in original:
                signal.signal(signum, original[signum] if signum == signal.SIGINT else _raise_terminated)
            with warnings.catch_warnings():
                if uses_jax:
                    _pipeline.configure_output(quiet=bool(args.quiet), verbose=bool(args.verbose))
                    # Python warnings (e.g. a cache file ignored) as the command's own: one escaped line.
                    warnings.showwarning = lambda message, *_, **__: _pipeline.warn(one_line(str(message)))
                    jax_changed = check_jax_environment(_pipeline.warn)
                    _pipeline.enable_compilation_cache()  # compiled programs persist across runs
                code = int(args.func(args) or 0)
                stdout.flush()  # a full disk is found here, not at the interpreter's exit
                return code
        except (SoftgripError, OutputRefusedError) as err:
            if args.debug:
                raise
            print(f"softgrip {args.command}: error: {one_line(str(err))}", file=sys.stderr)
            return EXIT_USER_ERROR
        except StdoutError as err:
            stdout.discard()
            print(f"softgrip {args.command}: error: {one_line(str(err))}", file=sys.stderr)
            return EXIT_USER_ERROR
        except KeyboardInterrupt:
            stdout.discard()
            print("interrupted", file=sys.stderr)
            return EXIT_INTERRUPTED
        except Terminated as stop:
            stdout.discard()
            print(_stop_message(stop.signum).decode().strip(), file=sys.stderr)
            return 128 + stop.signum
        except BrokenPipeError:
            # The reader of our standard output went away (`softgrip score ... | head`): not an error of
            # ours. Point stdout at /dev/null so that flushing it at exit cannot raise again.
            try:
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            except (OSError, ValueError):  # stdout without a file descriptor (captured, replaced)
                pass
            return EXIT_BROKEN_PIPE
    finally:
        if sys.stdout is stdout:
            sys.stdout = stdout.stream
        restore_jax_settings(jax_changed)
        _restore_handlers(original)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
