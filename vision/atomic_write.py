"""Replacing a file so that a failure never leaves it truncated: profiles, overlays, JSON summaries.

The bytes go to a new hidden file in the target's folder (``.<name>.<random>.tmp``, created like
any new file: mode 0o666 less the umask), are flushed to the disk, and the temporary file is then
renamed over the target with ``os.replace``, which is atomic within one file system. Until the
rename the target keeps its old content; after it, the new. On any failure the temporary file is
removed and the target is untouched.

Example:
    >>> import pathlib, tempfile
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "out.json"
    >>> write_atomic(path, b"{}\\n").read_bytes()
    b'{}\\n'
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path


def write_atomic(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (replacing an existing file) and return the path.

    Raises:
        OSError: the folder is missing or not writable, the disk is full, ``path`` is a folder, ...;
            ``path`` is then unchanged and no temporary file is left. Callers turn it into their own
            :class:`~softgrip_jax.SoftgripError` naming the file.
    """
    target = Path(path)
    temporary = target.with_name(f".{target.name}.{uuid.uuid4().hex[:12]}.tmp")
    fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, target)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    return target
