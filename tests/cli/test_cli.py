"""The `softgrip` command: user errors without tracebacks, --debug (its outputs: test_commands.py)."""

import pytest

from softgrip_cli import main


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


def test_version_prints_the_distributions_version(capsys):
    from importlib.metadata import version

    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0
    assert capsys.readouterr().out.strip() == f"softgrip {version('softgrip-jax')}"


@pytest.mark.parametrize("command", [["demo"], ["capture"], ["estimate", "F", "--profile", "P"],
                                     ["score", "F", "--profile", "P"], ["calibrate", "C", "--open", "O"]])
def test_every_command_that_writes_takes_o_and_output_and_q_v_after_it(command):
    from softgrip_cli._main import build_parser

    parser = build_parser()
    for flag in ("-o", "--output"):
        args = parser.parse_args([*command, flag, "target", "-q", "-v"])
        assert str(getattr(args, "out", None) or args.output) == "target" and args.quiet and args.verbose


def test_q_silences_warnings_and_v_prints_details(capsys):
    from softgrip_cli import _pipeline

    try:
        _pipeline.configure_output(quiet=True, verbose=True)
        _pipeline.warn("w"), _pipeline.note("n"), _pipeline.info("i")
        assert capsys.readouterr().err == "" and _pipeline.quiet()
        _pipeline.configure_output(quiet=False, verbose=True)
        _pipeline.warn("w"), _pipeline.note("n"), _pipeline.info("i")
        assert capsys.readouterr().err == "warning: w\nn\ni\n"
        _pipeline.configure_output()
        _pipeline.info("i")
        assert capsys.readouterr().err == "" and not _pipeline.quiet()
    finally:
        _pipeline.configure_output()
