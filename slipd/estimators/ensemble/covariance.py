"""The ensemble's error statistics without ground truth: pairwise difference moments and the
N-cornered hat with family terms that turns them into P, and eq. 38's weights (the
``ensemble`` module docstring states the model; tests/test_ensemble.py has its plain twin)."""

from __future__ import annotations

import math

from slipd.channels import N_OUT, Out
from slipd.estimators.ensemble.state import FAMILY, N_MEMBERS, F
from slipd.numba_cache import nb


@nb.njit(cache=True, _nrt=False)
def update_moments(state, decay):
    """D_ij, M_ij <- EWMA of (beta_i - beta_j)^2 and of 1 over the pairs usable this tick."""
    for i in range(N_MEMBERS):
        if state[F.USABLE + i] < 0.5:
            continue
        beta_i = state[F.MEMBER_OUT + i * N_OUT + Out.BETA]
        for j in range(i + 1, N_MEMBERS):
            if state[F.USABLE + j] < 0.5:
                continue
            diff = beta_i - state[F.MEMBER_OUT + j * N_OUT + Out.BETA]
            ij = i * N_MEMBERS + j
            d = (1.0 - decay) * state[F.MOMENT + ij] + decay * diff * diff
            mass = (1.0 - decay) * state[F.MASS + ij] + decay
            state[F.MOMENT + ij] = d
            state[F.MOMENT + j * N_MEMBERS + i] = d
            state[F.MASS + ij] = mass
            state[F.MASS + j * N_MEMBERS + i] = mass


@nb.njit(cache=True, _nrt=False)
def _moment(state, i, j):
    """The bias-corrected moment D_ij / M_ij."""
    ij = i * N_MEMBERS + j
    mass = state[F.MASS + ij]
    return state[F.MOMENT + ij] / mass if mass > 0.0 else 0.0


@nb.njit(cache=True, _nrt=False)
def own_variance(state, m, calibrated):
    """Member m's own error variance: its sigma_beta squared, or with ``calibrated`` its
    consistency monitor's calibrated sigma (``monitor_members``: its own sigma together with
    what the witnesses say of its error) where the monitor has run."""
    sigma = state[F.MEMBER_OUT + m * N_OUT + Out.SIGMA_BETA]
    if calibrated and math.isfinite(state[F.CALIBRATED_SIGMA + m]):
        sigma = state[F.CALIBRATED_SIGMA + m]
    return sigma * sigma if math.isfinite(sigma) and sigma > 0.0 else 0.0


@nb.njit(cache=True, _nrt=False)
def _fused(state, m):
    return state[F.FUSED + m] > 0.5


#: Row stride of the scratch matrix at F.SYSTEM.
STRIDE = 2 * N_MEMBERS
#: Pivot of the unit-diagonal (scaled) system below which it is taken as singular.
SINGULAR_PIVOT = 1e-12


@nb.njit(cache=True, _nrt=False)
def _solve_spd(state, n):
    """Solve A x = b in place for the SPD n x n system A at ``state[F.SYSTEM:]`` (row stride
    STRIDE) and b at ``state[F.RHS:]``, x replacing b: the system is first scaled to a unit
    diagonal, then Gaussian elimination without pivoting (valid for SPD). False if a pivot is
    not positive (A singular or not positive definite)."""
    a0 = F.SYSTEM
    b0 = F.RHS
    for p in range(n):
        diagonal = state[a0 + p * STRIDE + p]
        if not diagonal > 0.0:
            return False
        state[F.SCALE + p] = 1.0 / math.sqrt(diagonal)
    for p in range(n):
        for q in range(n):
            state[a0 + p * STRIDE + q] *= state[F.SCALE + p] * state[F.SCALE + q]
        state[b0 + p] *= state[F.SCALE + p]
    for k in range(n):
        pivot = state[a0 + k * STRIDE + k]
        if not pivot > SINGULAR_PIVOT:
            return False
        for i in range(k + 1, n):
            factor = state[a0 + i * STRIDE + k] / pivot
            if factor != 0.0:
                for j in range(k, n):
                    state[a0 + i * STRIDE + j] -= factor * state[a0 + k * STRIDE + j]
                state[b0 + i] -= factor * state[b0 + k]
    for k in range(n - 1, -1, -1):
        acc = state[b0 + k]
        for j in range(k + 1, n):
            acc -= state[a0 + k * STRIDE + j] * state[b0 + j]
        state[b0 + k] = acc / state[a0 + k * STRIDE + k]
    for p in range(n):
        state[b0 + p] *= state[F.SCALE + p]
    return True


@nb.njit(cache=True, _nrt=False)
def _family_count(state, n, family):
    count = 0
    for p in range(n):
        if FAMILY[int(state[F.INDEX + p])] == family:
            count += 1
    return count


@nb.njit(cache=True, _nrt=False)
def _add_pair(state, p, q, fp, fq, same, weight, value):
    """Add one pair's row a (U_p + U_q [+ C_fp + C_fq across families]) to the normal
    equations: A += weight a a', b += weight a value."""
    k0 = p
    k1 = q
    k2 = -1
    k3 = -1
    if not same:
        k2 = int(state[F.UNKNOWN + fp])
        k3 = int(state[F.UNKNOWN + fq])
    for a in (k0, k1, k2, k3):
        if a < 0:
            continue
        state[F.RHS + a] += weight * value
        for b in (k0, k1, k2, k3):
            if b >= 0:
                state[F.SYSTEM + a * STRIDE + b] += weight


@nb.njit(cache=True, inline="always")
def _select_fused(state):
    """Reset the tick's weights, variances and family terms; the fused members' indices into
    ``state[F.INDEX:]``. Returns their number n."""
    n = 0
    for i in range(N_MEMBERS):
        state[F.VARIANCE + i] = math.nan
        state[F.WEIGHT + i] = 0.0
        state[F.COMMON + i] = 0.0
        state[F.UNKNOWN + i] = -1.0
        if _fused(state, i):
            state[F.INDEX + n] = i
            n += 1
    return n


@nb.njit(cache=True, inline="always")
def _fit_moments(state, n, floor):
    """The N-cornered hat with family terms (module docstring): U_p of the n fused members and
    C_f of each identifiable family, fitted to the moments by weighted least squares (the
    solution in ``state[F.RHS:]``, C_f into ``state[F.COMMON:]``). Returns whether it was
    solved (it needs n >= 3 and a positive definite system)."""
    # unknowns: U_p for p < n, then C_f of each family with >= 2 fused members and >= 2 fused
    # members outside it (else C_f is not identifiable and taken as 0)
    m = n
    for family in range(N_MEMBERS):
        inside = _family_count(state, n, family)
        if inside >= 2 and n - inside >= 2:
            state[F.UNKNOWN + family] = m
            m += 1
    if n < 3:
        return False
    for a in range(m):
        state[F.RHS + a] = 0.0
        for b in range(m):
            state[F.SYSTEM + a * STRIDE + b] = 0.0
    for p in range(n):
        i = int(state[F.INDEX + p])
        for q in range(p + 1, n):
            j = int(state[F.INDEX + q])
            d = _moment(state, i, j)
            weight = 1.0 / ((d + floor) * (d + floor))
            _add_pair(state, p, q, FAMILY[i], FAMILY[j], FAMILY[i] == FAMILY[j], weight, d)
    if not _solve_spd(state, m):
        return False
    for family in range(N_MEMBERS):
        k = int(state[F.UNKNOWN + family])
        if k >= 0:
            state[F.COMMON + family] = max(state[F.RHS + k], 0.0)
    return True


@nb.njit(cache=True, inline="always")
def _member_variances(state, n, solved, floor, calibrated):
    """P_ii = max(U_i + C_f, own sigma^2) + floor into ``state[F.VARIANCE:]`` (with n = 2 the
    moment shared in proportion to the own variances, with n = 1 the own variance)."""
    for p in range(n):
        i = int(state[F.INDEX + p])
        own = own_variance(state, i, calibrated)
        if solved:
            hat = max(state[F.RHS + p], 0.0) + state[F.COMMON + FAMILY[i]]
        elif n == 2:
            other = int(state[F.INDEX + 1 - p])
            own_other = own_variance(state, other, calibrated)
            share = own / (own + own_other) if own + own_other > 0.0 else 0.5
            hat = share * _moment(state, i, other)
        else:
            hat = own
        state[F.VARIANCE + i] = max(hat, own) + floor


@nb.njit(cache=True, inline="always")
def _covariance(state, i, j, diagonal):
    """P_ij of the model: P_ii on the diagonal, C_f within a family, 0 across families."""
    if diagonal:
        return state[F.VARIANCE + i]
    if FAMILY[i] == FAMILY[j]:
        return state[F.COMMON + FAMILY[i]]
    return 0.0


@nb.njit(cache=True, inline="always")
def _minimum_variance_weights(state, n):
    """Eq. 38 with the model's P: x = P^-1 1 (P rebuilt in the scratch matrix), negative x
    (a member correlated with a better one) clipped, w = x / (1' x) into ``state[F.WEIGHT:]``."""
    for p in range(n):
        i = int(state[F.INDEX + p])
        state[F.RHS + p] = 1.0
        for q in range(n):
            state[F.SYSTEM + p * STRIDE + q] = _covariance(state, i, int(state[F.INDEX + q]),
                                                           p == q)  # fmt: skip
    if not _solve_spd(state, n):
        for p in range(n):  # cannot happen for P = diag + family blocks; diagonal P then
            state[F.RHS + p] = 1.0 / state[F.VARIANCE + int(state[F.INDEX + p])]
    total = 0.0
    for p in range(n):
        x = state[F.RHS + p]
        total += x if x > 0.0 else 0.0
    for p in range(n):
        x = state[F.RHS + p]
        state[F.WEIGHT + int(state[F.INDEX + p])] = x / total if x > 0.0 else 0.0


@nb.njit(cache=True, _nrt=False)
def error_covariance(state, floor, calibrated):
    """P of the fused members (module docstring) and the weights of eq. 38 into
    ``state[F.WEIGHT:]``; P_ii into ``state[F.VARIANCE:]`` (NaN for members not fused), C_f
    into ``state[F.COMMON:]``. Returns (number fused, fused variance w' P w)."""
    n = _select_fused(state)
    if n == 0:
        return 0, math.nan
    solved = _fit_moments(state, n, floor)
    _member_variances(state, n, solved, floor, calibrated)
    _minimum_variance_weights(state, n)
    # fused variance w' P w
    variance = 0.0
    for p in range(n):
        i = int(state[F.INDEX + p])
        for q in range(n):
            j = int(state[F.INDEX + q])
            variance += state[F.WEIGHT + i] * state[F.WEIGHT + j] * _covariance(state, i, j,
                                                                                p == q)
    return n, variance
