"""The one way a file a person named is read: regular files only, never more than a limit, and
every message about it safe to print.

Every input of a ``softgrip`` command (a pose file, a calibration profile, a frame's
``intrinsics.json``, ``color.png`` and ``depth.png``) goes through :func:`read_user_file`:

* the file is opened with ``O_NONBLOCK``, so a FIFO (named pipe) never blocks, and the *opened*
  file is checked with ``fstat`` (no gap between the check and the read): a folder, a FIFO, a
  device such as ``/dev/zero``, or a socket is refused with a message naming the path and what it
  is;
* a file larger than the limit of its kind (:data:`MAX_POSE_BYTES`, :data:`MAX_PROFILE_BYTES`,
  :data:`MAX_INTRINSICS_BYTES`, :data:`MAX_FRAME_FILE_BYTES`) is refused, and at most limit + 1
  bytes are ever read (a file that grows while it is read is caught too);
* an operating-system failure is one line naming the path and the cause, e.g. a folder or file
  name longer than the file system allows (``ENAMETOOLONG``).

Standard input (``--poses -``) stays a stream, read with the same limit by :func:`read_user_stream`.
Text is decoded by :func:`decode_user_text` as UTF-8 with or without a byte-order mark (Excel's
"CSV UTF-8" writes one); a file that is not UTF-8 is named without quoting its bytes.

:func:`one_line` makes any text safe to print on a terminal: control characters (ESC, newlines,
...), and bytes that were not valid UTF-8 in a file name (Python's ``surrogateescape``), are
escaped as in a Python string literal. Every message the command line prints goes through it.

Like the rest of :mod:`softgrip_base`, this module imports the standard library only.

Example:
    >>> import tempfile
    >>> folder = tempfile.mkdtemp()
    >>> read_user_file(folder, what="the pose file", max_bytes=10, error=ValueError)
    Traceback (most recent call last):
    ...
    ValueError: the pose file .../tmp... is a folder, not a file: give the file itself
    >>> one_line("frame\\x1b[31m\\nred\\udcff")
    'frame\\\\x1b[31m\\\\nred\\\\udcff'
"""

from __future__ import annotations

import errno
import os
import stat
from typing import BinaryIO

#: Largest pose file (bytes): a million poses (the most one call takes) as CSV are about 20 MiB; the
#: rest leaves room for ``softgrip score --json`` output read back as poses.
MAX_POSE_BYTES = 256 * 1024 * 1024
#: Largest calibration profile (bytes); a profile of hundreds of calibration frames is under 1 MB.
MAX_PROFILE_BYTES = 16 * 1024 * 1024
#: Largest ``intrinsics.json`` of a frame (bytes); a real one is a few hundred bytes.
MAX_INTRINSICS_BYTES = 1024 * 1024
#: Largest image file of a frame (bytes): a 1920x1080 16-bit PNG without compression is about 4 MB.
MAX_FRAME_FILE_BYTES = 256 * 1024 * 1024

_CHUNK = 1 << 20


def file_kind(mode: int) -> str:
    """What a file of ``st_mode`` ``mode`` is, for a message (``"a FIFO (named pipe)"``, ...)."""
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "a regular file" if stat.S_ISREG(mode) else "not a regular file"


def os_error_reason(err: OSError) -> str:
    """The cause of an operating-system failure on a path, in words a user can act on."""
    if err.errno == errno.ENAMETOOLONG:
        return ("a folder or file name in the path is too long (ENAMETOOLONG: at most 255 bytes per name): "
                "rename it or use a shorter path")
    if err.errno == errno.ELOOP:
        return "too many levels of symbolic links (ELOOP): a link points to itself, directly or not"
    if err.errno in (errno.EACCES, errno.EPERM):
        return f"permission denied ({errno.errorcode[err.errno]}): check the file's owner and mode"
    name = errno.errorcode.get(err.errno or 0)
    return f"{err.strerror or err}" + (f" ({name})" if name else "")


def read_user_file(path: str | os.PathLike[str], *, what: str, max_bytes: int, error: type[Exception],
                   missing: str | None = None) -> bytes:
    """The bytes of the regular file ``path`` that a person named, at most ``max_bytes`` of them.

    Args:
        path: the file (a symbolic link is followed to the file it names).
        what: how messages name the file, e.g. ``"the pose file"`` or ``"--profile"``.
        max_bytes: the largest size accepted (bytes); at most ``max_bytes + 1`` bytes are read.
        error: the exception type raised, called with one line of text.
        missing: what a missing file's message says after ``"<path>: "`` (default: ``"no such file"``).

    Raises:
        error: ``path`` is missing, not a regular file (folder, FIFO, device, socket), larger than
            ``max_bytes``, or cannot be opened or read; the message names the path and the cause.
    """
    name = os.fspath(path)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(name, flags)
    except FileNotFoundError:
        raise error(f"{name}: {missing or 'no such file'}") from None
    except IsADirectoryError:  # some systems refuse to open a folder at all
        raise error(f"{what} {name} is a folder, not a file: give the file itself") from None
    except OSError as err:
        raise error(f"cannot open {what} {name}: {os_error_reason(err)}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = file_kind(st.st_mode)
            hint = "give the file itself" if stat.S_ISDIR(st.st_mode) else "save the data to a file and give that"
            raise error(f"{what} {name} is {kind}, not a file: {hint}")
        if st.st_size > max_bytes:
            raise error(_too_large(what, name, st.st_size, max_bytes))
        os.set_blocking(fd, True)
        chunks, size = [], 0
        while size <= max_bytes:
            chunk = os.read(fd, min(_CHUNK, max_bytes + 1 - size))
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
    except OSError as err:
        raise error(f"cannot read {what} {name}: {os_error_reason(err)}") from None
    finally:
        os.close(fd)
    if size > max_bytes:  # it grew while being read
        raise error(_too_large(what, name, size, max_bytes))
    return b"".join(chunks)


def check_user_file(path: str | os.PathLike[str], *, what: str, error: type[Exception],
                    missing: str | None = None) -> os.stat_result:
    """Check, without reading it, that ``path`` is a regular file (for a file that another library
    opens, e.g. a RealSense recording); its ``os.stat`` result.

    Raises:
        error: as :func:`read_user_file` (missing, not a regular file, a path that cannot be opened).
    """
    name = os.fspath(path)
    try:
        st = os.stat(name)
    except (FileNotFoundError, NotADirectoryError):
        raise error(f"{name}: {missing or 'no such file'}") from None
    except OSError as err:
        raise error(f"cannot open {what} {name}: {os_error_reason(err)}") from None
    if not stat.S_ISREG(st.st_mode):
        raise error(f"{what} {name} is {file_kind(st.st_mode)}, not a file: give the file itself")
    return st


def read_user_stream(stream: BinaryIO, *, what: str, max_bytes: int, error: type[Exception]) -> bytes:
    """At most ``max_bytes`` bytes of a binary ``stream`` (standard input), to its end.

    Raises:
        error: the stream holds more than ``max_bytes`` bytes, or cannot be read.
    """
    try:
        data = stream.read(max_bytes + 1)
    except OSError as err:
        raise error(f"cannot read {what}: {os_error_reason(err)}") from None
    if len(data) > max_bytes:
        raise error(f"{what} holds more than {_size(max_bytes)}, more than softgrip reads there: is it the "
                    f"right input? (split it)")
    return data


def decode_user_text(data: bytes, name: str, *, what: str, error: type[Exception]) -> str:
    """``data`` as UTF-8 text, a leading byte-order mark dropped (Excel's "CSV UTF-8").

    Raises:
        error: ``data`` is not UTF-8; the message names the byte offset, never the bytes.
    """
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        binary = b"\0" in data[:4096]
        hint = ("it looks like a binary file" if binary else
                       "save it as UTF-8 (e.g. Excel's \"CSV UTF-8\")")
        raise error(f"{what} {name} is not UTF-8 text (invalid byte at offset {err.start}): "
                    f"{hint}") from None


def read_user_text(path: str | os.PathLike[str], *, what: str, max_bytes: int, error: type[Exception],
                   missing: str | None = None) -> str:
    """:func:`read_user_file` decoded by :func:`decode_user_text`."""
    data = read_user_file(path, what=what, max_bytes=max_bytes, error=error, missing=missing)
    return decode_user_text(data, os.fspath(path), what=what, error=error)


def one_line(text: str) -> str:
    """``text`` with line breaks, ESC and every other unprintable character (also the lone
    surrogates that stand for bytes of a file name that were not UTF-8) escaped as in a Python
    string literal: safe to print on a terminal, and on one line."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def ascii_text(text: str) -> str:
    """:func:`one_line` with every non-ASCII character escaped too (``\\xe9``, ``\\u4e2d``): for
    text drawn with OpenCV's Hershey fonts, which draw ASCII only."""
    return one_line(text).encode("ascii", "backslashreplace").decode("ascii")


def _size(count: int) -> str:
    return f"{count / 2**20:.0f} MiB" if count >= 2**20 else f"{count} bytes"


def _too_large(what: str, name: str, size: int, max_bytes: int) -> str:
    return (f"{what} {name} is {_size(size)}, more than such a file can be ({_size(max_bytes)}): "
            f"is it the right file?")
