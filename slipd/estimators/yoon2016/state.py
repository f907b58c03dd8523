"""The state vector of ``gnss_magnetometer`` and the history entry of its sideslip KF."""

from __future__ import annotations

from slipd.estimators.common.inputs import ImuMemory, Offsets
from slipd.estimators.common.layout import build_layout

#: Ticks of filter history kept for the delayed GNSS samples (0.63 s at 100 Hz > 0.4 s delay).
BUFFER_TICKS = 64
#: Slots of the sideslip KF's covariance (4 x 4 symmetric, packed: common.kalman.tri).
KF_P_LEN = 10

#: One history entry of the sideslip KF (``ENTRY.size`` slots per tick).
ENTRY = build_layout(
    "yoon2016_entry",
    "VX", "BX", "VY", "BY",  # a posteriori state [vx, bx, vy, by] at the end of the tick
    ("P", KF_P_LEN),  # its covariance
    "AX",  # m/s^2, CoG, the input of the prediction from this tick to the next
    "AY_NO_GRAVITY",  # m/s^2, a_y - g sin(phi)
    "YAW_RATE",  # rad/s, bias removed
    "PSI",  # rad, heading EKF at this tick (rotates a GNSS sample taken now, eq. 10)
    "PHI",  # rad
    "ROLL_RATE",  # rad/s (antenna lever arm)
    "PITCH_RATE",
    "MAG_X", "MAG_Y", "MAG_Z",  # uT, newest raw magnetometer sample (calibration)
    "PITCH",  # rad, pitch estimate at this tick (-bx / g)
)  # fmt: skip
E = ENTRY.S

LAYOUT = build_layout(
    "yoon2016",
    # --- checked for finiteness (filters and calibration): KF_VX .. CAL_P
    "KF_VX",  # m/s        sideslip KF x = [vx, bx, vy, by] (eq. 9)
    "KF_BX",  # m/s^2
    "KF_VY",  # m/s
    "KF_BY",  # m/s^2
    ("KF_P", KF_P_LEN),  # P packed
    "HEAD_PSI",  # rad, heading from east, CCW (heading EKF, eq. 7)
    "HEAD_PHI",  # rad, roll (ISO 8855)
    ("HEAD_P", 3),  # packed: p_psi_psi, p_psi_phi, p_phi_phi
    "MU",  # friction EKF (eq. 16)
    "MU_P",
    ("CAL_C", 9),  # magnetometer calibration C, row-major (heading module docstring)
    ("CAL_P", 9),  # its RLS covariance (adjacent to CAL_C: CAL_PRIOR copies both)
    # --- bookkeeping
    "MAG_SEEN",  # 1 once a magnetometer sample was valid
    "GNSS_SEEN",  # 1 once a GNSS fix was valid
    "HEAD_INIT",  # 1 while the heading EKF runs
    "KF_INIT",  # 1 while the sideslip KF runs
    "KF_TICKS",  # ticks since the sideslip KF (re)started
    "TICK",  # ticks since init (the history's clock)
    "KF_START_TICK",  # tick the sideslip KF (re)started: the oldest usable history entry
    "GATE_REJECT_RUN",  # ticks since the last accepted magnetometer sample
    "GATE_REJECTS",  # total rejected samples (diagnostics)
    "GATE_ACCEPTS",  # total accepted samples
    "CAL_SAMPLES",  # calibration samples taken
    "MU_UPDATES",  # excited friction updates since (re)start
    "GNSS_AGE",  # ticks since the last fused GNSS sample
    "LAST_VN", "LAST_VE", "LAST_VU",  # last latched GNSS velocity (new-sample detection)
    "LAST_MAG_X", "LAST_MAG_Y", "LAST_MAG_Z",  # last latched magnetometer sample
    "PREV_YAW_RATE",  # rad/s, bias-free rates of tick k-1 (eq. 7 time update)
    "PREV_ROLL_RATE",
    "LAST_D2",  # Mahalanobis d^2 of the newest magnetometer sample (diagnostics)
    ("IMU", ImuMemory),  # CoG translation filters, held ax and steer (its ROLL is unused)
    ("OFFSETS", Offsets),  # gyro offsets learnt at standstill
    "GNSS_UPDATES",  # GNSS samples fused since the KF (re)started
    "HISTORY_START_TICK",  # first tick of the history since the heading EKF (re)started
    "FIRST_FIX_TICK",  # tick of the first GNSS fix (NaN: none yet)
    "PITCH",  # rad, pitch estimate fed to the magnetometer model (slipd)
    "YAW_RATE_BIAS",  # rad/s, b_r of eq. 7 left after the standstill offset (slipd)
    "PATH_ANGLE",  # rad, climb angle atan(v_up / v_h) of the newest GNSS sample (NaN: none)
    "PATH_ANGLE_SLOW",  # rad, its average from 0: the road's grade (slipd)
    "YAW_ACC_SLOW",  # rad/s^2, low-passed yaw acceleration: the tilt's quasi-steady test (slipd)
    "STRAIGHT_S",  # s the car has driven straight without a break, up to now (course_heading)
    ("CAL_PRIOR", 18),  # the calibration's prior C and covariance, for a reset
    ("SCRATCH", 16),  # working memory
    ("HISTORY", BUFFER_TICKS * ENTRY.size),
)  # fmt: skip
S = LAYOUT.S
KF = int(S.KF_VX)
KF_P = int(S.KF_P)
#: the KF's state and covariance: what a history entry starts with
KF_LEN = 4 + KF_P_LEN
HEAD = int(S.HEAD_PSI)
HEAD_P = int(S.HEAD_P)
CAL_C = int(S.CAL_C)
CAL_P = int(S.CAL_P)
CAL_PRIOR = int(S.CAL_PRIOR)
FINITE_END = CAL_P + 9  # slots 0 .. FINITE_END - 1 must stay finite
IMU = int(S.IMU)
OFFSETS = int(S.OFFSETS)
SCRATCH = int(S.SCRATCH)
HISTORY = int(S.HISTORY)
ENTRY_LEN = ENTRY.size
