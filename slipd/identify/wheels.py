"""Relative rolling radius of each wheel (straight, steady driving), absolute against the GNSS
speed where the bus carries it.

On a straight at constant speed with little drive or brake torque every wheel rolls at the
car's speed, so a wheel that reads more has a larger (assumed) radius than its real rolling
radius: scale_i = v / w_i (ISO 8855 straight running; the tyre's longitudinal slip at a steady
speed is ~0.1 %, Pacejka, Tire and Vehicle Dynamics, 3rd ed. 2012, ch. 1.2). Without a speed
reference v is the mean of the four wheels (the scales' geometric mean is then 1: only the
wheels' differences are found); with GNSS it is the receiver's 3-D speed (its 0.1-0.5 s
latency does not matter at a steady speed).
"""

from __future__ import annotations

import math

import numpy as np

from slipd.channels import In
from slipd.identify.data import Signals, lowpass, runs, split
from slipd.identify.results import Finding, Missing, Outcome, segment_mean

SOURCE = ("straight steady driving: every wheel at the car's speed (Pacejka 2012, ch. 1.2: "
          "~0.1 % free-rolling slip)")
MIN_SPEED = 8.0  # m/s
MAX_YAW_RATE = math.radians(1.0)
MAX_AX = 0.3  # m/s^2: little drive or brake slip
MIN_SEGMENT_S = 3.0
#: relative, the method's model error added to each interval in quadrature: a wheel at a
#: steady speed is not slip-free, a driven one runs ahead and a braked-by-rolling-resistance
#: one behind by ~0.1 % (Pacejka 2012, ch. 1.2; on simulated drives of CommonRoad vehicles
#: 1-3 front and rear came out 0.07-0.11 % apart from the truth).
SLIP_ALLOWANCE = 0.0015
WHEEL_CHANNELS = (In.WHEEL_SPEED_FL, In.WHEEL_SPEED_FR, In.WHEEL_SPEED_RL, In.WHEEL_SPEED_RR)


def steady_straights(sig: Signals, yaw_offset: float) -> list[tuple[int, int]]:
    ok = sig.all_ok(*WHEEL_CHANNELS, In.YAW_RATE, In.AX)
    r = lowpass(sig.yaw_rate - yaw_offset, 1.0)
    ax = lowpass(sig.ax, 1.0)
    dvx = lowpass(sig.dvx, 1.0)
    mask = ok & (sig.vx > MIN_SPEED) & (np.abs(r) < MAX_YAW_RATE) & (np.abs(dvx) < MAX_AX)
    mask &= np.abs(ax - np.median(ax[mask])) < 1.0 if mask.any() else mask
    return runs(mask, MIN_SEGMENT_S, 0.5)


def identify_wheels(sigs: list[Signals], yaw_offset: float, outcome: Outcome) -> dict:
    """Per wheel the relative rolling radius (``wheel_radius_scale``); findings into
    ``outcome``. Returns {'wheel_radius_scale': (fl, fr, rl, rr)} or {}."""
    measured = [k for k, s in enumerate(sigs)
                if not any(c.name.lower() in s.drive.derived for c in WHEEL_CHANNELS)]
    if sigs and not measured:
        how = next(iter(sigs[0].drive.derived.values()))
        outcome.add(Missing("calibration.wheel_radius_scale",
                            f"the wheel speeds were derived by slipd import ({how}), not "
                            "measured: rolling radii not identified"))
        return {}
    segs = [(k, a, b) for k in measured for a, b in steady_straights(sigs[k], yaw_offset)]
    if not segs:
        outcome.add(Missing("calibration.wheel_radius_scale",
                            "no straight steady driving above 8 m/s: rolling radii not "
                            "identified"))
        return {}
    units = split(segs, 30.0)
    with_gnss = all(sigs[k].gnss_speed is not None for k, _, _ in units)
    rows = []
    for k, a, b in units:
        w = sigs[k].wheels[a:b]
        mean = w.mean(axis=1)
        if with_gnss:
            reference = sigs[k].gnss_speed[a:b]
            good = np.isfinite(reference)
            if good.sum() < 0.5 * (b - a):
                with_gnss = False
            ratio = np.where(good[:, None], reference[:, None] / w, np.nan)
        else:
            ratio = mean[:, None] / w
        rows.append(ratio)
    if not with_gnss:  # a unit without fixes: all relative
        rows = [sigs[k].wheels[a:b].mean(axis=1)[:, None] / sigs[k].wheels[a:b]
                for k, a, b in units]
    values = [r[np.all(np.isfinite(r), axis=1)] for r in rows]
    values = [v for v in values if len(v)]
    scale, ci, how = segment_mean(values, seconds_per_independent=1.0)
    if not with_gnss:
        norm = math.exp(np.mean(np.log(scale)))
        scale = scale / norm
        ci = [(lo / norm, hi / norm) for lo, hi in ci]
    ci = [(float(v - math.hypot(0.5 * (hi - lo), SLIP_ALLOWANCE)),
           float(v + math.hypot(0.5 * (hi - lo), SLIP_ALLOWANCE)))
          for v, (lo, hi) in zip(scale, ci, strict=True)]
    how += f", +-{100 * SLIP_ALLOWANCE:g} % slip allowance"
    seconds = sum(b - a for _, a, b in segs) * 0.01
    logs = len({k for k, _, _ in segs})
    reference = "GNSS speed (absolute)" if with_gnss else \
        "mean of the four wheels (relative: no GNSS speed on the bus)"
    outcome.add(Finding("calibration.wheel_radius_scale", tuple(float(v) for v in scale),
                        tuple(ci), f"steady straights against the {reference}, {how}", SOURCE,
                        len(segs), seconds, logs))
    outcome.diagnostics["wheel_units"] = (units, with_gnss)
    return {"wheel_radius_scale": tuple(float(v) for v in scale)}
