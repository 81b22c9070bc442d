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
