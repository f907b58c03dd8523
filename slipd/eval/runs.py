"""Evaluation runs: estimators over logs with truth, one profile at a time, scores pooled.

Shared by ``slipd eval``, ``benchmarks/accuracy.py`` and the accuracy regression test, so
every figure slipd reports about itself comes from one path: the log is read and decoded
through the codec like the car's bus, streamed chunk by chunk (slipd.replay.stream: memory
bounded by a chunk, not the log), the truth interpolated onto each chunk's ticks
(slipd.eval.metrics.errors) and the errors accumulated (metrics.Accumulator, exact sums: the
scores are those of the whole log at once). :func:`score_log` is one log's task, on this
machine or a Dask worker (``slipd eval --dask``).
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


@dataclass
class LogScores:
    """One log's errors per method, accumulated (bounded memory), the ticks each method had
    no finite estimate at in the scored window, and (``keep=True``) every scored error and the
    series a plot needs."""

    accumulators: dict[str, Accumulator]
    rejected_nonfinite: dict[str, int]
    errors: dict[str, Errors] | None = None
    plot: dict | None = None

    def scores(self) -> dict[str, Scores]:
        return {m: acc.scores() for m, acc in self.accumulators.items()}


def score_log(log: Path, truth_path: Path, methods: list[str], profile,
              min_speed_kph: float = 20.0, keep: bool = False,
              chunk_bytes: int | None = None) -> LogScores:
    """Stream one log through ``methods`` and score each chunk against the truth."""
    import numpy as np

    from slipd.replay.stream import CHUNK_BYTES, LogStream
    from slipd.sim.writer import read_truth_csv

    if not log.exists():
        raise ConfigError(f"{log}: no such log")
    if not truth_path.exists():
        raise ConfigError(f"{truth_path}: no such truth file")
    truth, epoch = read_truth_csv(truth_path)
    truth_t = truth["t"] + epoch
    speed = truth.get("speed")
    result = LogScores({m: Accumulator() for m in methods}, dict.fromkeys(methods, 0))
    parts: dict[str, list[Errors]] = {m: [] for m in methods}
    series: dict[str, list] = {m: [] for m in methods}
    for chunk in LogStream(log, profile, methods, chunk_bytes=chunk_bytes or CHUNK_BYTES):
        t = chunk.inputs.t
        if not len(t):
            continue
        for name in methods:
            out = chunk.outputs[name]
            part = errors(t, out, truth_t, truth["beta"], truth["vx"], speed,
                          min_speed=min_speed_kph * KPH)
            result.accumulators[name].add(part)
            result.rejected_nonfinite[name] += part.rejected_nonfinite
            if keep:
                parts[name].append(part)
                series[name].append((t - epoch, out))
    if keep:
        result.errors = {m: joined_errors(parts[m]) for m in methods}
        result.plot = {"truth_t": truth["t"], "truth_beta": truth["beta"], "series": {
            m: (np.concatenate([s[0] for s in series[m]]) if series[m] else np.zeros(0),
                np.concatenate([s[1] for s in series[m]]) if series[m] else np.zeros((0, 0)))
            for m in methods}}
    return result


def joined_errors(parts: list[Errors]) -> Errors:
    """Chunks' errors as one (what ``metrics.errors`` gives for the whole log)."""
    import numpy as np

    def cat(name: str) -> np.ndarray:
        return np.concatenate([getattr(p, name) for p in parts]) if parts else np.zeros(0)

    return Errors(cat("t"), cat("beta_err"), cat("vx_err"), cat("beta_true"), cat("beta_est"),
                  sum(p.rejected_nonfinite for p in parts),
                  cat("valid").astype(bool) if parts else np.zeros(0, bool), cat("sigma_beta"))


def evaluate_log(log: Path, truth_path: Path, methods: list[str], profile,
                 min_speed_kph: float = 20.0) -> tuple[dict[str, Errors], dict]:
    """Errors per method on one log (every scored tick), plus the series a plot needs (times
    on the truth axis)."""
    scored = score_log(log, truth_path, methods, profile, min_speed_kph, keep=True)
    return scored.errors, scored.plot


@dataclass
class CaseResult:
    """Scores of one profile (nominal or a mismatch case) over a run's logs."""

    name: str
    description: str
    logs: dict[str, dict[str, Scores]] = field(default_factory=dict)
    pooled: dict[str, Accumulator] = field(default_factory=dict)
    #: log name -> error, the logs a cluster run could not score (left out of ``pooled``)
    failed: dict[str, str] = field(default_factory=dict)

    def overall(self) -> dict[str, Scores]:
        return {m: acc.scores() for m, acc in self.pooled.items()}


def evaluate_logs(logs: list[LogCase], methods: list[str], profile, min_speed_kph: float = 20.0,
                  name: str = "nominal", description: str = "the profile as given",
                  keep_last: bool = False, client=None, profile_spec: str | None = None,
                  chunk_bytes: int | None = None
                  ) -> tuple[CaseResult, dict | None, dict | None]:
    """Every log with one profile; returns the case's scores and, with ``keep_last``, the
    last log's errors and plot series (for a single-log plot). With a dask ``client``, one
    task per log (``profile_spec``: the profile as the workers load it, a name or a path, and
    ``profile`` the loaded one, or a ``load_profile`` edit of it for a mismatch case); the
    logs' accumulators are pooled in the logs' order either way, so the figures are the
    same."""
    case = CaseResult(name, description, pooled={m: Accumulator() for m in methods})
    if client is not None:
        scored = _score_on_cluster(client, logs, methods, profile_spec, name, min_speed_kph,
                                   chunk_bytes)
        case.failed = {e.name: r for e, r in zip(logs, scored, strict=True) if isinstance(r, str)}
        logs = [e for e, r in zip(logs, scored, strict=True) if not isinstance(r, str)]
        scored = [r for r in scored if not isinstance(r, str)]
    else:
        scored = [score_log(entry.log, entry.truth, methods, profile, min_speed_kph,
                            keep=keep_last and k == len(logs) - 1, chunk_bytes=chunk_bytes)
                  for k, entry in enumerate(logs)]
    for entry, result in zip(logs, scored, strict=True):
        case.logs[entry.name] = result.scores()
        for m, acc in result.accumulators.items():
            case.pooled[m].merge(acc)
    if not keep_last or not scored:
        return case, None, None
    if scored[-1].errors is None:  # scored on the cluster: the plotted log again, here
        scored[-1] = score_log(logs[-1].log, logs[-1].truth, methods, profile, min_speed_kph,
                               keep=True, chunk_bytes=chunk_bytes)
    return case, scored[-1].plot, scored[-1].errors


@dataclass(frozen=True)
class _ScoreJob:
    log: Path
    truth: Path
    methods: tuple[str, ...]
    profile: str
    case: str
    min_speed_kph: float
    chunk_bytes: int | None


def _score_job(job: _ScoreJob) -> LogScores:
    """A cluster task: one log scored with the profile as given or one mismatch case of it."""
    from slipd.eval.mismatch import CASES
    from slipd.profile import load_profile

    edit = CASES[job.case].edit() if job.case in CASES else None
    profile = load_profile(job.profile, edit=edit)
    return score_log(job.log, job.truth, list(job.methods), profile, job.min_speed_kph,
                     chunk_bytes=job.chunk_bytes)


def _score_on_cluster(client, logs: list[LogCase], methods: list[str],
                      profile_spec: str | None, case: str, min_speed_kph: float,
                      chunk_bytes: int | None) -> list[LogScores | str]:
    """Each log's scores, or the text of its error (the other logs go on)."""
    from slipd.errors import SlipdError
    from slipd.replay.fleet import file_sizes, run_tasks

    if profile_spec is None:
        raise ConfigError("a cluster evaluation needs the profile as a name or path")
    jobs = [_ScoreJob(entry.log.resolve(), entry.truth.resolve(), tuple(methods), profile_spec,
                      case, min_speed_kph, chunk_bytes) for entry in logs]
    results = run_tasks(client, _score_job, jobs, [f"{case}-{e.name}" for e in logs],
                        sizes=file_sizes(job.log for job in jobs))
    return [result if error is None else
            str(error) if isinstance(error, SlipdError) else f"{type(error).__name__}: {error}"
            for result, error in results]


def jsonable(rows: dict[str, Scores]) -> dict:
    """``{"estimators": {name: scores}}`` with NaN as null."""
    def clean(d: dict) -> dict:
        return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in d.items()}

    return {"estimators": {name: clean(s.as_dict()) for name, s in rows.items()}}
