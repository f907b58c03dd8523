"""``d_ekf``: the dynamic-only EKF baseline of Righetti & Lenzo 2025 (Sec. 4, "D-EKF").

The dynamic part of the DK-EKF alone (Sec. 2.1): state [vy, r] of the nonlinear single-track
model with the tanh tyre of eq. 7, Euler-discretised (eq. 8), measurements [r, ay] (eq. 9).
Its speed input and output vx is not estimated but computed from the corner velocities
(eq. 5-6: "For the D-EKF, vx is not an output of the extended Kalman filter, but it is computed
from Equation (5)"). beta = atan2(vy, vx_meas) (eq. 4).

Friction (slipd, ``slip_friction``; 0 = the paper's): eq. 7 takes the profile's peak friction,
which on a low-friction road puts the model's saturation three times too high: the filter then
reads a saturated axle as a linear one and bends vy to explain the measurements (snow_drift,
mu 0.3: 4.0 deg RMS). With ``slip_friction`` = 1 (the default) eq. 7's mu is the friction
estimate of ``hybrid_friction`` (Carnier, Corno, Savaresi 2023: the slip-based classifier of
its Sec. 3 on wheel slip against traction force, which re-initialises the adaptive law of its
eq. 14-15), run beside the filter on the same inputs, its state nested in this one
(``FRICTION``) and its params under ``friction__<field>``. Why that signal and not one of the
EKF's own: with only r and ay measured, a lower friction explains a road bank or an
accelerometer offset as well as a slippery road, and both a third EKF state and a bank of
fixed-friction filters (MMAE) ran away on the banked road and the j-turn (figures in
benchmarks/MEASUREMENTS.md); the classifier's evidence is the wheels' slip, which no bank or
ay offset produces. Measured (benchmarks.accuracy): snow_drift 3.99 / 3.96 -> 1.88 / 2.01 deg
(seeds 0 / 1), mu_jump 0.95 / 0.96 -> 0.72 / 0.36, j_turn 1.33 -> 0.74 (seed 0; seed 1's
classifier stays at the profile's friction there), every other log of the suite, the sensor
variants, the other cars and the real run unchanged. Not given to dk_ekf: its kinematic KF,
fed the dynamic vy as pseudo-measurement, followed a wrong low-friction vy on vehicle 3's snow
drift (2.5 -> 9.9 deg). Out.MU and FRICTION_CLASS report the friction used while its
estimator is converged (NaN and 0 otherwise, and always with ``slip_friction`` = 0).

Parameters: Q_D = Q_dyn, R_D = R_dyn of eq. 28 (Sec. 4: "The D-EKF covariance matrices are set
equal to the ones in (28)"); the initial covariance, speed floor, yaw-acceleration filter and
convergence rule are slipd's own (the paper gives none), as are the pre-processing blocks
beyond the paper's Sec. 3.1 (see ``filters``). sigma_beta comes from the EKF's vy
variance and the vx measurement variance (R_VX, the r_vx of eq. 29, as the speed's noise).
"""

from __future__ import annotations

import math

import numpy as np

from slipd.channels import N_OUT, ST_INPUT_TIMEOUT, ST_NOT_CONVERGED, ST_RESET, Out, Veh
from slipd.errors import ConfigError
from slipd.estimators.carnier2023 import hybrid_friction
from slipd.estimators.common.layout import build_layout
from slipd.estimators.common.params import nested_fields
from slipd.estimators.righetti_lenzo2025 import filters as rl
from slipd.estimators.righetti_lenzo2025.filters import S
from slipd.numba_cache import nb

#: The family's state (filters.FIELDS, at the same slots) and the friction estimator's.
LAYOUT = build_layout(
    "righetti_lenzo2025_d_ekf",
    *rl.FIELDS,
    ("FRICTION", hybrid_friction.LAYOUT),  # hybrid_friction's state (slip_friction)
    ("FRICTION_OUT", N_OUT),  # hybrid_friction's outputs of the tick
    "TYRE_MU",  # eq. 7's friction: its last finite estimate (NaN before the first)
)  # fmt: skip
_FRICTION = int(LAYOUT.S.FRICTION)
_FRICTION_END = _FRICTION + hybrid_friction.LAYOUT.size
_FRICTION_OUT = int(LAYOUT.S.FRICTION_OUT)
_TYRE_MU = int(LAYOUT.S.TYRE_MU)

#: the friction estimator's params, ``friction__<field>`` (defaults: hybrid_friction's)
_FRICTION_FIELDS = nested_fields("friction", hybrid_friction.PARAMS, hybrid_friction.DEFAULTS)
PARAMS, DEFAULTS = rl.shared_params(
    "d_ekf",
    ("R_VX", 2e-3),  # (m/s)^2, variance of vx_meas for sigma_beta only (r_vx of eq. 29)
    rl.P0_R,
    ("SLIP_FRICTION", 1.0),  # 1: eq. 7's mu from hybrid_friction's estimate (slipd), 0: profile's
    *_FRICTION_FIELDS,
    dynamic=True,  # eq. 28, as the DK-EKF's
)  # fmt: skip
_DYN_P_VV = int(S.DYN_P)
_FRICTION_PARAMS = int(PARAMS[_FRICTION_FIELDS[0][0]])
_FRICTION_PARAMS_END = _FRICTION_PARAMS + len(_FRICTION_FIELDS)
#: the friction estimator's statuses under which its mu is not reported
_FRICTION_UNSETTLED = ST_NOT_CONVERGED | ST_RESET | ST_INPUT_TIMEOUT


def init(params: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """A fresh state vector (``LAYOUT``): the filter starts on the first speed sample; the
    friction estimator's block is hybrid_friction's ``init`` with the ``friction__`` params
    (left zero, and its vehicle data not required, with ``slip_friction`` = 0)."""
    state = np.zeros(LAYOUT.size, dtype=np.float64)
    state[: rl.LAYOUT.size] = rl.new_state(vehicle, "d_ekf")
    state[_FRICTION_OUT : _FRICTION_OUT + N_OUT] = np.nan
    state[_TYRE_MU] = np.nan
    if params[PARAMS.SLIP_FRICTION] > 0.5:
        friction_params = np.array(params[_FRICTION_PARAMS:_FRICTION_PARAMS_END], dtype=np.float64)
        try:
            state[_FRICTION:_FRICTION_END] = hybrid_friction.init(friction_params, vehicle)
        except ConfigError as exc:
            raise ConfigError(f"d_ekf's friction estimator (slip_friction = 1): {exc}; or run "
                              "d_ekf:slip_friction=0 at the profile's friction") from None
    return state


@nb.njit(cache=True, inline="always")
def tyre_friction(state, u, params, vehicle, dt):
    """eq. 7's mu for this tick: with ``slip_friction`` hybrid_friction's estimate after its
    step on this tick's inputs (its last finite one while it has none, the profile's before
    the first), else the profile's."""
    if params[PARAMS.SLIP_FRICTION] < 0.5:
        return vehicle[Veh.MU_NOMINAL]
    friction_out = state[_FRICTION_OUT : _FRICTION_OUT + N_OUT]
    hybrid_friction.step(state[_FRICTION:_FRICTION_END], u,
                         params[_FRICTION_PARAMS:_FRICTION_PARAMS_END], vehicle, dt, friction_out)
    mu = friction_out[Out.MU]
    if math.isfinite(mu) and mu > 0.0:
        state[_TYRE_MU] = mu
    elif not state[_TYRE_MU] > 0.0:
        return vehicle[Veh.MU_NOMINAL]
    return state[_TYRE_MU]


@nb.njit(cache=True, inline="always")
def report_friction(state, out):
    """Out.MU and FRICTION_CLASS: the friction estimator's, while it is settled."""
    friction_out = state[_FRICTION_OUT : _FRICTION_OUT + N_OUT]
    status = friction_out[Out.STATUS]
    if math.isfinite(status) and not (int(status) & _FRICTION_UNSETTLED):
        out[Out.MU] = friction_out[Out.MU]
        out[Out.FRICTION_CLASS] = friction_out[Out.FRICTION_CLASS]


@nb.njit(cache=True, _nrt=False)
def step(state, u, params, vehicle, dt, out):
    """One 100 Hz tick of the D-EKF; writes every element of ``out``, allocates nothing.

    The kinematic slots of the state hold vx_meas (KIN_VX) and are otherwise unused.
    """
    p0_r = params[PARAMS.P0_R]
    mu = tyre_friction(state, u, params, vehicle, dt)
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
        report_friction(state, out)


@nb.njit(cache=True, nogil=True, _nrt=False)
def run_ticks(state, U, params, vehicle, dt, OUT):
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])

