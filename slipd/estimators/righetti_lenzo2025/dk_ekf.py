"""``dk_ekf``: the combined dynamic-kinematic EKF of Righetti & Lenzo 2025 (Sec. 2.3, Fig. 3).

Per tick k (inputs of tick k-1 feed the predictions, measurements of tick k the updates):

1. dynamic EKF [vy, r] (eq. 1-3, 7-9): predict from [vy_kin, r_dyn] of k-1 with u = [vx_kin, delta]
   of k-1, update with y = [r, ay];
2. kinematic KF [vx, vy] (eq. 10-13): predict with [ax, ay, r] of k-1, update with
   y = [vx_meas (eq. 5-6), vy_dyn] and H = I (eq. 19), the dynamic vy variance p_vy setting both
   Q_kin[1,1] = 0.1 p_vy and R_kin[1,1] = p_vy (eq. 29);
3. vy_kin replaces the dynamic vy for the next prediction and vx_kin is the dynamic part's speed
   input (Sec. 2.3, last paragraph).

beta = atan2(vy_kin, vx_kin) (eq. 4); sigma_beta from the kinematic covariance.

Parameters (``DEFAULTS``): eq. 28 (Q_dyn, R_dyn) and eq. 29 (Q_kin, R_kin) of Sec. 4, dt of eq. 8.
The paper gives no initial covariance, speed floor, yaw-acceleration filter or convergence rule;
those defaults are slipd's own (``filters.FILTER_PARAMS``), as are the two pre-processing
blocks beyond the paper's Sec. 3.1 (roll / gravity compensation, 3-D lever arm; see
``filters``). Tyre and vehicle data come from the vehicle vector (axle cornering stiffness,
MU_NOMINAL, mass, Iz, lf, lr, tracks, IMU position, roll stiffness and roll-axis height).
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
    P0_VX,
    S,
    begin_tick,
    dynamic_predict,
    dynamic_update,
    finish_tick,
    hold,
    kinematic_predict,
    kinematic_update,
    measured_speed,
    new_state,
    remember_inputs,
    single_track,
    write_estimate,
)

PARAMS, DEFAULTS = build_params(
    "dk_ekf",
    ("Q_VY_DYN", 3e-6),  # (m/s)^2 per tick, eq. 28
    ("Q_R_DYN", 1e-6),  # (rad/s)^2 per tick, eq. 28
    ("R_YAW_RATE_DYN", 4e-7),  # (rad/s)^2, eq. 28
    ("R_AY_DYN", 6e-2),  # (m/s^2)^2, eq. 28
    ("Q_VX_KIN", 5e-3),  # (m/s)^2 per tick, eq. 29
    ("Q_VY_KIN_RATIO", 1e-1),  # -, q_vy_kin = ratio * p_vy_dyn, eq. 29
    ("R_VX_KIN", 2e-3),  # (m/s)^2, eq. 29
    ("R_VY_KIN_RATIO", 1.0),  # -, r_vy_kin = ratio * p_vy_dyn, eq. 29
    *FILTER_PARAMS, P0_R, P0_VX,
)  # fmt: skip
_DYN_P_VV = int(S.DYN_P)
_KIN_P = int(S.KIN_P)


def init(params: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """A fresh state vector (``filters.LAYOUT``); the filters start on the first speed sample."""
    return new_state(vehicle, "dk_ekf")


@nb.njit(cache=True)
def step(state, u, params, vehicle, dt, out):
    """One 100 Hz tick of the DK-EKF; writes every element of ``out``, allocates nothing."""
    p0_vy = params[PARAMS.P0_VY]
    min_speed = params[PARAMS.MIN_SPEED]
    p0_r = params[PARAMS.P0_R]
    p0_vx = params[PARAMS.P0_VX]
    nominal_dt = params[PARAMS.NOMINAL_DT]
    ax, ay, yaw_rate, steer, ay_ok, yaw_rate_ok, running, status = begin_tick(
        state, u, vehicle, params[PARAMS.YAW_ACC_CUTOFF_HZ], params[PARAMS.ROLL_TIME_CONSTANT],
        params[PARAMS.LEVER_ARM_3D] > 0.5, min_speed, dt,
    )  # fmt: skip
    if running:
        # 1. dynamic EKF, a priori (eq. 8) with u_dyn = [vx_kin, delta] of tick k-1
        dynamic_predict(
            state, state[S.PREV_VX], state[S.PREV_STEER], vehicle,
            per_step(params[PARAMS.Q_VY_DYN], dt, nominal_dt),
            per_step(params[PARAMS.Q_R_DYN], dt, nominal_dt), dt,
        )  # fmt: skip
        if not yaw_rate_ok:
            yaw_rate = state[S.DYN_R]  # the model's yaw rate stands in for the gyro
    vx_meas, vx_ok, status = measured_speed(u, steer, yaw_rate, vehicle, status)
    if not running:
        hold(state, out, vx_meas, vx_ok, ax, ay, yaw_rate, steer, p0_vy, p0_r, p0_vx, min_speed,
             status)  # fmt: skip
        return
    # 1. dynamic EKF, a posteriori with y = [r, ay] (eq. 9); speed input: vx_kin of k-1
    dynamic_update(
        state, yaw_rate, yaw_rate_ok, ay, ay_ok, state[S.PREV_VX], steer, vehicle,
        params[PARAMS.R_YAW_RATE_DYN], params[PARAMS.R_AY_DYN],
    )  # fmt: skip
    if not ay_ok:
        ay = single_track(state[S.DYN_VY], state[S.DYN_R], state[S.PREV_VX], steer, vehicle)[2]
    p_vy_dyn = state[_DYN_P_VV]
    # 2. kinematic KF, a priori (eq. 13) with [ax, ay, r] of tick k-1, Q_kin of eq. 29
    kinematic_predict(
        state, state[S.PREV_AX], state[S.PREV_AY], state[S.PREV_YAW_RATE],
        per_step(params[PARAMS.Q_VX_KIN], dt, nominal_dt),
        per_step(params[PARAMS.Q_VY_KIN_RATIO] * p_vy_dyn, dt, nominal_dt), dt,
    )  # fmt: skip
    # 2. a posteriori with y = [vx_meas, vy_dyn], H = I (eq. 19), R_kin of eq. 29
    kinematic_update(
        state, vx_meas, vx_ok, params[PARAMS.R_VX_KIN],
        state[S.DYN_VY], True, params[PARAMS.R_VY_KIN_RATIO] * p_vy_dyn,
    )  # fmt: skip
    # 3. vy_kin and r_dyn form the next dynamic prediction's state; vx_kin its speed input
    state[S.DYN_VY] = state[S.KIN_VY]
    state[S.PREV_VX] = state[S.KIN_VX]
    remember_inputs(state, ax, ay, yaw_rate, steer)
    status, was_reset = finish_tick(state, out, status, vx_meas, vx_ok, yaw_rate, steer, p0_vy,
                                    p0_r, p0_vx, min_speed)  # fmt: skip
    if not was_reset:
        write_estimate(state, out, state[S.KIN_VX], state[S.KIN_VY], state[_KIN_P],
                       state[_KIN_P + 1], state[_KIN_P + 2], ax, ay, yaw_rate,
                       params[PARAMS.SETTLE_TICKS], params[PARAMS.CONVERGED_SIGMA_BETA], status)


@nb.njit(cache=True)
def run_ticks(state, U, params, vehicle, dt, OUT):
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])


__all__ = ["DEFAULTS", "LAYOUT", "PARAMS", "init", "run_ticks", "step"]
