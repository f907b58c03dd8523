"""``d_ekf``: the dynamic-only EKF baseline of Righetti & Lenzo 2025 (Sec. 4, "D-EKF").

The dynamic part of the DK-EKF alone (Sec. 2.1): state [vy, r] of the nonlinear single-track
model with the tanh tyre of eq. 7, Euler-discretised (eq. 8), measurements [r, ay] (eq. 9).
Its speed input and output vx is not estimated but computed from the corner velocities
(eq. 5-6: "For the D-EKF, vx is not an output of the extended Kalman filter, but it is computed
from Equation (5)"). beta = atan2(vy, vx_meas) (eq. 4).

Parameters: Q_D = Q_dyn, R_D = R_dyn of eq. 28 (Sec. 4: "The D-EKF covariance matrices are set
equal to the ones in (28)"); the initial covariance, speed floor, yaw-acceleration filter and
convergence rule are slipd's own (the paper gives none), as are the pre-processing blocks
beyond the paper's Sec. 3.1 (see righetti_lenzo). sigma_beta comes from the EKF's vy
variance and the vx measurement variance (R_VX, the r_vx of eq. 29, as the speed's noise).
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
    R_VX = 4  # (m/s)^2, variance of vx_meas for sigma_beta only (r_vx of eq. 29)
    NOMINAL_DT = 5  # s, the sampling interval the Q values hold for (eq. 8)
    MIN_SPEED = 6  # m/s, below it the filter is held (slipd)
    P0_VY = 7  # (m/s)^2, initial vy variance (slipd)
    P0_R = 8  # (rad/s)^2, initial yaw-rate variance (slipd)
    YAW_ACC_CUTOFF_HZ = 9  # Hz, derivative filter of the yaw rate for eq. 22-23 (slipd)
    SETTLE_TICKS = 10  # ticks after (re)start before convergence may be claimed (slipd)
    CONVERGED_SIGMA_BETA = 11  # rad, sigma_beta below which the estimate counts as settled
    # pre-processing beyond the paper's Sec. 3.1 (see righetti_lenzo's docstring; 0 and 0 = paper)
    ROLL_TIME_CONSTANT = 12  # s, roll complementary filter; 0 = none (slipd)
    LEVER_ARM_3D = 13  # 1 = CoG shift with roll/pitch motion, 0 = planar (slipd)


DEFAULTS = {
    "q_vy_dyn": 3e-6,
    "q_r_dyn": 1e-6,
    "r_yaw_rate_dyn": 4e-7,
    "r_ay_dyn": 6e-2,
    "r_vx": 2e-3,
    "nominal_dt": 0.01,
    "min_speed": 3.0,
    "p0_vy": 1.0,
    "p0_r": 1e-2,
    "yaw_acc_cutoff_hz": 10.0,
    "settle_ticks": 100.0,
    "converged_sigma_beta": 0.0175,
    "roll_time_constant": 1.0,
    "lever_arm_3d": 1.0,
}


def init(params: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """A fresh state vector (``righetti_lenzo.S``); the filter starts on the first speed sample."""
    validate_vehicle(vehicle)
    return new_state()


@nb.njit(cache=True)
def step(state, u, params, vehicle, dt, out):
    """One 100 Hz tick of the D-EKF; writes every element of ``out``, allocates nothing.

    The kinematic slots of the state hold vx_meas (KIN_VX) and are otherwise unused.
    """
    p0_vy = params[PARAMS.P0_VY]
    min_speed = params[PARAMS.MIN_SPEED]
    p0_r = params[PARAMS.P0_R]
    ax, ay, yaw_rate, steer, ax_ok, ay_ok, yaw_rate_ok, steer_ok, status = read_inputs(
        state, u, vehicle, params[PARAMS.YAW_ACC_CUTOFF_HZ], params[PARAMS.ROLL_TIME_CONSTANT],
        params[PARAMS.LEVER_ARM_3D] > 0.5, dt,
    )  # fmt: skip
    running = state[S.INITIALISED] > 0.5 and state[S.KIN_VX] >= min_speed
    q_scale = dt / params[PARAMS.NOMINAL_DT]
    if running:
        # a priori (eq. 8) with u_dyn = [vx_meas, delta] of tick k-1
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
        hold(state, vx_meas, vx_ok, ax, ay, yaw_rate, steer, p0_vy, p0_r, 0.0)
        write_held_outputs(out, vx_meas if vx_ok else state[S.KIN_VX], p0_vy, min_speed, status)
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
    state[S.PREV_AX] = ax
    state[S.PREV_AY] = ay
    state[S.PREV_YAW_RATE] = yaw_rate
    state[S.PREV_STEER] = steer
    status, was_reset = finish_tick(
        state, status, vx_meas, vx_ok, yaw_rate, steer, p0_vy, p0_r, 0.0
    )
    if was_reset:
        write_held_outputs(out, state[S.KIN_VX], p0_vy, min_speed, status)
        return
    vy = state[S.DYN_VY]
    sigma = beta_sigma(vx_meas, vy, params[PARAMS.R_VX], 0.0, state[S.DYN_P_VV])
    if state[S.TICKS] < params[PARAMS.SETTLE_TICKS] or not (
        sigma <= params[PARAMS.CONVERGED_SIGMA_BETA]
    ):
        status |= ST_NOT_CONVERGED
    write_outputs(out, vx_meas, vy, ax, ay, yaw_rate, sigma, state[S.ROLL], status)


@nb.njit(cache=True)
def run_ticks(state, U, params, vehicle, dt, OUT):
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])
