"""Roll gradient and roll stiffness from the roll rate.

The estimators' static roll model (slipd.estimators.preprocess.roll_static_gain, Selmanaj et
al. 2017 eq. 16) is phi = m h / K a_y,meas with the accelerometer's a_y (gravity from the roll
included) and h the profile's roll_axis_height. Equivalently, with the tyres' lateral force
per unit mass f = a_y,meas - g phi (the body-frame accelerometer reads f + g sin(phi_total)),
the moment balance of the sprung mass is phi (K - m g h) = m h f (Gillespie 1992, ch. 8,
"roll gradient"; Milliken & Milliken 1995, ch. 16: K_phi = W h / (d phi / d a_y), here per
m/s^2). The fit is phi = c f, K = m h (1 / c + g), with the profile's own m and h, so the model
the estimators run reproduces the measured gradient even where m or h are guesses.

Why f and not a_y,meas: the integrated roll rate is the body's roll plus the road's bank, and
a bank enters a_y,meas as g sin(bank): regressed on a_y,meas the bank's changes pull the slope
towards 1/g (on the simulated endurance route, -14 % on K); f carries the bank only through
the speed the driver chooses on it.

phi is the roll rate integrated; to be free of its offset's drift and of the roll dynamics
both phi and a_y are band-passed alike (0.02-0.5 Hz, zero phase: below the body's roll
resonance of 1-2 Hz the roll follows a_y statically) before the regression over the driving
pieces.
"""

from __future__ import annotations

import numpy as np

from slipd.channels import G, In, Veh
from slipd.identify.data import DT, Signals, runs, split
from slipd.identify.results import Finding, Missing, Outcome, regression_interval

SOURCE = ("roll gradient of the roll rate integrated against the tyres' lateral force, "
          "phi (K - m g h) = m h f (Gillespie 1992, ch. 8; Milliken & Milliken 1995, ch. 16), "
          "as the estimators' static roll model (Selmanaj et al. 2017, eq. 16)")
BAND_HZ = (0.02, 0.5)
MIN_SPEED = 5.0
MIN_SEGMENT_S = 60.0
PIECE_S = 60.0


def _bandpass(x: np.ndarray) -> np.ndarray:
    from scipy.signal import butter, sosfiltfilt

    sos = butter(2, BAND_HZ, btype="bandpass", fs=1.0 / DT, output="sos")
    return sosfiltfilt(sos, x)


def roll_gradient_data(sigs: list[Signals], roll_offset: float):
    pieces = []
    for k, s in enumerate(sigs):
        if not s.has(In.ROLL_RATE):
            continue
        mask = s.all_ok(In.ROLL_RATE, In.AY) & (s.vx > MIN_SPEED)
        for a, b in runs(mask, MIN_SEGMENT_S, 1.0):
            phi = _bandpass(np.cumsum(s.roll_rate[a:b] - roll_offset) * DT)
            ay = _bandpass(s.ay_cog[a:b])
            edge = int(10.0 / DT)  # the filters' start and end transients
            for _, lo, hi in split([(k, edge, b - a - edge)], PIECE_S):
                pieces.append((k, a + lo, a + hi, phi[lo:hi], ay[lo:hi]))
    return pieces


def _fit(pieces, idx) -> np.ndarray:
    """c of phi = c f, f = a_y,meas - g phi (band-passed alike)."""
    phi = np.concatenate([pieces[i][3] for i in idx])
    force = np.concatenate([pieces[i][4] for i in idx]) - G * phi
    return np.array([float(phi @ force / (force @ force))])


def identify_roll(sigs: list[Signals], profile, roll_offset: float, outcome: Outcome) -> dict:
    """Roll stiffness from the roll gradient; {'roll_stiffness': Nm/rad} or {}."""
    if not any(s.has(In.ROLL_RATE) for s in sigs):
        outcome.add(Missing("vehicle.roll_stiffness", "no roll-rate channel: roll gradient not "
                                                      "identified"))
        return {}
    pieces = [p for p in roll_gradient_data(sigs, roll_offset) if len(p[3]) > 100]
    if len(pieces) < 2 or np.std(np.concatenate([p[4] for p in pieces])) < 0.5:
        outcome.add(Missing("vehicle.roll_stiffness",
                            "no cornering with a valid roll rate for 60 s at a time: roll "
                            "gradient not identified"))
        return {}
    estimate = _fit(pieces, np.arange(len(pieces)))
    intervals, how = regression_interval(lambda idx: _fit(pieces, idx), len(pieces), estimate)
    veh = profile.vehicle
    arm = float(veh[Veh.MASS] * veh[Veh.H_ROLL_AXIS])
    c = float(estimate[0])
    if c <= 0:
        outcome.add(Missing("vehicle.roll_stiffness",
                            f"the roll gradient came out {np.degrees(c):.3f} deg per m/s^2 "
                            "(not positive): check the roll rate's sign"))
        return {}
    stiffness = arm * (1.0 / c + G)
    gradient = arm / stiffness  # d phi / d a_y,meas, the estimators' static gain
    lo, hi = intervals[0]
    ci = (arm * (1.0 / hi + G), arm * (1.0 / lo + G) if lo > 0 else float("inf"))
    seconds = sum(p[2] - p[1] for p in pieces) * DT
    outcome.diagnostics["roll"] = {"pieces": pieces, "gradient": gradient, "c": c}
    outcome.add(Finding("vehicle.roll_stiffness", stiffness, ci,
                        f"band-passed regression phi = c (a_y - g phi), roll gradient "
                        f"{np.degrees(gradient):.3f} deg per m/s^2, {how}", SOURCE,
                        len(pieces), seconds, len({p[0] for p in pieces}),
                        note="with the profile's mass and roll_axis_height"))
    return {"roll_stiffness": stiffness}
