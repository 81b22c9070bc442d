"""The output policy (softgrip_base.atomic_write): never onto inputs, devices, FIFOs or folders; links and
read-only files only with force; an existing file's mode kept; a failed write leaves nothing."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest
from hypothesis import given, settings, strategies as st

from softgrip_base.atomic_write import OutputRefusedError, atomic_open, check_output, frame_inputs, write_atomic


def test_refuses_each_input_however_it_is_spelled(tmp_path: Path) -> None:
    frame = tmp_path / "frame"
    frame.mkdir()
    for name in ("color.png", "depth.png", "intrinsics.json"):
        (frame / name).write_bytes(b"input")
    os.link(frame / "color.png", tmp_path / "hard.png")
    inputs = frame_inputs(frame)
    for target in (frame / "intrinsics.json", tmp_path / "frame" / ".." / "frame" / "depth.png",
                   tmp_path / "hard.png", frame):
        with pytest.raises(OutputRefusedError, match="inputs"):
            write_atomic(target, b"new", inputs=inputs, force=True)
    assert all((frame / n).read_bytes() == b"input" for n in ("color.png", "depth.png", "intrinsics.json"))


def test_refuses_folders_and_fifos_even_with_force(tmp_path: Path) -> None:
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    with pytest.raises(OutputRefusedError, match="FIFO"):
        write_atomic(fifo, b"x", force=True)
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    with pytest.raises(OutputRefusedError, match="folder"):
        write_atomic(tmp_path, b"x", force=True)


def test_refuses_a_device() -> None:
    with pytest.raises(OutputRefusedError, match="device"):
        check_output("/dev/null", force=True)


def test_a_link_is_refused_unless_forced_then_its_target_is_replaced_and_the_link_kept(tmp_path: Path) -> None:
    real, link = tmp_path / "real.json", tmp_path / "link.json"
    real.write_bytes(b"old")
    link.symlink_to(real.name)
    with pytest.raises(OutputRefusedError, match="symbolic link"):
        write_atomic(link, b"new")
    assert real.read_bytes() == b"old"
    assert write_atomic(link, b"new", force=True) == real.resolve()
    assert link.is_symlink() and real.read_bytes() == b"new"


@settings(max_examples=20, deadline=None)
@given(mode=st.sampled_from([0o600, 0o640, 0o644, 0o660, 0o604]))
def test_an_existing_files_mode_is_kept(tmp_path_factory, mode: int) -> None:
    path = tmp_path_factory.mktemp("mode") / "out.json"
    path.write_bytes(b"old")
    path.chmod(mode)
    write_atomic(path, b"new")
    assert stat.S_IMODE(path.stat().st_mode) == mode and path.read_bytes() == b"new"


def test_a_write_that_fails_midway_leaves_the_target_and_no_temporary_file(tmp_path: Path) -> None:
    path = tmp_path / "big.json"
    path.write_bytes(b"complete")
    with pytest.raises(KeyboardInterrupt):
        with atomic_open(path) as handle:
            handle.write(b"{" * 1000)
            raise KeyboardInterrupt  # as Ctrl-C in the middle of streaming a large result
    assert path.read_bytes() == b"complete"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["big.json"]


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write any file")
def test_a_read_only_file_needs_force(tmp_path: Path) -> None:
    path = tmp_path / "ro.json"
    path.write_bytes(b"old")
    path.chmod(0o444)
    with pytest.raises(OutputRefusedError, match="read-only"):
        write_atomic(path, b"new")
    write_atomic(path, b"new", force=True)
    assert path.read_bytes() == b"new"
