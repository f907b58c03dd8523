"""What slipd identify finds: a value per profile key with its method, the data it used and a
95 % confidence interval, or the reason it could not be found; and the statistics behind the
intervals (a bootstrap over segments: Efron & Tibshirani, An Introduction to the Bootstrap,
1993, ch. 6 and 13, percentile intervals; segments, not ticks, are resampled because the ticks
of one segment are strongly correlated)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

#: Bootstrap resamples per quantity and the least number of segments it needs; with fewer,
#: an interval comes from the spread inside the segments (said in the finding's method).
N_BOOTSTRAP = 200
MIN_BOOTSTRAP_SEGMENTS = 4
BOOTSTRAP_SEED = 18


@dataclass
class Finding:
    """One identified profile value. ``key`` is ``table.key`` as in the profile
    (``calibration.gyro_offset``, ``vehicle.tyre.cornering_stiffness_front``); ``value`` and
    ``ci`` (low, high) are in the profile's units, per element for a list."""

    key: str
    value: float | tuple[float, ...]
    ci: tuple[float, float] | tuple[tuple[float, float], ...]
    method: str
    source: str
    segments: int
    seconds: float
    logs: int
    note: str = ""

    def values(self) -> tuple[float, ...]:
        return self.value if isinstance(self.value, tuple) else (self.value,)

    def intervals(self) -> tuple[tuple[float, float], ...]:
        if self.ci and isinstance(self.ci[0], tuple):
            return self.ci  # type: ignore[return-value]
        return (self.ci,)  # type: ignore[return-value]

    def data_text(self) -> str:
        logs = f"{self.logs} log{'s' if self.logs != 1 else ''}"
        return f"{self.segments} segment{'s' if self.segments != 1 else ''}, " \
               f"{self.seconds:.0f} s, {logs}"


@dataclass
class Missing:
    """A quantity the data cannot support, and why (its profile value is left as it was)."""

    key: str
    reason: str


@dataclass
class Outcome:
    """Everything one run found: findings by key, the quantities left alone, diagnostics for
    the report (series and fits by name)."""

    findings: dict[str, Finding] = field(default_factory=dict)
    missing: dict[str, Missing] = field(default_factory=dict)
    diagnostics: dict = field(default_factory=dict)
    messages: list[str] = field(default_factory=list)

    def add(self, item: Finding | Missing) -> None:
        if isinstance(item, Finding):
            self.missing.pop(item.key, None)
            self.findings[item.key] = item
        else:
            self.findings.pop(item.key, None)
            self.missing[item.key] = item


def bootstrap(fit: Callable[[np.ndarray], np.ndarray], n_units: int, n: int = N_BOOTSTRAP,
              seed: int = BOOTSTRAP_SEED) -> np.ndarray:
    """Parameters of ``fit`` on ``n`` resamples (with replacement) of ``n_units`` segment
    indices: [n, k]. A resample the fit cannot handle (singular) is dropped."""
    rng = np.random.default_rng(seed)
    rows = []
    for _ in range(n):
        chosen = rng.integers(0, n_units, n_units)
        try:
            value = np.atleast_1d(np.asarray(fit(chosen), dtype=np.float64))
        except (np.linalg.LinAlgError, ValueError, ZeroDivisionError):
            continue
        if np.all(np.isfinite(value)):
            rows.append(value)
    return np.array(rows) if rows else np.zeros((0, 0))


def percentile_interval(samples: np.ndarray, level: float = 0.95
                        ) -> list[tuple[float, float]]:
    """Per column of bootstrap ``samples`` [n, k], the (low, high) percentile interval."""
    if samples.size == 0:
        return []
    tail = 50.0 * (1.0 - level)
    low = np.percentile(samples, tail, axis=0)
    high = np.percentile(samples, 100.0 - tail, axis=0)
    return [(float(a), float(b)) for a, b in zip(low, high, strict=True)]


def segment_mean(values: Sequence[np.ndarray], seconds_per_independent: float = 1.0,
                 dt: float = 0.01) -> tuple[np.ndarray, list[tuple[float, float]], str]:
    """Duration-weighted mean of per-segment sample arrays ([m] or [m, k]) with a 95 %
    interval: a bootstrap over the segments when there are enough, else the standard error
    of all samples taking one independent sample per ``seconds_per_independent`` (the
    correlation of slow drifts). Returns (mean, intervals, how the interval was found)."""
    stacked = [np.atleast_2d(np.asarray(v, dtype=np.float64).T).T for v in values]
    weights = np.array([len(v) for v in stacked], dtype=np.float64)
    means = np.array([v.mean(axis=0) for v in stacked])
    total = (means * weights[:, None]).sum(axis=0) / weights.sum()
    if len(stacked) >= MIN_BOOTSTRAP_SEGMENTS:
        def fit(idx: np.ndarray) -> np.ndarray:
            w = weights[idx]
            return (means[idx] * w[:, None]).sum(axis=0) / w.sum()

        return total, percentile_interval(bootstrap(fit, len(stacked))), \
            f"bootstrap over {len(stacked)} segments"
    everything = np.concatenate(stacked)
    n_eff = max(1.0, len(everything) * dt / seconds_per_independent)
    half = 1.96 * everything.std(axis=0) / math.sqrt(n_eff)
    how = (f"standard error, {len(stacked)} segment(s) (1 independent sample per "
           f"{seconds_per_independent:g} s)")
    if len(stacked) >= 2:
        # too few segments for a bootstrap, but their means' spread shows what drifts between
        # them (a sensor offset's slow wander, the road at each stop): Student's t interval
        # of the segment means when it is the wider (Efron & Tibshirani 1993, ch. 12)
        from scipy.stats import t as student

        between = (student.ppf(0.975, len(stacked) - 1) * means.std(axis=0, ddof=1)
                   / math.sqrt(len(stacked)))
        if np.any(between > half):
            how += f" or Student's t over the {len(stacked)} segment means, the wider"
        half = np.maximum(half, between)
    return total, [(float(m - h), float(m + h)) for m, h in zip(total, half, strict=True)], how


def regression_interval(fit: Callable[[np.ndarray], np.ndarray], n_units: int,
                        estimate: np.ndarray) -> tuple[list[tuple[float, float]], str]:
    """95 % intervals of a fit over segment units: bootstrap when there are enough units,
    else none (NaN) and said so."""
    if n_units >= MIN_BOOTSTRAP_SEGMENTS:
        intervals = percentile_interval(bootstrap(fit, n_units))
        if intervals:
            return intervals, f"bootstrap over {n_units} segments"
    return [(math.nan, math.nan)] * len(estimate), f"only {n_units} segment(s): no interval"
