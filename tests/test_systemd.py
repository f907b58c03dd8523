"""systemd/slipd.service passes systemd-analyze verify and keeps its exposure <= 2.0."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

UNIT = Path(__file__).resolve().parent.parent / "systemd" / "slipd.service"
pytestmark = pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                                reason="systemd-analyze not installed (.ci/vm-setup installs it)")


def _unit_here(tmp_path: Path) -> Path:
    """The unit with ExecStart pointing at this checkout's slipd (verify checks the path)."""
    slipd = Path(sys.executable).parent / "slipd"
    text = UNIT.read_text().replace("/opt/slipd/.venv/bin/slipd", str(slipd))
    unit = tmp_path / "slipd.service"
    unit.write_text(text)
    return unit


def test_unit_verifies_clean(tmp_path):
    result = subprocess.run(["systemd-analyze", "verify", str(_unit_here(tmp_path))],
                            capture_output=True, text=True, timeout=60)
    problems = [line for line in (result.stdout + result.stderr).splitlines()
                if "slipd.service" in line]
    assert result.returncode == 0 and not problems, problems


def test_unit_exposure_at_most_2(tmp_path):
    result = subprocess.run(["systemd-analyze", "security", "--offline=true",
                             str(_unit_here(tmp_path))], capture_output=True, text=True,
                            timeout=60)
    match = re.search(r"Overall exposure level for slipd.service: ([0-9.]+)", result.stdout)
    assert match, result.stdout[-500:] + result.stderr[-500:]
    assert float(match.group(1)) <= 2.0
