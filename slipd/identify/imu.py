"""The IMU's errors: gyro and accelerometer offsets and the mounting misalignment.

Sensor model (the simulator's and slipd.codec.calibration's): the IMU reads
s = R^T v + b of a body-frame vector v (specific force f or angular rate w), R = Rz(yaw)
Ry(pitch) Rx(roll) its mounting, b its offsets. For small angles theta = (roll, pitch, yaw),
R^T v = v - theta x v, so the channels read

    ax = fx - pitch fz + yaw fy + bx      p = wx - pitch wz + yaw wy + bp
    ay = fy - yaw fx + roll fz + by       q = wy - yaw wx + roll wz + bq
    az = fz - roll fy + pitch fx + bz     r = wz - roll wy + pitch wx + br

Methods (each quantity says which one found it):

- gyro offsets: the mean at standstill (w = 0; the earth's rate, 0.004 deg/s, is below any
  automotive gyro's resolution). Without a standstill: roll and pitch rate average to zero
  over a drive (roll and pitch angles are bounded), so their offsets are the intercepts of the
  misalignment regressions below; the yaw-rate offset is the median yaw rate on straights.
- roll and pitch misalignment: a stationary accelerometer cannot tell a tilt from an offset
  (the levelling error of an INS is b/g: Titterton & Weston, Strapdown Inertial Navigation
  Technology, 2nd ed. 2004, sec. 10.3.1; Groves, Principles of GNSS, Inertial, and
  Multisensor Integrated Navigation Systems, 2nd ed. 2013, sec. 5.6.2), so gravity at
  standstill gives ax and ay offsets only once the tilt is known. The tilt comes from the
  cross-coupling it causes while driving: the yaw rate leaks into the roll- and pitch-rate
  channels (slopes -pitch and +roll), and ax and ay leak into az (slopes +pitch and -roll);
  roll and pitch motion are uncorrelated with the yaw rate and are quadratic in ay and ax,
  which the regressions carry as nuisance terms. Both estimates, where the channels exist,
  are combined by their variances.
- yaw misalignment: the ax/ay correlation in straight acceleration and braking, ay = fy - yaw
  ax, on the signals with roll and pitch already corrected (the centripetal r vx of
  near-straight driving is a regressor too; every straight has its own intercept: bank and
  offsets; with a roll rate, the bank's changes along a straight are taken out).
- accelerometer offsets: the mean at standstill minus gravity through the mounting,
  b = s - R^T (0, 0, g) with g = 9.81 m/s^2 (local gravity differs by up to 0.03 m/s^2: the az
  offset carries that; roads at the stops are taken as level on average, their slopes enter
  the interval through the spread between stops). Without a standstill: on straights, ax
  against the wheels' dvx/dt and ay against r vx (grades and banks average out).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from slipd.channels import G, In
from slipd.codec.calibration import mounting_rotation
from slipd.identify.data import DT, Signals, lowpass, runs, split
from slipd.identify.results import (
    MIN_BOOTSTRAP_SEGMENTS,
    Finding,
    Missing,
    Outcome,
    bootstrap,
    percentile_interval,
    segment_mean,
)
from slipd.profile import Calibration

STANDSTILL_SPEED = 0.05  # m/s, every wheel below: standing
STANDSTILL_MIN_S = 3.0  # s of standing for a usable standstill
STANDSTILL_TRIM_S = 1.0  # s cut at each end (the body settles after the stop)
DRIVING_SPEED = 5.0  # m/s, above: driving for the misalignment regressions
STRAIGHT_YAW_RATE = math.radians(1.5)  # rad/s, below (offset removed): straight
STRAIGHT_MIN_S = 3.0
PIECE_S = 60.0  # s, the bootstrap unit of the driving regressions
YAW_PIECE_S = 10.0  # s, shorter: the roll rate integrated over a piece drifts with its offset
LEVEL_FRAME_AZ = 0.5 * G  # az below this on average: a gravity-free (level-frame) accelerometer
#: rad, the tilt regressions' model error (added to their intervals in quadrature): their
#: bias on noise-free simulated drives (slipd sim endurance, vehicles 1-3, mountings up to
#: 1.5 deg) was below 0.15 deg; the road's grade and bank along the route cause it.
TILT_MODEL_ERROR = math.radians(0.15)
STRAIGHT_YAW_RATE_STRICT = math.radians(0.5)  # rad/s, straights for the yaw misalignment
REGRESSION_DECIMATE = 4  # ticks: the regressions fit at 25 Hz (their inputs are below 2 Hz)

SOURCE_STANDSTILL = ("standstill mean (Titterton & Weston 2004, sec. 10.3.1: stationary "
                     "alignment)")
SOURCE_MISALIGN = ("cross-coupling regressions while driving (slipd.identify.imu; levelling "
                   "error = b/g: Titterton & Weston 2004, sec. 10.3.1)")


def _sd(interval: tuple[float, float]) -> float:
    """Standard deviation of a 95 % interval (NaN stays NaN)."""
    return (interval[1] - interval[0]) / (2 * 1.96)


def standstills(sigs: list[Signals]) -> list[tuple[int, int, int]]:
    """(drive index, start, stop) of every standstill: all four wheels valid and below
    STANDSTILL_SPEED for at least STANDSTILL_MIN_S after trimming."""
    found = []
    for k, s in enumerate(sigs):
        wheels_ok = s.all_ok(In.WHEEL_SPEED_FL, In.WHEEL_SPEED_FR, In.WHEEL_SPEED_RL,
                             In.WHEEL_SPEED_RR)
        still = wheels_ok & (np.abs(s.wheels).max(axis=1) < STANDSTILL_SPEED)
        for a, b in runs(still, STANDSTILL_MIN_S, STANDSTILL_TRIM_S):
            found.append((k, a, b))
    return found


def _seconds(segments) -> float:
    return float(sum(b - a for _, a, b in segments) * DT)


def _logs(segments) -> int:
    return len({k for k, _, _ in segments})


GYRO = (In.ROLL_RATE, In.PITCH_RATE, In.YAW_RATE)
ACCEL = (In.AX, In.AY, In.AZ)


def _channel(s: Signals, channel: In) -> np.ndarray:
    return {In.AX: s.ax, In.AY: s.ay, In.AZ: s.az, In.ROLL_RATE: s.roll_rate,
            In.PITCH_RATE: s.pitch_rate, In.YAW_RATE: s.yaw_rate}[channel]


def gyro_offsets_at_standstill(sigs: list[Signals], stops, outcome: Outcome
                               ) -> np.ndarray | None:
    """rad/s (roll, pitch, yaw rate; NaN for a channel the car lacks) from the standstills,
    or None without one."""
    if not stops:
        return None
    present = [c for c in GYRO if any(s.has(c) for s in sigs)]
    values = [np.column_stack([_channel(sigs[k], c)[a:b] for c in present]) for k, a, b in stops]
    mean, ci, how = segment_mean(values, seconds_per_independent=1.0)
    result = np.full(3, np.nan)
    intervals = [(math.nan, math.nan)] * 3
    for i, c in enumerate(present):
        j = GYRO.index(c)
        result[j] = mean[i]
        intervals[j] = ci[i]
    outcome.diagnostics["standstill_gyro"] = (stops, result)
    outcome.add(Finding(
        "calibration.gyro_offset", tuple(float(np.degrees(v)) if math.isfinite(v) else 0.0
                                         for v in result),
        tuple((float(np.degrees(lo)), float(np.degrees(hi))) for lo, hi in intervals),
        f"standstill mean, {how}", SOURCE_STANDSTILL, len(stops), _seconds(stops),
        _logs(stops),
        note="" if len(present) == 3 else
        "no " + ", ".join(c.name.lower() for c in GYRO if c not in present) + " channel: 0"))
    return result


def _driving_pieces(sigs: list[Signals], channels, min_speed: float = DRIVING_SPEED):
    pieces = []
    for k, s in enumerate(sigs):
        mask = s.all_ok(*channels) & (s.vx > min_speed)
        for a, b in split(runs(mask, 10.0), PIECE_S):
            pieces.append((k, a, b))
    return pieces


def _within(x: np.ndarray, groups: list[slice]) -> np.ndarray:
    """``x`` ([n] or [n, k]) with each group's mean removed (one intercept per segment)."""
    out = np.array(x, dtype=np.float64, copy=True)
    for g in groups:
        out[g] -= out[g].mean(axis=0)
    return out


def _stacked_regression(units: list[tuple[np.ndarray, np.ndarray]], n_out: int = 1):
    """Least squares of y on X with one intercept per unit (units: (y [m], X [m, k])).
    Returns fit(indices) -> the first ``n_out`` coefficients, for the bootstrap."""
    # every REGRESSION_DECIMATE-th tick: the signals are low-passed at 1-2 Hz
    demeaned = [((y - y.mean())[::REGRESSION_DECIMATE], (X - X.mean(axis=0))[::REGRESSION_DECIMATE])
                for y, X in units]

    def fit(idx: np.ndarray) -> np.ndarray:
        y = np.concatenate([demeaned[i][0] for i in idx])
        X = np.concatenate([demeaned[i][1] for i in idx])
        coef, *_ = np.linalg.lstsq(X, y, rcond=None)
        return coef[:n_out]

    return fit


def _widen(ci: tuple[float, float]) -> tuple[float, float]:
    """A 95 % interval widened by the model-error allowance of the tilt regressions."""
    if not all(math.isfinite(v) for v in ci):
        return ci
    centre, half = 0.5 * (ci[0] + ci[1]), 0.5 * (ci[1] - ci[0])
    half = math.hypot(half, TILT_MODEL_ERROR)
    return centre - half, centre + half


def _regress(units):
    """(estimate, 95 % interval, n units) of the first coefficient."""
    fit = _stacked_regression(units)
    estimate = float(fit(np.arange(len(units)))[0])
    if len(units) >= MIN_BOOTSTRAP_SEGMENTS:
        intervals = percentile_interval(bootstrap(fit, len(units)))
        if intervals:
            return estimate, intervals[0]
    return estimate, (math.nan, math.nan)


def tilt_from_gyro(sigs: list[Signals]) -> dict:
    """Roll and pitch misalignment from the yaw rate's leak into the roll- and pitch-rate
    channels (slopes +roll on q, -pitch on p). The Euler kinematics p = phi' - psi' sin(theta),
    q = theta' + psi' phi (ISO 8855) add r times the pitch and roll of body and road, which ax
    and ay carry (g sin of them, centred so that their offsets do not leak into the slope):
    r (ax - mean) and r (ay - mean) are nuisance regressors. Returns {'roll': (est, ci),
    'pitch': ..., 'units', 'seconds', 'logs', 'intercepts': (bp, bq)} or {}."""
    if not any(s.has(In.ROLL_RATE) and s.has(In.PITCH_RATE) for s in sigs):
        return {}
    pieces = _driving_pieces(sigs, (In.ROLL_RATE, In.PITCH_RATE, In.YAW_RATE, In.AX, In.AY))
    if len(pieces) < 2:
        return {}
    filtered = {}
    for k in {k for k, _, _ in pieces}:
        s = sigs[k]
        mask = s.all_ok(In.AX, In.AY) & (s.vx > DRIVING_SPEED)
        ax, ay = lowpass(s.ax, 2.0), lowpass(s.ay, 2.0)
        filtered[k] = [lowpass(s.roll_rate, 2.0), lowpass(s.pitch_rate, 2.0),
                       lowpass(s.yaw_rate, 2.0), ax - ax[mask].mean(), ay - ay[mask].mean()]
    p_units, q_units = [], []
    for k, a, b in pieces:
        p, q, r, ax, ay = (x[a:b] for x in filtered[k])
        p_units.append((p, np.column_stack([r, r * ax])))
        q_units.append((q, np.column_stack([r, r * ay])))
    minus_pitch, pitch_ci = _regress(p_units)
    roll, roll_ci = _regress(q_units)
    intercepts = []
    for units in (p_units, q_units):  # offsets without a standstill: the intercepts at r = 0
        y = np.concatenate([u[0] for u in units])
        X = np.concatenate([u[1] for u in units])
        intercepts.append(float(np.linalg.lstsq(np.column_stack([np.ones(len(y)), X]), y,
                                                rcond=None)[0][0]))
    return {"roll": (roll, _widen(roll_ci)),
            "pitch": (-minus_pitch, _widen((-pitch_ci[1], -pitch_ci[0]))),
            "units": len(pieces), "seconds": _seconds(pieces), "logs": _logs(pieces),
            "intercepts": tuple(intercepts)}


def level_frame(sigs: list[Signals]) -> bool:
    """True when az carries no gravity (an INS's gravity-compensated, levelled output)."""
    values = [s.az[s.ok[In.AZ]] for s in sigs if s.has(In.AZ)]
    if not values:
        return False
    return bool(np.median(np.concatenate(values)) < LEVEL_FRAME_AZ)


def tilt_from_accel(sigs: list[Signals], still_accel: np.ndarray | None) -> dict:
    """Roll and pitch misalignment from ax's and ay's leak into az (slopes +pitch, -roll),
    with the squares of the body's fx and fy for its own pitch and roll. The regressors are the
    body-frame specific force of the estimate so far, f = R (s - b) with the offsets b the
    standstill gives for that R (three passes): a tilt or an offset left in ax and ay would,
    squared, leak into the linear terms. Without a standstill the squares come from the
    wheels' dvx/dt and r vx instead. {} without az (or a level-frame az)."""
    if not any(s.has(In.AZ) for s in sigs) or level_frame(sigs):
        return {}
    pieces = _driving_pieces(sigs, (In.AX, In.AY, In.AZ, In.YAW_RATE))
    if len(pieces) < 2:
        return {}
    kinematic = {}
    filtered = {}
    for k in {k for k, _, _ in pieces}:
        s = sigs[k]
        filtered[k] = np.column_stack([lowpass(x, 2.0) for x in (s.ax, s.ay, s.az)])
        vx = lowpass(s.vx, 2.0)
        kinematic[k] = (lowpass(s.dvx, 2.0), lowpass(s.yaw_rate, 2.0) * vx)
    angles = np.zeros(3)
    for _ in range(3):
        rotation = mounting_rotation(*angles)
        offset = (still_accel - rotation.T @ np.array([0.0, 0.0, G])
                  if still_accel is not None else np.zeros(3))
        pitch_units, roll_units = [], []
        for k, a, b in pieces:
            body = (filtered[k][a:b] - offset) @ rotation.T
            if still_accel is not None:
                sq_x, sq_y = body[:, 0] ** 2, body[:, 1] ** 2
            else:
                sq_x, sq_y = kinematic[k][0][a:b] ** 2, kinematic[k][1][a:b] ** 2
            X = np.column_stack([body[:, 0], body[:, 1], sq_x, sq_y])
            pitch_units.append((body[:, 2], X))
            roll_units.append((body[:, 2], X[:, [1, 0, 2, 3]]))
        d_pitch, pitch_ci = _regress(pitch_units)
        minus_d_roll, roll_ci = _regress(roll_units)
        angles[0] -= minus_d_roll
        angles[1] += d_pitch
    roll_ci = (angles[0] - roll_ci[1] + minus_d_roll, angles[0] - roll_ci[0] + minus_d_roll)
    pitch_ci = (angles[1] + pitch_ci[0] - d_pitch, angles[1] + pitch_ci[1] - d_pitch)
    return {"roll": (float(angles[0]), _widen(roll_ci)),
            "pitch": (float(angles[1]), _widen(pitch_ci)),
            "units": len(pieces), "seconds": _seconds(pieces), "logs": _logs(pieces)}


def _combine(estimates: list[tuple[float, tuple[float, float]]]
             ) -> tuple[float, tuple[float, float]]:
    """Inverse-variance mean of (estimate, 95 % interval) pairs (an interval-less estimate
    only counts when it is alone)."""
    usable = [(e, _sd(ci)) for e, ci in estimates if math.isfinite(_sd(ci)) and _sd(ci) > 0]
    if not usable:
        e = estimates[0][0]
        return e, (math.nan, math.nan)
    w = np.array([1.0 / sd**2 for _, sd in usable])
    e = float(np.sum(w * np.array([x for x, _ in usable])) / w.sum())
    sd = float(1.0 / math.sqrt(w.sum()))
    return e, (e - 1.96 * sd, e + 1.96 * sd)


def straights(sigs: list[Signals], yaw_offset: float, min_speed: float = DRIVING_SPEED,
              threshold: float = STRAIGHT_YAW_RATE):
    """(drive, start, stop) of straight driving: yaw rate (offset removed) below
    ``threshold`` for STRAIGHT_MIN_S, above ``min_speed``."""
    found = []
    for k, s in enumerate(sigs):
        r = lowpass(s.yaw_rate - yaw_offset, 1.0)
        mask = s.all_ok(In.AX, In.AY, In.YAW_RATE, In.WHEEL_SPEED_RL, In.WHEEL_SPEED_RR)
        mask &= (np.abs(r) < threshold) & (s.vx > min_speed)
        for a, b in runs(mask, STRAIGHT_MIN_S, 0.5):
            found.append((k, a, b))
    return found


def lateral_gain(sigs: list[Signals], yaw_offset: float) -> float:
    """d ay / d (r vx) while cornering: 1 plus the gravity of the body's roll per unit of
    lateral acceleration (a body-frame accelerometer reads a_y + g sin(phi))."""
    pieces = _driving_pieces(sigs, (In.AY, In.YAW_RATE))
    units = []
    for k, a, b in pieces:
        s = sigs[k]
        centripetal = lowpass((s.yaw_rate[a:b] - yaw_offset) * s.vx[a:b], 1.0)
        units.append((lowpass(s.ay[a:b], 1.0), centripetal[:, None]))
    if len(units) < 2:
        return 1.0
    return float(_stacked_regression(units)(np.arange(len(units)))[0])


def yaw_misalignment(sigs: list[Signals], yaw_offset: float, roll_offset: float) -> dict:
    """Yaw misalignment from ay = fy - yaw ax on straights (yaw rate below 0.5 deg/s) while
    accelerating and braking, an intercept and a trend per straight. What is left of cornering
    on a straight correlates with ax (the braking before a bend): it is taken out with a known
    gain, r vx with a roll rate (the roll integrated takes the bank and the body's roll) or
    lateral_gain x r vx without one (the bank's changes along a straight then stay in: said in
    the result). A fitted gain would come out attenuated: r is small and noisy on straights."""
    segs = straights(sigs, yaw_offset, threshold=STRAIGHT_YAW_RATE_STRICT)
    units = []
    with_roll = all(sigs[k].has(In.ROLL_RATE) for k, _, _ in segs) if segs else False
    gain = 1.0 if with_roll else lateral_gain(sigs, yaw_offset)
    for k, a, b in split(segs, YAW_PIECE_S):
        s = sigs[k]
        ax, ay = lowpass(s.ax[a:b], 2.0), lowpass(s.ay[a:b], 2.0)
        if with_roll:
            ay = ay - G * np.cumsum(s.roll_rate[a:b] - roll_offset) * DT
            if s.has(In.PITCH_RATE):
                # the yaw error left also leaks the pitch rate into that roll rate: yaw g
                # (pitch change) enters ay, so the regressor is ax + g (pitch change), the
                # acceleration without the grade's and the pitching body's gravity
                q = s.pitch_rate[a:b]
                ax = ax + G * np.cumsum(q - q.mean()) * DT
        ay = ay - gain * lowpass((s.yaw_rate[a:b] - yaw_offset) * s.vx[a:b], 2.0)
        units.append((ay, np.column_stack([ax, np.arange(b - a) * DT])))
    spread = float(np.std(np.concatenate([u[1][:, 0] for u in units]))) if units else 0.0
    if not units:
        return {"reason": "no straight driving above 5 m/s (yaw rate below 0.5 deg/s for 3 s)"}
    if len(units) < 2:
        return {"reason": f"one straight only ({_seconds(segs):.0f} s with the yaw rate below "
                          "0.5 deg/s for 3 s at a time; needs two)"}
    if spread < 0.3:
        return {"reason": "no straight acceleration or braking (ax varies by "
                          f"{spread:.2f} m/s^2 on straights, needs 0.3)"}
    minus_yaw, ci = _regress(units)
    return {"yaw": (-minus_yaw, (-ci[1], -ci[0])), "units": len(units), "seconds": _seconds(segs),
            "logs": _logs(segs),
            "note": "" if with_roll else "no roll rate: bank changes along the straights are "
                                         "not compensated"}


def yaw_rate_offset_on_straights(sigs: list[Signals]) -> tuple[float, tuple[float, float], int,
                                                                float, int] | None:
    """The median yaw rate on straights (two passes: the straights are found again around
    the first estimate)."""
    offset = 0.0
    for _ in range(2):
        segs = straights(sigs, offset, min_speed=8.0)
        if not segs:
            return None
        values = [sigs[k].yaw_rate[a:b] for k, a, b in segs]
        offset = float(np.median(np.concatenate(values)))
    mean, ci, _ = segment_mean([v - offset for v in values])
    return offset + float(mean[0]), (offset + ci[0][0], offset + ci[0][1]), len(segs), \
        _seconds(segs), _logs(segs)


def identify_imu(sigs: list[Signals], outcome: Outcome,
                 resignal: Callable[[Calibration], list[Signals]]) -> dict:
    """Gyro offsets, mounting and accelerometer offsets on the raw signals ``sigs``; the yaw
    misalignment on ``resignal(calibration)``, the signals with the gyro offsets, roll and
    pitch found so far corrected (R = Rz(yaw) Ry(pitch) Rx(roll): the yaw is the last
    rotation). Adds findings (or the reasons) to ``outcome`` and returns the values found in
    calibration units ({'gyro_offset': deg/s x3, 'imu_mounting_deg': deg x3,
    'accel_offset': m/s^2 x3})."""
    found: dict = {}
    stops = standstills(sigs)
    outcome.diagnostics["standstills"] = stops
    has_gyro = any(s.has(In.YAW_RATE) for s in sigs)

    # -- gyro offsets -------------------------------------------------------------------------
    gyro = gyro_offsets_at_standstill(sigs, stops, Outcome()) if stops else None
    tilt_g = tilt_from_gyro(sigs)
    if gyro is None and has_gyro:
        off = np.zeros(3)
        intervals = [(0.0, 0.0)] * 3
        parts, notes, n_seg, secs, logs = [], [], 0, 0.0, 0
        if tilt_g:
            off[0], off[1] = tilt_g["intercepts"]
            intervals[0] = intervals[1] = (math.nan, math.nan)
            parts.append("roll/pitch rate: intercepts of the misalignment regressions")
            n_seg, secs, logs = tilt_g["units"], tilt_g["seconds"], tilt_g["logs"]
        else:
            notes.append("roll/pitch rate: no channel")
        yaw = yaw_rate_offset_on_straights(sigs)
        if yaw is not None:
            off[2] = yaw[0]
            intervals[2] = yaw[1]
            parts.append("yaw rate: median on straights")
            n_seg, secs, logs = n_seg + yaw[2], secs + yaw[3], max(logs, yaw[4])
        if yaw is None and not tilt_g:
            outcome.add(Missing("calibration.gyro_offset",
                                "no standstill and no straight driving: gyro offsets not "
                                "identified"))
        else:
            gyro = off
            outcome.add(Finding(
                "calibration.gyro_offset", tuple(float(np.degrees(v)) for v in off),
                tuple((float(np.degrees(lo)), float(np.degrees(hi))) for lo, hi in intervals),
                "no standstill: " + "; ".join(parts),
                "straight driving (yaw rate ~ 0 on straights; roll and pitch angles bounded)",
                n_seg, secs, logs, note="; ".join(notes)))
    elif gyro is not None:
        gyro_offsets_at_standstill(sigs, stops, outcome)
    elif not has_gyro:
        outcome.add(Missing("calibration.gyro_offset", "no gyro channel"))
    if gyro is not None:
        gyro = np.where(np.isfinite(gyro), gyro, 0.0)
        found["gyro_offset"] = tuple(float(np.degrees(v)) for v in gyro)
    yaw_offset = float(gyro[2]) if gyro is not None else 0.0

    # -- mounting -----------------------------------------------------------------------------
    present_accel = [c for c in ACCEL if any(sg.has(c) for sg in sigs)]
    still_accel = None
    if stops and len(present_accel) == 3:
        still_accel = np.mean(np.concatenate([np.column_stack(
            [_channel(sigs[k], c)[a:b] for c in ACCEL]) for k, a, b in stops]), axis=0)
    tilt_a = tilt_from_accel(sigs, still_accel)
    angles = np.zeros(3)
    intervals = [(0.0, 0.0)] * 3
    methods, reasons = [], []
    segments = seconds = logs = 0
    for index, name in ((0, "roll"), (1, "pitch")):
        sources = [fit[name] for fit in (tilt_g, tilt_a) if fit]
        if sources:
            angles[index], intervals[index] = _combine(sources)
    if tilt_g:
        methods.append("roll/pitch: yaw rate into roll/pitch rate")
        segments, seconds, logs = tilt_g["units"], tilt_g["seconds"], tilt_g["logs"]
    if tilt_a:
        methods.append("roll/pitch: ax/ay into az")
        segments = max(segments, tilt_a["units"])
        seconds, logs = max(seconds, tilt_a["seconds"]), max(logs, tilt_a["logs"])
    if not tilt_g and not tilt_a:
        reasons.append("roll/pitch not identified (needs roll and pitch rate or az while "
                       "driving; a standstill alone cannot tell a tilt from an offset): 0"
                       + ("; az is gravity-free (level frame)" if level_frame(sigs) else ""))
    # the yaw on the signals corrected for everything found so far, three passes: the yaw
    # misalignment leaks the pitch rate into the roll rate that takes the bank out of ay
    yaw_fit: dict = {}
    for _ in range(3):
        tilted = resignal(Calibration(
            imu_mounting_deg=(float(np.degrees(angles[0])), float(np.degrees(angles[1])),
                              float(np.degrees(angles[2]))),
            gyro_offset=tuple(float(np.degrees(v)) for v in gyro) if gyro is not None
            else (0.0, 0.0, 0.0)))
        step = yaw_misalignment(tilted, 0.0, 0.0)
        if "yaw" not in step:
            yaw_fit = step if not yaw_fit else yaw_fit
            break
        residual, ci = step["yaw"]
        angles[2] += residual
        yaw_fit = {**step, "yaw": (float(angles[2]), (angles[2] - residual + ci[0],
                                                      angles[2] - residual + ci[1]))}
        if abs(residual) < math.radians(0.01):
            break
    if "yaw" in yaw_fit:
        intervals[2] = yaw_fit["yaw"][1]
        methods.append("yaw: ax into ay on straights")
        if yaw_fit["note"]:
            reasons.append(yaw_fit["note"])
        segments += yaw_fit["units"]
        seconds += yaw_fit["seconds"]
        logs = max(logs, yaw_fit["logs"])
    else:
        reasons.append(f"yaw not identified: {yaw_fit['reason']}: 0")
    outcome.diagnostics["tilt"] = {"gyro": tilt_g, "accel": tilt_a, "yaw": yaw_fit}
    if methods:
        found["imu_mounting_deg"] = tuple(float(np.degrees(a)) for a in angles)
        outcome.add(Finding(
            "calibration.imu_mounting_deg", found["imu_mounting_deg"],
            tuple((float(np.degrees(lo)), float(np.degrees(hi))) for lo, hi in intervals),
            "; ".join(methods), SOURCE_MISALIGN, segments, seconds, logs,
            note="; ".join(reasons)))
    else:
        outcome.add(Missing("calibration.imu_mounting_deg", "; ".join(reasons)))

    # -- accelerometer offsets ----------------------------------------------------------------
    rotation = mounting_rotation(*angles)
    level = level_frame(sigs)
    gravity = np.zeros(3) if level else rotation.T @ np.array([0.0, 0.0, G])
    present = [c for c in ACCEL if any(s.has(c) for s in sigs)]
    if stops:
        values = [np.column_stack([_channel(sigs[k], c)[a:b] for c in present])
                  for k, a, b in stops]
        mean, ci, how = segment_mean(values, seconds_per_independent=1.0)
        offsets = np.zeros(3)
        bounds = [(0.0, 0.0)] * 3
        tilt_sd = [_sd(intervals[1]), _sd(intervals[0]), 0.0]  # ax <- pitch, ay <- roll
        for i, c in enumerate(present):
            j = ACCEL.index(c)
            offsets[j] = mean[i] - gravity[j]
            half = 0.5 * (ci[i][1] - ci[i][0])
            if math.isfinite(tilt_sd[j]) and not level:
                half = math.hypot(half, 1.96 * G * tilt_sd[j])
            bounds[j] = (offsets[j] - half, offsets[j] + half)
        found["accel_offset"] = tuple(float(v) for v in offsets)
        outcome.add(Finding(
            "calibration.accel_offset", found["accel_offset"], tuple(bounds),
            f"standstill mean minus gravity through the mounting, {how}",
            SOURCE_STANDSTILL, len(stops), _seconds(stops), _logs(stops),
            note=("gravity-free (level-frame) accelerometer; " if level else "") +
                 ("" if len(present) == 3 else "no az channel: 0")))
    else:
        segs = straights(sigs, yaw_offset)
        if not segs:
            outcome.add(Missing("calibration.accel_offset",
                                "no standstill and no straight driving: accelerometer offsets "
                                "not identified"))
        else:
            body_x, body_y, body_z = [], [], []
            for k, a, b in segs:
                s = sigs[k]
                f = np.column_stack([s.ax[a:b], s.ay[a:b], s.az[a:b] if s.has(In.AZ)
                                     else np.full(b - a, G)]) @ rotation.T
                body_x.append(f[:, 0] - s.dvx[a:b])
                body_y.append(f[:, 1] - (s.yaw_rate[a:b] - yaw_offset) * s.vx[a:b])
                body_z.append(f[:, 2] - (0.0 if level else G))
            mean, ci, how = segment_mean([np.column_stack(v) for v in
                                          zip(body_x, body_y, body_z, strict=True)])
            sensor = rotation.T @ mean
            if not any(s.has(In.AZ) for s in sigs):
                sensor[2] = 0.0
                ci[2] = (0.0, 0.0)
            found["accel_offset"] = tuple(float(v) for v in sensor)
            outcome.add(Finding(
                "calibration.accel_offset", found["accel_offset"],
                tuple((float(sensor[i] - (mean[i] - lo)), float(sensor[i] + (hi - mean[i])))
                      for i, (lo, hi) in enumerate(ci)),
                f"no standstill: ax - dvx/dt and ay - r vx on straights, {how}",
                "straight driving (grades and banks average out)", len(segs), _seconds(segs),
                _logs(segs),
                note="the x/y values include the unidentified tilt's g sin(angle)" if
                not (tilt_g or tilt_a) else ""))
    return found
