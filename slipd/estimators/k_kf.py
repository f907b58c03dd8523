"""``k_kf``: the kinematic-only Kalman filter baseline of Righetti & Lenzo 2025 (Sec. 4, "K-KF").

The kinematic model of Sec. 2.2: state [vx, vy], inputs [ax, ay] at the CoG, the measured yaw
rate in the transition matrix (eq. 10-13), the single measurement vx_meas of eq. 5-6 (eq. 14).
No vehicle or tyre parameter enters (only tracks and IMU position for the pre-processing).
Sec. 4: "the estimated lateral velocity is set to zero when |r| < 0.01 rad/s, to reduce drift
during straights". beta = atan2(vy, vx) (eq. 4).

With r = 0 the lateral velocity is unobservable (PBH test, eq. 15-18): its variance grows by
Q[1,1] every tick, so sigma_beta grows on straights and the status says NOT_CONVERGED there.

Parameters: Q_K, R_K of eq. 30 and the 0.01 rad/s threshold of Sec. 4; initial covariance,
speed floor, variance cap, yaw-acceleration filter, convergence rule and the pre-processing
beyond the paper's Sec. 3.1 (see righetti_lenzo) are slipd's own.
"""

from __future__ import annotations

import enum
import math

import numba as nb
import numpy as np

from slipd.channels import ST_INPUT_TIMEOUT, ST_NOT_CONVERGED
from slipd.estimators.preprocess import corner_speed_mean
from slipd.estimators.righetti_lenzo import (
    S,
    beta_sigma,
    finish_tick,
    hold,
    kinematic_predict,
    kinematic_update,
    new_state,
    read_inputs,
    validate_vehicle,
    write_held_outputs,
    write_outputs,
)


@enum.unique
class PARAMS(enum.IntEnum):
    Q_VX = 0  # (m/s)^2 per tick, eq. 30
    Q_VY = 1  # (m/s)^2 per tick, eq. 30
    R_VX = 2  # (m/s)^2, eq. 30
    ZERO_VY_YAW_RATE = 3  # rad/s, |r| below which vy is set to zero (Sec. 4)
    NOMINAL_DT = 4  # s, the sampling interval the Q values hold for (eq. 8)
    MIN_SPEED = 5  # m/s, below it the filter is held (slipd)
    P0_VY = 6  # (m/s)^2, initial vy variance (slipd)
    P0_VX = 7  # (m/s)^2, initial vx variance (slipd)
    P_VY_MAX = 8  # (m/s)^2, cap of the vy variance while vy is unobservable (slipd)
    YAW_ACC_CUTOFF_HZ = 9  # Hz, derivative filter of the yaw rate for eq. 22-23 (slipd)
    SETTLE_TICKS = 10  # ticks after (re)start before convergence may be claimed (slipd)
    CONVERGED_SIGMA_BETA = 11  # rad, sigma_beta below which the estimate counts as settled
    # pre-processing beyond the paper's Sec. 3.1 (see righetti_lenzo's docstring; 0 and 0 = paper)
    ROLL_TIME_CONSTANT = 12  # s, roll complementary filter; 0 = none (slipd)
    LEVER_ARM_3D = 13  # 1 = CoG shift with roll/pitch motion, 0 = planar (slipd)


DEFAULTS = {
    "q_vx": 5e-3,
    "q_vy": 3e-3,
    "r_vx": 2e-3,
    "zero_vy_yaw_rate": 0.01,
    "nominal_dt": 0.01,
    "min_speed": 3.0,
    "p0_vy": 1.0,
    "p0_vx": 1.0,
    "p_vy_max": 100.0,
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
    """One 100 Hz tick of the K-KF; writes every element of ``out``, allocates nothing.

    The dynamic slots of the state are unused.
    """
    p0_vy = params[PARAMS.P0_VY]
    min_speed = params[PARAMS.MIN_SPEED]
    p0_vx = params[PARAMS.P0_VX]
    ax, ay, yaw_rate, steer, ax_ok, ay_ok, yaw_rate_ok, steer_ok, status = read_inputs(
        state, u, vehicle, params[PARAMS.YAW_ACC_CUTOFF_HZ], params[PARAMS.ROLL_TIME_CONSTANT],
        params[PARAMS.LEVER_ARM_3D] > 0.5, dt,
    )  # fmt: skip
    vx_meas, n_wheels = corner_speed_mean(u, steer, yaw_rate, vehicle)
    vx_ok = n_wheels > 0
    if n_wheels < 4:
        status |= ST_INPUT_TIMEOUT  # a wheel speed is missing
    running = state[S.INITIALISED] > 0.5 and state[S.KIN_VX] >= min_speed
    if not running:
        hold(state, vx_meas, vx_ok, ax, ay, yaw_rate, steer, p0_vy, 0.0, p0_vx)
        write_held_outputs(out, vx_meas if vx_ok else state[S.KIN_VX], p0_vy, min_speed, status)
        return
    q_scale = dt / params[PARAMS.NOMINAL_DT]
    # a priori (eq. 13) with [ax, ay, r] of tick k-1, Q_K of eq. 30. Without ay (invalid) the
    # kinematic model has no lateral input: the previous one is held (flagged INPUT_TIMEOUT).
    kinematic_predict(
        state, state[S.PREV_AX], state[S.PREV_AY], state[S.PREV_YAW_RATE],
        params[PARAMS.Q_VX] * q_scale, params[PARAMS.Q_VY] * q_scale, dt,
    )  # fmt: skip
    # a posteriori with y = vx_meas, H = [1 0] (eq. 14), R_K of eq. 30
    kinematic_update(state, vx_meas, vx_ok, params[PARAMS.R_VX], 0.0, False, 1.0)
    if abs(yaw_rate) < params[PARAMS.ZERO_VY_YAW_RATE]:
        state[S.KIN_VY] = 0.0  # Sec. 4: vy := 0 on straights against the drift
    p_yy = state[S.KIN_P_YY]
    p_vy_max = params[PARAMS.P_VY_MAX]
    if p_yy > p_vy_max:
        # vy unobservable for long: cap its variance (scaling the covariance row/column keeps P
        # positive definite) so that a day of straight driving cannot run P to overflow
        shrink = math.sqrt(p_vy_max / p_yy)
        state[S.KIN_P_XY] *= shrink
        state[S.KIN_P_YY] = p_vy_max
    state[S.PREV_AX] = ax
    state[S.PREV_AY] = ay if ay_ok else state[S.PREV_AY]
    state[S.PREV_YAW_RATE] = yaw_rate
    state[S.PREV_STEER] = steer
    status, was_reset = finish_tick(
        state, status, vx_meas, vx_ok, yaw_rate, steer, p0_vy, 0.0, p0_vx
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
    write_outputs(out, vx, vy, ax, state[S.PREV_AY], yaw_rate, sigma, state[S.ROLL], status)


@nb.njit(cache=True)
def run_ticks(state, U, params, vehicle, dt, OUT):
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])
