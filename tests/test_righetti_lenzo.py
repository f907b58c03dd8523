"""Tests of the Righetti & Lenzo 2025 family: dk_ekf, d_ekf, k_kf (slipd.estimators).

- the jitted 2x2 scalar algebra agrees with a plain-numpy matrix EKF to 1e-12 (one predict and
  update of each filter) and a whole DK-EKF tick sequence with a numpy re-implementation;
- the analytic Jacobians of the single-track model match finite differences;
- the paper's observability argument (Sec. 2.3): with r = 0 the DK-EKF's vy stays observable,
  the K-KF's does not;
- robustness: invalid and non-finite inputs, non-finite state (RESET), standstill;
- zero allocations per step (numba NRT statistics in a subprocess);
- the paper's Table 2 claims on the simulator (double lane change, slalom) and no NaN or
  divergence over the simulator suite.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
import pytest
from nrt import allocations, sine_drive_inputs

from slipd.channels import (
    N_OUT,
    ST_INPUT_TIMEOUT,
    ST_NOT_CONVERGED,
    ST_RESET,
    U_LEN,
    U_TIME,
    VALID,
    WHEEL_SPEEDS,
    G,
    In,
    Out,
    Veh,
)
from slipd.estimators import registry
from slipd.estimators.common.tyres import tanh_tyre
from slipd.estimators.righetti_lenzo2025 import d_ekf, dk_ekf, k_kf
from slipd.estimators.righetti_lenzo2025 import filters as rl
from slipd.estimators.righetti_lenzo2025.filters import S

METHODS = {"dk_ekf": dk_ekf, "d_ekf": d_ekf, "k_kf": k_kf}
#: The paper's own pre-processing (Sec. 3.1: planar CoG translation only). The synthetic plant
#: below has no roll, so slipd's default gravity compensation would only add an error there.
PAPER_PREPROCESSING = {"roll_time_constant": 0.0, "lever_arm_3d": 0.0}
DT = 0.01
REPO = Path(__file__).resolve().parents[1]


def load_vehicle() -> np.ndarray:
    """The default profile's vehicle vector (the simulator's BMW 320i)."""
    from slipd.profile import load_profile

    return np.asarray(load_profile("default").vehicle, dtype=np.float64)


# ---------------------------------------------------------------------------------------------
# a synthetic plant: the filter's own single-track model (model-matched), sensors at the CoG
# ---------------------------------------------------------------------------------------------


def single_track_ticks(
    vehicle: np.ndarray,
    steer: np.ndarray,
    speed: float = 20.0,
    ay_offset: float = 0.0,
    noise: bool = True,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Input matrix U and true beta of the tanh single-track model driven by ``steer`` at
    constant ``speed`` (Euler, 100 Hz). IMU at the CoG for this plant (IMU_* zeroed by callers).
    """
    n = steer.size
    rng = np.random.default_rng(seed)
    U = np.zeros((n, U_LEN))
    beta = np.zeros(n)
    vy = 0.0
    r = 0.0
    half_f = 0.5 * vehicle[Veh.TRACK_F]
    half_r = 0.5 * vehicle[Veh.TRACK_R]
    for k in range(n):
        vy_dot, r_dot, ay, *_ = rl.single_track(vy, r, speed, steer[k], vehicle,
                                                vehicle[Veh.MU_NOMINAL])
        U[k, In.AY] = ay + ay_offset
        U[k, In.YAW_RATE] = r
        U[k, In.STEER] = steer[k]
        U[k, In.WHEEL_SPEED_FL] = (speed - half_f * r) / math.cos(steer[k])
        U[k, In.WHEEL_SPEED_FR] = (speed + half_f * r) / math.cos(steer[k])
        U[k, In.WHEEL_SPEED_RL] = speed - half_r * r
        U[k, In.WHEEL_SPEED_RR] = speed + half_r * r
        U[k, U_TIME] = k * DT
        beta[k] = math.atan2(vy, speed)
        vy += vy_dot * DT
        r += r_dot * DT
    if noise:
        U[:, In.AX] += rng.normal(0.0, 0.05, n)
        U[:, In.AY] += rng.normal(0.0, 0.1, n)
        U[:, In.YAW_RATE] += rng.normal(0.0, 0.001, n)
        for ch in WHEEL_SPEEDS:
            U[:, ch] += rng.normal(0.0, 0.02, n)
    for ch in (In.AX, In.AY, In.YAW_RATE, In.STEER, *WHEEL_SPEEDS):
        U[:, VALID + ch] = 1.0
    return U, beta


def cog_vehicle(vehicle: np.ndarray) -> np.ndarray:
    veh = vehicle.copy()
    veh[Veh.IMU_X] = veh[Veh.IMU_Y] = veh[Veh.IMU_Z] = 0.0
    return veh


def run(module, U: np.ndarray, vehicle: np.ndarray, overrides: dict | None = None):
    """Run ``module`` over ``U`` with the paper's pre-processing (plus ``overrides``)."""
    params = registry.make_params(module, {**PAPER_PREPROCESSING, **(overrides or {})})
    state = module.init(params, vehicle)
    OUT = np.zeros((U.shape[0], N_OUT))
    module.run_ticks(state, U, params, vehicle, DT, OUT)
    return OUT, state


# ---------------------------------------------------------------------------------------------
# plain-numpy reference (matrix form, np.linalg), the filterpy/rednose way to trust a kernel
# ---------------------------------------------------------------------------------------------


def ref_model(x: np.ndarray, vx: float, steer: float, veh: np.ndarray):
    """f(x, u) of eq. 1-2, h(x, u) of eq. 9 and their Jacobians, in numpy matrix form."""
    m, iz, a, b = veh[Veh.MASS], veh[Veh.YAW_INERTIA], veh[Veh.LF], veh[Veh.LR]
    stiffness = np.array([veh[Veh.CORNERING_STIFFNESS_F], veh[Veh.CORNERING_STIFFNESS_R]])
    mu_fz = veh[Veh.MU_NOMINAL] * m * G * np.array([b, a]) / (a + b)
    lever = np.array([[1.0, a], [1.0, -b]])  # rows: (vy + a r), (vy - b r)
    lateral = lever @ x
    alpha = np.array([steer, 0.0]) - np.arctan2(lateral, vx)
    dalpha_dx = -(vx / (vx**2 + lateral**2))[:, None] * lever
    tanh = np.tanh(stiffness * alpha / mu_fz)
    force = mu_fz * tanh
    dforce_dx = (stiffness * (1.0 - tanh**2))[:, None] * dalpha_dx
    proj = np.array([math.cos(steer), 1.0])  # front force projected on the body y axis
    moment = np.array([a * math.cos(steer), -b])
    f = np.array([proj @ force / m - vx * x[1], moment @ force / iz])
    J = np.vstack([proj @ dforce_dx / m - np.array([0.0, vx]), moment @ dforce_dx / iz])
    h = np.array([x[1], proj @ force / m])
    H = np.vstack([[0.0, 1.0], proj @ dforce_dx / m])
    return f, J, h, H


def ref_predict(x, P, f, F, Q, dt):
    """x^- = x + f dt (eq. 8), P^- = F P F' + Q."""
    return x + f * dt, F @ P @ F.T + Q


def ref_update(x, P, y, h, H, R):
    """Textbook update, Joseph form (filterpy KalmanFilter.update)."""
    S_ = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S_)
    x = x + K @ (y - h)
    IKH = np.eye(2) - K @ H
    return x, IKH @ P @ IKH.T + K @ R @ K.T


def sym(state: np.ndarray, p11: int) -> np.ndarray:
    return np.array([[state[p11], state[p11 + 1]], [state[p11 + 1], state[p11 + 2]]])


RANDOM_CASES = [
    # vy, r, vx, steer, p_vv, p_vr, p_rr, yaw_rate_meas, ay_meas
    (0.0, 0.0, 20.0, 0.0, 1.0, 0.0, 1e-2, 0.001, 0.05),
    (0.4, 0.3, 14.0, 0.04, 2e-3, 1e-4, 5e-4, 0.31, 4.2),
    (-1.2, -0.6, 25.0, -0.07, 3e-4, -2e-5, 2e-5, -0.58, -8.5),  # both axles near saturation
    (0.05, 0.02, 35.0, 0.002, 1e-5, 3e-7, 2e-6, 0.021, 0.6),
]


@pytest.mark.parametrize("case", RANDOM_CASES)
def test_dynamic_ekf_matches_numpy_reference(case, vehicle):
    vy, r, vx, steer, p11, p12, p22, r_meas, ay_meas = case
    q = (3e-6, 1e-6)
    R = np.diag([4e-7, 6e-2])
    state = np.zeros(rl.LAYOUT.size)
    state[[S.DYN_VY, S.DYN_R, S.DYN_P, S.DYN_P + 1, S.DYN_P + 2]] = vy, r, p11, p12, p22
    rl.dynamic_predict(state, vx, steer, vehicle, vehicle[Veh.MU_NOMINAL], q[0], q[1], DT)
    x = np.array([vy, r])
    P = np.array([[p11, p12], [p12, p22]])
    f, J, _, _ = ref_model(x, vx, steer, vehicle)
    x, P = ref_predict(x, P, f, np.eye(2) + J * DT, np.diag(q), DT)
    np.testing.assert_allclose(state[[S.DYN_VY, S.DYN_R]], x, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(sym(state, S.DYN_P), P, rtol=1e-12, atol=1e-18)

    rl.dynamic_update(state, r_meas, True, ay_meas, True, vx, steer, vehicle,
                      vehicle[Veh.MU_NOMINAL], R[0, 0], R[1, 1])
    _, _, h, H = ref_model(x, vx, steer, vehicle)
    x, P = ref_update(x, P, np.array([r_meas, ay_meas]), h, H, R)
    np.testing.assert_allclose(state[[S.DYN_VY, S.DYN_R]], x, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(sym(state, S.DYN_P), P, rtol=1e-12, atol=1e-18)


def test_dynamic_update_without_ay_is_the_scalar_yaw_rate_update(vehicle):
    state = np.zeros(rl.LAYOUT.size)
    state[[S.DYN_VY, S.DYN_R, S.DYN_P, S.DYN_P + 1, S.DYN_P + 2]] = 0.3, 0.2, 2e-3, 1e-4, 5e-4
    rl.dynamic_update(state, 0.25, True, 99.0, False, 15.0, 0.03, vehicle, vehicle[Veh.MU_NOMINAL],
                      4e-7, 6e-2)
    x = np.array([0.3, 0.2])
    P = np.array([[2e-3, 1e-4], [1e-4, 5e-4]])
    x, P = ref_update(x, P, np.array([0.25]), np.array([0.2]), np.array([[0.0, 1.0]]),
                      np.array([[4e-7]]))  # fmt: skip
    np.testing.assert_allclose(state[[S.DYN_VY, S.DYN_R]], x, rtol=1e-12)
    np.testing.assert_allclose(sym(state, S.DYN_P), P, rtol=1e-12, atol=1e-18)


@pytest.mark.parametrize("with_vy", [True, False])
def test_kinematic_kf_matches_numpy_reference(with_vy):
    vx, vy, p11, p12, p22 = 18.0, 0.7, 4e-3, -3e-4, 2e-2
    ax, ay, yaw_rate = 0.4, 3.1, 0.17
    q = (5e-3, 1e-4)
    vx_meas, vy_dyn, r_vx, r_vy = 18.1, 0.62, 2e-3, 1e-3
    state = np.zeros(rl.LAYOUT.size)
    state[[S.KIN_VX, S.KIN_VY, S.KIN_P, S.KIN_P + 1, S.KIN_P + 2]] = vx, vy, p11, p12, p22
    rl.kinematic_predict(state, ax, ay, yaw_rate, q[0], q[1], DT)
    rl.kinematic_update(state, vx_meas, True, r_vx, vy_dyn, with_vy, r_vy)
    # eq. 12-13: F_k = I + [[0, r], [-r, 0]] dt, G_k = I dt
    F = np.eye(2) + np.array([[0.0, yaw_rate], [-yaw_rate, 0.0]]) * DT
    x = F @ np.array([vx, vy]) + np.array([ax, ay]) * DT
    P = F @ np.array([[p11, p12], [p12, p22]]) @ F.T + np.diag(q)
    if with_vy:  # eq. 19
        H, y, R = np.eye(2), np.array([vx_meas, vy_dyn]), np.diag([r_vx, r_vy])
    else:  # eq. 14
        H, y, R = np.array([[1.0, 0.0]]), np.array([vx_meas]), np.array([[r_vx]])
    x, P = ref_update(x, P, y, H @ x, H, R)
    np.testing.assert_allclose(state[[S.KIN_VX, S.KIN_VY]], x, rtol=1e-12)
    np.testing.assert_allclose(sym(state, S.KIN_P), P, rtol=1e-12, atol=1e-18)


@pytest.mark.parametrize("case", RANDOM_CASES)
def test_single_track_jacobian_matches_finite_differences(case, vehicle):
    vy, r, vx, steer = case[:4]
    mu = vehicle[Veh.MU_NOMINAL]
    _, _, _, j11, j12, j21, j22 = rl.single_track(vy, r, vx, steer, vehicle, mu)
    eps = 1e-6
    numeric = np.zeros((3, 2))
    for col, (dvy, dr) in enumerate(((eps, 0.0), (0.0, eps))):
        plus = rl.single_track(vy + dvy, r + dr, vx, steer, vehicle, mu)[:3]
        minus = rl.single_track(vy - dvy, r - dr, vx, steer, vehicle, mu)[:3]
        numeric[:, col] = (np.array(plus) - np.array(minus)) / (2 * eps)
    analytic = np.array([[j11, j12], [j21, j22], [j11, j12 + vx]])  # last row: d ay / d x
    np.testing.assert_allclose(analytic, numeric, rtol=1e-6, atol=1e-6)


def test_tanh_tyre_is_linear_then_saturates():
    force, slope = tanh_tyre(1e-4, 1.3e5 / 7000.0, 7000.0, 1.3e5)
    assert force == pytest.approx(13.0, rel=1e-5) and slope == pytest.approx(1.3e5, rel=1e-5)
    force, slope = tanh_tyre(0.5, 1.3e5 / 7000.0, 7000.0, 1.3e5)
    assert force == pytest.approx(7000.0, rel=1e-6) and slope < 1.0


def ref_dk_ekf(U: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """The whole DK-EKF (Fig. 3) in numpy matrices, with dk_ekf's defaults; returns beta.

    Same tick order as the kernel: dynamic predict (u of k-1, vx_kin of k-1) and update
    (y of k), kinematic predict (u of k-1, Q of eq. 29) and update (eq. 19), vy_kin -> dynamic.
    Valid inputs and speed above the floor only.
    """
    p = {**dk_ekf.DEFAULTS, **PAPER_PREPROCESSING}
    wc = 2 * math.pi * p["yaw_acc_cutoff_hz"]
    imu_x, imu_y = vehicle[Veh.IMU_X], vehicle[Veh.IMU_Y]
    half_f, half_r = 0.5 * vehicle[Veh.TRACK_F], 0.5 * vehicle[Veh.TRACK_R]
    beta = np.zeros(U.shape[0])
    prev = None
    r_filtered = None
    for k, u in enumerate(U):
        yaw_rate, steer = u[In.YAW_RATE], u[In.STEER]
        if r_filtered is None:
            yaw_acc, r_filtered = 0.0, yaw_rate
        else:
            yaw_acc = wc * (yaw_rate - r_filtered)
            r_filtered += min(wc * DT, 1.0) * (yaw_rate - r_filtered)
        ax = u[In.AX] + yaw_acc * imu_y + yaw_rate**2 * imu_x  # eq. 22
        ay = u[In.AY] - yaw_acc * imu_x + yaw_rate**2 * imu_y  # eq. 23
        corners = [
            u[In.WHEEL_SPEED_FL] * math.cos(steer) + yaw_rate * half_f,
            u[In.WHEEL_SPEED_FR] * math.cos(steer) - yaw_rate * half_f,
            u[In.WHEEL_SPEED_RL] + yaw_rate * half_r,
            u[In.WHEEL_SPEED_RR] - yaw_rate * half_r,
        ]
        vx_meas = float(np.mean(corners))  # eq. 5-6
        if prev is None:
            xd, Pd = np.array([0.0, yaw_rate]), np.diag([p["p0_vy"], p["p0_r"]])
            xk, Pk = np.array([vx_meas, 0.0]), np.diag([p["p0_vx"], p["p0_vy"]])
        else:
            f, J, _, _ = ref_model(xd, prev["vx"], prev["steer"], vehicle)
            xd, Pd = ref_predict(xd, Pd, f, np.eye(2) + J * DT,
                                 np.diag([p["q_vy_dyn"], p["q_r_dyn"]]), DT)  # fmt: skip
            _, _, h, H = ref_model(xd, prev["vx"], steer, vehicle)
            xd, Pd = ref_update(xd, Pd, np.array([yaw_rate, ay]), h, H,
                                np.diag([p["r_yaw_rate_dyn"], p["r_ay_dyn"]]))  # fmt: skip
            p_vy = Pd[0, 0]
            F = np.eye(2) + np.array([[0.0, prev["r"]], [-prev["r"], 0.0]]) * DT
            xk = F @ xk + np.array([prev["ax"], prev["ay"]]) * DT
            Pk = F @ Pk @ F.T + np.diag([p["q_vx_kin"], p["q_vy_kin_ratio"] * p_vy])
            xk, Pk = ref_update(xk, Pk, np.array([vx_meas, xd[0]]), xk, np.eye(2),
                                np.diag([p["r_vx_kin"], p["r_vy_kin_ratio"] * p_vy]))  # fmt: skip
            xd = np.array([xk[1], xd[1]])
        prev = {"vx": xk[0], "steer": steer, "r": yaw_rate, "ax": ax, "ay": ay}
        beta[k] = math.atan2(xk[1], xk[0]) if k else 0.0
    return beta


def test_dk_ekf_tick_sequence_matches_numpy_reference(vehicle):
    t = np.arange(300) * DT
    U, _ = single_track_ticks(vehicle, 0.04 * np.sin(2 * np.pi * 0.7 * t) * (t > 0.5))
    U[:, In.AX] += 0.3  # let the kinematic vx channel work too
    OUT, _ = run(dk_ekf, U, vehicle)  # the vehicle's real IMU offset exercises eq. 22-23
    np.testing.assert_allclose(OUT[:, Out.BETA], ref_dk_ekf(U, vehicle), rtol=1e-9, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# behaviour on the filter's own model
# ---------------------------------------------------------------------------------------------


def test_dk_ekf_tracks_a_model_matched_plant(vehicle):
    veh = cog_vehicle(vehicle)
    t = np.arange(2000) * DT
    U, beta = single_track_ticks(veh, 0.03 * np.sin(2 * np.pi * 0.5 * t) * (t > 2.0))
    for module in (dk_ekf, d_ekf):
        OUT, _ = run(module, U, veh)
        err = OUT[200:, Out.BETA] - beta[200:]
        assert np.degrees(np.sqrt(np.mean(err**2))) < 0.05, module.__name__
        assert np.all(OUT[200:, Out.STATUS] == 0.0)
    assert np.degrees(np.abs(beta).max()) > 0.3  # the manoeuvre really excites beta


def test_dk_ekf_stays_observable_at_zero_yaw_rate(vehicle):
    """Sec. 2.3: the kinematic model alone loses vy at r = 0 (PBH rank 1, eq. 18); with the
    dynamic vy as a measurement (eq. 19) it keeps rank 2 (eq. 20). Straight run with an ay
    offset of 0.3 m/s^2 (e.g. a bank): the K-KF without its vy := 0 patch integrates the
    offset, its vy variance grows without bound; the DK-EKF's stays bounded and vy stays small.
    """
    veh = cog_vehicle(vehicle)
    n = 3000
    U, _ = single_track_ticks(veh, np.zeros(n), ay_offset=0.3)
    dk_out, dk_state = run(dk_ekf, U, veh)
    kkf_out, kkf_state = run(k_kf, U, veh, {"zero_vy_yaw_rate": 0.0,
                                            "vy_leak_time_constant": 0.0})  # the paper's
    assert np.abs(U[:, In.YAW_RATE]).max() < 0.01  # truly straight
    # DK-EKF: bounded vy (the tyre model balances the offset with ~0.03 m/s) and variance
    assert np.abs(dk_out[500:, Out.VY]).max() < 0.1
    assert dk_state[S.KIN_P + 2] < 1e-3
    assert np.all(dk_out[500:, Out.STATUS] == 0.0)
    # K-KF: vy = offset * t drift, variance ~ q_vy * ticks
    assert kkf_out[-1, Out.VY] > 0.8 * 0.3 * (n - 1) * DT
    assert kkf_state[S.KIN_P + 2] > 0.5 * 3e-3 * n
    assert kkf_out[-1, Out.STATUS] == ST_NOT_CONVERGED
    # PBH test of eq. 17-20 at r = 0, lambda = 0: [F - lambda I; H]
    F0 = np.zeros((2, 2))
    assert np.linalg.matrix_rank(np.vstack([F0, [[1.0, 0.0]]])) == 1
    assert np.linalg.matrix_rank(np.vstack([F0, np.eye(2)])) == 2


@pytest.mark.parametrize("leak", [0.0, 2.0])
def test_k_kf_leak_bounds_the_drift_of_a_banked_curve(vehicle, leak):
    """A steady curve (r ~ 0.1 rad/s at 20 m/s) with 0.34 m/s^2 of unmodelled ay (2 deg of
    bank): the paper's K-KF settles at a vy error of b / r (module docstring), the leak
    (``vy_leak_time_constant``, slipd's default 2 s) bounds it near b tau."""
    veh = cog_vehicle(vehicle)
    n, bank = 4000, 0.34
    U, beta = single_track_ticks(veh, np.full(n, 0.013), ay_offset=bank, noise=False)
    OUT, _ = run(k_kf, U, veh, {"vy_leak_time_constant": leak})
    r = U[-1, In.YAW_RATE]
    error = OUT[-500:, Out.VY] - 20.0 * np.tan(beta[-500:])
    assert 0.09 < r < 0.11
    if leak:  # measured 0.63 m/s, b tau = 0.68
        assert np.abs(error).max() < 1.2 * bank * leak
    else:  # measured 4.3 m/s, b / r = 3.4: 12 deg of beta for the whole curve
        assert np.abs(error).max() > 0.8 * bank / r


def test_k_kf_zeroes_vy_on_straights(vehicle):
    veh = cog_vehicle(vehicle)
    U, _ = single_track_ticks(veh, np.zeros(1000), ay_offset=0.3)
    OUT, _ = run(k_kf, U, veh)
    assert np.all(OUT[:, Out.VY] == 0.0)


# ---------------------------------------------------------------------------------------------
# robustness and the contract
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(METHODS))
def test_registry_loads_method_with_paper_defaults(name):
    method = registry.load(name)
    assert method.module is METHODS[name]
    assert method.params.shape == (len(METHODS[name].PARAMS),)
    own = [p for p in METHODS[name].PARAMS if not p.name.startswith("FRICTION__")]
    assert np.all(np.isfinite(method.params[own]))
    if name == "d_ekf":  # the friction estimator's params: hybrid_friction's defaults (NaN =
        # derived from the profile there)
        from slipd.estimators.carnier2023 import hybrid_friction

        nested = method.params[d_ekf._FRICTION_PARAMS :]
        assert nested.tobytes() == registry.make_params(hybrid_friction).tobytes()


@pytest.mark.parametrize("name", list(METHODS))
def test_invalid_and_non_finite_inputs_never_give_nan(name, vehicle):
    module = METHODS[name]
    t = np.arange(3000) * DT
    U, _ = single_track_ticks(vehicle, 0.03 * np.sin(2 * np.pi * 0.5 * t))
    rng = np.random.default_rng(1)
    dropped = rng.random((3000, 8)) < 0.2  # each core channel invalid on 20 % of the ticks
    for col, ch in enumerate((In.AX, In.AY, In.YAW_RATE, In.STEER, *WHEEL_SPEEDS)):
        U[dropped[:, col], VALID + ch] = 0.0
        U[dropped[:, col], ch] = np.nan  # an invalid channel may carry garbage
    U[1000:1100, VALID : VALID + 12] = 0.0  # a 1 s outage of everything
    U[1000:1100, :12] = np.inf
    U[:, VALID + In.ROLL_RATE] = U[:, VALID + In.PITCH_RATE] = 1.0  # used by the default
    U[::7, In.ROLL_RATE] = np.nan  # pre-processing, garbage included
    slipd_defaults = {key: module.DEFAULTS[key] for key in PAPER_PREPROCESSING}
    OUT, state = run(module, U, vehicle, slipd_defaults)
    assert np.all(np.isfinite(OUT[:, [Out.BETA, Out.BETA_RATE, Out.VX, Out.VY]]))
    assert np.all(np.isfinite(state[: rl.LAYOUT.size]))  # d_ekf's nested friction estimator:
    # hybrid_friction's own business (test_d_ekf_runs_hybrid_friction_as_alone)
    status = OUT[:, Out.STATUS].astype(int)
    assert np.all(status[dropped.any(axis=1)] & ST_INPUT_TIMEOUT)
    assert np.all(status[1000:1100] & ST_INPUT_TIMEOUT)
    assert np.abs(OUT[:, Out.BETA]).max() < 0.2


@pytest.mark.parametrize("name", list(METHODS))
def test_non_finite_state_resets_and_says_so(name, vehicle):
    module = METHODS[name]
    t = np.arange(400) * DT
    U, _ = single_track_ticks(vehicle, 0.03 * np.sin(2 * np.pi * 0.5 * t))
    params = registry.make_params(module, PAPER_PREPROCESSING)
    state = module.init(params, vehicle)
    OUT = np.zeros((400, N_OUT))
    module.run_ticks(state, U[:200], params, vehicle, DT, OUT[:200])
    state[S.DYN_P] = np.nan
    state[S.KIN_P + 2] = np.nan
    module.run_ticks(state, U[200:], params, vehicle, DT, OUT[200:])
    status = OUT[:, Out.STATUS].astype(int)
    assert status[200] & ST_RESET and status[200] & ST_NOT_CONVERGED
    assert not np.any(status[201:] & ST_RESET)
    assert np.all(np.isfinite(OUT[:, [Out.BETA, Out.VX, Out.VY, Out.SIGMA_BETA]][201:]))
    if module is not k_kf:  # k_kf's vy variance stays large at this low excitation
        assert np.all(status[-50:] == 0)  # converged again


@pytest.mark.parametrize("name", list(METHODS))
def test_standstill_and_start_up(name, vehicle):
    module = METHODS[name]
    U = np.zeros((600, U_LEN))
    for ch in (In.AX, In.AY, In.YAW_RATE, In.STEER, *WHEEL_SPEEDS):
        U[:, VALID + ch] = 1.0
    U[:50, VALID : VALID + 12] = 0.0  # nothing on the bus yet
    speed = np.clip((np.arange(600) - 200) * 0.05, 0.0, None)  # standing, then 5 m/s^2
    U[:, In.AX] = np.where(speed > 0, 5.0, 0.0)
    for ch in WHEEL_SPEEDS:
        U[:, ch] = speed
    OUT, _ = run(module, U, vehicle)
    status = OUT[:, Out.STATUS].astype(int)
    assert np.all(status[:250] & ST_NOT_CONVERGED)
    assert np.all(OUT[:250, Out.BETA] == 0.0)
    assert np.all(np.isfinite(OUT[:, [Out.BETA, Out.BETA_RATE, Out.VX, Out.VY]]))
    assert OUT[-1, Out.VX] == pytest.approx(speed[-1], abs=0.3)
    assert status[-1] == (ST_NOT_CONVERGED if module is k_kf else 0)  # k_kf: r = 0, vy unobservable
    if module is d_ekf:  # the friction its tyre model uses, once its estimator has settled
        mu = OUT[:, Out.MU][np.isfinite(OUT[:, Out.MU])]
        assert np.all(np.isnan(OUT[:250, Out.MU])) and np.all((mu > 0.0) & (mu < 1.5))
    else:
        assert np.all(np.isnan(OUT[:, Out.MU]))


def test_step_allocates_nothing():
    counts = allocations(METHODS, sine_drive_inputs(5000, 0.03, 0.2, 3.0), load_vehicle())
    assert set(counts) == set(METHODS)
    for name, (ticks_10, ticks_4980) in counts.items():
        # whatever the call itself costs (argument boxing), 4970 more ticks add nothing
        assert ticks_4980 == ticks_10, name


# ---------------------------------------------------------------------------------------------
# the simulator (CommonRoad multi-body plant, production-grade sensor errors)
# ---------------------------------------------------------------------------------------------

#: Beta RMS is taken where the true speed exceeds 20 km/h (the issue's evaluation rule).
MIN_EVAL_SPEED = 20.0 / 3.6


@functools.cache
def simulated(scenario: str, seed: int = 0) -> tuple[dict, np.ndarray]:
    from slipd.sim import simulate

    result = simulate(scenario, vehicle=2, seed=seed)
    return result.truth, result.ticks()


def simulated_outputs(name: str, scenario: str, seed: int = 0) -> tuple[np.ndarray, dict, int]:
    """(OUT, truth, n) of method ``name`` with its defaults on ``scenario``."""
    truth, U = simulated(scenario, seed)
    vehicle = load_vehicle()
    method = registry.load(name)
    state = method.init(vehicle)
    OUT = np.zeros((U.shape[0], N_OUT))
    method.run_ticks(state, U, method.params, vehicle, DT, OUT)
    return OUT, truth, min(U.shape[0], truth["t"].size)


def beta_rms_deg(name: str, scenario: str, seed: int = 0) -> float:
    OUT, truth, n = simulated_outputs(name, scenario, seed)
    fast = np.hypot(truth["vx"][:n], truth["vy"][:n]) > MIN_EVAL_SPEED
    error = OUT[:n, Out.BETA][fast] - truth["beta"][:n][fast]
    return float(np.degrees(np.sqrt(np.mean(error**2))))


@pytest.mark.parametrize("scenario", ["double_lane_change", "slalom"])
def test_dk_ekf_beats_both_baselines_on_the_table_2_manoeuvres(scenario):
    """Table 2: DK-EKF 0.27 / 0.22 deg vs D-EKF 0.40 / 0.33 and K-KF 0.60 / 0.33 (DLC / slalom);
    the issue asks <= 0.5 deg and better than both baselines."""
    rms = {name: beta_rms_deg(name, scenario) for name in METHODS}
    assert rms["dk_ekf"] <= 0.5, rms
    assert rms["dk_ekf"] < rms["d_ekf"], rms
    assert rms["dk_ekf"] < rms["k_kf"], rms


def test_d_ekf_slip_friction_follows_a_snow_drift_and_leaves_a_dry_road_alone():
    """slip_friction (d_ekf's docstring): on the snow drift (mu 0.3 against the profile's 1.05)
    eq. 7 with the friction of hybrid_friction's classifier halves the paper's error (measured
    here 1.93 against 3.99 deg; through the codec 1.88 / 2.01 against 3.99 / 3.96 on seeds 0 /
    1), and reports that friction (median 0.28 over the last 5 s); on a dry lane change, where
    the classifier keeps the profile's friction, beta is the paper's filter's (measured:
    identical)."""
    snow = beta_rms_deg("d_ekf", "snow_drift")
    paper = beta_rms_deg("d_ekf:slip_friction=0", "snow_drift")
    assert snow <= 2.2 and paper - snow >= 1.5, (snow, paper)
    OUT, _, _ = simulated_outputs("d_ekf", "snow_drift")
    reported = OUT[-500:, Out.MU]  # the drift's last 5 s
    assert np.nanmedian(reported) == pytest.approx(0.3, abs=0.1)
    dry, truth, n = simulated_outputs("d_ekf", "double_lane_change")
    dry_paper, _, _ = simulated_outputs("d_ekf:slip_friction=0", "double_lane_change")
    difference = np.degrees(dry[:n, Out.BETA] - dry_paper[:n, Out.BETA])
    assert np.sqrt(np.mean(difference**2)) < 0.01
    assert np.all(np.isnan(dry_paper[:, Out.MU]))


def test_d_ekf_without_the_friction_estimators_vehicle_data_says_so(vehicle):
    """hybrid_friction needs the CoG height and wheel radius, which the paper's D-EKF does
    not: a profile without them fails naming d_ekf's parameter, and the paper's filter runs."""
    from slipd.errors import ConfigError

    no_height = vehicle.copy()
    no_height[Veh.H_COG] = np.nan
    with pytest.raises(ConfigError, match=r"d_ekf's friction estimator .*h_cog.*slip_friction=0"):
        registry.load("d_ekf").init(no_height)
    registry.load("d_ekf:slip_friction=0").init(no_height)


def test_d_ekf_runs_hybrid_friction_as_alone(vehicle):
    """The friction estimator nested in d_ekf is hybrid_friction's kernel on the same inputs:
    its state and outputs equal the method's run alone, bit for bit (and MU is what d_ekf
    reports while it is settled)."""
    _, U = simulated("snow_drift")
    U = U[:1500]
    method = registry.load("d_ekf")
    state = method.init(vehicle)
    OUT = np.zeros((U.shape[0], N_OUT))
    method.run_ticks(state, U, method.params, vehicle, DT, OUT)
    alone = registry.load("hybrid_friction")
    alone_state = alone.init(vehicle)
    ALONE = np.zeros((U.shape[0], N_OUT))
    alone.run_ticks(alone_state, U, alone.params, vehicle, DT, ALONE)
    nested = state[d_ekf.LAYOUT.span("FRICTION")]
    assert nested.tobytes() == alone_state.tobytes()
    assert state[d_ekf.LAYOUT.span("FRICTION_OUT")].tobytes() == ALONE[-1].tobytes()
    reported = np.isfinite(OUT[:, Out.MU])
    assert reported.mean() > 0.5
    np.testing.assert_array_equal(OUT[reported, Out.MU], ALONE[reported, Out.MU])


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["double_lane_change", "slalom"])
def test_table_2_ranking_over_sensor_seeds(scenario):
    """The ranking is not an accident of one noise draw: over 8 sensor seeds (each its own
    offsets, drifts, misalignment) dk_ekf stays <= 0.5 deg and is the best of the three in at
    least 6 (measured: 7/8 on both; mean 0.112 vs d_ekf 0.131 vs k_kf 0.279 deg on the lane
    change, 0.152 vs 0.159 vs 0.300 on the slalom; the one loss each is to d_ekf)."""
    seeds = range(8)
    rms = {name: np.array([beta_rms_deg(name, scenario, s) for s in seeds]) for name in METHODS}
    assert np.all(rms["dk_ekf"] <= 0.5)
    best = (rms["dk_ekf"] < rms["d_ekf"]) & (rms["dk_ekf"] < rms["k_kf"])
    assert best.sum() >= 6, rms
    assert rms["dk_ekf"].mean() < rms["k_kf"].mean()


def suite_scenarios() -> list[str]:
    from slipd.sim import SCENARIOS

    return list(SCENARIOS)


#: Scenarios that leave the single-track models' domain on purpose (a held drift beyond 30 deg):
#: only finite outputs within the reset rule's bound are asked there.
OUT_OF_DOMAIN = {"snow_drift"}


@pytest.mark.slow
@pytest.mark.parametrize("scenario", suite_scenarios())
def test_no_nan_or_divergence_over_the_suite(scenario):
    from slipd.sim.plant import SimulationError

    try:
        simulated(scenario)
    except SimulationError as exc:  # the plant's failure is the simulator tests' business
        pytest.skip(f"the simulator cannot run {scenario}: {exc}")
    for name in METHODS:
        OUT, truth, n = simulated_outputs(name, scenario)
        values = OUT[:, [Out.BETA, Out.BETA_RATE, Out.VX, Out.VY, Out.SIGMA_BETA, Out.STATUS]]
        assert np.all(np.isfinite(values)), name
        assert np.all(np.abs(OUT[:, Out.BETA]) <= math.pi / 4), name  # the reset rule's bound
        if name == "k_kf" or scenario in OUT_OF_DOMAIN:
            continue  # k_kf drifts by design where vy is unobservable (Sec. 2.3)
        in_domain = (np.hypot(truth["vx"][:n], truth["vy"][:n]) > MIN_EVAL_SPEED) & (
            np.abs(truth["beta"][:n]) < math.radians(10.0)
        )
        error = np.degrees(np.abs(OUT[:n, Out.BETA] - truth["beta"][:n]))[in_domain]
        assert error.max() < 5.0, (name, error.max())
        assert not np.any(OUT[:n, Out.STATUS].astype(int)[in_domain] & ST_RESET), name
