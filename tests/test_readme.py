"""The README's Python planner example is the example in ``softgrip_jax.score``'s docstring, which
the doctest run (``--doctest-modules``, pyproject's pytest settings) executes and checks; the same
holds for the frame-to-scene example. The examples are looked for in the README and in the pages
under docs/ (wherever an edit moves them, each stays the doctested one), and every relative link of
the README and the pages leads to a file of the repository."""

from __future__ import annotations

import doctest
import re
from pathlib import Path

import softgrip_jax

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
# The README and the documentation pages; docs/api holds mkdocstrings directives, no examples.
PAGES = [README, *sorted((ROOT / "docs").glob("*.md"))]


def _python_blocks() -> list[str]:
    """The ```python blocks of the README and of the pages under docs/."""
    blocks = []
    for page in PAGES:
        blocks += re.findall(r"^```python\n(.*?)^```", page.read_text(encoding="utf-8"), flags=re.S | re.M)
    return blocks


def _code(source: str) -> list[str]:
    """Non-empty lines of Python source, comments and trailing blanks dropped."""
    lines = []
    for line in source.splitlines():
        code = re.sub(r"\s*#.*$", "", line).rstrip()
        if code:
            lines.append(code)
    return lines


def test_readme_planner_is_the_doctested_example():
    planner = [b for b in _python_blocks() if "refine(" in b]
    assert len(planner) == 1, "the README and docs/ have one planner example (score, refine, contacts)"
    examples = doctest.DocTestParser().get_examples(softgrip_jax.score.__doc__)
    doctested = "".join(e.source for e in examples if not e.source.startswith("bool(refined"))
    assert _code(planner[0]) == _code(doctested)


def test_readme_scene_example_is_the_doctested_example_outputs_included():
    import softgrip_vision.scene

    scene = [b for b in _python_blocks() if "frame_scene(" in b]
    assert len(scene) == 1, "the README and docs/ have one frame-to-scene example"
    examples = doctest.DocTestParser().get_examples(softgrip_vision.scene.__doc__)
    assert _code(scene[0]) == _code("".join(e.source for e in examples))
    # Every output the doctest checks is shown in the README, as a comment, in the same order.
    shown = [line[2:] for line in scene[0].splitlines() if line.startswith("# ")]
    wanted = [line for e in examples for line in e.want.splitlines()]
    assert wanted and [line for line in shown if line in wanted] == wanted


def test_readme_keeps_its_two_commands_first_and_links_resolve():
    text = README.read_text(encoding="utf-8")
    first = text.split("\n## ", 1)[0]
    assert "make demo" in first and "make test" in first, "the README's first lines give make demo and make test"
    broken = []
    for page in PAGES:
        for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text(encoding="utf-8")):
            path = target.split("#", 1)[0]
            if path and "://" not in path and not (page.parent / path).exists():
                broken.append(f"{page.relative_to(ROOT)} -> {target}")
    assert not broken, broken
