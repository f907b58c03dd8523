"""The stages of a ``gnss_magnetometer`` tick that run the heading EKF and bring the GNSS in:
start-up alignment and the magnetometer calibration (slipd's, ``heading`` module docstring),
the gated magnetometer update with its lock-out and yaw-bias trim, and a new (delayed) GNSS
sample. Each takes the method's params vector (``params.PARAMS``)."""

from __future__ import annotations

import math

import numpy as np

from slipd.channels import G
from slipd.estimators.common.kinematics import vehicle_roll_gain
from slipd.estimators.yoon2016.heading import (
    calibration_residual,
    calibration_update,
    field_norm_error,
    heading_course_correction,
    heading_from_magnetometer,
    heading_predict,
    heading_roll_update,
    heading_update,
    magnetometer_model,
    wrap_angle,
)
from slipd.estimators.yoon2016.params import PARAMS
from slipd.estimators.yoon2016.sideslip import (
    entry,
    fuse_delayed_gnss,
    gnss_to_body,
    save_entry,
    start_kf,
)
from slipd.estimators.yoon2016.state import (
    BUFFER_TICKS,
    CAL_C,
    CAL_P,
    CAL_PRIOR,
    HEAD,
    HEAD_P,
    SCRATCH,
    E,
    S,
)
from slipd.numba_cache import nb

#: |sin| bound of the tilt pseudo-measurement (30 deg: beyond any car's roll and bank)
MAX_TILT_SINE = 0.5


def reset_calibration(state: np.ndarray, params: np.ndarray) -> None:
    """The calibration's prior: the site field seen by an ideal magnetometer (heading docstring)."""
    horizontal = params[PARAMS.FIELD_HORIZONTAL]
    east = horizontal * math.sin(params[PARAMS.DECLINATION])
    north = horizontal * math.cos(params[PARAMS.DECLINATION])
    up = -horizontal * math.tan(params[PARAMS.INCLINATION])
    state[CAL_C : CAL_C + 9] = (east, north, 0.0, north, -east, 0.0, 0.0, 0.0, up)
    soft = params[PARAMS.CAL_SIGMA_SOFT_IRON] ** 2
    hard = params[PARAMS.CAL_SIGMA_HARD_IRON] ** 2
    state[CAL_P : CAL_P + 9] = (soft, 0.0, 0.0, 0.0, soft, 0.0, 0.0, 0.0, hard)
    state[CAL_PRIOR : CAL_PRIOR + 18] = state[CAL_C : CAL_C + 18]


@nb.njit(cache=True, _nrt=False)
def start_heading(state, psi, phi, params):
    state[S.HEAD_PSI] = psi
    state[S.HEAD_PHI] = phi
    state[HEAD_P] = params[PARAMS.P0_PSI]
    state[HEAD_P + 1] = 0.0
    state[HEAD_P + 2] = params[PARAMS.P0_PHI]
    state[S.HEAD_INIT] = 1.0
    state[S.GATE_REJECT_RUN] = 0.0
    state[S.HISTORY_START_TICK] = state[S.TICK]  # the stored attitudes before are stale


@nb.njit(cache=True, inline="always")
def driving_straight(yaw_rate, speed, params):
    """The calibration's "straight" (beta ~ 0): |r| below ``cal_max_yaw_rate`` and the
    centripetal |r V| below ``cal_max_ay`` (False for a non-finite speed)."""
    return (abs(yaw_rate) < params[PARAMS.CAL_MAX_YAW_RATE]
            and abs(yaw_rate) * speed < params[PARAMS.CAL_MAX_AY])


@nb.njit(cache=True, inline="always")
def trim_yaw_rate_bias(state, params, correction):
    """slipd: the integral part of a complementary filter. A yaw-rate bias makes every heading
    update correct psi the same way; the corrections, integrated with time constant
    ``yaw_bias_time_constant``, are the bias (b_r of eq. 7 without a standstill)."""
    tau_bias = params[PARAMS.YAW_BIAS_TIME_CONSTANT]
    if tau_bias > 0.0:
        limit = params[PARAMS.MAX_YAW_RATE_BIAS]
        bias = state[S.YAW_RATE_BIAS] - correction / tau_bias
        state[S.YAW_RATE_BIAS] = min(max(bias, -limit), limit)


@nb.njit(cache=True, _nrt=False)
def course_update(state, params, tick, sample_tick, course, speed):
    """The GNSS course of a straight into the heading EKF (``course_heading``, slipd): the
    heading and roll at the sampling tick corrected (``heading_course_correction``) and the
    correction carried to everything that was computed with them since."""
    es = entry(sample_tick)
    # the course's variance: the GNSS velocity's noise across the track, r_gnss / V^2, and the
    # sideslip a straight still has (R_COURSE)
    d_psi, d_phi = heading_course_correction(
        state, HEAD, HEAD_P, wrap_angle(course - state[es + E.PSI]),
        params[PARAMS.R_GNSS] / (speed * speed) + params[PARAMS.R_COURSE],
    )  # fmt: skip
    # a yaw-rate offset shows in these corrections as in the magnetometer's
    trim_yaw_rate_bias(state, params, d_psi)
    # the attitude stored from the sampling tick on, so that this and the next delayed samples
    # are rotated with the heading as now known (eq. 10) ...
    j = sample_tick
    while j <= tick:
        ej = entry(j)
        state[ej + E.PSI] = wrap_angle(state[ej + E.PSI] + d_psi)
        state[ej + E.PHI] += d_phi
        j += 1
    # ... and the sideslip KF's body-frame velocity at the sampling tick (the delayed fusion
    # re-propagates from there), which followed the GNSS velocity rotated with the old heading:
    # it turns with the heading, else the step would be read as an acceleration offset
    c, s = math.cos(d_psi), math.sin(d_psi)
    vx, vy = state[es + E.VX], state[es + E.VY]
    state[es + E.VX] = c * vx + s * vy
    state[es + E.VY] = -s * vx + c * vy
    if sample_tick == tick:
        state[S.KF_VX] = state[es + E.VX]
        state[S.KF_VY] = state[es + E.VY]


@nb.njit(cache=True, _nrt=False)
def calibration_sample(state, tick, sample_tick, v_north, v_east, params, dt):
    """Calibrate the magnetometer against a GNSS course when the car drove straight at the
    sampling tick (beta ~ 0, so the course is the heading; slipd, see the module docstring),
    and correct the heading with that course (``course_update``) when the straight has lasted.

    The first ``align_samples`` samples re-initialise the heading EKF (start-up alignment) and
    ask the sideslip KF to restart. Returns True when a sample was taken.
    """
    es = entry(sample_tick)
    speed = math.hypot(v_north, v_east)
    yaw_rate = state[es + E.YAW_RATE]
    if not (
        speed > params[PARAMS.CAL_MIN_SPEED]
        and driving_straight(yaw_rate, speed, params)
        and math.isfinite(state[es + E.MAG_X])
    ):
        return False
    course = math.atan2(v_north, v_east)
    # the course as the heading: once aligned, on a straight that began COURSE_MIN_STRAIGHT_S
    # before the sampling tick and has lasted until now
    if (params[PARAMS.COURSE_HEADING] > 0.5
            and state[S.CAL_SAMPLES] >= params[PARAMS.ALIGN_SAMPLES]
            and state[S.STRAIGHT_S] >= (tick - sample_tick) * dt
            + params[PARAMS.COURSE_MIN_STRAIGHT_S]):
        course_update(state, params, tick, sample_tick, course, speed)
    # the sample levelled: the model's change from (roll, pitch) of the sampling tick to level
    # taken off (bank and grade would otherwise enter the fit as offsets)
    inclination = params[PARAMS.INCLINATION]
    tilted = magnetometer_model(
        state, CAL_C, course, state[es + E.PHI], state[es + E.PITCH], inclination
    )
    level = magnetometer_model(state, CAL_C, course, 0.0, 0.0, inclination)
    m_x = state[es + E.MAG_X] - tilted[0] + level[0]
    m_y = state[es + E.MAG_Y] - tilted[1] + level[1]
    m_z = state[es + E.MAG_Z] - tilted[2] + level[2]
    # a disturbed field must not bend the fit, but a fit that went wrong must still be able to
    # come back: a sample beyond the chi-square gate is down-weighted by d^2 / gate (Huber)
    # instead of rejected
    r_sample = params[PARAMS.CAL_R]
    if state[S.CAL_SAMPLES] >= params[PARAMS.ALIGN_SAMPLES]:
        d2 = calibration_residual(
            state, CAL_C, CAL_P, course, m_x, m_y, m_z, params[PARAMS.R_MAG]
        )
        if d2 > params[PARAMS.GATE_CHI2]:
            r_sample *= d2 / params[PARAMS.GATE_CHI2]
    calibration_update(state, CAL_C, CAL_P, course, m_x, m_y, m_z, r_sample,
                       params[PARAMS.CAL_Q])  # fmt: skip
    state[S.CAL_SAMPLES] += 1.0
    if state[S.CAL_SAMPLES] <= params[PARAMS.ALIGN_SAMPLES]:
        psi = heading_from_magnetometer(state, CAL_C, state[S.LAST_MAG_X], state[S.LAST_MAG_Y])
        if math.isfinite(psi):
            # roll 0 on the straight: the roll learned against the uncalibrated model is as
            # wrong as its heading was
            start_heading(state, psi, 0.0, params)
            # and the sideslip KF restarts: its biases would otherwise explain the jump of
            # the rotated GNSS velocity as an acceleration offset
            state[S.KF_INIT] = 0.0
    return True


@nb.njit(cache=True, inline="always")
def magnetometer_update(state, params, tick, m_x, m_y, m_z, dt):
    """A new magnetometer sample into the heading EKF behind the gate (Sec. 2.2), with the
    gate lock-out and the integral trim of the yaw-rate bias (slipd, module docstring)."""
    psi_before = state[S.HEAD_PSI]
    gate = params[PARAMS.GATE_CHI2]
    if state[S.GATE_REJECT_RUN] * dt > params[PARAMS.GATE_LOCKOUT_S] and (
        field_norm_error(state, CAL_C, m_x, m_y, m_z, state[S.HEAD_PHI], state[S.PITCH],
                         params[PARAMS.INCLINATION])
        < params[PARAMS.FIELD_NORM_TOLERANCE]
    ):  # fmt: skip
        # lock-out: the gate has rejected for long, yet the field's norm is the earth
        # field's (Sec. 2.2's basis of disturbance detection), so the model, not the
        # field, is wrong: psi restarts from the calibrated magnetometer
        psi0 = heading_from_magnetometer(state, CAL_C, m_x, m_y)
        if math.isfinite(psi0):
            start_heading(state, psi0, state[S.HEAD_PHI], params)
            state[S.HISTORY_START_TICK] = tick  # this tick's entry is still to come
    d2 = heading_update(
        state, HEAD, HEAD_P, state, CAL_C, m_x, m_y, m_z, state[S.PITCH],
        params[PARAMS.R_MAG], params[PARAMS.INCLINATION], gate,
    )  # fmt: skip
    state[S.LAST_D2] = d2
    if not d2 <= gate:
        state[S.GATE_REJECTS] += 1.0
        return
    state[S.GATE_ACCEPTS] += 1.0
    state[S.GATE_REJECT_RUN] = 0.0
    if gate < math.inf:
        trim_yaw_rate_bias(state, params, wrap_angle(state[S.HEAD_PSI] - psi_before))


@nb.njit(cache=True, inline="always")
def heading_tick(state, params, vehicle, tick, m_x, m_y, m_z, mag_ok, new_mag, ay_imu, ay_ok,
                  tilt_seen, tilt_speed, dt):  # fmt: skip
    """1. the heading EKF (eq. 5-7): started from the magnetometer, then predicted with the
    bias-free rates of tick k-1 and updated with each new sample (``_magnetometer_update``) and
    the static roll pseudo-measurement (slipd)."""
    if state[S.HEAD_INIT] < 0.5:
        if mag_ok:
            psi0 = heading_from_magnetometer(state, CAL_C, m_x, m_y)
            if math.isfinite(psi0):
                start_heading(state, psi0, 0.0, params)
        return
    heading_predict(
        state, HEAD, HEAD_P, state[S.PREV_YAW_RATE] - state[S.YAW_RATE_BIAS],
        state[S.PREV_ROLL_RATE], params[PARAMS.Q_PSI] * dt, params[PARAMS.Q_PHI] * dt, dt,
    )  # fmt: skip
    state[S.GATE_REJECT_RUN] += 1.0  # ticks since the last accepted sample
    if new_mag:
        magnetometer_update(state, params, tick, m_x, m_y, m_z, dt)
    if ay_ok and params[PARAMS.R_ROLL_STATIC] > 0.0:
        # slipd: the static roll model (Selmanaj 2017 eq. 16, common.kinematics) as a weak
        # pseudo-measurement; eq. 6 alone lets an uncalibrated field direction trade heading
        # for roll
        heading_roll_update(state, HEAD, HEAD_P, SCRATCH,
                            roll_pseudo_measurement(state, params, vehicle, ay_imu,
                                                    tilt_seen, tilt_speed),
                            params[PARAMS.R_ROLL_STATIC])  # fmt: skip


@nb.njit(cache=True, inline="always")
def roll_pseudo_measurement(state, params, vehicle, ay_imu, tilt_seen, speed):
    """The roll the heading EKF's weak pseudo-measurement pulls phi towards (slipd).

    ``roll_tilt``, where the accelerometer carries gravity and the driving is quasi-steady
    (``tilt_seen``) and a speed is known (``speed``, finite: the wheels' v_x, which no
    heading error can bend, else the sideslip KF's): the tilt the accelerometer sees, phi =
    asin((a_y - r v_x) / g), a_y less the centripetal part (the speed-aided attitude of an
    AHRS). It is body roll and road bank together, the total tilt that turns
    the vertical field into the magnetometer's y axis and g into a_y; its error is the
    lateral slip rate v_y', small in quasi-steady driving (and averaged by the loose
    variance), large in a slalom, hence the condition. Else the static roll model (Selmanaj
    2017 eq. 16, ``vehicle_roll_gain``): body roll only, no bank; the only choice for a
    levelled accelerometer (whose a_y shows no tilt)."""
    if params[PARAMS.ROLL_TILT] > 0.5 and tilt_seen and math.isfinite(speed):
        sine = (ay_imu - state[S.PREV_YAW_RATE] * speed) / G
        return math.asin(min(max(sine, -MAX_TILT_SINE), MAX_TILT_SINE))
    return ay_imu * vehicle_roll_gain(vehicle)


@nb.njit(cache=True, inline="always")
def gnss_sample(state, params, tick, ax, ay_no_gravity, yaw_rate, roll_rate, pitch_rate,
                 v_north, v_east, v_up, dt):  # fmt: skip
    """A new GNSS sample (Sec. 2.3): calibrates the magnetometer when the car drove straight at
    its sampling tick, then is fused into the running sideslip KF at that tick, or (re)starts
    the KF once aligned. Returns whether the KF runs."""
    if not math.isfinite(state[S.FIRST_FIX_TICK]):
        state[S.FIRST_FIX_TICK] = tick
    delay_ticks = 0.0
    if params[PARAMS.DELAY_COMPENSATION] > 0.5:
        delay_ticks = min(float(round(params[PARAMS.GNSS_DELAY] / dt)), BUFFER_TICKS - 2.0)
    sample_tick = max(tick - delay_ticks, state[S.HISTORY_START_TICK])
    calibration_sample(state, tick, sample_tick, v_north, v_east, params, dt)
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
        fuse_delayed_gnss(
            state, tick, sample_tick, v_north, v_east, v_up, params[PARAMS.ANTENNA_X],
            params[PARAMS.ANTENNA_Y], params[PARAMS.ANTENNA_Z], params[PARAMS.Q_V] * dt,
            params[PARAMS.Q_B] * dt, params[PARAMS.R_GNSS], dt,
        )  # fmt: skip
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
            params[PARAMS.ANTENNA_X], params[PARAMS.ANTENNA_Y], params[PARAMS.ANTENNA_Z],
        )  # fmt: skip
        start_kf(state, vx0, vy0, params[PARAMS.P0_V], params[PARAMS.P0_B], tick)
        save_entry(state, tick, ax, ay_no_gravity, yaw_rate, roll_rate, pitch_rate)
        kf_running = True
    return kf_running

