"""``gnss_magnetometer``: sideslip and friction from GNSS velocity, a magnetometer and the IMU
(Yoon, Li, Ahn 2016, Fig. 1-2; kernels in ``heading``, ``sideslip`` and ``friction``).

Three filters in cascade, per 100 Hz tick k:

1. heading EKF x = [psi, phi] (Sec. 3.2): time update eq. 7 with the bias-free yaw and roll
   rates, measurement update with the three magnetometer axes (eq. 5, the pitch an input, see
   below; eq. 6 is its pitch-0 case) on every new magnetometer sample, gated by the
   Mahalanobis distance of the innovation (eq. 4, Sec. 2.2): d^2 > ``gate_chi2`` (chi-square,
   3 degrees of freedom) replaces H by zero (no update);
2. sideslip KF x = [vx, bx, vy, by] (Sec. 3.3): time update eq. 9 with a_x, a_y - g sin(phi)
   at the CoG and r; on every new GNSS sample the earth-frame velocity is rotated into the body
   frame with the heading and roll *of the instant the receiver sampled it* (eq. 10) and fused
   with H of eq. 11. Delay (Sec. 2.3, Larsen et al. 1998): the sample is ``gnss_delay`` old when
   it arrives. The filter keeps its states, covariances and inputs of the last ``BUFFER_TICKS``
   ticks; a delayed sample is fused at its own tick s and the filter is re-propagated over the
   stored inputs from s to now. For a linear filter this is the exact result that Larsen's
   measurement extrapolation approximates (Larsen's contribution is doing it without the
   re-propagation, which matters for big filters; a 4-state filter re-propagated over 40 ticks
   is cheap: benchmarks/estimators.py). ``delay_compensation`` = 0 fuses the
   sample as if it were current (the uncompensated filter, for comparison);
3. friction EKF x = mu (Sec. 4): f(mu) = mu, h(mu) = a_y of eq. 13 with the slip angles of
   eq. 14 from the estimated beta and the brush tyre of eq. 15 (eq. 16). The brush model's
   c_p l^2 comes from the axle cornering stiffness of the vehicle profile (2 c_p l^2 = C_alpha
   per tyre, the slope of eq. 15 at alpha = 0).

beta = atan2(vy, vx) (eq. 12 prints tan^-1(vx / vy), a typo for vy / vx).

Sign conventions (converted here, at the method's boundary): the paper's earth frame is
X north, Y west, Z up with the yaw from north toward west; slipd's is east-north-up with the
heading from east, counter-clockwise (psi = psi_paper + pi / 2, V_west = -V_east), the frame of
the GNSS channels (In.GNSS_VN / VE / VU). The paper's eq. 8 prints a_x,m = vx' + psi' vy, but its
eq. 9 (vx' = a_x,m + psi' vy - bx) is the ISO 8855 kinematics used here; body axes, roll and the
eq. 14 slip angles are ISO 8855 in the paper already.

Beyond the paper (all marked, all slipd's choices, each measured on the simulator suite):
- Magnetometer calibration. The paper uses offsets "determined by calibration" (Sec. 3.1). A
  car's magnetometer sits among steel and wiring (hard-iron offsets of several uT against a
  ~21 uT horizontal field), so slipd learns the calibration on the road: on straights (small
  yaw rate and r V, where beta ~ 0) the delayed GNSS course is the heading of the magnetometer
  sample stored at the GNSS sampling tick, and a recursive least-squares fit of
  m = C [cos psi, sin psi, 1] (``heading.calibration_update``) absorbs hard and soft iron and the
  declination; samples are levelled with the roll and pitch of their tick, and a sample beyond
  the chi-square gate is down-weighted (Huber), not dropped, so that a fit gone wrong can come
  back. Its prior is the site's field (``declination``, ``field_horizontal``, ``inclination``;
  defaults: central Europe, WMM) with ``cal_sigma_hard_iron`` and ``cal_sigma_soft_iron`` as
  1-sigma. The first ``align_samples`` calibration samples re-initialise the heading and the
  sideslip KF (start-up alignment); the KF waits for that alignment (at most
  ``align_timeout_s``) and the estimate is NOT_CONVERGED until then. Headings the car has not
  yet driven straight at keep the prior's soft-iron uncertainty (a few degrees of heading).
- Pitch: eq. 6 sets it to 0, which the paper blames for its public-road degradation (Sec. 5.3).
  slipd feeds eq. 5 the road's grade as the GNSS velocity's climb angle, atan(v_up / v_h)
  averaged over ``PATH_ANGLE_TIME_CONSTANT`` (``pitch_from_gnss``; the body's pitch on its
  springs, a fraction of a degree, is left out), else the pitch -bx / g from the sideslip KF's
  bias state (``pitch_from_bias``), which also holds the accelerometer's offset and nothing at
  all for a levelled accelerometer. Measured on the endurance drive: pitch error 0.58 against
  1.13 deg RMS (levelled accelerometer: 0.57 against 1.66), heading error 1.08 against 1.62;
  benchmarks.accuracy beta RMS (before ``course_heading``) s0 / s1 1.12 / 1.11 against
  1.57 / 1.42, the sensor variants 1.12-1.49 against 1.55-1.76, level frame 2.11 against 2.79,
  the other cars 1.15 against 1.52; VALID on 55 % of the suite's ticks (40 %), none over 5 deg
  off.
- Roll pseudo-measurement: a weak update of phi (``r_roll_static``); without it an
  uncalibrated field direction can trade heading for roll (18 deg of roll seen on
  handling_low_mu). In quasi-steady driving (the yaw acceleration, low-passed at
  ``TILT_YAW_ACC_CUTOFF_HZ``, below common.kinematics' bound) it is the tilt the
  accelerometer sees, asin((a_y - r v_x) / g) with the wheels' v_x (``roll_tilt``,
  ``stages.roll_pseudo_measurement``): road bank and body roll together, which is what turns
  the 44 uT vertical field into the magnetometer's y axis; else, and with ``roll_tilt`` = 0,
  the static roll model (Selmanaj 2017 eq. 16), which sees no bank. Measured before the
  GNSS pitch below (benchmarks.accuracy, beta RMS against the static model alone): suite
  1.57 / 1.42 deg against 2.16 / 2.09 (seeds 0 / 1), banked_road 1.75 against 3.05, the
  sensor variants 1.55-1.76 against 2.16-2.79; its roll error on the endurance drive 0.47
  against 1.57 deg, its heading error 1.6 against 2.3 deg.
- Levelled accelerometer (``common.inputs.accel_carries_gravity``, as every method's
  preprocessing: declared in the profile, or its az on the bus reading no gravity): a_y carries
  no g sin(phi), so eq. 9 takes a_y as it is and the roll pseudo-measurement is the static
  model's.
- Gate lock-out: when the gate has rejected every sample for ``gate_lockout_s`` while the
  field's norm matches the earth field's (``field_norm_tolerance``, the paper's basis of
  disturbance detection, Sec. 2.2) the model, not the field, is wrong: psi restarts from the
  calibrated magnetometer.
- Heading from the GNSS course of a straight (``course_heading``; 0: the paper's magnetometer
  heading alone). The calibration above already takes the course of a straight for the
  heading (beta ~ 0 there); once aligned, the heading EKF takes it too
  (``stages.course_update``), on a straight that began ``course_min_straight_s`` before the
  sampling tick and has lasted until now (a drift's reversal, where the yaw rate crosses zero
  at 20 deg of sideslip, is not one): psi += K (course - psi_s), phi with it through their
  covariance, K = P H' / (H P H' + r) with H = [1, 0], psi_s the heading stored for the
  sampling tick, r = r_gnss / V^2 + ``r_course`` (the GNSS noise across the track and a
  straight's own sideslip); the attitudes stored since the sampling tick and the sideslip
  KF's velocity there turn by the same angle, and the yaw-rate trim below takes the correction
  as it takes a magnetometer's. P is left as it is: the course's error is the straight's own
  sideslip, common to every sample of it (``heading.heading_course_correction``). Why: a roll
  error turns the 44 uT vertical field into the magnetometer's y axis, ~2 deg of heading per
  degree of roll, and the roll the magnetometer is read with misses a road's cross slope where
  the accelerometer cannot show it (a levelled INS keeps the static roll model): on the
  level-frame endurance drive the heading was 3-5 deg off on cross-sloped straights at 36 m/s
  (vy 1-3 m/s off). Measured (benchmarks.accuracy, beta RMS [deg] against the paper's
  heading): s0 / s1 0.79 / 0.86 against 1.12 / 1.11, the sensor variants 0.79-1.29 against
  1.12-1.49, level frame 1.55 against 2.11, the other cars 0.77 against 1.15; VALID on 73 % of
  the suite's ticks (56 %), none over 5 deg off; no drive of any block worse by more than 5 %.
  Tried and not kept: the full update (P reduced as for independent samples): s0 0.75, level
  frame 1.46, but step_steer 0.36 -> 0.94 and loaded_vehicle 0.66 -> 1.34 (a heading sure to
  a tenth of a degree gave the magnetometer no weight in the next corner and ran off with the
  gyro's unlearnt offset); without the straight's minimum duration: the vibration variant's
  snow drift 3.35 -> 4.83 (one course taken mid-drift).
- Gyro biases b_r, b_p of eq. 7: the paper takes them from standstill; slipd learns them at
  standstill (``common.inputs.update_gyro_offset``) and trims b_r while driving by integrating the
  heading corrections (the integral part of a complementary filter, ``yaw_bias_time_constant``).
- GNSS antenna lever arm (``antenna_x/y/z``, body axes from the CoG): v_ant = v + omega x rho.
  Default 0: the vehicle profile has no antenna position yet (requested).
- Friction EKF: updated only when |d a_y / d mu| >= ``mu_min_sensitivity`` (the paper notes the
  estimate is unreliable without excitation, Sec. 5.2); an innovation beyond ``mu_gate_chi2``
  is down-weighted (longitudinal forces, which eq. 13 leaves out, and beta errors).
- Accelerations are moved from the IMU to the CoG (``common.kinematics.translate_to_cog``); below
  ``min_speed`` beta is reported as 0 (atan2 of two noisy numbers near 0 is no sideslip).

Parameters: the paper publishes no covariances, thresholds or start values; every default
below is slipd's and says what it was chosen from. Table 1 gives the sensor noise (magnetometer
0.5 mG = 0.05 uT, IMU 0.02 m/s^2 and 0.08 deg/s); the filters' R and Q are larger because
they also carry model error (pitch neglected in eq. 6, calibration residual, roll in eq. 9).

Inputs: core IMU, steer and wheel speeds (wheels only for the speed output before the first
GNSS fix), GNSS velocity and fix, the three magnetometer axes. Without a GNSS fix or a
magnetometer ever seen the method reports UNAVAILABLE (beta 0, vx from the wheels) and never
invents the data. New samples are detected by a change of the latched value (u carries no
per-channel age): a repeated identical sample is skipped, which only loses one sample.
"""


from __future__ import annotations

import math

import numpy as np

from slipd.channels import (
    CORE_CHANNELS,
    ST_DEGRADED,
    ST_INPUT_TIMEOUT,
    ST_NOT_CONVERGED,
    ST_RESET,
    ST_UNAVAILABLE,
    G,
    In,
    Veh,
)
from slipd.errors import ConfigError
from slipd.estimators.common.filters import lowpass
from slipd.estimators.common.inputs import (
    ImuMemory,
    Offsets,
    accel_carries_gravity,
    channel,
    corner_speed_mean,
    hold_last,
    imu_at_cog,
    reset_imu,
    update_gyro_offset,
    update_standstill,
    wheel_speeds,
)
from slipd.estimators.common.kalman import beta_sigma, tri
from slipd.estimators.common.kinematics import GRAVITY_SHARE_MAX_YAW_ACC, kinematic_beta_rate
from slipd.estimators.common.outputs import held_sigma, write_held, write_outputs
from slipd.estimators.common.vehicle import require_vehicle
from slipd.estimators.yoon2016.friction import friction_update
from slipd.estimators.yoon2016.params import DEFAULTS, PARAMS
from slipd.estimators.yoon2016.sideslip import (
    entry,
    kf4_predict,
    save_entry,
)
from slipd.estimators.yoon2016.stages import (
    driving_straight,
    gnss_sample,
    heading_tick,
    reset_calibration,
)
from slipd.estimators.yoon2016.state import (
    BUFFER_TICKS,
    CAL_C,
    CAL_PRIOR,
    FINITE_END,
    IMU,
    KF,
    KF_P,
    LAYOUT,
    OFFSETS,
    SCRATCH,
    E,
    S,
)
from slipd.numba_cache import nb

#: Time constant of the GNSS climb angle's average, the pitch of ``pitch_from_gnss`` (s): a
#: road's grade changes over tens of metres, the vertical velocity's noise from sample to
#: sample.
PATH_ANGLE_TIME_CONSTANT = 1.0
#: Cut-off of the yaw acceleration the tilt pseudo-measurement's quasi-steady test reads (Hz):
#: kinematic_heuristic's steady detector's, whose 1 Hz filters carry a tenth of the noise of
#: the 10 Hz ones (a vibrating gyro kept the 10 Hz yaw acceleration above the bound).
TILT_YAW_ACC_CUTOFF_HZ = 1.0

#: Channels whose loss makes the output invalid (the pipeline's required-channel mask).
REQUIRED = (
    *CORE_CHANNELS,
    In.GNSS_VN, In.GNSS_VE, In.GNSS_VU, In.GNSS_FIX,
    In.MAG_X, In.MAG_Y, In.MAG_Z,
)  # fmt: skip
#: s, the tick interval the history's length is counted in (gnss_delay's bound at init)
NOMINAL_DT = 0.01
#: speed floor of the held sigma_beta, m/s
HELD_SPEED_FLOOR = 1.0
#: sigma_beta where the speed is zero and beta is not defined: the whole circle
STANDSTILL_SIGMA = math.pi
_LAST_AX = IMU + int(ImuMemory.LAST_AX)
_LAST_STEER = IMU + int(ImuMemory.LAST_STEER)
_LAST_MAG = int(S.LAST_MAG_X)
_LAST_GNSS = int(S.LAST_VN)
_MAG_SEEN = int(S.MAG_SEEN)
_GNSS_SEEN = int(S.GNSS_SEEN)


#: Friction classes of Out.FRICTION_CLASS by the estimated mu (slipd): below 0.4 low (ice,
#: snow), below 0.8 medium (wet), else high (dry).
MU_CLASS_LOW = 0.4
MU_CLASS_MEDIUM = 0.8
FRICTION_LOW, FRICTION_MEDIUM, FRICTION_HIGH = 1.0, 2.0, 3.0

#: Kept across key cycles by the daemon (slipd.daemon.service.StateStore): the magnetometer
#: calibration learned on straights and its covariance, and the yaw-rate bias. Without them
#: every drive starts uncalibrated (a few degrees of heading, hence of beta, until the car has
#: driven straight at each heading again).
PERSISTENT = ("CAL_C", "CAL_P", "YAW_RATE_BIAS")


def init(params: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """A fresh state vector: every filter waits for its first sample."""
    require_vehicle("gnss_magnetometer", vehicle, (
        Veh.MASS, Veh.LF, Veh.LR, Veh.CORNERING_STIFFNESS_F, Veh.CORNERING_STIFFNESS_R,
        Veh.MU_NOMINAL,
    ))  # fmt: skip
    delay = float(params[PARAMS.GNSS_DELAY])
    if not (0.0 <= delay <= (BUFFER_TICKS - 2) * NOMINAL_DT):
        raise ConfigError(
            f"gnss_delay = {delay} s: must be within 0 .. {(BUFFER_TICKS - 2) * NOMINAL_DT:.2f} s "
            f"(the history holds {BUFFER_TICKS} ticks)"
        )
    state = np.zeros(LAYOUT.size, dtype=np.float64)
    reset_imu(state, IMU)
    state[S.LAST_VN] = np.nan
    state[S.LAST_MAG_X] = np.nan
    state[S.FIRST_FIX_TICK] = np.nan
    state[S.PATH_ANGLE] = np.nan
    state[S.PATH_ANGLE_SLOW] = 0.0  # a level road until the GNSS says otherwise
    reset_calibration(state, params)
    state[S.MU] = vehicle[Veh.MU_NOMINAL]
    state[S.MU_P] = params[PARAMS.P0_MU]
    return state

@nb.njit(cache=True, _nrt=False)
def state_is_finite(state):
    """True when the filters and the calibration are finite."""
    for i in range(FINITE_END):
        if not math.isfinite(state[i]):
            return False
    return True


# ---------------------------------------------------------------------------------------------
# stages of a tick
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True, inline="always")
def _rates(state, u, params, dt, status):
    """The three gyro rates with the offsets learnt at standstill removed (eq. 7's b_r, b_p);
    an invalid yaw rate is the previous tick's (INPUT_TIMEOUT), an invalid roll or pitch rate
    0 (roll missing: DEGRADED, the roll comes from the magnetometer alone). Returns (yaw_rate,
    roll_rate, pitch_rate, status)."""
    v_fl, v_fr, v_rl, v_rr, ok_fl, ok_fr, ok_rl, ok_rr = wheel_speeds(u)
    all_wheels = ok_fl and ok_fr and ok_rl and ok_rr
    fastest = max(max(v_fl, v_fr), max(v_rl, v_rr)) if all_wheels else math.inf
    still_time = update_standstill(
        state, OFFSETS, fastest, all_wheels, dt, params[PARAMS.STANDSTILL_SPEED]
    )
    standstill = still_time > params[PARAMS.STANDSTILL_DELAY_S]
    settling = params[PARAMS.GYRO_OFFSET_SETTLING_S]
    yaw_rate, yaw_rate_ok = channel(u, In.YAW_RATE)
    if yaw_rate_ok:
        yaw_rate -= update_gyro_offset(state, OFFSETS, Offsets.YAW_RATE, yaw_rate, standstill,
                                       dt, settling)  # fmt: skip
    else:
        yaw_rate = state[S.PREV_YAW_RATE]
        status |= ST_INPUT_TIMEOUT
    roll_rate, roll_rate_ok = channel(u, In.ROLL_RATE)
    pitch_rate, pitch_rate_ok = channel(u, In.PITCH_RATE)
    if roll_rate_ok:
        roll_rate -= update_gyro_offset(state, OFFSETS, Offsets.ROLL_RATE, roll_rate, standstill,
                                        dt, settling)  # fmt: skip
    else:
        roll_rate = 0.0
        status |= ST_DEGRADED  # roll from the magnetometer alone
    if pitch_rate_ok:
        pitch_rate -= update_gyro_offset(state, OFFSETS, Offsets.PITCH_RATE, pitch_rate,
                                         standstill, dt, settling)  # fmt: skip
    else:
        pitch_rate = 0.0
    return yaw_rate, roll_rate, pitch_rate, status


@nb.njit(cache=True, inline="always")
def _latched_sample(state, u, channel_a, last, seen, extra_ok):
    """Three consecutive channels from ``channel_a`` as one sample: their values, whether all
    are valid (and ``extra_ok``), and whether the sample is new (u carries no per-channel age:
    a changed latched value is a new sample, so a repeated identical one is skipped, which only
    loses one sample). A valid sample is remembered in ``state[last:last + 3]`` and sets
    ``state[seen]``. Returns (a, b, c, ok, new)."""
    a, ok_a = channel(u, channel_a)
    b, ok_b = channel(u, channel_a + 1)
    c, ok_c = channel(u, channel_a + 2)
    ok = ok_a and ok_b and ok_c and extra_ok
    new = ok and (a != state[last] or b != state[last + 1] or c != state[last + 2])
    if ok:
        state[seen] = 1.0
        state[last] = a
        state[last + 1] = b
        state[last + 2] = c
    return a, b, c, ok, new


@nb.njit(cache=True, inline="always")
def _new_samples(state, u, status):
    """The newest magnetometer and GNSS samples and whether each is new this tick; a missing
    one is an INPUT_TIMEOUT. Returns (m_x, m_y, m_z, mag_ok, new_mag, v_north, v_east, v_up,
    new_gnss, status)."""
    m_x, m_y, m_z, mag_ok, new_mag = _latched_sample(state, u, In.MAG_X, _LAST_MAG, _MAG_SEEN,
                                                     True)  # fmt: skip
    if not mag_ok:
        status |= ST_INPUT_TIMEOUT
    fix, ok_fix = channel(u, In.GNSS_FIX)
    v_north, v_east, v_up, gnss_ok, new_gnss = _latched_sample(
        state, u, In.GNSS_VN, _LAST_GNSS, _GNSS_SEEN, ok_fix and fix > 0.5
    )
    if not gnss_ok:
        status |= ST_INPUT_TIMEOUT
    return m_x, m_y, m_z, mag_ok, new_mag, v_north, v_east, v_up, new_gnss, status


@nb.njit(cache=True, inline="always")
def _restart(state, params, vehicle):
    """Reset on a non-finite or implausible state (openpilot paramsd's rule): the heading EKF
    and the sideslip KF restart; a broken calibration restarts from its prior."""
    state[S.KF_INIT] = 0.0
    state[S.HEAD_INIT] = 0.0
    for i in range(CAL_C, CAL_C + 18):
        if not math.isfinite(state[i]):
            for j in range(18):
                state[CAL_C + j] = state[CAL_PRIOR + j]
            state[S.CAL_SAMPLES] = 0.0
            break
    state[S.MU] = vehicle[Veh.MU_NOMINAL]
    state[S.MU_P] = params[PARAMS.P0_MU]
    state[S.MU_UPDATES] = 0.0


@nb.njit(cache=True, inline="always")
def _friction_class(state, params):
    """Out.FRICTION_CLASS by the estimated mu, once it has been excited often enough."""
    if state[S.MU_UPDATES] < params[PARAMS.MU_CLASS_UPDATES]:
        return 0.0
    if state[S.MU] < MU_CLASS_LOW:
        return FRICTION_LOW
    if state[S.MU] < MU_CLASS_MEDIUM:
        return FRICTION_MEDIUM
    return FRICTION_HIGH


@nb.njit(cache=True, inline="always")
def _write_held(out, vx, roll, params, status):
    write_held(out, vx, held_sigma(params[PARAMS.P0_V], vx, HELD_SPEED_FLOOR), roll, status)


# ---------------------------------------------------------------------------------------------
# the tick
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True, _nrt=False)
def step(state, u, params, vehicle, dt, out):
    """One 100 Hz tick of the three filters; writes every element of ``out``, allocates nothing."""
    tick = state[S.TICK]
    state[S.TICK] = tick + 1.0
    # --- inputs: gyro offsets at standstill (eq. 7's b_r, b_p), CoG accelerations -----------
    yaw_rate, roll_rate, pitch_rate, status = _rates(state, u, params, dt, 0)
    steer, steer_ok = channel(u, In.STEER)
    steer = hold_last(state, _LAST_STEER, steer, steer_ok)
    if not steer_ok:
        status |= ST_INPUT_TIMEOUT
    ax, ay, _, yaw_acc, ax_ok, ay_ok = imu_at_cog(
        state, IMU, u, yaw_rate, roll_rate, pitch_rate, dt, params[PARAMS.YAW_ACC_CUTOFF_HZ],
        vehicle, True, params[PARAMS.ACCEL_LOWPASS_HZ],
    )  # fmt: skip
    ay_imu = u[In.AY]  # at the sensor, for the roll pseudo-measurement
    gravity_in_ay = accel_carries_gravity(u, vehicle)  # slipd: not for a levelled INS
    # quasi-steady (common.kinematics' criterion, on the yaw acceleration low-passed at
    # TILT_YAW_ACC_CUTOFF_HZ): a_y - r v_x is then tilt, not lateral slip rate
    yaw_acc_slow = state[S.YAW_ACC_SLOW]
    if math.isfinite(yaw_acc):
        yaw_acc_slow = lowpass(state, S.YAW_ACC_SLOW, yaw_acc, dt,
                               1.0 / (2.0 * math.pi * TILT_YAW_ACC_CUTOFF_HZ))
    tilt_seen = gravity_in_ay and abs(yaw_acc_slow) < GRAVITY_SHARE_MAX_YAW_ACC
    ax = hold_last(state, _LAST_AX, ax, ax_ok)
    if not (ax_ok and ay_ok):
        status |= ST_INPUT_TIMEOUT
    vx_wheels, n_wheels = corner_speed_mean(u, steer, yaw_rate, vehicle)
    if n_wheels < 4:
        status |= ST_INPUT_TIMEOUT
    # how long the car has driven straight without a break (course_heading's test)
    if driving_straight(yaw_rate, vx_wheels, params):
        state[S.STRAIGHT_S] += dt
    else:
        state[S.STRAIGHT_S] = 0.0
    m_x, m_y, m_z, mag_ok, new_mag, v_north, v_east, v_up, new_gnss, status = _new_samples(
        state, u, status
    )

    # --- 1. heading EKF (eq. 5-7) with the Mahalanobis gate (Sec. 2.2) ---------------------
    tilt_speed = vx_wheels if n_wheels == 4 else (
        state[S.KF_VX] if state[S.KF_INIT] > 0.5 else math.nan)
    heading_tick(state, params, vehicle, tick, m_x, m_y, m_z, mag_ok, new_mag, ay_imu, ay_ok,
                 tilt_seen, tilt_speed, dt)  # fmt: skip
    state[S.PREV_YAW_RATE] = yaw_rate
    state[S.PREV_ROLL_RATE] = roll_rate
    head_running = state[S.HEAD_INIT] > 0.5
    roll = state[S.HEAD_PHI] if head_running else 0.0
    # eq. 9's input a_y,m - g sin(phi) (an invalid ay: the model's r vx, no lateral slip rate)
    if ay_ok:
        ay_no_gravity = ay - G * math.sin(roll) if gravity_in_ay else ay
    else:
        ay_no_gravity = yaw_rate * state[S.KF_VX]
    # --- availability: both sensors must have been seen -----------------------------------
    if state[S.MAG_SEEN] < 0.5 or not head_running:
        _write_held(out, vx_wheels, roll, params, status | ST_UNAVAILABLE)
        return

    # --- 2. sideslip KF (eq. 9-11) with the delayed GNSS (Sec. 2.3) ------------------------
    kf_running = state[S.KF_INIT] > 0.5
    if kf_running:
        e_prev = entry(tick - 1.0)
        kf4_predict(
            state, KF, KF_P, SCRATCH, state[e_prev + E.AX], state[e_prev + E.AY_NO_GRAVITY],
            state[e_prev + E.YAW_RATE], params[PARAMS.Q_V] * dt, params[PARAMS.Q_B] * dt, dt,
        )  # fmt: skip
        state[S.KF_TICKS] += 1.0
        state[S.GNSS_AGE] += 1.0
    save_entry(state, tick, ax, ay_no_gravity, yaw_rate, roll_rate, pitch_rate)
    if new_gnss:
        speed_h = math.hypot(v_north, v_east)
        if speed_h > params[PARAMS.CAL_MIN_SPEED]:  # the course, and the climb, defined
            state[S.PATH_ANGLE] = math.atan2(v_up, speed_h)
        kf_running = gnss_sample(state, params, tick, ax, ay_no_gravity, yaw_rate, roll_rate,
                                 pitch_rate, v_north, v_east, v_up, dt)  # fmt: skip
    if not kf_running:
        if state[S.GNSS_SEEN] < 0.5:
            status |= ST_UNAVAILABLE  # no fix ever: the method cannot run
        _write_held(out, vx_wheels, roll, params, status)
        return

    # --- reset on a non-finite or implausible state (openpilot paramsd's rule) -------------
    vx = state[S.KF_VX]
    vy = state[S.KF_VY]
    if not state_is_finite(state) or abs(vy) > max(abs(vx), 1.0):
        _restart(state, params, vehicle)
        _write_held(out, vx_wheels, 0.0, params, status | ST_RESET)
        return

    path = state[S.PATH_ANGLE]
    if math.isfinite(path):
        # slipd: the road's grade as the GNSS velocity's climb angle, averaged over
        # PATH_ANGLE_TIME_CONSTANT from a level road (0.1 m/s of vertical noise is 0.3 deg a
        # sample at 20 m/s; taking the first sample as it is cost the endurance drive 1.11 ->
        # 1.33 deg: a noisy first climb angle levels the first calibration samples wrongly)
        lowpass(state, S.PATH_ANGLE_SLOW, path, dt, PATH_ANGLE_TIME_CONSTANT)
    if params[PARAMS.PITCH_FROM_GNSS] > 0.5 and math.isfinite(path):
        # ISO 8855 pitch is nose-down positive: climbing is a negative pitch
        max_pitch = params[PARAMS.MAX_PITCH]
        state[S.PITCH] = min(max(-state[S.PATH_ANGLE_SLOW], -max_pitch), max_pitch)
    elif params[PARAMS.PITCH_FROM_BIAS] > 0.5:
        # slipd: eq. 9's bx holds the accelerometer offset minus g sin(pitch) (a_x,m =
        # vx' - r vy - g sin(theta) + offset in ISO 8855); the offset (~0.1 m/s^2 = 0.6 deg) is
        # the smaller part on a road with grades, so theta ~ -bx / g
        max_pitch = params[PARAMS.MAX_PITCH]
        state[S.PITCH] = min(max(-state[S.KF_BX] / G, -max_pitch), max_pitch)
    if vx < params[PARAMS.MIN_SPEED]:
        # beta = atan2(vy, vx) is undefined at standstill; the filters keep running
        _write_held(out, max(vx, 0.0), roll, params, status)
        return

    # --- 3. friction EKF (eq. 13-16) -------------------------------------------------------
    beta = math.atan2(vy, vx)
    friction_update(
        state, S.MU, S.MU_P, S.MU_UPDATES, SCRATCH, beta, yaw_rate, vx, steer, ay_no_gravity, ay_ok,
        vehicle, params[PARAMS.Q_MU] * dt, params[PARAMS.R_AY], params[PARAMS.MU_MIN_SPEED],
        params[PARAMS.MU_MIN_SENSITIVITY], params[PARAMS.MU_GATE_CHI2], params[PARAMS.MU_MIN],
        params[PARAMS.MU_MAX],
    )  # fmt: skip

    # --- outputs ---------------------------------------------------------------------------
    sigma = beta_sigma(vx, vy, state[KF_P], state[KF_P + tri(0, 2, 4)], state[KF_P + tri(2, 2, 4)],
                       STANDSTILL_SIGMA)
    if (
        state[S.KF_TICKS] < params[PARAMS.SETTLE_TICKS]
        or state[S.CAL_SAMPLES] < params[PARAMS.ALIGN_SAMPLES]
        or state[S.GNSS_AGE] * dt > params[PARAMS.GNSS_OUTAGE_S]
        or not (sigma <= params[PARAMS.CONVERGED_SIGMA_BETA])
    ):
        status |= ST_NOT_CONVERGED
    write_outputs(
        out, beta, kinematic_beta_rate(vx, vy, ax - state[S.KF_BX],
                                       ay_no_gravity - state[S.KF_BY], yaw_rate),
        vx, vy, state[S.MU], sigma, roll, _friction_class(state, params), status,
    )  # fmt: skip


@nb.njit(cache=True, nogil=True, _nrt=False)
def run_ticks(state, U, params, vehicle, dt, OUT):
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])


@nb.njit(cache=True, nogil=True, _nrt=False)
def run_ticks_diagnostic(state, U, params, vehicle, dt, OUT, DIAG):
    """``run_ticks`` that also records, per tick, DIAG[k] = (psi, phi, d^2 of the newest
    magnetometer sample, total rejected samples, mu, calibration samples[, pitch, accepted
    samples] (the last two when DIAG has 8 columns))."""
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])
        DIAG[k, 0] = state[S.HEAD_PSI]
        DIAG[k, 1] = state[S.HEAD_PHI]
        DIAG[k, 2] = state[S.LAST_D2]
        DIAG[k, 3] = state[S.GATE_REJECTS]
        DIAG[k, 4] = state[S.MU]
        DIAG[k, 5] = state[S.CAL_SAMPLES]
        if DIAG.shape[1] > 7:
            DIAG[k, 6] = state[S.PITCH]
            DIAG[k, 7] = state[S.GATE_ACCEPTS]


__all__ = ["DEFAULTS", "LAYOUT", "PARAMS", "PERSISTENT", "REQUIRED", "init", "run_ticks", "step"]
