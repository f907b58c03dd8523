"""Plain twins of the Kalman algebra (slipd.estimators.common.kalman): each kernel against the
textbook matrix form in numpy, on random filters of every size the methods use."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipd.estimators.common import kalman

RTOL = 1e-12


def random_spd(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.normal(size=(n, n))
    return a @ a.T + n * np.eye(n) * rng.uniform(0.1, 2.0)


def packed(P: np.ndarray) -> np.ndarray:
    n = len(P)
    return np.array([P[i, j] for i in range(n) for j in range(i, n)])


def unpacked(values: np.ndarray, n: int) -> np.ndarray:
    P = np.zeros((n, n))
    k = 0
    for i in range(n):
        for j in range(i, n):
            P[i, j] = P[j, i] = values[k]
            k += 1
    return P


def filter_state(x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, int, int, int]:
    """A state vector holding x, packed P and n * n scratch slots after a few unrelated slots."""
    n = len(x)
    x0, p0 = 3, 3 + n
    scratch = p0 + n * (n + 1) // 2 + 2
    state = np.full(scratch + n * n + 3, 7.0)
    state[x0 : x0 + n] = x
    state[p0 : p0 + n * (n + 1) // 2] = packed(P)
    return state, x0, p0, scratch


def test_tri_enumerates_the_upper_triangle_row_by_row():
    for n in (1, 2, 3, 4):
        offsets = [kalman.tri(i, j, n) for i in range(n) for j in range(i, n)]
        assert offsets == list(range(n * (n + 1) // 2))
        assert all(kalman.tri(i, j, n) == kalman.tri(j, i, n) for i in range(n) for j in range(n))


@pytest.mark.parametrize("n", [2, 3, 4])
def test_predict_covariance_is_f_p_ft_plus_q(n):
    rng = np.random.default_rng(n)
    P = random_spd(rng, n)
    F = np.eye(n) + 0.05 * rng.normal(size=(n, n))
    q = rng.uniform(0.0, 1e-2, n)
    state, _, p0, scratch = filter_state(np.zeros(n), P)
    kalman.predict_covariance(state, p0, scratch, tuple(F.ravel()), tuple(q))
    expected = F @ P @ F.T + np.diag(q)
    np.testing.assert_allclose(unpacked(state[p0 : p0 + n * (n + 1) // 2], n), expected,
                               rtol=RTOL, atol=1e-15)  # fmt: skip
    assert np.all(state[:3] == 7.0)  # nothing outside x, P and the scratch is touched


@pytest.mark.parametrize("n", [1, 2, 3])
def test_scalar_updates_in_sequence_are_the_batch_update(n):
    """Sequential scalar updates, each innovation taken after the earlier ones, equal the
    batch update with a diagonal R (the textbook K = P H' (H P H' + R)^-1)."""
    rng = np.random.default_rng(10 + n)
    x = rng.normal(size=n)
    P = random_spd(rng, n)
    H = rng.normal(size=(2, n))
    R = rng.uniform(0.1, 1.0, 2)
    y = rng.normal(size=2)
    state, x0, p0, scratch = filter_state(x, P)
    for row in range(2):
        innovation = y[row] - H[row] @ state[x0 : x0 + n]
        s = kalman.scalar_update(state, x0, p0, scratch, tuple(H[row]), innovation, R[row])
        assert s > R[row]
    S = H @ P @ H.T + np.diag(R)
    K = P @ H.T @ np.linalg.inv(S)
    np.testing.assert_allclose(state[x0 : x0 + n], x + K @ (y - H @ x), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(unpacked(state[p0 : p0 + n * (n + 1) // 2], n),
                               (np.eye(n) - K @ H) @ P, rtol=1e-10, atol=1e-12)  # fmt: skip


@given(st.integers(0, 10_000), st.booleans(), st.booleans())
@settings(max_examples=60, deadline=None)
def test_joseph_update_is_the_kalman_update_with_missing_rows_left_out(seed, first, second):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=2)
    P = random_spd(rng, 2)
    H = rng.normal(size=(2, 2))
    R = rng.uniform(0.05, 1.0, 2)
    y = rng.normal(size=2)
    used = np.array([first, second])
    state, x0, p0, _ = filter_state(x, P)
    inn = np.where(used, y - H @ x, 0.0)
    Hk = np.where(used[:, None], H, 0.0)
    nis = kalman.joseph_update2(state, x0, p0, *Hk.ravel(), *inn, *np.where(used, R, 1.0))
    if not used.any():
        np.testing.assert_array_equal(state[x0 : x0 + 2], x)
        return
    Hu, Ru, nu = H[used], np.diag(R[used]), (y - H @ x)[used]
    S = Hu @ P @ Hu.T + Ru
    K = P @ Hu.T @ np.linalg.inv(S)
    A = np.eye(2) - K @ Hu
    np.testing.assert_allclose(state[x0 : x0 + 2], x + K @ nu, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(unpacked(state[p0 : p0 + 3], 2), A @ P @ A.T + K @ Ru @ K.T,
                               rtol=1e-10, atol=1e-12)  # fmt: skip
    assert nis == pytest.approx(nu @ np.linalg.solve(S, nu), rel=1e-10)


def test_gated_update_applies_the_batch_update_only_inside_the_gate():
    rng = np.random.default_rng(5)
    x = rng.normal(size=2)
    P = random_spd(rng, 2) * 1e-2
    H = rng.normal(size=(3, 2))
    r = 0.3
    nu = rng.normal(size=3)
    S = H @ P @ H.T + r * np.eye(3)
    d2 = nu @ np.linalg.solve(S, nu)
    state, x0, p0, _ = filter_state(x, P)
    assert kalman.gated_update(state, x0, p0, tuple(H.ravel()), tuple(nu), r, 0.5 * d2) == \
        pytest.approx(d2, rel=1e-12)
    np.testing.assert_array_equal(state[x0 : x0 + 2], x)  # rejected: nothing changed
    assert kalman.gated_update(state, x0, p0, tuple(H.ravel()), tuple(nu), r, 2.0 * d2) == \
        pytest.approx(d2, rel=1e-12)
    K = P @ H.T @ np.linalg.inv(S)
    np.testing.assert_allclose(state[x0 : x0 + 2], x + K @ nu, rtol=1e-10)
    np.testing.assert_allclose(unpacked(state[p0 : p0 + 3], 2), P - K @ H @ P, rtol=1e-10,
                               atol=1e-15)  # fmt: skip


def test_input_noise_adds_g_q_gt():
    rng = np.random.default_rng(6)
    P = random_spd(rng, 3)
    g = rng.normal(size=3)
    state, _, p0, _ = filter_state(np.zeros(3), P)
    kalman.add_input_noise(state, p0, tuple(g), 0.04)
    np.testing.assert_allclose(unpacked(state[p0 : p0 + 6], 3), P + 0.04 * np.outer(g, g),
                               rtol=RTOL)  # fmt: skip


@given(st.floats(1.0, 60.0), st.floats(-10.0, 10.0), st.floats(1e-6, 1.0), st.floats(1e-6, 1.0),
       st.floats(-0.9, 0.9))
@settings(max_examples=80, deadline=None)
def test_beta_sigma_is_the_first_order_propagation(vx, vy, sx, sy, rho):
    """sigma of atan2(vy, vx) by the gradient, checked against a central difference."""
    P = np.array([[sx * sx, rho * sx * sy], [rho * sx * sy, sy * sy]])
    eps = 1e-6
    grad = np.array([(math.atan2(vy, vx + eps) - math.atan2(vy, vx - eps)) / (2 * eps),
                     (math.atan2(vy + eps, vx) - math.atan2(vy - eps, vx)) / (2 * eps)])
    sigma = kalman.beta_sigma(vx, vy, P[0, 0], P[0, 1], P[1, 1], math.nan)
    assert sigma == pytest.approx(math.sqrt(grad @ P @ grad), rel=1e-5)


def test_beta_sigma_at_standstill_is_what_the_method_says():
    assert math.isnan(kalman.beta_sigma(0.0, 0.0, 1.0, 0.0, 1.0, math.nan))
    assert kalman.beta_sigma(1e-4, 0.0, 1.0, 0.0, 1.0, math.pi) == math.pi
    assert kalman.per_step(0.5, 0.01, 1.0) == 0.5 * 0.01
    assert kalman.per_step(3e-6, 0.02, 0.01) == pytest.approx(6e-6, rel=1e-15)


def test_innovation_test_averages_nis_per_measurement_and_holds_without_one():
    from slipd.estimators.common.kalman import innovation_test

    state = np.full(1, np.nan)
    assert innovation_test(state, 0, 6.0, 2, 0.01, 1.0) == 3.0  # starts at the first value
    assert innovation_test(state, 0, 100.0, 0, 0.01, 1.0) == 3.0  # no measurement: held
    value = innovation_test(state, 0, 2.0, 1, 0.01, 1.0)  # NIS 2 of one measurement
    assert value == pytest.approx(3.0 + 0.01 * (2.0 - 3.0))
    for _ in range(2000):  # 20 time constants of chi-square(2) samples: mean 1 per dof
        value = innovation_test(state, 0, np.random.default_rng(_).chisquare(2), 2, 0.01, 1.0)
    assert 0.7 < value < 1.3
