"""``k_kf``: the kinematic-only Kalman filter baseline of Righetti & Lenzo 2025 (Sec. 4, "K-KF").

The kinematic model of Sec. 2.2: state [vx, vy], inputs [ax, ay] at the CoG, the measured yaw
rate in the transition matrix (eq. 10-13), the single measurement vx_meas of eq. 5-6 (eq. 14).
No vehicle or tyre parameter enters (only tracks and IMU position for the pre-processing).
Sec. 4: "the estimated lateral velocity is set to zero when |r| < 0.01 rad/s, to reduce drift
during straights". beta = atan2(vy, vx) (eq. 4).

With r = 0 the lateral velocity is unobservable (PBH test, eq. 15-18): its variance grows by
Q[1,1] every tick, so sigma_beta grows on straights and the status says NOT_CONVERGED there.

Bounded drift (slipd, ``vy_leak_time_constant`` = 2 s; 0 is the paper): vy decays to 0 with
that time constant, vy -= vy dt / tau after each update. In a curve the only correction of the
open integral of ay is the vx channel's r vy term, which settles an unmodelled lateral
acceleration b (the road's bank, g sin(bank); a roll or offset error) at a vy error of b / r:
0.34 m/s^2 (2 deg of bank) at r = 0.1 rad/s is 3.4 m/s, 9 deg at 22 m/s, held for the whole
curve. The leak bounds that error to b tau (0.7 m/s) at the price of pulling a steady corner's
true sideslip toward 0 over tau; it is the K-KF's drift the paper reports (Sec. 4), bounded, not
removed: the filter's covariance does not model the leak, so vy stays unobservable on
straights, sigma_beta large and the method never VALID. tau is the horizon over which the
open integral is trusted: a transient (a lane change, a corner's entry) lasts 1-3 s, and
there the kinematics beat any model; over longer, b dominates. Measured on every block of
``benchmarks.accuracy`` (beta RMS without snow_drift, simulator blocks / real run, deg; the
paper's 0: 1.9-6.3 / 1.12): 1.5 s 0.9-1.5 / 0.94, 2 s 1.0-1.7 / 0.83, 3 s 1.1-2.2 / 0.72; on
the endurance drive 1 s 1.30, 10 s 3.67, and the real run 1 s 1.11, 10 s 0.80. The KBE of
pseudo_fusion (Chen's kinematic part with slipd's straight-running pseudo-measurement) has the
same leak where it is the output (``pseudo_fusion_kbe``: 5.1 -> 1.8 deg on the suite, 1.73 ->
1.07 on the real run) and none inside the fusion, which weighs it by its covariance (there the
leak moved the fusion's real run from 0.58 to 0.71).

Parameters: Q_K, R_K of eq. 30 and the 0.01 rad/s threshold of Sec. 4; initial covariance,
speed floor, variance cap, the leak, yaw-acceleration filter, convergence rule and the
pre-processing beyond the paper's Sec. 3.1 (see ``filters``) are slipd's own.
"""

from __future__ import annotations

import math

import numpy as np

from slipd.estimators.common.filters import leak
from slipd.estimators.common.kalman import per_step
from slipd.estimators.righetti_lenzo2025 import filters as rl
from slipd.estimators.righetti_lenzo2025.filters import S
from slipd.numba_cache import nb

#: The state layout all three methods share (filters.LAYOUT).
LAYOUT = rl.LAYOUT

PARAMS, DEFAULTS = rl.shared_params(
    "k_kf",
    ("Q_VX", 5e-3),  # (m/s)^2 per tick, eq. 30
    ("Q_VY", 3e-3),  # (m/s)^2 per tick, eq. 30
    ("R_VX", 2e-3),  # (m/s)^2, eq. 30
    ("ZERO_VY_YAW_RATE", 0.01),  # rad/s, |r| below which vy is set to zero (Sec. 4)
    ("P_VY_MAX", 100.0),  # (m/s)^2, cap of the vy variance while vy is unobservable (slipd)
    # s, vy decays to 0 with this time constant (slipd; 0 = the paper: module docstring)
    ("VY_LEAK_TIME_CONSTANT", 2.0),
    rl.P0_VX,
)  # fmt: skip
_KIN_P = int(S.KIN_P)


def init(params: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """A fresh state vector (``filters.LAYOUT``); the filter starts on the first speed sample."""
    return rl.new_state(vehicle, "k_kf")


@nb.njit(cache=True, _nrt=False)
def step(state, u, params, vehicle, dt, out):
    """One 100 Hz tick of the K-KF; writes every element of ``out``, allocates nothing.

    The dynamic slots of the state are unused.
    """
    p0_vx = params[PARAMS.P0_VX]
    nominal_dt = params[PARAMS.NOMINAL_DT]
    ax, ay, yaw_rate, steer, ay_ok, _, running, status = rl.begin_tick(
        state, u, params, vehicle, dt
    )
    vx_meas, vx_ok, status = rl.measured_speed(u, steer, yaw_rate, vehicle, status)
    if not running:
        rl.hold(state, out, vx_meas, vx_ok, ax, ay, yaw_rate, steer, params, 0.0, p0_vx, status)
        return
    # a priori (eq. 13) with [ax, ay, r] of tick k-1, Q_K of eq. 30. Without ay (invalid) the
    # kinematic model has no lateral input: the previous one is held (flagged INPUT_TIMEOUT).
    rl.kinematic_predict(
        state, state[S.PREV_AX], state[S.PREV_AY], state[S.PREV_YAW_RATE],
        per_step(params[PARAMS.Q_VX], dt, nominal_dt),
        per_step(params[PARAMS.Q_VY], dt, nominal_dt), dt,
    )  # fmt: skip
    # a posteriori with y = vx_meas, H = [1 0] (eq. 14), R_K of eq. 30
    nis, dof = rl.kinematic_update(state, vx_meas, vx_ok, params[PARAMS.R_VX], 0.0, False, 1.0)
    rl.record_innovations(state, nis, dof, params, dt)
    if abs(yaw_rate) < params[PARAMS.ZERO_VY_YAW_RATE]:
        state[S.KIN_VY] = 0.0  # Sec. 4: vy := 0 on straights against the drift
    # slipd: the bound on the open integral in a curve (module docstring)
    leak(state, S.KIN_VY, dt, params[PARAMS.VY_LEAK_TIME_CONSTANT])
    p_yy = state[_KIN_P + 2]
    p_vy_max = params[PARAMS.P_VY_MAX]
    if p_yy > p_vy_max:
        # vy unobservable for long: cap its variance (scaling the covariance row/column keeps P
        # positive definite) so that a day of straight driving cannot run P to overflow
        shrink = math.sqrt(p_vy_max / p_yy)
        state[_KIN_P + 1] *= shrink
        state[_KIN_P + 2] = p_vy_max
    rl.remember_inputs(state, ax, ay if ay_ok else state[S.PREV_AY], yaw_rate, steer)
    status, was_reset = rl.finish_tick(state, out, status, vx_meas, vx_ok, yaw_rate, steer,
                                       params, 0.0, p0_vx)  # fmt: skip
    if not was_reset:
        rl.write_estimate(state, out, state[S.KIN_VX], state[S.KIN_VY], state[_KIN_P],
                          state[_KIN_P + 1], state[_KIN_P + 2], ax, state[S.PREV_AY], yaw_rate,
                          params, status)


@nb.njit(cache=True, nogil=True, _nrt=False)
def run_ticks(state, U, params, vehicle, dt, OUT):
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])
