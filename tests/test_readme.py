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


def test_readme_scene_example_is_the_doctested_example_outputs_included():
    import softgrip_vision.scene

    blocks = re.findall(r"^```python\n(.*?)^```", README.read_text(encoding="utf-8"), flags=re.S | re.M)
    scene = [b for b in blocks if "frame_scene(" in b]
    assert len(scene) == 1, "the README has one frame-to-scene example"
    examples = doctest.DocTestParser().get_examples(softgrip_vision.scene.__doc__)
    assert _code(scene[0]) == _code("".join(e.source for e in examples))
    # Every output the doctest checks is shown in the README, as a comment, in the same order.
    shown = [line[2:] for line in scene[0].splitlines() if line.startswith("# ")]
    wanted = [line for e in examples for line in e.want.splitlines()]
    assert wanted and [line for line in shown if line in wanted] == wanted
