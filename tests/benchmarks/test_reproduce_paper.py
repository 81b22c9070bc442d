"""The reproduction harness (benchmarks/reproduce_paper.py) on its tiny configuration."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import reproduce_paper as rp  # noqa: E402


def _flags(touching_nodes, m=40):
    flags = np.zeros(m + 1, bool)
    flags[list(touching_nodes)] = True
    return flags


@pytest.mark.parametrize("nodes, case", [
    ((), 0),  # nothing touches
    ((39, 40), 1),  # one run ending at the tip
    ((15, 16, 17), 3),  # one run in the middle
    ((15, 16, 40), 2),  # a middle run and the tip
    (range(20, 41), 1),  # one run wrapped along the finger up to the tip is the tip's
])
def test_rod_case_from_contact_runs(nodes, case):
    # N = 4: the tip zone is the last half link, arc >= 7/8 L, nodes 35..40 of 40.
    assert rp.rod_case(_flags(nodes), n_links=4) == case
    assert rp.rod_case(_flags([34]), n_links=4) == 3 and rp.rod_case(_flags([35]), n_links=4) == 1


def _chain_tip_miss(theta, n, length):
    """|PCC chain tip (eqs. 1-3) - free rod tip|: links of L/N at angles (2k+1) Theta / N against the arc of
    length L whose chord is at Theta; worked out by hand, independent of the library."""
    angles = (2 * np.arange(n) + 1) * theta / n
    chain = length / n * np.array([np.sin(angles).sum(), np.cos(angles).sum()])
    chord = length * math.sin(theta) / theta
    return float(np.hypot(*(chain - chord * np.array([math.sin(theta), math.cos(theta)]))))


@pytest.mark.slow
def test_quick_harness_reproduces_the_model_error_and_writes_its_outputs(tmp_path):
    out = rp.main(["--quick", "--out", str(tmp_path)])
    records = out["records"]
    # With the true geometry and no object, the only error is the chain's own discretisation.
    for side in rp.SIDES:
        for n in (2, 4):
            rows = rp._select(records, experiment="A-a", source="truth", side=side, n_links=n)
            assert rows
            expected = _chain_tip_miss(rp.THETA[side], n, rp.LENGTH)
            for r in rows:
                assert r["error_tip"] == pytest.approx(expected, abs=0.02)
    # Through the vision pipeline the error grows by what the pipeline costs, not more than 0.5 mm here.
    for key in ("error_mid", "error_tip"):
        frames = np.mean([r[key] for r in rp._select(records, source="frames")])
        truth = np.mean([r[key] for r in rp._select(records, source="truth")])
        assert abs(frames - truth) < 0.5
    assert all(r["case"] == r["rod_case"] for r in rp._select(records, experiment="A-a"))
    saved = json.loads((tmp_path / "results.json").read_text())
    assert len(saved["records"]) == len(records)
    assert "Experiment A-a" in (tmp_path / "tables.md").read_text()
    assert all(path.exists() and path.stat().st_size > 10_000 for path in out["sheets"].values())
