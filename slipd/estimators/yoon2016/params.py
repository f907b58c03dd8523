"""The params of ``gnss_magnetometer`` (Yoon, Li, Ahn 2016). The paper publishes no covariances,
thresholds or start values; every default is slipd's and says what it was chosen from. Table 1
gives the sensor noise (magnetometer 0.5 mG = 0.05 uT, IMU 0.02 m/s^2 and 0.08 deg/s); the
filters' R and Q are larger because they also carry model error (pitch neglected in eq. 6,
calibration residual, roll in eq. 9)."""

from __future__ import annotations

import enum
import math


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
    ACCEL_LOWPASS_HZ = 52  # accelerometer vibration low-pass, Hz; 0 = none (the paper)
    ROLL_TILT = 53  # 1: the roll pseudo-measurement is the tilt asin((a_y - r v_x) / g)
    PITCH_FROM_GNSS = 54  # 1: pitch = -(the GNSS velocity's climb angle), 0: pitch_from_bias
    COURSE_HEADING = 55  # 1: on a straight the GNSS course is a heading measurement (slipd)
    R_COURSE = 56  # rad^2, its variance beyond the GNSS noise: the sideslip of a straight
    COURSE_MIN_STRAIGHT_S = 57  # s of straight driving before the sampling tick it needs

DEFAULTS = {
    # the heading EKF is driven by the gyro and corrected at 50 Hz; a small yaw random walk
    # makes it average the magnetometer over seconds (passing disturbances, pitch errors) and
    # leave the gyro bias to the integral term below (the sweep: benchmarks/MEASUREMENTS.md)
    "q_psi": 1e-6,
    "q_phi": 1e-4,
    # 1.2 uT per axis: Table 1's noise is 0.05 uT; the rest is model error of eq. 5 (soft-iron
    # residual at headings not yet calibrated, pitch from -bx / g, roll): the residual of the
    # learned model with the true attitude was 0.8-1.3 uT RMS per axis on the simulator's
    # endurance drive (the sweep of r_mag: benchmarks/MEASUREMENTS.md)
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
    "accel_lowpass_hz": 0.0,
    # 1: the roll pseudo-measurement is the accelerometer's tilt in quasi-steady driving
    # (bank included), 0: the static roll model always (gnss_magnetometer's docstring)
    "roll_tilt": 1.0,
    # 1: the pitch fed to eq. 5 is the road's grade from the GNSS climb angle (a levelled
    # accelerometer has none in its bx; gnss_magnetometer's docstring has the figures)
    "pitch_from_gnss": 1.0,
    # 1: the GNSS course of a straight corrects the heading (gnss_magnetometer's docstring
    # has the figures); 0: the paper's magnetometer heading
    "course_heading": 1.0,
    # (0.3 deg)^2: a 3 deg cross slope holds a car at ~0.2 deg of sideslip on a straight; the
    # GNSS velocity's own noise across the track, r_gnss / V^2, is added per sample
    "r_course": math.radians(0.3) ** 2,
    # 1 s: a corner's sideslip has decayed (the yaw mode's time constant is 0.1-0.3 s), and a
    # drift's reversal, where the yaw rate crosses zero at 20 deg of sideslip, is not a straight
    "course_min_straight_s": 1.0,
}
