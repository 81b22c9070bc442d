"""Argument parsing, error reporting and exit codes of the ``softgrip`` command."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

# Exit codes: 0 success, 1 unexpected failure (a bug: traceback shown), 2 user error (bad input,
# message only), 130 interrupted, 141 output pipe closed early (as `yes | head` gives).
EXIT_USER_ERROR = 2
EXIT_BROKEN_PIPE = 141
EXIT_INTERRUPTED = 130


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
            stream.reconfigure(errors="backslashreplace")
        except (AttributeError, OSError, ValueError):
            pass


def _command_named(argv: Sequence[str]) -> str | None:
    """The command ``argv`` names (its first word that is not an option), if it is one of
    :data:`COMMANDS`; None otherwise (``softgrip --help``, a misspelt command: the full parser)."""
    words = [word for word in argv if not word.startswith("-")]
    return words[0] if words and words[0] in COMMANDS else None


def _interrupted_while_starting(signum, frame) -> None:
    """Ctrl-C while JAX and OpenCV are imported: nothing is written yet, so leave at once. (A
    KeyboardInterrupt raised in the middle of an extension module's import can leave it half set
    up, and the interpreter then crashes on the way out.)"""
    os.write(2, b"interrupted\n")
    os._exit(EXIT_INTERRUPTED)


def main(argv: Sequence[str] | None = None) -> int:
    # Ctrl-C at any moment, also while JAX and OpenCV are being imported (the first second or so),
    # ends with "interrupted" and exit 130, never a traceback. This module imports nothing heavy
    # at its top, so that the handler below covers those imports.
    import signal

    # equinox's runtime checks (inside optimistix's and lineax's solves) as NaNs, not host callbacks:
    # programs with callbacks never enter the compilation cache. Read once, when equinox is imported,
    # so it is set before anything below imports it; a value the user set (e.g. "raise") is kept.
    os.environ.setdefault("EQX_ON_ERROR", "nan")
    safe_streams()
    try:
        previous = signal.signal(signal.SIGINT, _interrupted_while_starting)
    except ValueError:  # not the main thread: signals are not ours to handle
        previous = None
    try:
        from softgrip_base import OutputRefusedError, SoftgripError

        words = sys.argv[1:] if argv is None else list(argv)
        parser = build_parser(only=_command_named(words))
        args = parser.parse_args(words)
        uses_jax = getattr(args, "uses_jax", True)  # every command but capture
        if uses_jax:  # imported here, under the handler above, as the command modules are
            from softgrip_cli import _pipeline
    finally:
        if previous is not None:  # from here Ctrl-C is a KeyboardInterrupt: writes clean up after it
            signal.signal(signal.SIGINT, previous)
    import warnings

    try:
        with warnings.catch_warnings():
            if uses_jax:
                _pipeline.configure_output(quiet=bool(args.quiet), verbose=bool(args.verbose))
                # Python warnings (e.g. a cache file ignored) as the command's own: one escaped line.
                warnings.showwarning = lambda message, *_, **__: _pipeline.warn(one_line(str(message)))
                _pipeline.enable_compilation_cache()  # compiled programs persist across runs
            return int(args.func(args) or 0)
    except (SoftgripError, OutputRefusedError) as err:
        if args.debug:
            raise
        print(f"softgrip {args.command}: error: {one_line(str(err))}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        # The reader of our standard output went away (`softgrip score ... | head`): not an error of
        # ours. Point stdout at /dev/null so that flushing it at exit cannot raise again.
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError):  # stdout without a file descriptor (captured, replaced)
            pass
        return EXIT_BROKEN_PIPE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
