"""Kalman-filter algebra on the caller's state vector: packed covariances, the predict, the
updates (sequential scalar, Joseph, gated), the sideslip's sigma from [vx, vy].

Storage. A filter's state x is ``n`` consecutive slots at ``x0`` and its symmetric covariance
P the upper triangle, row-major, at ``p0`` (``tri``: for n = 3 the slots are P00 P01 P02 P11
P12 P22). Kernels that need working memory take a ``scratch`` offset of n * n slots. Nothing
is allocated; the loops run over tuples whose length numba knows at compile time, so each
filter size gets its own unrolled code.

Process noise, one convention: a kernel adds Q as the covariance *of one step*; a method's
params state a variance over an interval (``per_step``: per second for most, per
``nominal_dt`` where a paper publishes per-sample values) and convert at the call.

Each line sits under the equation it computes (filterpy's style); the plain twins in
tests/test_kalman.py check every kernel against the textbook matrix form.
"""

from __future__ import annotations

import math

from slipd.estimators.common.filters import lowpass
from slipd.numba_cache import nb


@nb.njit(cache=True, _nrt=False)
def tri(i, j, n):
    """Offset of element (i, j) of a symmetric n x n matrix stored as its upper triangle."""
    if i > j:
        i, j = j, i
    return i * n - (i * (i - 1)) // 2 + (j - i)


@nb.njit(cache=True, _nrt=False)
def per_step(variance, dt, interval):
    """The process noise of one step of ``dt`` from a random walk's ``variance`` per
    ``interval`` seconds (the variance of a random walk grows linearly in time)."""
    return variance * (dt / interval)


@nb.njit(cache=True, inline="always")
def predict_covariance(state, p0, scratch, F, Q):
    """P^- = F P F' + Q, Q diagonal. ``F``: the n x n transition (Jacobian) as a row-major
    tuple, ``Q``: its n diagonal elements (per step); P packed at ``p0``, n * n scratch.
    Zero elements of ``F`` are skipped: a literal 0.0 in the caller's tuple costs
    nothing once numba has inlined the kernel, so a sparse F runs as its hand-written form."""
    n = len(Q)
    # B = F P
    for i in range(n):
        for j in range(n):
            acc = 0.0
            first = True
            for k in range(n):
                f = F[i * n + k]
                if f != 0.0:
                    term = f * state[p0 + tri(k, j, n)]
                    acc = term if first else acc + term
                    first = False
            state[scratch + i * n + j] = acc
    # P^- = B F' + Q
    for i in range(n):
        for j in range(i, n):
            acc = 0.0
            first = True
            for k in range(n):
                f = F[j * n + k]
                if f != 0.0:
                    term = state[scratch + i * n + k] * f
                    acc = term if first else acc + term
                    first = False
            if i == j:
                acc += Q[i]
            state[p0 + tri(i, j, n)] = acc


@nb.njit(cache=True, _nrt=False)
def add_input_noise(state, p0, G, variance):
    """P += G variance G': the covariance a noisy input (variance ``variance``) adds through
    its input matrix column ``G`` (a tuple of n), e.g. a measured steer angle driving a model."""
    n = len(G)
    for i in range(n):
        for j in range(i, n):
            state[p0 + tri(i, j, n)] += G[i] * variance * G[j]


@nb.njit(cache=True, inline="always")
def scalar_update(state, x0, p0, scratch, H, innovation, r):
    """Update with one scalar measurement y = H x + v, var(v) = r (``innovation`` = y - h(x^-)):

        S = H P H' + r,  K = P H' / S,  x = x + K (y - h),  P = P - K (P H')'

    Several measurements with independent noise, processed one after the other with each
    innovation taken after the earlier updates, give exactly the batch update (Chen eq. 11-13
    with a diagonal R). ``H``: tuple of n; n scratch slots. Returns S (the innovation
    variance: innovation^2 / S is the normalised innovation squared)."""
    n = len(H)
    # P H' (zero elements of H skipped, as in ``predict_covariance``)
    for i in range(n):
        acc = 0.0
        first = True
        for j in range(n):
            if H[j] != 0.0:
                term = state[p0 + tri(i, j, n)] * H[j]
                acc = term if first else acc + term
                first = False
        state[scratch + i] = acc
    # S = H P H' + r
    s = 0.0
    first = True
    for i in range(n):
        if H[i] != 0.0:
            term = H[i] * state[scratch + i]
            s = term if first else s + term
            first = False
    s += r
    # x = x + K (y - h), K = P H' / S
    for i in range(n):
        state[x0 + i] += state[scratch + i] / s * innovation
    # P = P - K (P H')'
    for i in range(n):
        k = state[scratch + i] / s
        for j in range(i, n):
            state[p0 + tri(i, j, n)] -= k * state[scratch + j]
    return s


@nb.njit(cache=True, inline="always")
def optional_row(ok, h1, h2, innovation, r):
    """A measurement row for ``joseph_update2``: as given when ``ok``, else the zero row (H = 0,
    innovation 0, r = 1) that leaves the measurement out. Returns (h1, h2, innovation, r)."""
    if ok:
        return h1, h2, innovation, r
    return 0.0, 0.0, 0.0, 1.0


@nb.njit(cache=True, _nrt=False)
def joseph_update2(state, x0, p0, h11, h12, h21, h22, inn1, inn2, r1, r2):
    """One Kalman update of a 2-state filter with two measurements (x at ``x0``, packed P at
    ``p0``): H = [[h11, h12], [h21, h22]], R = diag(r1, r2), innovation [inn1, inn2].

    A missing measurement is passed as a zero H row, zero innovation and r = 1: its gain column
    is then exactly zero and the update reduces to the scalar update of the other one.
    Covariance in Joseph form (as filterpy's ``KalmanFilter.update``), which keeps P symmetric
    positive definite with any gain. Returns the normalised innovation squared inn' S^-1 inn.
    """
    x1 = state[x0]
    x2 = state[x0 + 1]
    p11 = state[p0]
    p12 = state[p0 + 1]
    p22 = state[p0 + 2]
    # PHt = P H'
    b11 = p11 * h11 + p12 * h12
    b12 = p11 * h21 + p12 * h22
    b21 = p12 * h11 + p22 * h12
    b22 = p12 * h21 + p22 * h22
    # S = H P H' + R
    s11 = h11 * b11 + h12 * b21 + r1
    s12 = h11 * b12 + h12 * b22
    s21 = h21 * b11 + h22 * b21
    s22 = h21 * b12 + h22 * b22 + r2
    det = s11 * s22 - s12 * s21
    # S^-1
    i11 = s22 / det
    i12 = -s12 / det
    i21 = -s21 / det
    i22 = s11 / det
    # K = P H' S^-1
    k11 = b11 * i11 + b12 * i21
    k12 = b11 * i12 + b12 * i22
    k21 = b21 * i11 + b22 * i21
    k22 = b21 * i12 + b22 * i22
    # x = x + K (y - h(x))
    state[x0] = x1 + k11 * inn1 + k12 * inn2
    state[x0 + 1] = x2 + k21 * inn1 + k22 * inn2
    # A = I - K H
    a11 = 1.0 - (k11 * h11 + k12 * h21)
    a12 = -(k11 * h12 + k12 * h22)
    a21 = -(k21 * h11 + k22 * h21)
    a22 = 1.0 - (k21 * h12 + k22 * h22)
    # P = A P A' + K R K'
    c11 = a11 * p11 + a12 * p12
    c12 = a11 * p12 + a12 * p22
    c21 = a21 * p11 + a22 * p12
    c22 = a21 * p12 + a22 * p22
    state[p0] = c11 * a11 + c12 * a12 + k11 * k11 * r1 + k12 * k12 * r2
    state[p0 + 1] = c11 * a21 + c12 * a22 + k11 * k21 * r1 + k12 * k22 * r2
    state[p0 + 2] = c21 * a21 + c22 * a22 + k21 * k21 * r1 + k22 * k22 * r2
    # inn' S^-1 inn
    return inn1 * (i11 * inn1 + i12 * inn2) + inn2 * (i21 * inn1 + i22 * inn2)


@nb.njit(cache=True, _nrt=False)
def gated_update(state, x0, p0, H, nu, r, gate):
    """Update of a 2-state filter with three measurements (R = r I) behind a Mahalanobis gate.

    d^2 = nu' S^-1 nu with S = H P H' + R, the innovation covariance the filter provides
    (Yoon eq. 4); when d^2 exceeds ``gate`` (a chi-square quantile with 3 degrees of freedom)
    H is replaced by zero (Sec. 2.2), i.e. nothing changes. Otherwise the batch update
    K = P H' S^-1, x = x + K nu, P = P - K (P H')'. ``H``: the 3 x 2 Jacobian row-major,
    ``nu``: the three innovations. Returns d^2 (inf when S is not positive definite)."""
    p11 = state[p0]
    p12 = state[p0 + 1]
    p22 = state[p0 + 2]
    h1a, h1b, h2a, h2b, h3a, h3b = H
    nu1, nu2, nu3 = nu
    # P H' (2 x 3)
    b11 = p11 * h1a + p12 * h1b
    b12 = p11 * h2a + p12 * h2b
    b13 = p11 * h3a + p12 * h3b
    b21 = p12 * h1a + p22 * h1b
    b22 = p12 * h2a + p22 * h2b
    b23 = p12 * h3a + p22 * h3b
    # S = H P H' + R (symmetric 3 x 3)
    s11 = h1a * b11 + h1b * b21 + r
    s12 = h1a * b12 + h1b * b22
    s13 = h1a * b13 + h1b * b23
    s22 = h2a * b12 + h2b * b22 + r
    s23 = h2a * b13 + h2b * b23
    s33 = h3a * b13 + h3b * b23 + r
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
    # S^-1 nu
    w1 = i11 * nu1 + i12 * nu2 + i13 * nu3
    w2 = i12 * nu1 + i22 * nu2 + i23 * nu3
    w3 = i13 * nu1 + i23 * nu2 + i33 * nu3
    # d^2 = nu' S^-1 nu (Yoon eq. 4)
    d2 = nu1 * w1 + nu2 * w2 + nu3 * w3
    if not (d2 <= gate):
        return d2
    # x = x + K nu with K = P H' S^-1, so K nu = P H' (S^-1 nu)
    state[x0] = state[x0] + b11 * w1 + b12 * w2 + b13 * w3
    state[x0 + 1] = state[x0 + 1] + b21 * w1 + b22 * w2 + b23 * w3
    # K (2 x 3) = P H' S^-1
    k11 = b11 * i11 + b12 * i12 + b13 * i13
    k12 = b11 * i12 + b12 * i22 + b13 * i23
    k13 = b11 * i13 + b12 * i23 + b13 * i33
    k21 = b21 * i11 + b22 * i12 + b23 * i13
    k22 = b21 * i12 + b22 * i22 + b23 * i23
    k23 = b21 * i13 + b22 * i23 + b23 * i33
    # P = P - K (P H')'
    state[p0] = p11 - (k11 * b11 + k12 * b12 + k13 * b13)
    state[p0 + 1] = p12 - (k11 * b21 + k12 * b22 + k13 * b23)
    state[p0 + 2] = p22 - (k21 * b21 + k22 * b22 + k23 * b23)
    return d2


# ---------------------------------------------------------------------------------------------
# the sideslip angle's uncertainty
# ---------------------------------------------------------------------------------------------

#: (m/s)^2 below which the direction of [vx, vy] is not defined (1 mm/s).
SPEED2_FLOOR = 1e-6


@nb.njit(cache=True, _nrt=False)
def beta_variance(vx, vy, p_xx, p_xy, p_yy):
    """First-order propagation of the [vx, vy] covariance to beta = atan2(vy, vx):
    g = grad beta = [-vy, vx] / V^2 (V^2 floored at SPEED2_FLOOR), var = g P g'.
    Returns (g1, g2, var)."""
    speed2 = vx * vx + vy * vy
    if speed2 < SPEED2_FLOOR:
        speed2 = SPEED2_FLOOR
    g1 = -vy / speed2
    g2 = vx / speed2
    return g1, g2, g1 * g1 * p_xx + 2.0 * g1 * g2 * p_xy + g2 * g2 * p_yy


@nb.njit(cache=True, _nrt=False)
def beta_sigma(vx, vy, p_xx, p_xy, p_yy, standstill_sigma):
    """1-sigma of beta (``beta_variance``); ``standstill_sigma`` where V^2 <= SPEED2_FLOOR
    and beta is not defined (each method says what it reports there)."""
    if vx * vx + vy * vy <= SPEED2_FLOOR:
        return standstill_sigma
    var = beta_variance(vx, vy, p_xx, p_xy, p_yy)[2]
    return math.sqrt(var) if var > 0.0 else 0.0


@nb.njit(cache=True, inline="always")
def innovation_test(state, slot, nis, dof, dt, time_constant):
    """The innovation test of a Kalman filter (Bar-Shalom, Li, Kirubarajan 2001, "Estimation
    with Applications to Tracking and Navigation", Sec. 5.4.2): for a filter whose model and
    noise are right, the normalised innovation squared ``nis`` = nu' S^-1 nu of each update is
    chi-square with ``dof`` degrees of freedom (the measurements used), mean ``dof``. Kept in
    ``state[slot]`` is its time average per degree of freedom, NIS / dof low-passed with
    ``time_constant`` (``filters.lowpass``; NaN starts it), so about 1 while the model explains
    the measurements and well above it when it does not (a wrong tyre, a saturating axle, a
    biased sensor). A tick without a measurement (``dof`` 0) holds it. Returns the average."""
    if dof < 1:
        return state[slot]
    return lowpass(state, slot, nis / dof, dt, time_constant)
