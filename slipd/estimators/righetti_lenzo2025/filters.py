"""The two filters of Righetti & Lenzo 2025 and the tick scaffolding their three methods share.

dynamic EKF (Sec. 2.1), x_dyn = [vy, r], u_dyn = [vx, delta]
    eq. 1  vy' = (Fyf cos(delta) + Fyr) / m - vx r
    eq. 2  r'  = (a Fyf cos(delta) - b Fyr) / Izz
    eq. 7  Fy  = mu Fz tanh(C alpha / (mu Fz)), Fz the static axle load m g b / l, m g a / l
           alpha_f = delta - atan((vy + a r) / vx), alpha_r = -atan((vy - b r) / vx)  (Sec. 3.2)
    eq. 8  forward Euler, x_k = x_{k-1} + f(x_{k-1}, u_{k-1}) dt
    eq. 9  y_dyn = [r_meas, ay_meas] = [r, (Fyf cos(delta) + Fyr) / m]

kinematic KF (Sec. 2.2), x_kin = [vx, vy], u_kin = [ax, ay]
    eq. 10-13  vx' = vy r + ax, vy' = -vx r + ay, F_k = I + [[0, r], [-r, 0]] dt, G_k = I dt
    eq. 14     y_kin = vx_meas (K-KF)
    eq. 19     y_kin = [vx_meas, vy_dyn] with H = I (DK-EKF: the dynamic vy as pseudo-measurement)
    eq. 5-6    vx_meas = mean of the four corner velocities, corrected for steer (front) and the
               yaw rate times the half track (``common.inputs.corner_speed_mean``)

Covariances (Sec. 4): eq. 28 Q_dyn, R_dyn; eq. 29 Q_kin = diag(q_vx, 0.1 p_vy_dyn),
R_kin = diag(r_vx, p_vy_dyn) with p_vy_dyn the vy variance of the dynamic EKF at tick k;
eq. 30 the K-KF's own Q and R. The paper states its Q matrices for its sampling interval
dt = 0.01 s (eq. 8): the params keep the paper's per-sample values (``nominal_dt``) and the
kernels get Q per step (``common.kalman.per_step``), so that the process noise per second
stays the paper's at another rate. The algebra is ``common.kalman``'s (packed P, Joseph form).

Sign convention: the paper's axes are x forward, y left, r positive turning left (its
eq. 6 adds r t/2 to the left wheels), i.e. ISO 8855 as in slipd; a = lf, b = lr. No
conversion is needed.

Pre-processing. The paper (Sec. 3.1) only moves the IMU accelerations to the CoG in the plane
(eq. 21-23, r_dot from a derivative filter). slipd adds two blocks of ``estimators.common``
by default, the same for all three methods so that the comparison stays the paper's: the
gravity component of the body roll is removed from ay (Selmanaj 2017 eq. 16-17,
complementary filter with the roll rate; ``roll_time_constant`` > 0) and the lever arm
includes roll and pitch motion (``lever_arm_3d``). Why: the kinematic part integrates ay,
and in steady cornering a roll of phi adds g sin(phi) to it; the DK-EKF's pseudo-measurement
only pulls vy back with gain K ~ 0.27 per tick (steady state of eq. 29's q/r = 0.1), which
leaves a vy error of about b (1 - K) / (K |d vy'/d vy|) for an ay error b (measured on the
step steer: benchmarks/MEASUREMENTS.md). Set both params to 0 for the paper's.

Robustness (not in the paper): invalid inputs fall back (yaw rate -> the model's, ay -> the
model's, steer and ax -> last valid) and raise INPUT_TIMEOUT; below ``min_speed`` the filters
are held at vy = 0 (the slip angles of eq. 7 are undefined at vx -> 0); a non-finite state or
one with |vy| > vx (outside any single-track model's domain) restarts the filters with RESET.

State vector: ``LAYOUT``, one for all three methods (a method leaves the slots it does not use
at their init values).
"""

from __future__ import annotations

import math

import numpy as np

from slipd.channels import ST_INPUT_TIMEOUT, ST_NOT_CONVERGED, ST_RESET, G, Out, Veh
from slipd.estimators.common.inputs import ImuMemory, corner_speed_mean, read_inputs, reset_imu
from slipd.estimators.common.kalman import (
    beta_sigma,
    innovation_test,
    joseph_update2,
    optional_row,
    per_step,
    predict_covariance,
)
from slipd.estimators.common.kinematics import kinematic_beta_rate
from slipd.estimators.common.layout import build_layout
from slipd.estimators.common.outputs import held_sigma, write_held, write_outputs
from slipd.estimators.common.params import build_params
from slipd.estimators.common.tyres import slip_angles, tanh_tyre
from slipd.estimators.common.vehicle import require_vehicle
from slipd.numba_cache import nb

#: The fields of the state all three methods share (``LAYOUT``); d_ekf appends its friction
#: estimator's block to them (``d_ekf.LAYOUT``), so these slots sit where ``S`` says in both.
FIELDS = (
    # dynamic EKF (eq. 3): lateral velocity [m/s], yaw rate [rad/s], P_dyn packed
    "DYN_VY", "DYN_R", ("DYN_P", 3),
    # kinematic KF (eq. 12): longitudinal, lateral velocity [m/s], P_kin packed
    "KIN_VX", "KIN_VY", ("KIN_P", 3),
    # the inputs of tick k-1, which feed the prediction at tick k (Fig. 3)
    "PREV_AX",  # m/s^2 at the CoG
    "PREV_AY",  # m/s^2 at the CoG
    "PREV_YAW_RATE",  # rad/s
    "PREV_STEER",  # rad
    "PREV_VX",  # m/s, the dynamic part's speed input
    ("IMU", ImuMemory),  # CoG translation, roll compensation, held ax and steer
    "INITIALISED",  # 0 until the first tick with a usable speed measurement
    "TICKS",  # ticks since init or reset
    "NIS_MEAN",  # the innovation test: NIS per measurement, averaged (common.kalman)
    ("SCRATCH", 4),  # working memory of the covariance predict
)  # fmt: skip
LAYOUT = build_layout("righetti_lenzo2025", *FIELDS)
S = LAYOUT.S
_DYN_VY = int(S.DYN_VY)
_DYN_P = int(S.DYN_P)
_KIN_VX = int(S.KIN_VX)
_KIN_P = int(S.KIN_P)
_IMU = int(S.IMU)
_SCRATCH = int(S.SCRATCH)
_NIS_MEAN = int(S.NIS_MEAN)
_ROLL = _IMU + int(ImuMemory.ROLL)
_LAST_AX = _IMU + int(ImuMemory.LAST_AX)
_LAST_STEER = _IMU + int(ImuMemory.LAST_STEER)
#: slots that must stay finite: both filters, the held inputs (the derivative and roll
#: filters restart themselves from a non-finite value)
_FILTERS_END = int(S.PREV_VX) + 1

#: The bookkeeping params every method of the family has (slipd's: the paper gives none). They
#: come first in every method's PARAMS (``shared_params``), so the scaffolding reads them itself.
FILTER_PARAMS = (
    ("NOMINAL_DT", 0.01),  # s, the sampling interval the paper's Q values hold for (eq. 8)
    ("MIN_SPEED", 3.0),  # m/s, below it the filters are held
    ("P0_VY", 1.0),  # (m/s)^2, initial vy variance
    ("YAW_ACC_CUTOFF_HZ", 10.0),  # Hz, derivative filter of the yaw rate for eq. 22-23
    ("SETTLE_TICKS", 100.0),  # ticks after (re)start before convergence may be claimed
    ("CONVERGED_SIGMA_BETA", 0.0175),  # rad, sigma_beta below which the estimate has settled
    # pre-processing beyond the paper's Sec. 3.1 (module docstring; 0 and 0 = the paper's)
    ("ROLL_TIME_CONSTANT", 1.0),  # s, roll complementary filter; 0 = none
    ("LEVER_ARM_3D", 1.0),  # 1 = CoG shift with roll/pitch motion, 0 = planar
    ("ROLL_GAIN_LEARNING", 1.0),  # 1 = the roll compensation's static gain learnt, 0 = profile's
    ("ACCEL_LOWPASS_HZ", 0.0),  # accelerometer vibration low-pass, Hz; 0 = none (the paper)
    ("NIS_TIME_CONSTANT", 1.0),  # s, averaging of the innovation test (Out.NIS)
)
#: Q_dyn and R_dyn of eq. 28 (Sec. 4), the dynamic EKF's in dk_ekf and d_ekf ("The D-EKF
#: covariance matrices are set equal to the ones in (28)"); they follow FILTER_PARAMS there.
DYNAMIC_PARAMS = (
    ("Q_VY_DYN", 3e-6),  # (m/s)^2 per tick
    ("Q_R_DYN", 1e-6),  # (rad/s)^2 per tick
    ("R_YAW_RATE_DYN", 4e-7),  # (rad/s)^2
    ("R_AY_DYN", 6e-2),  # (m/s^2)^2
)
FILTER, _ = build_params("righetti_lenzo2025", *FILTER_PARAMS)
DYNAMIC, _ = build_params("righetti_lenzo2025_dynamic", *FILTER_PARAMS, *DYNAMIC_PARAMS)
P0_R = ("P0_R", 1e-2)  # (rad/s)^2, initial yaw-rate variance (slipd)
P0_VX = ("P0_VX", 1.0)  # (m/s)^2, initial vx variance (slipd)


def shared_params(method: str, *own: tuple[str, float], dynamic: bool = False):
    """(PARAMS, DEFAULTS) of a method of the family: FILTER_PARAMS first, then (with
    ``dynamic``) eq. 28's DYNAMIC_PARAMS, then the method's own."""
    return build_params(method, *FILTER_PARAMS, *(DYNAMIC_PARAMS if dynamic else ()), *own)
#: floor of the speed in the held sigma_beta, m/s
HELD_SPEED_FLOOR = 0.1


# ---------------------------------------------------------------------------------------------
# the models
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True, _nrt=False)
def single_track(vy, r, vx, steer, vehicle, mu):
    """The nonlinear single-track model (eq. 1, 2, 7) and its Jacobians, at the tyre-road
    friction ``mu`` of eq. 7 (the profile's peak friction in the paper; d_ekf's slip-based
    estimate with its ``slip_friction``).

    Returns (vy_dot, r_dot, ay_model, J11, J12, J21, J22) where J = d(vy_dot, r_dot)/d(vy, r) and
    ay_model = (Fyf cos(delta) + Fyr) / m is the measurement of eq. 9, whose Jacobian row is
    [J11, J12 + vx] (vy_dot = ay_model - vx r). ``vx`` must be positive (the caller holds the
    filter below its minimum speed).
    """
    inv_mass = 1.0 / vehicle[Veh.MASS]
    inv_yaw_inertia = 1.0 / vehicle[Veh.YAW_INERTIA]
    lf = vehicle[Veh.LF]
    lr = vehicle[Veh.LR]
    # static axle loads, Sec. 2.1 (F_zf = m g b / l, F_zr = m g a / l), times mu
    mu_weight_per_length = mu * vehicle[Veh.MASS] * G / (lf + lr)
    mu_fz_front = mu_weight_per_length * lr
    mu_fz_rear = mu_weight_per_length * lf
    # slip angles (Sec. 3.2) and their partial derivatives
    alpha_f, alpha_r, dalpha_f_dvy, dalpha_r_dvy = slip_angles(vx, vy, r, steer, lf, lr)
    dalpha_f_dr = lf * dalpha_f_dvy
    dalpha_r_dr = -lr * dalpha_r_dvy
    stiffness_f = vehicle[Veh.CORNERING_STIFFNESS_F]
    stiffness_r = vehicle[Veh.CORNERING_STIFFNESS_R]
    force_f, slope_f = tanh_tyre(alpha_f, stiffness_f / mu_fz_front, mu_fz_front, stiffness_f)
    force_r, slope_r = tanh_tyre(alpha_r, stiffness_r / mu_fz_rear, mu_fz_rear, stiffness_r)
    cos_steer = math.cos(steer)
    force_f_y = force_f * cos_steer  # front force projected on the body y axis
    slope_f_y = slope_f * cos_steer
    ay_model = (force_f_y + force_r) * inv_mass
    vy_dot = ay_model - vx * r
    r_dot = (lf * force_f_y - lr * force_r) * inv_yaw_inertia
    j11 = (slope_f_y * dalpha_f_dvy + slope_r * dalpha_r_dvy) * inv_mass
    j12 = (slope_f_y * dalpha_f_dr + slope_r * dalpha_r_dr) * inv_mass - vx
    j21 = (lf * slope_f_y * dalpha_f_dvy - lr * slope_r * dalpha_r_dvy) * inv_yaw_inertia
    j22 = (lf * slope_f_y * dalpha_f_dr - lr * slope_r * dalpha_r_dr) * inv_yaw_inertia
    return vy_dot, r_dot, ay_model, j11, j12, j21, j22


@nb.njit(cache=True, _nrt=False)
def dynamic_predict(state, vx, steer, vehicle, mu, q_vy, q_r, dt):
    """A priori step of the dynamic EKF (eq. 8): x^- = x + f(x, u) dt, P^- = F P F' + Q_dyn
    (Q per step), at friction ``mu``."""
    vy = state[S.DYN_VY]
    r = state[S.DYN_R]
    vy_dot, r_dot, _, j11, j12, j21, j22 = single_track(vy, r, vx, steer, vehicle, mu)
    state[S.DYN_VY] = vy + vy_dot * dt
    state[S.DYN_R] = r + r_dot * dt
    # F = I + J dt (the Jacobian of the Euler map eq. 8)
    predict_covariance(state, _DYN_P, _SCRATCH,
                       (1.0 + j11 * dt, j12 * dt, j21 * dt, 1.0 + j22 * dt), (q_vy, q_r))


@nb.njit(cache=True, _nrt=False)
def dynamic_update(state, yaw_rate, yaw_rate_ok, ay, ay_ok, vx, steer, vehicle, mu, r_r, r_ay):
    """A posteriori step of the dynamic EKF with y = [r_meas, ay_meas] (eq. 9), at friction
    ``mu``.

    A measurement flagged not ok is left out (its H row and innovation zeroed). Returns the
    normalised innovation squared and the number of measurements used."""
    _, _, ay_model, j11, j12, _, _ = single_track(state[S.DYN_VY], state[S.DYN_R], vx, steer,
                                                  vehicle, mu)  # fmt: skip
    # H = d h / d x: row 1 picks r, row 2 is d ay_model / d(vy, r) = [J11, J12 + vx]
    h11, h12, inn1, r1 = optional_row(yaw_rate_ok, 0.0, 1.0, yaw_rate - state[S.DYN_R], r_r)
    h21, h22, inn2, r2 = optional_row(ay_ok, j11, j12 + vx, ay - ay_model, r_ay)
    nis = joseph_update2(state, _DYN_VY, _DYN_P, h11, h12, h21, h22, inn1, inn2, r1, r2)
    return nis, int(yaw_rate_ok) + int(ay_ok)


@nb.njit(cache=True, _nrt=False)
def kinematic_predict(state, ax, ay, yaw_rate, q_vx, q_vy, dt):
    """A priori step of the kinematic KF (eq. 13): x^- = (I + F dt) x + G dt u (Q per step)."""
    vx = state[S.KIN_VX]
    vy = state[S.KIN_VY]
    state[S.KIN_VX] = vx + (vy * yaw_rate + ax) * dt  # eq. 10
    state[S.KIN_VY] = vy + (-vx * yaw_rate + ay) * dt  # eq. 11
    predict_covariance(state, _KIN_P, _SCRATCH, (1.0, yaw_rate * dt, -yaw_rate * dt, 1.0),
                       (q_vx, q_vy))  # fmt: skip


@nb.njit(cache=True, _nrt=False)
def kinematic_update(state, vx_meas, vx_ok, r_vx, vy_pseudo, vy_ok, r_vy):
    """A posteriori step of the kinematic KF, H = I (eq. 19) or H = [1 0] (eq. 14, vy_ok False).
    Returns the normalised innovation squared and the number of measurements used."""
    h11, h12, inn1, r1 = optional_row(vx_ok, 1.0, 0.0, vx_meas - state[S.KIN_VX], r_vx)
    h21, h22, inn2, r2 = optional_row(vy_ok, 0.0, 1.0, vy_pseudo - state[S.KIN_VY], r_vy)
    nis = joseph_update2(state, _KIN_VX, _KIN_P, h11, h12, h21, h22, inn1, inn2, r1, r2)
    return nis, int(vx_ok) + int(vy_ok)


# ---------------------------------------------------------------------------------------------
# the tick scaffolding of the three methods
# ---------------------------------------------------------------------------------------------


def new_state(vehicle: np.ndarray, method: str) -> np.ndarray:
    """A state vector before the first tick (filters not started: INITIALISED = 0), after
    checking the vehicle the single-track model needs."""
    require_vehicle(method, vehicle, (
        Veh.MASS, Veh.YAW_INERTIA, Veh.LF, Veh.LR, Veh.TRACK_F, Veh.TRACK_R,
        Veh.CORNERING_STIFFNESS_F, Veh.CORNERING_STIFFNESS_R, Veh.MU_NOMINAL,
    ))  # fmt: skip
    state = np.zeros(LAYOUT.size, dtype=np.float64)
    reset_imu(state, _IMU)
    state[S.NIS_MEAN] = np.nan
    return state


@nb.njit(cache=True, _nrt=False)
def reset_state(state, vx, yaw_rate, steer, p0_vy, p0_r, p0_vx):
    """Start (or restart) both filters: vy = 0 (straight-running assumption), r = measured."""
    # a reset must not inherit a non-finite input fallback from the state it replaces
    vx = vx if math.isfinite(vx) else 0.0
    yaw_rate = yaw_rate if math.isfinite(yaw_rate) else 0.0
    steer = steer if math.isfinite(steer) else 0.0
    state[S.DYN_VY] = 0.0
    state[S.DYN_R] = yaw_rate
    state[_DYN_P] = p0_vy
    state[_DYN_P + 1] = 0.0
    state[_DYN_P + 2] = p0_r
    state[S.KIN_VX] = vx
    state[S.KIN_VY] = 0.0
    state[_KIN_P] = p0_vx
    state[_KIN_P + 1] = 0.0
    state[_KIN_P + 2] = p0_vy
    state[S.PREV_AX] = 0.0
    state[S.PREV_AY] = 0.0
    state[S.PREV_YAW_RATE] = yaw_rate
    state[S.PREV_STEER] = steer
    state[S.PREV_VX] = vx
    state[_LAST_AX] = 0.0
    state[_LAST_STEER] = steer
    state[S.TICKS] = 0.0
    state[S.NIS_MEAN] = math.nan


@nb.njit(cache=True, inline="always")
def state_is_finite(state):
    """True when both filters and the held inputs are finite."""
    for i in range(_FILTERS_END):
        if not math.isfinite(state[i]):
            return False
    return math.isfinite(state[_LAST_AX]) and math.isfinite(state[_LAST_STEER])


@nb.njit(cache=True, inline="always")
def begin_tick(state, u, params, vehicle, dt):
    """The tick's inputs (``common.inputs.read_inputs``; an invalid yaw rate falls back to
    the previous tick's, a caller with a model may prefer its estimate) and whether the
    filters run (started and at least ``min_speed``). Returns (ax, ay, yaw_rate, steer,
    ay_ok, yaw_rate_ok, running, status)."""
    ax, ay, yaw_rate, _, steer, _, _, ay_ok, yaw_rate_ok, _, status = read_inputs(
        state, _IMU, u, vehicle, state[S.PREV_YAW_RATE], params[FILTER.YAW_ACC_CUTOFF_HZ],
        params[FILTER.ROLL_TIME_CONSTANT], params[FILTER.LEVER_ARM_3D] > 0.5, dt,
        params[FILTER.ROLL_GAIN_LEARNING] > 0.5, params[FILTER.ACCEL_LOWPASS_HZ],
    )  # fmt: skip
    running = state[S.INITIALISED] > 0.5 and state[S.KIN_VX] >= params[FILTER.MIN_SPEED]
    return ax, ay, yaw_rate, steer, ay_ok, yaw_rate_ok, running, status


@nb.njit(cache=True, inline="always")
def begin_dynamic_tick(state, u, params, vehicle, mu, dt):
    """``begin_tick``, then, while the filters run, the dynamic EKF's a priori step (eq. 8)
    with u_dyn = [vx, delta] of tick k-1, eq. 28's Q (``params`` laid out as DYNAMIC's) and
    friction ``mu``; the model's yaw rate stands in for an invalid gyro. Returns what
    ``begin_tick`` does."""
    ax, ay, yaw_rate, steer, ay_ok, yaw_rate_ok, running, status = begin_tick(
        state, u, params, vehicle, dt
    )
    if running:
        nominal_dt = params[DYNAMIC.NOMINAL_DT]
        dynamic_predict(state, state[S.PREV_VX], state[S.PREV_STEER], vehicle, mu,
                        per_step(params[DYNAMIC.Q_VY_DYN], dt, nominal_dt),
                        per_step(params[DYNAMIC.Q_R_DYN], dt, nominal_dt), dt)
        if not yaw_rate_ok:
            yaw_rate = state[S.DYN_R]  # the model's yaw rate stands in for the gyro
    return ax, ay, yaw_rate, steer, ay_ok, yaw_rate_ok, running, status


@nb.njit(cache=True, inline="always")
def measured_speed(u, steer, yaw_rate, vehicle, status):
    """vx_meas of eq. 5-6; INPUT_TIMEOUT when a wheel speed is missing. Returns (vx_meas,
    vx_ok, status)."""
    vx_meas, n_wheels = corner_speed_mean(u, steer, yaw_rate, vehicle)
    if n_wheels < 4:
        status |= ST_INPUT_TIMEOUT
    return vx_meas, n_wheels > 0, status


@nb.njit(cache=True, inline="always")
def hold(state, out, vx_meas, vx_ok, ax, ay, yaw_rate, steer, params, p0_r, p0_vx, status):
    """A tick on which the filters cannot run: before the first speed sample or below the
    minimum speed, where the slip angles of eq. 7 (atan of (vy + a r) / vx) are undefined.

    With a speed sample both filters restart at vy = 0 with their initial covariance and
    vx = vx_meas, and the tick's inputs are kept for the next prediction. Writes the held
    outputs."""
    if vx_ok:
        reset_state(state, vx_meas, yaw_rate, steer, params[FILTER.P0_VY], p0_r, p0_vx)
        state[S.INITIALISED] = 1.0
    state[S.PREV_AX] = ax
    state[S.PREV_AY] = ay
    _write_held(out, vx_meas if vx_ok else state[S.KIN_VX], params, status)


@nb.njit(cache=True, inline="always")
def _write_held(out, vx, params, status):
    floor = max(params[FILTER.MIN_SPEED], HELD_SPEED_FLOOR)
    write_held(out, vx, held_sigma(params[FILTER.P0_VY], vx, floor), 0.0, status)


@nb.njit(cache=True, inline="always")
def finish_tick(state, out, status, vx_meas, vx_ok, yaw_rate, steer, params, p0_r, p0_vx):
    """Reset on a non-finite or implausible state (writing the held outputs); returns (status
    with RESET, reset?).

    Non-finite: openpilot paramsd's rule. Implausible: the velocity estimate points more than
    45 deg off the x axis (|vy| > vx), beyond any single-track tyre model's domain; it comes
    from inputs the models cannot explain (a spin, a corrupt sensor) and a filter that has
    left the domain does not come back by itself.
    """
    if state_is_finite(state) and abs(state[S.KIN_VY]) <= state[S.KIN_VX]:
        state[S.TICKS] += 1.0
        return status, False
    reset_state(state, vx_meas if vx_ok else 0.0, yaw_rate, steer, params[FILTER.P0_VY], p0_r,
                p0_vx)  # fmt: skip
    if not vx_ok:
        state[S.INITIALISED] = 0.0
    status |= ST_RESET
    _write_held(out, state[S.KIN_VX], params, status)
    return status, True


@nb.njit(cache=True, inline="always")
def write_estimate(state, out, vx, vy, p_xx, p_xy, p_yy, ax, ay, yaw_rate, params, status):
    """Outputs of a running tick: beta = atan2(vy, vx) (eq. 4) with the 1-sigma of the [vx, vy]
    covariance, the kinematic beta rate, the gravity compensation's roll; NOT_CONVERGED until
    ``settle_ticks`` after a (re)start and while sigma exceeds ``converged_sigma_beta``."""
    sigma = beta_sigma(vx, vy, p_xx, p_xy, p_yy, math.nan)
    if state[S.TICKS] < params[FILTER.SETTLE_TICKS] or not (
        sigma <= params[FILTER.CONVERGED_SIGMA_BETA]
    ):
        status |= ST_NOT_CONVERGED
    write_outputs(out, math.atan2(vy, vx), kinematic_beta_rate(vx, vy, ax, ay, yaw_rate), vx, vy,
                  math.nan, sigma, state[_ROLL], 0.0, status)  # fmt: skip
    out[Out.NIS] = state[S.NIS_MEAN]


@nb.njit(cache=True, inline="always")
def record_innovations(state, nis, dof, params, dt):
    """The tick's update into the innovation test (``common.kalman.innovation_test``)."""
    innovation_test(state, _NIS_MEAN, nis, dof, dt, params[FILTER.NIS_TIME_CONSTANT])


@nb.njit(cache=True, inline="always")
def remember_inputs(state, ax, ay, yaw_rate, steer):
    """Keep tick k's inputs: they drive the predictions at tick k + 1 (Fig. 3)."""
    state[S.PREV_AX] = ax
    state[S.PREV_AY] = ay
    state[S.PREV_YAW_RATE] = yaw_rate
    state[S.PREV_STEER] = steer
