"""Steering-wheel angle offset, steering ratio and understeer gradient: the handling diagram.

In steady-state cornering the single-track model gives the road-wheel angle
delta = L / R + K_us a_y with R = v_x / r and a_y = r v_x (Gillespie, Fundamentals of Vehicle
Dynamics, 1992, ch. 6, eq. 6-15 and the handling diagram of Fig. 6.6; Milliken & Milliken,
Race Car Vehicle Dynamics, 1995, ch. 5). The steering signal reads delta_meas = SWA / i_p with
the profile's ratio i_p, while the car's SWA = i delta + SWA_0. So, on quasi-steady ticks,

    delta_meas = A (L r / v_x) + B (r v_x) + c,   A = i / i_p,  B = A K_us,  c = SWA_0 / i_p,

linear in (A, B, c): least squares (scipy.optimize.least_squares with a soft-L1 loss, robust
to the odd transient that passes the selection). The low-speed (kinematic) corners fix A and
the offset, the faster ones K_us; the centripetal r v_x is used instead of the accelerometer,
so neither the IMU's offsets nor the body's roll nor the road's bank enter. The ratio is the
one that makes the profile's wheelbase L right: a wrong wheelbase comes back as a wrong
ratio, with the same product i / L that the kinematics see.
"""

from __future__ import annotations

import math

import numpy as np

from slipd.channels import In, Veh
from slipd.identify.data import DT, Signals, lowpass, runs, split
from slipd.identify.results import Finding, Missing, Outcome, regression_interval

SOURCE = ("steady-state handling diagram delta = L/R + K_us a_y (Gillespie 1992, ch. 6, "
          "eq. 6-15; Milliken & Milliken 1995, ch. 5)")
MIN_SPEED = 3.0  # m/s
MAX_AY = 4.0  # m/s^2: the linear range (~0.4 g on a dry road)
MAX_AX = 1.0  # m/s^2: no hard driving or braking (their forces steer the car too)
MAX_YAW_ACC = 0.05  # rad/s^2 (low-passed): quasi-steady
MAX_STEER_RATE = 0.01  # rad/s of the road wheels (low-passed)
MIN_SEGMENT_S = 1.0
PIECE_S = 20.0
MIN_CORNER_AY = 1.0  # m/s^2: segments that corner at least this much carry the gradient
#: fit every 10th tick (10 Hz): the signals are low-passed at 1 Hz, so the ticks between
#: carry no new information and only cost the bootstrap's 200 fits time
DECIMATE = 10
#: rad of road-wheel angle, the offset's model error (added to its interval in quadrature): a
#: car does not drive straight at a zero road-wheel angle (its tyres' ply steer and conicity
#: pull, the road's cross slope), and the intercept carries that with the sensor's offset
#: (on simulated drives of CommonRoad vehicles 1 and 3 up to 0.008 deg; 0.01 deg here)
OFFSET_MODEL_ERROR = math.radians(0.01)


def quasi_steady(sig: Signals, max_ay: float = MAX_AY) -> np.ndarray:
    """Ticks of quasi-steady driving in the linear range (every signal of the diagram valid)."""
    ok = sig.all_ok(In.STEER, In.YAW_RATE, In.WHEEL_SPEED_RL, In.WHEEL_SPEED_RR, In.AX)
    r = lowpass(sig.yaw_rate, 1.0)
    vx = lowpass(sig.vx, 1.0)
    steer_rate = np.gradient(lowpass(sig.steer, 1.0), DT)
    yaw_acc = np.gradient(r, DT)
    ax = lowpass(sig.ax, 1.0)
    return (ok & (vx > MIN_SPEED) & (np.abs(r * vx) < max_ay) & (np.abs(ax) < MAX_AX)
            & (np.abs(yaw_acc) < MAX_YAW_ACC) & (np.abs(steer_rate) < MAX_STEER_RATE))


def handling_data(sigs: list[Signals], wheelbase: float):
    """Per segment piece: (drive, start, stop, kinematic L r/vx, centripetal r vx, delta)."""
    pieces = []
    for k, s in enumerate(sigs):
        r = lowpass(s.yaw_rate, 1.0)
        vx = lowpass(s.vx, 1.0)
        delta = lowpass(s.steer, 1.0)
        for _, a, b in split([(k, a, b) for a, b in runs(quasi_steady(s), MIN_SEGMENT_S, 0.2)],
                             PIECE_S):
            ticks = slice(a, b, DECIMATE)
            pieces.append((k, a, b, wheelbase * r[ticks] / vx[ticks], r[ticks] * vx[ticks],
                           delta[ticks]))
    return pieces


def _fit(pieces, idx) -> np.ndarray:
    from scipy.optimize import least_squares

    kin = np.concatenate([pieces[i][3] for i in idx])
    cen = np.concatenate([pieces[i][4] for i in idx])
    delta = np.concatenate([pieces[i][5] for i in idx])
    X = np.column_stack([kin, cen, np.ones_like(kin)])
    start, *_ = np.linalg.lstsq(X, delta, rcond=None)
    result = least_squares(lambda p: X @ p - delta, start, loss="soft_l1", f_scale=0.002)
    return result.x


def identify_steering(sigs: list[Signals], profile, outcome: Outcome) -> dict:
    """Steering ratio, steering-wheel offset and understeer gradient from the handling
    diagram; findings (or reasons) into ``outcome``. Returns {'steering_ratio',
    'steer_offset_deg', 'understeer_gradient' (rad per m/s^2)}."""
    veh = profile.vehicle
    wheelbase = float(veh[Veh.LF] + veh[Veh.LR])
    ratio = float(veh[Veh.STEER_RATIO])
    divisor = profile.calibration.steer_divisor
    pieces = handling_data(sigs, wheelbase)
    seconds = sum(p[2] - p[1] for p in pieces) * DT
    cornering = [p for p in pieces if np.abs(p[4]).mean() > MIN_CORNER_AY]
    if not pieces or len(cornering) < 2:
        reason = ("no quasi-steady cornering in the linear range (|ay| < 4 m/s^2, speed > 3 "
                  f"m/s): steering ratio and offset not identified ({seconds:.0f} s "
                  f"quasi-steady, {len(cornering)} segment(s) cornering)")
        for key in ("vehicle.steering_ratio", "calibration.steer_offset_deg"):
            outcome.add(Missing(key, reason))
        return {}
    estimate = _fit(pieces, np.arange(len(pieces)))
    intervals, how = regression_interval(lambda idx: _fit(pieces, idx), len(pieces), estimate)
    gain, gradient_gain, intercept = estimate
    logs = len({p[0] for p in pieces})
    new_ratio = gain * ratio if divisor != 1.0 else gain * ratio
    offset_deg = math.degrees(intercept * divisor)
    k_us = gradient_gain / gain
    outcome.diagnostics["handling"] = {"pieces": pieces, "fit": estimate, "ratio": ratio,
                                       "wheelbase": wheelbase, "divisor": divisor}
    method = f"handling diagram, least squares (soft L1), {how}"
    found = {"steer_offset_deg": offset_deg, "understeer_gradient": k_us}
    lo, hi = intervals[2]
    half = math.hypot(0.5 * (hi - lo), OFFSET_MODEL_ERROR) if math.isfinite(hi - lo) else hi - lo
    outcome.add(Finding(
        "calibration.steer_offset_deg", offset_deg,
        (math.degrees((intercept - half) * divisor), math.degrees((intercept + half) * divisor)),
        method + f", +-{math.degrees(OFFSET_MODEL_ERROR):g} deg road-wheel model error", SOURCE,
        len(pieces), seconds, logs,
        note="at the steering wheel" if divisor != 1.0 else "of the road-wheel angle"))
    if divisor != 1.0:
        found["steering_ratio"] = new_ratio
        outcome.add(Finding(
            "vehicle.steering_ratio", new_ratio, tuple(v * ratio for v in intervals[0]),
            method, SOURCE, len(pieces), seconds, logs,
            note=f"for the profile's wheelbase {wheelbase:.4g} m"))
    else:
        outcome.add(Missing("vehicle.steering_ratio",
                            "the steer channel is not divided by steering_ratio (it carries the "
                            f"road-wheel angle): its gain against L r / v_x is {gain:.4f}"))
    outcome.diagnostics["understeer_gradient"] = (
        k_us, tuple(v / gain for v in intervals[1]))
    return found
