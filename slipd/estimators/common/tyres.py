"""Tyre models and what they are evaluated on: slip angles and wheel loads.

Lateral force models, each with its slope for the filters' Jacobians:

- ``tanh_tyre``: F = peak tanh(shape alpha) (Righetti-Lenzo eq. 7, Carnier eq. 8);
- ``magic_formula``: Pacejka's D sin(C atan(B a - E (B a - atan(B a)))) (Chen eq. 5);
- ``brush_tyre``: the brush model with its friction derivative (Yoon eq. 15).

Axes ISO 8855: slip angles and lateral forces are positive to the left.
"""

from __future__ import annotations

import math

from slipd.channels import G, Veh
from slipd.numba_cache import nb


@nb.njit(cache=True, _nrt=False)
def tanh_tyre(alpha, shape, peak, stiffness):
    """Lateral force F = peak tanh(shape alpha) and its slope dF/dalpha = stiffness (1 - tanh^2).

    The cornering stiffness is shape x peak; both parameterisations of the papers are passed
    as they come, so that neither is rounded through the other: Righetti-Lenzo eq. 7
    (mu Fz tanh(C alpha / (mu Fz)): shape C / (mu Fz), peak mu Fz, stiffness C) and Carnier
    eq. 8 (C_r / k tanh(k alpha): shape k, peak C_r / k, stiffness C_r). Returns (F, dF/dalpha).
    """
    t = math.tanh(shape * alpha)
    return peak * t, stiffness * (1.0 - t * t)


@nb.njit(cache=True, _nrt=False)
def magic_formula(alpha, b_factor, c_factor, e_factor, peak):
    """Chen eq. 5: Fy = D sin(C atan(B a - E (B a - atan(B a)))) with D = ``peak``; returns
    (Fy [N], dFy/dalpha [N/rad])."""
    ba = b_factor * alpha
    phi = ba - e_factor * (ba - math.atan(ba))
    angle = c_factor * math.atan(phi)
    dphi = b_factor - e_factor * (b_factor - b_factor / (1.0 + ba * ba))
    return peak * math.sin(angle), peak * math.cos(angle) * c_factor / (1.0 + phi * phi) * dphi


@nb.njit(cache=True, _nrt=False)
def brush_tyre(alpha, mu, fz, tyre_stiffness):
    """Lateral force of one tyre by the brush model (Yoon eq. 15) and its derivative in mu.

    theta_y = 2 c_p l^2 / (3 mu Fz) with 2 c_p l^2 = C_alpha, the tyre's cornering stiffness
    (the slope of eq. 15 at alpha = 0 is 3 mu Fz theta_y = C_alpha), sigma_y = tan(alpha),
    alpha_sl = atan(1 / theta_y). Below alpha_sl:
        f = 3 mu Fz z (1 - |z| + z^2 / 3), z = theta_y sigma_y
          = k - k |k| / (3 mu Fz) + k^3 / (27 mu^2 Fz^2),  k = C_alpha tan(alpha)
    and above it f = mu Fz sgn(alpha). Returns (f [N], df/dmu [N]).
    """
    k = tyre_stiffness * math.tan(alpha)
    mu_fz = mu * fz
    if abs(k) >= 3.0 * mu_fz:  # |theta_y sigma_y| >= 1  <=>  |alpha| >= alpha_sl
        sign = 1.0 if alpha > 0.0 else -1.0
        return mu_fz * sign, fz * sign
    force = k - k * abs(k) / (3.0 * mu_fz) + k * k * k / (27.0 * mu_fz * mu_fz)
    dforce_dmu = k * abs(k) / (3.0 * mu * mu_fz) - 2.0 * k * k * k / (27.0 * mu * mu_fz * mu_fz)
    return force, dforce_dmu


@nb.njit(cache=True, _nrt=False)
def slip_angles(vx, vy, yaw_rate, steer, lf, lr):
    """Axle slip angles of the single-track model, alpha_F = delta - atan((vy + lf r) / vx),
    alpha_R = -atan((vy - lr r) / vx), and their derivatives in vy (those in r are lf and -lr
    times these). ``vx`` > 0 (callers hold their filters below a minimum speed). Returns
    (alpha_F, alpha_R, d alpha_F / d vy, d alpha_R / d vy)."""
    inv_vx = 1.0 / vx
    tan_f = (vy + lf * yaw_rate) * inv_vx
    tan_r = (vy - lr * yaw_rate) * inv_vx
    alpha_f = steer - math.atan(tan_f)
    alpha_r = -math.atan(tan_r)
    return alpha_f, alpha_r, -inv_vx / (1.0 + tan_f * tan_f), -inv_vx / (1.0 + tan_r * tan_r)


@nb.njit(cache=True, _nrt=False)
def static_wheel_loads(vehicle):
    """Static load of one front and one rear wheel, N: (m g l_r / 2l, m g l_f / 2l)."""
    m = vehicle[Veh.MASS]
    wheelbase = vehicle[Veh.LF] + vehicle[Veh.LR]
    return (0.5 * (vehicle[Veh.LR] / wheelbase) * m * G,
            0.5 * (vehicle[Veh.LF] / wheelbase) * m * G)


@nb.njit(cache=True, _nrt=False)
def wheel_loads(ax, ay, vehicle, floor_f, floor_r):
    """Vertical wheel loads with rigid-body load transfer from the CoG accelerations (Carnier
    eq. 20, Chen eq. 6): F_z = static share m g -+ m A_x h / 2l (accelerating moves load to the
    rear) -+ m A_y h / track x the axle's static share (ISO: A_y > 0, a left turn, loads the
    right wheels). Each load is at least ``floor_f`` / ``floor_r`` (N): a lifted wheel keeps a
    small, well-defined force. Returns (Fz_fl, Fz_fr, Fz_rl, Fz_rr), N."""
    m = vehicle[Veh.MASS]
    h = vehicle[Veh.H_COG]
    wheelbase = vehicle[Veh.LF] + vehicle[Veh.LR]
    share_f = vehicle[Veh.LR] / wheelbase
    share_r = vehicle[Veh.LF] / wheelbase
    static_f = 0.5 * share_f * m * G
    static_r = 0.5 * share_r * m * G
    long_f = -0.5 * h / wheelbase * m * ax
    lat_f = h / vehicle[Veh.TRACK_F] * share_f * m * ay
    lat_r = h / vehicle[Veh.TRACK_R] * share_r * m * ay
    return (
        max(static_f + long_f - lat_f, floor_f),
        max(static_f + long_f + lat_f, floor_f),
        max(static_r - long_f - lat_r, floor_r),
        max(static_r - long_f + lat_r, floor_r),
    )
