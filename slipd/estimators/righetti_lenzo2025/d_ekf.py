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

import numpy as np

from slipd.channels import Veh
from slipd.estimators.righetti_lenzo2025 import filters as rl
from slipd.estimators.righetti_lenzo2025.filters import S
from slipd.numba_cache import nb

#: The state layout all three methods share (filters.LAYOUT).
LAYOUT = rl.LAYOUT

PARAMS, DEFAULTS = rl.shared_params(
    "d_ekf",
    ("R_VX", 2e-3),  # (m/s)^2, variance of vx_meas for sigma_beta only (r_vx of eq. 29)
    rl.P0_R,
    dynamic=True,  # eq. 28, as the DK-EKF's
)  # fmt: skip
_DYN_P_VV = int(S.DYN_P)


def init(params: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """A fresh state vector (``filters.LAYOUT``); the filter starts on the first speed sample."""
    return rl.new_state(vehicle, "d_ekf")


@nb.njit(cache=True, _nrt=False)
def step(state, u, params, vehicle, dt, out):
    """One 100 Hz tick of the D-EKF; writes every element of ``out``, allocates nothing.

    The kinematic slots of the state hold vx_meas (KIN_VX) and are otherwise unused.
    """
    p0_r = params[PARAMS.P0_R]
    mu = vehicle[Veh.MU_NOMINAL]  # eq. 7 at the profile's peak friction (the paper's)
    # a priori (eq. 8) with u_dyn = [vx_meas, delta] of tick k-1
    ax, ay, yaw_rate, steer, ay_ok, yaw_rate_ok, running, status = rl.begin_dynamic_tick(
        state, u, params, vehicle, mu, dt
    )
    vx_meas, vx_ok, status = rl.measured_speed(u, steer, yaw_rate, vehicle, status)
    if not running:
        rl.hold(state, out, vx_meas, vx_ok, ax, ay, yaw_rate, steer, params, p0_r, 0.0, status)
        return
    if not vx_ok:
        vx_meas = state[S.PREV_VX]  # no wheel: hold the last speed (flagged above)
    elif vx_meas < params[PARAMS.MIN_SPEED]:
        # the wheels fell below the model's speed range since the last tick (a stop, or all
        # wheels locked at speed): eq. 7's slip angles divide by vx, so hold as at start-up
        rl.hold(state, out, vx_meas, vx_ok, ax, ay, yaw_rate, steer, params, p0_r, 0.0, status)
        return
    # a posteriori with y = [r, ay] (eq. 9) at tick k's speed
    nis, dof = rl.dynamic_update(
        state, yaw_rate, yaw_rate_ok, ay, ay_ok, vx_meas, steer, vehicle, mu,
        params[PARAMS.R_YAW_RATE_DYN], params[PARAMS.R_AY_DYN],
    )  # fmt: skip
    rl.record_innovations(state, nis, dof, params, dt)
    if not ay_ok:
        ay = rl.single_track(state[S.DYN_VY], state[S.DYN_R], vx_meas, steer, vehicle, mu)[2]
    state[S.KIN_VX] = vx_meas
    state[S.KIN_VY] = state[S.DYN_VY]
    state[S.PREV_VX] = vx_meas
    rl.remember_inputs(state, ax, ay, yaw_rate, steer)
    status, was_reset = rl.finish_tick(state, out, status, vx_meas, vx_ok, yaw_rate, steer,
                                       params, p0_r, 0.0)  # fmt: skip
    if not was_reset:
        rl.write_estimate(state, out, vx_meas, state[S.DYN_VY], params[PARAMS.R_VX], 0.0,
                          state[_DYN_P_VV], ax, ay, yaw_rate, params, status)


@nb.njit(cache=True, nogil=True, _nrt=False)
def run_ticks(state, U, params, vehicle, dt, OUT):
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])

