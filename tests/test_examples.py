"""The notebook-style examples run as a user runs them (``python examples/NAME.py OUT``)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
REAL_CSV = ROOT.parent / "shared" / "realdata" / "revs_250lm" / "revs_250lm.csv"


def test_real_run_example_imports_evaluates_three_methods_and_plots(tmp_path):
    pytest.importorskip("pandas")
    pytest.importorskip("matplotlib")
    if not REAL_CSV.exists():
        pytest.skip(f"{REAL_CSV} not found (CI has ../shared beside the clone)")
    done = subprocess.run([sys.executable, str(ROOT / "examples" / "real_run.py"),
                           str(tmp_path)], capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    for method in ("d_ekf", "kinematic_heuristic", "zero"):
        assert method in done.stdout
    assert "max |difference| = 0 rad" in done.stdout
    assert (tmp_path / "revs_250lm.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / "revs_250lm.truth.csv").exists()
