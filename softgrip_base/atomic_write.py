"""The output policy of every ``softgrip`` command: files are replaced atomically, and never onto
something the user did not mean to lose.

Writing: the bytes go to a new hidden file in the target's folder (``.<name>.<random>.tmp``), are
flushed to the disk, and the temporary file is then renamed over the target with ``os.replace``,
which is atomic within one file system. Until the rename the target keeps its old content; after it,
the new. On any failure (an exception, a full disk, Ctrl-C) the temporary file is removed and the
target is untouched; a ``kill -9`` can leave only the hidden temporary file, never a partial target.

What is refused (:class:`OutputRefusedError`, naming the path and what to do), before anything is
written:

* a target that is one of the command's own inputs (compared by resolved path and by device and
  inode, so hard links and ``..`` spellings are caught; a frame folder's inputs are its
  ``color.png``, ``depth.png`` and ``intrinsics.json``, see :func:`frame_inputs`);
* a target that exists and is not a regular file: a folder, a FIFO, a device (``/dev/full``), a
  socket. These are never replaced, with or without ``force``;
* a target that is a symbolic link, unless ``force``: the policy is to **follow** a link only when
  asked. With ``force`` the file the link points to (its final target) is replaced atomically, the
  link itself is kept, and every other check applies to that final target;
* an existing file we may not write (read-only for us), unless ``force``.

An existing file's permission bits are kept (a 0600 file stays 0600); a new file is created like any
new file (mode 0o666 less the umask). The module imports neither JAX nor OpenCV.

Example:
    >>> import pathlib, tempfile
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "out.json"
    >>> write_atomic(path, b"{}\\n").read_bytes()
    b'{}\\n'
    >>> write_atomic(path, b"[]\\n", inputs=[path])
    Traceback (most recent call last):
    ...
    softgrip_base.atomic_write.OutputRefusedError: ... is one of this command's inputs; ...
"""

from __future__ import annotations

import contextlib
import os
import stat
import uuid
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO

#: The files of a frame folder (see ``softgrip_vision.frames``): what a command reading that frame must not
#: overwrite.
FRAME_FILES = ("color.png", "depth.png", "intrinsics.json")


class OutputRefusedError(ValueError):
    """An output path the policy refuses (an input, not a regular file, a link or read-only file
    without ``force``). A user error: the command line prints the message and exits with 2."""


def frame_inputs(folder: str | os.PathLike[str]) -> list[Path]:
    """The input files of frame ``folder``, and the folder itself."""
    folder = Path(folder)
    return [folder, *(folder / name for name in FRAME_FILES)]


def _identity(path: Path) -> tuple[str, tuple[int, int] | None]:
    try:
        st = os.stat(path)
        inode = (st.st_dev, st.st_ino)
    except OSError:
        inode = None
    return os.path.realpath(path), inode


def check_output(path: str | os.PathLike[str], *, inputs: Iterable[str | os.PathLike[str]] = (),
                 force: bool = False, what: str = "output") -> Path:
    """Apply the policy (module docstring) to ``path`` and return the path to write: ``path``
    itself, or with ``force`` the final target of a symbolic link.

    Args:
        path: the output file.
        inputs: the command's input files (and frame folders, see :func:`frame_inputs`).
        force: replace through a symbolic link, or a file that is read-only for us.
        what: how the message names the output (e.g. ``"-o"``, ``"--heatmap"``).

    Raises:
        OutputRefusedError: the policy refuses ``path``.
    """
    from softgrip_base.input_guard import os_error_reason

    given = Path(path)
    target = given
    try:
        is_link = given.is_symlink()
    except OSError as err:  # e.g. a name longer than the file system allows (ENAMETOOLONG)
        raise OutputRefusedError(f"{what} {given}: cannot write there: {os_error_reason(err)}") from None
    if is_link:
        if not force:
            raise OutputRefusedError(
                f"{what} {given} is a symbolic link (to {os.readlink(given)}); softgrip does not write through "
                f"links unless told to: give the real file, or add --force to replace the file the link points "
                f"to (the link is kept)")
        target = Path(os.path.realpath(given))
    real, inode = _identity(target)
    for item in inputs:
        item_real, item_inode = _identity(Path(item))
        if real == item_real or (inode is not None and inode == item_inode):
            raise OutputRefusedError(
                f"{what} {given} is one of this command's inputs; writing there would destroy it: choose another "
                f"file name")
    try:
        st = os.stat(target)
    except FileNotFoundError:
        return target
    except OSError as err:
        raise OutputRefusedError(f"{what} {given}: cannot check the file: {os_error_reason(err)}") from None
    if stat.S_ISDIR(st.st_mode):
        raise OutputRefusedError(f"{what} {given} is a folder, not a file: add a file name, e.g. {given / 'out'}")
    if not stat.S_ISREG(st.st_mode):
        kind = ("a FIFO" if stat.S_ISFIFO(st.st_mode) else "a device" if stat.S_ISCHR(st.st_mode) or
                stat.S_ISBLK(st.st_mode) else "a socket" if stat.S_ISSOCK(st.st_mode) else "not a regular file")
        raise OutputRefusedError(f"{what} {given} is {kind}; softgrip writes only regular files (it would be "
                                 f"replaced by one): give a file name, or write to stdout and redirect it")
    if not force and not os.access(target, os.W_OK):
        raise OutputRefusedError(f"{what} {given} is read-only; add --force to replace it anyway")
    return target


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike[str], *, inputs: Iterable[str | os.PathLike[str]] = (),
                force: bool = False, what: str = "output") -> Iterator[IO[bytes]]:
    """A binary file to write ``path``'s new content into; it replaces ``path`` atomically when the
    ``with`` block ends without an exception (the policy of the module docstring is checked first).
    For large outputs written piece by piece (streamed JSON).

    Raises:
        OutputRefusedError: the policy refuses ``path``.
        OSError: the folder is missing or not writable, the disk is full, ...; ``path`` is then
            unchanged and no temporary file is left.
    """
    target = check_output(path, inputs=inputs, force=force, what=what)
    try:
        mode = stat.S_IMODE(os.stat(target).st_mode)
    except FileNotFoundError:
        mode = None
    temporary = target.with_name(f".{target.name}.{uuid.uuid4().hex[:12]}.tmp")
    try:  # the file is created inside the try: a signal turned exception right after it removes it too
        fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        if mode is not None:
            os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        # The target may have become a link, folder or FIFO while we wrote: check again.
        check_output(path, inputs=inputs, force=force, what=what)
        os.replace(temporary, target)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def write_atomic(path: str | os.PathLike[str], data: bytes, *, inputs: Iterable[str | os.PathLike[str]] = (),
                 force: bool = False, what: str = "output") -> Path:
    """Write ``data`` to ``path`` atomically (replacing an existing regular file, keeping its mode)
    and return the path written (with ``force``, a link's final target).

    Raises:
        OutputRefusedError: the policy (module docstring) refuses ``path``.
        OSError: the folder is missing or not writable, the disk is full, ...; ``path`` is then
            unchanged and no temporary file is left. Callers turn it into their own
            :class:`~softgrip_jax.SoftgripError` naming the file.
    """
    inputs = list(inputs)
    target = check_output(path, inputs=inputs, force=force, what=what)
    with atomic_open(path, inputs=inputs, force=force, what=what) as handle:
        handle.write(data)
    return target


def probe_folder(folder: str | os.PathLike[str], *, what: str = "output") -> None:
    """Check that a file can be created in ``folder`` (or, if it does not exist yet, in its nearest
    existing parent, where it would be created) by creating and removing an empty hidden file
    there, before any work: permission bits alone do not tell (a process running as root
    passes ``os.access`` on a read-only folder, and a read-only mount refuses even root).

    Raises:
        OutputRefusedError: the file could not be created; the message names ``what``, the folder
            and the cause.
    """
    folder = Path(folder)
    while not folder.exists() and folder.parent != folder:  # not created yet: where it would be
        folder = folder.parent
    probe = folder / f".softgrip-probe.{uuid.uuid4().hex[:12]}.tmp"
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError as err:
        cause = err.strerror or str(err)
        raise OutputRefusedError(f"{what}: cannot create a file in the folder {folder} ({cause}); make it writable "
                                 f"or choose another folder") from None
    os.close(fd)
    probe.unlink(missing_ok=True)


# ---------------------------------------------------------------------------------------------
# Standard output: complete or absent


def _is_append(fd: int) -> bool:
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not a POSIX system
        return False
    return bool(fcntl.fcntl(fd, fcntl.F_GETFL) & os.O_APPEND)


class StdoutError(Exception):
    """Standard output failed while a command wrote its results (a full disk, ``/dev/full``, an
    I/O error, a descriptor not open for writing). Not an ``OSError``, so that a command's handling
    of its own files' errors cannot mistake it for one; the command line prints one line and exits
    with 2. (A reader that went away, ``BrokenPipeError``, is not this: it stays an ``OSError``.)"""


class GuardedStdout:
    """Standard output for one command: a text stream that wraps ``stream`` (``sys.stdout``) and
    turns a failed write or flush into :class:`StdoutError`, and :meth:`discard`, which makes the
    command's output absent rather than partial.

    When stdout is a regular file (``> out.json``) that stderr does not share, the offset where the
    command began writing is recorded, and :meth:`discard` truncates the file back to it. On a pipe
    or a terminal what was written stays written (the reader sees the nonzero exit status), but what
    is still buffered is dropped. Everything else (``encoding``, ``isatty``, ``fileno``, ...) is
    ``stream``'s own.
    """

    def __init__(self, stream) -> None:
        self.stream = stream
        self._start = None
        try:
            fd = stream.fileno()
            st = os.fstat(fd)
            shared = False
            try:
                err = os.fstat(2)
                shared = (err.st_dev, err.st_ino) == (st.st_dev, st.st_ino)
            except OSError:
                pass
            if stat.S_ISREG(st.st_mode) and not shared:
                stream.flush()  # anything written before the command belongs to the caller
                # Opened with >> (O_APPEND), every write goes to the end, whatever the offset says.
                append = _is_append(fd)
                self._start = (fd, os.fstat(fd).st_size if append else os.lseek(fd, 0, os.SEEK_CUR))
        except (AttributeError, OSError, ValueError):  # captured (io.StringIO), closed, ...
            pass

    def __getattr__(self, name: str):
        return getattr(self.stream, name)

    def _guarded(self, operation, *args):
        try:
            return operation(*args)
        except BrokenPipeError:
            raise
        except OSError as err:
            cause = err.strerror or str(err)
            raise StdoutError(f"cannot write the results to standard output ({cause}); nothing complete was "
                              f"written there: free some space or redirect it elsewhere (or use -o FILE)") from None

    def write(self, text: str) -> int:
        return self._guarded(self.stream.write, text)

    def writelines(self, lines) -> None:
        return self._guarded(self.stream.writelines, lines)

    def flush(self) -> None:
        return self._guarded(self.stream.flush)

    def discard(self) -> None:
        """Make this command's output absent: truncate a regular file back to where the command
        began, and point file descriptor 1 at ``/dev/null`` so that what is still buffered goes
        nowhere when the interpreter flushes it at exit (never a traceback there)."""
        try:
            fd = self.stream.fileno()
        except (AttributeError, OSError, ValueError):
            return
        if fd != 1:  # not the process's standard output (a stream a caller put in its place)
            return
        if self._start is not None and self._start[0] == fd:
            try:
                os.ftruncate(fd, self._start[1])
                os.lseek(fd, self._start[1], os.SEEK_SET)  # whoever writes next to the file continues there
            except OSError:
                pass
        try:
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, fd)
            os.close(null)
        except OSError:
            pass
