"""The adaptive observer of Carnier, Corno, Savaresi 2023 (Sec. 2): V_x tilde from the wheels,
the friction-dependent tyre model and one step of the observer.

S. Carnier, M. Corno, S. M. Savaresi, "Hybrid Kinematic-Dynamic Sideslip and Friction
Estimation" (shared/papers/carnier-corno-savaresi2023-hybrid-sideslip-friction.md).

Blocks, each under the equation it computes:

- ``vx_from_wheels_lt``: V_x tilde of Sec. 2.1: load-transfer weighted mean (eq. 3), IQR outlier
  rejection over the five signals (Fig. 6) and the min/max logic (eq. 4);
- ``kx_gain``: the scheduled longitudinal gain (eq. 5-6);
- ``tyre_force`` / ``axle_forces`` / ``lateral_model``: the friction-dependent tanh tyre model
  (eq. 8-10, ``common.tyres.tanh_tyre``) on the slip angles of eq. 9 and the lateral balance
  of eq. 7;
- ``observer_step``: one forward-Euler step of the adaptive observer (eq. 2) with the scheduled
  K_y (eq. 11-13) and the switched friction law (eq. 14-15).

The slip-based friction classifier of Sec. 3 is in ``classifier``.

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

Everything here is a numba kernel on scalars and the caller's float64 state vector (``LAYOUT``);
nothing is allocated per tick (the IQR sort uses five scratch slots of the state vector).
"""

from __future__ import annotations

import enum
import math

import numpy as np

from slipd.channels import G, Veh
from slipd.estimators.common.filters import lowpass, noise_power, straight_settled
from slipd.estimators.common.inputs import ImuMemory, reset_imu
from slipd.estimators.common.layout import build_layout
from slipd.estimators.common.tyres import slip_angles, tanh_tyre
from slipd.numba_cache import nb


@enum.unique
class Tyre(enum.IntEnum):
    """The eq. 10 coefficients, resolved at init (params or the vehicle's reference curves) and
    kept across resets: C_r(mu) = a_C mu + b_C, k(mu) = a_k mu + b_k per axle."""

    A_CF = 0
    B_CF = 1
    A_KF = 2
    B_KF = 3
    A_CR = 4
    B_CR = 5
    A_KR = 6
    B_KR = 7


LAYOUT = build_layout(
    "carnier2023",
    "VX",  # m/s, V_x hat (eq. 2)
    "VY",  # m/s, V_y hat (eq. 2), ISO 8855 (+ left)
    "MU",  # -, mu hat (eq. 2, 14)
    "MU_DEFAULT",  # -, mu bar of eq. 14: the attraction value, set by the classifier
    "CLASS_HIGH",  # 1.0 high grip, 0.0 low grip: the classifier's boolean mu bar (Sec. 3)
    "HIGH_TICKS",  # consecutive ticks with a point in the high-grip region
    "LOW_TICKS",  # consecutive ticks with a point in the low-grip region
    "INITIALISED",  # 0 until the first tick with a wheel-speed measurement
    "TICKS",  # ticks since init or reset
    "PREV_YAW_RATE",  # rad/s, last valid yaw rate (fallback)
    "INNOVATION_VAR",  # (m/s^2)^2, low-passed (ay - ay_hat)^2 (quality figure)
    "DETECTIONS",  # number of friction changes the classifier has signalled (diagnostic)
    ("IMU", ImuMemory),  # CoG translation, roll compensation, held ax and steer
    ("WHEEL_ACC", 4),  # derivative filters of the raw wheel speeds FL FR RL RR (eq. 5, 21)
    ("SORT", 5),  # scratch area of the IQR sort (eq. 4 step 1): five values, no allocation
    ("TYRE", Tyre),
    "BETA_RATE_LOWPASS",  # rad/s, low-pass of eq. 13's beta_dot (NaN = not started)
    "AY_UTILISATION",  # m/s^2, low-passed |A_y| for the friction floor (NaN = not started)
    "SWITCH_NOISE",  # (m/s^2)^2, the switches' vx beta_dot squared on straights (NaN = none yet)
    "STRAIGHT_TIME",  # s the yaw rate has stayed below omega_z bar (the noise's sampling)
)
S = LAYOUT.S
#: slots that must stay finite, with the held inputs (the filters after them restart
#: themselves from NaN)
_CHECKED_END = int(S.DETECTIONS) + 1
_IMU = int(S.IMU)
_LAST_AX = _IMU + int(ImuMemory.LAST_AX)
_LAST_STEER = _IMU + int(ImuMemory.LAST_STEER)
_SORT0 = int(S.SORT)
_WHEEL0 = int(S.WHEEL_ACC)
TYRE0 = int(S.TYRE)  # first of the eq. 10 coefficients (Tyre)
#: |vy| (m/s) below which the secant slope of eq. 11 is replaced by the tangent (0/0)
SECANT_MIN_VY = 0.02


# ---------------------------------------------------------------------------------------------
# Sec. 2.1: V_x tilde from the wheels (eq. 3-4, Fig. 4-6) and K_x (eq. 5-6)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True, _nrt=False)
def load_transfer_weight(wheel_x, wheel_y, transfer_angle, gamma_minus, gamma_plus):
    """k_wi of eq. 3: 1 when the wheel lies within [-gamma_minus, +gamma_plus] of the load
    transfer direction (angles of the wheel position seen from the CoG), else 0 (Fig. 5)."""
    d = math.atan2(wheel_y, wheel_x) - transfer_angle
    d = (d + math.pi) % (2.0 * math.pi) - math.pi  # wrap to [-pi, pi)
    return 1.0 if -gamma_minus <= d <= gamma_plus else 0.0


@nb.njit(cache=True, _nrt=False)
def _insert_sorted(buf, n, value):
    """Insert ``value`` into the sorted ``buf[_SORT0:_SORT0 + n]``; returns n + 1."""
    i = n
    while i > 0 and buf[_SORT0 + i - 1] > value:
        buf[_SORT0 + i] = buf[_SORT0 + i - 1]
        i -= 1
    buf[_SORT0 + i] = value
    return n + 1


@nb.njit(cache=True, _nrt=False)
def _quantile_sorted(buf, n, q):
    """Quantile q of the sorted ``buf[_SORT0:_SORT0 + n]``, linear interpolation (numpy's
    default "linear" method: position q (n - 1))."""
    pos = q * (n - 1)
    lo = int(math.floor(pos))
    hi = min(lo + 1, n - 1)
    frac = pos - lo
    return buf[_SORT0 + lo] + frac * (buf[_SORT0 + hi] - buf[_SORT0 + lo])


@nb.njit(cache=True, _nrt=False)
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


@nb.njit(cache=True, inline="always")
def _add_deviation(total, n, ok, wheel_accel, ax):
    """One valid wheel's |dV_i/dt - A_x| into eq. 5's sum (total, count)."""
    if not ok:
        return total, n
    return total + abs(wheel_accel - ax), n + 1


@nb.njit(cache=True, _nrt=False)
def kx_gain(
    a_fl, a_fr, a_rl, a_rr, ok_fl, ok_fr, ok_rl, ok_rr, ax, threshold, kx_min, kx_max
):  # fmt: skip
    """eq. 5-6: Delta_Ax = sum_i |dV_i/dt - A_x| over the valid wheels (scaled to four when
    some are missing); K_x = K_x,min when Delta_Ax >= threshold, else K_x,max.
    Returns (K_x, Delta_Ax)."""
    total, n = _add_deviation(0.0, 0, ok_fl, a_fl, ax)
    total, n = _add_deviation(total, n, ok_fr, a_fr, ax)
    total, n = _add_deviation(total, n, ok_rl, a_rl, ax)
    total, n = _add_deviation(total, n, ok_rr, a_rr, ax)
    if n == 0:
        return 0.0, math.inf
    delta_ax = total * 4.0 / n
    return (kx_min if delta_ax >= threshold else kx_max), delta_ax


# ---------------------------------------------------------------------------------------------
# Sec. 2.2: the friction-dependent tyre model (eq. 7-10)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True, _nrt=False)
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


@nb.njit(cache=True, _nrt=False)
def tyre_force(alpha, c_r, k):
    """eq. 8: F_y = C_r / k tanh(k alpha) and its slope dF_y/dalpha = C_r (1 - tanh^2)."""
    return tanh_tyre(alpha, k, c_r / k, c_r)


@nb.njit(cache=True, _nrt=False)
def axle_forces(alpha_f, alpha_r, mu, state, k_floor):
    """eq. 8, 10 for both axles at friction ``mu``: (F_yF, dF_yF/dalpha, F_yR, dF_yR/dalpha)."""
    t = TYRE0
    c_f, k_f = tyre_coefficients(mu, state[t], state[t + 1], state[t + 2], state[t + 3], k_floor)
    c_r, k_r = tyre_coefficients(
        mu, state[t + 4], state[t + 5], state[t + 6], state[t + 7], k_floor
    )
    force_f, slope_f = tyre_force(alpha_f, c_f, k_f)
    force_r, slope_r = tyre_force(alpha_r, c_r, k_r)
    return force_f, slope_f, force_r, slope_r


@nb.njit(cache=True, _nrt=False)
def lateral_model(vx, vy, yaw_rate, steer, mu, state, vehicle, k_floor):
    """eq. 7-10: A_y hat = (F_yF cos(delta) + F_yR) / m at friction ``mu`` and its slope
    d A_y hat / d vy (the xi of eq. 11 when mu is the nominal friction).

    The eq. 10 coefficients are read from the state's TYRE block.
    Returns (ay_hat, d ay_hat / d vy, alpha_F, alpha_R).
    """
    alpha_f, alpha_r, dalpha_f, dalpha_r = slip_angles(
        vx, vy, yaw_rate, steer, vehicle[Veh.LF], vehicle[Veh.LR]
    )
    force_f, slope_f, force_r, slope_r = axle_forces(alpha_f, alpha_r, mu, state, k_floor)
    cos_steer = math.cos(steer)
    inv_mass = 1.0 / vehicle[Veh.MASS]
    ay_hat = (force_f * cos_steer + force_r) * inv_mass
    slope = (slope_f * cos_steer * dalpha_f + slope_r * dalpha_r) * inv_mass
    return ay_hat, slope, alpha_f, alpha_r


@nb.njit(cache=True, _nrt=False)
def mu_for_peak(utilisation, fz, a_c, b_c, a_k, b_k):
    """The mu at which the eq. 8-10 axle peak C_r(mu) / k(mu) equals ``utilisation`` x Fz:
    a_C mu + b_C = u Fz (a_k mu + b_k), linear in mu. NaN when no such mu exists."""
    denominator = a_c - utilisation * fz * a_k
    if denominator <= 0.0:
        return math.nan
    return (utilisation * fz * b_k - b_c) / denominator


@nb.njit(cache=True, _nrt=False)
def mu_for_utilisation(state, utilisation, vehicle):
    """Lowest mu whose model peak reaches ``utilisation`` (|A_y| / g) on both axles (static
    loads). Eq. 10's linear k(mu) puts the peak of an intermediate mu below mu itself, so the
    floor is found on the model, not as mu >= utilisation."""
    mass_g = vehicle[Veh.MASS] * G
    wheelbase = vehicle[Veh.LF] + vehicle[Veh.LR]
    t = TYRE0
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


@nb.njit(cache=True, _nrt=False)
def linear_slope(vx, vehicle, state):
    """xi_lin: d A_y / d vy of the linear tyre range at the nominal friction (the cornering
    stiffnesses C_r(mu_nominal) of both axles), -(C_F + C_R) / (m vx) < 0."""
    mu = vehicle[Veh.MU_NOMINAL]
    c_f = state[TYRE0] * mu + state[TYRE0 + 1]
    c_r = state[TYRE0 + 4] * mu + state[TYRE0 + 5]
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


@nb.njit(cache=True, inline="always")
def _model_terms(state, vx, vy, mu, yaw_rate, steer, vehicle, k_floor):
    """Eq. 7-11's model terms at the estimate: A_y hat at mu hat, A*_y at the nominal friction,
    its slope xi over vy (before the floor), the slip angles and the nominal axle forces.

    xi: [26]'s secant between the estimate and the true vy, which is unknown. The secant to
    vy_ref = l_r r stands in for it: there the rear slip angle is zero (the low-speed,
    kinematic-steering vy), so vy_ref lies in the linear tyre range whatever the speed and
    curvature, where the car normally is. Near vy_ref it is the tangent; unlike the tangent it
    does not vanish once the estimate has drifted into the saturated range, where a vanishing
    gain would leave the drift uncorrected for good (a -37 deg runaway in a 20 m radius corner
    of the endurance drive). Returns (ay_hat, ay_star, xi, alpha_F, alpha_R, F_yF*, F_yR*)."""
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
    vy_ref = lr * yaw_rate
    if abs(vy - vy_ref) > SECANT_MIN_VY:
        ref_f, ref_r, _, _ = slip_angles(vx, vy_ref, yaw_rate, steer, lf, lr)
        ref_force_f, _, ref_force_r, _ = axle_forces(ref_f, ref_r, mu_nominal, state, k_floor)
        ay_star_ref = (ref_force_f * cos_steer + ref_force_r) * inv_mass
        xi = (ay_star - ay_star_ref) / (vy - vy_ref)
    else:
        xi = (slope_f * cos_steer * dalpha_f + slope_r * dalpha_r) * inv_mass  # the tangent
    return ay_hat, ay_star, xi, alpha_f, alpha_r, nominal_f, nominal_r


@nb.njit(cache=True, inline="always")
def _switch_rate(state, ay, yaw_rate, vx, beta_rate_highpass, dt):
    """The kinematic beta_dot of eq. 13 the k_y and mu switches see. slipd: minus its low-pass
    (time constant ``beta_rate_highpass``, 0 = the paper's raw eq. 13): a road bank or an ay
    offset adds a constant to eq. 13 that would hold k_y at k_y,min for good, while a real
    sideslip rate cannot stay away from zero."""
    beta_dot = (ay - yaw_rate * vx) / vx  # eq. 13
    if beta_rate_highpass > 0.0:
        beta_dot -= lowpass(state, S.BETA_RATE_LOWPASS, beta_dot, dt, beta_rate_highpass)
    return beta_dot


@nb.njit(cache=True, inline="always")
def _switch_noise(state, beta_dot, vx, yaw_rate, straight_yaw_rate, time_constant, dt):
    """slipd: the noise of the switches' beta_dot, as the acceleration vx beta_dot that drives
    it, averaged (``time_constant``) where the true sideslip rate is ~0: going straight, |r|
    below Table 1's omega_z bar for STRAIGHT_SETTLE s (a slalom's yaw rate crosses zero where
    its sideslip rate peaks). Returns its standard deviation in rad/s at this speed (NaN:
    none seen yet).

    Why: eq. 12's beta_dot bar = 0.3 deg/s was tuned on the paper's SUV sensors. Eq. 13's
    beta_dot carries the accelerometer's noise over vx: 0.3 m/s^2 left after the 5 Hz
    vibration low-pass is 0.9 deg/s at 20 m/s, so k_y sat at k_y,min on noise and the
    observer integrated open loop (a -40 deg runaway in a corner of the endurance drive with
    a raw IMU's vibration). What it costs: the straights of a manoeuvre-dense drive still
    carry some real sideslip rate (mu_jump: 0.14 m/s^2 against 0.06 of the sensor alone), and
    a higher threshold keeps k_y at k_y,max through a low-grip curve, so the observer follows
    the high-grip model and the classifier sees less slip."""
    settled = straight_settled(state, S.STRAIGHT_TIME, abs(yaw_rate) < straight_yaw_rate, dt)
    noise = noise_power(state, S.SWITCH_NOISE, beta_dot * vx, settled, dt, time_constant)
    return math.sqrt(noise) / vx if math.isfinite(noise) else math.nan


@nb.njit(cache=True, inline="always")
def _friction_floor(state, mu, ay, ay_ok, vehicle, utilisation_floor, dt):
    """slipd: the road transmits at least the friction in use, |A_y| / g (low-passed with
    ``utilisation_floor`` s; 0 = the paper's unbounded eq. 14). Without this floor a mu hat
    below it is unstable: the mu-model saturates below the measured A_y, the innovation keeps
    one sign whatever vy, and eq. 2 drives vy to ever larger slip."""
    if utilisation_floor > 0.0 and ay_ok:
        utilisation = lowpass(state, S.AY_UTILISATION, abs(ay), dt, utilisation_floor)
        mu = max(mu, mu_for_utilisation(state, utilisation / G, vehicle))
    return mu


@nb.njit(cache=True, _nrt=False)
def observer_step(
    state, ax, ay, ay_ok, yaw_rate, steer, vx_tilde, vx_ok, kx, vehicle, dt,
    ky_min, ky_max, beta_rate_threshold, k_mu, k_mu_bar, beta_rate_mu_threshold,
    yaw_rate_threshold, mu_min, mu_max, k_floor, delta_gain, beta_rate_highpass,
    utilisation_floor, xi_floor, switch_noise_sigmas, switch_noise_time_constant,
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
    ay_hat, ay_star, xi, alpha_f, alpha_r, nominal_f, nominal_r = _model_terms(
        state, vx, vy, mu, yaw_rate, steer, vehicle, k_floor
    )
    xi_lin = linear_slope(vx, vehicle, state)
    # slipd: |xi| >= xi_floor |xi_lin| (both negative): a gain that never fades completely
    xi = min(xi, xi_floor * xi_lin)
    delta = delta_gain / (xi_lin * xi_lin)
    if not ay_ok:
        ay = ay_hat
    innovation = ay - ay_hat
    beta_dot = _switch_rate(state, ay, yaw_rate, vx, beta_rate_highpass, dt)
    if switch_noise_sigmas > 0.0 and ay_ok:
        # slipd: neither switch trips on noise (``_switch_noise``)
        noise = _switch_noise(state, beta_dot, vx, yaw_rate, yaw_rate_threshold,
                              switch_noise_time_constant, dt)  # fmt: skip
        if math.isfinite(noise):
            beta_rate_threshold = max(beta_rate_threshold, switch_noise_sigmas * noise)
            beta_rate_mu_threshold = max(beta_rate_mu_threshold, switch_noise_sigmas * noise)
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
    mu = _friction_floor(state, mu + mu_dot * dt, ay, ay_ok, vehicle, utilisation_floor, dt)
    state[S.MU] = min(max(mu, mu_min), mu_max)
    return beta_dot, innovation, alpha_f, alpha_r, ay, nominal_f, nominal_r


# ---------------------------------------------------------------------------------------------
# bookkeeping
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True, _nrt=False)
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
    if not math.isfinite(state[_LAST_AX]):
        state[_LAST_AX] = 0.0
    if not math.isfinite(state[_LAST_STEER]):
        state[_LAST_STEER] = 0.0
    if not math.isfinite(state[S.PREV_YAW_RATE]):
        state[S.PREV_YAW_RATE] = 0.0


@nb.njit(cache=True, _nrt=False)
def state_is_finite(state):
    for i in range(_CHECKED_END):
        if not math.isfinite(state[i]):
            return False
    return math.isfinite(state[_LAST_AX]) and math.isfinite(state[_LAST_STEER])


def new_state(mu_init: float, class_high: bool) -> np.ndarray:
    """A state vector before the first tick (observer not started, filters NaN = not started)."""
    state = np.zeros(LAYOUT.size, dtype=np.float64)
    state[S.MU] = mu_init
    state[S.MU_DEFAULT] = mu_init
    state[S.CLASS_HIGH] = 1.0 if class_high else 0.0
    reset_imu(state, _IMU)
    state[LAYOUT.span("WHEEL_ACC").start : LAYOUT.span("WHEEL_ACC").stop] = np.nan
    state[S.BETA_RATE_LOWPASS] = np.nan
    state[S.AY_UTILISATION] = np.nan
    state[S.SWITCH_NOISE] = np.nan
    return state
