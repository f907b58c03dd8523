"""Vx from the four wheel speeds, Selmanaj et al. 2017 section 2.3 (Fig. 4, eq. 11-13)."""

from __future__ import annotations

import enum
import math

from slipd.estimators.common.filters import DERIVATIVE_CUTOFF_HZ, derivative_filter
from slipd.estimators.common.kinematics import compensate_wheel_speeds
from slipd.numba_cache import nb


@enum.unique
class Wheels(enum.IntEnum):
    """Slots of the wheel-speed block: the derivative-filter memory of each compensated wheel
    speed (eq. 11) used by the weights of eq. 13 (NaN = not started)."""

    FL = 0
    FR = 1
    RL = 2
    RR = 3


@enum.unique
class VxMode(enum.IntEnum):
    """Which branch of Fig. 4 produced vx (returned as a float by ``vx_from_wheels``)."""

    NONE = 0  # no valid wheel speed: vx is NaN
    MIN = 1  # accelerating: slowest wheel
    WEIGHTED_MEAN = 2  # |ax| below the threshold: eq. 12-13
    MAX = 3  # braking: fastest wheel
    MEDIAN = 4  # weighted mean with every weight ~0 (all wheels disagree): median fallback


# Plain floats for the kernels (numba cannot convert an IntEnum member to float).
_MODE_NONE = float(VxMode.NONE)
_MODE_MIN = float(VxMode.MIN)
_MODE_MEAN = float(VxMode.WEIGHTED_MEAN)
_MODE_MAX = float(VxMode.MAX)
_MODE_MEDIAN = float(VxMode.MEDIAN)
#: Sum of eq. 13's weights below which the weighted mean is not defined (all ~0).
MIN_WEIGHT_SUM = 1e-9


@nb.njit(cache=True, _nrt=False)
def wheel_weight(ax, wheel_accel, vx_prev, wheel_speed, sigma_w1, sigma_w2):
    """Reliability weight of one wheel, eq. 13 (bivariate Gaussian, Fig. 5):
    W = exp(-(Ax - dV_i/dt)^2 / (2 sigma_w1^2) - (vx_prev - V_i)^2 / (2 sigma_w2^2)).
    A non-finite ``vx_prev`` (first tick) drops the second term."""
    accel_error = ax - wheel_accel
    exponent = accel_error * accel_error / (2.0 * sigma_w1 * sigma_w1)
    if math.isfinite(vx_prev):
        speed_error = vx_prev - wheel_speed
        exponent += speed_error * speed_error / (2.0 * sigma_w2 * sigma_w2)
    return math.exp(-exponent)


@nb.njit(cache=True, _nrt=False)
def _wheel_update(buf, slot, speed, valid, ax, vx_prev, dt, sigma_w1, sigma_w2):
    # The derivative filter only sees valid samples (an invalid one would be a step to 0).
    if not valid:
        return 0.0
    wheel_accel = derivative_filter(buf, slot, speed, dt, DERIVATIVE_CUTOFF_HZ)
    return wheel_weight(ax, wheel_accel, vx_prev, speed, sigma_w1, sigma_w2)


@nb.njit(cache=True, inline="always")
def _accumulate(sums, valid, speed, weight):
    """One wheel into (n_valid, lowest, highest, total, weight_sum, weighted)."""
    n_valid, lowest, highest, total, weight_sum, weighted = sums
    if not valid:
        return sums
    return (n_valid + 1, min(lowest, speed), max(highest, speed), total + speed,
            weight_sum + weight, weighted + weight * speed)


@nb.njit(cache=True, inline="always")
def vx_from_wheels(buf, i, v_fl, v_fr, v_rl, v_rr, valid_fl, valid_fr, valid_rl, valid_rr,
                   steer, yaw_rate, ax, vx_prev, track_f, track_r, dt, ax_threshold, sigma_w1,
                   sigma_w2):  # fmt: skip
    """Longitudinal speed from the four wheel speeds (Fig. 4, eq. 11-13).

    Wheel speeds are first compensated for steer and yaw (eq. 11, ``compensate_wheel_speeds``).
    Then by the ax thresholds of Fig. 4:
    - ax > ax_threshold (accelerating, wheels spin faster than the car): the slowest wheel;
    - ax < -ax_threshold (braking, wheels slower): the fastest wheel;
    - otherwise the weighted mean of eq. 12 with the weights of eq. 13 (``wheel_weight``),
      which drops a wheel whose derivative disagrees with ax or whose speed disagrees with
      the previous estimate ``vx_prev`` (a spinning or locking wheel). If every weight
      underflows (all wheels disagree with vx_prev, e.g. after an outage) the median of the
      valid wheels is used instead of dividing by ~0.
    Invalid wheels take no part in any branch; their derivative-filter memory is held.

    ``buf[i + Wheels.*]``: derivative-filter memory per wheel (NaN at start). ``ax``: the
    corrected CoG ax (m/s^2); ``vx_prev``: the previous vx estimate (NaN if none);
    Table 1: ax_threshold 1 m/s^2, sigma_w1 4.5, sigma_w2 1.
    Returns (vx, mode) with mode a ``VxMode`` value as float; vx is NaN with no valid wheel.
    """
    c_fl, c_fr, c_rl, c_rr = compensate_wheel_speeds(
        v_fl, v_fr, v_rl, v_rr, steer, yaw_rate, track_f, track_r
    )
    w_fl = _wheel_update(buf, i + Wheels.FL, c_fl, valid_fl, ax, vx_prev, dt, sigma_w1, sigma_w2)
    w_fr = _wheel_update(buf, i + Wheels.FR, c_fr, valid_fr, ax, vx_prev, dt, sigma_w1, sigma_w2)
    w_rl = _wheel_update(buf, i + Wheels.RL, c_rl, valid_rl, ax, vx_prev, dt, sigma_w1, sigma_w2)
    w_rr = _wheel_update(buf, i + Wheels.RR, c_rr, valid_rr, ax, vx_prev, dt, sigma_w1, sigma_w2)
    # unrolled over the four wheels: no temporary arrays in the per-tick path
    sums = (0, math.inf, -math.inf, 0.0, 0.0, 0.0)
    sums = _accumulate(sums, valid_fl, c_fl, w_fl)
    sums = _accumulate(sums, valid_fr, c_fr, w_fr)
    sums = _accumulate(sums, valid_rl, c_rl, w_rl)
    sums = _accumulate(sums, valid_rr, c_rr, w_rr)
    n_valid, lowest, highest, total, weight_sum, weighted = sums
    if n_valid == 0:
        return math.nan, _MODE_NONE
    if ax > ax_threshold:
        return lowest, _MODE_MIN
    if ax < -ax_threshold:
        return highest, _MODE_MAX
    if weight_sum > MIN_WEIGHT_SUM:
        return weighted / weight_sum, _MODE_MEAN
    # Median of up to four values without sorting: drop the extremes, average the rest.
    if n_valid >= 3:
        return (total - lowest - highest) / (n_valid - 2), _MODE_MEDIAN
    return total / n_valid, _MODE_MEDIAN
