"""Shared kernels of the Righetti & Lenzo 2025 DK-EKF family (``dk_ekf``, ``d_ekf``, ``k_kf``).

G. Righetti, B. Lenzo, "A Combined Dynamic-Kinematic Extended Kalman Filter for Estimating
Vehicle Sideslip Angle", Appl. Sci. 15(3), 1365, 2025 (shared/papers/righetti-lenzo2025-dk-ekf.txt).

Two filters, each on a 2-state vector, with every 2x2 product written out in scalars so the
per-tick path allocates nothing and calls no ``np.linalg``:

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
               yaw rate times the half track

Covariances (Sec. 4): eq. 28 Q_dyn, R_dyn; eq. 29 Q_kin = diag(q_vx, 0.1 p_vy_dyn),
R_kin = diag(r_vx, p_vy_dyn) with p_vy_dyn the vy variance of the dynamic EKF at tick k;
eq. 30 the K-KF's own Q and R.

Sign convention: the paper's axes are x forward, y left, r positive turning left (its
eq. 6 adds r t/2 to the left wheels), i.e. ISO 8855 as in slipd; a = lf, b = lr. No
conversion is needed.

The paper states its Q matrices for its sampling interval dt = 0.01 s (eq. 8); the kernels scale
Q by dt / NOMINAL_DT so that the process noise per second stays the paper's at another rate.

Pre-processing. The paper (Sec. 3.1) only moves the IMU accelerations to the CoG in the plane
(eq. 21-23, r_dot from a derivative filter). slipd adds two blocks of
``slipd.estimators.preprocess`` by default, the same for all three methods so that the
comparison stays the paper's: the gravity component of the body roll is removed from ay
(Selmanaj 2017 eq. 16-17, complementary filter with the roll rate; ``roll_time_constant`` > 0)
and the lever arm includes roll and pitch motion (``lever_arm_3d``). Why: the kinematic part
integrates ay, and in steady cornering a roll of phi adds g sin(phi) to it; the DK-EKF's
pseudo-measurement only pulls vy back with gain K ~ 0.27 per tick (steady state of eq. 29's
q/r = 0.1), which leaves a vy error of about b (1 - K) / (K |d vy'/d vy|) for an ay error b.
On the simulator's step steer (7 deg of roll at 8.7 m/s^2) that was 0.59 deg of beta RMS with
the paper's pre-processing and 0.20 deg with both blocks. Set both params to 0 for the paper's.

Robustness (not in the paper): invalid inputs fall back (yaw rate -> the model's, ay -> the
model's, steer and ax -> last valid) and raise INPUT_TIMEOUT; below ``min_speed`` the filters
are held at vy = 0 (the slip angles of eq. 7 are undefined at vx -> 0); a non-finite state or
one with |vy| > vx (outside any single-track model's domain) restarts the filters with RESET.

State vector layout: ``S`` below, one layout for all three methods (a method leaves the slots it
does not use at their init values). Everything is float64.
"""

from __future__ import annotations

import enum
import math

import numba as nb
import numpy as np

from slipd.channels import (
    ST_DEGRADED,
    ST_INPUT_TIMEOUT,
    ST_NOT_CONVERGED,
    ST_RESET,
    G,
    In,
    Out,
    Veh,
)
from slipd.estimators.preprocess import (
    channel,
    compensate_gravity_ay,
    derivative_filter,
    roll_complementary_filter,
    roll_static_gain,
    translate_to_cog,
    translate_to_cog_planar,
)


@enum.unique
class S(enum.IntEnum):
    """Elements of the state vector shared by dk_ekf, d_ekf and k_kf."""

    # dynamic EKF (eq. 3): lateral velocity [m/s], yaw rate [rad/s], covariance P_dyn (symmetric)
    DYN_VY = 0
    DYN_R = 1
    DYN_P_VV = 2  # (m/s)^2
    DYN_P_VR = 3  # m/s * rad/s
    DYN_P_RR = 4  # (rad/s)^2
    # kinematic KF (eq. 12): longitudinal, lateral velocity [m/s], covariance P_kin (symmetric)
    KIN_VX = 5
    KIN_VY = 6
    KIN_P_XX = 7
    KIN_P_XY = 8
    KIN_P_YY = 9
    # the inputs of tick k-1, which feed the prediction at tick k (Fig. 3)
    PREV_AX = 10  # m/s^2 at the CoG
    PREV_AY = 11  # m/s^2 at the CoG
    PREV_YAW_RATE = 12  # rad/s
    PREV_STEER = 13  # rad
    PREV_VX = 14  # m/s, the dynamic part's speed input
    # last finite, valid value of inputs that have no model-based fallback
    LAST_AX = 15
    LAST_STEER = 16
    # yaw-acceleration derivative filter (CoG translation, eq. 21-23)
    YAW_RATE_FILTERED = 17
    # bookkeeping
    INITIALISED = 18  # 0 until the first tick with a usable speed measurement
    TICKS = 19  # ticks since init or reset
    ROLL = 20  # rad, roll estimate of the optional gravity compensation (NaN: not started)
    ROLL_RATE_FILTERED = 21  # derivative filters of the optional 3-D lever-arm translation
    PITCH_RATE_FILTERED = 22


N_STATE = len(S)

# ---------------------------------------------------------------------------------------------
# 2x2 Kalman algebra in scalars (symmetric P stored as p11, p12, p22)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def predict_covariance(p11, p12, p22, f11, f12, f21, f22, q1, q2):
    """P^- = F P F' + Q with Q = diag(q1, q2); returns (p11, p12, p22)."""
    # FP = F P
    a11 = f11 * p11 + f12 * p12
    a12 = f11 * p12 + f12 * p22
    a21 = f21 * p11 + f22 * p12
    a22 = f21 * p12 + f22 * p22
    # (F P) F' + Q
    n11 = a11 * f11 + a12 * f12 + q1
    n12 = a11 * f21 + a12 * f22
    n22 = a21 * f21 + a22 * f22 + q2
    return n11, n12, n22


@nb.njit(cache=True)
def update_two(x1, x2, p11, p12, p22, h11, h12, h21, h22, inn1, inn2, r1, r2):
    """One Kalman measurement update of a 2-state filter with two measurements.

    H = [[h11, h12], [h21, h22]], R = diag(r1, r2), innovation (y - h(x^-)) = [inn1, inn2].
    A missing measurement is passed as a zero H row, zero innovation and r = 1: its gain column
    is then exactly zero and the update reduces to the scalar update of the other one.
    Covariance in Joseph form (as filterpy's ``KalmanFilter.update``), which keeps P symmetric
    positive definite with any gain. Returns (x1, x2, p11, p12, p22).
    """
    # PHt = P H'
    b11 = p11 * h11 + p12 * h12
    b12 = p11 * h21 + p12 * h22
    b21 = p12 * h11 + p22 * h12
    b22 = p12 * h21 + p22 * h22
    # S = H P H' + R
    s11 = h11 * b11 + h12 * b21 + r1
    s12 = h11 * b12 + h12 * b22
    s21 = h21 * b11 + h22 * b21
    s22 = h21 * b12 + h22 * b22 + r2
    det = s11 * s22 - s12 * s21
    # S^-1
    i11 = s22 / det
    i12 = -s12 / det
    i21 = -s21 / det
    i22 = s11 / det
    # K = P H' S^-1
    k11 = b11 * i11 + b12 * i21
    k12 = b11 * i12 + b12 * i22
    k21 = b21 * i11 + b22 * i21
    k22 = b21 * i12 + b22 * i22
    # x = x + K (y - h(x))
    x1n = x1 + k11 * inn1 + k12 * inn2
    x2n = x2 + k21 * inn1 + k22 * inn2
    # A = I - K H
    a11 = 1.0 - (k11 * h11 + k12 * h21)
    a12 = -(k11 * h12 + k12 * h22)
    a21 = -(k21 * h11 + k22 * h21)
    a22 = 1.0 - (k21 * h12 + k22 * h22)
    # P = A P A' + K R K'
    c11 = a11 * p11 + a12 * p12
    c12 = a11 * p12 + a12 * p22
    c21 = a21 * p11 + a22 * p12
    c22 = a21 * p12 + a22 * p22
    n11 = c11 * a11 + c12 * a12 + k11 * k11 * r1 + k12 * k12 * r2
    n12 = c11 * a21 + c12 * a22 + k11 * k21 * r1 + k12 * k22 * r2
    n22 = c21 * a21 + c22 * a22 + k21 * k21 * r1 + k22 * k22 * r2
    return x1n, x2n, n11, n12, n22


# ---------------------------------------------------------------------------------------------
# the models
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def tanh_tyre(alpha, cornering_stiffness, mu_fz):
    """Axle lateral force of eq. 7 and its slope: Fy = mu Fz tanh(C alpha / (mu Fz)).

    Returns (Fy [N], dFy/dalpha [N/rad]); the slope is C at alpha = 0 and falls to zero at
    saturation (sech^2).
    """
    t = math.tanh(cornering_stiffness / mu_fz * alpha)
    return mu_fz * t, cornering_stiffness * (1.0 - t * t)


@nb.njit(cache=True)
def single_track(vy, r, vx, steer, vehicle):
    """The nonlinear single-track model (eq. 1, 2, 7) and its Jacobians.

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
    mu_weight_per_length = vehicle[Veh.MU_NOMINAL] * vehicle[Veh.MASS] * G / (lf + lr)
    mu_fz_front = mu_weight_per_length * lr
    mu_fz_rear = mu_weight_per_length * lf
    # slip angles (Sec. 3.2) and their partial derivatives; vx > 0, so atan(n / vx) = atan2
    inv_vx = 1.0 / vx
    num_f = vy + lf * r
    num_r = vy - lr * r
    tan_f = num_f * inv_vx
    tan_r = num_r * inv_vx
    alpha_f = steer - math.atan(tan_f)
    alpha_r = -math.atan(tan_r)
    # d atan(n / vx) / dn = (1 / vx) / (1 + (n / vx)^2)
    datan_f = inv_vx / (1.0 + tan_f * tan_f)
    datan_r = inv_vx / (1.0 + tan_r * tan_r)
    dalpha_f_dvy = -datan_f
    dalpha_f_dr = -lf * datan_f
    dalpha_r_dvy = -datan_r
    dalpha_r_dr = lr * datan_r
    force_f, slope_f = tanh_tyre(alpha_f, vehicle[Veh.CORNERING_STIFFNESS_F], mu_fz_front)
    force_r, slope_r = tanh_tyre(alpha_r, vehicle[Veh.CORNERING_STIFFNESS_R], mu_fz_rear)
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


@nb.njit(cache=True)
def dynamic_predict(state, vx, steer, vehicle, q_vy, q_r, dt):
    """A priori step of the dynamic EKF (eq. 8): x^- = x + f(x, u) dt, P^- = F P F' + Q_dyn."""
    vy = state[S.DYN_VY]
    r = state[S.DYN_R]
    vy_dot, r_dot, _, j11, j12, j21, j22 = single_track(vy, r, vx, steer, vehicle)
    state[S.DYN_VY] = vy + vy_dot * dt
    state[S.DYN_R] = r + r_dot * dt
    # F = I + J dt (the Jacobian of the Euler map eq. 8)
    p11, p12, p22 = predict_covariance(
        state[S.DYN_P_VV], state[S.DYN_P_VR], state[S.DYN_P_RR],
        1.0 + j11 * dt, j12 * dt, j21 * dt, 1.0 + j22 * dt,
        q_vy, q_r,
    )  # fmt: skip
    state[S.DYN_P_VV] = p11
    state[S.DYN_P_VR] = p12
    state[S.DYN_P_RR] = p22


@nb.njit(cache=True)
def dynamic_update(state, yaw_rate, yaw_rate_ok, ay, ay_ok, vx, steer, vehicle, r_r, r_ay):
    """A posteriori step of the dynamic EKF with y = [r_meas, ay_meas] (eq. 9).

    A measurement flagged not ok is left out (its H row and innovation zeroed).
    """
    vy = state[S.DYN_VY]
    r = state[S.DYN_R]
    _, _, ay_model, j11, j12, _, _ = single_track(vy, r, vx, steer, vehicle)
    # H = d h / d x: row 1 picks r, row 2 is d ay_model / d(vy, r) = [J11, J12 + vx]
    h11, h12, inn1, r1 = 0.0, 0.0, 0.0, 1.0
    if yaw_rate_ok:
        h12 = 1.0
        inn1 = yaw_rate - r
        r1 = r_r
    h21, h22, inn2, r2 = 0.0, 0.0, 0.0, 1.0
    if ay_ok:
        h21 = j11
        h22 = j12 + vx
        inn2 = ay - ay_model
        r2 = r_ay
    vy, r, p11, p12, p22 = update_two(
        vy, r, state[S.DYN_P_VV], state[S.DYN_P_VR], state[S.DYN_P_RR],
        h11, h12, h21, h22, inn1, inn2, r1, r2,
    )  # fmt: skip
    state[S.DYN_VY] = vy
    state[S.DYN_R] = r
    state[S.DYN_P_VV] = p11
    state[S.DYN_P_VR] = p12
    state[S.DYN_P_RR] = p22


@nb.njit(cache=True)
def kinematic_predict(state, ax, ay, yaw_rate, q_vx, q_vy, dt):
    """A priori step of the kinematic KF (eq. 13): x^- = (I + F dt) x + G dt u."""
    vx = state[S.KIN_VX]
    vy = state[S.KIN_VY]
    state[S.KIN_VX] = vx + (vy * yaw_rate + ax) * dt  # eq. 10
    state[S.KIN_VY] = vy + (-vx * yaw_rate + ay) * dt  # eq. 11
    p11, p12, p22 = predict_covariance(
        state[S.KIN_P_XX], state[S.KIN_P_XY], state[S.KIN_P_YY],
        1.0, yaw_rate * dt, -yaw_rate * dt, 1.0,
        q_vx, q_vy,
    )  # fmt: skip
    state[S.KIN_P_XX] = p11
    state[S.KIN_P_XY] = p12
    state[S.KIN_P_YY] = p22


@nb.njit(cache=True)
def kinematic_update(state, vx_meas, vx_ok, r_vx, vy_pseudo, vy_ok, r_vy):
    """A posteriori step of the kinematic KF, H = I (eq. 19) or H = [1 0] (eq. 14, vy_ok False)."""
    vx = state[S.KIN_VX]
    vy = state[S.KIN_VY]
    h11, inn1, r1 = 0.0, 0.0, 1.0
    if vx_ok:
        h11 = 1.0
        inn1 = vx_meas - vx
        r1 = r_vx
    h22, inn2, r2 = 0.0, 0.0, 1.0
    if vy_ok:
        h22 = 1.0
        inn2 = vy_pseudo - vy
        r2 = r_vy
    vx, vy, p11, p12, p22 = update_two(
        vx, vy, state[S.KIN_P_XX], state[S.KIN_P_XY], state[S.KIN_P_YY],
        h11, 0.0, 0.0, h22, inn1, inn2, r1, r2,
    )  # fmt: skip
    state[S.KIN_VX] = vx
    state[S.KIN_VY] = vy
    state[S.KIN_P_XX] = p11
    state[S.KIN_P_XY] = p12
    state[S.KIN_P_YY] = p22


# ---------------------------------------------------------------------------------------------
# shared step scaffolding
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def reset_state(state, vx, yaw_rate, steer, p0_vy, p0_r, p0_vx):
    """Start (or restart) both filters: vy = 0 (straight-running assumption), r = measured."""
    # a reset must not inherit a non-finite input fallback from the state it replaces
    vx = vx if math.isfinite(vx) else 0.0
    yaw_rate = yaw_rate if math.isfinite(yaw_rate) else 0.0
    steer = steer if math.isfinite(steer) else 0.0
    state[S.DYN_VY] = 0.0
    state[S.DYN_R] = yaw_rate
    state[S.DYN_P_VV] = p0_vy
    state[S.DYN_P_VR] = 0.0
    state[S.DYN_P_RR] = p0_r
    state[S.KIN_VX] = vx
    state[S.KIN_VY] = 0.0
    state[S.KIN_P_XX] = p0_vx
    state[S.KIN_P_XY] = 0.0
    state[S.KIN_P_YY] = p0_vy
    state[S.PREV_AX] = 0.0
    state[S.PREV_AY] = 0.0
    state[S.PREV_YAW_RATE] = yaw_rate
    state[S.PREV_STEER] = steer
    state[S.PREV_VX] = vx
    state[S.LAST_AX] = 0.0
    state[S.LAST_STEER] = steer
    state[S.TICKS] = 0.0


@nb.njit(cache=True)
def state_is_finite(state):
    """True when both filters and the held inputs are finite. The pre-processing slots after
    them (derivative and roll filters) restart themselves from a non-finite value."""
    for i in range(S.LAST_STEER + 1):
        if not math.isfinite(state[i]):
            return False
    return True


@nb.njit(cache=True)
def beta_sigma(vx, vy, p_xx, p_xy, p_yy):
    """1-sigma of beta = atan2(vy, vx) by first-order propagation of the [vx, vy] covariance.

    grad beta = [-vy, vx] / (vx^2 + vy^2); sigma^2 = g P g'.
    """
    speed2 = vx * vx + vy * vy
    if speed2 <= 0.0:
        return math.nan
    g1 = -vy / speed2
    g2 = vx / speed2
    var = g1 * g1 * p_xx + 2.0 * g1 * g2 * p_xy + g2 * g2 * p_yy
    return math.sqrt(var) if var > 0.0 else 0.0


@nb.njit(cache=True)
def write_outputs(out, vx, vy, ax, ay, yaw_rate, sigma, roll, status):
    """Fill ``out``: beta = atan2(vy, vx) (eq. 4), beta rate from the kinematic model.

    beta_dot = (vx vy' - vy vx') / V^2 with eq. 10-11 gives (vx ay - vy ax) / V^2 - r: the rate
    of the velocity direction follows from the (CoG) accelerations without differentiating a
    noisy estimate.
    """
    speed2 = vx * vx + vy * vy
    beta = math.atan2(vy, vx)
    beta_rate = (vx * ay - vy * ax) / speed2 - yaw_rate if speed2 > 1.0 else 0.0
    out[Out.BETA] = beta
    out[Out.BETA_RATE] = beta_rate
    out[Out.VX] = vx
    out[Out.VY] = vy
    out[Out.MU] = math.nan  # the family does not estimate friction (mu is a fixed parameter)
    out[Out.SIGMA_BETA] = sigma
    out[Out.ROLL] = roll if math.isfinite(roll) else 0.0  # the gravity compensation's roll
    out[Out.FRICTION_CLASS] = 0.0
    out[Out.STATUS] = float(status)


@nb.njit(cache=True)
def write_held_outputs(out, vx, p0_vy, min_speed, status):
    """Outputs while the filter cannot run (start-up, standstill, no speed): beta 0, flagged.

    sigma_beta is that of the initial vy variance at the speed floor (or above it), a finite
    "unknown" rather than NaN so that every consumer can encode it.
    """
    out[Out.BETA] = 0.0
    out[Out.BETA_RATE] = 0.0
    out[Out.VX] = vx
    out[Out.VY] = 0.0
    out[Out.MU] = math.nan
    out[Out.SIGMA_BETA] = math.atan(math.sqrt(p0_vy) / max(vx, min_speed, 0.1))
    out[Out.ROLL] = 0.0
    out[Out.FRICTION_CLASS] = 0.0
    out[Out.STATUS] = float(status | ST_NOT_CONVERGED)


@nb.njit(cache=True)
def read_inputs(state, u, vehicle, cutoff_hz, roll_time_constant, lever_arm_3d, dt):
    """The pre-processed inputs of one tick, with fallbacks for invalid channels.

    Returns (ax, ay, yaw_rate, steer, ax_ok, ay_ok, yaw_rate_ok, steer_ok, status) with ax, ay
    translated to the CoG (Sec. 3.1). An invalid yaw rate is replaced by the previous tick's
    (a caller with a model may prefer its estimate), an invalid steer or ax by the last valid
    value, an invalid ay by 0 (callers substitute their model's ay); the flags say which
    channels were real and ``status`` carries INPUT_TIMEOUT when any of them was not.
    """
    status = 0
    yaw_rate, yaw_rate_ok = channel(u, In.YAW_RATE)
    if not yaw_rate_ok:
        yaw_rate = state[S.PREV_YAW_RATE]
        status |= ST_INPUT_TIMEOUT
    steer, steer_ok = channel(u, In.STEER)
    if steer_ok:
        state[S.LAST_STEER] = steer
    else:
        steer = state[S.LAST_STEER]
        status |= ST_INPUT_TIMEOUT
    # r_dot for the CoG translation (eq. 22-23): derivative filter of the yaw rate
    yaw_acc = derivative_filter(state, S.YAW_RATE_FILTERED, yaw_rate, dt, cutoff_hz)
    ax_imu, ax_ok = channel(u, In.AX)
    ay_imu, ay_ok = channel(u, In.AY)
    ax_in = ax_imu if ax_ok else 0.0
    ay_in = ay_imu if ay_ok else 0.0
    if lever_arm_3d:
        # not in the paper: the rigid-body translation with roll and pitch motion too (an IMU
        # above or below the CoG sees roll acceleration times its height in ay)
        roll_rate, roll_rate_ok = channel(u, In.ROLL_RATE)
        pitch_rate, pitch_rate_ok = channel(u, In.PITCH_RATE)
        if not (roll_rate_ok and pitch_rate_ok):
            status |= ST_DEGRADED  # optional inputs: the translation falls back toward planar
        roll_rate = roll_rate if roll_rate_ok else 0.0
        pitch_rate = pitch_rate if pitch_rate_ok else 0.0
        roll_acc = derivative_filter(state, S.ROLL_RATE_FILTERED, roll_rate, dt, cutoff_hz)
        pitch_acc = derivative_filter(state, S.PITCH_RATE_FILTERED, pitch_rate, dt, cutoff_hz)
        ax, ay, _ = translate_to_cog(
            ax_in, ay_in, 0.0, roll_rate, pitch_rate, yaw_rate, roll_acc, pitch_acc, yaw_acc,
            vehicle[Veh.IMU_X], vehicle[Veh.IMU_Y], vehicle[Veh.IMU_Z],
        )  # fmt: skip
    else:
        # Sec. 3.1, eq. 21-23 (planar): a_G = a_P + r_dot k x PG - r^2 PG, PG = -(IMU_X, IMU_Y)
        ax, ay = translate_to_cog_planar(
            ax_in, ay_in, yaw_rate, yaw_acc, vehicle[Veh.IMU_X], vehicle[Veh.IMU_Y]
        )
    if ax_ok:
        state[S.LAST_AX] = ax
    else:
        ax = state[S.LAST_AX]
        status |= ST_INPUT_TIMEOUT
    if not ay_ok:
        ay = 0.0
        status |= ST_INPUT_TIMEOUT
    elif roll_time_constant > 0.0:
        # not in the paper (see the module docstring): gravity removed from ay with the roll
        # of the static model (Selmanaj eq. 16) fused with the roll rate (Fig. 9), eq. 17
        roll_rate, roll_rate_ok = channel(u, In.ROLL_RATE)
        if not roll_rate_ok:
            status |= ST_DEGRADED  # roll from the static model alone
        roll = roll_complementary_filter(
            state, S.ROLL, ay, roll_rate, roll_rate_ok, dt,
            roll_static_gain(vehicle[Veh.MASS], vehicle[Veh.H_ROLL_AXIS],
                             vehicle[Veh.ROLL_STIFFNESS]),
            roll_time_constant,
        )  # fmt: skip
        ay = compensate_gravity_ay(ay, roll)
    return ax, ay, yaw_rate, steer, ax_ok, ay_ok, yaw_rate_ok, steer_ok, status


@nb.njit(cache=True)
def hold(state, vx_meas, vx_ok, ax, ay, yaw_rate, steer, p0_vy, p0_r, p0_vx):
    """A tick on which the filters cannot run: before the first speed sample or below the
    minimum speed, where the slip angles of eq. 7 (atan of (vy + a r) / vx) are undefined.

    With a speed sample both filters restart at vy = 0 with their initial covariance and
    vx = vx_meas, and the tick's inputs are kept for the next prediction.
    """
    if vx_ok:
        reset_state(state, vx_meas, yaw_rate, steer, p0_vy, p0_r, p0_vx)
        state[S.INITIALISED] = 1.0
    state[S.PREV_AX] = ax
    state[S.PREV_AY] = ay


@nb.njit(cache=True)
def finish_tick(state, status, vx_meas, vx_ok, yaw_rate, steer, p0_vy, p0_r, p0_vx):
    """Reset on a non-finite or implausible state; returns (status with RESET, reset?).

    Non-finite: openpilot paramsd's rule. Implausible: the velocity estimate points more than
    45 deg off the x axis (|vy| > vx), beyond any single-track tyre model's domain; it comes
    from inputs the models cannot explain (a spin, a corrupt sensor) and a filter that has
    left the domain does not come back by itself.
    """
    if state_is_finite(state) and abs(state[S.KIN_VY]) <= state[S.KIN_VX]:
        state[S.TICKS] += 1.0
        return status, False
    reset_state(state, vx_meas if vx_ok else 0.0, yaw_rate, steer, p0_vy, p0_r, p0_vx)
    if not vx_ok:
        state[S.INITIALISED] = 0.0
    return status | ST_RESET, True


def new_state() -> np.ndarray:
    """A state vector before the first tick: filters not started (INITIALISED = 0)."""
    state = np.zeros(N_STATE, dtype=np.float64)
    state[S.YAW_RATE_FILTERED] = np.nan  # preprocess.derivative_filter: NaN = not started
    state[S.ROLL] = np.nan  # preprocess.roll_complementary_filter: NaN = not started
    state[S.ROLL_RATE_FILTERED] = np.nan
    state[S.PITCH_RATE_FILTERED] = np.nan
    return state


def validate_vehicle(vehicle: np.ndarray) -> None:
    """Refuse a vehicle vector the single-track model cannot use (names the element)."""
    from slipd.errors import ConfigError

    if vehicle.shape != (len(Veh),):
        raise ConfigError(f"vehicle vector has shape {vehicle.shape}, expected ({len(Veh)},)")
    for field in (
        Veh.MASS, Veh.YAW_INERTIA, Veh.LF, Veh.LR, Veh.TRACK_F, Veh.TRACK_R,
        Veh.CORNERING_STIFFNESS_F, Veh.CORNERING_STIFFNESS_R, Veh.MU_NOMINAL,
    ):  # fmt: skip
        value = float(vehicle[field])
        if not (np.isfinite(value) and value > 0.0):
            raise ConfigError(f"vehicle {field.name.lower()} = {value}: must be finite and > 0")


def default_vehicle() -> np.ndarray:
    """A vehicle vector of the simulator's BMW 320i (CommonRoad vehicle 2), SI.

    Used only where no profile is at hand (tests, examples); the daemon loads the profile.
    Cornering stiffnesses and mu are those the lead quoted for the simulator's tyre set.
    """
    vehicle = np.zeros(len(Veh), dtype=np.float64)
    vehicle[Veh.MASS] = 1093.3
    vehicle[Veh.YAW_INERTIA] = 1791.6
    vehicle[Veh.LF] = 1.156
    vehicle[Veh.LR] = 1.423
    vehicle[Veh.TRACK_F] = 1.387
    vehicle[Veh.TRACK_R] = 1.364
    vehicle[Veh.H_COG] = 0.575
    vehicle[Veh.WHEEL_RADIUS] = 0.344
    vehicle[Veh.CORNERING_STIFFNESS_F] = 1.30e5
    vehicle[Veh.CORNERING_STIFFNESS_R] = 1.05e5
    vehicle[Veh.MU_NOMINAL] = 1.05
    return vehicle
