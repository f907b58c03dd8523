"""The params of ``kinematic_heuristic`` (Selmanaj et al. 2017): Table 1 verbatim and the
defaults, each departure from the table with its reason (the method's docstring explains the
derivative widths and the extensions)."""

from __future__ import annotations

import enum
import math

from slipd.estimators.common.filters import DERIVATIVE_CUTOFF_HZ
from slipd.estimators.common.inputs import ACCEL_OFFSET_SETTLING_S, GYRO_OFFSET_SETTLING_S


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
    ROLL_GAIN_LEARNING = 34  # 1: eq. 16's static roll gain learnt from the drive, 0 = paper
    ACCEL_LOWPASS_HZ = 35  # accelerometer vibration low-pass, Hz; 0 = none (the paper)
    STEADY_BIAS_STRAIGHT_FORGET = 36  # s, the steady bias fades on straights (weight F), 0 = held
    STEADY_JERK_NOISE_WIDTH = 37  # -, the jerk bell at least this x its noise; 0 = fixed width
    NOISE_STRAIGHT_YAW_RATE = 38  # rad/s, below it (for 2 s) the jerk is noise
    NOISE_TIME_CONSTANT = 39  # s, averaging of that noise


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
    "derivative_cutoff_hz": DERIVATIVE_CUTOFF_HZ,
    "gyro_offset_settling": GYRO_OFFSET_SETTLING_S,
    "accel_offset_settling": ACCEL_OFFSET_SETTLING_S,
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
    # A straight ends the corner whose bank the steady bias learnt: it fades there (weight
    # F / f_gain) with F_max's own 1 s time constant (figures in benchmarks/MEASUREMENTS.md).
    "steady_bias_straight_forget": 1.0,
    # The paper's rule for its bell widths (section 2.1, "wider than the noise of the
    # signal") applied online to the steady detector's jerk bell (not in the paper; 0 = the
    # fixed width): at least 12 x (the multiple the steady bells were set with above) the RMS
    # of the jerk on straights (|omega_z| below Carnier 2023's omega_z bar, 5 deg/s, for 2 s,
    # as hybrid_friction's switches; averaged over 10 s). The default profile's sensors leave
    # it at sigma_steady_jerk; a raw, vibrating IMU widens it (benchmarks/MEASUREMENTS.md).
    "steady_jerk_noise_width": 12.0,
    "noise_straight_yaw_rate": math.radians(5.0),
    "noise_time_constant": 10.0,
    # Extension, not in the paper (0 = eq. 16 with the profile's roll data): the gravity share
    # of ay learnt from quasi-steady driving (kinematics.learn_gravity_share); a wrong roll
    # stiffness or a levelled accelerometer otherwise biases ay in every corner (issue 17).
    "roll_gain_learning": 1.0,
    # Extension, not in the paper (0 = the paper, whose ESC sensor is filtered already): a raw
    # IMU on a car body carries ~1 m/s^2 of vibration above 5 Hz (the revs_250lm run), which
    # keeps the straight-running bells of eq. 5-7 from closing; 5 Hz is above the vehicle's
    # lateral dynamics (yaw and roll modes 1-2 Hz).
    "accel_lowpass_hz": 5.0,
}
