"""Shared kernels of the Carnier, Corno, Savaresi 2023 hybrid sideslip/friction observer
(``hybrid_friction``, ``hybrid_friction_nocls``).

S. Carnier, M. Corno, S. M. Savaresi, "Hybrid Kinematic-Dynamic Sideslip and Friction
Estimation" (shared/papers/carnier-corno-savaresi2023-hybrid-sideslip-friction.md).

Blocks, each under the equation it computes:

- ``vx_from_wheels_lt``: V_x tilde of Sec. 2.1: load-transfer weighted mean (eq. 3), IQR outlier
  rejection over the five signals (Fig. 6) and the min/max logic (eq. 4);
- ``kx_gain``: the scheduled longitudinal gain (eq. 5-6);
- ``tyre_force`` / ``axle_forces`` / ``lateral_model``: the friction-dependent tanh tyre model
  (eq. 8-10) on the slip angles of eq. 9 and the lateral balance of eq. 7;
- ``observer_step``: one forward-Euler step of the adaptive observer (eq. 2) with the scheduled
  K_y (eq. 11-13) and the switched friction law (eq. 14-15);
- ``classifier_step``: the slip-based friction classifier (Sec. 3): lambda-mu_x maps on
  Burckhardt curves per wheel (eq. 17-18, 20-21) and alpha-mu_y maps on the observer's own tyre
  model per axle (eq. 9, 19, 20, 22); a detected change re-initialises mu_hat.

Sign convention. The paper's kinematic model (eq. 1: Vx' = -w Vy + Ax, Vy' = w Vx + Ay) is
written in axes where the yaw rate and the lateral axis have opposite handedness; with ISO 8855
(x forward, y left, yaw rate r positive turning left) it reads vx' = ax + r vy, vy' = ay - r vx,
i.e. the paper's omega_z is -r with V_y, A_y, beta, delta left-positive. Its eq. 9 prints the
same sign for the yaw term of both axles, which cannot hold for both (the front and rear axles
sit on opposite sides of the CoG); the rear line agrees with the kinematic slip angle in the
convention above, so both are implemented as the standard kinematic slip angles in ISO 8855:
alpha_F = delta - atan((vy + lf r) / vx), alpha_R = -atan((vy - lr r) / vx)
(= delta - beta - lf r / V, -beta + lr r / V for small angles, V = vx / cos(beta)).
Lateral forces, mu_y and slip angles are then positive to the left; beta = atan2(vy, vx).

Everything here is a numba kernel on scalars and the caller's float64 state vector; nothing is
allocated per tick (the IQR sort uses five scratch slots of the state vector).
"""

from __future__ import annotations

import enum
import math

import numba as nb
import numpy as np

from slipd.channels import (
    ST_DEGRADED,
    ST_INPUT_TIMEOUT,
    G,
    In,
    Veh,
)
from slipd.estimators.preprocess import (
    channel,
    compensate_gravity_ay,
    compensate_wheel_speeds,
    derivative_filter,
    imu_at_cog,
    roll_complementary_filter,
    roll_static_gain,
)


@enum.unique
class S(enum.IntEnum):
    """Elements of the state vector (float64)."""

    VX = 0  # m/s, V_x hat (eq. 2)
    VY = 1  # m/s, V_y hat (eq. 2), ISO 8855 (+ left)
    MU = 2  # -, mu hat (eq. 2, 14)
    MU_DEFAULT = 3  # -, mu bar of eq. 14: the attraction value, set by the classifier
    CLASS_HIGH = 4  # 1.0 high grip, 0.0 low grip: the classifier's boolean mu bar (Sec. 3)
    HIGH_TICKS = 5  # consecutive ticks with a point in the high-grip region
    LOW_TICKS = 6  # consecutive ticks with a point in the low-grip region
    INITIALISED = 7  # 0 until the first tick with a wheel-speed measurement
    TICKS = 8  # ticks since init or reset
    LAST_AX = 9  # m/s^2, last valid CoG ax (fallback)
    LAST_STEER = 10  # rad, last valid steer (fallback)
    PREV_YAW_RATE = 11  # rad/s, last valid yaw rate (fallback)
    INNOVATION_VAR = 12  # (m/s^2)^2, low-passed (ay - ay_hat)^2 (quality figure)
    DETECTIONS = 13  # number of friction changes the classifier has signalled (diagnostic)
    # pre-processing memories (NaN = not started, see preprocess.reset_slots)
    YAW_RATE_FILTERED = 14
    ROLL_RATE_FILTERED = 15
    PITCH_RATE_FILTERED = 16
    ROLL = 17
    WHEEL_FL_FILTERED = 18  # derivative filters of the raw wheel speeds (eq. 5, 21)
    WHEEL_FR_FILTERED = 19
    WHEEL_RL_FILTERED = 20
    WHEEL_RR_FILTERED = 21
    # scratch area of the IQR sort (eq. 4 step 1): five values, no allocation
    SORT0 = 22
    SORT1 = 23
    SORT2 = 24
    SORT3 = 25
    SORT4 = 26
    # eq. 10 coefficients resolved at init (params or the vehicle's reference curves), kept
    # across resets: a_CF, b_CF, a_kF, b_kF, a_CR, b_CR, a_kR, b_kR
    TYRE_A_CF = 27
    TYRE_B_CF = 28
    TYRE_A_KF = 29
    TYRE_B_KF = 30
    TYRE_A_CR = 31
    TYRE_B_CR = 32
    TYRE_A_KR = 33
    TYRE_B_KR = 34
    BETA_RATE_LOWPASS = 35  # rad/s, low-pass of eq. 13's beta_dot (NaN = not started)
    AY_UTILISATION = 36  # m/s^2, low-passed |A_y| for the friction floor (NaN = not started)


N_STATE = len(S)
#: state slots that must stay finite (the filters after them restart themselves from NaN)
_LAST_CHECKED = int(S.DETECTIONS)
_SORT0 = int(S.SORT0)
_WHEEL0 = int(S.WHEEL_FL_FILTERED)
_TYRE = int(S.TYRE_A_CF)
#: |vy| (m/s) below which the secant slope of eq. 11 is replaced by the tangent (0/0)
SECANT_MIN_VY = 0.02

#: Burckhardt (1993) tyre-road characteristics, mu(lambda) = c1 (1 - exp(-c2 lambda)) - c3 lambda,
#: as tabulated e.g. by Kiencke & Nielsen, "Automotive Control Systems" (Table 7.1).
BURCKHARDT_DRY_ASPHALT = (1.2801, 23.99, 0.52)
BURCKHARDT_WET_ASPHALT = (0.857, 33.822, 0.347)
BURCKHARDT_SNOW = (0.1946, 94.129, 0.0646)


# ---------------------------------------------------------------------------------------------
# inputs
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def read_inputs(state, u, vehicle, cutoff_hz, roll_time_constant, dt):
    """Pre-processed IMU and steer of one tick (the paper's "standard filtering techniques").

    Accelerations moved to the CoG (rigid body, ``preprocess.translate_to_cog``; the paper's
    A_x, A_y are "barycentric"), gravity of the body roll removed from ay (Selmanaj 2017
    eq. 16-17, ``roll_time_constant`` > 0; 0 leaves ay as translated). Fallbacks: yaw rate and
    steer and ax hold their last valid value; an invalid ay is returned with ay_ok False (the
    caller skips the lateral correction). Returns (ax, ay, yaw_rate, yaw_acc, steer, ay_ok,
    status); yaw_acc is the derivative-filtered yaw rate (rad/s^2).
    """
    status = 0
    yaw_rate, yaw_rate_ok = channel(u, In.YAW_RATE)
    if yaw_rate_ok:
        state[S.PREV_YAW_RATE] = yaw_rate
    else:
        yaw_rate = state[S.PREV_YAW_RATE]
        status |= ST_INPUT_TIMEOUT
    steer, steer_ok = channel(u, In.STEER)
    if steer_ok:
        state[S.LAST_STEER] = steer
    else:
        steer = state[S.LAST_STEER]
        status |= ST_INPUT_TIMEOUT
    roll_rate, roll_rate_ok = channel(u, In.ROLL_RATE)
    pitch_rate, pitch_rate_ok = channel(u, In.PITCH_RATE)
    if not (roll_rate_ok and pitch_rate_ok):
        status |= ST_DEGRADED  # optional: the CoG shift falls back toward planar
    roll_rate = roll_rate if roll_rate_ok else 0.0
    pitch_rate = pitch_rate if pitch_rate_ok else 0.0
    ax, ay, yaw_acc, ax_ok, ay_ok = imu_at_cog(
        state, S.YAW_RATE_FILTERED, S.ROLL_RATE_FILTERED, S.PITCH_RATE_FILTERED, u, yaw_rate,
        roll_rate, pitch_rate, dt, cutoff_hz, vehicle,
    )  # fmt: skip
    if ax_ok:
        state[S.LAST_AX] = ax
    else:
        ax = state[S.LAST_AX]
        status |= ST_INPUT_TIMEOUT
    if not ay_ok:
        status |= ST_INPUT_TIMEOUT
    elif roll_time_constant > 0.0:
        roll = roll_complementary_filter(
            state, S.ROLL, ay, roll_rate, roll_rate_ok, dt,
            roll_static_gain(vehicle[Veh.MASS], vehicle[Veh.H_ROLL_AXIS],
                             vehicle[Veh.ROLL_STIFFNESS]),
            roll_time_constant,
        )  # fmt: skip
        ay = compensate_gravity_ay(ay, roll)
    return ax, ay, yaw_rate, yaw_acc, steer, ay_ok, status


# ---------------------------------------------------------------------------------------------
# Sec. 2.1: V_x tilde from the wheels (eq. 3-4, Fig. 4-6) and K_x (eq. 5-6)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def angle_between(a, b):
    """|a - b| wrapped to [0, pi]."""
    d = abs(a - b) % (2.0 * math.pi)
    return 2.0 * math.pi - d if d > math.pi else d


@nb.njit(cache=True)
def load_transfer_weight(wheel_x, wheel_y, transfer_angle, gamma_minus, gamma_plus):
    """k_wi of eq. 3: 1 when the wheel lies within [-gamma_minus, +gamma_plus] of the load
    transfer direction (angles of the wheel position seen from the CoG), else 0 (Fig. 5)."""
    d = math.atan2(wheel_y, wheel_x) - transfer_angle
    d = (d + math.pi) % (2.0 * math.pi) - math.pi  # wrap to [-pi, pi)
    return 1.0 if -gamma_minus <= d <= gamma_plus else 0.0


@nb.njit(cache=True)
def _insert_sorted(buf, n, value):
    """Insert ``value`` into the sorted ``buf[_SORT0:_SORT0 + n]``; returns n + 1."""
    i = n
    while i > 0 and buf[_SORT0 + i - 1] > value:
        buf[_SORT0 + i] = buf[_SORT0 + i - 1]
        i -= 1
    buf[_SORT0 + i] = value
    return n + 1


@nb.njit(cache=True)
def _quantile_sorted(buf, n, q):
    """Quantile q of the sorted ``buf[_SORT0:_SORT0 + n]``, linear interpolation (numpy's
    default "linear" method: position q (n - 1))."""
    pos = q * (n - 1)
    lo = int(math.floor(pos))
    hi = min(lo + 1, n - 1)
    frac = pos - lo
    return buf[_SORT0 + lo] + frac * (buf[_SORT0 + hi] - buf[_SORT0 + lo])


@nb.njit(cache=True)
def vx_from_wheels_lt(
    state, c_fl, c_fr, c_rl, c_rr, ok_fl, ok_fr, ok_rl, ok_rr, ax, ay, vehicle,
    gamma_minus, gamma_plus, min_transfer_accel, iqr_scale,
):  # fmt: skip
    """V_x tilde of Sec. 2.1 from the four wheel speeds referred to the CoG (c_*).

    1. eq. 3: V_WM = sum k_wi V_wi / sum k_wi with k_wi = 1 for the wheels within
       [gamma-, gamma+] of the load-transfer direction. The load moves against the
       acceleration (braking: to the front), so the direction is atan2(-ay, -ax). Below
       ``min_transfer_accel`` the direction is noise and, when no wheel falls in the cone (a
       pure lateral acceleration: the wheels sit ~30 deg off the x axis, the cone is +-35 deg
       about the y axis), every valid wheel gets k = 1 (slipd's fallbacks; the paper shows
       only braking, Fig. 5).
    2. Fig. 6: the five values (valid wheels and V_WM) sorted, Q1, Q3, IQR = Q3 - Q1; values
       outside [Q1 - 1.5 IQR, Q3 + 1.5 IQR] are discarded.
    3. eq. 4: the minimum of the remaining values when A_x >= 0, the maximum when A_x < 0.
    Returns (vx_tilde, n_valid); vx_tilde is NaN without a valid wheel.
    """
    n_valid = int(ok_fl) + int(ok_fr) + int(ok_rl) + int(ok_rr)
    if n_valid == 0:
        return math.nan, 0
    lf = vehicle[Veh.LF]
    lr = vehicle[Veh.LR]
    half_f = 0.5 * vehicle[Veh.TRACK_F]
    half_r = 0.5 * vehicle[Veh.TRACK_R]
    k_fl = k_fr = k_rl = k_rr = 1.0
    if ax * ax + ay * ay >= min_transfer_accel * min_transfer_accel:
        direction = math.atan2(-ay, -ax)
        k_fl = load_transfer_weight(lf, half_f, direction, gamma_minus, gamma_plus)
        k_fr = load_transfer_weight(lf, -half_f, direction, gamma_minus, gamma_plus)
        k_rl = load_transfer_weight(-lr, half_r, direction, gamma_minus, gamma_plus)
        k_rr = load_transfer_weight(-lr, -half_r, direction, gamma_minus, gamma_plus)
    k_fl = k_fl if ok_fl else 0.0
    k_fr = k_fr if ok_fr else 0.0
    k_rl = k_rl if ok_rl else 0.0
    k_rr = k_rr if ok_rr else 0.0
    weight_sum = k_fl + k_fr + k_rl + k_rr
    if weight_sum == 0.0:
        k_fl = 1.0 if ok_fl else 0.0
        k_fr = 1.0 if ok_fr else 0.0
        k_rl = 1.0 if ok_rl else 0.0
        k_rr = 1.0 if ok_rr else 0.0
        weight_sum = float(n_valid)
    weighted = 0.0
    if ok_fl:
        weighted += k_fl * c_fl
    if ok_fr:
        weighted += k_fr * c_fr
    if ok_rl:
        weighted += k_rl * c_rl
    if ok_rr:
        weighted += k_rr * c_rr
    v_wm = weighted / weight_sum  # eq. 3
    # Fig. 6: sort the (up to) five signals in the scratch slots
    n = 0
    if ok_fl:
        n = _insert_sorted(state, n, c_fl)
    if ok_fr:
        n = _insert_sorted(state, n, c_fr)
    if ok_rl:
        n = _insert_sorted(state, n, c_rl)
    if ok_rr:
        n = _insert_sorted(state, n, c_rr)
    n = _insert_sorted(state, n, v_wm)
    q1 = _quantile_sorted(state, n, 0.25)
    q3 = _quantile_sorted(state, n, 0.75)
    iqr = q3 - q1
    low_fence = q1 - iqr_scale * iqr
    high_fence = q3 + iqr_scale * iqr
    lowest = math.inf
    highest = -math.inf
    for i in range(n):
        v = state[_SORT0 + i]
        if low_fence <= v <= high_fence:
            lowest = min(lowest, v)
            highest = max(highest, v)
    # eq. 4: accelerating, the wheels spin faster than the car -> the slowest; braking -> the
    # fastest. V_WM lies between its wheels and always survives the fences.
    return (lowest if ax >= 0.0 else highest), n_valid


@nb.njit(cache=True)
def wheel_accelerations(state, u, dt, cutoff_hz):
    """d V_wi / dt of the raw wheel speeds by 10 Hz derivative filters (Selmanaj Sec. 2.1, the
    same filters as ``preprocess``); an invalid wheel's filter is held and its rate is 0.
    Returns (a_fl, a_fr, a_rl, a_rr, ok_fl, ok_fr, ok_rl, ok_rr)."""
    v_fl, ok_fl = channel(u, In.WHEEL_SPEED_FL)
    v_fr, ok_fr = channel(u, In.WHEEL_SPEED_FR)
    v_rl, ok_rl = channel(u, In.WHEEL_SPEED_RL)
    v_rr, ok_rr = channel(u, In.WHEEL_SPEED_RR)
    a_fl = derivative_filter(state, _WHEEL0 + 0, v_fl, dt, cutoff_hz) if ok_fl else 0.0
    a_fr = derivative_filter(state, _WHEEL0 + 1, v_fr, dt, cutoff_hz) if ok_fr else 0.0
    a_rl = derivative_filter(state, _WHEEL0 + 2, v_rl, dt, cutoff_hz) if ok_rl else 0.0
    a_rr = derivative_filter(state, _WHEEL0 + 3, v_rr, dt, cutoff_hz) if ok_rr else 0.0
    return a_fl, a_fr, a_rl, a_rr, ok_fl, ok_fr, ok_rl, ok_rr


@nb.njit(cache=True)
def kx_gain(
    a_fl, a_fr, a_rl, a_rr, ok_fl, ok_fr, ok_rl, ok_rr, ax, threshold, kx_min, kx_max
):  # fmt: skip
    """eq. 5-6: Delta_Ax = sum_i |dV_i/dt - A_x| over the valid wheels (scaled to four when
    some are missing); K_x = K_x,min when Delta_Ax >= threshold, else K_x,max.
    Returns (K_x, Delta_Ax)."""
    total = 0.0
    n = 0
    if ok_fl:
        total += abs(a_fl - ax)
        n += 1
    if ok_fr:
        total += abs(a_fr - ax)
        n += 1
    if ok_rl:
        total += abs(a_rl - ax)
        n += 1
    if ok_rr:
        total += abs(a_rr - ax)
        n += 1
    if n == 0:
        return 0.0, math.inf
    delta_ax = total * 4.0 / n
    return (kx_min if delta_ax >= threshold else kx_max), delta_ax


# ---------------------------------------------------------------------------------------------
# Sec. 2.2: the friction-dependent tyre model (eq. 7-10)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def tyre_coefficients(mu, a_c, b_c, a_k, b_k, k_floor):
    """eq. 10: C_r(mu) = a_C mu + b_C, k(mu) = a_k mu + b_k (interpolation between the two
    reference characteristics, extrapolation outside). ``k_floor`` keeps k positive when mu is
    extrapolated far beyond the high reference (k -> 0 would blow C_r / k up)."""
    c_r = a_c * mu + b_c
    k = a_k * mu + b_k
    if k < k_floor:
        k = k_floor
    if c_r < 0.0:
        c_r = 0.0
    return c_r, k


@nb.njit(cache=True)
def tyre_force(alpha, c_r, k):
    """eq. 8: F_y = C_r / k tanh(k alpha) and its slope dF_y/dalpha = C_r (1 - tanh^2)."""
    t = math.tanh(k * alpha)
    return c_r / k * t, c_r * (1.0 - t * t)


@nb.njit(cache=True)
def slip_angles(vx, vy, yaw_rate, steer, lf, lr):
    """eq. 9 in ISO 8855 (see the module docstring): alpha_F = delta - atan((vy + lf r) / vx),
    alpha_R = -atan((vy - lr r) / vx), and d alpha_{F,R} / d vy. ``vx`` > 0."""
    inv_vx = 1.0 / vx
    tan_f = (vy + lf * yaw_rate) * inv_vx
    tan_r = (vy - lr * yaw_rate) * inv_vx
    alpha_f = steer - math.atan(tan_f)
    alpha_r = -math.atan(tan_r)
    return alpha_f, alpha_r, -inv_vx / (1.0 + tan_f * tan_f), -inv_vx / (1.0 + tan_r * tan_r)


@nb.njit(cache=True)
def lateral_model(vx, vy, yaw_rate, steer, mu, state, vehicle, k_floor):
    """eq. 7-10: A_y hat = (F_yF cos(delta) + F_yR) / m at friction ``mu`` and its slope
    d A_y hat / d vy (the xi of eq. 11 when mu is the nominal friction).

    The eq. 10 coefficients are read from the state's TYRE_* slots.
    Returns (ay_hat, d ay_hat / d vy, alpha_F, alpha_R).
    """
    alpha_f, alpha_r, dalpha_f, dalpha_r = slip_angles(
        vx, vy, yaw_rate, steer, vehicle[Veh.LF], vehicle[Veh.LR]
    )
    t = _TYRE
    c_f, k_f = tyre_coefficients(mu, state[t], state[t + 1], state[t + 2], state[t + 3], k_floor)
    c_r, k_r = tyre_coefficients(
        mu, state[t + 4], state[t + 5], state[t + 6], state[t + 7], k_floor
    )
    force_f, slope_f = tyre_force(alpha_f, c_f, k_f)
    force_r, slope_r = tyre_force(alpha_r, c_r, k_r)
    cos_steer = math.cos(steer)
    inv_mass = 1.0 / vehicle[Veh.MASS]
    ay_hat = (force_f * cos_steer + force_r) * inv_mass
    slope = (slope_f * cos_steer * dalpha_f + slope_r * dalpha_r) * inv_mass
    return ay_hat, slope, alpha_f, alpha_r


@nb.njit(cache=True)
def axle_forces(alpha_f, alpha_r, mu, state, k_floor):
    """eq. 8, 10 for both axles at friction ``mu``: (F_yF, dF_yF/dalpha, F_yR, dF_yR/dalpha)."""
    t = _TYRE
    c_f, k_f = tyre_coefficients(mu, state[t], state[t + 1], state[t + 2], state[t + 3], k_floor)
    c_r, k_r = tyre_coefficients(
        mu, state[t + 4], state[t + 5], state[t + 6], state[t + 7], k_floor
    )
    force_f, slope_f = tyre_force(alpha_f, c_f, k_f)
    force_r, slope_r = tyre_force(alpha_r, c_r, k_r)
    return force_f, slope_f, force_r, slope_r


@nb.njit(cache=True)
def mu_for_peak(utilisation, fz, a_c, b_c, a_k, b_k):
    """The mu at which the eq. 8-10 axle peak C_r(mu) / k(mu) equals ``utilisation`` x Fz:
    a_C mu + b_C = u Fz (a_k mu + b_k), linear in mu. NaN when no such mu exists."""
    denominator = a_c - utilisation * fz * a_k
    if denominator <= 0.0:
        return math.nan
    return (utilisation * fz * b_k - b_c) / denominator


@nb.njit(cache=True)
def mu_for_utilisation(state, utilisation, vehicle):
    """Lowest mu whose model peak reaches ``utilisation`` (|A_y| / g) on both axles (static
    loads). Eq. 10's linear k(mu) puts the peak of an intermediate mu below mu itself, so the
    floor is found on the model, not as mu >= utilisation."""
    mass_g = vehicle[Veh.MASS] * G
    wheelbase = vehicle[Veh.LF] + vehicle[Veh.LR]
    t = _TYRE
    front = mu_for_peak(utilisation, mass_g * vehicle[Veh.LR] / wheelbase,
                        state[t], state[t + 1], state[t + 2], state[t + 3])  # fmt: skip
    rear = mu_for_peak(utilisation, mass_g * vehicle[Veh.LF] / wheelbase,
                       state[t + 4], state[t + 5], state[t + 6], state[t + 7])  # fmt: skip
    floor = utilisation
    if math.isfinite(front):
        floor = max(floor, front)
    if math.isfinite(rear):
        floor = max(floor, rear)
    return floor


@nb.njit(cache=True)
def linear_slope(vx, vehicle, state):
    """xi_lin: d A_y / d vy of the linear tyre range at the nominal friction (the cornering
    stiffnesses C_r(mu_nominal) of both axles), -(C_F + C_R) / (m vx) < 0."""
    mu = vehicle[Veh.MU_NOMINAL]
    c_f = state[_TYRE] * mu + state[_TYRE + 1]
    c_r = state[_TYRE + 4] * mu + state[_TYRE + 5]
    return -(c_f + c_r) / (vehicle[Veh.MASS] * vx)


def reference_tyre(vehicle: np.ndarray, mu_low: float, low_stiffness_ratio: float) -> tuple:
    """The eq. 10 coefficients from two reference characteristics of the vehicle (Sec. 2.2:
    "identifying the road-tire characteristics of two reference road surfaces with a high and
    a low friction"), each a tanh axle curve with peak mu Fz_static (the tanh model of eq. 8:
    peak C_r / k) and initial slope C_r:

    high: mu_high = MU_NOMINAL, C_r = the profile's axle cornering stiffness;
    low:  mu_low, C_r = low_stiffness_ratio x the same stiffness.

    Returns (a_CF, b_CF, a_kF, b_kF, a_CR, b_CR, a_kR, b_kR). With ratio 1 (a Pacejka tyre whose
    peak factor alone follows the road, as the simulator's) k = C / (mu Fz) at both references.
    """
    mass = float(vehicle[Veh.MASS])
    lf = float(vehicle[Veh.LF])
    lr = float(vehicle[Veh.LR])
    mu_high = float(vehicle[Veh.MU_NOMINAL])
    fz = (mass * G * lr / (lf + lr), mass * G * lf / (lf + lr))  # static axle loads
    stiffness = (
        float(vehicle[Veh.CORNERING_STIFFNESS_F]),
        float(vehicle[Veh.CORNERING_STIFFNESS_R]),
    )
    coefficients = []
    for c_high, fz_axle in zip(stiffness, fz, strict=True):
        c_low = low_stiffness_ratio * c_high
        k_high = c_high / (mu_high * fz_axle)
        k_low = c_low / (mu_low * fz_axle)
        a_c = (c_high - c_low) / (mu_high - mu_low)
        a_k = (k_high - k_low) / (mu_high - mu_low)
        coefficients += [a_c, c_high - a_c * mu_high, a_k, k_high - a_k * mu_high]
    return tuple(coefficients)


# ---------------------------------------------------------------------------------------------
# Sec. 2: one step of the adaptive observer (eq. 2, 11-15)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def observer_step(
    state, ax, ay, ay_ok, yaw_rate, steer, vx_tilde, vx_ok, kx, vehicle, dt,
    ky_min, ky_max, beta_rate_threshold, k_mu, k_mu_bar, beta_rate_mu_threshold,
    yaw_rate_threshold, mu_min, mu_max, k_floor, delta_gain, beta_rate_highpass,
    utilisation_floor, xi_floor,
):  # fmt: skip
    """Forward-Euler step of eq. 2 (ISO 8855 form, see the module docstring):

        vx' = ax + r vy + K_x (V_x tilde - vx)
        vy' = ay - r vx + K_y (A_y - A_y hat(vx, vy, mu))
        mu' = eq. 14

    eq. 11: K_y = xi Delta k_y with xi the slope of the nominal-friction model A*_y
    (mu = MU_NOMINAL) over vy, taken as the secant to vy_ref = l_r r (see below), and
    Delta = delta_gain / xi_lin^2 (``linear_slope``). [26]'s Delta is not given; this one makes
    k_y the decay rate (1/s) of the vy error in the linear tyre range: e' = -k_y (xi/xi_lin)^2 e,
    fading where the tyres saturate and A_y carries less information on vy.
    eq. 12-13: k_y = k_y,min when |beta_dot| >= beta_dot bar, else k_y,max, with the kinematic
    beta_dot = (A_y - r vx) / vx.
    eq. 14-15: with |beta_dot| >= beta_dot bar_mu and |r| >= r bar, mu' = K_mu (A_y - A_y hat),
    K_mu = k_mu A*_y Delta_mu; otherwise mu' = K_mu bar (mu bar - mu). Here Delta_mu = 1 s^3/m^2
    (k_mu A*_y (A_y - A_y hat) is a rate in 1/s): with Table 1's k_mu = 0.007 this adapts mu
    by ~0.1/s at 6 m/s^2 of innovation, the ~10 s of Fig. 13; the Delta of eq. 11 would make
    Table 1's k_mu ~200 times slower (see hybrid_friction's docstring). Both switches see the
    high-passed beta_dot (``beta_rate_highpass``). mu is kept in [mu_min, mu_max] and, with
    ``utilisation_floor`` > 0, not below the friction in use (``mu_for_utilisation``).

    ``vx_ok`` False: no wheel speed, the longitudinal correction is skipped. ``ay_ok`` False:
    the model's A_y hat is integrated instead of A_y and neither vy nor mu is corrected.
    Returns (beta_dot_kinematic, innovation, alpha_F, alpha_R, ay_used, F_yF*, F_yR*) with
    F_y* the axle forces at the nominal friction (the classifier's high-grip curve).
    """
    vx = state[S.VX]
    vy = state[S.VY]
    mu = state[S.MU]
    lf = vehicle[Veh.LF]
    lr = vehicle[Veh.LR]
    cos_steer = math.cos(steer)
    inv_mass = 1.0 / vehicle[Veh.MASS]
    # eq. 9 once; eq. 7-8 at mu hat (A_y hat) and at the nominal friction (A*_y, xi)
    alpha_f, alpha_r, dalpha_f, dalpha_r = slip_angles(vx, vy, yaw_rate, steer, lf, lr)
    force_f, _, force_r, _ = axle_forces(alpha_f, alpha_r, mu, state, k_floor)
    ay_hat = (force_f * cos_steer + force_r) * inv_mass
    mu_nominal = vehicle[Veh.MU_NOMINAL]
    nominal_f, slope_f, nominal_r, slope_r = axle_forces(
        alpha_f, alpha_r, mu_nominal, state, k_floor
    )
    ay_star = (nominal_f * cos_steer + nominal_r) * inv_mass
    # xi: [26]'s secant between the estimate and the true vy, which is unknown. The secant to
    # vy_ref = l_r r stands in for it: there the rear slip angle is zero (the low-speed,
    # kinematic-steering vy), so vy_ref lies in the linear tyre range whatever the speed and
    # curvature, where the car normally is. Near vy_ref it is the tangent; unlike the tangent it
    # does not vanish once the estimate has drifted into the saturated range, where a vanishing
    # gain would leave the drift uncorrected for good (measured: a -37 deg runaway in a 20 m
    # radius corner of the endurance drive).
    vy_ref = lr * yaw_rate
    if abs(vy - vy_ref) > SECANT_MIN_VY:
        ref_f, ref_r, _, _ = slip_angles(vx, vy_ref, yaw_rate, steer, lf, lr)
        ref_force_f, _, ref_force_r, _ = axle_forces(ref_f, ref_r, mu_nominal, state, k_floor)
        ay_star_ref = (ref_force_f * cos_steer + ref_force_r) * inv_mass
        xi = (ay_star - ay_star_ref) / (vy - vy_ref)
    else:
        xi = (slope_f * cos_steer * dalpha_f + slope_r * dalpha_r) * inv_mass  # the tangent
    xi_lin = linear_slope(vx, vehicle, state)
    # slipd: |xi| >= xi_floor |xi_lin| (both negative): a gain that never fades completely
    xi = min(xi, xi_floor * xi_lin)
    delta = delta_gain / (xi_lin * xi_lin)
    if not ay_ok:
        ay = ay_hat
    innovation = ay - ay_hat
    beta_dot = (ay - yaw_rate * vx) / vx  # eq. 13
    # slipd: the switches see beta_dot minus its low-pass (time constant ``beta_rate_highpass``,
    # 0 = the paper's raw eq. 13): a road bank or an ay offset adds a constant to eq. 13 that
    # would hold k_y at k_y,min for good, while a real sideslip rate cannot stay away from zero
    if beta_rate_highpass > 0.0:
        if not math.isfinite(state[S.BETA_RATE_LOWPASS]):
            state[S.BETA_RATE_LOWPASS] = beta_dot
        state[S.BETA_RATE_LOWPASS] += min(dt / beta_rate_highpass, 1.0) * (
            beta_dot - state[S.BETA_RATE_LOWPASS]
        )
        beta_dot -= state[S.BETA_RATE_LOWPASS]
    ky = ky_min if abs(beta_dot) >= beta_rate_threshold else ky_max  # eq. 12
    gain_y = xi * delta * ky if ay_ok else 0.0  # eq. 11
    if not vx_ok:
        kx = 0.0
        vx_tilde = vx
    vx_dot = ax + yaw_rate * vy + kx * (vx_tilde - vx)
    vy_dot = ay - yaw_rate * vx + gain_y * innovation
    if ay_ok and abs(beta_dot) >= beta_rate_mu_threshold and abs(yaw_rate) >= yaw_rate_threshold:
        mu_dot = k_mu * ay_star * innovation  # eq. 14 (excited), eq. 15 with Delta_mu = 1
    else:
        mu_dot = k_mu_bar * (state[S.MU_DEFAULT] - mu)  # eq. 14 (not excited)
    state[S.VX] = vx + vx_dot * dt
    state[S.VY] = vy + vy_dot * dt
    mu = mu + mu_dot * dt
    # slipd: the road transmits at least the friction in use, |A_y| / g (low-passed). Without
    # this floor a mu hat below it is unstable: the mu-model saturates below the measured A_y,
    # the innovation keeps one sign whatever vy, and eq. 2 drives vy to ever larger slip.
    if utilisation_floor > 0.0 and ay_ok:
        if not math.isfinite(state[S.AY_UTILISATION]):
            state[S.AY_UTILISATION] = abs(ay)
        state[S.AY_UTILISATION] += min(dt / utilisation_floor, 1.0) * (
            abs(ay) - state[S.AY_UTILISATION]
        )
        mu = max(mu, mu_for_utilisation(state, state[S.AY_UTILISATION] / G, vehicle))
    state[S.MU] = min(max(mu, mu_min), mu_max)
    return beta_dot, innovation, alpha_f, alpha_r, ay, nominal_f, nominal_r


# ---------------------------------------------------------------------------------------------
# Sec. 3: the friction classifier (eq. 17-22, Fig. 9-10)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def burckhardt(slip, c1, c2, c3):
    """Burckhardt's mu(lambda) = c1 (1 - exp(-c2 lambda)) - c3 lambda for lambda >= 0."""
    return c1 * (1.0 - math.exp(-c2 * slip)) - c3 * slip


@nb.njit(cache=True)
def map_region(slip, mu_measured, curve_high, curve_low, low_peak, slip_min, band, high_margin,
               min_gap):  # fmt: skip
    """Region of a (slip, mu) point on a classification map (Fig. 10): +1 high grip (red),
    -1 low grip (blue), 0 undefined (white).

    - high: |mu| >= low_peak + high_margin, whatever the slip - the tyre transmits more than
      the low surface can at any slip (its curve's peak ``low_peak``), which proves high grip
      even where the slip estimate is poor; or, above the slip limit, |mu| within
      ``band`` x gap of the high curve (gap = curve_high - curve_low);
    - low: above the slip limit, | |mu| - curve_low | <= band x gap - on the low curve, far
      below what high grip gives. A point well *below* the low curve fits neither surface (at
      that slip both would transmit more): it betrays a slip estimate that is too large, not
      low grip, and stays white;
    - white otherwise, and wherever |slip| < ``slip_min`` or gap < ``min_gap`` (the paper's
      green limits and white area: the curves merge at small slip, Fig. 19) or force and slip
      have opposite signs (a transient the steady maps do not describe).
    """
    if abs(mu_measured) >= low_peak + high_margin:
        return 1
    if abs(slip) < slip_min:
        return 0
    if mu_measured * slip <= 0.0:
        return 0
    gap = curve_high - curve_low
    if gap < min_gap:
        return 0
    excess = abs(mu_measured) - curve_low
    if excess >= (1.0 - band) * gap:
        return 1
    if abs(excess) <= band * gap:
        return -1
    return 0


@nb.njit(cache=True)
def burckhardt_peak(c1, c2, c3):
    """Maximum of the Burckhardt curve: d mu / d lambda = c1 c2 exp(-c2 lambda) - c3 = 0."""
    if c3 <= 0.0:
        return c1
    slip = math.log(c1 * c2 / c3) / c2
    return burckhardt(max(slip, 0.0), c1, c2, c3)


@nb.njit(cache=True)
def wheel_loads(ax, ay, vehicle):
    """eq. 20: F_zi = k1 m g + k2 m A_x + k3 m A_y with the rigid-body coefficients
    k1 = static share (l_r / 2l front, l_f / 2l rear), k2 = -+ h / 2l (accelerating moves load
    to the rear), k3 = -+ h / track x the axle's static share (ISO: A_y > 0, a left turn, loads
    the right wheels). Returns (Fz_fl, Fz_fr, Fz_rl, Fz_rr) in N, each at least 5 % of its
    static load."""
    m = vehicle[Veh.MASS]
    lf = vehicle[Veh.LF]
    lr = vehicle[Veh.LR]
    h = vehicle[Veh.H_COG]
    wheelbase = lf + lr
    share_f = lr / wheelbase
    share_r = lf / wheelbase
    static_f = 0.5 * share_f * m * G
    static_r = 0.5 * share_r * m * G
    long_f = -0.5 * h / wheelbase * m * ax
    lat_f = h / vehicle[Veh.TRACK_F] * share_f * m * ay
    lat_r = h / vehicle[Veh.TRACK_R] * share_r * m * ay
    fz_fl = max(static_f + long_f - lat_f, 0.05 * static_f)
    fz_fr = max(static_f + long_f + lat_f, 0.05 * static_f)
    fz_rl = max(static_r - long_f - lat_r, 0.05 * static_r)
    fz_rr = max(static_r - long_f + lat_r, 0.05 * static_r)
    return fz_fl, fz_fr, fz_rl, fz_rr


@nb.njit(cache=True)
def longitudinal_point(wheel_speed, wheel_accel, drive, brake, vx_wheel, fz, vehicle):
    """(lambda, mu_x) of one wheel: eq. 17 lambda = (V_w - V_x) / max(V_w, V_x) with V_x the
    estimate referred to the wheel; eq. 21 F_x = (T_en - T_br - J omega_dot) / R with
    omega_dot = (dV_w / dt) / R; eq. 18 mu_x = F_x / F_z."""
    radius = vehicle[Veh.WHEEL_RADIUS]
    denominator = max(wheel_speed, vx_wheel)
    slip = (wheel_speed - vx_wheel) / denominator if denominator > 0.5 else 0.0
    force = (drive - brake - vehicle[Veh.WHEEL_INERTIA] * wheel_accel / radius) / radius
    return slip, force / fz


@nb.njit(cache=True)
def _low_curve(alpha, fz_axle, mu_low, a_c, b_c, a_k, b_k, k_floor):
    """|mu_y| of the observer's own axle model (eq. 8, 10) at the low reference friction and
    the curve's peak C_r / k / Fz."""
    c_l, k_l = tyre_coefficients(mu_low, a_c, b_c, a_k, b_k, k_floor)
    return abs(tyre_force(alpha, c_l, k_l)[0]) / fz_axle, c_l / k_l / fz_axle


@nb.njit(cache=True)
def classify_tick(
    state, u, ax, ay, yaw_acc, steer, alpha_f, alpha_r, force_f_high, force_r_high, speeds,
    speeds_ok, wheel_acc, vx, vehicle, mu_low, k_floor, burckhardt_high, burckhardt_low,
    slip_min, alpha_min, band, high_margin, min_gap, yaw_moment_split,
):  # fmt: skip
    """Regions of every map point of one tick (Fig. 9): two axles on the alpha-mu_y map, four
    wheels on the lambda-mu_x map (only where the wheel's drive and brake torques are valid).

    ``force_*_high``: the axle forces of the observer's model at the high reference friction
    (MU_NOMINAL) at ``alpha_*``, from ``observer_step`` (the high curve of the lateral map, the
    same model (8) as the observer, Sec. 3). ``speeds``: the four wheel speeds referred to the
    CoG x axis (``compensate_wheel_speeds``), so lambda of eq. 17 compares them with vx hat
    directly; ``speeds_ok`` their validity; ``wheel_acc``: dV_w/dt of the raw speeds.
    Returns (any_high, any_low).

    Axle forces: eq. 22 is the steady-state split (yaw_acc = 0). With ``yaw_moment_split``
    (slipd, default on) the yaw balance I_z r' = l_f F_yF cos(delta) - l_r F_yR is kept too,
    F_yF cos(delta) = (l_r m A_y + I_z r') / l, F_yR = (l_f m A_y - I_z r') / l: in a steering
    transient the front force leads A_y, and the steady split would put a large front slip
    angle next to a small force, i.e. in the low-grip region, on a dry road.
    """
    fz_fl, fz_fr, fz_rl, fz_rr = wheel_loads(ax, ay, vehicle)
    any_high = False
    any_low = False
    # lateral map per axle, eq. 19 and 22 (with the yaw balance, see above)
    lf = vehicle[Veh.LF]
    lr = vehicle[Veh.LR]
    wheelbase = lf + lr
    m_ay = vehicle[Veh.MASS] * ay
    yaw_moment = vehicle[Veh.YAW_INERTIA] * yaw_acc if yaw_moment_split else 0.0
    t = _TYRE
    fz_front = fz_fl + fz_fr
    mu_y_front = (lr * m_ay + yaw_moment) / (wheelbase * math.cos(steer)) / fz_front
    low, low_peak = _low_curve(
        alpha_f, fz_front, mu_low, state[t], state[t + 1], state[t + 2], state[t + 3], k_floor
    )
    region = map_region(alpha_f, mu_y_front, abs(force_f_high) / fz_front, low, low_peak,
                        alpha_min, band, high_margin, min_gap)  # fmt: skip
    any_high |= region > 0
    any_low |= region < 0
    fz_rear = fz_rl + fz_rr
    mu_y_rear = (lf * m_ay - yaw_moment) / wheelbase / fz_rear
    low, low_peak = _low_curve(
        alpha_r,
        fz_rear,
        mu_low,
        state[t + 4],
        state[t + 5],
        state[t + 6],
        state[t + 7],
        k_floor,
    )
    region = map_region(alpha_r, mu_y_rear, abs(force_r_high) / fz_rear, low, low_peak,
                        alpha_min, band, high_margin, min_gap)  # fmt: skip
    any_high |= region > 0
    any_low |= region < 0
    # longitudinal map per wheel (eq. 17-18, 21)
    long_low_peak = burckhardt_peak(burckhardt_low[0], burckhardt_low[1], burckhardt_low[2])
    for i in range(4):
        if not speeds_ok[i]:
            continue
        drive, drive_ok = channel(u, In.DRIVE_TORQUE_FL + i)
        brake, brake_ok = channel(u, In.BRAKE_TORQUE_FL + i)
        if not (drive_ok and brake_ok):
            continue
        fz = fz_fl if i == 0 else fz_fr if i == 1 else fz_rl if i == 2 else fz_rr
        slip, mu_x = longitudinal_point(speeds[i], wheel_acc[i], drive, brake, vx, fz, vehicle)
        abs_slip = abs(slip)
        if abs_slip < slip_min and abs(mu_x) < long_low_peak + high_margin:
            continue  # white: skip the curves
        curve_high = burckhardt(abs_slip, burckhardt_high[0], burckhardt_high[1],
                                burckhardt_high[2])  # fmt: skip
        curve_low = burckhardt(abs_slip, burckhardt_low[0], burckhardt_low[1], burckhardt_low[2])
        region = map_region(slip, mu_x, curve_high, curve_low, long_low_peak, slip_min, band,
                            high_margin, min_gap)  # fmt: skip
        any_high |= region > 0
        any_low |= region < 0
    return any_high, any_low


@nb.njit(cache=True)
def classifier_update(state, any_high, any_low, persistence_ticks, mu_high, mu_low):
    """The boolean mu bar of Sec. 3: a high-grip point while mu bar = 0 switches to high, a
    low-grip point while mu bar = 1 switches to low, anything else keeps it. A switch needs the
    points in the new region on ``persistence_ticks`` consecutive ticks (slipd: a one-sample
    noise spike must not re-initialise mu). On a switch mu hat and the attraction value mu bar
    of eq. 14 are re-initialised to the class's reference friction. Returns True on a switch.
    """
    state[S.HIGH_TICKS] = state[S.HIGH_TICKS] + 1.0 if any_high and not any_low else 0.0
    state[S.LOW_TICKS] = state[S.LOW_TICKS] + 1.0 if any_low and not any_high else 0.0
    is_high = state[S.CLASS_HIGH] > 0.5
    if not is_high and state[S.HIGH_TICKS] >= persistence_ticks:
        state[S.CLASS_HIGH] = 1.0
        state[S.MU] = mu_high
        state[S.MU_DEFAULT] = mu_high
        state[S.DETECTIONS] += 1.0
        return True
    if is_high and state[S.LOW_TICKS] >= persistence_ticks:
        state[S.CLASS_HIGH] = 0.0
        state[S.MU] = mu_low
        state[S.MU_DEFAULT] = mu_low
        state[S.DETECTIONS] += 1.0
        return True
    return False


# ---------------------------------------------------------------------------------------------
# bookkeeping
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def reset_observer(state, vx, mu_default):
    """(Re)start the observer: vx = V_x tilde, vy = 0 (straight-running assumption), mu at the
    current attraction value (the classifier's class survives a reset)."""
    state[S.VX] = vx if math.isfinite(vx) else 0.0
    state[S.VY] = 0.0
    state[S.MU] = mu_default
    state[S.MU_DEFAULT] = mu_default
    state[S.HIGH_TICKS] = 0.0
    state[S.LOW_TICKS] = 0.0
    state[S.TICKS] = 0.0
    state[S.INNOVATION_VAR] = 0.0
    if not math.isfinite(state[S.LAST_AX]):
        state[S.LAST_AX] = 0.0
    if not math.isfinite(state[S.LAST_STEER]):
        state[S.LAST_STEER] = 0.0
    if not math.isfinite(state[S.PREV_YAW_RATE]):
        state[S.PREV_YAW_RATE] = 0.0


@nb.njit(cache=True)
def state_is_finite(state):
    for i in range(_LAST_CHECKED + 1):
        if not math.isfinite(state[i]):
            return False
    return True


def new_state(mu_init: float, class_high: bool) -> np.ndarray:
    """A state vector before the first tick (observer not started, filters NaN = not started)."""
    state = np.zeros(N_STATE, dtype=np.float64)
    state[S.MU] = mu_init
    state[S.MU_DEFAULT] = mu_init
    state[S.CLASS_HIGH] = 1.0 if class_high else 0.0
    for slot in (
        S.YAW_RATE_FILTERED, S.ROLL_RATE_FILTERED, S.PITCH_RATE_FILTERED, S.ROLL,
        S.WHEEL_FL_FILTERED, S.WHEEL_FR_FILTERED, S.WHEEL_RL_FILTERED, S.WHEEL_RR_FILTERED,
        S.BETA_RATE_LOWPASS, S.AY_UTILISATION,
    ):  # fmt: skip
        state[slot] = np.nan
    return state


__all__ = [
    "BURCKHARDT_DRY_ASPHALT",
    "BURCKHARDT_SNOW",
    "BURCKHARDT_WET_ASPHALT",
    "N_STATE",
    "S",
    "axle_forces",
    "burckhardt",
    "burckhardt_peak",
    "classifier_update",
    "classify_tick",
    "compensate_wheel_speeds",
    "kx_gain",
    "lateral_model",
    "map_region",
    "mu_for_utilisation",
    "new_state",
    "observer_step",
    "read_inputs",
    "reference_tyre",
    "reset_observer",
    "state_is_finite",
    "vx_from_wheels_lt",
    "wheel_accelerations",
    "wheel_loads",
]
