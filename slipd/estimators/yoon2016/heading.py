"""The heading EKF of Yoon, Li, Ahn 2016 [psi, phi] (eq. 5-7, Sec. 2.2) with its magnetometer
model, and the magnetometer calibration slipd learns on the road (not in the paper).

- ``magnetometer_model``: the measurement model of eq. 5 and its Jacobian; the heading EKF's
  time update (``heading_predict``, eq. 7) and its three-axis update behind the Mahalanobis
  gate of Sec. 2.2 (``heading_update``, eq. 4, ``common.kalman.gated_update``);
- ``calibration_update``: the online calibration (below);
- ``field_norm_error``: how far a sample's field is from the earth's (disturbance detection).

Axes. The paper's G-frame is X north, Y west, Z up with the yaw psi_paper measured from north
toward west. slipd uses an east-north-up earth frame (x east, y north, z up: an ISO 8855
earth-fixed system) with the heading psi measured from east, counter-clockwise seen from above,
so psi = psi_paper + pi/2, V_E = -V_W. Body axes are ISO 8855 (x forward, y left, z up, roll
positive right side down); the paper's eq. 10 has exactly this roll sign (its third row
v_z = sin(phi) sin(psi) V_N ...). The magnetic field is in uT.

Magnetometer model (eq. 5; the paper's eq. 6 sets the pitch to 0, slipd feeds the pitch
estimated by the sideslip KF's bx state, see ``gnss_magnetometer``). The paper
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

from slipd.estimators.common.kalman import gated_update, scalar_update
from slipd.numba_cache import nb

#: |det| below which the horizontal calibration map is singular (no heading from it)
MIN_CALIBRATION_DET = 1e-9


@nb.njit(cache=True, _nrt=False)
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


@nb.njit(cache=True, _nrt=False)
def heading_from_magnetometer(cal, c0, m_x, m_y):
    """Heading (rad, from east, CCW) of a level body from the horizontal magnetometer axes.

    Inverts m_xy = C[0:2, 0:2] [cos psi, sin psi]' + C[0:2, 2]. NaN if the map is singular.
    """
    a11 = cal[c0]
    a12 = cal[c0 + 1]
    a21 = cal[c0 + 3]
    a22 = cal[c0 + 4]
    det = a11 * a22 - a12 * a21
    if abs(det) < MIN_CALIBRATION_DET:
        return math.nan
    ex = m_x - cal[c0 + 2]
    ey = m_y - cal[c0 + 5]
    cos_psi = (a22 * ex - a12 * ey) / det
    sin_psi = (-a21 * ex + a11 * ey) / det
    return math.atan2(sin_psi, cos_psi)


@nb.njit(cache=True, inline="always")
def wrap_angle(angle):
    """``angle`` wrapped into [-pi, pi) (inlined: the tests call it on arrays, which needs
    numba's runtime, see slipd.numba_cache)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


@nb.njit(cache=True, _nrt=False)
def heading_predict(state, i_psi, i_p, yaw_rate, roll_rate, q_psi, q_phi, dt):
    """Time update of eq. 7 (F = I): psi += (r_m - b_r) dt, phi += (p_m - b_p) dt, P += Q.

    ``state[i_psi]``, ``state[i_psi + 1]`` are psi and phi, ``state[i_p:i_p + 3]`` P (p11, p12,
    p22). The rates come in with their biases already removed.
    """
    state[i_psi] = wrap_angle(state[i_psi] + yaw_rate * dt)
    state[i_psi + 1] = state[i_psi + 1] + roll_rate * dt
    state[i_p] += q_psi
    state[i_p + 2] += q_phi


@nb.njit(cache=True, _nrt=False)
def heading_update(state, i_psi, i_p, cal, c0, m_x, m_y, m_z, pitch, r_mag, inclination, gate):
    """Measurement update of the heading EKF with the three magnetometer axes (eq. 2, 6).

    Mahalanobis distance of the innovation (eq. 4) with S = H P H' + R the innovation covariance
    the filter provides; when d^2 exceeds ``gate`` (a chi-square quantile with 3 degrees of
    freedom) H is replaced by zero (Sec. 2.2), i.e. the update is skipped. Returns d^2 (the
    caller counts rejections); the state is updated only when d^2 <= gate.
    """
    mx, my, mz, h1_psi, h2_psi, h3_psi, h2_phi, h3_phi = magnetometer_model(
        cal, c0, state[i_psi], state[i_psi + 1], pitch, inclination
    )
    # innovation y~ = y - h(x); H rows (d/dpsi, d/dphi), dm_x/dphi = 0 (roll turns about x)
    d2 = gated_update(state, i_psi, i_p, (h1_psi, 0.0, h2_psi, h2_phi, h3_psi, h3_phi),
                      (m_x - mx, m_y - my, m_z - mz), r_mag, gate)  # fmt: skip
    if d2 <= gate:
        state[i_psi] = wrap_angle(state[i_psi])
    return d2


@nb.njit(cache=True, _nrt=False)
def heading_roll_update(state, i_psi, i_p, scratch, roll_measured, r_roll):
    """Scalar update of the heading EKF with a roll pseudo-measurement (H = [0, 1]; slipd).

    K = P H' / (H P H' + r); x += K (phi_meas - phi); P = P - K H P.
    """
    scalar_update(state, i_psi, i_p, scratch, (0.0, 1.0), roll_measured - state[i_psi + 1],
                  r_roll)  # fmt: skip
    state[i_psi] = wrap_angle(state[i_psi])


@nb.njit(cache=True, _nrt=False)
def heading_course_correction(state, i_psi, i_p, innovation, r_course):
    """The GNSS course of a straight as a heading measurement (H = [1, 0]; slipd,
    ``gnss_magnetometer``'s docstring): x += K (course - psi) with K = P H' / (H P H' + r),
    P left as it is. Returns the changes of psi and phi.

    P is not reduced because the course's error is not white: it is the straight's own
    sideslip (a cross slope, a crosswind), shared by every sample of that straight, so ten
    samples a second are not ten independent measurements. Taken as independent (the full
    update P -= K H P) they made the filter sure of its heading to a tenth of a degree, the
    magnetometer lost its weight and in the next corner the heading ran off with the gyro's
    unlearnt offset (step_steer 0.36 -> 0.94 deg beta RMS, loaded_vehicle 0.66 -> 1.34)."""
    p_psi = state[i_p]
    gain_psi = p_psi / (p_psi + r_course)
    gain_phi = state[i_p + 1] / (p_psi + r_course)
    d_psi = gain_psi * innovation
    phi = state[i_psi + 1]
    state[i_psi] = wrap_angle(state[i_psi] + d_psi)
    state[i_psi + 1] = phi + gain_phi * innovation
    return d_psi, state[i_psi + 1] - phi  # the change applied, to the last bit


# ---------------------------------------------------------------------------------------------
# magnetometer calibration (slipd; the paper assumes a calibrated magnetometer, Sec. 3.1)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True, _nrt=False)
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


@nb.njit(cache=True, _nrt=False)
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


@nb.njit(cache=True, _nrt=False)
def field_norm_error(state, c0, m_x, m_y, m_z, phi, pitch, inclination):
    """How far the measured field is from the earth field, uT: the larger of the errors of its
    horizontal norm and of its vertical component, both in the level frame.

    The sample minus the hard iron (C[0,2], C[1,2], C[2,2] - b_lz) is turned back to level by
    Ry(pitch) Rx(phi) and compared with B_h and b_lz (``magnetometer_model``). A disturbance
    changes the norm (Sec. 2.2's basis of detection); its horizontal and vertical parts are
    checked apart because the vertical field (~44 uT) would hide a horizontal disturbance in
    the total norm. A heading error changes neither. ``state[c0:c0 + 9]``: the calibration.
    """
    horizontal = math.sqrt(abs(state[c0] * state[c0 + 4] - state[c0 + 1] * state[c0 + 3]))
    b_lz = -horizontal * math.tan(inclination)
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

