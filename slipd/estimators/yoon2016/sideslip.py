"""The sideslip KF of Yoon, Li, Ahn 2016 (Sec. 3.3, eq. 8-11): x = [vx, bx, vy, by] with the GNSS
velocity as its measurement, and the history that fuses a delayed GNSS sample at the tick the
receiver sampled it (Sec. 2.3, Larsen et al. 1998).

eq. 9   vx' = a_x,m + r vy - bx, vy' = a_y,m - g sin(phi) - r vx - by (ISO 8855; the paper's
        eq. 8 prints a_x,m = vx' + psi' vy), biases as random walks, forward Euler;
eq. 10  the earth-frame GNSS velocity rotated into the body with heading and roll;
eq. 11  y = [vx_GPS, vy_GPS], H = [[1, 0, 0, 0], [0, 0, 1, 0]].

Delay: a sample is ``gnss_delay`` old when it arrives. The filter keeps its states,
covariances and inputs of the last ``BUFFER_TICKS`` ticks (``state.ENTRY``); a delayed sample
is fused at its own tick s and the filter is re-propagated over the stored inputs from s to
now. For a linear filter this is the exact result that Larsen's measurement extrapolation
approximates (Larsen's contribution is doing it without the re-propagation, which matters for
big filters; a 4-state filter re-propagated over 40 ticks is cheap).
"""

from __future__ import annotations

import math

from slipd.estimators.common.kalman import predict_covariance, scalar_update, tri
from slipd.estimators.yoon2016.state import (
    BUFFER_TICKS,
    ENTRY_LEN,
    HISTORY,
    KF,
    KF_LEN,
    KF_P,
    KF_P_LEN,
    SCRATCH,
    E,
    S,
)
from slipd.numba_cache import nb


@nb.njit(cache=True, _nrt=False)
def kf4_predict(state, ix, ip, scratch, ax, ay_no_gravity, yaw_rate, q_v, q_b, dt):
    """Time update of eq. 9 by forward Euler: x += (A x + B u) dt, P = F P F' + Q, F = I + A dt.

    A = [[0, -1, r, 0], [0, 0, 0, 0], [-r, 0, 0, -1], [0, 0, 0, 0]] (r = yaw rate without bias),
    u = [a_x,m, a_y,m - g sin(phi)]. Q = diag(q_v, q_b, q_v, q_b) per tick. ``state[ix:ix+4]``
    is x, ``state[ip:]`` the packed P, ``state[scratch:scratch+16]`` working memory.
    """
    vx = state[ix]
    bx = state[ix + 1]
    vy = state[ix + 2]
    by = state[ix + 3]
    state[ix] = vx + (-bx + yaw_rate * vy + ax) * dt
    state[ix + 2] = vy + (-yaw_rate * vx - by + ay_no_gravity) * dt
    rd = yaw_rate * dt
    F = (1.0, -dt, rd, 0.0,
         0.0, 1.0, 0.0, 0.0,
         -rd, 0.0, 1.0, -dt,
         0.0, 0.0, 0.0, 1.0)  # fmt: skip
    predict_covariance(state, ip, scratch, F, (q_v, q_b, q_v, q_b))


@nb.njit(cache=True, _nrt=False)
def kf4_update_velocity(state, ix, ip, scratch, vx_meas, vy_meas, r_vx, r_vy):
    """Measurement update with y = [vx_GPS, vy_GPS] and H = [[1, 0, 0, 0], [0, 0, 1, 0]] (eq. 11),
    the two (independent) components one after the other: the batch update of eq. 2."""
    scalar_update(state, ix, ip, scratch, (1.0, 0.0, 0.0, 0.0), vx_meas - state[ix], r_vx)
    scalar_update(state, ix, ip, scratch, (0.0, 0.0, 1.0, 0.0), vy_meas - state[ix + 2], r_vy)


@nb.njit(cache=True, _nrt=False)
def entry(tick):
    """Offset of the history entry of tick ``tick`` (a ring of BUFFER_TICKS)."""
    return HISTORY + (int(tick) % BUFFER_TICKS) * ENTRY_LEN


@nb.njit(cache=True, _nrt=False)
def gnss_to_body(v_north, v_east, v_up, psi, phi, yaw_rate, roll_rate, pitch_rate, antenna_x,
                 antenna_y, antenna_z):  # fmt: skip
    """Eq. 10 in east-north-up: the GNSS velocity in body axes at heading psi and roll phi,
    then the antenna lever arm rho = (antenna_x, antenna_y, antenna_z) (body axes from the CoG)
    removed (v_CoG = v_ant - omega x rho). Returns (vx, vy)."""
    c = math.cos(psi)
    s = math.sin(psi)
    vx = c * v_east + s * v_north
    vy_level = -s * v_east + c * v_north
    vy = math.cos(phi) * vy_level + math.sin(phi) * v_up
    vx -= pitch_rate * antenna_z - yaw_rate * antenna_y
    vy -= yaw_rate * antenna_x - roll_rate * antenna_z
    return vx, vy


@nb.njit(cache=True, _nrt=False)
def start_kf(state, vx, vy, p0_v, p0_b, tick):
    """(Re)start the sideslip KF at [vx, 0, vy, 0] with P0 (biases unknown, Sec. 3.3)."""
    state[S.KF_VX] = vx
    state[S.KF_BX] = 0.0
    state[S.KF_VY] = vy
    state[S.KF_BY] = 0.0
    for i in range(KF_P_LEN):
        state[KF_P + i] = 0.0
    state[KF_P + tri(0, 0, 4)] = p0_v
    state[KF_P + tri(1, 1, 4)] = p0_b
    state[KF_P + tri(2, 2, 4)] = p0_v
    state[KF_P + tri(3, 3, 4)] = p0_b
    state[S.KF_INIT] = 1.0
    state[S.KF_TICKS] = 0.0
    state[S.KF_START_TICK] = tick
    state[S.GNSS_AGE] = 0.0
    state[S.GNSS_UPDATES] = 0.0


@nb.njit(cache=True, _nrt=False)
def save_entry(state, tick, ax, ay_no_gravity, yaw_rate, roll_rate, pitch_rate):
    """Store the tick's KF posterior, attitude and inputs in the history."""
    e = entry(tick)
    state[e + E.PITCH] = state[S.PITCH]
    for i in range(KF_LEN):
        state[e + i] = state[KF + i]
    state[e + E.AX] = ax
    state[e + E.AY_NO_GRAVITY] = ay_no_gravity
    state[e + E.YAW_RATE] = yaw_rate
    state[e + E.PSI] = state[S.HEAD_PSI]
    state[e + E.PHI] = state[S.HEAD_PHI]
    state[e + E.ROLL_RATE] = roll_rate
    state[e + E.PITCH_RATE] = pitch_rate
    state[e + E.MAG_X] = state[S.LAST_MAG_X]
    state[e + E.MAG_Y] = state[S.LAST_MAG_Y]
    state[e + E.MAG_Z] = state[S.LAST_MAG_Z]


@nb.njit(cache=True, _nrt=False)
def fuse_delayed_gnss(state, tick, sample_tick, v_north, v_east, v_up, antenna_x, antenna_y,
                      antenna_z, q_v, q_b, r_gnss, dt):  # fmt: skip
    """Fuse a GNSS sample taken at ``sample_tick`` (<= ``tick``), Sec. 2.3.

    Rotates it with the attitude stored for ``sample_tick`` (eq. 10), updates the stored
    posterior of that tick (eq. 11) and re-propagates eq. 9 over the stored inputs up to
    ``tick``, rewriting the history on the way so that the next delayed sample starts from the
    corrected trajectory. ``q_v``, ``q_b``: process noise per step; ``r_gnss`` the sample's
    variance per axis.
    """
    es = entry(sample_tick)
    vx_meas, vy_meas = gnss_to_body(
        v_north, v_east, v_up, state[es + E.PSI], state[es + E.PHI], state[es + E.YAW_RATE],
        state[es + E.ROLL_RATE], state[es + E.PITCH_RATE], antenna_x, antenna_y, antenna_z,
    )  # fmt: skip
    if sample_tick == tick:
        kf4_update_velocity(state, KF, KF_P, SCRATCH, vx_meas, vy_meas, r_gnss, r_gnss)
        for i in range(KF_LEN):
            state[es + i] = state[KF + i]
        return
    # rewind to the sampling tick, update there (eq. 11), then re-run eq. 9 up to now
    for i in range(KF_LEN):
        state[KF + i] = state[es + i]
    kf4_update_velocity(state, KF, KF_P, SCRATCH, vx_meas, vy_meas, r_gnss, r_gnss)
    for i in range(KF_LEN):
        state[es + i] = state[KF + i]
    j = sample_tick
    while j < tick:
        ej = entry(j)
        kf4_predict(
            state, KF, KF_P, SCRATCH, state[ej + E.AX], state[ej + E.AY_NO_GRAVITY],
            state[ej + E.YAW_RATE], q_v, q_b, dt,
        )  # fmt: skip
        j += 1
        en = entry(j)
        for i in range(KF_LEN):
            state[en + i] = state[KF + i]

