"""``kinematic_heuristic``: the kinematic sideslip observer of Selmanaj, Corno, Panzani,
Savaresi (2017), "Vehicle sideslip estimation: a kinematic based approach".

Observer (eq. 5), with the IMU accelerations at the CoG (Ax, Ay), the yaw rate omega_z and the
wheel-based longitudinal speed Vx as the measurement::

    Vx_hat' = -(a0 + a1 |omega_z|) (Vx_hat - Vx) + omega_z Vy_hat + Ax
    Vy_hat' = -omega_z Vx_hat - a2 omega_z (Vx_hat - Vx) - F Vy_hat + Ay
    beta    = atan2(Vy_hat, Vx_hat)                                           (eq. 3)

F (section 2.1, Fig. 2) is the heuristic that drives Vy_hat to zero when the car goes straight:
F = F_gain * F_omega * F_delta * F_betadot, each term the bivariate Gaussian of eq. 7,
F_i = exp(-(i^2 / sigma_i^2 + di^2 / sigma_di^2) / 2), on the yaw rate, the steering-wheel
angle and the sideslip rate of eq. 6, beta_dot = (Ay - omega_z Vx) / Vx, with their
derivatives from 10 Hz derivative filters (forward Euler). Any term near zero (cornering)
switches the heuristic off and leaves the observable kinematic observer alone.

Preprocessing (section 3, Fig. 6; ``slipd.estimators.preprocess``): gyro offsets at standstill,
CoG translation of the accelerations (full rigid body, IMU position from the profile),
roll by complementary filter of the static roll model and the roll rate (eq. 16, Fig. 9),
gravity compensation of ay (eq. 17), ax and ay offsets (Fig. 10, eq. 21) and Vx from the
compensated wheel speeds (eq. 11-13, Fig. 4). The paper neglects pitch (section 3.1), so
does this module.

Sign conventions: everything is ISO 8855 (the paper's eq. 11 and 16 are printed in the
paper's own signs; the preprocess docstrings say how they were converted). The heuristic's
delta is the *steering-wheel* angle (section 2.1: "delta is the steering wheel angle"), i.e.
``u[In.STEER] * vehicle[Veh.STEER_RATIO]``; with sigma_delta = 0.1 rad on the road-wheel angle
the bell would only close at ~6 deg of road-wheel steer, far beyond normal cornering.

Parameters (``DEFAULTS``): Table 1 of the paper (``TABLE_1``) for a0, a1, a2, the Vx
selection (ax threshold, sigma_w1, sigma_w2) and the three value widths of F (sigma_omega_z,
sigma_delta, sigma_beta_dot); section 2.1 for the 10 Hz derivative filters; section 4 for the
offset settling times (150 s gyros, 1500 s accelerometers). Not given by the paper and chosen
here (each says why in ``DEFAULTS``): the amplitude of F, the roll complementary-filter time
constant, the standstill and minimum-speed thresholds, the start-up settling time, the
quality-figure noise levels.

Departure from Table 1, by the paper's own tuning rule (section 2.1: "a good starting guess
[...] comes from the amplitude of the noise of the corresponding signal: the width of each
bell should be large enough such that the variations of F due to measurement noises is
negligible"): the three *derivative* widths of eq. 7, sigma_d_omega_z (``sigma_yaw_acc``),
sigma_d_delta (``sigma_steer_rate``) and sigma_d_beta_dot (``sigma_beta_acc``). Table 1's
0.18 / 0.1 / 0.3 were tuned to the Alfa 159's sensors; through the paper's 10 Hz derivative
filter the default profile's ESC/EPS signals (0.08 deg/s gyro, 0.1 deg steering-wheel angle
noise) carry derivative noise of 0.107 rad/s^2 (yaw acceleration), 0.134 rad/s
(steering-wheel rate) and 1.49 m/s^3 (ay rate), measured at standstill in a replayed log.
With Table 1's widths F then averaged 0.31 of F_max on the straights of handling_low_mu
(steer-rate bell alone 0.58): the heuristic was off most of the time it should be on, so
ay biases integrated on straights too. The defaults are 3 x that noise (a Gaussian bell then
loses < 6 % to noise): 0.32 rad/s^2, 0.40 rad/s and 0.9 rad/s^2 (= 3 x 1.49 / 5 m/s, the
beta-acc noise at the 20 km/h lower end of the speed range). On another car, re-derive them
from its sensors' noise the same way.

Extension, off by default (``straight_offset_time_constant`` = 0 is the paper): eq. 21
learnt with a time constant of seconds while the heuristic says "straight" (weight F / F_max),
i.e. integral action on the heuristic that keeps the straight's ay bias into the next corner.
Measured on the simulator suite it helps the sine steer and mu jump and hurts the step steer
and the banked road (it learns the bank of the straight, not of the curve), so it stays off.

Extension, ON by default (``steady_gain`` = 0 is the paper exactly): steady-state hold.
A kinematic observer integrates any Ay bias wherever F ~ 0. In a steady corner the true Vy' is
~0, so (Ay - omega_z Vx) is then bias, not sideslip: the road bank (g sin(bank), up to
1 m/s^2, invisible to eq. 16), the static roll model's error (nominal mass: +300 kg gives 7.4
instead of 9.8 deg of roll, ~0.4 m/s^2) and the unsettled eq. 21 offset (1500 s). Eq. 8's
only correction in a corner is the slow a2 eigenvalue (~(a2 + 1) omega_z^2 / (a0 + a1
|omega_z|), 0.05-0.2/s), so a bias b settles at e_y ~ (a0 + a1|omega_z|) b / ((a2 + 1)
omega_z^2): the estimate ramped ~1 m/s per second through each banked corner (-18 deg on a
-6 deg bank). The extension builds a steady indicator S: Gaussian bells (eq. 7's form) on
derivatives only -- yaw acceleration, steering-wheel rate and d/dt (Ay - omega_z Vx), from
its own 1 Hz derivative filters (``steady_cutoff_hz``; the 10 Hz ones of eq. 7 are too noisy
for bells narrow enough to see a 0.25-1 Hz manoeuvre), widths ``sigma_steady_*`` -- times a
countersteer bell (steering against the yaw rate = a drift, whose slow sideslip change is
real), rate-limited to rise in ``steady_rise_time`` = 1 s and to drop at once. Then (i)
Vy_hat' loses the fraction hold = steady_gain * S of its open-loop integrand
(Ay - omega_z Vx_hat) and hold * ``steady_hold_correction`` (0.5) of the a2 correction (which
in a corner turns an Ax bias such as the road grade into a Vy error of bias / omega_z), and
(ii) (Ay - omega_z Vx) is learnt as a bias with time constant ``steady_bias_time_constant`` =
3 s and weight S, held through the next transient and subtracted from Ay (observer and
eq. 6). Eq. 8's Lyapunov argument still holds (the e_x -> e_y coupling stays
-(a2 + 1 - hold) omega_z with a2 + 1 - hold > 0). What it rests on, and its limit: a real
sideslip change with steady steer, yaw rate and ay (a slow drift without countersteer) is
taken for bias.
Measured beta RMS [deg] on the simulator suite (``slipd eval --suite``, pre-generated logs),
paper -> extension: banked_road 7.28 -> 1.01, endurance 6.45 -> 1.00, loaded_vehicle 2.49 ->
0.34, snow_drift 5.67 -> 3.31, handling_high_mu 0.44 -> 0.36, handling_low_mu 1.06 -> 0.14,
j_turn 0.83 -> 0.26, mu_jump 0.43 -> 0.37, sine_steer 0.24 -> 0.16, slalom 0.74 -> 0.72,
step_steer 0.31 -> 0.06, straight_offsets 0.050 -> 0.033; double_lane_change 0.053 -> 0.061
(the one that got worse). Rigid-body sines (exact kinematics, no bias; paper 0.03-0.05 deg):
0.04 deg at 0.5 Hz / 0.4 rad/s, 0.26 deg at 0.25 Hz / 0.3 rad/s, 0.16 deg at 1 Hz. Sweeps:
the 10 Hz eq. 7 derivatives with 3 x wider bells gave endurance 0.94 but 1.35 deg on the
0.5 Hz rigid-body sine; widths 2 x narrower than the defaults leave banked_road at 3.2,
1.5 x wider at 0.9 but 0.2-0.6 deg on the sines; without the bias learning endurance is 1.59;
steady_hold_correction 0 / 1 trade banked_road (0.89 / 1.30) against endurance (1.13 / 0.87);
rise 0.5 s gives 0.77 / 0.93 but 0.31 deg on the 0.25 Hz sine.

Quality figure ``SIGMA_BETA`` (not in the paper; the paper has no covariance): a propagated
1-sigma of the lateral-velocity error divided by max(vx, min_speed). The variance P of
e_y = Vy_hat - Vy follows P' = -2 lambda P + q, where lambda is the decay rate of e_y in the
error dynamics (eq. 8): F on straights plus, in corners, the slow eigenvalue of the
(e_x, e_y) coupling, (a2 + 1) omega_z^2 / (a0 + a1 |omega_z|) (eq. 8 with a0 + a1|w| >> w);
q = accel_noise^2 + (accel_rel_error * Ay)^2 is the white-noise density of the ay error
(sensor noise, roll and offset residuals that grow with Ay). It says "how well has the
observer been able to correct itself lately": it grows without bound in a long low-yaw drift
where the kinematic model is unobservable and F is off, which is exactly when the estimate is
an open-loop integral. It is a calibrated heuristic, not a Bayesian posterior.

Status: NOT_CONVERGED from start/reset until the observer has run ``settle_time`` with valid
IMU and wheel speeds; UNAVAILABLE never (only IMU, wheels and steer are needed);
INPUT_TIMEOUT when ax, ay or the yaw rate, every wheel speed, or the steer is invalid;
DEGRADED when some but not all wheel speeds, or the roll rate, are invalid; RESET on the tick
the state was non-finite and was re-initialised. Invalid inputs are never integrated:
without IMU the observer holds its state; without wheel speeds it integrates the IMU open
loop (no Vx feedback, eq. 5 with K_n = 0); without steer the last valid steer is held.
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
    VALID,
    In,
    Out,
    Veh,
)
from slipd.estimators import preprocess as pp


@enum.unique
class PARAMS(enum.IntEnum):
    ALPHA_0 = 0  # 1/s, constant Vx feedback gain (Table 1: 10)
    ALPHA_1 = 1  # -, yaw-rate-scheduled Vx feedback gain (Table 1: 5)
    ALPHA_2 = 2  # -, Vx-error to Vy feedback gain (Table 1: 10)
    AX_THRESHOLD = 3  # m/s^2, Fig. 4 min/mean/max switching (Table 1: 1)
    SIGMA_W1 = 4  # m/s^2, eq. 13 width on Ax - dV_i/dt (Table 1 sigma_dw1: 4.5)
    SIGMA_W2 = 5  # m/s, eq. 13 width on Vx_prev - V_i (Table 1 sigma_dw2: 1)
    SIGMA_YAW_RATE = 6  # rad/s (Table 1: 0.18)
    SIGMA_YAW_ACC = 7  # rad/s^2, eq. 7 sigma_d_omega_z (Table 1: 0.18; default 0.32, see doc)
    SIGMA_STEER = 8  # rad, steering-wheel angle (Table 1: 0.1)
    SIGMA_STEER_RATE = 9  # rad/s, steering-wheel rate sigma_d_delta (Table 1: 0.1; default 0.40)
    SIGMA_BETA_RATE = 10  # rad/s (Table 1: 0.06)
    SIGMA_BETA_ACC = 11  # rad/s^2, sigma_d_beta_dot (Table 1: 0.3; default 0.9)
    F_GAIN = 12  # 1/s, amplitude of F (not in Table 1; eq. 7 has unit amplitude)
    DERIVATIVE_CUTOFF_HZ = 13  # Hz (section 2.1: 10)
    GYRO_OFFSET_SETTLING = 14  # s (section 4: 150)
    ACCEL_OFFSET_SETTLING = 15  # s (section 4: 1500)
    ROLL_FILTER_TIME_CONSTANT = 16  # s, complementary filter split (not in the paper)
    MIN_SPEED = 17  # m/s, "moving" and the beta denominator floor (not in the paper)
    STANDSTILL_SPEED = 18  # m/s, every wheel below it = standing still (not in the paper)
    STANDSTILL_HOLD = 19  # s of standstill before the gyro offsets learn (not in the paper)
    SETTLE_TIME = 20  # s of valid running before NOT_CONVERGED clears (not in the paper)
    SIGMA_VY_INIT = 21  # m/s, quality figure: initial lateral-velocity uncertainty
    ACCEL_NOISE = 22  # m/s^2 sqrt(s), quality figure: ay error density at Ay = 0
    ACCEL_REL_ERROR = 23  # -, quality figure: ay error density per unit of |Ay|
    STRAIGHT_OFFSET_TIME_CONSTANT = 24  # s, extension (not in the paper), 0 = off; see below
    # Steady-state hold, extension (not in the paper); STEADY_GAIN = 0 is the paper. See below.
    STEADY_GAIN = 25  # -, fraction of (Ay - omega_z Vx_hat) removed from Vy_hat' when steady
    STEADY_CUTOFF_HZ = 26  # Hz, the steady detector's own (slower) derivative filters
    SIGMA_STEADY_YAW_ACC = 27  # rad/s^2, steady bell on the yaw acceleration
    SIGMA_STEADY_STEER_RATE = 28  # rad/s, steady bell on the steering-wheel rate
    SIGMA_STEADY_JERK = 29  # m/s^3, steady bell on d/dt (Ay - omega_z Vx)
    STEADY_RISE_TIME = 30  # s, the steady indicator rises at most 1/T per second, drops at once
    STEADY_BIAS_TIME_CONSTANT = 31  # s, learning of the steady-state ay bias, 0 = no learning
    STEADY_HOLD_CORRECTION = 32  # -, share of the hold also applied to the a2 Vx-error term
    STEADY_COUNTERSTEER = 33  # -, 1: steering against the yaw rate (a drift) is never steady


#: Table 1 of Selmanaj et al. 2017, verbatim (paper symbol -> params name): alpha_0, alpha_1,
#: alpha_2; A_x^threshold; sigma_dw1, sigma_dw2 (eq. 13); sigma_omega_z, sigma_d_omega_z,
#: sigma_delta, sigma_d_delta, sigma_beta_dot, sigma_d_beta_dot (eq. 7).
TABLE_1: dict[str, float] = {
    "alpha_0": 10.0,
    "alpha_1": 5.0,
    "alpha_2": 10.0,
    "ax_threshold": 1.0,
    "sigma_w1": 4.5,
    "sigma_w2": 1.0,
    "sigma_yaw_rate": 0.18,
    "sigma_yaw_acc": 0.18,
    "sigma_steer": 0.1,
    "sigma_steer_rate": 0.1,
    "sigma_beta_rate": 0.06,
    "sigma_beta_acc": 0.3,
}

DEFAULTS: dict[str, float] = {
    # Table 1 of Selmanaj et al. 2017 ...
    **TABLE_1,
    # ... but the eq. 7 derivative widths set by the paper's own rule (section 2.1: each bell
    # wider than the noise of its signal) from the noise of this profile's sensors through the
    # 10 Hz derivative filter: 3 x 0.107 rad/s^2, 3 x 0.134 rad/s, 3 x 1.49 m/s^3 / 5 m/s.
    # Table 1's values left F at ~0.3 on noisy straights (module docstring).
    "sigma_yaw_acc": 0.32,
    "sigma_steer_rate": 0.40,
    "sigma_beta_acc": 0.9,
    # Eq. 7 is a unit-amplitude bell and Table 1 lists no gain: F_max = 1/s (a 1 s time
    # constant pulling Vy to zero on straights).
    "f_gain": 1.0,
    # Section 2.1 and section 4.
    "derivative_cutoff_hz": pp.DERIVATIVE_CUTOFF_HZ,
    "gyro_offset_settling": pp.GYRO_OFFSET_SETTLING_S,
    "accel_offset_settling": pp.ACCEL_OFFSET_SETTLING_S,
    # Not in the paper. 0.5 s: the static roll model (eq. 16) is right below the ~1.5 Hz roll
    # eigenfrequency, the gyro above it; a 0.5 deg/s roll-rate offset biases roll by 0.25 deg.
    "roll_filter_time_constant": 0.5,
    # Below 1 m/s wheel-speed sensors lose resolution and beta is ill-defined.
    "min_speed": 1.0,
    "standstill_speed": 0.05,
    "standstill_hold": 1.0,
    # 2 s = 20 time constants of the Vx loop (a0 = 10/s) and 2 of the heuristic (F = 1/s).
    "settle_time": 2.0,
    # Quality figure (see module docstring); calibrated on the simulator suite.
    "sigma_vy_init": 1.0,
    "accel_noise": 0.1,
    "accel_rel_error": 0.05,
    # Extension, not in the paper (0 reproduces the paper exactly): eq. 21 learnt fast while
    # the heuristic says "straight" (weight F / f_gain), see the module docstring.
    "straight_offset_time_constant": 0.0,
    # Extension, not in the paper (steady_gain = 0 reproduces the paper exactly): steady-state
    # hold of Vy_hat with a steady-state ay bias; every value measured on the simulator suite
    # and on rigid-body sines, see the module docstring. 1 Hz derivative filters: 10x less
    # noise than the 10 Hz ones (0.010 rad/s^2, 0.013 rad/s, 0.13-0.5 m/s^3), so the bells
    # can be narrow enough to close on any real manoeuvre (12 x that noise for the yaw
    # acceleration and steering-wheel rate). Rise 1 s: a transient's tail is over first.
    "steady_gain": 1.0,
    "steady_cutoff_hz": 1.0,
    "sigma_steady_yaw_acc": 0.12,
    "sigma_steady_steer_rate": 0.16,
    "sigma_steady_jerk": 3.2,
    "steady_rise_time": 1.0,
    "steady_bias_time_constant": 3.0,
    "steady_hold_correction": 0.5,
    "steady_countersteer": 1.0,
}


@enum.unique
class State(enum.IntEnum):
    """Layout of the state vector (blocks of ``preprocess`` start at the *_BASE slots)."""

    VX_HAT = 0  # m/s, observer longitudinal velocity (NaN until the first wheel speed)
    VY_HAT = 1  # m/s, observer lateral velocity
    RUN_TIME = 2  # s of valid running since init/reset
    P_VY = 3  # (m/s)^2, quality-figure variance of Vy_hat
    STEER_HELD = 4  # rad, last valid road-wheel steer
    VX_WHEELS = 5  # m/s, last wheel-based Vx (eq. 12 / Fig. 4)
    VX_MODE = 6  # preprocess.VxMode of the last wheel-based Vx
    F = 7  # 1/s, last heuristic gain
    BETA = 8  # rad, last output (held while the IMU is invalid)
    BETA_RATE = 9  # rad/s, last output
    D_YAW_RATE = 10  # derivative-filter memories (preprocess.FILTER_LEN each)
    D_ROLL_RATE = 11
    D_PITCH_RATE = 12
    D_STEER_WHEEL = 13
    D_BETA_RATE = 14
    D_VX = 15
    ROLL = 16  # rad, complementary-filter roll (preprocess.ROLL_LEN)
    OFFSETS_BASE = 17  # preprocess.Offsets block, OFFSETS_LEN slots
    WHEELS_BASE = OFFSETS_BASE + pp.OFFSETS_LEN  # preprocess.Wheels block, WHEELS_LEN slots
    STEADY = WHEELS_BASE + pp.WHEELS_LEN  # -, rate-limited steady-state indicator (extension)
    STEADY_BIAS = STEADY + 1  # m/s^2, ay bias learnt in steady states (extension)
    D_STEADY_YAW = STEADY + 2  # the steady detector's derivative-filter memories
    D_STEADY_STEER = STEADY + 3
    D_STEADY_RESIDUAL = STEADY + 4


STATE_LEN = State.D_STEADY_RESIDUAL + 1

# Plain ints for the kernels (numba cannot convert IntEnum members to float).
_VX_HAT, _VY_HAT, _RUN_TIME, _P_VY = 0, 1, 2, 3
_STEER_HELD, _VX_WHEELS, _VX_MODE, _F, _BETA, _BETA_RATE = 4, 5, 6, 7, 8, 9
_D_YAW_RATE, _D_ROLL_RATE, _D_PITCH_RATE = 10, 11, 12
_D_STEER_WHEEL, _D_BETA_RATE, _D_VX, _ROLL = 13, 14, 15, 16
_OFFSETS = int(State.OFFSETS_BASE)
#: State slots the daemon persists across restarts: the learned sensor offsets (and their
#: settling bookkeeping), which the paper carries over from the last drive at key-on.
PERSISTENT_STATE = tuple(range(_OFFSETS, _OFFSETS + int(pp.Offsets.STANDSTILL_TIME)))
_WHEELS = int(State.WHEELS_BASE)
_STEADY = int(State.STEADY)
_STEADY_BIAS = int(State.STEADY_BIAS)
_D_STEADY_YAW = int(State.D_STEADY_YAW)
_D_STEADY_STEER = int(State.D_STEADY_STEER)
_D_STEADY_RESIDUAL = int(State.D_STEADY_RESIDUAL)
_OFF_YAW = int(pp.Offsets.YAW_RATE)
_OFF_ROLL = int(pp.Offsets.ROLL_RATE)
_OFF_PITCH = int(pp.Offsets.PITCH_RATE)
_OFF_AX = int(pp.Offsets.AX)
_OFF_AY = int(pp.Offsets.AY)
assert _ROLL == State.ROLL and _D_VX == State.D_VX and _BETA_RATE == State.BETA_RATE


def init(params: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """The state at start or reset: filters not started (NaN), offsets 0, Vx unknown.

    Offsets learnt in an earlier run can be copied into
    ``state[State.OFFSETS_BASE:State.OFFSETS_BASE + preprocess.OFFSETS_LEN]`` (the paper
    starts each key-on from the last estimate, section 5.2).
    """
    state = np.empty(STATE_LEN, dtype=np.float64)
    _reset(state, params)
    pp.reset_offsets(state, State.OFFSETS_BASE)
    return state


@nb.njit(cache=True)
def _reset(state, params):
    """Everything but the offsets (slow estimates that survive a reset of the observer)."""
    state[_VX_HAT] = math.nan
    state[_VY_HAT] = 0.0
    state[_RUN_TIME] = 0.0
    state[_P_VY] = params[PARAMS.SIGMA_VY_INIT] ** 2
    state[_STEER_HELD] = 0.0
    state[_VX_WHEELS] = math.nan
    state[_VX_MODE] = 0.0
    state[_F] = 0.0
    state[_BETA] = 0.0
    state[_BETA_RATE] = 0.0
    for k in range(_D_YAW_RATE, _ROLL + 1):
        state[k] = math.nan
    for k in range(_WHEELS, _WHEELS + pp.WHEELS_LEN):
        state[k] = math.nan
    state[_STEADY] = 0.0
    state[_STEADY_BIAS] = 0.0
    for k in range(_D_STEADY_YAW, _D_STEADY_RESIDUAL + 1):
        state[k] = math.nan


@nb.njit(cache=True)
def step(state, u, params, vehicle, dt, out):
    """One 100 Hz tick of the Selmanaj observer; see the module docstring.

    state: float64[STATE_LEN] (``init``), u: float64[U_LEN], params: float64[len(PARAMS)],
    vehicle: float64[N_VEH], dt: s, out: float64[N_OUT] (written completely).
    """
    status = 0
    if not (math.isfinite(state[_VY_HAT]) and math.isfinite(state[_P_VY])):
        # A non-finite state cannot recover by itself: restart and say so (openpilot paramsd).
        _reset(state, params)
        status |= ST_RESET
    cutoff = params[PARAMS.DERIVATIVE_CUTOFF_HZ]
    min_speed = params[PARAMS.MIN_SPEED]

    imu_ok = u[VALID + In.AX] > 0.5 and u[VALID + In.AY] > 0.5 and u[VALID + In.YAW_RATE] > 0.5
    roll_rate_ok = u[VALID + In.ROLL_RATE] > 0.5
    pitch_rate_ok = u[VALID + In.PITCH_RATE] > 0.5
    az_ok = u[VALID + In.AZ] > 0.5
    valid_fl = u[VALID + In.WHEEL_SPEED_FL] > 0.5
    valid_fr = u[VALID + In.WHEEL_SPEED_FR] > 0.5
    valid_rl = u[VALID + In.WHEEL_SPEED_RL] > 0.5
    valid_rr = u[VALID + In.WHEEL_SPEED_RR] > 0.5
    n_wheels = int(valid_fl) + int(valid_fr) + int(valid_rl) + int(valid_rr)
    if u[VALID + In.STEER] > 0.5:
        state[_STEER_HELD] = u[In.STEER]
    else:
        status |= ST_INPUT_TIMEOUT
    steer = state[_STEER_HELD]
    if not imu_ok or n_wheels == 0:
        status |= ST_INPUT_TIMEOUT
    elif n_wheels < 4 or not roll_rate_ok:
        status |= ST_DEGRADED

    # --- standstill and gyro offsets (section 4) ----------------------------------------
    max_wheel = 0.0
    if valid_fl:
        max_wheel = max(max_wheel, abs(u[In.WHEEL_SPEED_FL]))
    if valid_fr:
        max_wheel = max(max_wheel, abs(u[In.WHEEL_SPEED_FR]))
    if valid_rl:
        max_wheel = max(max_wheel, abs(u[In.WHEEL_SPEED_RL]))
    if valid_rr:
        max_wheel = max(max_wheel, abs(u[In.WHEEL_SPEED_RR]))
    standstill_time = pp.update_standstill(
        state, _OFFSETS, max_wheel, n_wheels == 4, dt, params[PARAMS.STANDSTILL_SPEED]
    )
    learning_gyros = standstill_time >= params[PARAMS.STANDSTILL_HOLD]
    gyro_settling = params[PARAMS.GYRO_OFFSET_SETTLING]

    if not imu_ok:
        # Hold: nothing from the IMU may be integrated. Outputs repeat the last estimate.
        _write_outputs(state, params, out, status)
        return

    yaw_offset = pp.update_gyro_offset(
        state, _OFFSETS, _OFF_YAW, u[In.YAW_RATE], learning_gyros, dt, gyro_settling
    )
    yaw_rate = u[In.YAW_RATE] - yaw_offset
    roll_rate = 0.0
    pitch_rate = 0.0
    if roll_rate_ok:
        roll_offset = pp.update_gyro_offset(
            state, _OFFSETS, _OFF_ROLL, u[In.ROLL_RATE], learning_gyros, dt, gyro_settling
        )
        roll_rate = u[In.ROLL_RATE] - roll_offset
    if pitch_rate_ok:
        pitch_offset = pp.update_gyro_offset(
            state, _OFFSETS, _OFF_PITCH, u[In.PITCH_RATE], learning_gyros, dt, gyro_settling
        )
        pitch_rate = u[In.PITCH_RATE] - pitch_offset

    # --- CoG translation (section 3) ----------------------------------------------------
    yaw_acc = pp.derivative_filter(state, _D_YAW_RATE, yaw_rate, dt, cutoff)
    roll_acc = pp.derivative_filter(state, _D_ROLL_RATE, roll_rate, dt, cutoff)
    pitch_acc = pp.derivative_filter(state, _D_PITCH_RATE, pitch_rate, dt, cutoff)
    az = u[In.AZ] if az_ok else 9.81
    ax_cog, ay_cog, _ = pp.translate_to_cog(
        u[In.AX],
        u[In.AY],
        az,
        roll_rate,
        pitch_rate,
        yaw_rate,
        roll_acc,
        pitch_acc,
        yaw_acc,
        vehicle[Veh.IMU_X],
        vehicle[Veh.IMU_Y],
        vehicle[Veh.IMU_Z],
    )

    # --- roll and gravity (section 3.1, eq. 16-17) --------------------------------------
    roll_gain = pp.roll_static_gain(
        vehicle[Veh.MASS], vehicle[Veh.H_ROLL_AXIS], vehicle[Veh.ROLL_STIFFNESS]
    )
    roll = pp.roll_complementary_filter(
        state,
        _ROLL,
        ay_cog,
        roll_rate,
        roll_rate_ok,
        dt,
        roll_gain,
        params[PARAMS.ROLL_FILTER_TIME_CONSTANT],
    )
    ay_with_offset = pp.compensate_gravity_ay(ay_cog, roll)
    ax_with_offset = ax_cog  # pitch neglected, as in the paper (section 3.1)
    ax = ax_with_offset - state[_OFFSETS + _OFF_AX]
    ay = ay_with_offset - state[_OFFSETS + _OFF_AY]

    # --- Vx from the wheels (section 2.3) -----------------------------------------------
    vx_wheels, vx_mode = pp.vx_from_wheels(
        state,
        _WHEELS,
        u[In.WHEEL_SPEED_FL],
        u[In.WHEEL_SPEED_FR],
        u[In.WHEEL_SPEED_RL],
        u[In.WHEEL_SPEED_RR],
        valid_fl,
        valid_fr,
        valid_rl,
        valid_rr,
        steer,
        yaw_rate,
        ax,
        state[_VX_HAT],
        vehicle[Veh.TRACK_F],
        vehicle[Veh.TRACK_R],
        dt,
        params[PARAMS.AX_THRESHOLD],
        params[PARAMS.SIGMA_W1],
        params[PARAMS.SIGMA_W2],
    )
    state[_VX_MODE] = vx_mode
    have_vx = math.isfinite(vx_wheels)
    if have_vx:
        state[_VX_WHEELS] = vx_wheels
        if not math.isfinite(state[_VX_HAT]):
            state[_VX_HAT] = vx_wheels  # first wheel speed: start the observer there
            state[_VY_HAT] = 0.0
    if not math.isfinite(state[_VX_HAT]):
        # No speed has ever been seen: nothing to integrate from yet.
        _write_outputs(state, params, out, status | ST_NOT_CONVERGED)
        return

    # --- accelerometer offsets (section 4, Fig. 10-11, eq. 21) --------------------------
    accel_settling = params[PARAMS.ACCEL_OFFSET_SETTLING]
    if have_vx:
        dvx_dt = pp.derivative_filter(state, _D_VX, vx_wheels, dt, cutoff)
        moving = vx_wheels > min_speed
        pp.update_ax_offset(
            state,
            _OFFSETS,
            ax_with_offset,
            dvx_dt,
            pp.ax_offset_active(vx_wheels, ax_with_offset, yaw_rate, min_speed),
            dt,
            accel_settling,
        )
        pp.update_ay_offset(
            state, _OFFSETS, ay_with_offset, yaw_rate, vx_wheels, moving, dt, accel_settling
        )
        fast_tc = params[PARAMS.STRAIGHT_OFFSET_TIME_CONSTANT]
        if fast_tc > 0.0 and moving and params[PARAMS.F_GAIN] > 0.0:
            # Extension: integral action of the heuristic. On a straight (F ~ F_max) eq. 21's
            # residual is offset + bank; learn it in seconds, hold it (F ~ 0) in the corner.
            weight = state[_F] / params[PARAMS.F_GAIN]
            gain = min(dt * weight / fast_tc, 1.0)
            slot = _OFFSETS + _OFF_AY
            state[slot] += gain * (ay_with_offset - yaw_rate * vx_wheels - state[slot])

    vx_hat = state[_VX_HAT]
    vy_hat = state[_VY_HAT]
    vx_meas = vx_wheels if have_vx else vx_hat
    speed_floor = max(vx_meas, min_speed)

    # --- heuristic F (section 2.1, eq. 6-7) ---------------------------------------------
    steer_wheel = steer * vehicle[Veh.STEER_RATIO]
    steer_wheel_rate = pp.derivative_filter(state, _D_STEER_WHEEL, steer_wheel, dt, cutoff)
    ay_raw = ay
    ay = ay - state[_STEADY_BIAS]  # extension: steady-state ay bias (0 when off)
    beta_rate_meas = (ay - yaw_rate * vx_meas) / speed_floor  # eq. 6
    beta_acc_meas = pp.derivative_filter(state, _D_BETA_RATE, beta_rate_meas, dt, cutoff)
    f_heuristic = (
        params[PARAMS.F_GAIN]
        * pp.gaussian_bell(
            yaw_rate, params[PARAMS.SIGMA_YAW_RATE], yaw_acc, params[PARAMS.SIGMA_YAW_ACC]
        )
        * pp.gaussian_bell(
            steer_wheel,
            params[PARAMS.SIGMA_STEER],
            steer_wheel_rate,
            params[PARAMS.SIGMA_STEER_RATE],
        )
        * pp.gaussian_bell(
            beta_rate_meas,
            params[PARAMS.SIGMA_BETA_RATE],
            beta_acc_meas,
            params[PARAMS.SIGMA_BETA_ACC],
        )
    )
    if vx_meas < min_speed:
        # Not in the paper: at walking pace Ay and omega_z carry no sideslip information and
        # a parked car with the wheel turned would otherwise integrate the ay offset.
        f_heuristic = params[PARAMS.F_GAIN]
    state[_F] = f_heuristic

    # --- extension: steady-state hold (not in the paper; module docstring) ---------------
    # S = bells (eq. 7's form) on derivatives only (no value terms: a steady corner is steady),
    # from the detector's own 1 Hz derivative filters, closed by countersteer (a drift),
    # rate-limited on the way up, instant on the way down.
    hold = 0.0
    steady_gain = params[PARAMS.STEADY_GAIN]
    if steady_gain > 0.0:
        steady_cutoff = params[PARAMS.STEADY_CUTOFF_HZ]
        residual = ay_raw - yaw_rate * vx_meas
        yaw_acc_slow = pp.derivative_filter(state, _D_STEADY_YAW, yaw_rate, dt, steady_cutoff)
        steer_rate_slow = pp.derivative_filter(state, _D_STEADY_STEER, steer_wheel, dt,
                                               steady_cutoff)
        residual_rate = pp.derivative_filter(state, _D_STEADY_RESIDUAL, residual, dt,
                                             steady_cutoff)
        countersteer = 0.0
        if params[PARAMS.STEADY_COUNTERSTEER] > 0.0 and steer_wheel * yaw_rate < 0.0:
            countersteer = steer_wheel
        steady_now = pp.gaussian_bell(
            yaw_acc_slow, params[PARAMS.SIGMA_STEADY_YAW_ACC],
            steer_rate_slow, params[PARAMS.SIGMA_STEADY_STEER_RATE],
        ) * pp.gaussian_bell(
            residual_rate, params[PARAMS.SIGMA_STEADY_JERK],
            countersteer, params[PARAMS.SIGMA_STEER],
        )
        if not math.isfinite(steady_now) or not have_vx or vx_meas < min_speed:
            steady_now = 0.0
        rise_time = params[PARAMS.STEADY_RISE_TIME]
        steady = state[_STEADY]
        if rise_time > 0.0:
            steady = min(steady_now, steady + dt / rise_time)
        else:
            steady = steady_now
        state[_STEADY] = steady
        hold = min(steady_gain, 1.0) * steady
        bias_tc = params[PARAMS.STEADY_BIAS_TIME_CONSTANT]
        if bias_tc > 0.0 and steady > 0.0:
            # Steady: the true Vy' ~ 0, so Ay - omega_z Vx is bias (bank, roll model, offset).
            # Learnt with weight S, held through the next transient, re-learnt at the next
            # steady state; subtracted from Ay above (observer and eq. 6).
            gain = min(dt * steady / bias_tc, 1.0)
            state[_STEADY_BIAS] += gain * (residual - state[_STEADY_BIAS])

    # --- observer (eq. 5), forward Euler at the tick rate ------------------------------
    if have_vx:
        gain_x = params[PARAMS.ALPHA_0] + params[PARAMS.ALPHA_1] * abs(yaw_rate)
        gain_y = params[PARAMS.ALPHA_2] * yaw_rate
        vx_error = vx_hat - vx_meas
    else:
        gain_x = 0.0  # no measurement: K_n = 0, open-loop kinematic model
        gain_y = 0.0
        vx_error = 0.0
    vx_dot = -gain_x * vx_error + yaw_rate * vy_hat + ax
    # Eq. 5; with the extension the open-loop integrand (Ay - omega_z Vx_hat) is scaled by
    # 1 - hold and the a2 correction by 1 - hold * steady_hold_correction (both 1 = the paper).
    hold_c = 1.0 - hold * params[PARAMS.STEADY_HOLD_CORRECTION]
    vy_dot = (
        (1.0 - hold) * (ay - yaw_rate * vx_hat)
        - hold_c * gain_y * vx_error
        - f_heuristic * vy_hat
    )
    vx_hat += dt * vx_dot
    vy_hat += dt * vy_dot
    state[_VX_HAT] = vx_hat
    state[_VY_HAT] = vy_hat

    # --- quality figure (module docstring) ----------------------------------------------
    decay = f_heuristic
    if have_vx:
        decay += (params[PARAMS.ALPHA_2] + 1.0) * yaw_rate * yaw_rate / gain_x
    rel = params[PARAMS.ACCEL_REL_ERROR] * ay
    noise = params[PARAMS.ACCEL_NOISE]
    q = noise * noise + rel * rel
    p_vy = state[_P_VY]
    p_vy += dt * (q - 2.0 * decay * p_vy)
    state[_P_VY] = max(p_vy, 0.0)

    # --- outputs --------------------------------------------------------------------------
    vx_den = max(vx_hat, min_speed)
    state[_BETA] = math.atan2(vy_hat, vx_den)
    # d/dt atan2(vy, vx) from the observer's own derivatives (eq. 5), not the raw eq. 6.
    state[_BETA_RATE] = (vx_den * vy_dot - vy_hat * vx_dot) / (vx_den * vx_den + vy_hat * vy_hat)
    if have_vx:
        state[_RUN_TIME] += dt
    if state[_RUN_TIME] < params[PARAMS.SETTLE_TIME]:
        status |= ST_NOT_CONVERGED
    if not (math.isfinite(vx_hat) and math.isfinite(vy_hat)):
        _reset(state, params)
        status |= ST_RESET | ST_NOT_CONVERGED
    _write_outputs(state, params, out, status)


@nb.njit(cache=True)
def _write_outputs(state, params, out, status):
    out[Out.BETA] = state[_BETA]
    out[Out.BETA_RATE] = state[_BETA_RATE]
    # Before the first wheel speed vx is unknown: 0 with NOT_CONVERGED, never NaN on the bus.
    out[Out.VX] = state[_VX_HAT] if math.isfinite(state[_VX_HAT]) else 0.0
    out[Out.VY] = state[_VY_HAT]
    out[Out.MU] = math.nan  # the method does not estimate friction
    vx_den = (
        state[_VX_HAT] if state[_VX_HAT] > params[PARAMS.MIN_SPEED] else params[PARAMS.MIN_SPEED]
    )
    out[Out.SIGMA_BETA] = math.sqrt(state[_P_VY]) / vx_den
    out[Out.ROLL] = state[_ROLL] if math.isfinite(state[_ROLL]) else 0.0
    out[Out.FRICTION_CLASS] = 0.0
    out[Out.STATUS] = float(status)


@nb.njit(cache=True)
def run_ticks(state, U, params, vehicle, dt, OUT):
    """Batch loop: ``step`` on every row of ``U`` (n, U_LEN) into ``OUT`` (n, N_OUT)."""
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])
