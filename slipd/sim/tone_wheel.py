"""Wheel speed as an ABS control unit computes it from the tone wheel's edges.

An active wheel-speed sensor sees the teeth of a tone wheel (``teeth`` per revolution, e.g. 44
in a Hyundai service manual's sensor specification, 29 on a Saab 900, 48 common) and gives one
edge per tooth. The control unit turns the edges into a speed once per loop (``gate`` s, here
the simulator's 10 ms grid) in one of two ways:

- ``"count"``: the edges counted in the gate, ``omega = m * 2 pi / (teeth * gate)``: a speed
  resolution of ``2 pi r / (teeth * gate)`` (4.5 m/s for 48 teeth, r = 0.344 m, 10 ms), the
  frequency measurement of a plain counter;
- ``"edge_timing"``: the edges counted in the gate over the time from the last edge of the
  previous gate to the last edge of this one (Delco Electronics, US patent 4,799,178, 1989:
  "the calculation interval ... from the next-to-last speed signal generated in the prior
  sampling interval to the last speed signal generated"; the M/T method of motor drives). The
  speed is exact at constant speed and the mean over the edge interval otherwise, so it lags
  by about half an edge interval. With no edge in a gate the last value is held, bounded by
  ``2 pi / teeth / (t - t_last_edge)`` (the wheel cannot be faster than that, or an edge would
  have come), and below ``2 pi / teeth / timeout`` the unit reports 0.

Both give the unsigned angular speed (rad/s) on the grid; the tooth phase of each wheel is
random (``phase`` in [0, 1) of a pitch).
"""

from __future__ import annotations

import math

import numpy as np

METHODS = ("edge_timing", "count")


def _edge_times(theta: np.ndarray, t: np.ndarray, edge_angle: np.ndarray) -> np.ndarray:
    """Times at which the non-decreasing angle ``theta(t)`` first reaches ``edge_angle``
    (linear between grid points)."""
    i = np.clip(np.searchsorted(theta, edge_angle, side="left"), 1, len(t) - 1)
    span = theta[i] - theta[i - 1]
    frac = np.where(span > 0, (edge_angle - theta[i - 1]) / np.where(span > 0, span, 1.0), 1.0)
    return t[i - 1] + np.clip(frac, 0.0, 1.0) * (t[i] - t[i - 1])


def tone_wheel_speed(
    t: np.ndarray,
    omega: np.ndarray,
    teeth: int,
    phase: float,
    method: str = "edge_timing",
    timeout: float = 0.1,
) -> np.ndarray:
    """The angular speed (rad/s, unsigned) an ABS unit reports each grid step for a wheel turning
    at ``omega`` (rad/s) on the grid ``t``, from a tone wheel of ``teeth`` teeth."""
    n_out = len(t)
    if n_out < 2:
        return np.zeros(n_out)
    # the wheel turned before the first sample: a pre-roll at the first speed, long enough for
    # two edges or the timeout, so the unit reports from the first sample on (dropped below)
    dt0 = float(t[1] - t[0])
    pre = int(math.ceil((timeout + 2.0 * dt0) / dt0))
    t = np.concatenate((t[0] - dt0 * np.arange(pre, 0, -1), t))
    omega = np.concatenate((np.full(pre, omega[0]), omega))
    n = len(t)
    pitch = 2.0 * math.pi / teeth
    w = np.abs(np.asarray(omega, dtype=np.float64))
    theta = np.concatenate(([0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))))
    edges = np.floor(theta / pitch + phase)  # edges passed by each grid time (edge e sits at
    # theta = (e - phase) pitch, the first one e = 1)
    count = np.diff(edges, prepend=edges[0])
    if method == "count":
        gate = np.diff(t, prepend=t[0] - dt0)
        return (count * pitch / gate)[pre:]
    if method != "edge_timing":
        raise ValueError(f"unknown wheel-speed method {method!r}; expected one of {METHODS}")
    has_edge = edges >= 1
    t_last = np.where(has_edge, _edge_times(theta, t, (edges - phase) * pitch), np.nan)
    t_prev = np.concatenate(([np.nan], t_last[:-1]))
    fresh = (count >= 1) & ~np.isnan(t_prev)  # an edge now, and one before to time it from
    interval = np.where(fresh, t_last - np.where(fresh, t_prev, 0.0), 1.0)
    measured = np.where(fresh, count * pitch / np.where(interval > 0, interval, 1.0), 0.0)
    # hold the newest measurement between edges, bounded by what the missing edge says
    newest = np.maximum.accumulate(np.where(fresh, np.arange(n), -1))
    held = np.where(newest >= 0, measured[np.maximum(newest, 0)], 0.0)
    since = np.where(has_edge, t - np.where(has_edge, t_last, 0.0), 0.0)
    bound = np.where(since > 0, pitch / np.where(since > 0, since, 1.0), np.inf)
    speed = np.where(fresh, measured, np.where(has_edge, np.minimum(held, bound), 0.0))
    return np.where(speed < pitch / timeout, 0.0, speed)[pre:]
