"""The README's Python planner example is the example in ``softgrip_jax.score``'s docstring, which
the doctest run (``--doctest-modules``, pyproject's pytest settings) executes and checks."""

from __future__ import annotations

import doctest
import re
from pathlib import Path

import softgrip_jax

README = Path(__file__).resolve().parents[1] / "README.md"


def _code(source: str) -> list[str]:
    """Non-empty lines of Python source, comments and trailing blanks dropped."""
    lines = []
    for line in source.splitlines():
        code = re.sub(r"\s*#.*$", "", line).rstrip()
        if code:
            lines.append(code)
    return lines


def test_readme_planner_is_the_doctested_example():
    blocks = re.findall(r"^```python\n(.*?)^```", README.read_text(encoding="utf-8"), flags=re.S | re.M)
    planner = [b for b in blocks if "refine(" in b]
    assert len(planner) == 1, "the README has one planner example (score, refine, contacts)"
    examples = doctest.DocTestParser().get_examples(softgrip_jax.score.__doc__)
    doctested = "".join(e.source for e in examples if not e.source.startswith("bool(refined"))
    assert _code(planner[0]) == _code(doctested)
