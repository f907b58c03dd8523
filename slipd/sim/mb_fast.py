"""A numba transcription of vehiclemodels' ``vehicle_dynamics_mb`` (CommonRoad multi-body model,
version 3.0.2) with its tyre model and input constraints, line for line.

Why: the package's pure-Python right-hand side costs ~60 us per call and a stiff integrator calls
it ~400 times per simulated second (70 % of them for finite-difference Jacobians), which makes the
4000 s endurance drive take many minutes. This transcription computes the same numbers ~50x
faster. It is not a different model: tests/test_sim.py evaluates both on random states and
inputs and requires agreement to 1e-9 (relative), and :class:`slipd.sim.plant.Plant` can run
either (``fast=False`` uses the package itself).

Parameters travel as two float64 vectors built by :func:`pack` (vehicle, ``P_*`` indices) and
:func:`pack_tire` (tyre, ``T_*`` indices).
"""

from __future__ import annotations

import math

import numpy as np

from slipd.numba_cache import nb as numba

_P_NAMES = (
    "m", "m_s", "m_uf", "m_ur", "a", "b", "I_Phi_s", "I_y_s", "I_z", "I_xz_s", "K_sf", "K_sdf",
    "K_sr", "K_sdr", "T_f", "T_r", "K_ras", "K_tsf", "K_tsr", "K_rad", "K_zt", "h_raf", "h_rar",
    "h_s", "I_uf", "I_ur", "I_y_w", "K_lt", "R_w", "T_sb", "T_se", "D_f", "D_r", "E_f", "E_r",
    "steer_min", "steer_max", "steer_v_min", "steer_v_max",
    "long_v_switch", "long_a_max", "long_v_min", "long_v_max",
)
_T_NAMES = (
    "p_cx1", "p_dx1", "p_dx3", "p_ex1", "p_kx1", "p_hx1", "p_vx1", "r_bx1", "r_bx2", "r_cx1",
    "r_ex1", "r_hx1", "p_cy1", "p_dy1", "p_dy3", "p_ey1", "p_ky1", "p_hy1", "p_hy3", "p_vy1",
    "p_vy3", "r_by1", "r_by2", "r_by3", "r_cy1", "r_ey1", "r_hy1", "r_vy1", "r_vy3", "r_vy4",
    "r_vy5", "r_vy6",
)
(P_M, P_M_S, P_M_UF, P_M_UR, P_A, P_B, P_I_PHI_S, P_I_Y_S, P_I_Z, P_I_XZ_S, P_K_SF, P_K_SDF,
 P_K_SR, P_K_SDR, P_T_F, P_T_R, P_K_RAS, P_K_TSF, P_K_TSR, P_K_RAD, P_K_ZT, P_H_RAF, P_H_RAR,
 P_H_S, P_I_UF, P_I_UR, P_I_Y_W, P_K_LT, P_R_W, P_T_SB, P_T_SE, P_D_F, P_D_R, P_E_F, P_E_R,
 P_STEER_MIN, P_STEER_MAX, P_STEER_V_MIN, P_STEER_V_MAX,
 P_V_SWITCH, P_A_MAX, P_V_MIN, P_V_MAX) = range(len(_P_NAMES))
(T_PCX1, T_PDX1, T_PDX3, T_PEX1, T_PKX1, T_PHX1, T_PVX1, T_RBX1, T_RBX2, T_RCX1, T_REX1,
 T_RHX1, T_PCY1, T_PDY1, T_PDY3, T_PEY1, T_PKY1, T_PHY1, T_PHY3, T_PVY1, T_PVY3, T_RBY1,
 T_RBY2, T_RBY3, T_RCY1, T_REY1, T_RHY1, T_RVY1, T_RVY3, T_RVY4, T_RVY5,
 T_RVY6) = range(len(_T_NAMES))


def pack(p) -> np.ndarray:
    """The vehicle parameters of a vehiclemodels parameter object as a vector (``P_*``)."""
    values = []
    for name in _P_NAMES:
        if name.startswith("steer_"):
            values.append(getattr(p.steering, name[len("steer_"):]))
        elif name.startswith("long_"):
            values.append(getattr(p.longitudinal, name[len("long_"):]))
        else:
            values.append(getattr(p, name))
    return np.array(values, dtype=np.float64)


def pack_tire(tire) -> np.ndarray:
    """The tyre parameters (``p.tire``) as a vector (``T_*``)."""
    return np.array([getattr(tire, n) for n in _T_NAMES], dtype=np.float64)


@numba.njit(cache=True)
def _sign(x):
    if x > 0:
        return 1.0
    elif x < 0:
        return -1.0
    return 0.0


@numba.njit(cache=True)
def steering_constraints(steering_angle, steering_velocity, P):
    if (steering_angle <= P[P_STEER_MIN] and steering_velocity <= 0) or (
        steering_angle >= P[P_STEER_MAX] and steering_velocity >= 0
    ):
        steering_velocity = 0.0
    elif steering_velocity <= P[P_STEER_V_MIN]:
        steering_velocity = P[P_STEER_V_MIN]
    elif steering_velocity >= P[P_STEER_V_MAX]:
        steering_velocity = P[P_STEER_V_MAX]
    return steering_velocity


@numba.njit(cache=True)
def acceleration_constraints(velocity, acceleration, P):
    if velocity > P[P_V_SWITCH]:
        pos_limit = P[P_A_MAX] * P[P_V_SWITCH] / velocity
    else:
        pos_limit = P[P_A_MAX]
    if (velocity <= P[P_V_MIN] and acceleration <= 0) or (
        velocity >= P[P_V_MAX] and acceleration >= 0
    ):
        acceleration = 0.0
    elif acceleration <= -P[P_A_MAX]:
        acceleration = -P[P_A_MAX]
    elif acceleration >= pos_limit:
        acceleration = pos_limit
    return acceleration


@numba.njit(cache=True)
def formula_longitudinal(kappa, gamma, F_z, T):
    kappa = -kappa
    S_hx = T[T_PHX1]
    S_vx = F_z * T[T_PVX1]
    kappa_x = kappa + S_hx
    mu_x = T[T_PDX1] * (1 - T[T_PDX3] * gamma**2)
    C_x = T[T_PCX1]
    D_x = mu_x * F_z
    E_x = T[T_PEX1]
    K_x = F_z * T[T_PKX1]
    B_x = K_x / (C_x * D_x)
    return D_x * math.sin(
        C_x * math.atan(B_x * kappa_x - E_x * (B_x * kappa_x - math.atan(B_x * kappa_x))) + S_vx
    )


@numba.njit(cache=True)
def formula_lateral(alpha, gamma, F_z, T):
    S_hy = _sign(gamma) * (T[T_PHY1] + T[T_PHY3] * math.fabs(gamma))
    S_vy = _sign(gamma) * F_z * (T[T_PVY1] + T[T_PVY3] * math.fabs(gamma))
    alpha_y = alpha + S_hy
    mu_y = T[T_PDY1] * (1 - T[T_PDY3] * gamma**2)
    C_y = T[T_PCY1]
    D_y = mu_y * F_z
    E_y = T[T_PEY1]
    K_y = F_z * T[T_PKY1]
    B_y = K_y / (C_y * D_y)
    F_y = D_y * math.sin(
        C_y * math.atan(B_y * alpha_y - E_y * (B_y * alpha_y - math.atan(B_y * alpha_y)))
    ) + S_vy
    return F_y, mu_y


@numba.njit(cache=True)
def formula_longitudinal_comb(kappa, alpha, F0_x, T):
    S_hxalpha = T[T_RHX1]
    alpha_s = alpha + S_hxalpha
    B_xalpha = T[T_RBX1] * math.cos(math.atan(T[T_RBX2] * kappa))
    C_xalpha = T[T_RCX1]
    E_xalpha = T[T_REX1]
    D_xalpha = F0_x / (math.cos(C_xalpha * math.atan(
        B_xalpha * S_hxalpha - E_xalpha * (B_xalpha * S_hxalpha - math.atan(B_xalpha * S_hxalpha))
    )))
    return D_xalpha * math.cos(C_xalpha * math.atan(
        B_xalpha * alpha_s - E_xalpha * (B_xalpha * alpha_s - math.atan(B_xalpha * alpha_s))
    ))


@numba.njit(cache=True)
def formula_lateral_comb(kappa, alpha, gamma, mu_y, F_z, F0_y, T):
    S_hykappa = T[T_RHY1]
    kappa_s = kappa + S_hykappa
    B_ykappa = T[T_RBY1] * math.cos(math.atan(T[T_RBY2] * (alpha - T[T_RBY3])))
    C_ykappa = T[T_RCY1]
    E_ykappa = T[T_REY1]
    D_ykappa = F0_y / (math.cos(C_ykappa * math.atan(
        B_ykappa * S_hykappa - E_ykappa * (B_ykappa * S_hykappa - math.atan(B_ykappa * S_hykappa))
    )))
    D_vykappa = mu_y * F_z * (T[T_RVY1] + T[T_RVY3] * gamma) * math.cos(
        math.atan(T[T_RVY4] * alpha))
    S_vykappa = D_vykappa * math.sin(T[T_RVY5] * math.atan(T[T_RVY6] * kappa))
    return D_ykappa * math.cos(C_ykappa * math.atan(
        B_ykappa * kappa_s - E_ykappa * (B_ykappa * kappa_s - math.atan(B_ykappa * kappa_s))
    )) + S_vykappa


@numba.njit(cache=True)
def vehicle_dynamics_mb(x_in, u_init0, u_init1, P, T):
    """Right-hand side of the 29 multi-body states (see vehiclemodels/vehicle_dynamics_mb.py).

    Raises ZeroDivisionError exactly where the package does (numba's division check)."""
    x = x_in.copy()
    g = 9.81
    u0 = steering_constraints(x[2], u_init0, P)
    u1 = acceleration_constraints(x[3], u_init1, P)

    a = P[P_A]
    b = P[P_B]
    T_f = P[P_T_F]
    T_r = P[P_T_R]
    R_w = P[P_R_W]
    K_zt = P[P_K_ZT]
    h_s = P[P_H_S]

    if abs(x[3]) < 0.1:
        beta = 0.0
    else:
        beta = math.atan(x[10] / x[3])
    vel = math.sqrt(x[3] ** 2 + x[10] ** 2)

    F_z_LF = (x[16] + R_w * (math.cos(x[13]) - 1) - 0.5 * T_f * math.sin(x[13])) * K_zt
    F_z_RF = (x[16] + R_w * (math.cos(x[13]) - 1) + 0.5 * T_f * math.sin(x[13])) * K_zt
    F_z_LR = (x[21] + R_w * (math.cos(x[18]) - 1) - 0.5 * T_r * math.sin(x[18])) * K_zt
    F_z_RR = (x[21] + R_w * (math.cos(x[18]) - 1) + 0.5 * T_r * math.sin(x[18])) * K_zt

    u_w_lf = (x[3] + 0.5 * T_f * x[5]) * math.cos(x[2]) + (x[10] + a * x[5]) * math.sin(x[2])
    u_w_rf = (x[3] - 0.5 * T_f * x[5]) * math.cos(x[2]) + (x[10] + a * x[5]) * math.sin(x[2])
    u_w_lr = x[3] + 0.5 * T_r * x[5]
    u_w_rr = x[3] - 0.5 * T_r * x[5]
    if u_w_lf < 0.0:
        u_w_lf *= 0
    if u_w_rf < 0.0:
        u_w_rf *= 0
    if u_w_lr < 0.0:
        u_w_lr *= 0
    if u_w_rr < 0.0:
        u_w_rr *= 0

    if abs(x[3]) < 0.1:
        s_lf = 0.0
        s_rf = 0.0
        s_lr = 0.0
        s_rr = 0.0
    else:
        s_lf = 1 - R_w * x[23] / u_w_lf
        s_rf = 1 - R_w * x[24] / u_w_rf
        s_lr = 1 - R_w * x[25] / u_w_lr
        s_rr = 1 - R_w * x[26] / u_w_rr

    if abs(x[3]) < 0.1:
        alpha_LF = 0.0
        alpha_RF = 0.0
        alpha_LR = 0.0
        alpha_RR = 0.0
    else:
        alpha_LF = math.atan((x[10] + a * x[5] - x[14] * (R_w - x[16])) / (x[3] + 0.5 * T_f * x[5])) - x[2]  # noqa: E501
        alpha_RF = math.atan((x[10] + a * x[5] - x[14] * (R_w - x[16])) / (x[3] - 0.5 * T_f * x[5])) - x[2]  # noqa: E501
        alpha_LR = math.atan((x[10] - b * x[5] - x[19] * (R_w - x[21])) / (x[3] + 0.5 * T_r * x[5]))  # noqa: E501
        alpha_RR = math.atan((x[10] - b * x[5] - x[19] * (R_w - x[21])) / (x[3] - 0.5 * T_r * x[5]))  # noqa: E501

    z_SLF = (h_s - R_w + x[16] - x[11]) / math.cos(x[6]) - h_s + R_w + a * x[8] + 0.5 * (x[6] - x[13]) * T_f  # noqa: E501
    z_SRF = (h_s - R_w + x[16] - x[11]) / math.cos(x[6]) - h_s + R_w + a * x[8] - 0.5 * (x[6] - x[13]) * T_f  # noqa: E501
    z_SLR = (h_s - R_w + x[21] - x[11]) / math.cos(x[6]) - h_s + R_w - b * x[8] + 0.5 * (x[6] - x[18]) * T_r  # noqa: E501
    z_SRR = (h_s - R_w + x[21] - x[11]) / math.cos(x[6]) - h_s + R_w - b * x[8] - 0.5 * (x[6] - x[18]) * T_r  # noqa: E501

    dz_SLF = x[17] - x[12] + a * x[9] + 0.5 * (x[7] - x[14]) * T_f
    dz_SRF = x[17] - x[12] + a * x[9] - 0.5 * (x[7] - x[14]) * T_f
    dz_SLR = x[22] - x[12] - b * x[9] + 0.5 * (x[7] - x[19]) * T_r
    dz_SRR = x[22] - x[12] - b * x[9] - 0.5 * (x[7] - x[19]) * T_r

    gamma_LF = x[6] + P[P_D_F] * z_SLF + P[P_E_F] * (z_SLF) ** 2
    gamma_RF = x[6] - P[P_D_F] * z_SRF - P[P_E_F] * (z_SRF) ** 2
    gamma_LR = x[6] + P[P_D_R] * z_SLR + P[P_E_R] * (z_SLR) ** 2
    gamma_RR = x[6] - P[P_D_R] * z_SRR - P[P_E_R] * (z_SRR) ** 2

    F0_x_LF = formula_longitudinal(s_lf, gamma_LF, F_z_LF, T)
    F0_x_RF = formula_longitudinal(s_rf, gamma_RF, F_z_RF, T)
    F0_x_LR = formula_longitudinal(s_lr, gamma_LR, F_z_LR, T)
    F0_x_RR = formula_longitudinal(s_rr, gamma_RR, F_z_RR, T)

    F0_y_LF, mu_y_LF = formula_lateral(alpha_LF, gamma_LF, F_z_LF, T)
    F0_y_RF, mu_y_RF = formula_lateral(alpha_RF, gamma_RF, F_z_RF, T)
    F0_y_LR, mu_y_LR = formula_lateral(alpha_LR, gamma_LR, F_z_LR, T)
    F0_y_RR, mu_y_RR = formula_lateral(alpha_RR, gamma_RR, F_z_RR, T)

    F_x_LF = formula_longitudinal_comb(s_lf, alpha_LF, F0_x_LF, T)
    F_x_RF = formula_longitudinal_comb(s_rf, alpha_RF, F0_x_RF, T)
    F_x_LR = formula_longitudinal_comb(s_lr, alpha_LR, F0_x_LR, T)
    F_x_RR = formula_longitudinal_comb(s_rr, alpha_RR, F0_x_RR, T)

    F_y_LF = formula_lateral_comb(s_lf, alpha_LF, gamma_LF, mu_y_LF, F_z_LF, F0_y_LF, T)
    F_y_RF = formula_lateral_comb(s_rf, alpha_RF, gamma_RF, mu_y_RF, F_z_RF, F0_y_RF, T)
    F_y_LR = formula_lateral_comb(s_lr, alpha_LR, gamma_LR, mu_y_LR, F_z_LR, F0_y_LR, T)
    F_y_RR = formula_lateral_comb(s_rr, alpha_RR, gamma_RR, mu_y_RR, F_z_RR, F0_y_RR, T)

    h_raf = P[P_H_RAF]
    h_rar = P[P_H_RAR]
    K_ras = P[P_K_RAS]
    K_rad = P[P_K_RAD]

    delta_z_f = h_s - R_w + x[16] - x[11]
    delta_z_r = h_s - R_w + x[21] - x[11]
    delta_phi_f = x[6] - x[13]
    delta_phi_r = x[6] - x[18]
    dot_delta_phi_f = x[7] - x[14]
    dot_delta_phi_r = x[7] - x[19]
    dot_delta_z_f = x[17] - x[12]
    dot_delta_z_r = x[22] - x[12]
    dot_delta_y_f = x[10] + a * x[5] - x[15]
    dot_delta_y_r = x[10] - b * x[5] - x[20]

    delta_f = delta_z_f * math.sin(x[6]) - x[27] * math.cos(x[6]) - (h_raf - R_w) * math.sin(delta_phi_f)  # noqa: E501
    delta_r = delta_z_r * math.sin(x[6]) - x[28] * math.cos(x[6]) - (h_rar - R_w) * math.sin(delta_phi_r)  # noqa: E501
    dot_delta_f = (delta_z_f * math.cos(x[6]) + x[27] * math.sin(x[6])) * x[7] + dot_delta_z_f * math.sin(x[6]) - dot_delta_y_f * math.cos(x[6]) - (h_raf - R_w) * math.cos(delta_phi_f) * dot_delta_phi_f  # noqa: E501
    dot_delta_r = (delta_z_r * math.cos(x[6]) + x[28] * math.sin(x[6])) * x[7] + dot_delta_z_r * math.sin(x[6]) - dot_delta_y_r * math.cos(x[6]) - (h_rar - R_w) * math.cos(delta_phi_r) * dot_delta_phi_r  # noqa: E501

    F_RAF = delta_f * K_ras + dot_delta_f * K_rad
    F_RAR = delta_r * K_ras + dot_delta_r * K_rad

    m_s = P[P_M_S]
    wb = a + b
    F_SLF = m_s * g * b / (2 * wb) - z_SLF * P[P_K_SF] - dz_SLF * P[P_K_SDF] + (x[6] - x[13]) * P[P_K_TSF] / T_f  # noqa: E501
    F_SRF = m_s * g * b / (2 * wb) - z_SRF * P[P_K_SF] - dz_SRF * P[P_K_SDF] - (x[6] - x[13]) * P[P_K_TSF] / T_f  # noqa: E501
    F_SLR = m_s * g * a / (2 * wb) - z_SLR * P[P_K_SR] - dz_SLR * P[P_K_SDR] + (x[6] - x[18]) * P[P_K_TSR] / T_r  # noqa: E501
    F_SRR = m_s * g * a / (2 * wb) - z_SRR * P[P_K_SR] - dz_SRR * P[P_K_SDR] - (x[6] - x[18]) * P[P_K_TSR] / T_r  # noqa: E501

    sumX = F_x_LR + F_x_RR + (F_x_LF + F_x_RF) * math.cos(x[2]) - (F_y_LF + F_y_RF) * math.sin(x[2])  # noqa: E501
    sumN = (F_y_LF + F_y_RF) * a * math.cos(x[2]) + (F_x_LF + F_x_RF) * a * math.sin(x[2]) \
        + (F_y_RF - F_y_LF) * 0.5 * T_f * math.sin(x[2]) + (F_x_LF - F_x_RF) * 0.5 * T_f * math.cos(x[2]) \
        + (F_x_LR - F_x_RR) * 0.5 * T_r - (F_y_LR + F_y_RR) * b  # noqa: E501
    sumY_s = (F_RAF + F_RAR) * math.cos(x[6]) + (F_SLF + F_SLR + F_SRF + F_SRR) * math.sin(x[6])
    sumL = 0.5 * F_SLF * T_f + 0.5 * F_SLR * T_r - 0.5 * F_SRF * T_f - 0.5 * F_SRR * T_r \
        - F_RAF / math.cos(x[6]) * (h_s - x[11] - R_w + x[16] - (h_raf - R_w) * math.cos(x[13])) \
        - F_RAR / math.cos(x[6]) * (h_s - x[11] - R_w + x[21] - (h_rar - R_w) * math.cos(x[18]))
    sumZ_s = (F_SLF + F_SLR + F_SRF + F_SRR) * math.cos(x[6]) - (F_RAF + F_RAR) * math.sin(x[6])
    sumM_s = a * (F_SLF + F_SRF) - b * (F_SLR + F_SRR) + ((F_x_LF + F_x_RF) * math.cos(x[2])
                                                          - (F_y_LF + F_y_RF) * math.sin(x[2])
                                                          + F_x_LR + F_x_RR) * (h_s - x[11])

    K_lt = P[P_K_LT]
    sumL_uf = 0.5 * F_SRF * T_f - 0.5 * F_SLF * T_f - F_RAF * (h_raf - R_w) \
        + F_z_LF * (R_w * math.sin(x[13]) + 0.5 * T_f * math.cos(x[13]) - K_lt * F_y_LF) \
        - F_z_RF * (-R_w * math.sin(x[13]) + 0.5 * T_f * math.cos(x[13]) + K_lt * F_y_RF) \
        - ((F_y_LF + F_y_RF) * math.cos(x[2]) + (F_x_LF + F_x_RF) * math.sin(x[2])) * (R_w - x[16])  # noqa: E501
    sumL_ur = 0.5 * F_SRR * T_r - 0.5 * F_SLR * T_r - F_RAR * (h_rar - R_w) \
        + F_z_LR * (R_w * math.sin(x[18]) + 0.5 * T_r * math.cos(x[18]) - K_lt * F_y_LR) \
        - F_z_RR * (-R_w * math.sin(x[18]) + 0.5 * T_r * math.cos(x[18]) + K_lt * F_y_RR) \
        - (F_y_LR + F_y_RR) * (R_w - x[21])
    sumZ_uf = F_z_LF + F_z_RF + F_RAF * math.sin(x[6]) - (F_SLF + F_SRF) * math.cos(x[6])
    sumZ_ur = F_z_LR + F_z_RR + F_RAR * math.sin(x[6]) - (F_SLR + F_SRR) * math.cos(x[6])
    sumY_uf = (F_y_LF + F_y_RF) * math.cos(x[2]) + (F_x_LF + F_x_RF) * math.sin(x[2]) \
        - F_RAF * math.cos(x[6]) - (F_SLF + F_SRF) * math.sin(x[6])
    sumY_ur = (F_y_LR + F_y_RR) - F_RAR * math.cos(x[6]) - (F_SLR + F_SRR) * math.sin(x[6])

    f = np.empty(29)
    I_z = P[P_I_Z]
    I_xz_s = P[P_I_XZ_S]
    I_Phi_s = P[P_I_PHI_S]
    m = P[P_M]
    if abs(x[3]) < 0.1:
        lwb = a + b
        # vehicle_dynamics_ks_cog re-applies the (idempotent) constraints to u
        uk0 = steering_constraints(x[2], u0, P)
        uk1 = acceleration_constraints(x[3], u1, P)
        beta_ks = math.atan(math.tan(x[2]) * b / lwb)
        f[0] = x[3] * math.cos(beta_ks + x[4])
        f[1] = x[3] * math.sin(beta_ks + x[4])
        f[2] = uk0
        f[3] = uk1
        f[4] = x[3] * math.cos(beta_ks) * math.tan(x[2]) / lwb
        d_beta = (b * u0) / (lwb * math.cos(x[2]) ** 2 * (1 + (math.tan(x[2]) ** 2 * b / lwb) ** 2))
        f[5] = 1 / lwb * (u1 * math.cos(x[6]) * math.tan(x[2])
                          - x[3] * math.sin(x[6]) * d_beta * math.tan(x[2])
                          + x[3] * math.cos(x[6]) * u0 / math.cos(x[2]) ** 2)
    else:
        f[0] = math.cos(beta + x[4]) * vel
        f[1] = math.sin(beta + x[4]) * vel
        f[2] = u0
        f[3] = 1 / m * sumX + x[5] * x[10]
        f[4] = x[5]
        f[5] = 1 / (I_z - (I_xz_s) ** 2 / I_Phi_s) * (sumN + I_xz_s / I_Phi_s * sumL)

    f[6] = x[7]
    f[7] = 1 / (I_Phi_s - (I_xz_s) ** 2 / I_z) * (I_xz_s / I_z * sumN + sumL)
    f[8] = x[9]
    f[9] = 1 / P[P_I_Y_S] * sumM_s
    f[10] = 1 / m_s * sumY_s - x[5] * x[3]
    f[11] = x[12]
    f[12] = g - 1 / m_s * sumZ_s
    f[13] = x[14]
    f[14] = 1 / P[P_I_UF] * sumL_uf
    f[15] = 1 / P[P_M_UF] * sumY_uf - x[5] * x[3]
    f[16] = x[17]
    f[17] = g - 1 / P[P_M_UF] * sumZ_uf
    f[18] = x[19]
    f[19] = 1 / P[P_I_UR] * sumL_ur
    f[20] = 1 / P[P_M_UR] * sumY_ur - x[5] * x[3]
    f[21] = x[22]
    f[22] = g - 1 / P[P_M_UR] * sumZ_ur

    if u1 > 0:
        T_B = 0.0
        T_E = m * R_w * u1
    else:
        T_B = m * R_w * u1
        T_E = 0.0
    I_y_w = P[P_I_Y_W]
    T_sb = P[P_T_SB]
    T_se = P[P_T_SE]
    f[23] = 1 / I_y_w * (-R_w * F_x_LF + 0.5 * T_sb * T_B + 0.5 * T_se * T_E)
    f[24] = 1 / I_y_w * (-R_w * F_x_RF + 0.5 * T_sb * T_B + 0.5 * T_se * T_E)
    f[25] = 1 / I_y_w * (-R_w * F_x_LR + 0.5 * (1 - T_sb) * T_B + 0.5 * (1 - T_se) * T_E)
    f[26] = 1 / I_y_w * (-R_w * F_x_RR + 0.5 * (1 - T_sb) * T_B + 0.5 * (1 - T_se) * T_E)
    for i in range(23, 27):
        if x[i] < 0.0:
            f[i] = 0.0
    f[27] = dot_delta_y_f
    f[28] = dot_delta_y_r
    return f
