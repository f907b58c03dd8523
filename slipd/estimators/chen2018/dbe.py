"""DBE, the dynamics-based estimator of Chen et al. 2018 (Sec. 2.2): an EKF on x_v = [vx, vy, r]
(eq. 8).

eq. 4   3-DOF model, four wheels, forces rotated by the steer angle at the front
eq. 5   lateral tyre force, magic formula (``common.tyres.magic_formula``),
        D = mu Fz; B, C, E and mu from the vehicle profile (TYRE_B/C/E, MU_NOMINAL)
eq. 6   vertical loads with longitudinal and lateral load transfer from the measured ax, ay
eq. 7   wheel slip angles
eq. 9   prediction by the second-order Taylor step x + f T + A f T^2 / 2 (the paper prints
        "f T + f T^2 / 2", dimensionally a typo for the Jacobian term), eq. 10 P = phi P phi' + Q
        with phi = I + A T (Q per second: ``q_*_dbe``)
eq. 11-13 update with y_v = [ax, ay] (the paper's measurements), here plus the wheel-based vx
        (slipd: without it nothing observes vx and it drifts with the force errors). The
        measurements are processed one scalar at a time with innovations corrected for the
        earlier ones (exactly the batch update of eq. 11-13 with a diagonal R).

The longitudinal tyre forces come from the wheel torques, Fx = (T_drive - T_brake -
J_w dw/dt) / r_w (the paper uses the force observer of its ref. [4]); without torque frames
the total m ax is shared equally (``pseudo_fusion.longitudinal_forces``, DEGRADED).

Signs: ISO 8855 (see ``pseudo_fusion``; eq. 6 and 7 print the half-track terms the other way).
"""

from __future__ import annotations

import math

from slipd.channels import Veh
from slipd.estimators.chen2018.state import DBE_P, DBE_VX, SCRATCH_P, S
from slipd.estimators.common.kalman import per_step, predict_covariance, scalar_update
from slipd.estimators.common.tyres import magic_formula, static_wheel_loads, wheel_loads
from slipd.numba_cache import nb

#: m/s: the wheel-centre speed below which a slip angle's denominator is clamped (the method
#: holds its filters far above it; this only guards the division)
MIN_WHEEL_SPEED = 0.1
#: share of the smaller static wheel load a lifted wheel keeps (a small, well-defined force)
MIN_LOAD_SHARE = 0.05


@nb.njit(cache=True, _nrt=False)
def vertical_loads(ax, ay, vehicle):
    """Eq. 6 (ISO 8855 signs, see ``pseudo_fusion``; ``common.tyres.wheel_loads``): (Fz_FL,
    Fz_FR, Fz_RL, Fz_RR) [N] with longitudinal transfer m ax h / (2 l) from front to rear and
    lateral transfer of each axle m ay h l_other / (l track), off the left wheels when ay > 0.
    Loads are floored at MIN_LOAD_SHARE of the smaller static wheel load (a lifted wheel keeps
    a well-defined, small force)."""
    static_f, static_r = static_wheel_loads(vehicle)
    floor = MIN_LOAD_SHARE * min(static_f, static_r)
    return wheel_loads(ax, ay, vehicle, floor, floor)


@nb.njit(cache=True, _nrt=False)
def _wheel_force(vx, vy, r, x_pos, y_pos, steer, fz, vehicle):
    """Lateral force of one wheel at (x_pos, y_pos) (eq. 5, 7) and its gradient wrt (vx, vy, r)."""
    num = vy + x_pos * r  # lateral velocity of the wheel centre
    den = vx - y_pos * r  # longitudinal velocity of the wheel centre
    if den < MIN_WHEEL_SPEED:
        den = MIN_WHEEL_SPEED
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


@nb.njit(cache=True, _nrt=False)
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


@nb.njit(cache=True, _nrt=False)
def dbe_predict(state, steer, fx, fz, vehicle, q_vx, q_vy, q_r, dt):
    """Eq. 9-10: x^- = x + f T + A f T^2 / 2, P^- = phi P phi' + Q, phi = I + A T.

    ``fx``, ``fz``: 4-tuples of longitudinal forces and vertical loads (FL, FR, RL, RR); the
    q's are per second.
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
    phi = (1.0 + a00 * dt, a01 * dt, a02 * dt,
           a10 * dt, 1.0 + a11 * dt, a12 * dt,
           a20 * dt, a21 * dt, 1.0 + a22 * dt)  # fmt: skip
    predict_covariance(state, DBE_P, SCRATCH_P, phi,
                       (per_step(q_vx, dt, 1.0), per_step(q_vy, dt, 1.0), per_step(q_r, dt, 1.0)))


@nb.njit(cache=True, _nrt=False)
def dbe_update(state, steer, fx, fz, vehicle, ax, ax_ok, r_ax, ay, ay_ok, r_ay, vx_meas, vx_ok,
               r_vx):  # fmt: skip
    """Eq. 11-13 with y = [ax, ay, vx_wheels], h linearised at the prior; the scalar updates
    use innovations y_j - h_j(x^-) - H_j (x - x^-) so that the result is the batch update."""
    vx = state[S.DBE_VX]
    vy = state[S.DBE_VY]
    r = state[S.DBE_R]
    m = three_dof(vx, vy, r, steer, fx[0], fx[1], fx[2], fx[3], fz[0], fz[1], fz[2], fz[3],
                  vehicle)  # fmt: skip
    if ax_ok:
        scalar_update(state, DBE_VX, DBE_P, SCRATCH_P, (m[14], m[15], m[16]), ax - m[3], r_ax)
    if ay_ok:
        h0, h1, h2 = m[17], m[18], m[19]
        moved = h0 * (state[DBE_VX] - vx) + h1 * (state[DBE_VX + 1] - vy) \
            + h2 * (state[DBE_VX + 2] - r)
        scalar_update(state, DBE_VX, DBE_P, SCRATCH_P, (h0, h1, h2), ay - m[4] - moved, r_ay)
    if vx_ok:
        scalar_update(state, DBE_VX, DBE_P, SCRATCH_P, (1.0, 0.0, 0.0), vx_meas - state[DBE_VX],
                      r_vx)  # fmt: skip
