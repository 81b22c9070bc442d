"""Reading JSON written by people: every way the text can fail is a ``json.JSONDecodeError``.

``json.loads`` fails on some valid-looking user files with other exceptions: an integer of more
than 4300 digits raises ``ValueError`` (Python's integer-string limit), a document nested a few
thousand levels deep raises ``RecursionError``, and an integer of a few hundred digits loads but
then raises ``OverflowError`` wherever it meets a float (``math.isfinite``). The frame, profile
and pose-file readers use :func:`loads` instead, so each of them turns one exception type into
its own error naming the file.

Example:
    >>> loads('{"fx": 1' + '0' * 400 + '}')
    {'fx': inf}
    >>> loads('[' * 100000)
    Traceback (most recent call last):
    ...
    json.decoder.JSONDecodeError: nested too deeply to read: line 1 column 1 (char 0)
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from softgrip_base import input_guard

#: Integers with more digits than this are read as floats (+-inf beyond 1.8e308): no JSON field
#: of a frame, profile or pose file needs an integer that large.
_MAX_INT_DIGITS = 300


def _parse_int(text: str) -> int | float:
    return int(text) if len(text) <= _MAX_INT_DIGITS else float(text)


def loads(text: str) -> Any:
    """``json.loads(text)`` that raises only ``json.JSONDecodeError`` for text it cannot read.

    Integers too long for a float come back as ``inf`` or ``-inf`` (and fail the readers' "finite
    number" checks); nesting deeper than the interpreter's recursion limit is a decode error at
    line 1, column 1.
    """
    try:
        return json.loads(text, parse_int=_parse_int)
    except RecursionError:
        raise json.JSONDecodeError("nested too deeply to read", text, 0) from None


def read_text(path: Path, error: type[Exception], missing: str, what: str, *,
              max_bytes: int = input_guard.MAX_POSE_BYTES) -> str:
    """The UTF-8 text of the file a person named, for :func:`loads` or a CSV reader, read through
    the input guard (:func:`softgrip_base.input_guard.read_user_text`: a regular file of at most
    ``max_bytes`` bytes, a byte-order mark dropped). A missing file raises
    ``error("<path>: <missing>")``; one that cannot be read (a folder, a FIFO or device, too large,
    no permission, not UTF-8) an ``error`` naming ``what``, the path and the cause.

    Example:
        >>> read_text(Path("no-such.json"), ValueError, "no such pose file", "the pose file")
        Traceback (most recent call last):
        ...
        ValueError: no-such.json: no such pose file
    """
    return input_guard.read_user_text(path, what=what, max_bytes=max_bytes, error=error, missing=missing)
