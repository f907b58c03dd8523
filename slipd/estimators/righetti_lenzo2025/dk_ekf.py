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

import numpy as np

from slipd.channels import Veh
from slipd.estimators.common.kalman import per_step
from slipd.estimators.righetti_lenzo2025 import filters as rl
from slipd.estimators.righetti_lenzo2025.filters import S
from slipd.numba_cache import nb

#: The state layout all three methods share (filters.LAYOUT).
LAYOUT = rl.LAYOUT

PARAMS, DEFAULTS = rl.shared_params(
    "dk_ekf",
    ("Q_VX_KIN", 5e-3),  # (m/s)^2 per tick, eq. 29
    ("Q_VY_KIN_RATIO", 1e-1),  # -, q_vy_kin = ratio * p_vy_dyn, eq. 29
    ("R_VX_KIN", 2e-3),  # (m/s)^2, eq. 29
    ("R_VY_KIN_RATIO", 1.0),  # -, r_vy_kin = ratio * p_vy_dyn, eq. 29
    rl.P0_R, rl.P0_VX,
    dynamic=True,  # eq. 28
)  # fmt: skip
_DYN_P_VV = int(S.DYN_P)
_KIN_P = int(S.KIN_P)


def init(params: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """A fresh state vector (``filters.LAYOUT``); the filters start on the first speed sample."""
    return rl.new_state(vehicle, "dk_ekf")


@nb.njit(cache=True, _nrt=False)
def step(state, u, params, vehicle, dt, out):
    """One 100 Hz tick of the DK-EKF; writes every element of ``out``, allocates nothing."""
    p0_r = params[PARAMS.P0_R]
    p0_vx = params[PARAMS.P0_VX]
    nominal_dt = params[PARAMS.NOMINAL_DT]
    mu = vehicle[Veh.MU_NOMINAL]  # eq. 7 at the profile's peak friction (the paper's)
    # 1. dynamic EKF, a priori (eq. 8) with u_dyn = [vx_kin, delta] of tick k-1
    ax, ay, yaw_rate, steer, ay_ok, yaw_rate_ok, running, status = rl.begin_dynamic_tick(
        state, u, params, vehicle, mu, dt
    )
    vx_meas, vx_ok, status = rl.measured_speed(u, steer, yaw_rate, vehicle, status)
    if not running:
        rl.hold(state, out, vx_meas, vx_ok, ax, ay, yaw_rate, steer, params, p0_r, p0_vx, status)
        return
    # 1. dynamic EKF, a posteriori with y = [r, ay] (eq. 9); speed input: vx_kin of k-1
    nis, dof = rl.dynamic_update(
        state, yaw_rate, yaw_rate_ok, ay, ay_ok, state[S.PREV_VX], steer, vehicle, mu,
        params[PARAMS.R_YAW_RATE_DYN], params[PARAMS.R_AY_DYN],
    )  # fmt: skip
    # the innovation test is the dynamic EKF's: the kinematic KF's pseudo-measurement is the
    # dynamic vy itself, its innovations say nothing about the model
    rl.record_innovations(state, nis, dof, params, dt)
    if not ay_ok:
        ay = rl.single_track(state[S.DYN_VY], state[S.DYN_R], state[S.PREV_VX], steer, vehicle,
                             mu)[2]
    p_vy_dyn = state[_DYN_P_VV]
    # 2. kinematic KF, a priori (eq. 13) with [ax, ay, r] of tick k-1, Q_kin of eq. 29
    rl.kinematic_predict(
        state, state[S.PREV_AX], state[S.PREV_AY], state[S.PREV_YAW_RATE],
        per_step(params[PARAMS.Q_VX_KIN], dt, nominal_dt),
        per_step(params[PARAMS.Q_VY_KIN_RATIO] * p_vy_dyn, dt, nominal_dt), dt,
    )  # fmt: skip
    # 2. a posteriori with y = [vx_meas, vy_dyn], H = I (eq. 19), R_kin of eq. 29
    rl.kinematic_update(
        state, vx_meas, vx_ok, params[PARAMS.R_VX_KIN],
        state[S.DYN_VY], True, params[PARAMS.R_VY_KIN_RATIO] * p_vy_dyn,
    )  # fmt: skip
    # 3. vy_kin and r_dyn form the next dynamic prediction's state; vx_kin its speed input
    state[S.DYN_VY] = state[S.KIN_VY]
    state[S.PREV_VX] = state[S.KIN_VX]
    rl.remember_inputs(state, ax, ay, yaw_rate, steer)
    status, was_reset = rl.finish_tick(state, out, status, vx_meas, vx_ok, yaw_rate, steer,
                                       params, p0_r, p0_vx)  # fmt: skip
    if not was_reset:
        rl.write_estimate(state, out, state[S.KIN_VX], state[S.KIN_VY], state[_KIN_P],
                          state[_KIN_P + 1], state[_KIN_P + 2], ax, ay, yaw_rate, params, status)


@nb.njit(cache=True, nogil=True, _nrt=False)
def run_ticks(state, U, params, vehicle, dt, OUT):
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])

