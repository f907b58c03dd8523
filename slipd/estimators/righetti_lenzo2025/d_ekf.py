"""``d_ekf``: the dynamic-only EKF baseline of Righetti & Lenzo 2025 (Sec. 4, "D-EKF").

The dynamic part of the DK-EKF alone (Sec. 2.1): state [vy, r] of the nonlinear single-track
model with the tanh tyre of eq. 7, Euler-discretised (eq. 8), measurements [r, ay] (eq. 9).
Its speed input and output vx is not estimated but computed from the corner velocities
(eq. 5-6: "For the D-EKF, vx is not an output of the extended Kalman filter, but it is computed
from Equation (5)"). beta = atan2(vy, vx_meas) (eq. 4).

Parameters: Q_D = Q_dyn, R_D = R_dyn of eq. 28 (Sec. 4: "The D-EKF covariance matrices are set
equal to the ones in (28)"); the initial covariance, speed floor, yaw-acceleration filter and
convergence rule are slipd's own (the paper gives none), as are the pre-processing blocks
beyond the paper's Sec. 3.1 (see ``filters``). sigma_beta comes from the EKF's vy
variance and the vx measurement variance (R_VX, the r_vx of eq. 29, as the speed's noise).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from slipd.estimators.common.kalman import per_step
from slipd.estimators.common.params import build_params
from slipd.estimators.righetti_lenzo2025.filters import (
    FILTER_PARAMS,
    LAYOUT,
    P0_R,
    S,
    begin_tick,
    dynamic_predict,
    dynamic_update,
    finish_tick,
    hold,
    measured_speed,
    new_state,
    remember_inputs,
    single_track,
    write_estimate,
)

PARAMS, DEFAULTS = build_params(
    "d_ekf",
    ("Q_VY_DYN", 3e-6),  # (m/s)^2 per tick, eq. 28
    ("Q_R_DYN", 1e-6),  # (rad/s)^2 per tick, eq. 28
    ("R_YAW_RATE_DYN", 4e-7),  # (rad/s)^2, eq. 28
    ("R_AY_DYN", 6e-2),  # (m/s^2)^2, eq. 28
    ("R_VX", 2e-3),  # (m/s)^2, variance of vx_meas for sigma_beta only (r_vx of eq. 29)
    *FILTER_PARAMS, P0_R,
)  # fmt: skip
_DYN_P_VV = int(S.DYN_P)


def init(params: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """A fresh state vector (``filters.LAYOUT``); the filter starts on the first speed sample."""
    return new_state(vehicle, "d_ekf")


@nb.njit(cache=True)
def step(state, u, params, vehicle, dt, out):
    """One 100 Hz tick of the D-EKF; writes every element of ``out``, allocates nothing.

    The kinematic slots of the state hold vx_meas (KIN_VX) and are otherwise unused.
    """
    p0_vy = params[PARAMS.P0_VY]
    min_speed = params[PARAMS.MIN_SPEED]
    p0_r = params[PARAMS.P0_R]
    nominal_dt = params[PARAMS.NOMINAL_DT]
    ax, ay, yaw_rate, steer, ay_ok, yaw_rate_ok, running, status = begin_tick(
        state, u, vehicle, params[PARAMS.YAW_ACC_CUTOFF_HZ], params[PARAMS.ROLL_TIME_CONSTANT],
        params[PARAMS.LEVER_ARM_3D] > 0.5, min_speed, dt,
    )  # fmt: skip
    if running:
        # a priori (eq. 8) with u_dyn = [vx_meas, delta] of tick k-1
        dynamic_predict(
            state, state[S.PREV_VX], state[S.PREV_STEER], vehicle,
            per_step(params[PARAMS.Q_VY_DYN], dt, nominal_dt),
            per_step(params[PARAMS.Q_R_DYN], dt, nominal_dt), dt,
        )  # fmt: skip
        if not yaw_rate_ok:
            yaw_rate = state[S.DYN_R]  # the model's yaw rate stands in for the gyro
    vx_meas, vx_ok, status = measured_speed(u, steer, yaw_rate, vehicle, status)
    if not running:
        hold(state, out, vx_meas, vx_ok, ax, ay, yaw_rate, steer, p0_vy, p0_r, 0.0, min_speed,
             status)  # fmt: skip
        return
    if not vx_ok:
        vx_meas = state[S.PREV_VX]  # no wheel: hold the last speed (flagged above)
    # a posteriori with y = [r, ay] (eq. 9) at tick k's speed
    dynamic_update(
        state, yaw_rate, yaw_rate_ok, ay, ay_ok, vx_meas, steer, vehicle,
        params[PARAMS.R_YAW_RATE_DYN], params[PARAMS.R_AY_DYN],
    )  # fmt: skip
    if not ay_ok:
        ay = single_track(state[S.DYN_VY], state[S.DYN_R], vx_meas, steer, vehicle)[2]
    state[S.KIN_VX] = vx_meas
    state[S.KIN_VY] = state[S.DYN_VY]
    state[S.PREV_VX] = vx_meas
    remember_inputs(state, ax, ay, yaw_rate, steer)
    status, was_reset = finish_tick(state, out, status, vx_meas, vx_ok, yaw_rate, steer, p0_vy,
                                    p0_r, 0.0, min_speed)  # fmt: skip
    if not was_reset:
        write_estimate(state, out, vx_meas, state[S.DYN_VY], params[PARAMS.R_VX], 0.0,
                       state[_DYN_P_VV], ax, ay, yaw_rate, params[PARAMS.SETTLE_TICKS],
                       params[PARAMS.CONVERGED_SIGMA_BETA], status)


@nb.njit(cache=True)
def run_ticks(state, U, params, vehicle, dt, OUT):
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])


__all__ = ["DEFAULTS", "LAYOUT", "PARAMS", "init", "run_ticks", "step"]
