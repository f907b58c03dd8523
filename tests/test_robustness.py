"""Safety defects of issue 17 (item 6), each with the regression test that failed before its
fix, and the robustness properties every method must keep."""

from __future__ import annotations

import numpy as np
import pytest

from slipd.channels import U_LEN, U_TIME, VALID, In, Out, Status
from slipd.estimators.registry import available
from slipd.pipeline import Pipeline
from slipd.profile import load_profile

PROFILE = load_profile("default")
WHEELS = (In.WHEEL_SPEED_FL, In.WHEEL_SPEED_FR, In.WHEEL_SPEED_RL, In.WHEEL_SPEED_RR)


def straight_run(n: int, speed: float) -> np.ndarray:
    """Ticks of a car running straight at ``speed`` with every core input fresh."""
    U = np.zeros((n, U_LEN))
    for ch in (In.AX, In.AY, In.AZ, In.YAW_RATE, In.ROLL_RATE, In.PITCH_RATE, In.STEER, *WHEELS):
        U[:, VALID + ch] = 1.0
    U[:, In.AZ] = 9.81
    U[:, U_TIME] = np.arange(n) * 0.01
    for w in WHEELS:
        U[:, w] = speed
    return U


@pytest.mark.parametrize("method", available())
def test_all_wheels_locking_at_speed_is_survived_and_never_valid(method):
    """Every wheel speed drops from 20 m/s to 0 in one tick while the car decelerates at 0.9 g
    (a wheel lock): no method may raise (d_ekf and ensemble divided by vx = 0), and none may
    send VALID frames whose speed is off by more than the monitor's tolerance while the wheels
    read 0 and the car is still moving (the consistency monitor's speed check; before it every
    wheel-based method said VALID with vx = 0)."""
    U = straight_run(400, 20.0)
    for w in WHEELS:
        U[200:, w] = 0.0
    U[200:, In.AX] = -9.0
    out = Pipeline(method, PROFILE).run(U)
    assert np.all(np.isfinite(out[:, Out.STATUS]))
    locked = out[200:300]
    true_vx = 20.0 - 9.0 * 0.01 * np.arange(len(locked))
    valid = (locked[:, Out.STATUS].astype(int) & Status.VALID) != 0
    wrong = np.abs(locked[:, Out.VX] - true_vx) > 1.0 + 0.05 * true_vx + 0.5
    assert not (valid & wrong).any(), (
        f"{method}: VALID with vx {locked[valid & wrong, Out.VX][:3]} while the car moves at "
        f"{true_vx[valid & wrong][:3]} m/s on locked wheels")
