"""``linear_kf``: the classic linear single-track (bicycle) Kalman filter, x = [vy, r].

The baseline nearly every sideslip paper compares against, and slipd's second floor beside
``zero``: the linear single-track model (R. Rajamani, *Vehicle Dynamics and Control*, 2nd ed.,
Springer 2012, Sec. 2.3, eq. 2.31, lateral dynamics in body-fixed coordinates) with the axle
cornering stiffnesses of the profile, scheduled on the measured speed vx, measuring the lateral
acceleration and the yaw rate, driven by the road-wheel steer angle. It is the filter of the
source of ``shared/realdata`` (MBDS/sideslip-angle-vehicle-estimation, estimators/matlab_kf,
Leanza et al. 2021) in the state [vy, r] instead of [beta, r].

Model (ISO 8855: y left, r and delta positive to the left; C_f, C_r axle stiffnesses, N/rad;
a = l_f, b = l_r; Rajamani writes 2 C_alpha per axle)::

    vy' = -(C_f + C_r) / (m vx) vy + (-vx - (C_f a - C_r b) / (m vx)) r + C_f / m delta
    r'  = -(C_f a - C_r b) / (Iz vx) vy - (C_f a^2 + C_r b^2) / (Iz vx) r + C_f a / Iz delta

i.e. x' = A(vx) x + B delta (small slip angles, tyre forces F = C alpha: the linear range).
Measurements y = [ay, r] with ay = vy' + vx r (the CoG lateral acceleration)::

    ay = -(C_f + C_r) / (m vx) vy - (C_f a - C_r b) / (m vx) r + C_f / m delta
    y  = C(vx) x + D delta,  C = [[-(C_f + C_r) / (m vx), -(C_f a - C_r b) / (m vx)], [0, 1]]

Discretised by forward Euler at the tick, as the source does: x_k = (I + A dt) x_{k-1} +
B dt delta_{k-1} with the speed of tick k-1, updated with y_k (C, D at vx_k and delta_k).

Noise, from the sensors' specifications (not tuned to any drive): the process noise is the
steer angle's, propagated through the input matrix (the source's Q_d = B_d q B_d'): the
steering-wheel angle sensor's 0.1 deg (slipd.sim.sensors; production EPS sensors resolve
0.05-0.1 deg) over the profile's steering ratio; R = diag(ay, r) from an ESC unit's IMU,
0.02 m/s^2 and 0.08 deg/s (Yoon et al. 2016, Table 1). The model's own error (tyre
saturation, a wrong cornering stiffness, road bank) is in neither: sigma_beta is the filter's
covariance as the classic filter states it, and says how far the linear model is trusted.

beta = atan2(vy, vx), vx the mean of the corner-compensated wheel speeds (as ``d_ekf``);
sigma_beta from the vy variance (vx taken as known). Pre-processing is the classic one: ay
moved to the CoG in the plane (Righetti-Lenzo eq. 21-23); ``roll_time_constant`` > 0 adds
slipd's roll-gravity compensation, ``lever_arm_3d`` the 3-D lever arm (both off: the baseline).

Status: as the other methods. Below ``min_speed`` (the model divides by vx) and before the
first speed sample the filter is held at vy = 0, r = the gyro, NOT_CONVERGED; INPUT_TIMEOUT
when ay, the yaw rate, the steer or a wheel speed is invalid (a missing measurement is left out
of the update, a missing steer holds the last one); RESET when the state is non-finite or
|vy| > vx (outside any single-track model); NOT_CONVERGED for ``settle_ticks`` after a (re)start
and while sigma_beta exceeds ``converged_sigma_beta``.
"""

from __future__ import annotations

import math

import numpy as np

from slipd.channels import (
    ST_INPUT_TIMEOUT,
    ST_NOT_CONVERGED,
    ST_RESET,
    WHEEL_SPEEDS,
    In,
    Out,
    Veh,
)
from slipd.estimators.common.inputs import ImuMemory, corner_speed_mean, read_inputs, reset_imu
from slipd.estimators.common.kalman import (
    add_input_noise,
    beta_sigma,
    innovation_test,
    joseph_update2,
    predict_covariance,
)
from slipd.estimators.common.kinematics import kinematic_beta_rate
from slipd.estimators.common.layout import build_layout
from slipd.estimators.common.outputs import held_sigma, write_held, write_outputs
from slipd.estimators.common.params import build_params
from slipd.estimators.common.vehicle import require_vehicle
from slipd.numba_cache import nb

PARAMS, DEFAULTS = build_params(
    "linear_kf",
    # sensor specifications (module docstring)
    ("SIGMA_STEER_WHEEL", math.radians(0.1)),  # rad, steering-wheel angle noise
    ("SIGMA_AY", 0.02),  # m/s^2, lateral accelerometer noise (Yoon 2016 Table 1)
    ("SIGMA_YAW_RATE", math.radians(0.08)),  # rad/s, gyro noise (Yoon 2016 Table 1)
    # bookkeeping (slipd; the values of the righetti_lenzo2025 family)
    ("MIN_SPEED", 3.0),  # m/s, below it the filter is held (A and C divide by vx)
    ("P0_VY", 1.0),  # (m/s)^2, initial vy variance
    ("P0_R", 1e-2),  # (rad/s)^2, initial yaw-rate variance
    ("YAW_ACC_CUTOFF_HZ", 10.0),  # Hz, derivative filter of the yaw rate (CoG translation)
    ("SETTLE_TICKS", 100.0),  # ticks after (re)start before convergence may be claimed
    ("CONVERGED_SIGMA_BETA", 0.0175),  # rad, sigma_beta below which the estimate has settled
    # pre-processing beyond the classic filter (0 and 0: the baseline)
    ("ROLL_TIME_CONSTANT", 0.0),  # s, roll-gravity compensation of ay; 0 = none
    ("LEVER_ARM_3D", 0.0),  # 1 = CoG shift with roll/pitch motion, 0 = planar
    ("ROLL_GAIN_LEARNING", 1.0),  # with the roll compensation: its static gain learnt (slipd)
    ("ACCEL_LOWPASS_HZ", 0.0),  # accelerometer vibration low-pass, Hz; 0 = none (the paper)
    ("NIS_TIME_CONSTANT", 1.0),  # s, averaging of the innovation test (Out.NIS)
)  # fmt: skip

LAYOUT = build_layout(
    "linear_kf",
    "VY",  # m/s, lateral velocity at the CoG
    "R",  # rad/s, yaw rate
    ("P", 3),  # packed covariance of [vy, r]
    "PREV_STEER",  # rad, the input of tick k-1 (drives the prediction at tick k)
    "PREV_VX",  # m/s, the speed the prediction is scheduled on
    "INITIALISED",  # 0 until the first tick with a usable speed measurement
    "TICKS",  # ticks since (re)start
    "NIS_MEAN",  # the innovation test: NIS per measurement, averaged (common.kalman)
    ("IMU", ImuMemory),  # CoG translation, optional roll compensation, held ax and steer
    ("SCRATCH", 4),  # working memory of the covariance predict
)
S = LAYOUT.S
#: Channels whose loss makes the output invalid (ax is not used).
REQUIRED = (In.AY, In.YAW_RATE, In.STEER, *WHEEL_SPEEDS)
_VY = int(S.VY)
_P = int(S.P)
_IMU = int(S.IMU)
_SCRATCH = int(S.SCRATCH)
_NIS_MEAN = int(S.NIS_MEAN)
_ROLL = _IMU + int(ImuMemory.ROLL)
#: floor of the speed in the held sigma_beta, m/s
HELD_SPEED_FLOOR = 0.1


def init(params: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """A fresh state vector (``LAYOUT``); the filter starts on the first speed sample."""
    require_vehicle("linear_kf", vehicle, (
        Veh.MASS, Veh.YAW_INERTIA, Veh.LF, Veh.LR, Veh.TRACK_F, Veh.TRACK_R,
        Veh.CORNERING_STIFFNESS_F, Veh.CORNERING_STIFFNESS_R, Veh.STEER_RATIO,
    ))  # fmt: skip
    state = np.zeros(LAYOUT.size, dtype=np.float64)
    reset_imu(state, _IMU)
    state[S.NIS_MEAN] = np.nan
    return state


@nb.njit(cache=True, _nrt=False)
def single_track_matrices(vx, vehicle):
    """A, B, C, D of the linear single-track model at speed ``vx`` > 0 (module docstring), as
    tuples: A row-major (4), B (2), C's first row (2; its second is [0, 1]), D's first element
    (its second is 0)."""
    mass = vehicle[Veh.MASS]
    yaw_inertia = vehicle[Veh.YAW_INERTIA]
    a = vehicle[Veh.LF]
    b = vehicle[Veh.LR]
    c_f = vehicle[Veh.CORNERING_STIFFNESS_F]
    c_r = vehicle[Veh.CORNERING_STIFFNESS_R]
    sum_c = (c_f + c_r) / (mass * vx)
    moment_c = (c_f * a - c_r * b) / (mass * vx)
    A = (-sum_c, -vx - moment_c,
         -(c_f * a - c_r * b) / (yaw_inertia * vx),
         -(c_f * a * a + c_r * b * b) / (yaw_inertia * vx))  # fmt: skip
    B = (c_f / mass, c_f * a / yaw_inertia)
    return A, B, (-sum_c, -moment_c), c_f / mass


@nb.njit(cache=True, _nrt=False)
def predict(state, vx, steer, sigma_steer, vehicle, dt):
    """x^- = (I + A dt) x + B dt delta, P^- = F P F' + (B dt) sigma_steer^2 (B dt)'."""
    A, B, _, _ = single_track_matrices(vx, vehicle)
    vy = state[S.VY]
    r = state[S.R]
    state[S.VY] = vy + (A[0] * vy + A[1] * r + B[0] * steer) * dt
    state[S.R] = r + (A[2] * vy + A[3] * r + B[1] * steer) * dt
    F = (1.0 + A[0] * dt, A[1] * dt, A[2] * dt, 1.0 + A[3] * dt)
    predict_covariance(state, _P, _SCRATCH, F, (0.0, 0.0))
    add_input_noise(state, _P, (B[0] * dt, B[1] * dt), sigma_steer * sigma_steer)


@nb.njit(cache=True, _nrt=False)
def model_ay(state, vx, steer, vehicle):
    """The model's lateral acceleration at the CoG, C[0] x + D[0] delta."""
    _, _, C, D = single_track_matrices(vx, vehicle)
    return C[0] * state[S.VY] + C[1] * state[S.R] + D * steer


@nb.njit(cache=True, _nrt=False)
def update(state, ay, ay_ok, yaw_rate, yaw_rate_ok, vx, steer, r_ay, r_yaw_rate, vehicle):
    """x, P with y = [ay, r] (H = C, innovation y - C x - D delta); a measurement flagged not
    ok is left out. Returns the normalised innovation squared and the number of measurements
    used."""
    _, _, C, _ = single_track_matrices(vx, vehicle)
    h11, h12, inn1, r1 = 0.0, 0.0, 0.0, 1.0
    if ay_ok:
        h11, h12 = C
        inn1 = ay - model_ay(state, vx, steer, vehicle)
        r1 = r_ay
    h22, inn2, r2 = 0.0, 0.0, 1.0
    if yaw_rate_ok:
        h22 = 1.0
        inn2 = yaw_rate - state[S.R]
        r2 = r_yaw_rate
    nis = joseph_update2(state, _VY, _P, h11, h12, 0.0, h22, inn1, inn2, r1, r2)
    return nis, int(ay_ok) + int(yaw_rate_ok)


@nb.njit(cache=True, _nrt=False)
def _start(state, vx, yaw_rate, steer, p0_vy, p0_r):
    """(Re)start at vy = 0 (straight-running assumption), r = measured, P = P0."""
    state[S.VY] = 0.0
    state[S.R] = yaw_rate if math.isfinite(yaw_rate) else 0.0
    state[_P] = p0_vy
    state[_P + 1] = 0.0
    state[_P + 2] = p0_r
    state[S.PREV_STEER] = steer if math.isfinite(steer) else 0.0
    state[S.PREV_VX] = vx
    state[S.TICKS] = 0.0
    state[S.NIS_MEAN] = math.nan


@nb.njit(cache=True, _nrt=False)
def step(state, u, params, vehicle, dt, out):
    """One 100 Hz tick; writes every element of ``out``, allocates nothing."""
    min_speed = params[PARAMS.MIN_SPEED]
    p0_vy = params[PARAMS.P0_VY]
    ax, ay, yaw_rate, _, steer, _, _, ay_ok, yaw_rate_ok, _, status = read_inputs(
        state, _IMU, u, vehicle, state[S.R], params[PARAMS.YAW_ACC_CUTOFF_HZ],
        params[PARAMS.ROLL_TIME_CONSTANT], params[PARAMS.LEVER_ARM_3D] > 0.5, dt,
        params[PARAMS.ROLL_GAIN_LEARNING] > 0.5, params[PARAMS.ACCEL_LOWPASS_HZ],
    )  # fmt: skip
    vx, n_wheels = corner_speed_mean(u, steer, yaw_rate, vehicle)
    if n_wheels < 4:
        status |= ST_INPUT_TIMEOUT
    held_floor = max(min_speed, HELD_SPEED_FLOOR)
    if not (state[S.INITIALISED] > 0.5 and state[S.PREV_VX] >= min_speed and vx >= min_speed):
        # start-up, standstill or crawling: A and C divide by vx
        if n_wheels > 0:
            _start(state, vx, yaw_rate, steer, p0_vy, params[PARAMS.P0_R])
            state[S.INITIALISED] = 1.0
        write_held(out, vx, held_sigma(p0_vy, vx, held_floor), 0.0, status)
        return
    sigma_steer = params[PARAMS.SIGMA_STEER_WHEEL] / vehicle[Veh.STEER_RATIO]
    predict(state, state[S.PREV_VX], state[S.PREV_STEER], sigma_steer, vehicle, dt)
    sigma_ay = params[PARAMS.SIGMA_AY]
    sigma_r = params[PARAMS.SIGMA_YAW_RATE]
    nis, dof = update(state, ay, ay_ok, yaw_rate, yaw_rate_ok, vx, steer, sigma_ay * sigma_ay,
                      sigma_r * sigma_r, vehicle)  # fmt: skip
    innovation_test(state, _NIS_MEAN, nis, dof, dt, params[PARAMS.NIS_TIME_CONSTANT])
    state[S.PREV_STEER] = steer
    state[S.PREV_VX] = vx
    vy = state[S.VY]
    finite = True
    for i in range(_VY, _P + 3):
        finite = finite and math.isfinite(state[i])
    if not (finite and abs(vy) <= vx):
        # outside any single-track model's domain (a spin, a corrupt sensor): restart
        _start(state, vx, yaw_rate, steer, p0_vy, params[PARAMS.P0_R])
        write_held(out, vx, held_sigma(p0_vy, vx, held_floor), 0.0, status | ST_RESET)
        return
    state[S.TICKS] += 1.0
    if not ay_ok:
        ay = model_ay(state, vx, steer, vehicle)  # for the beta rate: the model's ay
    sigma = beta_sigma(vx, vy, 0.0, 0.0, state[_P], math.nan)
    if state[S.TICKS] < params[PARAMS.SETTLE_TICKS] or not (
        sigma <= params[PARAMS.CONVERGED_SIGMA_BETA]
    ):
        status |= ST_NOT_CONVERGED
    write_outputs(out, math.atan2(vy, vx), kinematic_beta_rate(vx, vy, ax, ay, state[S.R]), vx,
                  vy, math.nan, sigma, state[_ROLL], 0.0, status)  # fmt: skip
    out[Out.NIS] = state[S.NIS_MEAN]


@nb.njit(cache=True, nogil=True, _nrt=False)
def run_ticks(state, U, params, vehicle, dt, OUT):
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])


__all__ = ["DEFAULTS", "LAYOUT", "PARAMS", "REQUIRED", "init", "run_ticks", "step"]
