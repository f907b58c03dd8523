"""Shared kernels of Chen et al. 2018, pseudo-multi-sensor fusion (``pseudo_fusion`` and parts).

T. Chen, L. Chen, Y. Cai, X. Xu, "Estimation of vehicle sideslip angle via pseudo-multisensor
information fusion method", Metrol. Meas. Syst. 25(3), 2018
(shared/papers/chen2018-pseudo-multisensor-fusion.md).

Three sideslip estimators ("pseudo-sensors") run side by side on the same inputs, each giving
x_i = (gamma_i, beta_i) (yaw rate, sideslip), and are fused by the matrix-weighted linear
minimum-variance rule (Sec. 3.2):

KBE, kinematics-based estimator (Sec. 2.1), state [vx, vy]
    eq. 1-2  vx' = ax + vy r,  vy' = ay - vx r (integrated, forward Euler), eq. 3 beta = vy / vx
             (slipd writes atan2(vy, vx), equal to first order). gamma_1 is the measured yaw rate
             (the paper: "in x_1, the estimation of yaw rate is the real yaw rate").
    slipd additions (the open integral of eq. 2 drifts without bound: gyro and accelerometer
    offsets of the simulator's production sensors integrate to metres per second within a
    minute): the integral is run as a Kalman filter whose vx is corrected by the wheel-based
    speed (R ``r_vx_kbe``) and whose vy is pulled to 0 by a pseudo-measurement only while the
    car runs straight: R = ``r_vy0_kbe`` / F with F = exp(-(r^2 / s_r^2 + ay^2 / s_ay^2) / 2)
    the Gaussian straight-running heuristic of Selmanaj et al. 2017 (eq. 5-6). In a corner
    F ~ 0 and the integral runs open, as in the paper. Its covariance (random-walk process
    noise ``q_vx_kbe``, ``q_vy_kbe``) is the KBE's own error covariance for the fusion.

DBE, dynamics-based estimator (Sec. 2.2), EKF on x_v = [vx, vy, r] (eq. 8)
    eq. 4   3-DOF model, four wheels, forces rotated by the steer angle at the front
    eq. 5   lateral tyre force, magic formula Fy = D sin(C atan(B a - E (B a - atan(B a)))),
            D = mu Fz; B, C, E and mu from the vehicle profile (TYRE_B/C/E, MU_NOMINAL)
    eq. 6   vertical loads with longitudinal and lateral load transfer from the measured ax, ay
    eq. 7   wheel slip angles
    eq. 9   prediction by the second-order Taylor step x + f T + A f T^2 / 2 (the paper prints
            "f T + f T^2 / 2", dimensionally a typo for the Jacobian term), eq. 10 P = phi P
            phi' + Q with phi = I + A T
    eq. 11-13 update with y_v = [ax, ay] (the paper's measurements), here plus the wheel-based
            vx (slipd: without it nothing observes vx and it drifts with the force errors).
            The measurements are processed one scalar at a time with innovations corrected for
            the earlier ones (exactly the batch update of eq. 11-13 with a diagonal R).
    The longitudinal tyre forces come from the wheel torques, Fx = (T_drive - T_brake -
    J_w dw/dt) / r_w (the paper uses the force observer of its ref. [4]); without torque
    frames the total m ax is shared equally (and DEGRADED is raised).

WBE, wheel-speed coupling estimator (Sec. 2.3), xi = [vx, vy, r]
    eq. 14-15 Y = H xi + V with the four wheel speeds. slipd's channels are linear wheel
            speeds omega r_w, so Y = r_w n and H is the paper's H times r_w (rows
            [cos d, sin d, -b_f cos d + l_f sin d], [cos d, sin d, b_f cos d + l_f sin d],
            [1, 0, -b_r], [1, 0, b_r] for FL, FR, RL, RR with b = half track)
    eq. 24-25 ridge (Tikhonov) estimate with forgetting factor rho, recursively:
            M_k = rho M_{k-1} + H_k' H_k + (1 - rho) k1 I,  g_k = rho g_{k-1} + H_k' Y_k,
            xi_k = M_k^-1 g_k. Started from M_0 = k1 I this is exactly the minimiser of
            sum_j rho^(k-j) |Y_j - H_j xi|^2 + k1 |xi|^2, i.e. eq. 24 with exponential
            weighting; the (1 - rho) k1 I term keeps the eigenvalue increment k1 of eq. 24 in
            the information matrix for ever (the paper's eq. 25 is garbled in print; this is
            the regularised RLS of Gunnarsson 1996 it describes). P_k = M_k^-1 (eq. 25).
            Error covariance for the fusion: s^2 M^-1 / (1 + rho) with s^2 the exponentially
            weighted mean squared residual (the variance of an exponentially weighted mean).
            As in the paper, xi is modelled constant over the memory of rho / (1 - rho)
            ticks: under a steady acceleration a the WBE's vx lags by a rho / (1 - rho) dt
            (2.5 m/s at 5 m/s^2 with rho = 0.98); the ridge shrinks vx by about k1 (1 - rho) / 4
            and beta toward 0 where the steer angle gives vy little weight.

Fusion (Sec. 3.2, eq. 26-39)
    x_0 = sum W_i x_i with W = (L' P^-1 L)^-1 L' P^-1 (eq. 38), L = [I I I]', P the 6x6 error
    covariance of (x_1, x_2, x_3). The fused covariance is (L' P^-1 L)^-1.
    How P is obtained online (the paper does not say; slipd's choice, documented here):
    * pairwise difference moments D_ij = E[(x_i - x_j)(x_i - x_j)'] are tracked with
      exponential forgetting (time constant ``fusion_time_constant``). They are observable
      without truth, and D_ij = P_ii + P_jj - P_ij - P_ji for any error statistics.
    * diagonal blocks (``variance_from_differences`` = 2, default): P_11 = C_1, and
      P_jj = s_j C_j for j = 2, 3 with s_j = max(1, (D_1j[gg] - C_1[gg]) / C_j[gg]): C_i is the
      estimator's own covariance (KBE/DBE filter covariances, WBE's RLS covariance), which
      knows its model's noise but not its model error (DBE with the wrong friction, WBE's
      tyre radii). gamma_1 is the gyro, so D_1j[gg] - C_1[gg] is the observed yaw-rate error
      variance of estimator j: where it exceeds what C_j claims, the whole block is scaled
      (covariance matching on the one channel with a reference, Mehra 1972).
      Mode 1 instead takes P_ii = C_i + (T_i - C_i)+ with the three-cornered-hat variance
      T_1 = (D_12 + D_13 - D_23) / 2 (and cyclic; ()+ the positive part of the symmetric 2x2);
      it assumes uncorrelated errors and failed on the simulator (the KBE's and WBE's errors
      are correlated: both lean to beta = 0), see the report. Mode 0 uses C_i alone.
    * cross blocks: P_ij = (P_ii + P_jj - D_ij) / 2 (symmetric part; the antisymmetric part is
      not observable from D and is taken as zero). ``cross_covariance`` = 0 sets them to zero.
    * every cross element is clipped to a correlation of at most 0.9 in magnitude
      (``CROSS_CORRELATION_LIMIT``): when a filter's own covariance is too small for the
      observed differences, (P_ii + P_jj - D_ij) / 2 would claim a correlation beyond -1.
    * P (``fusion_floor`` added to the gamma and beta variances) is factorised by Cholesky; if
      it is still not positive definite the cross blocks are dropped for this tick
      (``S.CROSS_SCALE`` says which: 1 used, 0 dropped).
    Measured on the simulator suite: the own covariances (even rescaled) are far smaller than
    the observed differences, so the cross terms (P_ii + P_jj - D_ij) / 2 would need
    correlations beyond -1 for all three pairs and the fusion runs with a block-diagonal P on
    nearly every tick; the cross terms work where the moments are consistent (tests:
    synthetic pseudo-sensors with correlated errors).
    The weights are kept in the state (W1..W3 at ``S.W1_GG`` .., 4 per estimator, row-major
    [[gg, gb], [bg, bb]]), so "the weight coefficient of estimator i" for beta is W_i[b, b].

Sign convention. Chen's axes are x forward, y left (Fig. 1: "the right-to-left direction is
positive"), which is ISO 8855, and eq. 4 is ISO-consistent with wheel 1 front-left at y = +b_f.
Eq. 6, 7 and 14 print the opposite sign on the half-track terms (as if wheel 1 were on the
right, or the yaw rate positive clockwise): slipd uses the ISO 8855 form throughout, left
wheels at y = +b (slower and unloaded in a left turn): alpha_FL = d - atan((vy + l_f r) / (vx -
b_f r)), n_FL = (vx - r b_f) cos d + (vy + r l_f) sin d, F_zFL = ... - m ay h l_r / (2 b_f l).
No other conversion is needed (ay, r, beta all + to the left).

Pre-processing (shared blocks of ``slipd.estimators.preprocess``, as in the righetti_lenzo
family): IMU accelerations moved to the CoG with the 3-D lever arm, gravity from body roll
removed from ay by the roll complementary filter. Not in the paper (its CarSim sensors sit at
the CoG without roll).

Robustness (not in the paper): invalid steer / ax / ay hold the last valid value and an invalid
yaw rate is replaced by the DBE's (the DBE also skips the ax / ay update); invalid wheels leave
their rows out of the WBE and the vx updates; without torque frames Fx = m ax / 4 (DEGRADED);
below ``min_speed`` everything is held at vy = 0. Each estimator restarts on its own when its
state is non-finite or leaves its model's domain (DBE |vy| >= vx, KBE |vy| >= 2 vx), the fusion
statistics when they are non-finite; RESET is raised when the output's source restarted (for
the fused output: any part). An output beyond +-45 deg is clamped and flagged NOT_CONVERGED.
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
    G,
    In,
    Out,
    Veh,
)
from slipd.errors import ConfigError
from slipd.estimators.preprocess import (
    DERIVATIVE_CUTOFF_HZ,
    channel,
    compensate_gravity_ay,
    compensate_wheel_speeds,
    derivative_filter,
    gaussian_bell,
    imu_at_cog,
    roll_complementary_filter,
    roll_static_gain,
)


@enum.unique
class Part(enum.IntEnum):
    """Which estimate the method outputs (params[PART])."""

    FUSED = 0  # IFE of the paper: eq. 39
    KBE = 1
    DBE = 2
    WBE = 3


@enum.unique
class PARAMS(enum.IntEnum):
    PART = 0  # Part: 0 fused, 1 KBE, 2 DBE, 3 WBE
    # KBE (slipd's Kalman form of eq. 2)
    Q_VX_KBE = 1  # (m/s)^2 per s, process noise of the vx integral
    Q_VY_KBE = 2  # (m/s)^2 per s, process noise of the vy integral
    R_VX_KBE = 3  # (m/s)^2, wheel-based vx
    R_VY0_KBE = 4  # (m/s)^2, the vy = 0 pseudo-measurement (leak)
    SIGMA_YAW_RATE = 5  # rad/s, error of the measured yaw rate (gamma_1)
    # DBE (eq. 8-13)
    Q_VX_DBE = 6  # (m/s)^2 per s
    Q_VY_DBE = 7  # (m/s)^2 per s
    Q_R_DBE = 8  # (rad/s)^2 per s
    R_AX_DBE = 9  # (m/s^2)^2
    R_AY_DBE = 10  # (m/s^2)^2
    R_VX_DBE = 11  # (m/s)^2, wheel-based vx (slipd)
    # WBE (eq. 24-25)
    FORGETTING = 12  # rho of eq. 25, per tick
    RIDGE = 13  # k1 of eq. 24-25, eigenvalue increment, (m/s)^-2 units of H'H
    # fusion
    FUSION_TIME_CONSTANT = 14  # s, forgetting of the difference moments D_ij
    VARIANCE_FROM_DIFFERENCES = 15  # P_ii: 2 yaw-rate matching, 1 three-cornered hat, 0 C_i
    CROSS_COVARIANCE = 16  # 1: P_ij from the differences, 0: P_ij = 0
    FUSION_FLOOR = 17  # rad^2 added to both variances of every P_ii
    # common
    MIN_SPEED = 18  # m/s, below it the estimators are held at vy = 0
    P0_VX = 19  # (m/s)^2 initial variances
    P0_VY = 20
    P0_R = 21  # (rad/s)^2
    SETTLE_TICKS = 22  # ticks after (re)start before convergence may be claimed
    CONVERGED_SIGMA_BETA = 23  # rad
    ROLL_TIME_CONSTANT = 24  # s, roll complementary filter (0: no gravity compensation)
    STRAIGHT_SIGMA_YAW_RATE = 25  # rad/s, width of the KBE's straight-running Gaussian
    STRAIGHT_SIGMA_AY = 26  # m/s^2, width of the KBE's straight-running Gaussian


#: Defaults. The paper publishes no filter tuning (only the vehicle of Table 1, which slipd takes
#: from the profile); every value below is slipd's, chosen from the sensor specifications of
#: the simulator (slipd.sim.sensors.SensorConfig) and the time scales named in the comments.
DEFAULTS = {
    "part": 0.0,
    "q_vx_kbe": 0.05,  # ~0.1 m/s^2 accelerometer offset over ~0.5 s correlation
    "q_vy_kbe": 0.005,  # chosen on the simulator suite from {0.02, 0.005} (see the report)
    "r_vx_kbe": 0.04,
    "r_vy0_kbe": 0.25,  # with q_vy_kbe: leak time constant ~0.35 s on a straight
    "sigma_yaw_rate": math.radians(0.3),  # the gyro turn-on offset (sensors.py)
    "q_vx_dbe": 0.05,
    "q_vy_dbe": 0.01,
    "q_r_dbe": 0.01,
    "r_ax_dbe": 0.25,  # force observer errors: 5-8 % torque gain errors, rolling resistance
    "r_ay_dbe": 0.06,  # righetti_lenzo eq. 28's R_ay
    "r_vx_dbe": 0.04,
    "forgetting": 0.98,  # 0.5 s memory at 100 Hz
    "ridge": 0.5,  # vx shrinks by k1 (1 - rho) / 4 = 0.25 %, beta toward 0 at small steer
    "fusion_time_constant": 2.0,
    # yaw-rate matching (docstring); pooled beta RMS on the simulator suite: 0.41 deg, mode 0
    # (own covariances): 0.73, mode 1 (three-cornered hat): 1.85
    "variance_from_differences": 2.0,
    "cross_covariance": 1.0,
    "fusion_floor": 1e-8,
    "min_speed": 3.0,
    "p0_vx": 1.0,
    "p0_vy": 1.0,
    "p0_r": 1e-2,
    "settle_ticks": 200.0,
    "converged_sigma_beta": 0.0175,
    "roll_time_constant": 1.0,
    "straight_sigma_yaw_rate": 0.05,  # Selmanaj 2017 Table 1 uses 0.18 on the yaw rate alone
    "straight_sigma_ay": 1.0,
}


@enum.unique
class S(enum.IntEnum):
    """Elements of the state vector (float64)."""

    # KBE: [vx, vy] m/s, covariance (symmetric)
    KBE_VX = 0
    KBE_VY = 1
    KBE_P_XX = 2
    KBE_P_XY = 3
    KBE_P_YY = 4
    # DBE: [vx, vy, r], covariance upper triangle row-major
    DBE_VX = 5
    DBE_VY = 6
    DBE_R = 7
    DBE_P00 = 8
    DBE_P01 = 9
    DBE_P02 = 10
    DBE_P11 = 11
    DBE_P12 = 12
    DBE_P22 = 13
    # WBE: xi = [vx, vy, r], information matrix M (upper triangle), g = sum rho^j H'Y
    WBE_VX = 14
    WBE_VY = 15
    WBE_R = 16
    WBE_M00 = 17
    WBE_M01 = 18
    WBE_M02 = 19
    WBE_M11 = 20
    WBE_M12 = 21
    WBE_M22 = 22
    WBE_G0 = 23
    WBE_G1 = 24
    WBE_G2 = 25
    WBE_RES_VAR = 26  # (m/s)^2, weighted mean squared wheel-speed residual
    # difference moments D_ij (gg, gb, bb) of x_i - x_j
    D12_GG = 27
    D12_GB = 28
    D12_BB = 29
    D13_GG = 30
    D13_GB = 31
    D13_BB = 32
    D23_GG = 33
    D23_GB = 34
    D23_BB = 35
    # fusion weights W_i (2x2 row-major: gg, gb, bg, bb); rows/cols: 0 yaw rate, 1 beta
    W1_GG = 36
    W1_GB = 37
    W1_BG = 38
    W1_BB = 39
    W2_GG = 40
    W2_GB = 41
    W2_BG = 42
    W2_BB = 43
    W3_GG = 44
    W3_GB = 45
    W3_BG = 46
    W3_BB = 47
    FUSED_R = 48  # rad/s
    FUSED_BETA = 49  # rad
    FUSED_VAR_BB = 50  # rad^2, (L' P^-1 L)^-1 [b, b]
    CROSS_SCALE = 51  # 1: the fusion used the cross blocks, 0: P was not PD with them
    # held inputs and pre-processing memory
    LAST_AX = 52
    LAST_AY = 53
    LAST_YAW_RATE = 54
    LAST_STEER = 55
    YAW_RATE_FILTERED = 56
    ROLL_RATE_FILTERED = 57
    PITCH_RATE_FILTERED = 58
    ROLL = 59
    WHEEL_FILTERED_FL = 60  # derivative filters of the wheel speeds (J_w dw/dt of the DBE)
    WHEEL_FILTERED_FR = 61
    WHEEL_FILTERED_RL = 62
    WHEEL_FILTERED_RR = 63
    INITIALISED = 64
    TICKS = 65
    # scratch of the fusion solve: P (6x6 row-major) then Z = P^-1 L (6x2 row-major)
    SCRATCH_P = 66
    SCRATCH_Z = 102


N_STATE = S.SCRATCH_Z + 12
#: Index of W_i[row, col] in the state: W_INDEX[i - 1] + 2 * row + col.
W_INDEX = (int(S.W1_GG), int(S.W2_GG), int(S.W3_GG))
_SP = int(S.SCRATCH_P)
_SZ = int(S.SCRATCH_Z)
# plain ints for the kernels (numba cannot call int() on an IntEnum member)
_DBE_VX = int(S.DBE_VX)
_DBE_P00 = int(S.DBE_P00)
_WBE_FIRST = int(S.WBE_M00)  # M and g, scaled by rho together
_WBE_LAST = int(S.WBE_G2)
_FUSION_FIRST = int(S.D12_GG)
_FUSION_LAST = int(S.CROSS_SCALE)  # the last slot checked by insane_parts
_WBE_VX = int(S.WBE_VX)
_WBE_RES_VAR = int(S.WBE_RES_VAR)
_TORQUE_FIRST = int(In.DRIVE_TORQUE_FL)
_TORQUE_LAST = int(In.BRAKE_TORQUE_RR)
#: |beta| beyond which the output is clamped and flagged (the 45 deg of the models' domain)
BETA_LIMIT = 0.25 * math.pi


# ---------------------------------------------------------------------------------------------
# small helpers
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def beta_moments(vx, vy, p_xx, p_xy, p_yy):
    """Gradient of beta = atan2(vy, vx), g = [-vy, vx] / V^2, and var = g P g'."""
    speed2 = vx * vx + vy * vy
    if speed2 < 1e-6:
        speed2 = 1e-6
    g1 = -vy / speed2
    g2 = vx / speed2
    return g1, g2, g1 * g1 * p_xx + 2.0 * g1 * g2 * p_xy + g2 * g2 * p_yy


@nb.njit(cache=True)
def positive_part_2x2(a, b, c):
    """Positive part of the symmetric [[a, b], [b, c]] (negative eigenvalues set to 0)."""
    half_trace = 0.5 * (a + c)
    half_diff = 0.5 * (a - c)
    radius = math.sqrt(half_diff * half_diff + b * b)
    lam1 = half_trace + radius
    lam2 = half_trace - radius
    if lam2 >= 0.0:
        return a, b, c
    if lam1 <= 0.0:
        return 0.0, 0.0, 0.0
    # only lam1 > 0: lam1 v v' with v the unit eigenvector of lam1
    if radius > 0.0:
        # (A - lam2 I) = (lam1 - lam2) v v'
        scale = lam1 / (lam1 - lam2)
        return scale * (a - lam2), scale * b, scale * (c - lam2)
    return a, b, c


# ---------------------------------------------------------------------------------------------
# the tyre and the 3-DOF model (eq. 4-7)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def magic_formula(alpha, b_factor, c_factor, e_factor, peak):
    """Eq. 5: Fy = D sin(C atan(B a - E (B a - atan(B a)))) with D = ``peak``; returns
    (Fy [N], dFy/dalpha [N/rad])."""
    ba = b_factor * alpha
    phi = ba - e_factor * (ba - math.atan(ba))
    angle = c_factor * math.atan(phi)
    dphi = b_factor - e_factor * (b_factor - b_factor / (1.0 + ba * ba))
    return peak * math.sin(angle), peak * math.cos(angle) * c_factor / (1.0 + phi * phi) * dphi


@nb.njit(cache=True)
def vertical_loads(ax, ay, vehicle):
    """Eq. 6 (ISO 8855 signs, see the module docstring): (Fz_FL, Fz_FR, Fz_RL, Fz_RR) [N].

    Longitudinal transfer m ax h / (2 l) from front to rear; lateral transfer of each axle
    m ay h l_other / (l track), off the left wheels when ay > 0. Loads are floored at 5 % of the
    static wheel load (a lifted wheel keeps a well-defined, small force).
    """
    mass = vehicle[Veh.MASS]
    lf = vehicle[Veh.LF]
    lr = vehicle[Veh.LR]
    wheelbase = lf + lr
    h = vehicle[Veh.H_COG]
    static_f = 0.5 * mass * G * lr / wheelbase
    static_r = 0.5 * mass * G * lf / wheelbase
    long_transfer = 0.5 * mass * ax * h / wheelbase
    lat_f = mass * ay * h * lr / (wheelbase * vehicle[Veh.TRACK_F])
    lat_r = mass * ay * h * lf / (wheelbase * vehicle[Veh.TRACK_R])
    floor = 0.05 * min(static_f, static_r)
    return (
        max(static_f - long_transfer - lat_f, floor),
        max(static_f - long_transfer + lat_f, floor),
        max(static_r + long_transfer - lat_r, floor),
        max(static_r + long_transfer + lat_r, floor),
    )


@nb.njit(cache=True)
def _wheel_force(vx, vy, r, x_pos, y_pos, steer, fz, vehicle):
    """Lateral force of one wheel at (x_pos, y_pos) (eq. 5, 7) and its gradient wrt (vx, vy, r)."""
    num = vy + x_pos * r  # lateral velocity of the wheel centre
    den = vx - y_pos * r  # longitudinal velocity of the wheel centre
    if den < 0.1:
        den = 0.1  # the caller keeps vx above min_speed; this only guards the division
    q = num * num + den * den
    alpha = steer - math.atan2(num, den)
    force, slope = magic_formula(
        alpha, vehicle[Veh.TYRE_B], vehicle[Veh.TYRE_C], vehicle[Veh.TYRE_E],
        vehicle[Veh.MU_NOMINAL] * fz,
    )  # fmt: skip
    da_dnum = -den / q
    da_dden = num / q
    # d num / d(vx, vy, r) = (0, 1, x_pos); d den / d(vx, vy, r) = (1, 0, -y_pos)
    return (
        force,
        slope * da_dden,
        slope * da_dnum,
        slope * (da_dnum * x_pos - da_dden * y_pos),
    )


@nb.njit(cache=True)
def three_dof(vx, vy, r, steer, fx_fl, fx_fr, fx_rl, fx_rr, fz_fl, fz_fr, fz_rl, fz_rr, vehicle):
    """Eq. 4 with eq. 5-7: derivatives, the accelerations it implies and their Jacobians.

    Returns (vx_dot, vy_dot, r_dot, ax_model, ay_model, J (9, row-major d(vx', vy', r')/d(vx,
    vy, r)), dax (3), day (3)) as a flat tuple. ax_model / ay_model are the force sums over m
    (what an accelerometer at the CoG measures): vx_dot = ax_model + r vy, vy_dot = ay_model
    - r vx.
    """
    lf = vehicle[Veh.LF]
    lr = vehicle[Veh.LR]
    bf = 0.5 * vehicle[Veh.TRACK_F]
    br = 0.5 * vehicle[Veh.TRACK_R]
    inv_m = 1.0 / vehicle[Veh.MASS]
    inv_iz = 1.0 / vehicle[Veh.YAW_INERTIA]
    fy1, a1, b1, c1 = _wheel_force(vx, vy, r, lf, bf, steer, fz_fl, vehicle)
    fy2, a2, b2, c2 = _wheel_force(vx, vy, r, lf, -bf, steer, fz_fr, vehicle)
    fy3, a3, b3, c3 = _wheel_force(vx, vy, r, -lr, br, 0.0, fz_rl, vehicle)
    fy4, a4, b4, c4 = _wheel_force(vx, vy, r, -lr, -br, 0.0, fz_rr, vehicle)
    cos_d = math.cos(steer)
    sin_d = math.sin(steer)
    fx_front = fx_fl + fx_fr
    fy_front = fy1 + fy2
    ax_model = (fx_front * cos_d - fy_front * sin_d + fx_rl + fx_rr) * inv_m
    ay_model = (fx_front * sin_d + fy_front * cos_d + fy3 + fy4) * inv_m
    yaw_moment = (
        fx_front * lf * sin_d
        - (fy3 + fy4) * lr
        + fy_front * lf * cos_d
        + (fy1 - fy2) * bf * sin_d
        - (fx_fl - fx_fr) * bf * cos_d
        - (fx_rl - fx_rr) * br
    )
    # gradients of the force sums wrt (vx, vy, r)
    dff0, dff1, dff2 = a1 + a2, b1 + b2, c1 + c2  # front sum
    dfd0, dfd1, dfd2 = a1 - a2, b1 - b2, c1 - c2  # front difference
    dfr0, dfr1, dfr2 = a3 + a4, b3 + b4, c3 + c4  # rear sum
    dax0 = -dff0 * sin_d * inv_m
    dax1 = -dff1 * sin_d * inv_m
    dax2 = -dff2 * sin_d * inv_m
    day0 = (dff0 * cos_d + dfr0) * inv_m
    day1 = (dff1 * cos_d + dfr1) * inv_m
    day2 = (dff2 * cos_d + dfr2) * inv_m
    k_front = lf * cos_d
    k_diff = bf * sin_d
    dm0 = (-dfr0 * lr + dff0 * k_front + dfd0 * k_diff) * inv_iz
    dm1 = (-dfr1 * lr + dff1 * k_front + dfd1 * k_diff) * inv_iz
    dm2 = (-dfr2 * lr + dff2 * k_front + dfd2 * k_diff) * inv_iz
    return (
        ax_model + r * vy,
        ay_model - r * vx,
        yaw_moment * inv_iz,
        ax_model,
        ay_model,
        # d vx' = dax + d(r vy)
        dax0, dax1 + r, dax2 + vy,
        # d vy' = day - d(r vx)
        day0 - r, day1, day2 - vx,
        dm0, dm1, dm2,
        dax0, dax1, dax2,
        day0, day1, day2,
    )  # fmt: skip


# ---------------------------------------------------------------------------------------------
# DBE: EKF on [vx, vy, r] (eq. 8-13)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def _sym3(state, i0, a, b):
    """Element (a, b) of the symmetric 3x3 stored as upper triangle at ``i0``."""
    if a > b:
        a, b = b, a
    # offsets of (0,0) (0,1) (0,2) (1,1) (1,2) (2,2)
    if a == 0:
        return state[i0 + b]
    if a == 1:
        return state[i0 + 2 + b]
    return state[i0 + 5]


@nb.njit(cache=True)
def dbe_predict(state, steer, fx, fz, vehicle, q_vx, q_vy, q_r, dt):
    """Eq. 9-10: x^- = x + f T + A f T^2 / 2, P^- = phi P phi' + Q, phi = I + A T.

    ``fx``, ``fz``: 4-tuples of longitudinal forces and vertical loads (FL, FR, RL, RR).
    """
    vx = state[S.DBE_VX]
    vy = state[S.DBE_VY]
    r = state[S.DBE_R]
    m = three_dof(vx, vy, r, steer, fx[0], fx[1], fx[2], fx[3], fz[0], fz[1], fz[2], fz[3],
                  vehicle)  # fmt: skip
    f0, f1, f2 = m[0], m[1], m[2]
    a00, a01, a02, a10, a11, a12, a20, a21, a22 = m[5], m[6], m[7], m[8], m[9], m[10], m[11], \
        m[12], m[13]  # fmt: skip
    half_t2 = 0.5 * dt * dt
    state[S.DBE_VX] = vx + f0 * dt + (a00 * f0 + a01 * f1 + a02 * f2) * half_t2
    state[S.DBE_VY] = vy + f1 * dt + (a10 * f0 + a11 * f1 + a12 * f2) * half_t2
    state[S.DBE_R] = r + f2 * dt + (a20 * f0 + a21 * f1 + a22 * f2) * half_t2
    # phi = I + A T
    p00 = 1.0 + a00 * dt
    p01 = a01 * dt
    p02 = a02 * dt
    p10 = a10 * dt
    p11 = 1.0 + a11 * dt
    p12 = a12 * dt
    p20 = a20 * dt
    p21 = a21 * dt
    p22 = 1.0 + a22 * dt
    i0 = _DBE_P00
    c00 = _sym3(state, i0, 0, 0)
    c01 = _sym3(state, i0, 0, 1)
    c02 = _sym3(state, i0, 0, 2)
    c11 = _sym3(state, i0, 1, 1)
    c12 = _sym3(state, i0, 1, 2)
    c22 = _sym3(state, i0, 2, 2)
    # B = phi P (row i of phi times P)
    b00 = p00 * c00 + p01 * c01 + p02 * c02
    b01 = p00 * c01 + p01 * c11 + p02 * c12
    b02 = p00 * c02 + p01 * c12 + p02 * c22
    b10 = p10 * c00 + p11 * c01 + p12 * c02
    b11 = p10 * c01 + p11 * c11 + p12 * c12
    b12 = p10 * c02 + p11 * c12 + p12 * c22
    b20 = p20 * c00 + p21 * c01 + p22 * c02
    b21 = p20 * c01 + p21 * c11 + p22 * c12
    b22 = p20 * c02 + p21 * c12 + p22 * c22
    # P^- = B phi' + Q
    state[S.DBE_P00] = b00 * p00 + b01 * p01 + b02 * p02 + q_vx * dt
    state[S.DBE_P01] = b00 * p10 + b01 * p11 + b02 * p12
    state[S.DBE_P02] = b00 * p20 + b01 * p21 + b02 * p22
    state[S.DBE_P11] = b10 * p10 + b11 * p11 + b12 * p12 + q_vy * dt
    state[S.DBE_P12] = b10 * p20 + b11 * p21 + b12 * p22
    state[S.DBE_P22] = b20 * p20 + b21 * p21 + b22 * p22 + q_r * dt


@nb.njit(cache=True)
def _scalar_update3(state, x0, p0, h0, h1, h2, innovation, variance):
    """One scalar Kalman update of a 3-state filter (state at x0, upper-triangle P at p0):
    K = P h / (h' P h + R), x += K inn, P -= K (P h)' (eq. 11-13 for one measurement)."""
    c00 = state[p0]
    c01 = state[p0 + 1]
    c02 = state[p0 + 2]
    c11 = state[p0 + 3]
    c12 = state[p0 + 4]
    c22 = state[p0 + 5]
    ph0 = c00 * h0 + c01 * h1 + c02 * h2
    ph1 = c01 * h0 + c11 * h1 + c12 * h2
    ph2 = c02 * h0 + c12 * h1 + c22 * h2
    s = h0 * ph0 + h1 * ph1 + h2 * ph2 + variance
    k0 = ph0 / s
    k1 = ph1 / s
    k2 = ph2 / s
    state[x0] += k0 * innovation
    state[x0 + 1] += k1 * innovation
    state[x0 + 2] += k2 * innovation
    state[p0] = c00 - k0 * ph0
    state[p0 + 1] = c01 - k0 * ph1
    state[p0 + 2] = c02 - k0 * ph2
    state[p0 + 3] = c11 - k1 * ph1
    state[p0 + 4] = c12 - k1 * ph2
    state[p0 + 5] = c22 - k2 * ph2


@nb.njit(cache=True)
def dbe_update(state, steer, fx, fz, vehicle, ax, ax_ok, r_ax, ay, ay_ok, r_ay, vx_meas, vx_ok,
               r_vx):  # fmt: skip
    """Eq. 11-13 with y = [ax, ay, vx_wheels], h linearised at the prior; the scalar updates
    use innovations y_j - h_j(x^-) - H_j (x - x^-) so that the result is the batch update."""
    vx = state[S.DBE_VX]
    vy = state[S.DBE_VY]
    r = state[S.DBE_R]
    m = three_dof(vx, vy, r, steer, fx[0], fx[1], fx[2], fx[3], fz[0], fz[1], fz[2], fz[3],
                  vehicle)  # fmt: skip
    x0 = _DBE_VX
    p0 = _DBE_P00
    if ax_ok:
        h0, h1, h2 = m[14], m[15], m[16]
        _scalar_update3(state, x0, p0, h0, h1, h2, ax - m[3], r_ax)
    if ay_ok:
        h0, h1, h2 = m[17], m[18], m[19]
        moved = h0 * (state[x0] - vx) + h1 * (state[x0 + 1] - vy) + h2 * (state[x0 + 2] - r)
        _scalar_update3(state, x0, p0, h0, h1, h2, ay - m[4] - moved, r_ay)
    if vx_ok:
        _scalar_update3(state, x0, p0, 1.0, 0.0, 0.0, vx_meas - state[x0], r_vx)


# ---------------------------------------------------------------------------------------------
# KBE: eq. 2 as a Kalman filter (see the module docstring)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def kbe_predict(state, ax, ay, yaw_rate, q_vx, q_vy, dt):
    """Eq. 2, forward Euler: vx += (ax + vy r) dt, vy += (ay - vx r) dt; P = F P F' + Q dt."""
    vx = state[S.KBE_VX]
    vy = state[S.KBE_VY]
    state[S.KBE_VX] = vx + (ax + vy * yaw_rate) * dt
    state[S.KBE_VY] = vy + (ay - vx * yaw_rate) * dt
    f12 = yaw_rate * dt
    f21 = -yaw_rate * dt
    p11 = state[S.KBE_P_XX]
    p12 = state[S.KBE_P_XY]
    p22 = state[S.KBE_P_YY]
    a11 = p11 + f12 * p12
    a12 = p12 + f12 * p22
    a21 = f21 * p11 + p12
    a22 = f21 * p12 + p22
    state[S.KBE_P_XX] = a11 + a12 * f12 + q_vx * dt
    state[S.KBE_P_XY] = a11 * f21 + a12
    state[S.KBE_P_YY] = a21 * f21 + a22 + q_vy * dt


@nb.njit(cache=True)
def _scalar_update2(state, i_x, i_p, h1, h2, innovation, variance):
    """Scalar Kalman update of the KBE ([vx, vy], P at i_p as p11, p12, p22)."""
    p11 = state[i_p]
    p12 = state[i_p + 1]
    p22 = state[i_p + 2]
    ph1 = p11 * h1 + p12 * h2
    ph2 = p12 * h1 + p22 * h2
    s = h1 * ph1 + h2 * ph2 + variance
    k1 = ph1 / s
    k2 = ph2 / s
    state[i_x] += k1 * innovation
    state[i_x + 1] += k2 * innovation
    state[i_p] = p11 - k1 * ph1
    state[i_p + 1] = p12 - k1 * ph2
    state[i_p + 2] = p22 - k2 * ph2


@nb.njit(cache=True)
def kbe_update(state, vx_meas, vx_ok, r_vx, r_vy0, straight):
    """vx from the wheels (if any) and the vy = 0 pseudo-measurement (slipd's bound on the
    integral of eq. 2) with variance r_vy0 / ``straight``: full strength on a straight, none
    in a corner, where the integral runs open as in the paper."""
    if vx_ok:
        _scalar_update2(state, S.KBE_VX, S.KBE_P_XX, 1.0, 0.0, vx_meas - state[S.KBE_VX], r_vx)
    if straight > 1e-6:
        _scalar_update2(state, S.KBE_VX, S.KBE_P_XX, 0.0, 1.0, -state[S.KBE_VY], r_vy0 / straight)


# ---------------------------------------------------------------------------------------------
# WBE: ridge RLS with forgetting on the wheel-speed coupling (eq. 14-25)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def _wbe_row(state, h0, h1, h2, y):
    """Accumulate one row of eq. 15 into M += h h', g += h y."""
    state[S.WBE_M00] += h0 * h0
    state[S.WBE_M01] += h0 * h1
    state[S.WBE_M02] += h0 * h2
    state[S.WBE_M11] += h1 * h1
    state[S.WBE_M12] += h1 * h2
    state[S.WBE_M22] += h2 * h2
    state[S.WBE_G0] += h0 * y
    state[S.WBE_G1] += h1 * y
    state[S.WBE_G2] += h2 * y


@nb.njit(cache=True)
def _residual(h0, h1, h2, y, x0, x1, x2):
    e = y - (h0 * x0 + h1 * x1 + h2 * x2)
    return e * e


@nb.njit(cache=True)
def inverse_sym3(m00, m01, m02, m11, m12, m22):
    """Inverse of a symmetric positive definite 3x3 by cofactors: (i00, i01, i02, i11, i12,
    i22), or all NaN when it is singular."""
    c00 = m11 * m22 - m12 * m12
    c01 = m02 * m12 - m01 * m22
    c02 = m01 * m12 - m02 * m11
    det = m00 * c00 + m01 * c01 + m02 * c02
    if not det > 0.0:
        return math.nan, math.nan, math.nan, math.nan, math.nan, math.nan
    inv = 1.0 / det
    return (
        c00 * inv,
        c01 * inv,
        c02 * inv,
        (m00 * m22 - m02 * m02) * inv,
        (m01 * m02 - m00 * m12) * inv,
        (m00 * m11 - m01 * m01) * inv,
    )


@nb.njit(cache=True)
def wbe_update(state, wheel_speeds, wheel_ok, steer, vehicle, rho, ridge):
    """Eq. 24-25 in information form (module docstring): M = rho M + H'H + (1 - rho) k1 I,
    g = rho g + H'Y, xi = M^-1 g. Invalid wheels leave their rows out; with no valid wheel
    nothing changes. Returns the number of rows used."""
    n_rows = 0
    for i in range(4):
        if wheel_ok[i]:
            n_rows += 1
    if n_rows == 0:
        return 0
    lf = vehicle[Veh.LF]
    bf = 0.5 * vehicle[Veh.TRACK_F]
    br = 0.5 * vehicle[Veh.TRACK_R]
    cos_d = math.cos(steer)
    sin_d = math.sin(steer)
    for i in range(_WBE_FIRST, _WBE_LAST + 1):
        state[i] *= rho
    leak = (1.0 - rho) * ridge
    state[S.WBE_M00] += leak
    state[S.WBE_M11] += leak
    state[S.WBE_M22] += leak
    x0 = state[S.WBE_VX]
    x1 = state[S.WBE_VY]
    x2 = state[S.WBE_R]
    sq = 0.0
    # eq. 14 in ISO 8855: left wheels at y = +b (module docstring)
    if wheel_ok[0]:
        h2 = -bf * cos_d + lf * sin_d
        _wbe_row(state, cos_d, sin_d, h2, wheel_speeds[0])
        sq += _residual(cos_d, sin_d, h2, wheel_speeds[0], x0, x1, x2)
    if wheel_ok[1]:
        h2 = bf * cos_d + lf * sin_d
        _wbe_row(state, cos_d, sin_d, h2, wheel_speeds[1])
        sq += _residual(cos_d, sin_d, h2, wheel_speeds[1], x0, x1, x2)
    if wheel_ok[2]:
        _wbe_row(state, 1.0, 0.0, -br, wheel_speeds[2])
        sq += _residual(1.0, 0.0, -br, wheel_speeds[2], x0, x1, x2)
    if wheel_ok[3]:
        _wbe_row(state, 1.0, 0.0, br, wheel_speeds[3])
        sq += _residual(1.0, 0.0, br, wheel_speeds[3], x0, x1, x2)
    # a priori residual of this tick, exponentially weighted like the data
    state[S.WBE_RES_VAR] = rho * state[S.WBE_RES_VAR] + (1.0 - rho) * sq / n_rows
    i00, i01, i02, i11, i12, i22 = inverse_sym3(
        state[S.WBE_M00], state[S.WBE_M01], state[S.WBE_M02],
        state[S.WBE_M11], state[S.WBE_M12], state[S.WBE_M22],
    )  # fmt: skip
    g0 = state[S.WBE_G0]
    g1 = state[S.WBE_G1]
    g2 = state[S.WBE_G2]
    state[S.WBE_VX] = i00 * g0 + i01 * g1 + i02 * g2
    state[S.WBE_VY] = i01 * g0 + i11 * g1 + i12 * g2
    state[S.WBE_R] = i02 * g0 + i12 * g1 + i22 * g2
    return n_rows


# ---------------------------------------------------------------------------------------------
# fusion (eq. 26-39)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def update_difference_moments(state, i0, d_gamma, d_beta, gain):
    """D = D + gain (d d' - D) for one pair (gg, gb, bb at ``i0``)."""
    state[i0] += gain * (d_gamma * d_gamma - state[i0])
    state[i0 + 1] += gain * (d_gamma * d_beta - state[i0 + 1])
    state[i0 + 2] += gain * (d_beta * d_beta - state[i0 + 2])


@nb.njit(cache=True)
def _set_block(state, i, j, gg, gb, bg, bb):
    """P block (i, j) (estimators 0..2) into the 6x6 scratch, and its transpose into (j, i)."""
    base = _SP + 12 * i + 2 * j
    state[base] = gg
    state[base + 1] = gb
    state[base + 6] = bg
    state[base + 7] = bb
    if i != j:
        base = _SP + 12 * j + 2 * i
        state[base] = gg
        state[base + 1] = bg
        state[base + 6] = gb
        state[base + 7] = bb


@nb.njit(cache=True)
def _cholesky_solve_lambda(state):
    """Z = P^-1 L for the 6x6 P in the scratch (overwritten by its Cholesky factor) and
    L = [I I I]'. Returns False when P is not positive definite."""
    # in-place Cholesky, lower triangle
    for j in range(6):
        s = state[_SP + 7 * j]
        for k in range(j):
            s -= state[_SP + 6 * j + k] ** 2
        if not s > 0.0:
            return False
        d = math.sqrt(s)
        state[_SP + 7 * j] = d
        for i in range(j + 1, 6):
            s = state[_SP + 6 * i + j]
            for k in range(j):
                s -= state[_SP + 6 * i + k] * state[_SP + 6 * j + k]
            state[_SP + 6 * i + j] = s / d
    for c in range(2):
        # forward: L y = e (e = column c of the stacked identities)
        for i in range(6):
            s = 1.0 if i % 2 == c else 0.0
            for k in range(i):
                s -= state[_SP + 6 * i + k] * state[_SZ + 2 * k + c]
            state[_SZ + 2 * i + c] = s / state[_SP + 7 * i]
        # backward: L' z = y
        for i in range(5, -1, -1):
            s = state[_SZ + 2 * i + c]
            for k in range(i + 1, 6):
                s -= state[_SP + 6 * k + i] * state[_SZ + 2 * k + c]
            state[_SZ + 2 * i + c] = s / state[_SP + 7 * i]
    return True


@nb.njit(cache=True)
def _block_inverse_into_z(state, i, p):
    """Rows 2i, 2i + 1 of Z = P^-1 L for a block-diagonal P: the inverse of the symmetric
    block p = (gg, gb, bb). Returns False when the block is not positive definite."""
    det = p[0] * p[2] - p[1] * p[1]
    if not (det > 0.0 and p[0] > 0.0):
        return False
    base = _SZ + 4 * i
    state[base] = p[2] / det
    state[base + 1] = -p[1] / det
    state[base + 2] = -p[1] / det
    state[base + 3] = p[0] / det
    return True


#: Largest |correlation| a cross-covariance element may express (module docstring).
CROSS_CORRELATION_LIMIT = 0.9


@nb.njit(cache=True)
def _clip(value, limit):
    if value > limit:
        return limit
    if value < -limit:
        return -limit
    return value


@nb.njit(cache=True)
def _clip_cross(c, pi, pj):
    """Cross block (gg, gb, bg, bb) from the symmetric (gg, gb, bb) estimate ``c``, each element
    clipped to CROSS_CORRELATION_LIMIT sqrt(var_i var_j)."""
    k = CROSS_CORRELATION_LIMIT
    gg = _clip(c[0], k * math.sqrt(pi[0] * pj[0]))
    gb = _clip(c[1], k * math.sqrt(pi[0] * pj[2]))
    bg = _clip(c[1], k * math.sqrt(pi[2] * pj[0]))
    bb = _clip(c[2], k * math.sqrt(pi[2] * pj[2]))
    return gg, gb, bg, bb


@nb.njit(cache=True)
def fuse(state, own1, own2, own3, x1, x2, x3, variance_mode, use_cross, floor):
    """Eq. 38-39 with P built as in the module docstring.

    own_i = (gg, gb, bb) own covariance, x_i = (gamma, beta). Writes the weights W1..W3, the
    fused (gamma, beta) and its beta variance into the state. Returns (gamma_0, beta_0, var).
    """
    d12 = (state[S.D12_GG], state[S.D12_GB], state[S.D12_BB])
    d13 = (state[S.D13_GG], state[S.D13_GB], state[S.D13_BB])
    d23 = (state[S.D23_GG], state[S.D23_GB], state[S.D23_BB])
    p1 = own1
    p2 = own2
    p3 = own3
    if variance_mode == 2:
        # yaw-rate covariance matching: gamma_1 is the gyro, so D_1j[gg] - C_1[gg] is the
        # observed yaw-rate error variance of estimator j; the ratio to its own C_j[gg] scales
        # its whole block (model error shows in the yaw rate and the sideslip together)
        s2 = (d12[0] - own1[0]) / own2[0] if own2[0] > 0.0 else 1.0
        s3 = (d13[0] - own1[0]) / own3[0] if own3[0] > 0.0 else 1.0
        s2 = s2 if s2 > 1.0 else 1.0
        s3 = s3 if s3 > 1.0 else 1.0
        p2 = (s2 * own2[0], s2 * own2[1], s2 * own2[2])
        p3 = (s3 * own3[0], s3 * own3[1], s3 * own3[2])
    elif variance_mode == 1:
        # three-cornered hat: T_1 = (D12 + D13 - D23) / 2 etc.; P_ii = C_i + (T_i - C_i)+
        t0 = 0.5 * (d12[0] + d13[0] - d23[0]) - own1[0]
        t1 = 0.5 * (d12[1] + d13[1] - d23[1]) - own1[1]
        t2 = 0.5 * (d12[2] + d13[2] - d23[2]) - own1[2]
        e0, e1, e2 = positive_part_2x2(t0, t1, t2)
        p1 = (own1[0] + e0, own1[1] + e1, own1[2] + e2)
        t0 = 0.5 * (d12[0] + d23[0] - d13[0]) - own2[0]
        t1 = 0.5 * (d12[1] + d23[1] - d13[1]) - own2[1]
        t2 = 0.5 * (d12[2] + d23[2] - d13[2]) - own2[2]
        e0, e1, e2 = positive_part_2x2(t0, t1, t2)
        p2 = (own2[0] + e0, own2[1] + e1, own2[2] + e2)
        t0 = 0.5 * (d13[0] + d23[0] - d12[0]) - own3[0]
        t1 = 0.5 * (d13[1] + d23[1] - d12[1]) - own3[1]
        t2 = 0.5 * (d13[2] + d23[2] - d12[2]) - own3[2]
        e0, e1, e2 = positive_part_2x2(t0, t1, t2)
        p3 = (own3[0] + e0, own3[1] + e1, own3[2] + e2)
    # P_ij = (P_ii + P_jj - D_ij) / 2
    c12 = (0.5 * (p1[0] + p2[0] - d12[0]), 0.5 * (p1[1] + p2[1] - d12[1]),
           0.5 * (p1[2] + p2[2] - d12[2]))  # fmt: skip
    c13 = (0.5 * (p1[0] + p3[0] - d13[0]), 0.5 * (p1[1] + p3[1] - d13[1]),
           0.5 * (p1[2] + p3[2] - d13[2]))  # fmt: skip
    c23 = (0.5 * (p2[0] + p3[0] - d23[0]), 0.5 * (p2[1] + p3[1] - d23[1]),
           0.5 * (p2[2] + p3[2] - d23[2]))  # fmt: skip
    # diagonal blocks with the floor
    p1 = (p1[0] + floor, p1[1], p1[2] + floor)
    p2 = (p2[0] + floor, p2[1], p2[2] + floor)
    p3 = (p3[0] + floor, p3[1], p3[2] + floor)
    scale = 0.0
    if use_cross:
        _set_block(state, 0, 0, p1[0], p1[1], p1[1], p1[2])
        _set_block(state, 1, 1, p2[0], p2[1], p2[1], p2[2])
        _set_block(state, 2, 2, p3[0], p3[1], p3[1], p3[2])
        # each cross element within |correlation| <= CROSS_CORRELATION_LIMIT of its variances
        # (difference moments larger than the own covariances allow would imply |rho| > 1)
        gg, gb, bg, bb12 = _clip_cross(c12, p1, p2)
        _set_block(state, 0, 1, gg, gb, bg, bb12)
        gg, gb, bg, bb13 = _clip_cross(c13, p1, p3)
        _set_block(state, 0, 2, gg, gb, bg, bb13)
        gg, gb, bg, bb23 = _clip_cross(c23, p2, p3)
        _set_block(state, 1, 2, gg, gb, bg, bb23)
        # necessary condition first (cheap): the 3x3 beta-error correlation matrix must be
        # positive definite, else the 6x6 cannot be and the Cholesky is skipped
        if p1[2] > 0.0 and p2[2] > 0.0 and p3[2] > 0.0:
            r12 = bb12 / math.sqrt(p1[2] * p2[2])
            r13 = bb13 / math.sqrt(p1[2] * p3[2])
            r23 = bb23 / math.sqrt(p2[2] * p3[2])
            if 1.0 + 2.0 * r12 * r13 * r23 - r12 * r12 - r13 * r13 - r23 * r23 > 0.0:
                scale = 1.0 if _cholesky_solve_lambda(state) else 0.0
    if scale == 0.0:
        # block-diagonal P (the cross blocks dropped): P^-1 L is the stack of the block
        # inverses, no 6x6 factorisation needed
        ok = _block_inverse_into_z(state, 0, p1)
        ok = _block_inverse_into_z(state, 1, p2) and ok
        ok = _block_inverse_into_z(state, 2, p3) and ok
        if not ok:
            return math.nan, math.nan, math.nan
    state[S.CROSS_SCALE] = scale
    # A = L' Z (2x2), its inverse is the fused covariance (eq. 37)
    a00 = state[_SZ] + state[_SZ + 4] + state[_SZ + 8]
    a01 = state[_SZ + 1] + state[_SZ + 5] + state[_SZ + 9]
    a10 = state[_SZ + 2] + state[_SZ + 6] + state[_SZ + 10]
    a11 = state[_SZ + 3] + state[_SZ + 7] + state[_SZ + 11]
    det = a00 * a11 - a01 * a10
    if not (det > 0.0 and math.isfinite(det)):
        return math.nan, math.nan, math.nan
    v00 = a11 / det
    v01 = -a01 / det
    v10 = -a10 / det
    v11 = a00 / det
    # W_i' = Z_i A^-1 (eq. 37-38) -> W_i = A^-T Z_i' ; A is symmetric so W_i = A^-1 Z_i'
    gamma0 = 0.0
    beta0 = 0.0
    for i in range(3):
        z00 = state[_SZ + 4 * i]
        z01 = state[_SZ + 4 * i + 1]
        z10 = state[_SZ + 4 * i + 2]
        z11 = state[_SZ + 4 * i + 3]
        # W_i = V Z_i' with V = A^-1: rows of W_i = output (gamma, beta), cols = input
        w_gg = v00 * z00 + v01 * z01
        w_gb = v00 * z10 + v01 * z11
        w_bg = v10 * z00 + v11 * z01
        w_bb = v10 * z10 + v11 * z11
        w0 = W_INDEX[i]
        state[w0] = w_gg
        state[w0 + 1] = w_gb
        state[w0 + 2] = w_bg
        state[w0 + 3] = w_bb
        if i == 0:
            xg, xb = x1[0], x1[1]
        elif i == 1:
            xg, xb = x2[0], x2[1]
        else:
            xg, xb = x3[0], x3[1]
        gamma0 += w_gg * xg + w_gb * xb
        beta0 += w_bg * xg + w_bb * xb
    state[S.FUSED_R] = gamma0
    state[S.FUSED_BETA] = beta0
    state[S.FUSED_VAR_BB] = v11
    return gamma0, beta0, v11


# ---------------------------------------------------------------------------------------------
# the tick
# ---------------------------------------------------------------------------------------------


def validate_vehicle(vehicle: np.ndarray) -> None:
    """Refuse a vehicle vector the 3-DOF model cannot use (at load time, not in the kernel)."""
    needed = (Veh.MASS, Veh.YAW_INERTIA, Veh.LF, Veh.LR, Veh.TRACK_F, Veh.TRACK_R,
              Veh.WHEEL_RADIUS, Veh.MU_NOMINAL, Veh.TYRE_B, Veh.TYRE_C)  # fmt: skip
    for field in needed:
        value = float(vehicle[field])
        if not (math.isfinite(value) and value > 0.0):
            raise ConfigError(f"pseudo_fusion needs a positive vehicle {field.name}, got {value}")
    if not math.isfinite(float(vehicle[Veh.TYRE_E])):
        raise ConfigError("pseudo_fusion needs a finite vehicle TYRE_E")


def new_state() -> np.ndarray:
    """A state vector that starts on the first tick with a usable wheel speed."""
    state = np.zeros(N_STATE, dtype=np.float64)
    state[S.YAW_RATE_FILTERED : S.WHEEL_FILTERED_RR + 1] = np.nan  # filters self-start
    return state


def init(params: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """A fresh state vector (``S``); the estimators start on the first speed sample."""
    validate_vehicle(vehicle)
    if int(params[PARAMS.PART]) not in tuple(Part):
        raise ConfigError(f"pseudo_fusion: part must be one of 0..3, got {params[PARAMS.PART]}")
    # the kernels divide by these (numba raises on a division by zero): refuse them at load
    positive = (PARAMS.R_VX_KBE, PARAMS.R_VY0_KBE, PARAMS.R_AX_DBE, PARAMS.R_AY_DBE,
                PARAMS.R_VX_DBE, PARAMS.FORGETTING, PARAMS.FUSION_TIME_CONSTANT,
                PARAMS.STRAIGHT_SIGMA_YAW_RATE, PARAMS.STRAIGHT_SIGMA_AY, PARAMS.P0_VX,
                PARAMS.P0_VY, PARAMS.P0_R)  # fmt: skip
    for field in positive:
        if not params[field] > 0.0:
            raise ConfigError(f"pseudo_fusion: {field.name.lower()} must be > 0")
    if not (params[PARAMS.FORGETTING] <= 1.0 and params[PARAMS.RIDGE] > 0.0):
        raise ConfigError("pseudo_fusion: forgetting must be in (0, 1] and ridge > 0")
    return new_state()


#: (m/s)^2, the WBE's residual variance before any residual is seen: the wheel-speed noise
#: of the simulator's sensors at 20 m/s, (0.01 + 0.002 x 20)^2 (slipd.sim.sensors), so that the
#: WBE does not start with a zero covariance and take all the fusion weight.
WHEEL_SPEED_VARIANCE0 = 2.5e-3

#: Bits of ``reset_state``'s ``parts`` (and of ``insane_parts``).
RESET_KBE = 1
RESET_DBE = 2
RESET_WBE = 4
RESET_FUSION = 8
RESET_ALL = 15


@nb.njit(cache=True)
def reset_state(state, vx, yaw_rate, params, parts):
    """(Re)start the estimators named by the bits ``parts`` at vy = 0 (straight-running
    assumption), vx and r as measured. Restarting the fusion restarts the tick counter."""
    vx = vx if math.isfinite(vx) else 0.0
    yaw_rate = yaw_rate if math.isfinite(yaw_rate) else 0.0
    p0_vx = params[PARAMS.P0_VX]
    p0_vy = params[PARAMS.P0_VY]
    if parts & RESET_KBE:
        state[S.KBE_VX] = vx
        state[S.KBE_VY] = 0.0
        state[S.KBE_P_XX] = p0_vx
        state[S.KBE_P_XY] = 0.0
        state[S.KBE_P_YY] = p0_vy
    if parts & RESET_DBE:
        state[S.DBE_VX] = vx
        state[S.DBE_VY] = 0.0
        state[S.DBE_R] = yaw_rate
        state[S.DBE_P00] = p0_vx
        state[S.DBE_P01] = 0.0
        state[S.DBE_P02] = 0.0
        state[S.DBE_P11] = p0_vy
        state[S.DBE_P12] = 0.0
        state[S.DBE_P22] = params[PARAMS.P0_R]
    if parts & RESET_WBE:
        # M_0 = k1 I, g_0 = 0 (eq. 24 without data: xi = 0); xi shows the start values until
        # the first wheel row arrives
        state[S.WBE_VX] = vx
        state[S.WBE_VY] = 0.0
        state[S.WBE_R] = yaw_rate
        for i in range(_WBE_FIRST, _WBE_LAST + 1):
            state[i] = 0.0
        ridge = params[PARAMS.RIDGE]
        state[S.WBE_M00] = ridge
        state[S.WBE_M11] = ridge
        state[S.WBE_M22] = ridge
        state[S.WBE_RES_VAR] = WHEEL_SPEED_VARIANCE0
    if parts & RESET_FUSION:
        for i in range(_FUSION_FIRST, _FUSION_LAST + 1):
            state[i] = 0.0
        state[S.TICKS] = 0.0


@nb.njit(cache=True)
def _finite(state, first, last):
    for i in range(first, last + 1):
        if not math.isfinite(state[i]):
            return False
    return True


@nb.njit(cache=True)
def insane_parts(state):
    """Bits of the estimators whose state must restart: non-finite, or outside their model's
    domain (DBE: |vy| < vx, beta within +-45 deg, the tyre model's; KBE: |vy| < 2 vx, the
    kinematics hold at any angle, this only catches a run-away integral)."""
    bad = 0
    vx = state[S.KBE_VX]
    if not (_finite(state, 0, 4) and vx > 0.0 and abs(state[S.KBE_VY]) < 2.0 * vx):
        bad |= RESET_KBE
    vx = state[S.DBE_VX]
    if not (_finite(state, _DBE_VX, _DBE_P00 + 5) and vx > 0.0 and abs(state[S.DBE_VY]) < vx):
        bad |= RESET_DBE
    if not _finite(state, _WBE_VX, _WBE_RES_VAR):
        bad |= RESET_WBE
    if not _finite(state, _FUSION_FIRST, _FUSION_LAST):
        bad |= RESET_FUSION
    return bad


@nb.njit(cache=True)
def own_covariances(state, params):
    """Each estimator's own (gamma, beta) covariance C_i as (gg, gb, bb) triples, and its beta."""
    sigma_r = params[PARAMS.SIGMA_YAW_RATE]
    # KBE: gamma_1 is the gyro (error sigma_yaw_rate), beta from the KF covariance
    vx, vy = state[S.KBE_VX], state[S.KBE_VY]
    _, _, var = beta_moments(vx, vy, state[S.KBE_P_XX], state[S.KBE_P_XY], state[S.KBE_P_YY])
    own1 = (sigma_r * sigma_r, 0.0, var)
    beta1 = math.atan2(vy, vx)
    # DBE: gradient [g1, g2, 0] of beta and e_r of gamma on the 3x3 covariance
    vx, vy = state[S.DBE_VX], state[S.DBE_VY]
    g1, g2, var = beta_moments(vx, vy, state[S.DBE_P00], state[S.DBE_P01], state[S.DBE_P11])
    own2 = (state[S.DBE_P22], g1 * state[S.DBE_P02] + g2 * state[S.DBE_P12], var)
    beta2 = math.atan2(vy, vx)
    # WBE: s^2 M^-1 / (1 + rho)
    rho = params[PARAMS.FORGETTING]
    i00, i01, i02, i11, i12, i22 = inverse_sym3(
        state[S.WBE_M00], state[S.WBE_M01], state[S.WBE_M02],
        state[S.WBE_M11], state[S.WBE_M12], state[S.WBE_M22],
    )  # fmt: skip
    scale = state[S.WBE_RES_VAR] / (1.0 + rho)
    vx, vy = state[S.WBE_VX], state[S.WBE_VY]
    g1, g2, var = beta_moments(vx, vy, scale * i00, scale * i01, scale * i11)
    own3 = (scale * i22, scale * (g1 * i02 + g2 * i12), var)
    beta3 = math.atan2(vy, vx)
    return own1, own2, own3, beta1, beta2, beta3


@nb.njit(cache=True)
def read_inputs(state, u, vehicle, roll_time_constant, dt):
    """Pre-processed inputs of one tick with fallbacks (module docstring).

    Returns (ax, ay, yaw_rate, steer, ax_ok, ay_ok, yaw_rate_ok, status): ax, ay at the CoG
    (3-D lever arm), ay without the gravity component of the roll.
    """
    status = 0
    yaw_rate, yaw_rate_ok = channel(u, In.YAW_RATE)
    if yaw_rate_ok:
        state[S.LAST_YAW_RATE] = yaw_rate
    else:
        status |= ST_INPUT_TIMEOUT
        # the DBE's yaw rate stands in for the gyro once it runs
        yaw_rate = state[S.DBE_R] if state[S.INITIALISED] > 0.5 else state[S.LAST_YAW_RATE]
    steer, steer_ok = channel(u, In.STEER)
    if steer_ok:
        state[S.LAST_STEER] = steer
    else:
        steer = state[S.LAST_STEER]
        status |= ST_INPUT_TIMEOUT
    roll_rate, roll_rate_ok = channel(u, In.ROLL_RATE)
    pitch_rate, pitch_rate_ok = channel(u, In.PITCH_RATE)
    if not (roll_rate_ok and pitch_rate_ok):
        status |= ST_DEGRADED  # the lever arm falls back toward planar
    roll_rate = roll_rate if roll_rate_ok else 0.0
    pitch_rate = pitch_rate if pitch_rate_ok else 0.0
    cutoff = DERIVATIVE_CUTOFF_HZ  # Selmanaj section 2.1: 10 Hz
    ax, ay, yaw_acc, ax_ok, ay_ok = imu_at_cog(
        state, S.YAW_RATE_FILTERED, S.ROLL_RATE_FILTERED, S.PITCH_RATE_FILTERED, u, yaw_rate,
        roll_rate, pitch_rate, dt, cutoff, vehicle,
    )  # fmt: skip
    if ax_ok:
        state[S.LAST_AX] = ax
    else:
        ax = state[S.LAST_AX]
        status |= ST_INPUT_TIMEOUT
    if ay_ok:
        if roll_time_constant > 0.0:
            roll = roll_complementary_filter(
                state, S.ROLL, ay, roll_rate, roll_rate_ok, dt,
                roll_static_gain(vehicle[Veh.MASS], vehicle[Veh.H_ROLL_AXIS],
                                 vehicle[Veh.ROLL_STIFFNESS]),
                roll_time_constant,
            )  # fmt: skip
            ay = compensate_gravity_ay(ay, roll)
        state[S.LAST_AY] = ay
    else:
        ay = state[S.LAST_AY]
        status |= ST_INPUT_TIMEOUT
    return ax, ay, yaw_rate, steer, ax_ok, ay_ok, yaw_rate_ok, status


@nb.njit(cache=True)
def _wheel_accel(state, slot, speed, ok, dt):
    return derivative_filter(state, slot, speed, dt, DERIVATIVE_CUTOFF_HZ) if ok else 0.0


@nb.njit(cache=True)
def longitudinal_forces(state, u, ax, vehicle, wheel_ok, dt):
    """Fx per wheel (FL, FR, RL, RR) [N] and whether the torque frames were usable.

    Fx = (T_drive - T_brake - J_w dw/dt) / r_w with dw/dt = (dv/dt) / r_w from the derivative
    filter of the wheel speed (slipd's stand-in for the force observer of Chen's ref. [4]).
    Without valid torques the total m ax is shared equally.
    """
    rw = vehicle[Veh.WHEEL_RADIUS]
    inertia = vehicle[Veh.WHEEL_INERTIA] / (rw * rw)
    acc_fl = _wheel_accel(state, S.WHEEL_FILTERED_FL, u[In.WHEEL_SPEED_FL], wheel_ok[0], dt)
    acc_fr = _wheel_accel(state, S.WHEEL_FILTERED_FR, u[In.WHEEL_SPEED_FR], wheel_ok[1], dt)
    acc_rl = _wheel_accel(state, S.WHEEL_FILTERED_RL, u[In.WHEEL_SPEED_RL], wheel_ok[2], dt)
    acc_rr = _wheel_accel(state, S.WHEEL_FILTERED_RR, u[In.WHEEL_SPEED_RR], wheel_ok[3], dt)
    torques_ok = True
    for ch in range(_TORQUE_FIRST, _TORQUE_LAST + 1):
        if not (u[VALID + ch] > 0.5 and math.isfinite(u[ch])):
            torques_ok = False
    if not torques_ok:
        share = 0.25 * vehicle[Veh.MASS] * ax
        return (share, share, share, share), False
    return (
        (u[In.DRIVE_TORQUE_FL] - u[In.BRAKE_TORQUE_FL]) / rw - inertia * acc_fl,
        (u[In.DRIVE_TORQUE_FR] - u[In.BRAKE_TORQUE_FR]) / rw - inertia * acc_fr,
        (u[In.DRIVE_TORQUE_RL] - u[In.BRAKE_TORQUE_RL]) / rw - inertia * acc_rl,
        (u[In.DRIVE_TORQUE_RR] - u[In.BRAKE_TORQUE_RR]) / rw - inertia * acc_rr,
    ), True


@nb.njit(cache=True)
def write_outputs(out, beta, vx, ax, ay, yaw_rate, sigma, roll, status):
    """Fill ``out``: vy = vx tan(beta); beta rate from the kinematic model,
    (vx ay - vy ax) / V^2 - r (no differentiation of a noisy estimate)."""
    vy = vx * math.tan(beta)
    speed2 = vx * vx + vy * vy
    out[Out.BETA] = beta
    out[Out.BETA_RATE] = (vx * ay - vy * ax) / speed2 - yaw_rate if speed2 > 1.0 else 0.0
    out[Out.VX] = vx
    out[Out.VY] = vy
    out[Out.MU] = math.nan  # mu is the fixed MU_NOMINAL of the tyre model, not estimated
    out[Out.SIGMA_BETA] = sigma
    out[Out.ROLL] = roll if math.isfinite(roll) else 0.0
    out[Out.FRICTION_CLASS] = 0.0
    out[Out.STATUS] = float(status)


@nb.njit(cache=True)
def step(state, u, params, vehicle, dt, out):
    """One tick: update the three estimators with tick k's measurements, fuse (eq. 38-39),
    write ``out`` (the part selected by params[PART]) and predict to tick k + 1 with tick k's
    inputs (eq. 2, eq. 9-10). Allocates nothing."""
    min_speed = params[PARAMS.MIN_SPEED]
    ax, ay, yaw_rate, steer, ax_ok, ay_ok, yaw_rate_ok, status = read_inputs(
        state, u, vehicle, params[PARAMS.ROLL_TIME_CONSTANT], dt
    )
    speed_fl, ok_fl = channel(u, In.WHEEL_SPEED_FL)
    speed_fr, ok_fr = channel(u, In.WHEEL_SPEED_FR)
    speed_rl, ok_rl = channel(u, In.WHEEL_SPEED_RL)
    speed_rr, ok_rr = channel(u, In.WHEEL_SPEED_RR)
    wheel_ok = (ok_fl, ok_fr, ok_rl, ok_rr)
    n_wheels = int(ok_fl) + int(ok_fr) + int(ok_rl) + int(ok_rr)
    if n_wheels < 4:
        status |= ST_INPUT_TIMEOUT
    corner_fl, corner_fr, corner_rl, corner_rr = compensate_wheel_speeds(
        speed_fl, speed_fr, speed_rl, speed_rr, steer, yaw_rate,
        vehicle[Veh.TRACK_F], vehicle[Veh.TRACK_R],
    )  # fmt: skip
    vx_meas = 0.0
    if ok_fl:
        vx_meas += corner_fl
    if ok_fr:
        vx_meas += corner_fr
    if ok_rl:
        vx_meas += corner_rl
    if ok_rr:
        vx_meas += corner_rr
    vx_ok = n_wheels > 0
    if vx_ok:
        vx_meas /= n_wheels
    fx, torques_ok = longitudinal_forces(state, u, ax, vehicle, wheel_ok, dt)
    if not torques_ok:
        status |= ST_DEGRADED
    fz = vertical_loads(ax, ay, vehicle)
    roll = state[S.ROLL]

    speed_now = vx_meas if vx_ok else state[S.DBE_VX]
    if state[S.INITIALISED] < 0.5 or speed_now < min_speed:
        # start-up / standstill: hold at vy = 0 on the wheel speed
        if vx_ok:
            reset_state(state, vx_meas, yaw_rate, params, RESET_ALL)
            state[S.INITIALISED] = 1.0
        sigma = math.atan(math.sqrt(params[PARAMS.P0_VY]) / max(speed_now, min_speed, 0.1))
        write_outputs(out, 0.0, max(speed_now, 0.0), ax, ay, yaw_rate, sigma, roll,
                      status | ST_NOT_CONVERGED)  # fmt: skip
        out[Out.BETA_RATE] = 0.0
        return

    first_tick = state[S.TICKS] < 0.5
    # --- a posteriori at tick k ---------------------------------------------------------------
    straight = gaussian_bell(  # how sure the car runs straight
        yaw_rate, params[PARAMS.STRAIGHT_SIGMA_YAW_RATE], ay, params[PARAMS.STRAIGHT_SIGMA_AY]
    )
    kbe_update(state, vx_meas, vx_ok, params[PARAMS.R_VX_KBE], params[PARAMS.R_VY0_KBE], straight)
    dbe_update(
        state, steer, fx, fz, vehicle, ax, ax_ok, params[PARAMS.R_AX_DBE], ay, ay_ok,
        params[PARAMS.R_AY_DBE], vx_meas, vx_ok, params[PARAMS.R_VX_DBE],
    )  # fmt: skip
    wbe_update(
        state, (speed_fl, speed_fr, speed_rl, speed_rr), wheel_ok, steer, vehicle,
        params[PARAMS.FORGETTING], params[PARAMS.RIDGE],
    )  # fmt: skip
    own1, own2, own3, beta1, beta2, beta3 = own_covariances(state, params)
    x1 = (yaw_rate, beta1)
    x2 = (state[S.DBE_R], beta2)
    x3 = (state[S.WBE_R], beta3)
    # --- difference moments and fusion (eq. 38-39) ---------------------------------------------
    if first_tick:
        # no history yet: the moments the own covariances imply for independent errors
        for k in range(3):
            state[S.D12_GG + k] = own1[k] + own2[k]
            state[S.D13_GG + k] = own1[k] + own3[k]
            state[S.D23_GG + k] = own2[k] + own3[k]
    gain = dt / params[PARAMS.FUSION_TIME_CONSTANT]
    if gain > 1.0:
        gain = 1.0
    update_difference_moments(state, S.D12_GG, x1[0] - x2[0], x1[1] - x2[1], gain)
    update_difference_moments(state, S.D13_GG, x1[0] - x3[0], x1[1] - x3[1], gain)
    update_difference_moments(state, S.D23_GG, x2[0] - x3[0], x2[1] - x3[1], gain)
    _, beta0, var0 = fuse(
        state, own1, own2, own3, x1, x2, x3,
        int(params[PARAMS.VARIANCE_FROM_DIFFERENCES]), params[PARAMS.CROSS_COVARIANCE] > 0.5,
        params[PARAMS.FUSION_FLOOR],
    )  # fmt: skip
    part = int(params[PARAMS.PART])
    if part == 1:
        beta, vx, var = beta1, state[S.KBE_VX], own1[2]
    elif part == 2:
        beta, vx, var = beta2, state[S.DBE_VX], own2[2]
    elif part == 3:
        beta, vx, var = beta3, state[S.WBE_VX], own3[2]
    else:
        beta, vx, var = beta0, state[S.DBE_VX], var0
    # --- a priori for tick k + 1 with tick k's inputs ------------------------------------------
    kbe_predict(state, ax, ay, yaw_rate, params[PARAMS.Q_VX_KBE], params[PARAMS.Q_VY_KBE], dt)
    dbe_predict(
        state, steer, fx, fz, vehicle,
        params[PARAMS.Q_VX_DBE], params[PARAMS.Q_VY_DBE], params[PARAMS.Q_R_DBE], dt,
    )  # fmt: skip
    state[S.TICKS] += 1.0
    bad = insane_parts(state)
    if not (math.isfinite(beta) and math.isfinite(vx) and vx > 0.0 and math.isfinite(var)):
        bad = RESET_ALL
    if bad:
        reset_state(state, speed_now, yaw_rate, params, bad)
        # RESET when the output's own source restarted (the fused output: any part)
        if part == 0 or bad & RESET_FUSION or bad & (1 << (part - 1)):
            status |= ST_RESET | ST_NOT_CONVERGED
        if bad == RESET_ALL or (part > 0 and bad & (1 << (part - 1))):
            sigma = math.atan(math.sqrt(params[PARAMS.P0_VY]) / max(speed_now, min_speed, 0.1))
            write_outputs(out, 0.0, speed_now, ax, ay, yaw_rate, sigma, roll, status)
            return
    if abs(beta) > BETA_LIMIT:
        # beyond a single-track model's domain (the fused output can be, by extrapolating
        # weights): clamp and say so
        beta = BETA_LIMIT if beta > 0.0 else -BETA_LIMIT
        status |= ST_NOT_CONVERGED
    sigma = math.sqrt(var) if var > 0.0 else 0.0
    if state[S.TICKS] < params[PARAMS.SETTLE_TICKS] or not (
        sigma <= params[PARAMS.CONVERGED_SIGMA_BETA]
    ):
        status |= ST_NOT_CONVERGED
    write_outputs(out, beta, vx, ax, ay, yaw_rate, sigma, roll, status)


@nb.njit(cache=True)
def run_ticks(state, U, params, vehicle, dt, OUT):
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])
