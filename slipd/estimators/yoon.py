"""Shared kernels of ``gnss_magnetometer`` (Yoon, Li, Ahn 2016): the three filters' algebra.

J.-H. Yoon, S. Eben Li, C. Ahn, "Estimation of vehicle sideslip angle and tire-road friction
coefficient based on magnetometer with GPS", Int. J. Automotive Technology 17(3), 2016
(shared/papers/yoon2016-magnetometer-gps-sideslip-friction.txt).

Everything here is a scalar ``@numba.njit(cache=True)`` kernel that reads and writes slots of the
caller's float64 state vector, so nothing is allocated per tick:

- the heading EKF [psi, phi] (eq. 5-7): magnetometer measurement model and its Jacobian
  (``magnetometer_model``), predict (eq. 7) and the three-axis update with the Mahalanobis gate
  of Sec. 2.2 (``heading_update``, eq. 4);
- the sideslip KF [vx, bx, vy, by] (eq. 9, 11): predict and the two-measurement update, on a
  4x4 covariance stored row-major in 16 slots (``kf4_predict``, ``kf4_update_velocity``);
- the brush tyre (eq. 15) and the lateral-acceleration model of the friction EKF (eq. 13, 14, 16)
  with its derivative in mu (``brush_force``, ``lateral_acceleration_model``);
- the online magnetometer calibration (``calibration_update``, not in the paper, see below).

Axes. The paper's G-frame is X north, Y west, Z up with the yaw psi_paper measured from north
toward west. slipd uses an east-north-up earth frame (x east, y north, z up: an ISO 8855
earth-fixed system) with the heading psi measured from east, counter-clockwise seen from above,
so psi = psi_paper + pi/2, V_E = -V_W. Body axes are ISO 8855 (x forward, y left, z up, roll
positive right side down); the paper's eq. 10 has exactly this roll sign (its third row
v_z = sin(phi) sin(psi) V_N ...). The magnetic field is in uT.

Magnetometer model (eq. 5; the paper's eq. 6 sets the pitch to 0, slipd feeds the pitch
estimated by the sideslip KF's bx state, see gnss_magnetometer). The paper
writes the body field as the rotation of a known earth field plus offsets "determined by
calibration" (Sec. 3.1). slipd learns that calibration on the road: with roll 0 the level body
field is linear in (cos psi, sin psi, 1) for any hard-iron offset, soft-iron matrix,
declination and field strength, m_level = C [cos psi, sin psi, 1]' (C 3x3). Roll rotates the
body about x and pitch about y (eq. 5): the level field l = (b_lx, b_ly, b_lz), b_lx =
C[0,0] cos psi + C[0,1] sin psi, b_ly = C[1,0] cos psi + C[1,1] sin psi, becomes
Rx(phi)' Ry(theta)' l, added to the offsets (C[0,2], C[1,2], C[2,2] - b_lz)
(``magnetometer_model``); b_lz = -B_h tan(inclination), B_h = sqrt(|det C[0:2, 0:2]|) (the
learned horizontal field). The roll and pitch terms treat the soft-iron matrix as the
identity (a 3 % soft-iron error changes them by 3 %); the hard-iron offset along z and the
vertical field cannot be told apart on level ground, hence the inclination parameter.
"""

from __future__ import annotations

import math

import numba as nb

# ---------------------------------------------------------------------------------------------
# heading EKF (eq. 5-7, Sec. 2.2)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def magnetometer_model(cal, c0, psi, phi, pitch, inclination):
    """Predicted magnetometer reading (uT) at heading ``psi``, roll ``phi`` and pitch ``pitch``
    (eq. 5; the pitch is an input, not a state) and its Jacobian in (psi, phi).

    ``cal[c0 + 3 i + j]`` is the calibration C (row i = body axis, columns cos, sin, 1); see the
    module docstring. The level field l = (C[0,0:2] . (c, s), C[1,0:2] . (c, s), b_lz) is
    turned by the pitch and roll of eq. 5: body = Rx(phi)' Ry(pitch)' l, added to the offsets
    (C[0,2], C[1,2], C[2,2] - b_lz) and the z row's soft-iron terms C[2,0:2] . (c, s).
    Returns (m_x, m_y, m_z, dm_x/dpsi, dm_y/dpsi, dm_z/dpsi, dm_y/dphi, dm_z/dphi); dm_x/dphi
    is 0 (roll turns about x).
    """
    c = math.cos(psi)
    s = math.sin(psi)
    cos_phi = math.cos(phi)
    sin_phi = math.sin(phi)
    cos_theta = math.cos(pitch)
    sin_theta = math.sin(pitch)
    horizontal = math.sqrt(abs(cal[c0] * cal[c0 + 4] - cal[c0 + 1] * cal[c0 + 3]))
    b_lz = -horizontal * math.tan(inclination)  # vertical field, up positive (points down)
    b_lx = cal[c0] * c + cal[c0 + 1] * s
    b_ly = cal[c0 + 3] * c + cal[c0 + 4] * s
    d_b_lx = -cal[c0] * s + cal[c0 + 1] * c
    d_b_ly = -cal[c0 + 3] * s + cal[c0 + 4] * c
    # Ry(pitch)'
    px = cos_theta * b_lx - sin_theta * b_lz
    py = b_ly
    pz = sin_theta * b_lx + cos_theta * b_lz
    d_px = cos_theta * d_b_lx
    d_pz = sin_theta * d_b_lx
    # Rx(phi)'
    m_x = cal[c0 + 2] + px
    m_y = cal[c0 + 5] + cos_phi * py + sin_phi * pz
    m_z = (cal[c0 + 8] - b_lz) + (-sin_phi * py + cos_phi * pz) + cal[c0 + 6] * c + cal[c0 + 7] * s
    dmx_dpsi = d_px
    dmy_dpsi = cos_phi * d_b_ly + sin_phi * d_pz
    dmz_dpsi = -sin_phi * d_b_ly + cos_phi * d_pz - cal[c0 + 6] * s + cal[c0 + 7] * c
    dmy_dphi = -sin_phi * py + cos_phi * pz
    dmz_dphi = -cos_phi * py - sin_phi * pz
    return m_x, m_y, m_z, dmx_dpsi, dmy_dpsi, dmz_dpsi, dmy_dphi, dmz_dphi


@nb.njit(cache=True)
def heading_from_magnetometer(cal, c0, m_x, m_y):
    """Heading (rad, from east, CCW) of a level body from the horizontal magnetometer axes.

    Inverts m_xy = C[0:2, 0:2] [cos psi, sin psi]' + C[0:2, 2]. NaN if the map is singular.
    """
    a11 = cal[c0]
    a12 = cal[c0 + 1]
    a21 = cal[c0 + 3]
    a22 = cal[c0 + 4]
    det = a11 * a22 - a12 * a21
    if abs(det) < 1e-9:
        return math.nan
    ex = m_x - cal[c0 + 2]
    ey = m_y - cal[c0 + 5]
    cos_psi = (a22 * ex - a12 * ey) / det
    sin_psi = (-a21 * ex + a11 * ey) / det
    return math.atan2(sin_psi, cos_psi)


@nb.njit(cache=True)
def wrap_angle(angle):
    """``angle`` wrapped into [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


@nb.njit(cache=True)
def heading_predict(state, i_psi, i_p, yaw_rate, roll_rate, q_psi, q_phi, dt):
    """Time update of eq. 7 (F = I): psi += (r_m - b_r) dt, phi += (p_m - b_p) dt, P += Q.

    ``state[i_psi]``, ``state[i_psi + 1]`` are psi and phi, ``state[i_p:i_p + 3]`` P (p11, p12,
    p22). The rates come in with their biases already removed.
    """
    state[i_psi] = wrap_angle(state[i_psi] + yaw_rate * dt)
    state[i_psi + 1] = state[i_psi + 1] + roll_rate * dt
    state[i_p] += q_psi
    state[i_p + 2] += q_phi


@nb.njit(cache=True)
def heading_update(state, i_psi, i_p, cal, c0, m_x, m_y, m_z, pitch, r_mag, inclination, gate):
    """Measurement update of the heading EKF with the three magnetometer axes (eq. 2, 6).

    Mahalanobis distance of the innovation (eq. 4) with S = H P H' + R the innovation covariance
    the filter provides; when d^2 exceeds ``gate`` (a chi-square quantile with 3 degrees of
    freedom) H is replaced by zero (Sec. 2.2), i.e. the update is skipped. Returns d^2 (the
    caller counts rejections); the state is updated only when d^2 <= gate.
    """
    psi = state[i_psi]
    phi = state[i_psi + 1]
    p11 = state[i_p]
    p12 = state[i_p + 1]
    p22 = state[i_p + 2]
    mx, my, mz, h1_psi, h2_psi, h3_psi, h2_phi, h3_phi = magnetometer_model(
        cal, c0, psi, phi, pitch, inclination
    )
    h1_phi = 0.0
    # innovation  y~ = y - h(x)
    nu1 = m_x - mx
    nu2 = m_y - my
    nu3 = m_z - mz
    # P H' (2 x 3): b_a_i = sum_b P_ab H_ib
    b11 = p11 * h1_psi + p12 * h1_phi
    b12 = p11 * h2_psi + p12 * h2_phi
    b13 = p11 * h3_psi + p12 * h3_phi
    b21 = p12 * h1_psi + p22 * h1_phi
    b22 = p12 * h2_psi + p22 * h2_phi
    b23 = p12 * h3_psi + p22 * h3_phi
    # S = H P H' + R (symmetric 3 x 3)
    s11 = h1_psi * b11 + h1_phi * b21 + r_mag
    s12 = h1_psi * b12 + h1_phi * b22
    s13 = h1_psi * b13 + h1_phi * b23
    s22 = h2_psi * b12 + h2_phi * b22 + r_mag
    s23 = h2_psi * b13 + h2_phi * b23
    s33 = h3_psi * b13 + h3_phi * b23 + r_mag
    # S^-1 by cofactors
    c11 = s22 * s33 - s23 * s23
    c12 = s13 * s23 - s12 * s33
    c13 = s12 * s23 - s13 * s22
    c22 = s11 * s33 - s13 * s13
    c23 = s12 * s13 - s11 * s23
    c33 = s11 * s22 - s12 * s12
    det = s11 * c11 + s12 * c12 + s13 * c13
    if not (det > 0.0):
        return math.inf
    i11 = c11 / det
    i12 = c12 / det
    i13 = c13 / det
    i22 = c22 / det
    i23 = c23 / det
    i33 = c33 / det
    # S^-1 y~
    w1 = i11 * nu1 + i12 * nu2 + i13 * nu3
    w2 = i12 * nu1 + i22 * nu2 + i23 * nu3
    w3 = i13 * nu1 + i23 * nu2 + i33 * nu3
    # d^2 = y~' S^-1 y~ (eq. 4)
    d2 = nu1 * w1 + nu2 * w2 + nu3 * w3
    if not (d2 <= gate):
        return d2
    # x = x + K y~ with K = P H' S^-1, so K y~ = P H' (S^-1 y~)
    state[i_psi] = wrap_angle(psi + b11 * w1 + b12 * w2 + b13 * w3)
    state[i_psi + 1] = phi + b21 * w1 + b22 * w2 + b23 * w3
    # K (2 x 3) = P H' S^-1
    k11 = b11 * i11 + b12 * i12 + b13 * i13
    k12 = b11 * i12 + b12 * i22 + b13 * i23
    k13 = b11 * i13 + b12 * i23 + b13 * i33
    k21 = b21 * i11 + b22 * i12 + b23 * i13
    k22 = b21 * i12 + b22 * i22 + b23 * i23
    k23 = b21 * i13 + b22 * i23 + b23 * i33
    # P = (I - K H) P = P - K (P H')'
    state[i_p] = p11 - (k11 * b11 + k12 * b12 + k13 * b13)
    state[i_p + 1] = p12 - (k11 * b21 + k12 * b22 + k13 * b23)
    state[i_p + 2] = p22 - (k21 * b21 + k22 * b22 + k23 * b23)
    return d2


@nb.njit(cache=True)
def heading_roll_update(state, i_psi, i_p, roll_measured, r_roll):
    """Scalar update of the heading EKF with a roll pseudo-measurement (H = [0, 1]; slipd).

    K = P H' / (H P H' + r); x += K (phi_meas - phi); P = P - K H P.
    """
    p11 = state[i_p]
    p12 = state[i_p + 1]
    p22 = state[i_p + 2]
    s = p22 + r_roll
    k1 = p12 / s
    k2 = p22 / s
    innovation = roll_measured - state[i_psi + 1]
    state[i_psi] = wrap_angle(state[i_psi] + k1 * innovation)
    state[i_psi + 1] += k2 * innovation
    state[i_p] = p11 - k1 * p12
    state[i_p + 1] = p12 - k1 * p22
    state[i_p + 2] = p22 - k2 * p22


# ---------------------------------------------------------------------------------------------
# sideslip KF (eq. 8-11): x = [vx, bx, vy, by], P row-major in 16 slots
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def kf4_predict(state, ix, ip, scratch, ax, ay_no_gravity, yaw_rate, q_v, q_b, dt):
    """Time update of eq. 9 by forward Euler: x += (A x + B u) dt, P = F P F' + Q, F = I + A dt.

    A = [[0, -1, r, 0], [0, 0, 0, 0], [-r, 0, 0, -1], [0, 0, 0, 0]] (r = yaw rate without bias),
    u = [a_x,m, a_y,m - g sin(phi)]. Q = diag(q_v, q_b, q_v, q_b) per tick. ``state[ix:ix+4]``
    is x, ``state[ip:ip+16]`` P row-major, ``state[scratch:scratch+16]`` working memory.
    """
    vx = state[ix]
    bx = state[ix + 1]
    vy = state[ix + 2]
    by = state[ix + 3]
    state[ix] = vx + (-bx + yaw_rate * vy + ax) * dt
    state[ix + 2] = vy + (-yaw_rate * vx - by + ay_no_gravity) * dt
    rd = yaw_rate * dt
    # F P: row 0 = P0 - dt P1 + rd P2, row 1 = P1, row 2 = -rd P0 + P2 - dt P3, row 3 = P3
    for j in range(4):
        p0 = state[ip + j]
        p1 = state[ip + 4 + j]
        p2 = state[ip + 8 + j]
        p3 = state[ip + 12 + j]
        state[scratch + j] = p0 - dt * p1 + rd * p2
        state[scratch + 4 + j] = p1
        state[scratch + 8 + j] = -rd * p0 + p2 - dt * p3
        state[scratch + 12 + j] = p3
    # (F P) F': column j of F' is row j of F
    for i in range(4):
        a0 = state[scratch + 4 * i]
        a1 = state[scratch + 4 * i + 1]
        a2 = state[scratch + 4 * i + 2]
        a3 = state[scratch + 4 * i + 3]
        state[ip + 4 * i] = a0 - dt * a1 + rd * a2
        state[ip + 4 * i + 1] = a1
        state[ip + 4 * i + 2] = -rd * a0 + a2 - dt * a3
        state[ip + 4 * i + 3] = a3
    state[ip] += q_v
    state[ip + 5] += q_b
    state[ip + 10] += q_v
    state[ip + 15] += q_b


@nb.njit(cache=True)
def kf4_update_velocity(state, ix, ip, scratch, vx_meas, vy_meas, r_vx, r_vy):
    """Measurement update with y = [vx_GPS, vy_GPS] and H = [[1, 0, 0, 0], [0, 0, 1, 0]] (eq. 11).

    S = H P H' + R is 2 x 2; K = P H' S^-1 (4 x 2); P = P - K (H P) (= (I - K H) P, eq. 2).
    ``state[scratch:scratch + 8]`` holds the columns 0 and 2 of the prior P while P is rewritten.
    """
    # S = [[P00 + r_vx, P02], [P20, P22 + r_vy]]
    s11 = state[ip] + r_vx
    s12 = state[ip + 2]
    s22 = state[ip + 10] + r_vy
    det = s11 * s22 - s12 * s12
    if not (det > 0.0):
        return
    i11 = s22 / det
    i12 = -s12 / det
    i22 = s11 / det
    # P H' = columns 0 and 2 of P (= rows 0 and 2 of H P by symmetry), kept before P changes
    for i in range(4):
        state[scratch + 2 * i] = state[ip + 4 * i]
        state[scratch + 2 * i + 1] = state[ip + 4 * i + 2]
    nu1 = vx_meas - state[ix]
    nu2 = vy_meas - state[ix + 2]
    w1 = i11 * nu1 + i12 * nu2
    w2 = i12 * nu1 + i22 * nu2
    for i in range(4):
        g0 = state[scratch + 2 * i]
        g2 = state[scratch + 2 * i + 1]
        # x = x + K y~ = x + P H' (S^-1 y~)
        state[ix + i] += g0 * w1 + g2 * w2
        # K row i = (P H')_i S^-1
        k0 = g0 * i11 + g2 * i12
        k2 = g0 * i12 + g2 * i22
        for j in range(4):
            state[ip + 4 * i + j] -= k0 * state[scratch + 2 * j] + k2 * state[scratch + 2 * j + 1]


# ---------------------------------------------------------------------------------------------
# friction EKF (eq. 13-16)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def brush_force(alpha, mu, fz, tyre_stiffness):
    """Lateral force of one tyre by the brush model (eq. 15) and its derivative in mu.

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


@nb.njit(cache=True)
def lateral_acceleration_model(
    mu, beta, yaw_rate, vx, steer, mass, lf, lr, stiffness_f, stiffness_r
):
    """h(mu) of eq. 16: a_y = (2 f_yf cos(delta) + 2 f_yr) / m (eq. 13) and dh/dmu.

    Slip angles of eq. 14 (ISO 8855, the paper's): alpha_f = delta - (beta + a r / vx),
    alpha_r = -(beta - b r / vx). Static tyre loads Fz = m g b / (2 l) front, m g a / (2 l) rear;
    ``stiffness_f``, ``stiffness_r`` are axle cornering stiffnesses (two tyres each).
    """
    wheelbase = lf + lr
    weight = mass * 9.81
    fz_front = 0.5 * weight * lr / wheelbase
    fz_rear = 0.5 * weight * lf / wheelbase
    alpha_f = steer - (beta + lf * yaw_rate / vx)
    alpha_r = -(beta - lr * yaw_rate / vx)
    force_f, dforce_f = brush_force(alpha_f, mu, fz_front, 0.5 * stiffness_f)
    force_r, dforce_r = brush_force(alpha_r, mu, fz_rear, 0.5 * stiffness_r)
    cos_steer = math.cos(steer)
    ay = (2.0 * force_f * cos_steer + 2.0 * force_r) / mass
    day_dmu = (2.0 * dforce_f * cos_steer + 2.0 * dforce_r) / mass
    return ay, day_dmu


# ---------------------------------------------------------------------------------------------
# magnetometer calibration (slipd; the paper assumes a calibrated magnetometer, Sec. 3.1)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def calibration_residual(state, c0, pc0, psi_ref, m_x, m_y, m_z, r_sample):
    """Normalised squared residual of a calibration sample against the current fit:
    sum_i (m_i - C_i z)^2 / (z' Pc z + r_sample), chi-square with 3 dof for a good sample."""
    z0 = math.cos(psi_ref)
    z1 = math.sin(psi_ref)
    spread = r_sample
    for a in range(3):
        za = z0 if a == 0 else (z1 if a == 1 else 1.0)
        for b in range(3):
            zb = z0 if b == 0 else (z1 if b == 1 else 1.0)
            spread += za * state[pc0 + 3 * a + b] * zb
    total = 0.0
    for row in range(3):
        m = m_x if row == 0 else (m_y if row == 1 else m_z)
        base = c0 + 3 * row
        error = m - (state[base] * z0 + state[base + 1] * z1 + state[base + 2])
        total += error * error
    return total / spread


@nb.njit(cache=True)
def calibration_update(state, c0, pc0, psi_ref, m_x, m_y, m_z, r_cal, q_cal):
    """One recursive-least-squares step of m_level = C [cos psi, sin psi, 1]' (all three rows
    share the regressor, hence one 3 x 3 covariance ``state[pc0:pc0 + 9]``, row-major).

    ``psi_ref`` is a heading reference (the GNSS course on a straight); ``q_cal`` is added to
    the covariance diagonal first so that the calibration can follow slow changes (a random
    walk of C), ``r_cal`` the variance of one sample (uT^2).
    """
    z0 = math.cos(psi_ref)
    z1 = math.sin(psi_ref)
    z2 = 1.0
    state[pc0] += q_cal
    state[pc0 + 4] += q_cal
    state[pc0 + 8] += q_cal
    # g = Pc z
    g0 = state[pc0] * z0 + state[pc0 + 1] * z1 + state[pc0 + 2] * z2
    g1 = state[pc0 + 3] * z0 + state[pc0 + 4] * z1 + state[pc0 + 5] * z2
    g2 = state[pc0 + 6] * z0 + state[pc0 + 7] * z1 + state[pc0 + 8] * z2
    denominator = r_cal + z0 * g0 + z1 * g1 + z2 * g2
    k0 = g0 / denominator
    k1 = g1 / denominator
    k2 = g2 / denominator
    # each row: C_i += k (m_i - C_i z)
    for row in range(3):
        m = m_x if row == 0 else (m_y if row == 1 else m_z)
        base = c0 + 3 * row
        error = m - (state[base] * z0 + state[base + 1] * z1 + state[base + 2] * z2)
        state[base] += k0 * error
        state[base + 1] += k1 * error
        state[base + 2] += k2 * error
    # Pc = Pc - k g' (symmetric: g = Pc z)
    state[pc0] -= k0 * g0
    state[pc0 + 1] -= k0 * g1
    state[pc0 + 2] -= k0 * g2
    state[pc0 + 3] -= k1 * g0
    state[pc0 + 4] -= k1 * g1
    state[pc0 + 5] -= k1 * g2
    state[pc0 + 6] -= k2 * g0
    state[pc0 + 7] -= k2 * g1
    state[pc0 + 8] -= k2 * g2
