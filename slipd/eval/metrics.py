"""Error metrics of sideslip and speed estimates against the simulator's (or a reference
sensor's) truth.

The truth is linearly interpolated onto the estimate's ticks; only ticks inside the truth's
time span, with a truth speed above the threshold and a finite estimate are scored (the papers
score the same way: Selmanaj et al. 2017 and Righetti & Lenzo 2025 report RMS over the
manoeuvre, above walking speed, where beta is defined).

Beside accuracy, the metrics a safety engineer needs to trust the VALID bit (DESIGN.md, "What
VALID means"): how often a method says VALID in the scored window (``valid_fraction``), how
often a VALID tick was wrong by more than 2 and 5 deg (``valid_err_over_2deg``/``_5deg``, as
shares of the VALID ticks), the worst VALID error, and whether the method's own sigma_beta
covers its error (``sigma2_coverage``: share of VALID ticks with |error| <= 2 sigma_beta; a
calibrated Gaussian 1-sigma gives 0.95).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from slipd.channels import Out, Status
from slipd.eval.exact_sum import ExactSum

KPH = 1.0 / 3.6


@dataclass(frozen=True)
class Scores:
    """Metrics of one estimator on one or more logs (degrees for beta, m/s for vx).

    ``beta_*`` and ``vx_rms_mps`` over every scored tick; ``valid_*`` over the VALID ones;
    ``valid_fraction`` is the share of the scored window (truth in range and fast enough,
    finite or not) that was VALID; NaN where a figure has no sample.
    """

    beta_rms_deg: float
    beta_max_deg: float
    beta_p99_deg: float
    vx_rms_mps: float
    samples: int
    valid_fraction: float = math.nan
    valid_samples: int = 0
    valid_rms_deg: float = math.nan
    valid_max_err_deg: float = math.nan
    valid_p99_deg: float = math.nan
    valid_err_over_2deg: float = math.nan
    valid_err_over_5deg: float = math.nan
    sigma2_coverage: float = math.nan

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class Errors:
    """The scored per-tick errors, kept so several logs can be pooled into one score."""

    t: np.ndarray  # s, estimate tick times of the scored samples
    beta_err: np.ndarray  # rad, estimate - truth, wrapped to [-pi, pi)
    vx_err: np.ndarray  # m/s
    beta_true: np.ndarray  # rad
    beta_est: np.ndarray  # rad
    rejected_nonfinite: int  # ticks in range whose estimate was NaN/inf
    valid: np.ndarray | None = None  # bool per scored tick: the frame said VALID
    sigma_beta: np.ndarray | None = None  # rad per scored tick: the method's own 1-sigma

    @property
    def window(self) -> int:
        """Ticks of the scored window, finite or not (the valid_fraction denominator)."""
        return int(self.beta_err.size + self.rejected_nonfinite)

    def scores(self) -> Scores:
        return score(self.beta_err, self.vx_err, self.valid, self.sigma_beta, self.window)


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def errors(
    est_t: np.ndarray,
    est_out: np.ndarray,
    truth_t: np.ndarray,
    truth_beta: np.ndarray,
    truth_vx: np.ndarray,
    truth_speed: np.ndarray | None = None,
    min_speed: float = 20.0 * KPH,
) -> Errors:
    """Errors at the estimate's ticks where the truth speed exceeds ``min_speed`` (m/s).

    ``est_out`` is (n, N_OUT) (slipd.channels.Out columns); the truth arrays share ``truth_t``
    (increasing). ``truth_speed`` defaults to |vx|.
    """
    est_t = np.asarray(est_t, dtype=np.float64)
    est_out = np.asarray(est_out, dtype=np.float64)
    truth_t = np.asarray(truth_t, dtype=np.float64)
    if est_out.ndim != 2 or est_out.shape[0] != est_t.shape[0]:
        raise ValueError(f"estimate outputs {est_out.shape} do not match {est_t.shape[0]} ticks")
    if truth_t.size < 2 or np.any(np.diff(truth_t) <= 0):
        raise ValueError("truth time must be increasing with at least two samples")
    speed = np.abs(truth_vx) if truth_speed is None else np.asarray(truth_speed)
    inside = (est_t >= truth_t[0]) & (est_t <= truth_t[-1])
    # beta is interpolated through its sine/cosine so a spin through +-180 deg stays correct
    beta_true = np.arctan2(np.interp(est_t, truth_t, np.sin(truth_beta)),
                           np.interp(est_t, truth_t, np.cos(truth_beta)))
    vx_true = np.interp(est_t, truth_t, truth_vx)
    speed_true = np.interp(est_t, truth_t, speed)
    beta_est = est_out[:, Out.BETA]
    vx_est = est_out[:, Out.VX]
    fast = inside & (speed_true > min_speed)
    finite = np.isfinite(beta_est) & np.isfinite(vx_est)
    keep = fast & finite
    valid = (est_out[:, Out.STATUS].astype(np.int64) & int(Status.VALID)) != 0
    return Errors(
        t=est_t[keep],
        beta_err=wrap_angle(beta_est[keep] - beta_true[keep]),
        vx_err=vx_est[keep] - vx_true[keep],
        beta_true=beta_true[keep],
        beta_est=beta_est[keep],
        rejected_nonfinite=int(np.sum(fast & ~finite)),
        valid=valid[keep],
        sigma_beta=est_out[keep, Out.SIGMA_BETA],
    )


#: |beta error| histogram of the accumulator: geometric bins of 0.1 % from 1e-4 deg (below it:
#: bin 0) to 360 deg, so the p99 of any number of pooled ticks costs 15,000 counters and is
#: exact to 0.05 % (the bin's geometric centre, clamped to the largest error seen).
_HIST_LOW_DEG = 1e-4
_HIST_RATIO = 1.001
_HIST_BINS = int(math.ceil(math.log(360.0 / _HIST_LOW_DEG) / math.log(_HIST_RATIO))) + 1


def _bins(abs_deg: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore"):
        k = np.floor(np.log(np.maximum(abs_deg, _HIST_LOW_DEG) / _HIST_LOW_DEG)
                     / math.log(_HIST_RATIO)).astype(np.int64) + 1
    k[abs_deg < _HIST_LOW_DEG] = 0
    return np.minimum(k, _HIST_BINS - 1)


class _ErrorStats:
    """Count, sum of squares (exact: the same whatever pieces the ticks came in), maximum and
    histogram of |beta error| in degrees."""

    __slots__ = ("n", "sq", "max", "hist")

    def __init__(self) -> None:
        self.n, self.sq, self.max = 0, ExactSum(), 0.0
        self.hist = np.zeros(_HIST_BINS, dtype=np.int64)

    def add(self, abs_deg: np.ndarray) -> None:
        if abs_deg.size:
            self.n += int(abs_deg.size)
            self.sq.add(abs_deg * abs_deg)
            self.max = max(self.max, float(np.max(abs_deg)))
            self.hist += np.bincount(_bins(abs_deg), minlength=_HIST_BINS)

    def rms(self) -> float:
        return math.sqrt(self.sq.value() / self.n) if self.n else math.nan

    def percentile(self, q: float) -> float:
        if not self.n:
            return math.nan
        k = int(np.searchsorted(np.cumsum(self.hist), q / 100.0 * self.n, side="left"))
        if k == 0:
            return min(_HIST_LOW_DEG / 2.0, self.max)
        centre = _HIST_LOW_DEG * _HIST_RATIO ** (k - 1) * math.sqrt(_HIST_RATIO)
        return min(centre, self.max)

    def cdf(self) -> tuple[np.ndarray, np.ndarray]:
        """(|error| in deg, share of samples at or below it) at each occupied bin's upper
        edge (clamped to the largest error): the CDF to the histogram's 0.1 %."""
        occupied = np.flatnonzero(self.hist)
        if not self.n:
            return np.zeros(0), np.zeros(0)
        upper = np.minimum(_HIST_LOW_DEG * _HIST_RATIO ** occupied.astype(np.float64), self.max)
        return upper, np.cumsum(self.hist)[occupied] / self.n


class Accumulator:
    """The :class:`Scores` of one estimator accumulated over logs (or pieces of a log) in
    memory bounded by its histograms, never by the number of ticks: pooling a whole suite,
    or every mismatch case of it, holds no per-tick array. Its sums are exact, so the scores
    do not depend on how the ticks were cut into pieces (a streamed log's chunks, a cluster's
    tasks)."""

    def __init__(self) -> None:
        self.all = _ErrorStats()
        self.valid = _ErrorStats()
        self.vx_n, self.vx_sq = 0, ExactSum()
        self.window = 0
        self.has_validity = True
        self.over_2deg = self.over_5deg = self.covered = 0
        self.has_sigma = True

    def add_arrays(self, beta_err: np.ndarray, vx_err: np.ndarray,
                   valid: np.ndarray | None = None, sigma_beta: np.ndarray | None = None,
                   window: int | None = None) -> Accumulator:
        b = np.degrees(np.abs(np.asarray(beta_err, dtype=np.float64)))
        v = np.asarray(vx_err, dtype=np.float64)
        self.all.add(b)
        self.vx_n += int(v.size)
        self.vx_sq.add(v * v)
        self.window += int(b.size if window is None else window)
        if valid is None:
            self.has_validity = self.has_sigma = False
            return self
        valid = np.asarray(valid, dtype=bool)
        bv = b[valid]
        self.valid.add(bv)
        self.over_2deg += int(np.count_nonzero(bv > 2.0))
        self.over_5deg += int(np.count_nonzero(bv > 5.0))
        if sigma_beta is None:
            self.has_sigma = False
        else:
            sigma = np.degrees(np.asarray(sigma_beta, dtype=np.float64)[valid])
            with np.errstate(invalid="ignore"):
                self.covered += int(np.count_nonzero(bv <= 2.0 * sigma))  # NaN covers nothing
        return self

    def add(self, part: Errors) -> Accumulator:
        return self.add_arrays(part.beta_err, part.vx_err, part.valid, part.sigma_beta,
                               part.window)

    def cdf(self, valid_only: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The pooled CDF of |beta error| (deg) over the scored (or only the VALID) ticks."""
        return (self.valid if valid_only else self.all).cdf()

    def merge(self, other: Accumulator) -> Accumulator:
        """Add another accumulator's ticks (e.g. pool the mismatch cases)."""
        for mine, theirs in ((self.all, other.all), (self.valid, other.valid)):
            mine.n += theirs.n
            mine.sq.merge(theirs.sq)
            mine.max = max(mine.max, theirs.max)
            mine.hist += theirs.hist
        self.vx_n += other.vx_n
        self.vx_sq.merge(other.vx_sq)
        self.window += other.window
        self.has_validity &= other.has_validity
        self.has_sigma &= other.has_sigma
        self.over_2deg += other.over_2deg
        self.over_5deg += other.over_5deg
        self.covered += other.covered
        return self

    def scores(self) -> Scores:
        nan = math.nan
        a = self.all
        figures = dict(
            beta_rms_deg=a.rms(), beta_max_deg=a.max if a.n else nan,
            beta_p99_deg=a.percentile(99.0),
            vx_rms_mps=math.sqrt(self.vx_sq.value() / self.vx_n) if self.vx_n else nan,
            samples=a.n,
        )
        if not self.has_validity:
            return Scores(**figures)
        v = self.valid
        figures.update(valid_fraction=v.n / self.window if self.window else nan,
                       valid_samples=v.n)
        if v.n:
            figures.update(valid_rms_deg=v.rms(), valid_max_err_deg=v.max,
                           valid_p99_deg=v.percentile(99.0),
                           valid_err_over_2deg=self.over_2deg / v.n,
                           valid_err_over_5deg=self.over_5deg / v.n)
            if self.has_sigma:
                figures["sigma2_coverage"] = self.covered / v.n
        return Scores(**figures)


def score(beta_err: np.ndarray, vx_err: np.ndarray, valid: np.ndarray | None = None,
          sigma_beta: np.ndarray | None = None, window: int | None = None) -> Scores:
    """RMS, maximum and 99th percentile of |beta error| (deg) and RMS of the vx error; with
    ``valid`` (bool per sample) the same on the VALID samples and the validity metrics, with
    ``sigma_beta`` (rad per sample) the 2-sigma coverage. ``window`` is the valid_fraction
    denominator (default: the samples). The p99 comes from :class:`Accumulator`'s histogram
    (0.05 %)."""
    return Accumulator().add_arrays(beta_err, vx_err, valid, sigma_beta, window).scores()


def pooled(parts: list[Errors]) -> Scores:
    """One score over the samples of several logs (every scored tick weighs the same)."""
    acc = Accumulator()
    for part in parts:
        acc.add(part)
    return acc.scores()


#: Columns of the text table: (heading, unit, Scores field, format).
TABLE_COLUMNS = (
    ("beta rms", "[deg]", "beta_rms_deg", "9.3f"),
    ("beta p99", "[deg]", "beta_p99_deg", "9.3f"),
    ("beta max", "[deg]", "beta_max_deg", "9.3f"),
    ("vx rms", "[m/s]", "vx_rms_mps", "7.3f"),
    ("valid", "[%]", "valid_fraction", "%6.1f"),
    ("V rms", "[deg]", "valid_rms_deg", "7.3f"),
    ("V max", "[deg]", "valid_max_err_deg", "7.2f"),
    ("V>2deg", "[%]", "valid_err_over_2deg", "%7.2f"),
    ("V>5deg", "[%]", "valid_err_over_5deg", "%7.2f"),
    ("2sig cov", "[%]", "sigma2_coverage", "%8.1f"),
    ("samples", "", "samples", "8d"),
)


def _cell(value, fmt: str) -> str:
    percent = fmt.startswith("%")
    fmt = fmt.lstrip("%")
    width = int(fmt.split(".")[0].rstrip("df"))
    if isinstance(value, float) and math.isnan(value):
        return f"{'-':>{width}s}"
    return format(100.0 * value if percent else value, fmt)


def format_table(rows: dict[str, Scores], title: str = "") -> str:
    """A fixed-width text table, one line per estimator; V = over the VALID ticks only,
    '-' where a figure has no sample (e.g. a method that is never VALID)."""
    name_width = max([22, *(len(n) + 1 for n in rows)])
    widths = [int(f.lstrip("%").split(".")[0].rstrip("df")) for *_, f in TABLE_COLUMNS]
    head = " ".join(f"{h:>{w}s}" for (h, *_), w in zip(TABLE_COLUMNS, widths, strict=True))
    units = " ".join(f"{u:>{w}s}" for (_, u, *_), w in zip(TABLE_COLUMNS, widths, strict=True))
    lines = [title] if title else []
    lines += [f"{'estimator':{name_width}s} {head}", f"{'':{name_width}s} {units}"]
    for name, s in rows.items():
        cells = " ".join(_cell(getattr(s, field), fmt) for _, _, field, fmt in TABLE_COLUMNS)
        lines.append(f"{name:{name_width}s} {cells}")
    return "\n".join(lines)
