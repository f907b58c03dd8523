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

Preprocessing (section 3, Fig. 6; ``slipd.estimators.common``): gyro offsets at standstill,
CoG translation of the accelerations (full rigid body, IMU position from the profile),
roll by complementary filter of the static roll model and the roll rate (eq. 16, Fig. 9),
gravity compensation of ay (eq. 17), ax and ay offsets (Fig. 10, eq. 21) and Vx from the
compensated wheel speeds (eq. 11-13, Fig. 4). The paper neglects pitch (section 3.1), so
does this module.

Sign conventions: everything is ISO 8855 (the paper's eq. 11 and 16 are printed in the
paper's own signs; the common blocks' docstrings say how they were converted). The heuristic's
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
On the simulator suite it helps the sine steer and mu jump and hurts the step steer and
the banked road (it learns the bank of the straight, not of the curve), so it stays off.

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
real), rate-limited to rise in ``steady_rise_time`` = 1 s and to drop at once. The jerk bell's
width follows the paper's own rule for its bells online: at least ``steady_jerk_noise_width``
= 12 x the jerk's RMS on straights (``common.filters.noise_power``), since a raw IMU's body
vibration (~1 m/s^2) otherwise keeps knocking it shut and the hold flickers. Then (i)
Vy_hat' loses the fraction hold = steady_gain * S of its open-loop integrand
(Ay - omega_z Vx_hat) and hold * ``steady_hold_correction`` (0.5) of the a2 correction (which
in a corner turns an Ax bias such as the road grade into a Vy error of bias / omega_z), and
(ii) (Ay - omega_z Vx) is learnt as a bias with time constant ``steady_bias_time_constant`` =
3 s and weight S, held through the next transient and subtracted from Ay (observer and
eq. 6). On a straight it fades with the heuristic's weight F / F_max and the time constant
``steady_bias_straight_forget`` = 1 s (F_max's own): a bank belongs to its corner, and a bias
held into the next corner of a track (the real revs_250lm run: +0.2 m/s^2 learnt in one
corner, subtracted through the next two) is an error of its own (0 = held until re-learnt).
Eq. 8's Lyapunov argument still holds (the e_x -> e_y coupling stays -(a2 + 1 - hold) omega_z
with a2 + 1 - hold > 0). What it rests on, and its limit: a real
sideslip change with steady steer, yaw rate and ay (a slow drift without countersteer) is
taken for bias.
Measured on the simulator suite (benchmarks/MEASUREMENTS.md): it takes the banked road,
the endurance drive and the loaded car from several degrees of beta RMS to about one or less
and costs a few hundredths of a degree on the double lane change.

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

import math

import numpy as np

from slipd.channels import (
    ST_DEGRADED,
    ST_INPUT_TIMEOUT,
    ST_NOT_CONVERGED,
    ST_RESET,
    In,
    Veh,
)
from slipd.estimators.common.filters import (
    derivative_filter,
    gaussian_bell,
    noise_power,
    straight_settled,
)
from slipd.estimators.common.inputs import (
    LEARNT_OFFSETS,
    LOWPASS_END,
    LOWPASS_FIRST,
    ImuMemory,
    Offsets,
    accel_carries_gravity,
    ax_offset_active,
    channel,
    corner_speed_mean,
    hold_last,
    imu_at_cog,
    reset_offsets,
    update_ax_offset,
    update_ay_offset,
    update_gyro_offset,
    update_standstill,
    wheel_speeds,
)
from slipd.estimators.common.kinematics import remove_roll_gravity
from slipd.estimators.common.layout import build_layout
from slipd.estimators.common.outputs import write_outputs
from slipd.estimators.selmanaj2017.params import DEFAULTS, PARAMS, TABLE_1
from slipd.estimators.selmanaj2017.wheel_speed import Wheels, vx_from_wheels
from slipd.numba_cache import nb

#: The state vector (common.layout). IMU: the CoG translation's derivative filters, the roll
#: of the gravity compensation and the held steer (its LAST_AX is unused: without the IMU the
#: observer holds everything).
LAYOUT = build_layout(
    "kinematic_heuristic",
    "VX_HAT",  # m/s, observer longitudinal velocity (NaN until the first wheel speed)
    "VY_HAT",  # m/s, observer lateral velocity
    "RUN_TIME",  # s of valid running since init/reset
    "P_VY",  # (m/s)^2, quality-figure variance of Vy_hat
    "VX_WHEELS",  # m/s, last wheel-based Vx (eq. 12 / Fig. 4)
    "VX_MODE",  # wheel_speed.VxMode of the last wheel-based Vx
    "F",  # 1/s, last heuristic gain
    "BETA",  # rad, last output (held while the IMU is invalid)
    "BETA_RATE",  # rad/s, last output
    ("IMU", ImuMemory),
    "D_STEER_WHEEL",  # derivative-filter memories of eq. 6-7 and of the Vx offset logic
    "D_BETA_RATE",
    "D_VX",
    ("OFFSETS", Offsets),  # learnt at standstill and on the move (section 4)
    ("WHEELS", Wheels),  # eq. 13's derivative filters
    "STEADY",  # -, rate-limited steady-state indicator (extension)
    "STEADY_BIAS",  # m/s^2, ay bias learnt in steady states (extension)
    "D_STEADY_YAW",  # the steady detector's derivative-filter memories
    "D_STEADY_STEER",
    "D_STEADY_RESIDUAL",
    "STRAIGHT_TIME",  # s the yaw rate has stayed below noise_straight_yaw_rate
    "JERK_NOISE",  # (m/s^3)^2, the steady detector's d/dt (Ay - omega_z Vx) on straights (NaN)
)
S = LAYOUT.S
#: Kept across restarts by the daemon: the learnt sensor offsets, which the paper carries over
#: from the last drive at key-on (section 5.2).
PERSISTENT = LEARNT_OFFSETS
_IMU = int(S.IMU)
_OFFSETS = int(S.OFFSETS)
_ROLL = _IMU + int(ImuMemory.ROLL)
_STEER_HELD = _IMU + int(ImuMemory.LAST_STEER)
_GRAVITY = _IMU + int(ImuMemory.GRAVITY_W)  # learn_gravity_share's moments
_WHEELS = int(S.WHEELS)
_N_WHEELS = len(Wheels)
_DERIVATIVES = (int(S.D_STEER_WHEEL), int(S.D_VX) + 1)  # slots [first, stop)
_STEADY_DERIVATIVES = (int(S.D_STEADY_YAW), int(S.D_STEADY_RESIDUAL) + 1)


def init(params: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """The state at start or reset: filters not started (NaN), offsets 0, Vx unknown.

    Offsets learnt in an earlier run can be copied into the OFFSETS block (the paper starts
    each key-on from the last estimate, section 5.2; the daemon does it by ``PERSISTENT``).
    """
    state = np.zeros(LAYOUT.size, dtype=np.float64)  # learnt blocks start empty (0)
    _reset(state, params)
    reset_offsets(state, _OFFSETS)
    state[S.JERK_NOISE] = math.nan  # the sensors' noise outlives a reset of the observer
    return state


@nb.njit(cache=True, _nrt=False)
def _reset(state, params):
    """Everything but the offsets (slow estimates that survive a reset of the observer)."""
    state[S.VX_HAT] = math.nan
    state[S.VY_HAT] = 0.0
    state[S.RUN_TIME] = 0.0
    state[S.P_VY] = params[PARAMS.SIGMA_VY_INIT] ** 2
    state[S.VX_WHEELS] = math.nan
    state[S.VX_MODE] = 0.0
    state[S.F] = 0.0
    state[S.BETA] = 0.0
    state[S.BETA_RATE] = 0.0
    for k in range(_IMU, _ROLL + 1):
        state[k] = math.nan
    state[_IMU + ImuMemory.LAST_AX] = 0.0
    state[_STEER_HELD] = 0.0
    for k in range(_IMU + LOWPASS_FIRST, _IMU + LOWPASS_END):
        state[k] = math.nan  # the ax, ay and yaw-rate low-pass filters restart
    for k in range(_DERIVATIVES[0], _DERIVATIVES[1]):
        state[k] = math.nan
    for k in range(_WHEELS, _WHEELS + _N_WHEELS):
        state[k] = math.nan
    state[S.STEADY] = 0.0
    state[S.STEADY_BIAS] = 0.0
    for k in range(_STEADY_DERIVATIVES[0], _STEADY_DERIVATIVES[1]):
        state[k] = math.nan
    state[S.STRAIGHT_TIME] = 0.0


# ---------------------------------------------------------------------------------------------
# stages of a tick
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True, inline="always")
def _check_inputs(state, u, params, dt, status):
    """Which inputs are usable, the held steer, the standstill timer (section 4) and the status
    bits they imply (module docstring). Returns (status, imu_ok, roll_rate_ok, pitch_rate_ok,
    steer, learning_gyros, wheel speeds, wheel flags)."""
    ax_ok = channel(u, In.AX)[1]
    ay_ok = channel(u, In.AY)[1]
    yaw_ok = channel(u, In.YAW_RATE)[1]
    imu_ok = ax_ok and ay_ok and yaw_ok
    roll_rate_ok = channel(u, In.ROLL_RATE)[1]
    pitch_rate_ok = channel(u, In.PITCH_RATE)[1]
    v_fl, v_fr, v_rl, v_rr, ok_fl, ok_fr, ok_rl, ok_rr = wheel_speeds(u)
    n_wheels = int(ok_fl) + int(ok_fr) + int(ok_rl) + int(ok_rr)
    steer, steer_ok = channel(u, In.STEER)
    steer = hold_last(state, _STEER_HELD, steer, steer_ok)
    if not steer_ok:
        status |= ST_INPUT_TIMEOUT
    if not imu_ok or n_wheels == 0:
        status |= ST_INPUT_TIMEOUT
    elif n_wheels < 4 or not roll_rate_ok:
        status |= ST_DEGRADED
    max_wheel = 0.0
    if ok_fl:
        max_wheel = max(max_wheel, abs(v_fl))
    if ok_fr:
        max_wheel = max(max_wheel, abs(v_fr))
    if ok_rl:
        max_wheel = max(max_wheel, abs(v_rl))
    if ok_rr:
        max_wheel = max(max_wheel, abs(v_rr))
    standstill_time = update_standstill(state, _OFFSETS, max_wheel, n_wheels == 4, dt,
                                        params[PARAMS.STANDSTILL_SPEED])  # fmt: skip
    learning_gyros = standstill_time >= params[PARAMS.STANDSTILL_HOLD]
    return (status, imu_ok, roll_rate_ok, pitch_rate_ok, steer, learning_gyros,
            v_fl, v_fr, v_rl, v_rr, ok_fl, ok_fr, ok_rl, ok_rr)


@nb.njit(cache=True, inline="always")
def _corrected_rate(state, u, ch, offset_slot, ok, learning, dt, settling):
    """A gyro channel minus its standstill offset (which it learns while ``learning``);
    0 where the channel is invalid."""
    if not ok:
        return 0.0
    return u[ch] - update_gyro_offset(state, _OFFSETS, offset_slot, u[ch], learning, dt,
                                      settling)  # fmt: skip


@nb.njit(cache=True, inline="always")
def _accelerations(state, u, params, vehicle, dt, roll_rate_ok, pitch_rate_ok, learning):
    """Sections 3-4 up to the accelerometer offsets: gyro offsets learnt at standstill and
    removed, accelerations moved to the CoG (rigid body), roll by the complementary filter and
    its gravity removed from ay (eq. 16-17; pitch neglected, as in the paper, section 3.1).
    Returns (ax_with_offset, ay_with_offset, yaw_rate, yaw_acc)."""
    settling = params[PARAMS.GYRO_OFFSET_SETTLING]
    yaw_rate = _corrected_rate(state, u, In.YAW_RATE, Offsets.YAW_RATE, True, learning, dt,
                               settling)  # fmt: skip
    roll_rate = _corrected_rate(state, u, In.ROLL_RATE, Offsets.ROLL_RATE, roll_rate_ok,
                                learning, dt, settling)  # fmt: skip
    pitch_rate = _corrected_rate(state, u, In.PITCH_RATE, Offsets.PITCH_RATE, pitch_rate_ok,
                                 learning, dt, settling)  # fmt: skip
    ax_cog, ay_cog, yaw_rate, yaw_acc, _, _ = imu_at_cog(
        state, _IMU, u, yaw_rate, roll_rate, pitch_rate, dt,
        params[PARAMS.DERIVATIVE_CUTOFF_HZ], vehicle, True, params[PARAMS.ACCEL_LOWPASS_HZ],
    )  # fmt: skip
    vx, _ = corner_speed_mean(u, state[_STEER_HELD], yaw_rate, vehicle)
    learn_at = _GRAVITY if params[PARAMS.ROLL_GAIN_LEARNING] > 0.5 else -1
    ay_with_offset = remove_roll_gravity(state, _ROLL, ay_cog, roll_rate, roll_rate_ok, dt,
                                         vehicle, accel_carries_gravity(u, vehicle),
                                         params[PARAMS.ROLL_FILTER_TIME_CONSTANT],
                                         learn_at, yaw_rate, yaw_acc, vx)  # fmt: skip
    return ax_cog, ay_with_offset, yaw_rate, yaw_acc


@nb.njit(cache=True, inline="always")
def _learn_accel_offsets(state, params, ax_with_offset, ay_with_offset, yaw_rate, vx_wheels,
                         dt):  # fmt: skip
    """Section 4, Fig. 10-11, eq. 21 (and the fast straight-line extension, off by default)."""
    min_speed = params[PARAMS.MIN_SPEED]
    settling = params[PARAMS.ACCEL_OFFSET_SETTLING]
    dvx_dt = derivative_filter(state, S.D_VX, vx_wheels, dt, params[PARAMS.DERIVATIVE_CUTOFF_HZ])
    moving = vx_wheels > min_speed
    update_ax_offset(state, _OFFSETS, ax_with_offset, dvx_dt,
                     ax_offset_active(vx_wheels, ax_with_offset, yaw_rate, min_speed), dt,
                     settling)  # fmt: skip
    update_ay_offset(state, _OFFSETS, ay_with_offset, yaw_rate, vx_wheels, moving, dt, settling)
    fast_tc = params[PARAMS.STRAIGHT_OFFSET_TIME_CONSTANT]
    if fast_tc > 0.0 and moving and params[PARAMS.F_GAIN] > 0.0:
        # Extension: integral action of the heuristic. On a straight (F ~ F_max) eq. 21's
        # residual is offset + bank; learn it in seconds, hold it (F ~ 0) in the corner.
        weight = state[S.F] / params[PARAMS.F_GAIN]
        gain = min(dt * weight / fast_tc, 1.0)
        slot = _OFFSETS + Offsets.AY
        state[slot] += gain * (ay_with_offset - yaw_rate * vx_wheels - state[slot])


@nb.njit(cache=True, inline="always")
def straight_heuristic(f_gain, yaw_rate, yaw_acc, steer_wheel, steer_wheel_rate, beta_rate,
                       beta_acc, sigma_yaw_rate, sigma_yaw_acc, sigma_steer, sigma_steer_rate,
                       sigma_beta_rate, sigma_beta_acc):  # fmt: skip
    """F of section 2.1 (eq. 7): F_gain times three bivariate Gaussian bells, each on a signal
    and its derivative (yaw rate, steering-wheel angle, the sideslip rate of eq. 6); 1/s."""
    return (
        f_gain
        * gaussian_bell(yaw_rate, sigma_yaw_rate, yaw_acc, sigma_yaw_acc)
        * gaussian_bell(steer_wheel, sigma_steer, steer_wheel_rate, sigma_steer_rate)
        * gaussian_bell(beta_rate, sigma_beta_rate, beta_acc, sigma_beta_acc)
    )


@nb.njit(cache=True, inline="always")
def _heuristic(state, params, steer_wheel, yaw_rate, yaw_acc, ay, vx_meas, dt):
    """Eq. 6-7 with their derivative filters; returns F (1/s), also kept in state[F]."""
    cutoff = params[PARAMS.DERIVATIVE_CUTOFF_HZ]
    min_speed = params[PARAMS.MIN_SPEED]
    steer_wheel_rate = derivative_filter(state, S.D_STEER_WHEEL, steer_wheel, dt, cutoff)
    beta_rate_meas = (ay - yaw_rate * vx_meas) / max(vx_meas, min_speed)  # eq. 6
    beta_acc_meas = derivative_filter(state, S.D_BETA_RATE, beta_rate_meas, dt, cutoff)
    f_heuristic = straight_heuristic(
        params[PARAMS.F_GAIN], yaw_rate, yaw_acc, steer_wheel, steer_wheel_rate,
        beta_rate_meas, beta_acc_meas, params[PARAMS.SIGMA_YAW_RATE],
        params[PARAMS.SIGMA_YAW_ACC], params[PARAMS.SIGMA_STEER],
        params[PARAMS.SIGMA_STEER_RATE], params[PARAMS.SIGMA_BETA_RATE],
        params[PARAMS.SIGMA_BETA_ACC],
    )  # fmt: skip
    if vx_meas < min_speed:
        # Not in the paper: at walking pace Ay and omega_z carry no sideslip information and
        # a parked car with the wheel turned would otherwise integrate the ay offset.
        f_heuristic = params[PARAMS.F_GAIN]
    state[S.F] = f_heuristic
    return f_heuristic


@nb.njit(cache=True, inline="always")
def _jerk_width(state, params, residual_rate, yaw_rate, moving, dt):
    """The steady detector's jerk-bell width by the paper's rule for its bells (section 2.1:
    wider than the noise of the signal), applied online: max(``sigma_steady_jerk``,
    ``steady_jerk_noise_width`` x the RMS of d/dt (Ay - omega_z Vx) on straights: moving,
    |omega_z| below ``noise_straight_yaw_rate`` for ``filters.STRAIGHT_SETTLE`` s). The one
    bell on an accelerometer signal: a raw IMU's body vibration reaches it, not the gyro's
    and the steering's (their signals on straights are driving as much as noise)."""
    multiple = params[PARAMS.STEADY_JERK_NOISE_WIDTH]
    sigma = params[PARAMS.SIGMA_STEADY_JERK]
    if not multiple > 0.0:
        return sigma
    straight = moving and abs(yaw_rate) < params[PARAMS.NOISE_STRAIGHT_YAW_RATE]
    power = noise_power(state, S.JERK_NOISE, residual_rate,
                        straight_settled(state, S.STRAIGHT_TIME, straight, dt), dt,
                        params[PARAMS.NOISE_TIME_CONSTANT])  # fmt: skip
    if not math.isfinite(power):
        return sigma
    return max(sigma, multiple * math.sqrt(power))


@nb.njit(cache=True, inline="always")
def _steady_hold(state, params, ay_raw, yaw_rate, vx_meas, steer_wheel, have_vx, dt):
    """Extension (module docstring): the steady indicator S, the steady-state ay bias it
    learns, and the share of the open-loop integrand it holds. Returns hold (0 = the paper).

    S = bells (eq. 7's form) on derivatives only (no value terms: a steady corner is steady),
    from the detector's own 1 Hz derivative filters, closed by countersteer (a drift),
    rate-limited on the way up, instant on the way down."""
    steady_gain = params[PARAMS.STEADY_GAIN]
    if not steady_gain > 0.0:
        return 0.0
    steady_cutoff = params[PARAMS.STEADY_CUTOFF_HZ]
    residual = ay_raw - yaw_rate * vx_meas
    yaw_acc_slow = derivative_filter(state, S.D_STEADY_YAW, yaw_rate, dt, steady_cutoff)
    steer_rate_slow = derivative_filter(state, S.D_STEADY_STEER, steer_wheel, dt, steady_cutoff)
    residual_rate = derivative_filter(state, S.D_STEADY_RESIDUAL, residual, dt, steady_cutoff)
    countersteer = 0.0
    if params[PARAMS.STEADY_COUNTERSTEER] > 0.0 and steer_wheel * yaw_rate < 0.0:
        countersteer = steer_wheel
    moving = have_vx and vx_meas > params[PARAMS.MIN_SPEED]
    steady_now = gaussian_bell(
        yaw_acc_slow, params[PARAMS.SIGMA_STEADY_YAW_ACC],
        steer_rate_slow, params[PARAMS.SIGMA_STEADY_STEER_RATE],
    ) * gaussian_bell(
        residual_rate, _jerk_width(state, params, residual_rate, yaw_rate, moving, dt),
        countersteer, params[PARAMS.SIGMA_STEER],
    )  # fmt: skip
    if not math.isfinite(steady_now) or not have_vx or vx_meas < params[PARAMS.MIN_SPEED]:
        steady_now = 0.0
    rise_time = params[PARAMS.STEADY_RISE_TIME]
    steady = state[S.STEADY]
    if rise_time > 0.0:
        steady = min(steady_now, steady + dt / rise_time)
    else:
        steady = steady_now
    state[S.STEADY] = steady
    bias_tc = params[PARAMS.STEADY_BIAS_TIME_CONSTANT]
    if bias_tc > 0.0 and steady > 0.0:
        # Steady: the true Vy' ~ 0, so Ay - omega_z Vx is bias (bank, roll model, offset).
        # Learnt with weight S, held through the next transient, re-learnt at the next
        # steady state; subtracted from Ay (observer and eq. 6) from the next tick on.
        gain = min(dt * steady / bias_tc, 1.0)
        state[S.STEADY_BIAS] += gain * (residual - state[S.STEADY_BIAS])
    forget = params[PARAMS.STEADY_BIAS_STRAIGHT_FORGET]
    if forget > 0.0 and params[PARAMS.F_GAIN] > 0.0:
        weight = state[S.F] / params[PARAMS.F_GAIN]
        state[S.STEADY_BIAS] -= min(dt * weight / forget, 1.0) * state[S.STEADY_BIAS]
    return min(steady_gain, 1.0) * steady


@nb.njit(cache=True, inline="always")
def observer_derivatives(vx_hat, vy_hat, vx_meas, have_vx, yaw_rate, ax, ay, alpha_0, alpha_1,
                         alpha_2, f_heuristic, hold, hold_correction):  # fmt: skip
    """Eq. 5: the observer's (Vx_hat', Vy_hat') and the Vx gain a0 + a1 |omega_z|.

    Without a wheel-based Vx the gains K_n are 0 (the open-loop kinematic model). With the
    steady-state extension the open-loop integrand (Ay - omega_z Vx_hat) is scaled by 1 - hold
    and the a2 correction by 1 - hold * hold_correction (hold = 0: the paper)."""
    if have_vx:
        gain_x = alpha_0 + alpha_1 * abs(yaw_rate)
        gain_y = alpha_2 * yaw_rate
        vx_error = vx_hat - vx_meas
    else:
        gain_x = 0.0  # no measurement: K_n = 0, open-loop kinematic model
        gain_y = 0.0
        vx_error = 0.0
    vx_dot = -gain_x * vx_error + yaw_rate * vy_hat + ax
    hold_c = 1.0 - hold * hold_correction
    vy_dot = (1.0 - hold) * (ay - yaw_rate * vx_hat) - hold_c * gain_y * vx_error \
        - f_heuristic * vy_hat
    return vx_dot, vy_dot, gain_x


@nb.njit(cache=True, inline="always")
def _propagate_quality(state, params, f_heuristic, yaw_rate, gain_x, have_vx, ay, dt):
    """The quality figure's variance P' = q - 2 lambda P (module docstring)."""
    decay = f_heuristic
    if have_vx:
        decay += (params[PARAMS.ALPHA_2] + 1.0) * yaw_rate * yaw_rate / gain_x
    rel = params[PARAMS.ACCEL_REL_ERROR] * ay
    noise = params[PARAMS.ACCEL_NOISE]
    q = noise * noise + rel * rel
    p_vy = state[S.P_VY]
    p_vy += dt * (q - 2.0 * decay * p_vy)
    state[S.P_VY] = max(p_vy, 0.0)


# ---------------------------------------------------------------------------------------------
# the tick
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True, _nrt=False)
def step(state, u, params, vehicle, dt, out):
    """One 100 Hz tick of the Selmanaj observer; see the module docstring.

    state: float64[LAYOUT.size] (``init``), u: float64[U_LEN], params: float64[len(PARAMS)],
    vehicle: float64[N_VEH], dt: s, out: float64[N_OUT] (written completely).
    """
    status = 0
    if not (math.isfinite(state[S.VY_HAT]) and math.isfinite(state[S.P_VY])):
        # A non-finite state cannot recover by itself: restart and say so (openpilot paramsd).
        _reset(state, params)
        status |= ST_RESET
    min_speed = params[PARAMS.MIN_SPEED]
    (status, imu_ok, roll_rate_ok, pitch_rate_ok, steer, learning_gyros,
     v_fl, v_fr, v_rl, v_rr, ok_fl, ok_fr, ok_rl, ok_rr) = _check_inputs(
        state, u, params, dt, status)  # fmt: skip
    if not imu_ok:
        # Hold: nothing from the IMU may be integrated. Outputs repeat the last estimate.
        _write(state, params, out, status)
        return
    ax_with_offset, ay_with_offset, yaw_rate, yaw_acc = _accelerations(
        state, u, params, vehicle, dt, roll_rate_ok, pitch_rate_ok, learning_gyros
    )
    ax = ax_with_offset - state[_OFFSETS + Offsets.AX]
    ay = ay_with_offset - state[_OFFSETS + Offsets.AY]

    # --- Vx from the wheels (section 2.3) -----------------------------------------------
    vx_wheels, vx_mode = vx_from_wheels(
        state, S.WHEELS, v_fl, v_fr, v_rl, v_rr, ok_fl, ok_fr, ok_rl, ok_rr, steer, yaw_rate,
        ax, state[S.VX_HAT], vehicle[Veh.TRACK_F], vehicle[Veh.TRACK_R], dt,
        params[PARAMS.AX_THRESHOLD], params[PARAMS.SIGMA_W1], params[PARAMS.SIGMA_W2],
    )  # fmt: skip
    state[S.VX_MODE] = vx_mode
    have_vx = math.isfinite(vx_wheels)
    if have_vx:
        state[S.VX_WHEELS] = vx_wheels
        if not math.isfinite(state[S.VX_HAT]):
            state[S.VX_HAT] = vx_wheels  # first wheel speed: start the observer there
            state[S.VY_HAT] = 0.0
    if not math.isfinite(state[S.VX_HAT]):
        # No speed has ever been seen: nothing to integrate from yet.
        _write(state, params, out, status | ST_NOT_CONVERGED)
        return
    if have_vx:
        _learn_accel_offsets(state, params, ax_with_offset, ay_with_offset, yaw_rate,
                             vx_wheels, dt)  # fmt: skip
    vx_hat = state[S.VX_HAT]
    vy_hat = state[S.VY_HAT]
    vx_meas = vx_wheels if have_vx else vx_hat

    # --- heuristic F (section 2.1, eq. 6-7) and the steady-state hold (extension) --------
    steer_wheel = steer * vehicle[Veh.STEER_RATIO]
    ay_raw = ay
    ay = ay - state[S.STEADY_BIAS]  # extension: steady-state ay bias (0 when off)
    f_heuristic = _heuristic(state, params, steer_wheel, yaw_rate, yaw_acc, ay, vx_meas, dt)
    hold = _steady_hold(state, params, ay_raw, yaw_rate, vx_meas, steer_wheel, have_vx, dt)

    # --- observer (eq. 5), forward Euler at the tick rate ------------------------------
    vx_dot, vy_dot, gain_x = observer_derivatives(
        vx_hat, vy_hat, vx_meas, have_vx, yaw_rate, ax, ay, params[PARAMS.ALPHA_0],
        params[PARAMS.ALPHA_1], params[PARAMS.ALPHA_2], f_heuristic, hold,
        params[PARAMS.STEADY_HOLD_CORRECTION],
    )  # fmt: skip
    vx_hat += dt * vx_dot
    vy_hat += dt * vy_dot
    state[S.VX_HAT] = vx_hat
    state[S.VY_HAT] = vy_hat
    _propagate_quality(state, params, f_heuristic, yaw_rate, gain_x, have_vx, ay, dt)

    # --- outputs --------------------------------------------------------------------------
    vx_den = max(vx_hat, min_speed)
    state[S.BETA] = math.atan2(vy_hat, vx_den)
    # d/dt atan2(vy, vx) from the observer's own derivatives (eq. 5), not the raw eq. 6.
    state[S.BETA_RATE] = (vx_den * vy_dot - vy_hat * vx_dot) / (vx_den * vx_den + vy_hat * vy_hat)
    if have_vx:
        state[S.RUN_TIME] += dt
    if state[S.RUN_TIME] < params[PARAMS.SETTLE_TIME]:
        status |= ST_NOT_CONVERGED
    if not (math.isfinite(vx_hat) and math.isfinite(vy_hat)):
        _reset(state, params)
        status |= ST_RESET | ST_NOT_CONVERGED
    _write(state, params, out, status)


@nb.njit(cache=True, inline="always")
def _write(state, params, out, status):
    vx_hat = state[S.VX_HAT]
    min_speed = params[PARAMS.MIN_SPEED]
    vx_den = vx_hat if vx_hat > min_speed else min_speed
    write_outputs(
        out, state[S.BETA], state[S.BETA_RATE],
        # before the first wheel speed vx is unknown: 0 with NOT_CONVERGED, never NaN on the bus
        vx_hat if math.isfinite(vx_hat) else 0.0,
        state[S.VY_HAT], math.nan, math.sqrt(state[S.P_VY]) / vx_den, state[_ROLL], 0.0, status,
    )  # fmt: skip


@nb.njit(cache=True, nogil=True, _nrt=False)
def run_ticks(state, U, params, vehicle, dt, OUT):
    """Batch loop: ``step`` on every row of ``U`` (n, U_LEN) into ``OUT`` (n, N_OUT)."""
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])


__all__ = ["DEFAULTS", "LAYOUT", "PARAMS", "PERSISTENT", "TABLE_1", "init", "run_ticks", "step"]
