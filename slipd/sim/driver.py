"""Driver models: open-loop steering profiles and closed-loop steering laws.

A steering law is a callable ``(t, x, s) -> delta_target`` (road-wheel angle, rad, ISO 8855:
positive left) where ``x`` is the multi-body model's state as a list and ``s`` the distance
travelled. The closed-loop laws read the true state: that is what a human driver or a test
robot sees (the car's motion and the road), not the car's sensors.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from slipd.sim.plant import OMEGA_RL, OMEGA_RR, POS_X, POS_Y, VX, VY, YAW, YAW_RATE


class LinearTable:
    """Piecewise-linear y(x) for scalar lookups in the right-hand side (np.interp costs ~5 us
    per scalar call; bisect on lists ~1 us). Clamped at both ends like np.interp."""

    def __init__(self, x: np.ndarray, y: np.ndarray) -> None:
        self.x = [float(v) for v in x]
        self.y = [float(v) for v in y]

    def __call__(self, xq: float) -> float:
        xs = self.x
        i = bisect.bisect_right(xs, xq)
        if i <= 0:
            return self.y[0]
        if i >= len(xs):
            return self.y[-1]
        x0, x1 = xs[i - 1], xs[i]
        w = (xq - x0) / (x1 - x0)
        return self.y[i - 1] + w * (self.y[i] - self.y[i - 1])


def smoothstep(u: float) -> float:
    """0 -> 1 over u in [0, 1] with zero slope at both ends (a cosine ramp)."""
    if u <= 0.0:
        return 0.0
    if u >= 1.0:
        return 1.0
    return 0.5 - 0.5 * math.cos(math.pi * u)


def steer_step(t_on: float, angle: float, ramp: float = 0.15) -> Callable:
    """Step steer: ``angle`` rad reached ``ramp`` s after ``t_on`` (ISO 7401 uses < 0.15 s)."""

    def law(t: float, x: list, s: float) -> float:
        return angle * smoothstep((t - t_on) / ramp)

    return law


def steer_pulses(events: Sequence[tuple[float, float, float, float]]) -> Callable:
    """Sum of trapezoid pulses ``(t_on, t_off, angle, ramp)``: J-turns and steer-and-hold."""

    def law(t: float, x: list, s: float) -> float:
        total = 0.0
        for t_on, t_off, angle, ramp in events:
            if t_on - 1e-9 <= t <= t_off + ramp:
                total += angle * (smoothstep((t - t_on) / ramp) - smoothstep((t - t_off) / ramp))
        return total

    return law


def steer_sine(t_on: float, amplitude: float, freq: float, cycles: float) -> Callable:
    """Sine steer of ``amplitude`` rad at ``freq`` Hz for ``cycles`` periods from ``t_on``."""
    t_off = t_on + cycles / freq

    def law(t: float, x: list, s: float) -> float:
        if t < t_on or t > t_off:
            return 0.0
        return amplitude * math.sin(2.0 * math.pi * freq * (t - t_on))

    return law


@dataclass
class CurvatureFollower:
    """Follow a road curvature profile ``kappa(s)`` (1/m, positive left).

    delta = (L + K_us v^2) kappa + k_yaw (v kappa - r): the steady-state single-track steer angle
    (Ackermann term plus understeer gradient ``K_us`` in rad s^2/m) and a yaw-rate correction,
    the way a driver holds a lane on a winding road without a path to track.
    """

    kappa_s: np.ndarray
    kappa: np.ndarray
    wheelbase: float
    understeer: float
    k_yaw: float = 0.08

    def __post_init__(self) -> None:
        self._table = LinearTable(self.kappa_s, self.kappa)

    def __call__(self, t: float, x: list, s: float) -> float:
        k = self._table(s)
        v = x[VX]
        return (self.wheelbase + self.understeer * v * v) * k + self.k_yaw * (v * k - x[YAW_RATE])


@dataclass
class PurePursuit:
    """Pure pursuit on a centre line given as ``y(x)`` (a cone course along the x axis).

    The target point lies ``max(min_lookahead, lookahead_time * v)`` ahead along x; the arc
    through it has curvature kappa = 2 y_local / L_d^2 (Coulter 1992) and the steer angle adds
    the understeer gradient as :class:`CurvatureFollower` does.
    """

    path_x: np.ndarray
    path_y: np.ndarray
    wheelbase: float
    understeer: float
    lookahead_time: float = 0.45
    min_lookahead: float = 4.0

    def __post_init__(self) -> None:
        self._path = LinearTable(self.path_x, self.path_y)

    def __call__(self, t: float, x: list, s: float) -> float:
        v = x[VX]
        ld = max(self.min_lookahead, self.lookahead_time * v)
        px, py, yaw = x[POS_X], x[POS_Y], x[YAW]
        tx = px + ld
        ty = self._path(tx)
        dx, dy = tx - px, ty - py
        y_local = -math.sin(yaw) * dx + math.cos(yaw) * dy
        kappa = 2.0 * y_local / (dx * dx + dy * dy)
        return (self.wheelbase + self.understeer * v * v) * kappa


@dataclass
class DriftHold:
    """Hold a power-on drift with counter-steer, the way a rally driver does:
    delta = k_beta (beta - beta_target(t)) + k_yaw (r_target - r) from ``t_on`` (before it, the
    ``before`` law steers). Ramping ``beta_target`` back to 0 catches the car. Reads the true
    beta (the driver feels it).
    """

    before: Callable
    t_on: float
    beta_target: Callable[[float], float]
    r_target: float
    k_beta: float = 2.0
    k_yaw: float = 0.3

    def __call__(self, t: float, x: list, s: float) -> float:
        if t < self.t_on:
            return self.before(t, x, s)
        beta = math.atan2(x[VY], max(x[VX], 0.1))
        return self.k_beta * (beta - self.beta_target(t)) + self.k_yaw * (
            self.r_target - x[YAW_RATE]
        )


@dataclass
class SlipThrottle:
    """Throttle on the rear (driven) wheels' slip, the way a driver holds a power slide:
    a = a_ff + k (slip_target(t) - slip), slip = omega_r R / v_x - 1 (mean of the rear wheels).
    NaN outside [t_on, t_off) (the speed controller drives)."""

    t_on: float
    t_off: float
    slip_target: Callable[[float], float]
    wheel_radius: float
    gain: float = 20.0
    a_ff: float = 1.0
    beta_target: Callable[[float], float] = lambda t: 0.0
    k_beta: float = 0.0  # slip per rad of sideslip beyond the target: lift off when oversliding

    def __call__(self, t: float, x: list) -> float:
        if not (self.t_on <= t < self.t_off):
            return math.nan
        wheel = 0.5 * (x[OMEGA_RL] + x[OMEGA_RR]) * self.wheel_radius
        slip = wheel / max(x[VX], 1.0) - 1.0
        target = self.slip_target(t)
        if self.k_beta:
            beta = math.atan2(x[VY], max(x[VX], 0.1))
            beta_t = self.beta_target(t)
            target = max(0.0, target - self.k_beta * abs(beta - beta_t) * (abs(beta) > abs(beta_t)))
        return self.a_ff + self.gain * (target - slip)


def iso3888_2_centreline(vehicle_width: float, approach: float = 60.0, exit_len: float = 60.0):
    """Centre line y(x) of the ISO 3888-2:2011 obstacle-avoidance lane change.

    Lane widths: section 1 = 1.1 W + 0.25, section 3 = W + 1, section 5 = max(1.3 W + 0.25, 3);
    lengths 12, 13.5, 11, 12.5, 12 m. Lane 3's right edge is 1 m left of lane 1's left edge;
    lane 5's right edge lines up with lane 1's. The centre line holds each lane's middle and
    changes with cosine ramps over sections 2 and 4. Returns (x, y) with x = 0 at the entry.
    """
    w1 = 1.1 * vehicle_width + 0.25
    w3 = vehicle_width + 1.0
    w5 = max(1.3 * vehicle_width + 0.25, 3.0)
    y3 = w1 / 2 + 1.0 + w3 / 2
    y5 = -w1 / 2 + w5 / 2
    x = np.arange(-approach, 61.0 + exit_len, 0.25)
    y = np.zeros_like(x)
    for i, xi in enumerate(x):
        if xi < 12.0:
            y[i] = 0.0
        elif xi < 25.5:
            y[i] = y3 * smoothstep((xi - 12.0) / 13.5)
        elif xi < 36.5:
            y[i] = y3
        elif xi < 49.0:
            y[i] = y3 + (y5 - y3) * smoothstep((xi - 36.5) / 12.5)
        else:
            y[i] = y5
    return x, y


def slalom_centreline(
    spacing: float = 20.0, cones: int = 10, amplitude: float = 1.1, approach: float = 60.0
):
    """Slalom centre line: cones on y = 0 every ``spacing`` m, entry/exit gates 10 m from the
    first/last cone (Righetti & Lenzo 2025, Fig. 6); the car passes each cone ``amplitude`` m
    to alternating sides. Returns (x, y) with x = 0 at the entry gate.
    """
    length = spacing * (cones - 1) + 20.0
    x = np.arange(-approach, length + approach, 0.25)
    y = np.where((x > 0.0) & (x < length), amplitude * np.sin(math.pi * x / spacing), 0.0)
    return x, y
