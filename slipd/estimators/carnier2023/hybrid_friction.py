"""``hybrid_friction``: the hybrid kinematic-dynamic sideslip and friction observer with the
slip-based friction classifier of Carnier, Corno, Savaresi 2023 (Fig. 1).

``hybrid_friction_nocls`` (a registry variant: ``classifier_enabled`` = 0) is the adaptive
state observer of Sec. 2 alone, the "pure adaptive observer" the paper compares against in
Fig. 13, 15 and 16: mu hat starts at MU_NOMINAL and adapts only through eq. 14-15.

Per tick (kernels in ``observer`` and ``classifier``, equations in their docstrings):

1. inputs at the CoG, roll gravity removed from ay (the paper's "standard filtering");
2. V_x tilde from the wheels: load-transfer weighted mean (eq. 3), IQR outlier rejection and the
   min/max logic (eq. 4); K_x scheduled on Delta_Ax (eq. 5-6);
3. the adaptive observer (eq. 2), forward Euler: the kinematic model (eq. 1) corrected by
   K_x (V_x tilde - V_x hat) and K_y (A_y - A_y hat), A_y hat from the friction-dependent tanh
   axle model (eq. 7-10), K_y scheduled on the kinematic sideslip rate (eq. 11-13), mu hat by
   the switched law (eq. 14-15);
4. the friction classifier (Sec. 3): lambda-mu_x maps on Burckhardt curves per wheel (forces
   from eq. 20-21) and alpha-mu_y maps on the observer's own tyre model per axle (eq. 22);
   a detected change re-initialises mu hat, and the attraction value mu bar of eq. 14, to the
   class's reference friction (MU_NOMINAL for high, ``mu_low`` for low).

Outputs: beta = atan2(vy, vx) (eq. 2), vx, vy, mu hat, friction class (3 high / 1 low from
the classifier's boolean; the paper's classifier is binary, so 2 "medium" is never produced;
0 when the classifier is disabled), roll of the gravity compensation, status bits.

Sign convention: ISO 8855 inside and out; the paper's eq. 1 and 9 are converted as the
``observer`` module docstring explains (its omega_z is -r; eq. 9's front yaw term corrected).

Parameters (``DEFAULTS``) - from Table 1: gamma-, gamma+ (35 deg), K_x,min 0.2, K_x,max 5,
k_y,min 0.3, k_y,max 10, beta_dot bar 0.3 deg/s, k_mu 0.007, K_mu bar 0.08, beta_dot bar_mu 7
(the table prints "deg"; read as deg/s, it is a rate threshold like beta_dot bar), omega_z bar
5 deg/s; from the text: the IQR scale 1.5 (Sec. 2.1), mu_low = 0.3 (the snow reference of
Fig. 8 and Sec. 4.1). Not in the paper, chosen here and marked "slipd" below: the Delta_Ax
threshold (Table 1 lacks it), the classifier's band, limits and persistence, the minimum
speed, the mu clamp, the quality figure, the convergence rule and the departures below.

What Table 1 cannot give for this car. (a) The dynamical-model parameters P_d = (a_C, b_C,
a_k, b_k) per axle (eq. 10) are identified on the paper's SUV (phase 1 of Sec. 2.4); Table 1's
pairs (-44, 57) and (-46, 79) behave as the shape factor k in 1/rad (k(1) = 13, k(0.3) = 44: the
peak moves from ~6 deg to ~1 deg of slip, as Fig. 8 describes), not as a stiffness. The same
identification is done here from the vehicle profile: two reference tanh characteristics, the
high one with the profile's axle cornering stiffness and peak MU_NOMINAL x static axle load,
the low one at ``mu_low`` with ``tyre_low_stiffness_ratio`` x that stiffness (1: a tyre whose
road friction scales only the peak, which is how the simulator's Pacejka tyres behave); the
eight coefficients default to NaN = "derive them" and can be set explicitly. (b) [26]'s
scaling factor Delta of eq. 11 and 15 is not given. Here Delta = 1 / xi_lin^2 in eq. 11, which
makes k_y the decay rate (1/s) of the vy error in the linear tyre range, and Delta_mu = 1 in
eq. 15 (mu' = k_mu A*_y (A_y - A_y hat) in 1/s), which gives Table 1's k_mu the ~10 s
adaptation of Fig. 13; one common Delta cannot honour both Table 1 gains.

Departures from the paper (slipd), each a parameter whose value 0 restores the paper's logic
where that is meaningful; measured on the simulator suite:

- ``beta_rate_highpass`` = 0.3 s: the k_y and mu switches (eq. 12, 14) see the kinematic
  beta_dot of eq. 13 minus its low-pass. A road bank or an ay offset adds a constant to eq. 13
  (6 deg of bank: 2.6 deg/s at 22 m/s, Table 1's threshold is 0.3 deg/s) that holds k_y at
  k_y,min for good (the banked road's figures: benchmarks/MEASUREMENTS.md).
- eq. 11's xi as the secant from vy_ref = l_r r (zero rear slip) to the estimate, with
  |xi| >= ``xi_floor`` |xi_lin| = 0.5: the tangent vanishes once the estimate has drifted into
  the saturated range and the drift then never comes back (a -37 deg runaway on the endurance
  drive). [26]'s xi is a secant to the (unknown) true vy; vy_ref is a stand-in in the linear
  range.
- ``mu_utilisation_time_constant`` = 0.2 s: mu hat is kept at or above the friction in use
  (the mu whose model peak reaches the low-passed |A_y| / g). Below it the innovation keeps
  one sign whatever vy and eq. 2 drives vy to ever larger slip.
- ``switch_noise_sigmas`` = 3: the k_y and mu switches (eq. 12, 14) trip only above 3 x the
  noise of their beta_dot, measured on straights (``observer._switch_noise``). Table 1's
  0.3 deg/s lies below what any raw IMU's ay noise puts on eq. 13 (0.3 m/s^2 is 0.9 deg/s at
  20 m/s): k_y then sat at k_y,min and the observer integrated open loop. Measured (beta RMS,
  paper's thresholds -> noise floor): the real run 0.84 -> 0.59 deg; the endurance drive
  with a raw IMU's vibration 5.94 -> 0.17 deg (VALID 47 -> 89 %; -40 deg runaways in slow
  corners) and without 0.24 -> 0.17; mu_jump 0.43 -> 0.83 deg (seed 0), where a steadier k_y
  lets the observer follow the high-grip model into the low patches and the classifier sees
  less slip. 3 x the noise as the kinematic heuristic's bells are set (selmanaj2017).
- classifier: the axle forces keep the yaw balance (``class_yaw_moment_split``; eq. 22 is its
  steady-state case) so that steering transients do not look like low grip; a point far
  *below* the low curve is white (it shows a bad slip estimate, not low grip); a utilisation
  above the low surface's peak + ``class_high_margin`` proves high grip at any slip; a switch
  needs ``class_persistence_ticks`` consecutive ticks. Fig. 19's 3 deg slip-angle limit is
  used as ``class_alpha_min``.

The wheel-speed side matters: V_x tilde (eq. 4), Delta_Ax and lambda (eq. 17) use the wheels
one by one, so a car (or simulator) whose left and right wheel channels are swapped breaks the
classifier's longitudinal map (lambda of ~5 % in every corner) - see the test module.

Robustness (slipd): invalid yaw rate, steer and ax hold their last valid values; an invalid
ay suspends the lateral correction and mu adaptation (the model's A_y hat is integrated);
invalid wheels are left out of V_x tilde and Delta_Ax, without any wheel the longitudinal
correction is skipped; without drive/brake torques the longitudinal maps are skipped. Below
``min_speed`` the observer is held at vy = 0, vx = V_x tilde (the slip angles of eq. 9 are
undefined at vx -> 0). A non-finite state or |vy| > vx restarts it with RESET.

Quality figure SIGMA_BETA (the paper has none): the vy error that would explain the recent
lateral innovation through the linear tyre range, atan(rms(A_y - A_y hat) / |xi_lin| / vx),
low-passed with ``innovation_time_constant``, plus ``sigma_beta_floor``. A heuristic, not a
posterior.
"""

from __future__ import annotations

import enum
import math

import numpy as np

from slipd.channels import ST_INPUT_TIMEOUT, ST_NOT_CONVERGED, ST_RESET, Veh
from slipd.errors import ConfigError
from slipd.estimators.carnier2023.classifier import classifier_update, classify_tick
from slipd.estimators.carnier2023.observer import (
    LAYOUT,
    S,
    kx_gain,
    linear_slope,
    new_state,
    observer_step,
    reference_tyre,
    reset_observer,
    state_is_finite,
    vx_from_wheels_lt,
)
from slipd.estimators.common.filters import lowpass
from slipd.estimators.common.inputs import (
    ImuMemory,
    read_inputs,
    wheel_accelerations,
    wheel_speeds,
)
from slipd.estimators.common.kinematics import compensate_wheel_speeds, kinematic_beta_rate
from slipd.estimators.common.outputs import held_sigma, write_outputs
from slipd.estimators.common.vehicle import require_vehicle
from slipd.numba_cache import nb

DEG = math.pi / 180.0


@enum.unique
class PARAMS(enum.IntEnum):
    # Sec. 2.1, V_x tilde and K_x
    GAMMA_MINUS = 0  # rad, load-transfer cone (Table 1: 35 deg)
    GAMMA_PLUS = 1  # rad (Table 1: 35 deg)
    MIN_TRANSFER_ACCEL = 2  # m/s^2, below it every wheel has k_w = 1 (slipd)
    IQR_SCALE = 3  # -, outlier fences Q1 - s IQR, Q3 + s IQR (Sec. 2.1: 1.5)
    KX_MIN = 4  # 1/s (Table 1)
    KX_MAX = 5  # 1/s (Table 1)
    DELTA_AX_THRESHOLD = 6  # m/s^2, eq. 6 (not in Table 1; slipd)
    WHEEL_ACC_CUTOFF_HZ = 7  # Hz, derivative filter of the wheel speeds (eq. 5, 21; slipd)
    # Sec. 2.2, K_y
    KY_MIN = 8  # 1/s (Table 1)
    KY_MAX = 9  # 1/s (Table 1)
    BETA_RATE_THRESHOLD = 10  # rad/s (Table 1: 0.3 deg/s)
    # Sec. 2.3, mu
    K_MU = 11  # (Table 1)
    K_MU_BAR = 12  # 1/s (Table 1)
    BETA_RATE_MU_THRESHOLD = 13  # rad/s (Table 1: 7 deg(/s))
    YAW_RATE_MU_THRESHOLD = 14  # rad/s (Table 1: 5 deg/s)
    MU_LOW = 15  # -, low reference friction (Fig. 8 / Sec. 4.1 snow: 0.3)
    MU_MIN = 16  # -, clamp of mu hat (slipd)
    MU_MAX = 17  # -, clamp of mu hat (slipd)
    MU_INIT = 18  # -, initial mu hat and mu bar; NaN = MU_NOMINAL (the paper starts on dry)
    # eq. 10 coefficients (NaN = derived from the vehicle's two reference curves)
    TYRE_LOW_STIFFNESS_RATIO = 19  # -, C_r(mu_low) / C_r(mu_high) of the derived references
    TYRE_A_CF = 20  # N/rad per unit mu
    TYRE_B_CF = 21  # N/rad
    TYRE_A_KF = 22  # 1/rad per unit mu
    TYRE_B_KF = 23  # 1/rad
    TYRE_A_CR = 24
    TYRE_B_CR = 25
    TYRE_A_KR = 26
    TYRE_B_KR = 27
    TYRE_K_FLOOR = 28  # 1/rad, lower bound of k(mu) under extrapolation (slipd)
    # Sec. 3, classifier
    CLASSIFIER_ENABLED = 29  # 1 = full observer (Fig. 1), 0 = the adaptive observer alone
    CLASS_BAND = 30  # -, s >= 1 - band high, s <= band low (slipd)
    CLASS_MIN_GAP = 31  # -, curves closer than this in mu are white (slipd)
    CLASS_SLIP_MIN = 32  # -, |lambda| limit (Fig. 19: lambda > 0.05)
    CLASS_ALPHA_MIN = 33  # rad, |alpha| limit (Fig. 19: the maps separate above 3 deg)
    CLASS_PERSISTENCE_TICKS = 34  # ticks a point must stay in the new region (slipd)
    BURCKHARDT_HIGH_C1 = 35  # Burckhardt dry asphalt (high grip reference)
    BURCKHARDT_HIGH_C2 = 36
    BURCKHARDT_HIGH_C3 = 37
    BURCKHARDT_LOW_C1 = 38  # Burckhardt snow (low grip reference)
    BURCKHARDT_LOW_C2 = 39
    BURCKHARDT_LOW_C3 = 40
    # slipd
    MIN_SPEED = 41  # m/s, below it the observer is held
    SETTLE_TICKS = 42  # ticks after (re)start flagged NOT_CONVERGED
    YAW_ACC_CUTOFF_HZ = 43  # Hz, derivative filters of the angular rates (CoG translation)
    ROLL_TIME_CONSTANT = 44  # s, roll complementary filter; 0 = no gravity compensation
    INNOVATION_TIME_CONSTANT = 45  # s, low-pass of the squared innovation (quality figure)
    SIGMA_BETA_FLOOR = 46  # rad, floor of the quality figure
    CLASS_HIGH_MARGIN = 47  # -, mu above the low curve that proves high grip (slipd)
    CLASS_YAW_MOMENT_SPLIT = 48  # 1 = axle forces with the yaw balance, 0 = eq. 22 (slipd)
    DELTA_GAIN = 49  # -, Delta = delta_gain / xi_lin^2 in eq. 11 (slipd)
    BETA_RATE_HIGHPASS = 50  # s, high-pass of eq. 13's beta_dot for the switches; 0 = paper
    MU_UTILISATION_TIME_CONSTANT = 51  # s, low-pass of |A_y| for mu >= |A_y| / g; 0 = paper
    XI_FLOOR = 52  # -, |xi| >= xi_floor |xi_lin| in eq. 11; 0 = paper
    ROLL_GAIN_LEARNING = 53  # 1 = the roll compensation's static gain learnt (slipd), 0 = profile
    ACCEL_LOWPASS_HZ = 54  # accelerometer vibration low-pass, Hz; 0 = none (the paper)
    SWITCH_NOISE_SIGMAS = 55  # -, switch thresholds at least this x beta_dot's noise; 0 = paper
    SWITCH_NOISE_TIME_CONSTANT = 56  # s, averaging of that noise on straights (slipd)


DEFAULTS = {
    "gamma_minus": 35.0 * DEG,
    "gamma_plus": 35.0 * DEG,
    "min_transfer_accel": 0.5,
    "iqr_scale": 1.5,
    "kx_min": 0.2,
    "kx_max": 5.0,
    # slipd: eq. 5 sums four derivatives; at 10 Hz (Selmanaj's filters) the wheel-speed noise
    # alone sums to ~10 m/s^2 at motorway speed and K_x sat at K_x,min, so a grade's ax
    # bias (g sin 4 % = 0.4 m/s^2) put vx off by 2 m/s (benchmarks/MEASUREMENTS.md)
    "delta_ax_threshold": 6.0,
    "wheel_acc_cutoff_hz": 2.0,
    "ky_min": 0.3,
    "ky_max": 10.0,
    "beta_rate_threshold": 0.3 * DEG,
    "k_mu": 0.007,
    "k_mu_bar": 0.08,
    "beta_rate_mu_threshold": 7.0 * DEG,
    "yaw_rate_mu_threshold": 5.0 * DEG,
    "mu_low": 0.3,
    "mu_min": 0.1,
    "mu_max": 1.3,
    "mu_init": math.nan,
    "tyre_low_stiffness_ratio": 1.0,
    "tyre_a_cf": math.nan,
    "tyre_b_cf": math.nan,
    "tyre_a_kf": math.nan,
    "tyre_b_kf": math.nan,
    "tyre_a_cr": math.nan,
    "tyre_b_cr": math.nan,
    "tyre_a_kr": math.nan,
    "tyre_b_kr": math.nan,
    "tyre_k_floor": 1.0,
    "classifier_enabled": 1.0,
    "class_band": 0.15,
    "class_min_gap": 0.15,
    "class_slip_min": 0.05,
    "class_alpha_min": 3.0 * DEG,
    "class_persistence_ticks": 5.0,
    "burckhardt_high_c1": 1.2801,
    "burckhardt_high_c2": 23.99,
    "burckhardt_high_c3": 0.52,
    "burckhardt_low_c1": 0.1946,
    "burckhardt_low_c2": 94.129,
    "burckhardt_low_c3": 0.0646,
    "min_speed": 3.0,
    "settle_ticks": 100.0,
    "yaw_acc_cutoff_hz": 10.0,
    "roll_time_constant": 1.0,
    "innovation_time_constant": 1.0,
    "sigma_beta_floor": 0.2 * DEG,
    "class_high_margin": 0.15,
    "class_yaw_moment_split": 1.0,
    "delta_gain": 1.0,
    "beta_rate_highpass": 0.3,
    "mu_utilisation_time_constant": 0.2,
    "xi_floor": 0.5,
    "roll_gain_learning": 1.0,
    # slipd: the switches of eq. 13 and the classifier read ay; a raw IMU's ~1 m/s^2 of body
    # vibration above 5 Hz (the revs_250lm run) trips them; 5 Hz is above the lateral dynamics
    "accel_lowpass_hz": 5.0,
    "switch_noise_sigmas": 3.0,
    "switch_noise_time_constant": 10.0,
}

_TYRE_PARAMS = (
    PARAMS.TYRE_A_CF, PARAMS.TYRE_B_CF, PARAMS.TYRE_A_KF, PARAMS.TYRE_B_KF,
    PARAMS.TYRE_A_CR, PARAMS.TYRE_B_CR, PARAMS.TYRE_A_KR, PARAMS.TYRE_B_KR,
)  # fmt: skip
_IMU = int(S.IMU)
_ROLL = _IMU + int(ImuMemory.ROLL)
_WHEEL_ACC = int(S.WHEEL_ACC)
#: m/s of lateral velocity the held sigma_beta stands for ("unknown")
HELD_SIGMA_VY = 1.0
#: Out.FRICTION_CLASS of the classifier's two classes (its boolean; no "medium")
CLASS_HIGH, CLASS_LOW = 3.0, 1.0


def tyre_coefficients(params: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """The eight eq. 10 coefficients: the params where set, else the vehicle's references."""
    mu_low = float(params[PARAMS.MU_LOW])
    if not 0.0 < mu_low < float(vehicle[Veh.MU_NOMINAL]):
        raise ConfigError(f"mu_low = {mu_low}: must lie between 0 and the vehicle's peak friction")
    derived = reference_tyre(vehicle, mu_low, float(params[PARAMS.TYRE_LOW_STIFFNESS_RATIO]))
    given = np.array([params[p] for p in _TYRE_PARAMS], dtype=np.float64)
    return np.where(np.isfinite(given), given, np.array(derived))


def init(params: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """A fresh state vector (``observer.LAYOUT``); the observer starts on the first wheel
    speed."""
    require_vehicle("hybrid_friction", vehicle, (
        Veh.MASS, Veh.LF, Veh.LR, Veh.TRACK_F, Veh.TRACK_R, Veh.H_COG, Veh.WHEEL_RADIUS,
        Veh.CORNERING_STIFFNESS_F, Veh.CORNERING_STIFFNESS_R, Veh.MU_NOMINAL,
    ))  # fmt: skip
    mu_init = float(params[PARAMS.MU_INIT])
    if not np.isfinite(mu_init):
        mu_init = float(vehicle[Veh.MU_NOMINAL])
    # the classifier's boolean starts on the side of the initial friction
    mu_mid = 0.5 * (float(vehicle[Veh.MU_NOMINAL]) + float(params[PARAMS.MU_LOW]))
    state = new_state(mu_init, mu_init >= mu_mid)
    tyre = LAYOUT.span("TYRE")
    state[tyre.start : tyre.stop] = tyre_coefficients(params, vehicle)
    return state


@nb.njit(cache=True, inline="always")
def _write(out, state, beta, beta_rate, sigma, classifier_on, status):
    friction_class = 0.0
    if classifier_on:
        friction_class = CLASS_HIGH if state[S.CLASS_HIGH] > 0.5 else CLASS_LOW
    write_outputs(out, beta, beta_rate, state[S.VX], state[S.VY], state[S.MU], sigma,
                  state[_ROLL], friction_class, status)  # fmt: skip


@nb.njit(cache=True, inline="always")
def _wheels(state, u, params, vehicle, ax, ay, yaw_rate, steer, dt, status):
    """Sec. 2.1: the wheel-speed rates (eq. 5, 21), the speeds referred to the CoG x axis and
    V_x tilde (eq. 3-4); INPUT_TIMEOUT when a wheel is missing. Returns (vx_tilde, vx_ok,
    rates, flags, compensated speeds, status)."""
    a_fl, a_fr, a_rl, a_rr, ok_fl, ok_fr, ok_rl, ok_rr = wheel_accelerations(
        state, _WHEEL_ACC, u, dt, params[PARAMS.WHEEL_ACC_CUTOFF_HZ]
    )
    v_fl, v_fr, v_rl, v_rr, _, _, _, _ = wheel_speeds(u)
    c_fl, c_fr, c_rl, c_rr = compensate_wheel_speeds(
        v_fl if ok_fl else 0.0, v_fr if ok_fr else 0.0, v_rl if ok_rl else 0.0,
        v_rr if ok_rr else 0.0, steer, yaw_rate, vehicle[Veh.TRACK_F], vehicle[Veh.TRACK_R],
    )  # fmt: skip
    vx_tilde, n_wheels = vx_from_wheels_lt(
        state, c_fl, c_fr, c_rl, c_rr, ok_fl, ok_fr, ok_rl, ok_rr, ax, ay, vehicle,
        params[PARAMS.GAMMA_MINUS], params[PARAMS.GAMMA_PLUS],
        params[PARAMS.MIN_TRANSFER_ACCEL], params[PARAMS.IQR_SCALE],
    )  # fmt: skip
    if n_wheels < 4:
        status |= ST_INPUT_TIMEOUT
    return (vx_tilde, n_wheels > 0, (a_fl, a_fr, a_rl, a_rr), (ok_fl, ok_fr, ok_rl, ok_rr),
            (c_fl, c_fr, c_rl, c_rr), status)


@nb.njit(cache=True, inline="always")
def _classify(state, u, params, vehicle, ax, ay, yaw_acc, steer, alpha_f, alpha_r, force_f_high,
              force_r_high, speeds, speeds_ok, rates, vx_prior):  # fmt: skip
    """Sec. 3: the map points of this tick and the classifier's switch (``classifier``)."""
    any_high, any_low = classify_tick(
        state, u, ax, ay, yaw_acc, steer, alpha_f, alpha_r, force_f_high, force_r_high,
        speeds, speeds_ok, rates, vx_prior, vehicle,
        params[PARAMS.MU_LOW], params[PARAMS.TYRE_K_FLOOR],
        (params[PARAMS.BURCKHARDT_HIGH_C1], params[PARAMS.BURCKHARDT_HIGH_C2],
         params[PARAMS.BURCKHARDT_HIGH_C3]),
        (params[PARAMS.BURCKHARDT_LOW_C1], params[PARAMS.BURCKHARDT_LOW_C2],
         params[PARAMS.BURCKHARDT_LOW_C3]),
        params[PARAMS.CLASS_SLIP_MIN], params[PARAMS.CLASS_ALPHA_MIN],
        params[PARAMS.CLASS_BAND], params[PARAMS.CLASS_HIGH_MARGIN],
        params[PARAMS.CLASS_MIN_GAP], params[PARAMS.CLASS_YAW_MOMENT_SPLIT] > 0.5,
    )  # fmt: skip
    classifier_update(
        state, any_high, any_low, params[PARAMS.CLASS_PERSISTENCE_TICKS],
        vehicle[Veh.MU_NOMINAL], params[PARAMS.MU_LOW],
    )  # fmt: skip


@nb.njit(cache=True, _nrt=False)
def step(state, u, params, vehicle, dt, out):
    """One tick of the full observer (Fig. 1); writes every element of ``out``, allocates
    nothing."""
    min_speed = params[PARAMS.MIN_SPEED]
    classifier_on = params[PARAMS.CLASSIFIER_ENABLED] > 0.5
    ax, ay, yaw_rate, yaw_acc, steer, _, _, ay_ok, yaw_rate_ok, _, status = read_inputs(
        state, _IMU, u, vehicle, state[S.PREV_YAW_RATE], params[PARAMS.YAW_ACC_CUTOFF_HZ],
        params[PARAMS.ROLL_TIME_CONSTANT], True, dt, params[PARAMS.ROLL_GAIN_LEARNING] > 0.5,
        params[PARAMS.ACCEL_LOWPASS_HZ],
    )  # fmt: skip
    if yaw_rate_ok:
        state[S.PREV_YAW_RATE] = yaw_rate
    vx_tilde, vx_ok, rates, wheels_ok, speeds, status = _wheels(
        state, u, params, vehicle, ax, ay, yaw_rate, steer, dt, status
    )
    running = state[S.INITIALISED] > 0.5 and state[S.VX] >= min_speed
    if not running:
        # start-up, standstill or crawling: slip angles undefined, hold vy = 0, vx = V_x tilde
        if vx_ok:
            reset_observer(state, vx_tilde, state[S.MU_DEFAULT])
            state[S.INITIALISED] = 1.0
        _write(out, state, 0.0, 0.0, held_sigma(HELD_SIGMA_VY, state[S.VX], min_speed),
               classifier_on, status | ST_NOT_CONVERGED)  # fmt: skip
        return
    kx, _ = kx_gain(
        rates[0], rates[1], rates[2], rates[3], wheels_ok[0], wheels_ok[1], wheels_ok[2],
        wheels_ok[3], ax, params[PARAMS.DELTA_AX_THRESHOLD], params[PARAMS.KX_MIN],
        params[PARAMS.KX_MAX],
    )  # fmt: skip
    vx_prior = state[S.VX]
    _, innovation, alpha_f, alpha_r, ay_used, force_f_high, force_r_high = observer_step(
        state, ax, ay, ay_ok, yaw_rate, steer, vx_tilde, vx_ok, kx, vehicle, dt,
        params[PARAMS.KY_MIN], params[PARAMS.KY_MAX], params[PARAMS.BETA_RATE_THRESHOLD],
        params[PARAMS.K_MU], params[PARAMS.K_MU_BAR], params[PARAMS.BETA_RATE_MU_THRESHOLD],
        params[PARAMS.YAW_RATE_MU_THRESHOLD], params[PARAMS.MU_MIN], params[PARAMS.MU_MAX],
        params[PARAMS.TYRE_K_FLOOR], params[PARAMS.DELTA_GAIN],
        params[PARAMS.BETA_RATE_HIGHPASS], params[PARAMS.MU_UTILISATION_TIME_CONSTANT],
        params[PARAMS.XI_FLOOR], params[PARAMS.SWITCH_NOISE_SIGMAS],
        params[PARAMS.SWITCH_NOISE_TIME_CONSTANT],
    )  # fmt: skip
    if classifier_on and ay_ok:
        _classify(state, u, params, vehicle, ax, ay, yaw_acc, steer, alpha_f, alpha_r,
                  force_f_high, force_r_high, speeds, wheels_ok, rates, vx_prior)  # fmt: skip
    # quality figure: low-passed squared lateral innovation
    if ay_ok and math.isfinite(innovation):
        lowpass(state, S.INNOVATION_VAR, innovation * innovation, dt,
                params[PARAMS.INNOVATION_TIME_CONSTANT])  # fmt: skip
    if not (state_is_finite(state) and abs(state[S.VY]) <= state[S.VX]):
        # non-finite or outside any single-track model's domain (> 45 deg): restart
        reset_observer(state, vx_tilde if vx_ok else 0.0, state[S.MU_DEFAULT])
        if not vx_ok:
            state[S.INITIALISED] = 0.0
        _write(out, state, math.atan2(state[S.VY], state[S.VX]), 0.0,
               held_sigma(HELD_SIGMA_VY, state[S.VX], min_speed), classifier_on,
               status | ST_RESET | ST_NOT_CONVERGED)  # fmt: skip
        return
    state[S.TICKS] += 1.0
    vx = state[S.VX]
    vy = state[S.VY]
    sigma_vy = math.sqrt(state[S.INNOVATION_VAR]) / abs(linear_slope(vx, vehicle, state))
    sigma = math.atan(sigma_vy / vx) + params[PARAMS.SIGMA_BETA_FLOOR]
    if state[S.TICKS] < params[PARAMS.SETTLE_TICKS]:
        status |= ST_NOT_CONVERGED
    _write(out, state, math.atan2(vy, vx), kinematic_beta_rate(vx, vy, ax, ay_used, yaw_rate),
           sigma, classifier_on, status)  # fmt: skip


@nb.njit(cache=True, nogil=True, _nrt=False)
def run_ticks(state, U, params, vehicle, dt, OUT):
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])


__all__ = ["DEFAULTS", "LAYOUT", "PARAMS", "init", "run_ticks", "step", "tyre_coefficients"]
