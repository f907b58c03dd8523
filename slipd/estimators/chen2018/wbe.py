"""WBE, the wheel-speed coupling estimator of Chen et al. 2018 (Sec. 2.3), xi = [vx, vy, r].

eq. 14-15 Y = H xi + V with the four wheel speeds. slipd's channels are linear wheel speeds
        omega r_w, so Y = r_w n and H is the paper's H times r_w (rows
        [cos d, sin d, -b_f cos d + l_f sin d], [cos d, sin d, b_f cos d + l_f sin d],
        [1, 0, -b_r], [1, 0, b_r] for FL, FR, RL, RR with b = half track; ISO 8855, left wheels
        at y = +b: eq. 14 prints the opposite sign)
eq. 24-25 ridge (Tikhonov) estimate with forgetting factor rho, recursively:
        M_k = rho M_{k-1} + H_k' H_k + (1 - rho) k1 I,  g_k = rho g_{k-1} + H_k' Y_k,
        xi_k = M_k^-1 g_k. Started from M_0 = k1 I this is exactly the minimiser of
        sum_j rho^(k-j) |Y_j - H_j xi|^2 + k1 |xi|^2, i.e. eq. 24 with exponential weighting;
        the (1 - rho) k1 I term keeps the eigenvalue increment k1 of eq. 24 in the information
        matrix for ever (the paper's eq. 25 is garbled in print; this is the regularised RLS
        of Gunnarsson 1996 it describes). P_k = M_k^-1 (eq. 25).

slipd (``wbe_speed_shift``, default 1; 0 is the paper): before each tick's rows, the rows seen so
far are advanced by the change of the rear axle's speed since the last tick, d = [v_r,k -
v_r,k-1, 0, 0] with v_r the mean of the rear wheels' speeds (their rows are [1, 0, -+b_r]: the
mean is vx itself), by ``wbe_shift``: in information form g += D d with D = M - k1 I, so the
ridge stays centred on 0 (no shift across a tick without both rear wheels). The paper's xi is
constant over the memory, which a braking or accelerating car is not: vx lags (below) and the
front rows, whose only other unknown is sin d vy, turn that lag into vy. The shift is the
wheels' own difference: no IMU offset enters (moving xi with the accelerometers instead, vx' =
ax + r vy and vy' = ay - r vx, imported their offsets through the same front rows: measured
worse on the simulator's seed 1).

Error covariance for the fusion: s^2 M^-1 / (1 + rho) with s^2 the exponentially weighted mean
squared residual (the variance of an exponentially weighted mean). As in the paper, xi is
modelled constant over the memory of rho / (1 - rho) ticks: under a steady acceleration a the
WBE's vx lags by a rho / (1 - rho) dt (2.5 m/s at 5 m/s^2 with rho = 0.98) unless the
speed shift is on; the ridge shrinks
vx by about k1 (1 - rho) / 4 and beta toward 0 where the steer angle gives vy little weight.
"""

from __future__ import annotations

import math

from slipd.channels import Veh
from slipd.estimators.chen2018.state import WBE_G, WBE_M, S
from slipd.numba_cache import nb


@nb.njit(cache=True, _nrt=False)
def _wbe_row(state, h0, h1, h2, y):
    """Accumulate one row of eq. 15 into M += h h', g += h y."""
    state[WBE_M] += h0 * h0
    state[WBE_M + 1] += h0 * h1
    state[WBE_M + 2] += h0 * h2
    state[WBE_M + 3] += h1 * h1
    state[WBE_M + 4] += h1 * h2
    state[WBE_M + 5] += h2 * h2
    state[WBE_G] += h0 * y
    state[WBE_G + 1] += h1 * y
    state[WBE_G + 2] += h2 * y


@nb.njit(cache=True, _nrt=False)
def _residual(h0, h1, h2, y, x0, x1, x2):
    e = y - (h0 * x0 + h1 * x1 + h2 * x2)
    return e * e


@nb.njit(cache=True, _nrt=False)
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


@nb.njit(cache=True, _nrt=False)
def wbe_shift(state, d_vx, ridge):
    """Advance the rows seen so far by a known change ``d_vx`` of vx since the last tick:
    g += D [d_vx, 0, 0]' with D = M - k1 I the data part of M, so that M^-1 g is the minimiser
    of eq. 24 with every past row's vx advanced by d_vx (the data's least-squares fit moves by
    exactly that; the ridge k1 I stays centred on 0)."""
    state[WBE_G] += (state[WBE_M] - ridge) * d_vx
    state[WBE_G + 1] += state[WBE_M + 1] * d_vx
    state[WBE_G + 2] += state[WBE_M + 2] * d_vx


@nb.njit(cache=True, _nrt=False)
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
    for i in range(WBE_M, WBE_G + 2 + 1):
        state[i] *= rho
    leak = (1.0 - rho) * ridge
    state[WBE_M] += leak
    state[WBE_M + 3] += leak
    state[WBE_M + 5] += leak
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
        state[WBE_M], state[WBE_M + 1], state[WBE_M + 2],
        state[WBE_M + 3], state[WBE_M + 4], state[WBE_M + 5],
    )  # fmt: skip
    g0 = state[WBE_G]
    g1 = state[WBE_G + 1]
    g2 = state[WBE_G + 2]
    state[S.WBE_VX] = i00 * g0 + i01 * g1 + i02 * g2
    state[S.WBE_VY] = i01 * g0 + i11 * g1 + i12 * g2
    state[S.WBE_R] = i02 * g0 + i12 * g1 + i22 * g2
    return n_rows

