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
those defaults are slipd's own and marked so, as are the two pre-processing blocks
beyond the paper's Sec. 3.1 (roll / gravity compensation, 3-D lever arm; see righetti_lenzo).
Tyre and vehicle data come from the vehicle vector (axle cornering stiffness, MU_NOMINAL, mass,
Iz, lf, lr, tracks, IMU position, roll stiffness and roll-axis height).
"""

from __future__ import annotations

import enum

import numba as nb
import numpy as np

from slipd.channels import ST_INPUT_TIMEOUT, ST_NOT_CONVERGED
from slipd.estimators.preprocess import corner_speed_mean
from slipd.estimators.righetti_lenzo import (
    S,
    beta_sigma,
    dynamic_predict,
    dynamic_update,
    finish_tick,
    hold,
    kinematic_predict,
    kinematic_update,
    new_state,
    read_inputs,
    single_track,
    validate_vehicle,
    write_held_outputs,
    write_outputs,
)


@enum.unique
class PARAMS(enum.IntEnum):
    Q_VY_DYN = 0  # (m/s)^2 per tick, eq. 28
    Q_R_DYN = 1  # (rad/s)^2 per tick, eq. 28
    R_YAW_RATE_DYN = 2  # (rad/s)^2, eq. 28
    R_AY_DYN = 3  # (m/s^2)^2, eq. 28
    Q_VX_KIN = 4  # (m/s)^2 per tick, eq. 29
    Q_VY_KIN_RATIO = 5  # -, q_vy_kin = ratio * p_vy_dyn, eq. 29
    R_VX_KIN = 6  # (m/s)^2, eq. 29
    R_VY_KIN_RATIO = 7  # -, r_vy_kin = ratio * p_vy_dyn, eq. 29
    NOMINAL_DT = 8  # s, the sampling interval the Q values hold for (eq. 8)
    MIN_SPEED = 9  # m/s, below it the filters are held (slipd)
    P0_VY = 10  # (m/s)^2, initial vy variance (slipd)
    P0_R = 11  # (rad/s)^2, initial yaw-rate variance (slipd)
    P0_VX = 12  # (m/s)^2, initial vx variance (slipd)
    YAW_ACC_CUTOFF_HZ = 13  # Hz, derivative filter of the yaw rate for eq. 22-23 (slipd)
    SETTLE_TICKS = 14  # ticks after (re)start before convergence may be claimed (slipd)
    CONVERGED_SIGMA_BETA = 15  # rad, sigma_beta below which the estimate counts as settled
    # pre-processing beyond the paper's Sec. 3.1 (see righetti_lenzo's docstring; 0 and 0 = paper)
    ROLL_TIME_CONSTANT = 16  # s, roll complementary filter; 0 = none (slipd)
    LEVER_ARM_3D = 17  # 1 = CoG shift with roll/pitch motion, 0 = planar (slipd)


DEFAULTS = {
    "q_vy_dyn": 3e-6,
    "q_r_dyn": 1e-6,
    "r_yaw_rate_dyn": 4e-7,
    "r_ay_dyn": 6e-2,
    "q_vx_kin": 5e-3,
    "q_vy_kin_ratio": 1e-1,
    "r_vx_kin": 2e-3,
    "r_vy_kin_ratio": 1.0,
    "nominal_dt": 0.01,
    "min_speed": 3.0,
    "p0_vy": 1.0,
    "p0_r": 1e-2,
    "p0_vx": 1.0,
    "yaw_acc_cutoff_hz": 10.0,
    "settle_ticks": 100.0,
    "converged_sigma_beta": 0.0175,
    "roll_time_constant": 1.0,
    "lever_arm_3d": 1.0,
}


def init(params: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """A fresh state vector (``righetti_lenzo.S``); the filters start on the first speed sample."""
    validate_vehicle(vehicle)
    return new_state()


@nb.njit(cache=True)
def step(state, u, params, vehicle, dt, out):
    """One 100 Hz tick of the DK-EKF; writes every element of ``out``, allocates nothing."""
    p0_vy = params[PARAMS.P0_VY]
    min_speed = params[PARAMS.MIN_SPEED]
    p0_r = params[PARAMS.P0_R]
    p0_vx = params[PARAMS.P0_VX]
    ax, ay, yaw_rate, steer, ax_ok, ay_ok, yaw_rate_ok, steer_ok, status = read_inputs(
        state, u, vehicle, params[PARAMS.YAW_ACC_CUTOFF_HZ], params[PARAMS.ROLL_TIME_CONSTANT],
        params[PARAMS.LEVER_ARM_3D] > 0.5, dt,
    )  # fmt: skip
    running = state[S.INITIALISED] > 0.5 and state[S.KIN_VX] >= min_speed
    # Q per tick scales with dt so that the paper's process noise per second holds at any rate
    q_scale = dt / params[PARAMS.NOMINAL_DT]
    if running:
        # 1. dynamic EKF, a priori (eq. 8) with u_dyn = [vx_kin, delta] of tick k-1
        dynamic_predict(
            state, state[S.PREV_VX], state[S.PREV_STEER], vehicle,
            params[PARAMS.Q_VY_DYN] * q_scale, params[PARAMS.Q_R_DYN] * q_scale, dt,
        )  # fmt: skip
        if not yaw_rate_ok:
            yaw_rate = state[S.DYN_R]  # the model's yaw rate stands in for the gyro
    vx_meas, n_wheels = corner_speed_mean(u, steer, yaw_rate, vehicle)
    vx_ok = n_wheels > 0
    if n_wheels < 4:
        status |= ST_INPUT_TIMEOUT  # a wheel speed is missing
    if not running:
        hold(state, vx_meas, vx_ok, ax, ay, yaw_rate, steer, p0_vy, p0_r, p0_vx)
        write_held_outputs(out, vx_meas if vx_ok else state[S.KIN_VX], p0_vy, min_speed, status)
        return
    # 1. dynamic EKF, a posteriori with y = [r, ay] (eq. 9); speed input: vx_kin of k-1
    dynamic_update(
        state, yaw_rate, yaw_rate_ok, ay, ay_ok, state[S.PREV_VX], steer, vehicle,
        params[PARAMS.R_YAW_RATE_DYN], params[PARAMS.R_AY_DYN],
    )  # fmt: skip
    if not ay_ok:
        ay = single_track(state[S.DYN_VY], state[S.DYN_R], state[S.PREV_VX], steer, vehicle)[2]
    p_vy_dyn = state[S.DYN_P_VV]
    # 2. kinematic KF, a priori (eq. 13) with [ax, ay, r] of tick k-1, Q_kin of eq. 29
    kinematic_predict(
        state, state[S.PREV_AX], state[S.PREV_AY], state[S.PREV_YAW_RATE],
        params[PARAMS.Q_VX_KIN] * q_scale, params[PARAMS.Q_VY_KIN_RATIO] * p_vy_dyn * q_scale, dt,
    )  # fmt: skip
    # 2. a posteriori with y = [vx_meas, vy_dyn], H = I (eq. 19), R_kin of eq. 29
    kinematic_update(
        state, vx_meas, vx_ok, params[PARAMS.R_VX_KIN],
        state[S.DYN_VY], True, params[PARAMS.R_VY_KIN_RATIO] * p_vy_dyn,
    )  # fmt: skip
    # 3. vy_kin and r_dyn form the next dynamic prediction's state; vx_kin its speed input
    state[S.DYN_VY] = state[S.KIN_VY]
    state[S.PREV_VX] = state[S.KIN_VX]
    state[S.PREV_AX] = ax
    state[S.PREV_AY] = ay
    state[S.PREV_YAW_RATE] = yaw_rate
    state[S.PREV_STEER] = steer
    status, was_reset = finish_tick(
        state, status, vx_meas, vx_ok, yaw_rate, steer, p0_vy, p0_r, p0_vx
    )
    if was_reset:
        write_held_outputs(out, state[S.KIN_VX], p0_vy, min_speed, status)
        return
    vx = state[S.KIN_VX]
    vy = state[S.KIN_VY]
    sigma = beta_sigma(vx, vy, state[S.KIN_P_XX], state[S.KIN_P_XY], state[S.KIN_P_YY])
    if state[S.TICKS] < params[PARAMS.SETTLE_TICKS] or not (
        sigma <= params[PARAMS.CONVERGED_SIGMA_BETA]
    ):
        status |= ST_NOT_CONVERGED
    write_outputs(out, vx, vy, ax, ay, yaw_rate, sigma, state[S.ROLL], status)


@nb.njit(cache=True)
def run_ticks(state, U, params, vehicle, dt, OUT):
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])
