"""The names of the integer codes results hold (:class:`~softgrip_jax.ContactCase`,
:class:`~softgrip_jax.Status`, :class:`~softgrip_jax.RefineStatus`), for people, logs and JSON.

Results keep integer arrays (they are computed under ``jit`` and ``vmap``); the ``*_name``
properties of :class:`~softgrip_jax.Estimate`, :class:`~softgrip_jax.Score` and
:class:`~softgrip_jax.Refined` read them back as the enum members' lower-case names, as the
``softgrip`` JSON documents write them. They copy to the host: call them outside ``jit``.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence

import numpy as np
from jaxtyping import ArrayLike


def code_names(codes: ArrayLike | Sequence[int], kind: type[enum.IntEnum], *,
               unknown: str = "unknown({})") -> str | np.ndarray:
    """The lower-case member names of ``kind`` for integer ``codes``: a ``str`` for one code (a
    scalar), a numpy array of ``str`` of the same shape for an array.

    ``unknown`` is how a code ``kind`` does not have reads: a :meth:`str.format` template given the
    code, ``"unknown(<code>)"`` by default (the ``softgrip`` JSON documents write ``"status_<code>"``,
    :func:`softgrip_vision.documents.status_name`).

    Example:
        >>> from softgrip_jax import ContactCase, Status, code_names
        >>> code_names(2, ContactCase), code_names([0, 2], Status).tolist()
        ('tip_and_other', ['ok', 'base_outside_sdf'])
        >>> code_names(7, ContactCase), code_names(7, ContactCase, unknown="case_{}")
        ('unknown(7)', 'case_7')
    """
    values = np.asarray(codes)
    table = {int(member): member.name.lower() for member in kind}
    flat = [table.get(int(v), unknown.format(int(v))) for v in values.reshape(-1)]
    if values.ndim == 0:
        return flat[0]
    return np.array(flat, dtype=str).reshape(values.shape)
