"""mypy (default settings) on the runtime packages of this checkout: no error anywhere.

A planner type-checks its own code against the installed wheel (``py.typed``): that check, on the
README's examples and every public module, is in tests/test_fresh_machine.py. This one checks the
library's own code, so that the annotations users read stay true.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("softgrip_base", "softgrip_jax", "softgrip_vision", "softgrip_calib", "softgrip_cli")


@pytest.mark.slow
def test_mypy_finds_no_error_in_the_library(tmp_path):
    pytest.importorskip("mypy")
    args = [sys.executable, "-m", "mypy", "--cache-dir", str(tmp_path / "mypy-cache")]
    for package in PACKAGES:
        args += ["-p", package]
    checked = subprocess.run(args, cwd=REPO, capture_output=True, text=True, timeout=900)
    assert checked.returncode == 0, checked.stdout[-5000:] + checked.stderr[-3000:]  # 1: errors; 2: mypy failed
    assert "Success: no issues found" in checked.stdout, checked.stdout[-3000:]
