"""A griffe extension for the API reference (mkdocs.yml): the docstrings' doctests render as code.

The project's docstrings are Google style but title their doctests ``Example:`` (napoleon's
spelling), which griffe reads as an admonition of prose, and ``softgrip_vision.scene`` keeps its
doctest at the top level of the module docstring. Before griffe parses a docstring, this turns
``Example:`` and ``Example (a note):`` into ``Examples:`` sections and puts a top-level doctest in
a fenced ``pycon`` block, and Sphinx roles become code spans. The docstrings themselves, and so the doctests, are unchanged.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

_EXAMPLE = re.compile(r"^(?P<indent>\s*)Example(?:\s*\((?P<note>.*)\))?:\s*$")
# Sphinx roles (:func:`x`, :class:`~a.b`) as code spans (``~`` keeps the last name, as Sphinx does).
_ROLE = re.compile(r":(?:func|class|meth|mod|attr|data|exc|obj|const):`(?P<tilde>~?)(?P<target>[^`]+)`")


def _role(m: re.Match[str]) -> str:
    target = m.group("target")
    return f"`{target.rsplit('.', 1)[-1] if m.group('tilde') else target}`"


def _rewrite(text: str) -> str:
    out: list[str] = []
    fence = False
    for line in _ROLE.sub(_role, text).splitlines():
        m = _EXAMPLE.match(line)
        if m:
            note = m.group("note")
            line = f"{m.group('indent')}Examples:" + (f" {note}" if note else "")
        top_level_doctest = line.startswith(">>>")
        if top_level_doctest and not fence:
            out.append("```pycon")
            fence = True
        elif fence and (not line.strip() or line[0].isspace()) and not line.startswith(">>>"):
            out.append("```")
            fence = False
        out.append(line)
    if fence:
        out.append("```")
    return "\n".join(out)


class DoctestExamples(griffe.Extension):
    """Rewrite each object's docstring as described in the module docstring."""

    def on_object(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = _rewrite(obj.docstring.value)
