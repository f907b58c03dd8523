"""``gnss_magnetometer``: sideslip and friction from GNSS velocity, a magnetometer and the IMU
(Yoon, Li, Ahn 2016, Fig. 1-2; kernels in ``slipd.estimators.yoon``).

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
   costs ~0.2 us per tick on average, measured). ``delay_compensation`` = 0 fuses the
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
  m = C [cos psi, sin psi, 1] (``yoon.calibration_update``) absorbs hard and soft iron and the
  declination; samples are levelled with the roll and pitch of their tick, and a sample beyond
  the chi-square gate is down-weighted (Huber), not dropped, so that a fit gone wrong can come
  back. Its prior is the site's field (``declination``, ``field_horizontal``, ``inclination``;
  defaults: central Europe, WMM) with ``cal_sigma_hard_iron`` and ``cal_sigma_soft_iron`` as
  1-sigma. The first ``align_samples`` calibration samples re-initialise the heading and the
  sideslip KF (start-up alignment); the KF waits for that alignment (at most
  ``align_timeout_s``) and the estimate is NOT_CONVERGED until then. Headings the car has not
  yet driven straight at keep the prior's soft-iron uncertainty (a few degrees of heading).
- Pitch: eq. 6 sets it to 0, which the paper blames for its public-road degradation (Sec. 5.3).
  slipd feeds eq. 5 the pitch -bx / g from the sideslip KF's bias state (``pitch_from_bias``).
- Roll pseudo-measurement: the static roll model (Selmanaj 2017 eq. 16) updates phi with a
  loose variance (``r_roll_static``); without it an uncalibrated field direction can trade
  heading for roll (18 deg of roll seen on handling_low_mu).
- Gate lock-out: when the gate has rejected every sample for ``gate_lockout_s`` while the
  field's norm matches the earth field's (``field_norm_tolerance``, the paper's basis of
  disturbance detection, Sec. 2.2) the model, not the field, is wrong: psi restarts from the
  calibrated magnetometer.
- Gyro biases b_r, b_p of eq. 7: the paper takes them from standstill; slipd learns them at
  standstill (``preprocess.update_gyro_offset``) and trims b_r while driving by integrating the
  heading corrections (the integral part of a complementary filter, ``yaw_bias_time_constant``).
- GNSS antenna lever arm (``antenna_x/y/z``, body axes from the CoG): v_ant = v + omega x rho.
  Default 0: the vehicle profile has no antenna position yet (requested).
- Friction EKF: updated only when |d a_y / d mu| >= ``mu_min_sensitivity`` (the paper notes the
  estimate is unreliable without excitation, Sec. 5.2); an innovation beyond ``mu_gate_chi2``
  is down-weighted (longitudinal forces, which eq. 13 leaves out, and beta errors).
- Accelerations are moved from the IMU to the CoG (``preprocess.translate_to_cog``); below
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

import enum
import math

import numba as nb
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
    Out,
    Veh,
)
from slipd.estimators.preprocess import (
    Offsets,
    channel,
    corner_speed_mean,
    imu_at_cog,
    roll_static_gain,
    update_gyro_offset,
    update_standstill,
)
from slipd.estimators.yoon import (
    calibration_residual,
    calibration_update,
    heading_from_magnetometer,
    heading_predict,
    heading_roll_update,
    heading_update,
    kf4_predict,
    kf4_update_velocity,
    lateral_acceleration_model,
    magnetometer_model,
    wrap_angle,
)

#: Channels whose loss makes the output invalid (base.required_channels).
REQUIRED = (
    *CORE_CHANNELS,
    In.GNSS_VN, In.GNSS_VE, In.GNSS_VU, In.GNSS_FIX,
    In.MAG_X, In.MAG_Y, In.MAG_Z,
)  # fmt: skip

#: Ticks of filter history kept for the delayed GNSS samples (0.63 s at 100 Hz > 0.4 s delay).
BUFFER_TICKS = 64


@enum.unique
class E(enum.IntEnum):
    """One history entry of the sideslip KF (``ENTRY_LEN`` slots per tick)."""

    VX = 0  # a posteriori state [vx, bx, vy, by] at the end of the tick
    BX = 1
    VY = 2
    BY = 3
    P = 4  # 16 slots, P row-major
    AX = 20  # m/s^2, CoG, the input of the prediction from this tick to the next
    AY_NO_GRAVITY = 21  # m/s^2, a_y - g sin(phi)
    YAW_RATE = 22  # rad/s, bias removed
    PSI = 23  # rad, heading EKF at this tick (rotates a GNSS sample taken now, eq. 10)
    PHI = 24  # rad
    ROLL_RATE = 25  # rad/s (antenna lever arm)
    PITCH_RATE = 26
    MAG_X = 27  # uT, newest raw magnetometer sample (calibration against the GNSS course)
    MAG_Y = 28
    MAG_Z = 29
    PITCH = 30  # rad, pitch estimate at this tick (-bx / g)


ENTRY_LEN = len(E) + 15  # P spans 16 slots


@enum.unique
class S(enum.IntEnum):
    """Slots of the state vector."""

    KF_VX = 0  # m/s        sideslip KF x = [vx, bx, vy, by] (eq. 9)
    KF_BX = 1  # m/s^2
    KF_VY = 2  # m/s
    KF_BY = 3  # m/s^2
    KF_P = 4  # 16 slots, P row-major
    HEAD_PSI = 20  # rad, heading from east, CCW (heading EKF, eq. 7)
    HEAD_PHI = 21  # rad, roll (ISO 8855)
    HEAD_P = 22  # 3 slots: p_psi_psi, p_psi_phi, p_phi_phi
    MU = 25  # friction EKF (eq. 16)
    MU_P = 26
    CAL_C = 27  # 9 slots, magnetometer calibration C, row-major (yoon module docstring)
    CAL_P = 36  # 9 slots, its RLS covariance
    MAG_SEEN = 45  # 1 once a magnetometer sample was valid
    GNSS_SEEN = 46  # 1 once a GNSS fix was valid
    HEAD_INIT = 47  # 1 while the heading EKF runs
    KF_INIT = 48  # 1 while the sideslip KF runs
    KF_TICKS = 49  # ticks since the sideslip KF (re)started
    TICK = 50  # ticks since init (the history's clock)
    KF_START_TICK = 51  # tick the sideslip KF (re)started: the oldest usable history entry
    GATE_REJECT_RUN = 52  # ticks since the last accepted magnetometer sample
    GATE_REJECTS = 53  # total rejected samples (diagnostics)
    GATE_ACCEPTS = 54  # total accepted samples
    CAL_SAMPLES = 55  # calibration samples taken
    MU_UPDATES = 56  # excited friction updates since (re)start
    GNSS_AGE = 57  # ticks since the last fused GNSS sample
    LAST_VN = 58  # last latched GNSS velocity (new-sample detection)
    LAST_VE = 59
    LAST_VU = 60
    LAST_MAG_X = 61  # last latched magnetometer sample
    LAST_MAG_Y = 62
    LAST_MAG_Z = 63
    PREV_YAW_RATE = 64  # rad/s, bias-free rates of tick k-1 (eq. 7 time update)
    PREV_ROLL_RATE = 65
    LAST_AX = 66  # last valid CoG ax
    LAST_STEER = 67
    LAST_D2 = 68  # Mahalanobis d^2 of the newest magnetometer sample (diagnostics)
    YAW_RATE_FILTERED = 69  # derivative-filter memories of the CoG translation
    ROLL_RATE_FILTERED = 70
    PITCH_RATE_FILTERED = 71
    OFFSETS = 72  # 6 slots, preprocess.Offsets (gyro offsets at standstill)
    GNSS_UPDATES = 78  # GNSS samples fused since the KF (re)started
    HISTORY_START_TICK = 79  # first tick of the history since the heading EKF (re)started
    FIRST_FIX_TICK = 80  # tick of the first GNSS fix (NaN: none yet)
    PITCH = 81  # rad, pitch estimate fed to the magnetometer model (slipd)
    YAW_RATE_BIAS = 82  # rad/s, b_r of eq. 7 left after the standstill offset (slipd)
    CAL_PRIOR = 83  # 18 slots: the calibration's prior C and covariance, for a reset
    SCRATCH = 101  # 16 slots of working memory
    HISTORY = 117  # BUFFER_TICKS * ENTRY_LEN slots


N_STATE = int(S.HISTORY) + BUFFER_TICKS * ENTRY_LEN

# plain ints for index arithmetic inside the kernels
_KF = int(S.KF_VX)
_KF_P = int(S.KF_P)
_HEAD = int(S.HEAD_PSI)
_HEAD_P = int(S.HEAD_P)
_CAL_C = int(S.CAL_C)
_CAL_P = int(S.CAL_P)
_OFFSETS = int(S.OFFSETS)
_SCRATCH = int(S.SCRATCH)
_HISTORY = int(S.HISTORY)
_N_FINITE = int(S.CAL_P) + 9  # filters' and calibration's slots checked for finiteness
_CAL_PRIOR = int(S.CAL_PRIOR)
_OFF_YAW = int(Offsets.YAW_RATE)
_OFF_ROLL = int(Offsets.ROLL_RATE)
_OFF_PITCH = int(Offsets.PITCH_RATE)


@enum.unique
class PARAMS(enum.IntEnum):
    # heading EKF (eq. 5-7, Sec. 2.2)
    Q_PSI = 0  # rad^2/s, yaw random walk: gyro noise and the part of its bias not removed
    Q_PHI = 1  # rad^2/s, roll random walk
    R_MAG = 2  # uT^2 per axis: noise + model error of eq. 6 (pitch 0, calibration residual)
    GATE_CHI2 = 3  # chi-square gate on d^2 (3 dof)
    GATE_LOCKOUT_S = 4  # s of consecutive rejections before psi is re-initialised (slipd)
    P0_PSI = 5  # rad^2
    P0_PHI = 6  # rad^2
    # site magnetic field: the calibration's prior (slipd)
    DECLINATION = 7  # rad, east positive
    INCLINATION = 8  # rad, down positive
    FIELD_HORIZONTAL = 9  # uT
    CAL_SIGMA_HARD_IRON = 10  # uT, prior 1-sigma of the offset column
    CAL_SIGMA_SOFT_IRON = 11  # uT, prior 1-sigma of the cos / sin columns
    CAL_R = 12  # uT^2, variance of one calibration sample
    CAL_Q = 13  # uT^2 per sample, random walk of C
    CAL_MAX_YAW_RATE = 14  # rad/s, "straight": |r| below
    CAL_MAX_AY = 15  # m/s^2, "straight": centripetal |r V| below (not the measured a_y, whose
    # gravity compensation needs the roll of the not yet calibrated magnetometer)
    CAL_MIN_SPEED = 16  # m/s, course defined
    ALIGN_SAMPLES = 17  # calibration samples that re-initialise psi / before convergence
    ALIGN_TIMEOUT_S = 18  # s after the first fix the KF waits for a straight to align on
    # sideslip KF (eq. 9-11)
    Q_V = 19  # (m/s)^2/s, velocity random walk (accelerometer noise + model error)
    Q_B = 20  # (m/s^2)^2/s, accelerometer bias random walk
    R_GNSS = 21  # (m/s)^2, body-frame GNSS velocity (receiver + rotation error)
    P0_V = 22  # (m/s)^2
    P0_B = 23  # (m/s^2)^2
    GNSS_DELAY = 24  # s, receiver latency (Sec. 5: 400 ms)
    DELAY_COMPENSATION = 25  # 1 = fuse at the sampling tick (Sec. 2.3), 0 = as if current
    ANTENNA_X = 26  # m, GNSS antenna from the CoG, body axes (slipd)
    ANTENNA_Y = 27
    ANTENNA_Z = 28
    # friction EKF (eq. 13-16)
    Q_MU = 29  # 1/s, mu random walk
    R_AY = 30  # (m/s^2)^2
    P0_MU = 31
    MU_MIN = 32
    MU_MAX = 33
    MU_MIN_SENSITIVITY = 34  # m/s^2 per unit mu: excitation gate (slipd)
    MU_MIN_SPEED = 35  # m/s
    MU_CLASS_UPDATES = 36  # excited updates before a friction class is reported
    # bookkeeping (slipd)
    SETTLE_TICKS = 37  # ticks after the KF (re)start before convergence may be claimed
    CONVERGED_SIGMA_BETA = 38  # rad
    GNSS_OUTAGE_S = 39  # s without a GNSS sample before the estimate counts as unsettled
    STANDSTILL_SPEED = 40  # m/s, every wheel below it = standstill (gyro offsets)
    STANDSTILL_DELAY_S = 41  # s of standstill before the gyro offsets learn
    GYRO_OFFSET_SETTLING_S = 42  # s, settling time of the standstill gyro offset filters
    YAW_ACC_CUTOFF_HZ = 43  # Hz, derivative filters of the CoG translation
    R_ROLL_STATIC = 44  # rad^2, roll pseudo-measurement from the static roll model (slipd)
    MIN_SPEED = 45  # m/s, below it beta is reported as 0 and NOT_CONVERGED (slipd)
    PITCH_FROM_BIAS = 46  # 1 = pitch -bx / g into eq. 5, 0 = the paper's pitch 0 (eq. 6)
    MAX_PITCH = 47  # rad, clamp of that pitch estimate
    YAW_BIAS_TIME_CONSTANT = 48  # s, integral correction of b_r from psi updates; 0 = off
    MAX_YAW_RATE_BIAS = 49  # rad/s, clamp of that correction
    FIELD_NORM_TOLERANCE = 50  # uT, |field norm - earth field| for a gate lock-out restart
    MU_GATE_CHI2 = 51  # chi-square (1 dof): beyond it the a_y sample is down-weighted (slipd)


DEFAULTS = {
    # the heading EKF is driven by the gyro and corrected at 50 Hz; a small yaw random walk
    # makes it average the magnetometer over seconds (passing disturbances, pitch errors) and
    # leave the gyro bias to the integral term below (suite: 1e-4 -> 3.7 deg pooled beta RMS,
    # 1e-5 -> 3.1, 1e-6 -> 2.7)
    "q_psi": 1e-6,
    "q_phi": 1e-4,
    # 1.2 uT per axis: Table 1's noise is 0.05 uT; the rest is model error of eq. 5 (soft-iron
    # residual at headings not yet calibrated, pitch from -bx / g, roll): the residual of the
    # learned model with the true attitude was 0.8-1.3 uT RMS per axis on the simulator's
    # endurance drive (suite pooled beta RMS: r_mag 0.64 -> 2.7 deg, 1.5 -> 2.2, 3.0 -> 2.2)
    "r_mag": 1.5,
    # chi-square 3 dof, 99.9 % (the paper gives the distribution, not the probability)
    "gate_chi2": 16.27,
    # longer than the simulator's and the paper's passing disturbances (trucks, poles: 1-4 s)
    "gate_lockout_s": 5.0,
    "p0_psi": 0.1,
    "p0_phi": 0.003,
    # central Europe (WMM, about 50 N 10 E): set per site; the calibration learns the rest
    "declination": math.radians(4.0),
    "inclination": math.radians(64.5),
    "field_horizontal": 21.0,
    "cal_sigma_hard_iron": 10.0,
    "cal_sigma_soft_iron": 2.0,
    "cal_r": 0.04,
    "cal_q": 1e-6,
    "cal_max_yaw_rate": math.radians(1.0),
    "cal_max_ay": 0.5,
    "cal_min_speed": 5.0,
    "align_samples": 3.0,
    "align_timeout_s": 10.0,
    "q_v": 0.05,
    "q_b": 1e-3,
    "r_gnss": 0.01,
    "p0_v": 1.0,
    "p0_b": 0.04,
    "gnss_delay": 0.4,
    "delay_compensation": 1.0,
    "antenna_x": 0.0,
    "antenna_y": 0.0,
    "antenna_z": 0.0,
    "q_mu": 0.01,
    "r_ay": 0.25,
    "p0_mu": 0.25,
    "mu_min": 0.05,
    "mu_max": 1.5,
    "mu_min_sensitivity": 2.0,
    "mu_min_speed": 5.0,
    "mu_class_updates": 50.0,
    "settle_ticks": 100.0,
    "converged_sigma_beta": 0.0175,
    "gnss_outage_s": 1.0,
    "standstill_speed": 0.1,
    "standstill_delay_s": 1.0,
    "gyro_offset_settling_s": 150.0,
    "yaw_acc_cutoff_hz": 10.0,
    # (2 deg)^2: loose enough for the magnetometer to lead, tight enough to stop the roll
    # drifting with an unremoved roll-rate bias into a wrong (heading, roll) pair
    "r_roll_static": math.radians(2.0) ** 2,
    "min_speed": 2.0,
    "pitch_from_bias": 1.0,
    "max_pitch": math.radians(10.0),
    "yaw_bias_time_constant": 60.0,
    "max_yaw_rate_bias": math.radians(2.0),
    # 3 sigma: an a_y the brush model cannot explain at any nearby mu is more likely a beta
    # error or a longitudinal force (which the paper's model leaves out) than mu
    "mu_gate_chi2": 9.0,
    # 3 uT: the norm residual of the learned calibration reached 2-3 uT in handling (roll,
    # headings not yet calibrated); a truck's disturbance is 2-15 uT
    "field_norm_tolerance": 3.0,
}

#: Friction classes of Out.FRICTION_CLASS by the estimated mu (slipd): below 0.4 low (ice,
#: snow), below 0.8 medium (wet), else high (dry).
MU_CLASS_LOW = 0.4
MU_CLASS_MEDIUM = 0.8

#: Kept across key cycles by the daemon (slipd.daemon.service.StateStore): the magnetometer
#: calibration learned on straights and its covariance, and the yaw-rate bias. Without them
#: every drive starts uncalibrated (a few degrees of heading, hence of beta, until the car has
#: driven straight at each heading again).
PERSISTENT_STATE = (
    *range(_CAL_C, _CAL_C + 9),
    *range(_CAL_P, _CAL_P + 9),
    int(S.YAW_RATE_BIAS),
)


def init(params: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """A fresh state vector: every filter waits for its first sample."""
    from slipd.errors import ConfigError

    if vehicle.shape != (len(Veh),):
        raise ConfigError(f"vehicle vector has shape {vehicle.shape}, expected ({len(Veh)},)")
    for field in (Veh.MASS, Veh.LF, Veh.LR, Veh.CORNERING_STIFFNESS_F,
                  Veh.CORNERING_STIFFNESS_R, Veh.MU_NOMINAL):  # fmt: skip
        value = float(vehicle[field])
        if not (np.isfinite(value) and value > 0.0):
            raise ConfigError(f"vehicle {field.name.lower()} = {value}: must be finite and > 0")
    delay = float(params[PARAMS.GNSS_DELAY])
    if not (0.0 <= delay <= (BUFFER_TICKS - 2) * 0.01):
        raise ConfigError(
            f"gnss_delay = {delay} s: must be within 0 .. {(BUFFER_TICKS - 2) * 0.01:.2f} s "
            f"(the history holds {BUFFER_TICKS} ticks)"
        )
    state = np.zeros(N_STATE, dtype=np.float64)
    state[S.YAW_RATE_FILTERED] = np.nan  # preprocess.derivative_filter: NaN = not started
    state[S.ROLL_RATE_FILTERED] = np.nan
    state[S.PITCH_RATE_FILTERED] = np.nan
    state[S.LAST_VN] = np.nan
    state[S.LAST_MAG_X] = np.nan
    state[S.FIRST_FIX_TICK] = np.nan
    reset_calibration(state, params)
    state[S.MU] = vehicle[Veh.MU_NOMINAL]
    state[S.MU_P] = params[PARAMS.P0_MU]
    return state


def reset_calibration(state: np.ndarray, params: np.ndarray) -> None:
    """The calibration's prior: the site field seen by an ideal magnetometer (yoon docstring)."""
    horizontal = params[PARAMS.FIELD_HORIZONTAL]
    east = horizontal * math.sin(params[PARAMS.DECLINATION])
    north = horizontal * math.cos(params[PARAMS.DECLINATION])
    up = -horizontal * math.tan(params[PARAMS.INCLINATION])
    state[_CAL_C : _CAL_C + 9] = (east, north, 0.0, north, -east, 0.0, 0.0, 0.0, up)
    soft = params[PARAMS.CAL_SIGMA_SOFT_IRON] ** 2
    hard = params[PARAMS.CAL_SIGMA_HARD_IRON] ** 2
    state[_CAL_P : _CAL_P + 9] = (soft, 0.0, 0.0, 0.0, soft, 0.0, 0.0, 0.0, hard)
    state[_CAL_PRIOR : _CAL_PRIOR + 18] = state[_CAL_C : _CAL_C + 18]


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def entry(tick):
    """Offset of the history entry of tick ``tick`` (a ring of BUFFER_TICKS)."""
    return _HISTORY + (int(tick) % BUFFER_TICKS) * ENTRY_LEN


@nb.njit(cache=True)
def gnss_to_body(v_north, v_east, v_up, psi, phi, yaw_rate, roll_rate, pitch_rate, params):
    """Eq. 10 in east-north-up: the GNSS velocity in body axes at heading psi and roll phi,
    then the antenna lever arm removed (v_CoG = v_ant - omega x rho). Returns (vx, vy)."""
    c = math.cos(psi)
    s = math.sin(psi)
    vx = c * v_east + s * v_north
    vy_level = -s * v_east + c * v_north
    vy = math.cos(phi) * vy_level + math.sin(phi) * v_up
    rho_x = params[PARAMS.ANTENNA_X]
    rho_y = params[PARAMS.ANTENNA_Y]
    rho_z = params[PARAMS.ANTENNA_Z]
    vx -= pitch_rate * rho_z - yaw_rate * rho_y
    vy -= yaw_rate * rho_x - roll_rate * rho_z
    return vx, vy


@nb.njit(cache=True)
def field_norm_error(state, m_x, m_y, m_z, phi, pitch, params):
    """How far the measured field is from the earth field, uT: the larger of the errors of its
    horizontal norm and of its vertical component, both in the level frame.

    The sample minus the hard iron (C[0,2], C[1,2], C[2,2] - b_lz) is turned back to level by
    Ry(pitch) Rx(phi) and compared with B_h and b_lz (yoon.magnetometer_model). A disturbance
    changes the norm (Sec. 2.2's basis of detection); its horizontal and vertical parts are
    checked apart because the vertical field (~44 uT) would hide a horizontal disturbance in
    the total norm. A heading error changes neither.
    """
    c0 = _CAL_C
    horizontal = math.sqrt(abs(state[c0] * state[c0 + 4] - state[c0 + 1] * state[c0 + 3]))
    b_lz = -horizontal * math.tan(params[PARAMS.INCLINATION])
    ex = m_x - state[c0 + 2]
    ey = m_y - state[c0 + 5]
    ez = m_z - (state[c0 + 8] - b_lz)
    # Rx(phi): undo the roll
    cos_phi = math.cos(phi)
    sin_phi = math.sin(phi)
    ry = cos_phi * ey - sin_phi * ez
    rz = sin_phi * ey + cos_phi * ez
    # Ry(pitch): undo the pitch
    cos_theta = math.cos(pitch)
    sin_theta = math.sin(pitch)
    lx = cos_theta * ex + sin_theta * rz
    lz = -sin_theta * ex + cos_theta * rz
    horizontal_error = abs(math.sqrt(lx * lx + ry * ry) - horizontal)
    vertical_error = abs(lz - b_lz)
    return max(horizontal_error, vertical_error)


@nb.njit(cache=True)
def start_kf(state, vx, vy, params, tick):
    """(Re)start the sideslip KF at [vx, 0, vy, 0] with P0 (biases unknown, Sec. 3.3)."""
    state[S.KF_VX] = vx
    state[S.KF_BX] = 0.0
    state[S.KF_VY] = vy
    state[S.KF_BY] = 0.0
    for i in range(16):
        state[_KF_P + i] = 0.0
    state[_KF_P] = params[PARAMS.P0_V]
    state[_KF_P + 5] = params[PARAMS.P0_B]
    state[_KF_P + 10] = params[PARAMS.P0_V]
    state[_KF_P + 15] = params[PARAMS.P0_B]
    state[S.KF_INIT] = 1.0
    state[S.KF_TICKS] = 0.0
    state[S.KF_START_TICK] = tick
    state[S.GNSS_AGE] = 0.0
    state[S.GNSS_UPDATES] = 0.0


@nb.njit(cache=True)
def start_heading(state, psi, phi, params):
    state[S.HEAD_PSI] = psi
    state[S.HEAD_PHI] = phi
    state[_HEAD_P] = params[PARAMS.P0_PSI]
    state[_HEAD_P + 1] = 0.0
    state[_HEAD_P + 2] = params[PARAMS.P0_PHI]
    state[S.HEAD_INIT] = 1.0
    state[S.GATE_REJECT_RUN] = 0.0
    state[S.HISTORY_START_TICK] = state[S.TICK]  # the stored attitudes before are stale


@nb.njit(cache=True)
def save_entry(state, tick, ax, ay_no_gravity, yaw_rate, roll_rate, pitch_rate):
    """Store the tick's KF posterior, attitude and inputs in the history."""
    e = entry(tick)
    state[e + E.PITCH] = state[S.PITCH]
    for i in range(20):
        state[e + i] = state[_KF + i]
    state[e + E.AX] = ax
    state[e + E.AY_NO_GRAVITY] = ay_no_gravity
    state[e + E.YAW_RATE] = yaw_rate
    state[e + E.PSI] = state[S.HEAD_PSI]
    state[e + E.PHI] = state[S.HEAD_PHI]
    state[e + E.ROLL_RATE] = roll_rate
    state[e + E.PITCH_RATE] = pitch_rate
    state[e + E.MAG_X] = state[S.LAST_MAG_X]
    state[e + E.MAG_Y] = state[S.LAST_MAG_Y]
    state[e + E.MAG_Z] = state[S.LAST_MAG_Z]


@nb.njit(cache=True)
def calibration_sample(state, sample_tick, v_north, v_east, params):
    """Calibrate the magnetometer against a GNSS course when the car drove straight at the
    sampling tick (beta ~ 0, so the course is the heading; slipd, see the module docstring).

    The first ``align_samples`` samples re-initialise the heading EKF (start-up alignment) and
    ask the sideslip KF to restart. Returns True when a sample was taken.
    """
    es = entry(sample_tick)
    speed = math.hypot(v_north, v_east)
    yaw_rate = state[es + E.YAW_RATE]
    if not (
        speed > params[PARAMS.CAL_MIN_SPEED]
        and abs(yaw_rate) < params[PARAMS.CAL_MAX_YAW_RATE]
        and abs(yaw_rate) * speed < params[PARAMS.CAL_MAX_AY]
        and math.isfinite(state[es + E.MAG_X])
    ):
        return False
    course = math.atan2(v_north, v_east)
    # the sample levelled: the model's change from (roll, pitch) of the sampling tick to level
    # taken off (bank and grade would otherwise enter the fit as offsets)
    inclination = params[PARAMS.INCLINATION]
    tilted = magnetometer_model(
        state, _CAL_C, course, state[es + E.PHI], state[es + E.PITCH], inclination
    )
    level = magnetometer_model(state, _CAL_C, course, 0.0, 0.0, inclination)
    m_x = state[es + E.MAG_X] - tilted[0] + level[0]
    m_y = state[es + E.MAG_Y] - tilted[1] + level[1]
    m_z = state[es + E.MAG_Z] - tilted[2] + level[2]
    # a disturbed field must not bend the fit, but a fit that went wrong must still be able to
    # come back: a sample beyond the chi-square gate is down-weighted by d^2 / gate (Huber)
    # instead of rejected
    r_sample = params[PARAMS.CAL_R]
    if state[S.CAL_SAMPLES] >= params[PARAMS.ALIGN_SAMPLES]:
        d2 = calibration_residual(
            state, _CAL_C, _CAL_P, course, m_x, m_y, m_z, params[PARAMS.R_MAG]
        )
        if d2 > params[PARAMS.GATE_CHI2]:
            r_sample *= d2 / params[PARAMS.GATE_CHI2]
    calibration_update(state, _CAL_C, _CAL_P, course, m_x, m_y, m_z, r_sample,
                       params[PARAMS.CAL_Q])  # fmt: skip
    state[S.CAL_SAMPLES] += 1.0
    if state[S.CAL_SAMPLES] <= params[PARAMS.ALIGN_SAMPLES]:
        psi = heading_from_magnetometer(state, _CAL_C, state[S.LAST_MAG_X], state[S.LAST_MAG_Y])
        if math.isfinite(psi):
            # roll 0 on the straight: the roll learned against the uncalibrated model is as
            # wrong as its heading was
            start_heading(state, psi, 0.0, params)
            # and the sideslip KF restarts: its biases would otherwise explain the jump of
            # the rotated GNSS velocity as an acceleration offset
            state[S.KF_INIT] = 0.0
    return True


@nb.njit(cache=True)
def fuse_delayed_gnss(state, tick, sample_tick, v_north, v_east, v_up, params, dt):
    """Fuse a GNSS sample taken at ``sample_tick`` (<= ``tick``), Sec. 2.3.

    Rotates it with the attitude stored for ``sample_tick`` (eq. 10), updates the stored
    posterior of that tick (eq. 11) and re-propagates eq. 9 over the stored inputs up to
    ``tick``, rewriting the history on the way so that the next delayed sample starts from the
    corrected trajectory.
    """
    es = entry(sample_tick)
    vx_meas, vy_meas = gnss_to_body(
        v_north, v_east, v_up, state[es + E.PSI], state[es + E.PHI], state[es + E.YAW_RATE],
        state[es + E.ROLL_RATE], state[es + E.PITCH_RATE], params,
    )  # fmt: skip
    q_v = params[PARAMS.Q_V] * dt
    q_b = params[PARAMS.Q_B] * dt
    r_gnss = params[PARAMS.R_GNSS]
    if sample_tick == tick:
        kf4_update_velocity(state, _KF, _KF_P, _SCRATCH, vx_meas, vy_meas, r_gnss, r_gnss)
        for i in range(20):
            state[es + i] = state[_KF + i]
        return
    # rewind to the sampling tick, update there (eq. 11), then re-run eq. 9 up to now
    for i in range(20):
        state[_KF + i] = state[es + i]
    kf4_update_velocity(state, _KF, _KF_P, _SCRATCH, vx_meas, vy_meas, r_gnss, r_gnss)
    for i in range(20):
        state[es + i] = state[_KF + i]
    j = sample_tick
    while j < tick:
        ej = entry(j)
        kf4_predict(
            state, _KF, _KF_P, _SCRATCH, state[ej + E.AX], state[ej + E.AY_NO_GRAVITY],
            state[ej + E.YAW_RATE], q_v, q_b, dt,
        )  # fmt: skip
        j += 1
        en = entry(j)
        for i in range(20):
            state[en + i] = state[_KF + i]


@nb.njit(cache=True)
def state_is_finite(state):
    for i in range(_N_FINITE):
        if not math.isfinite(state[i]):
            return False
    return True


@nb.njit(cache=True)
def beta_sigma(vx, vy, p_xx, p_xy, p_yy):
    """1-sigma of beta = atan2(vy, vx) from the [vx, vy] covariance (first order)."""
    speed2 = vx * vx + vy * vy
    if speed2 <= 1e-6:
        return math.pi
    g1 = -vy / speed2
    g2 = vx / speed2
    var = g1 * g1 * p_xx + 2.0 * g1 * g2 * p_xy + g2 * g2 * p_yy
    return math.sqrt(var) if var > 0.0 else 0.0


@nb.njit(cache=True)
def write_held(out, vx, roll, params, status):
    """Outputs while the sideslip KF cannot run: beta 0, vx from the wheels, flagged."""
    out[Out.BETA] = 0.0
    out[Out.BETA_RATE] = 0.0
    out[Out.VX] = vx
    out[Out.VY] = 0.0
    out[Out.MU] = math.nan
    out[Out.SIGMA_BETA] = math.atan(math.sqrt(params[PARAMS.P0_V]) / max(vx, 1.0))
    out[Out.ROLL] = roll
    out[Out.FRICTION_CLASS] = 0.0
    out[Out.STATUS] = float(status | ST_NOT_CONVERGED)


# ---------------------------------------------------------------------------------------------
# the tick
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def step(state, u, params, vehicle, dt, out):
    """One 100 Hz tick of the three filters; writes every element of ``out``, allocates nothing."""
    tick = state[S.TICK]
    state[S.TICK] = tick + 1.0
    status = 0

    # --- inputs: gyro offsets at standstill (eq. 7's b_r, b_p), CoG accelerations -----------
    v_fl, ok_fl = channel(u, In.WHEEL_SPEED_FL)
    v_fr, ok_fr = channel(u, In.WHEEL_SPEED_FR)
    v_rl, ok_rl = channel(u, In.WHEEL_SPEED_RL)
    v_rr, ok_rr = channel(u, In.WHEEL_SPEED_RR)
    all_wheels = ok_fl and ok_fr and ok_rl and ok_rr
    fastest = max(max(v_fl, v_fr), max(v_rl, v_rr)) if all_wheels else math.inf
    still_time = update_standstill(
        state, _OFFSETS, fastest, all_wheels, dt, params[PARAMS.STANDSTILL_SPEED]
    )
    standstill = still_time > params[PARAMS.STANDSTILL_DELAY_S]
    settling = params[PARAMS.GYRO_OFFSET_SETTLING_S]
    yaw_rate, yaw_rate_ok = channel(u, In.YAW_RATE)
    if yaw_rate_ok:
        yaw_rate -= update_gyro_offset(state, _OFFSETS, _OFF_YAW, yaw_rate, standstill, dt,
                                       settling)  # fmt: skip
    else:
        yaw_rate = state[S.PREV_YAW_RATE]
        status |= ST_INPUT_TIMEOUT
    roll_rate, roll_rate_ok = channel(u, In.ROLL_RATE)
    pitch_rate, pitch_rate_ok = channel(u, In.PITCH_RATE)
    if roll_rate_ok:
        roll_rate -= update_gyro_offset(state, _OFFSETS, _OFF_ROLL, roll_rate, standstill, dt,
                                        settling)  # fmt: skip
    else:
        roll_rate = 0.0
        status |= ST_DEGRADED  # roll from the magnetometer alone
    if pitch_rate_ok:
        pitch_rate -= update_gyro_offset(state, _OFFSETS, _OFF_PITCH, pitch_rate, standstill,
                                         dt, settling)  # fmt: skip
    else:
        pitch_rate = 0.0
    steer, steer_ok = channel(u, In.STEER)
    if steer_ok:
        state[S.LAST_STEER] = steer
    else:
        steer = state[S.LAST_STEER]
        status |= ST_INPUT_TIMEOUT
    cutoff = params[PARAMS.YAW_ACC_CUTOFF_HZ]
    ax, ay, yaw_acc, ax_ok, ay_ok = imu_at_cog(
        state, S.YAW_RATE_FILTERED, S.ROLL_RATE_FILTERED, S.PITCH_RATE_FILTERED, u, yaw_rate,
        roll_rate, pitch_rate, dt, cutoff, vehicle,
    )  # fmt: skip
    ay_imu = u[In.AY]  # at the sensor, for the static roll model below
    if ax_ok:
        state[S.LAST_AX] = ax
    else:
        ax = state[S.LAST_AX]
        status |= ST_INPUT_TIMEOUT
    if not ay_ok:
        status |= ST_INPUT_TIMEOUT
    vx_wheels, n_wheels = corner_speed_mean(u, steer, yaw_rate, vehicle)
    if n_wheels < 4:
        status |= ST_INPUT_TIMEOUT

    # --- new-sample detection (no per-channel age in u: a changed latched value) ----------
    m_x, ok_mx = channel(u, In.MAG_X)
    m_y, ok_my = channel(u, In.MAG_Y)
    m_z, ok_mz = channel(u, In.MAG_Z)
    mag_ok = ok_mx and ok_my and ok_mz
    new_mag = mag_ok and (
        m_x != state[S.LAST_MAG_X] or m_y != state[S.LAST_MAG_Y] or m_z != state[S.LAST_MAG_Z]
    )
    if mag_ok:
        state[S.MAG_SEEN] = 1.0
        state[S.LAST_MAG_X] = m_x
        state[S.LAST_MAG_Y] = m_y
        state[S.LAST_MAG_Z] = m_z
    else:
        status |= ST_INPUT_TIMEOUT
    v_north, ok_vn = channel(u, In.GNSS_VN)
    v_east, ok_ve = channel(u, In.GNSS_VE)
    v_up, ok_vu = channel(u, In.GNSS_VU)
    fix, ok_fix = channel(u, In.GNSS_FIX)
    gnss_ok = ok_vn and ok_ve and ok_vu and ok_fix and fix > 0.5
    new_gnss = gnss_ok and (
        v_north != state[S.LAST_VN] or v_east != state[S.LAST_VE] or v_up != state[S.LAST_VU]
    )
    if gnss_ok:
        state[S.GNSS_SEEN] = 1.0
        state[S.LAST_VN] = v_north
        state[S.LAST_VE] = v_east
        state[S.LAST_VU] = v_up
    else:
        status |= ST_INPUT_TIMEOUT

    # --- 1. heading EKF (eq. 5-7) with the Mahalanobis gate (Sec. 2.2) ---------------------
    if state[S.HEAD_INIT] < 0.5:
        if mag_ok:
            psi0 = heading_from_magnetometer(state, _CAL_C, m_x, m_y)
            if math.isfinite(psi0):
                start_heading(state, psi0, 0.0, params)
    else:
        heading_predict(
            state, _HEAD, _HEAD_P, state[S.PREV_YAW_RATE] - state[S.YAW_RATE_BIAS],
            state[S.PREV_ROLL_RATE],
            params[PARAMS.Q_PSI] * dt, params[PARAMS.Q_PHI] * dt, dt,
        )  # fmt: skip
        state[S.GATE_REJECT_RUN] += 1.0  # ticks since the last accepted sample
        psi_before = state[S.HEAD_PSI]
        if new_mag:
            gate = params[PARAMS.GATE_CHI2]
            if state[S.GATE_REJECT_RUN] * dt > params[PARAMS.GATE_LOCKOUT_S] and (
                field_norm_error(state, m_x, m_y, m_z, state[S.HEAD_PHI], state[S.PITCH], params)
                < params[PARAMS.FIELD_NORM_TOLERANCE]
            ):
                # lock-out: the gate has rejected for long, yet the field's norm is the earth
                # field's (Sec. 2.2's basis of disturbance detection), so the model, not the
                # field, is wrong: psi restarts from the calibrated magnetometer
                psi0 = heading_from_magnetometer(state, _CAL_C, m_x, m_y)
                if math.isfinite(psi0):
                    start_heading(state, psi0, state[S.HEAD_PHI], params)
                    state[S.HISTORY_START_TICK] = tick  # this tick's entry is still to come
            d2 = heading_update(
                state, _HEAD, _HEAD_P, state, _CAL_C, m_x, m_y, m_z, state[S.PITCH],
                params[PARAMS.R_MAG], params[PARAMS.INCLINATION], gate,
            )  # fmt: skip
            state[S.LAST_D2] = d2
            if d2 <= gate:
                state[S.GATE_ACCEPTS] += 1.0
                state[S.GATE_REJECT_RUN] = 0.0
                tau_bias = params[PARAMS.YAW_BIAS_TIME_CONSTANT]
                if tau_bias > 0.0 and gate < math.inf:
                    # slipd: the integral part of a complementary filter. A yaw-rate bias makes
                    # every update correct psi the same way; the corrections, integrated with
                    # time constant tau, are the bias (b_r of eq. 7 without a standstill)
                    correction = wrap_angle(state[S.HEAD_PSI] - psi_before)
                    limit = params[PARAMS.MAX_YAW_RATE_BIAS]
                    bias = state[S.YAW_RATE_BIAS] - correction / tau_bias
                    state[S.YAW_RATE_BIAS] = min(max(bias, -limit), limit)
            else:
                state[S.GATE_REJECTS] += 1.0
        if ay_ok and params[PARAMS.R_ROLL_STATIC] > 0.0:
            # slipd: the static roll model (Selmanaj 2017 eq. 16, preprocess.roll_static_gain)
            # as a weak pseudo-measurement; eq. 6 alone lets an uncalibrated field direction
            # trade heading for roll
            roll_static = ay_imu * roll_static_gain(
                vehicle[Veh.MASS], vehicle[Veh.H_ROLL_AXIS], vehicle[Veh.ROLL_STIFFNESS]
            )
            heading_roll_update(state, _HEAD, _HEAD_P, roll_static, params[PARAMS.R_ROLL_STATIC])
    state[S.PREV_YAW_RATE] = yaw_rate
    state[S.PREV_ROLL_RATE] = roll_rate
    head_running = state[S.HEAD_INIT] > 0.5
    roll = state[S.HEAD_PHI] if head_running else 0.0
    # eq. 9's input a_y,m - g sin(phi) (an invalid ay: the model's r vx, no lateral slip rate)
    if ay_ok:
        ay_no_gravity = ay - G * math.sin(roll)
    else:
        ay_no_gravity = yaw_rate * state[S.KF_VX]

    # --- availability: both sensors must have been seen -----------------------------------
    if state[S.MAG_SEEN] < 0.5 or not head_running:
        write_held(out, vx_wheels, roll, params, status | ST_UNAVAILABLE)
        return

    # --- 2. sideslip KF (eq. 9-11) with the delayed GNSS (Sec. 2.3) ------------------------
    kf_running = state[S.KF_INIT] > 0.5
    if kf_running:
        e_prev = entry(tick - 1.0)
        kf4_predict(
            state, _KF, _KF_P, _SCRATCH, state[e_prev + E.AX], state[e_prev + E.AY_NO_GRAVITY],
            state[e_prev + E.YAW_RATE], params[PARAMS.Q_V] * dt, params[PARAMS.Q_B] * dt, dt,
        )  # fmt: skip
        state[S.KF_TICKS] += 1.0
        state[S.GNSS_AGE] += 1.0
    save_entry(state, tick, ax, ay_no_gravity, yaw_rate, roll_rate, pitch_rate)
    if new_gnss:
        if not math.isfinite(state[S.FIRST_FIX_TICK]):
            state[S.FIRST_FIX_TICK] = tick
        delay_ticks = 0.0
        if params[PARAMS.DELAY_COMPENSATION] > 0.5:
            delay_ticks = min(float(round(params[PARAMS.GNSS_DELAY] / dt)), BUFFER_TICKS - 2.0)
        sample_tick = max(tick - delay_ticks, state[S.HISTORY_START_TICK])
        calibration_sample(state, sample_tick, v_north, v_east, params)
        if state[S.HISTORY_START_TICK] > tick:
            # the heading was just re-aligned: this tick's entry gets the new attitude
            save_entry(state, tick, ax, ay_no_gravity, yaw_rate, roll_rate, pitch_rate)
            state[S.HISTORY_START_TICK] = tick
        kf_running = state[S.KF_INIT] > 0.5  # an alignment step restarts the KF
        aligned = state[S.CAL_SAMPLES] >= 1.0 or (
            (tick - state[S.FIRST_FIX_TICK]) * dt > params[PARAMS.ALIGN_TIMEOUT_S]
        )
        sample_tick = max(sample_tick, state[S.HISTORY_START_TICK])
        if kf_running:
            sample_tick = max(sample_tick, state[S.KF_START_TICK])
            fuse_delayed_gnss(state, tick, sample_tick, v_north, v_east, v_up, params, dt)
            state[S.GNSS_AGE] = 0.0
            state[S.GNSS_UPDATES] += 1.0
        elif aligned:
            # (re)start from this sample, rotated with the attitude of its sampling tick and
            # taken as current: it is one delay old, an error of the velocity change over the
            # delay that the filter settles within SETTLE_TICKS, before convergence is claimed
            es = entry(sample_tick)
            vx0, vy0 = gnss_to_body(
                v_north, v_east, v_up, state[es + E.PSI], state[es + E.PHI],
                state[es + E.YAW_RATE], state[es + E.ROLL_RATE], state[es + E.PITCH_RATE],
                params,
            )  # fmt: skip
            start_kf(state, vx0, vy0, params, tick)
            save_entry(state, tick, ax, ay_no_gravity, yaw_rate, roll_rate, pitch_rate)
            kf_running = True
    if not kf_running:
        if state[S.GNSS_SEEN] < 0.5:
            status |= ST_UNAVAILABLE  # no fix ever: the method cannot run
        write_held(out, vx_wheels, roll, params, status)
        return

    # --- reset on a non-finite or implausible state (openpilot paramsd's rule) -------------
    vx = state[S.KF_VX]
    vy = state[S.KF_VY]
    if not state_is_finite(state) or abs(vy) > max(abs(vx), 1.0):
        state[S.KF_INIT] = 0.0
        state[S.HEAD_INIT] = 0.0
        for i in range(_CAL_C, _CAL_C + 18):
            if not math.isfinite(state[i]):  # a broken calibration restarts from its prior
                for j in range(18):
                    state[_CAL_C + j] = state[_CAL_PRIOR + j]
                state[S.CAL_SAMPLES] = 0.0
                break
        state[S.MU] = vehicle[Veh.MU_NOMINAL]
        state[S.MU_P] = params[PARAMS.P0_MU]
        state[S.MU_UPDATES] = 0.0
        write_held(out, vx_wheels, 0.0, params, status | ST_RESET)
        return

    if params[PARAMS.PITCH_FROM_BIAS] > 0.5:
        # slipd: eq. 9's bx holds the accelerometer offset minus g sin(pitch) (a_x,m =
        # vx' - r vy - g sin(theta) + offset in ISO 8855); the offset (~0.1 m/s^2 = 0.6 deg) is
        # the smaller part on a road with grades, so theta ~ -bx / g
        max_pitch = params[PARAMS.MAX_PITCH]
        state[S.PITCH] = min(max(-state[S.KF_BX] / G, -max_pitch), max_pitch)
    if vx < params[PARAMS.MIN_SPEED]:
        # beta = atan2(vy, vx) is undefined at standstill; the filters keep running
        write_held(out, max(vx, 0.0), roll, params, status)
        return

    # --- 3. friction EKF (eq. 13-16) -------------------------------------------------------
    beta = math.atan2(vy, vx)
    mu = state[S.MU]
    state[S.MU_P] += params[PARAMS.Q_MU] * dt  # f(mu) = mu
    if ay_ok and vx > params[PARAMS.MU_MIN_SPEED]:
        ay_model, h_mu = lateral_acceleration_model(
            mu, beta, yaw_rate, vx, steer, vehicle[Veh.MASS], vehicle[Veh.LF], vehicle[Veh.LR],
            vehicle[Veh.CORNERING_STIFFNESS_F], vehicle[Veh.CORNERING_STIFFNESS_R],
        )  # fmt: skip
        if abs(h_mu) >= params[PARAMS.MU_MIN_SENSITIVITY]:
            p_mu = state[S.MU_P]
            r_ay = params[PARAMS.R_AY]
            innovation = ay_no_gravity - ay_model
            d2 = innovation * innovation / (h_mu * p_mu * h_mu + r_ay)
            if d2 > params[PARAMS.MU_GATE_CHI2]:
                r_ay *= d2 / params[PARAMS.MU_GATE_CHI2]  # Huber: bounded pull, no lock-out
            innovation_variance = h_mu * p_mu * h_mu + r_ay
            gain = p_mu * h_mu / innovation_variance
            mu += gain * innovation
            state[S.MU] = min(max(mu, params[PARAMS.MU_MIN]), params[PARAMS.MU_MAX])
            state[S.MU_P] = (1.0 - gain * h_mu) * p_mu
            state[S.MU_UPDATES] += 1.0

    # --- outputs ---------------------------------------------------------------------------
    sigma = beta_sigma(vx, vy, state[_KF_P], state[_KF_P + 2], state[_KF_P + 10])
    if (
        state[S.KF_TICKS] < params[PARAMS.SETTLE_TICKS]
        or state[S.CAL_SAMPLES] < params[PARAMS.ALIGN_SAMPLES]
        or state[S.GNSS_AGE] * dt > params[PARAMS.GNSS_OUTAGE_S]
        or not (sigma <= params[PARAMS.CONVERGED_SIGMA_BETA])
    ):
        status |= ST_NOT_CONVERGED
    speed2 = vx * vx + vy * vy
    ax_kin = ax - state[S.KF_BX]
    ay_kin = ay_no_gravity - state[S.KF_BY]
    out[Out.BETA] = beta
    out[Out.BETA_RATE] = (vx * ay_kin - vy * ax_kin) / speed2 - yaw_rate if speed2 > 1.0 else 0.0
    out[Out.VX] = vx
    out[Out.VY] = vy
    out[Out.MU] = state[S.MU]
    out[Out.SIGMA_BETA] = sigma
    out[Out.ROLL] = roll
    friction_class = 0.0
    if state[S.MU_UPDATES] >= params[PARAMS.MU_CLASS_UPDATES]:
        if state[S.MU] < MU_CLASS_LOW:
            friction_class = 1.0
        elif state[S.MU] < MU_CLASS_MEDIUM:
            friction_class = 2.0
        else:
            friction_class = 3.0
    out[Out.FRICTION_CLASS] = friction_class
    out[Out.STATUS] = float(status)


@nb.njit(cache=True)
def run_ticks(state, U, params, vehicle, dt, OUT):
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])


@nb.njit(cache=True)
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


__all__ = ["PARAMS", "DEFAULTS", "REQUIRED", "init", "step", "run_ticks", "wrap_angle"]
