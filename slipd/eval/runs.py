"""Evaluation runs: estimators over logs with truth, one profile at a time, scores pooled.

Shared by ``slipd eval``, ``benchmarks/accuracy.py`` and the accuracy regression test, so
every figure slipd reports about itself comes from one path: the log is read and decoded
through the codec like the car's bus (slipd.replay.engine.run_log), the truth interpolated
onto the ticks (slipd.eval.metrics.errors).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from slipd.errors import ConfigError
from slipd.eval.metrics import KPH, Accumulator, Errors, Scores, errors
from slipd.sim.writer import truth_path_of as truth_of


@dataclass(frozen=True)
class LogCase:
    """A log to score: its name in tables, the candump log and its truth CSV."""

    name: str
    log: Path
    truth: Path


def suite_logs(folder: Path) -> list[LogCase]:
    """Every FOLDER/*.log with a truth CSV beside it, by name."""
    if not folder.is_dir():
        raise ConfigError(f"{folder}: not a directory")
    found = sorted(p for p in folder.glob("*.log") if truth_of(p).exists())
    if not found:
        raise ConfigError(f"{folder}: no *.log with a matching *.truth.csv")
    return [LogCase(p.name[: -len(".log")], p, truth_of(p)) for p in found]


def evaluate_log(log: Path, truth_path: Path, methods: list[str], profile,
                 min_speed_kph: float = 20.0) -> tuple[dict[str, Errors], dict]:
    """Errors per method on one log, plus the series a plot needs (times on the truth axis)."""
    from slipd.replay.engine import run_log
    from slipd.sim.writer import read_truth_csv

    if not log.exists():
        raise ConfigError(f"{log}: no such log")
    if not truth_path.exists():
        raise ConfigError(f"{truth_path}: no such truth file")
    truth, epoch = read_truth_csv(truth_path)
    truth_t = truth["t"] + epoch
    speed = truth.get("speed")
    estimates = run_log(log, profile, methods)
    result: dict[str, Errors] = {}
    series = {}
    for name in methods:
        est = estimates[name]
        result[name] = errors(est.t, est.out, truth_t, truth["beta"], truth["vx"], speed,
                              min_speed=min_speed_kph * KPH)
        series[name] = (est.t - epoch, est.out)
    return result, {"truth_t": truth["t"], "truth_beta": truth["beta"], "series": series}


@dataclass
class CaseResult:
    """Scores of one profile (nominal or a mismatch case) over a run's logs."""

    name: str
    description: str
    logs: dict[str, dict[str, Scores]] = field(default_factory=dict)
    pooled: dict[str, Accumulator] = field(default_factory=dict)

    def overall(self) -> dict[str, Scores]:
        return {m: acc.scores() for m, acc in self.pooled.items()}


def evaluate_logs(logs: list[LogCase], methods: list[str], profile, min_speed_kph: float = 20.0,
                  name: str = "nominal", description: str = "the profile as given",
                  keep_last: bool = False) -> tuple[CaseResult, dict | None, dict | None]:
    """Every log with one profile; returns the case's scores and, with ``keep_last``, the
    last log's errors and plot series (for a single-log plot)."""
    case = CaseResult(name, description, pooled={m: Accumulator() for m in methods})
    plot_data = last = None
    for entry in logs:
        errs, plot_data = evaluate_log(entry.log, entry.truth, methods, profile, min_speed_kph)
        case.logs[entry.name] = {m: e.scores() for m, e in errs.items()}
        for m, e in errs.items():
            case.pooled[m].add(e)
        last = errs
    if not keep_last:
        return case, None, None
    return case, plot_data, last


def jsonable(rows: dict[str, Scores]) -> dict:
    """``{"estimators": {name: scores}}`` with NaN as null."""
    def clean(d: dict) -> dict:
        return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in d.items()}

    return {"estimators": {name: clean(s.as_dict()) for name, s in rows.items()}}
