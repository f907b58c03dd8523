"""The fusion of Chen et al. 2018 (Sec. 3.2, eq. 26-39): the matrix-weighted linear minimum-
variance combination of the three estimators' (yaw rate, sideslip) x_i = (gamma_i, beta_i).

x_0 = sum W_i x_i with W = (L' P^-1 L)^-1 L' P^-1 (eq. 38), L = [I I I]', P the 6x6 error
covariance of (x_1, x_2, x_3). The fused covariance is (L' P^-1 L)^-1.
How P is obtained online (the paper does not say; slipd's choice, documented here):

* pairwise difference moments D_ij = E[(x_i - x_j)(x_i - x_j)'] are tracked with exponential
  forgetting (time constant ``fusion_time_constant``). They are observable without truth, and
  D_ij = P_ii + P_jj - P_ij - P_ji for any error statistics.
* diagonal blocks (``variance_from_differences`` = 2, default): P_11 = C_1, and
  P_jj = s_j C_j for j = 2, 3 with s_j = max(1, (D_1j[gg] - C_1[gg]) / C_j[gg]): C_i is the
  estimator's own covariance (KBE/DBE filter covariances, WBE's RLS covariance), which knows
  its model's noise but not its model error (DBE with the wrong friction, WBE's tyre radii).
  gamma_1 is the gyro, so D_1j[gg] - C_1[gg] is the observed yaw-rate error variance of
  estimator j: where it exceeds what C_j claims, the whole block is scaled (covariance
  matching on the one channel with a reference, Mehra 1972).
  Mode 1 instead takes P_ii = C_i + (T_i - C_i)+ with the three-cornered-hat variance
  T_1 = (D_12 + D_13 - D_23) / 2 (and cyclic; ()+ the positive part of the symmetric 2x2);
  it assumes uncorrelated errors and failed on the simulator (the KBE's and WBE's errors are
  correlated: both lean to beta = 0; benchmarks/MEASUREMENTS.md). Mode 0 uses C_i alone.
* cross blocks: P_ij = (P_ii + P_jj - D_ij) / 2 (symmetric part; the antisymmetric part is not
  observable from D and is taken as zero). ``cross_covariance`` = 0 sets them to zero.
* every cross element is clipped to a correlation of at most 0.9 in magnitude
  (``CROSS_CORRELATION_LIMIT``): when a filter's own covariance is too small for the
  observed differences, (P_ii + P_jj - D_ij) / 2 would claim a correlation beyond -1.
* P (``fusion_floor`` added to the gamma and beta variances) is factorised by Cholesky; if it
  is still not positive definite the cross blocks are dropped for this tick (``S.CROSS_SCALE``
  says which: 1 used, 0 dropped). On the simulator suite the own covariances (even rescaled)
  are far smaller than the observed differences, so the fusion runs with a block-diagonal P on
  nearly every tick; the cross terms work where the moments are consistent (tests: synthetic
  pseudo-sensors with correlated errors).

The weights are kept in the state (W1..W3, 4 per estimator, row-major [[gg, gb], [bg, bb]]),
so "the weight coefficient of estimator i" for beta is W_i[b, b].
"""

from __future__ import annotations

import math

from slipd.estimators.chen2018.state import (
    D12,
    D13,
    D23,
    DBE_P,
    KBE_P,
    SCRATCH_P,
    SCRATCH_Z,
    W_INDEX,
    WBE_M,
    S,
)
from slipd.estimators.chen2018.wbe import inverse_sym3
from slipd.estimators.common.kalman import beta_variance
from slipd.numba_cache import nb

#: Largest |correlation| a cross-covariance element may express (module docstring).
CROSS_CORRELATION_LIMIT = 0.9


@nb.njit(cache=True, _nrt=False)
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


@nb.njit(cache=True, _nrt=False)
def update_difference_moments(state, i0, d_gamma, d_beta, gain):
    """D = D + gain (d d' - D) for one pair (gg, gb, bb at ``i0``)."""
    state[i0] += gain * (d_gamma * d_gamma - state[i0])
    state[i0 + 1] += gain * (d_gamma * d_beta - state[i0 + 1])
    state[i0 + 2] += gain * (d_beta * d_beta - state[i0 + 2])


@nb.njit(cache=True, _nrt=False)
def _set_block(state, i, j, gg, gb, bg, bb):
    """P block (i, j) (estimators 0..2) into the 6x6 scratch, and its transpose into (j, i)."""
    base = SCRATCH_P + 12 * i + 2 * j
    state[base] = gg
    state[base + 1] = gb
    state[base + 6] = bg
    state[base + 7] = bb
    if i != j:
        base = SCRATCH_P + 12 * j + 2 * i
        state[base] = gg
        state[base + 1] = bg
        state[base + 6] = gb
        state[base + 7] = bb


@nb.njit(cache=True, _nrt=False)
def _cholesky_solve_lambda(state):
    """Z = P^-1 L for the 6x6 P in the scratch (overwritten by its Cholesky factor) and
    L = [I I I]'. Returns False when P is not positive definite."""
    # in-place Cholesky, lower triangle
    for j in range(6):
        s = state[SCRATCH_P + 7 * j]
        for k in range(j):
            s -= state[SCRATCH_P + 6 * j + k] ** 2
        if not s > 0.0:
            return False
        d = math.sqrt(s)
        state[SCRATCH_P + 7 * j] = d
        for i in range(j + 1, 6):
            s = state[SCRATCH_P + 6 * i + j]
            for k in range(j):
                s -= state[SCRATCH_P + 6 * i + k] * state[SCRATCH_P + 6 * j + k]
            state[SCRATCH_P + 6 * i + j] = s / d
    for c in range(2):
        # forward: L y = e (e = column c of the stacked identities)
        for i in range(6):
            s = 1.0 if i % 2 == c else 0.0
            for k in range(i):
                s -= state[SCRATCH_P + 6 * i + k] * state[SCRATCH_Z + 2 * k + c]
            state[SCRATCH_Z + 2 * i + c] = s / state[SCRATCH_P + 7 * i]
        # backward: L' z = y
        for i in range(5, -1, -1):
            s = state[SCRATCH_Z + 2 * i + c]
            for k in range(i + 1, 6):
                s -= state[SCRATCH_P + 6 * k + i] * state[SCRATCH_Z + 2 * k + c]
            state[SCRATCH_Z + 2 * i + c] = s / state[SCRATCH_P + 7 * i]
    return True


@nb.njit(cache=True, _nrt=False)
def _block_inverse_into_z(state, i, p):
    """Rows 2i, 2i + 1 of Z = P^-1 L for a block-diagonal P: the inverse of the symmetric
    block p = (gg, gb, bb). Returns False when the block is not positive definite."""
    det = p[0] * p[2] - p[1] * p[1]
    if not (det > 0.0 and p[0] > 0.0):
        return False
    base = SCRATCH_Z + 4 * i
    state[base] = p[2] / det
    state[base + 1] = -p[1] / det
    state[base + 2] = -p[1] / det
    state[base + 3] = p[0] / det
    return True


@nb.njit(cache=True, _nrt=False)
def _clip(value, limit):
    if value > limit:
        return limit
    if value < -limit:
        return -limit
    return value


@nb.njit(cache=True, _nrt=False)
def _clip_cross(c, pi, pj):
    """Cross block (gg, gb, bg, bb) from the symmetric (gg, gb, bb) estimate ``c``, each element
    clipped to CROSS_CORRELATION_LIMIT sqrt(var_i var_j)."""
    k = CROSS_CORRELATION_LIMIT
    gg = _clip(c[0], k * math.sqrt(pi[0] * pj[0]))
    gb = _clip(c[1], k * math.sqrt(pi[0] * pj[2]))
    bg = _clip(c[1], k * math.sqrt(pi[2] * pj[0]))
    bb = _clip(c[2], k * math.sqrt(pi[2] * pj[2]))
    return gg, gb, bg, bb


@nb.njit(cache=True, inline="always")
def block_variances(own1, own2, own3, d12, d13, d23, variance_mode):
    """The diagonal blocks P_ii from the own covariances C_i and the difference moments D_ij
    (module docstring): mode 2 yaw-rate covariance matching, 1 three-cornered hat, 0 C_i."""
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
    return p1, p2, p3


@nb.njit(cache=True, inline="always")
def _solve_z(state, p1, p2, p3, c12, c13, c23, use_cross):
    """Z = P^-1 L into the scratch: with the cross blocks when ``use_cross`` and P is positive
    definite with them (Cholesky), else block-diagonal. Returns the CROSS_SCALE (1 used, 0
    dropped), NaN when even the diagonal blocks are not positive definite."""
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
            return math.nan
    return scale


@nb.njit(cache=True, inline="always")
def _weights(state, x1, x2, x3):
    """Eq. 37-39 from Z = P^-1 L in the scratch: A = L' Z, the fused covariance A^-1, the
    weights W_i = A^-1 Z_i' (into the state) and the fused (gamma, beta). Returns (gamma_0,
    beta_0, var)."""
    # A = L' Z (2x2), its inverse is the fused covariance (eq. 37)
    a00 = state[SCRATCH_Z] + state[SCRATCH_Z + 4] + state[SCRATCH_Z + 8]
    a01 = state[SCRATCH_Z + 1] + state[SCRATCH_Z + 5] + state[SCRATCH_Z + 9]
    a10 = state[SCRATCH_Z + 2] + state[SCRATCH_Z + 6] + state[SCRATCH_Z + 10]
    a11 = state[SCRATCH_Z + 3] + state[SCRATCH_Z + 7] + state[SCRATCH_Z + 11]
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
        z00 = state[SCRATCH_Z + 4 * i]
        z01 = state[SCRATCH_Z + 4 * i + 1]
        z10 = state[SCRATCH_Z + 4 * i + 2]
        z11 = state[SCRATCH_Z + 4 * i + 3]
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


@nb.njit(cache=True, _nrt=False)
def fuse(state, own1, own2, own3, x1, x2, x3, variance_mode, use_cross, floor):
    """Eq. 38-39 with P built as in the module docstring.

    own_i = (gg, gb, bb) own covariance, x_i = (gamma, beta). Writes the weights W1..W3, the
    fused (gamma, beta) and its beta variance into the state. Returns (gamma_0, beta_0, var).
    """
    d12 = (state[D12], state[D12 + 1], state[D12 + 2])
    d13 = (state[D13], state[D13 + 1], state[D13 + 2])
    d23 = (state[D23], state[D23 + 1], state[D23 + 2])
    p1, p2, p3 = block_variances(own1, own2, own3, d12, d13, d23, variance_mode)
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
    scale = _solve_z(state, p1, p2, p3, c12, c13, c23, use_cross)
    if not scale >= 0.0:
        return math.nan, math.nan, math.nan
    state[S.CROSS_SCALE] = scale
    return _weights(state, x1, x2, x3)


@nb.njit(cache=True, _nrt=False)
def own_covariances(state, sigma_yaw_rate, forgetting):
    """Each estimator's own (gamma, beta) covariance C_i as (gg, gb, bb) triples, and its beta
    (``sigma_yaw_rate``: the gyro's error, gamma_1; ``forgetting``: the WBE's rho)."""
    sigma_r = sigma_yaw_rate
    # KBE: gamma_1 is the gyro (error sigma_yaw_rate), beta from the KF covariance
    vx, vy = state[S.KBE_VX], state[S.KBE_VY]
    _, _, var = beta_variance(vx, vy, state[KBE_P], state[KBE_P + 1], state[KBE_P + 2])
    own1 = (sigma_r * sigma_r, 0.0, var)
    beta1 = math.atan2(vy, vx)
    # DBE: gradient [g1, g2, 0] of beta and e_r of gamma on the 3x3 covariance
    vx, vy = state[S.DBE_VX], state[S.DBE_VY]
    g1, g2, var = beta_variance(vx, vy, state[DBE_P], state[DBE_P + 1], state[DBE_P + 3])
    own2 = (state[DBE_P + 5], g1 * state[DBE_P + 2] + g2 * state[DBE_P + 4], var)
    beta2 = math.atan2(vy, vx)
    # WBE: s^2 M^-1 / (1 + rho)
    rho = forgetting
    i00, i01, i02, i11, i12, i22 = inverse_sym3(
        state[WBE_M], state[WBE_M + 1], state[WBE_M + 2],
        state[WBE_M + 3], state[WBE_M + 4], state[WBE_M + 5],
    )  # fmt: skip
    scale = state[S.WBE_RES_VAR] / (1.0 + rho)
    vx, vy = state[S.WBE_VX], state[S.WBE_VY]
    g1, g2, var = beta_variance(vx, vy, scale * i00, scale * i01, scale * i11)
    own3 = (scale * i22, scale * (g1 * i02 + g2 * i12), var)
    beta3 = math.atan2(vy, vx)
    return own1, own2, own3, beta1, beta2, beta3
