"""Error metrics of sideslip and speed estimates against the simulator's (or a reference
sensor's) truth.

The truth is linearly interpolated onto the estimate's ticks; only ticks inside the truth's
time span, with a truth speed above the threshold and a finite estimate are scored (the papers
score the same way: Selmanaj et al. 2017 and Righetti & Lenzo 2025 report RMS over the
manoeuvre, above walking speed, where beta is defined).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from slipd.channels import Out

KPH = 1.0 / 3.6


@dataclass(frozen=True)
class Scores:
    """Metrics of one estimator on one or more logs (degrees for beta, m/s for vx)."""

    beta_rms_deg: float
    beta_max_deg: float
    beta_p99_deg: float
    vx_rms_mps: float
    samples: int

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

    def scores(self) -> Scores:
        return score(self.beta_err, self.vx_err)


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
    return Errors(
        t=est_t[keep],
        beta_err=wrap_angle(beta_est[keep] - beta_true[keep]),
        vx_err=vx_est[keep] - vx_true[keep],
        beta_true=beta_true[keep],
        beta_est=beta_est[keep],
        rejected_nonfinite=int(np.sum(fast & ~finite)),
    )


def score(beta_err: np.ndarray, vx_err: np.ndarray) -> Scores:
    """RMS, maximum and 99th percentile of |beta error| (deg) and RMS of the vx error."""
    n = int(np.asarray(beta_err).size)
    if n == 0:
        nan = float("nan")
        return Scores(nan, nan, nan, nan, 0)
    b = np.degrees(np.abs(np.asarray(beta_err, dtype=np.float64)))
    v = np.asarray(vx_err, dtype=np.float64)
    return Scores(
        beta_rms_deg=float(np.sqrt(np.mean(b * b))),
        beta_max_deg=float(np.max(b)),
        beta_p99_deg=float(np.percentile(b, 99.0)),
        vx_rms_mps=float(np.sqrt(np.mean(v * v))),
        samples=n,
    )


def pooled(parts: list[Errors]) -> Scores:
    """One score over the samples of several logs (every scored tick weighs the same)."""
    if not parts:
        return score(np.zeros(0), np.zeros(0))
    return score(np.concatenate([p.beta_err for p in parts]),
                 np.concatenate([p.vx_err for p in parts]))


def format_table(rows: dict[str, Scores], title: str = "") -> str:
    """A fixed-width text table, one line per estimator."""
    head = f"{'estimator':22s} {'beta rms':>9s} {'beta max':>9s} {'beta p99':>9s} " \
           f"{'vx rms':>8s} {'samples':>8s}"
    lines = [title] if title else []
    lines += [head, f"{'':22s} {'[deg]':>9s} {'[deg]':>9s} {'[deg]':>9s} {'[m/s]':>8s}"]
    for name, s in rows.items():
        lines.append(f"{name:22s} {s.beta_rms_deg:9.3f} {s.beta_max_deg:9.3f} "
                     f"{s.beta_p99_deg:9.3f} {s.vx_rms_mps:8.3f} {s.samples:8d}")
    return "\n".join(lines)
