"""A 5-minute soak of the daemon on slipd_unix under a full bus, its recorder rotating and
stats readers (benchmarks/soak.py; `pytest -m slow`). The 1-hour figure is the benchmark's."""

from __future__ import annotations

import tempfile
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow


def test_five_minutes_without_growth_or_crash():
    from benchmarks.soak import soak, summarize

    with tempfile.TemporaryDirectory(prefix="slipd-soak-") as workdir:
        result = soak(300.0, 5.0, 60.0, "kinematic_heuristic", 4000.0, 2.0, Path(workdir))
    s = summarize(result)
    assert s["exit"] == 0 and not s["crashed"], result["log"][-3000:]
    assert s["ticks"] > 29_000
    assert abs(s["rss_growth_mb"]) < 1.0, s
    assert s["failed_queries"] == 0, s["first_error"]
    assert s["recorder_errors"] == 0 and len(s["recordings"]) >= 2  # it rotated
    # a shared 2-CPU machine stalls now and then: misses are reported, bounded loosely here
    # (benchmarks/daemon_latency.py measures them)
    assert s["misses"] <= 0.005 * s["ticks"], s
