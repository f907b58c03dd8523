"""``linear_kf``, the classic linear single-track Kalman filter: against a plain numpy twin of
the textbook filter, on the model it assumes, and as a floor on the simulator."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slipd.channels import (
    N_IN,
    N_OUT,
    ST_INPUT_TIMEOUT,
    ST_NOT_CONVERGED,
    ST_RESET,
    U_LEN,
    VALID,
    WHEEL_SPEEDS,
    In,
    Out,
    Veh,
)
from slipd.estimators import linear_kf, registry

DT = 0.01


@pytest.fixture(scope="module")
def car(vehicle) -> np.ndarray:
    """The default car with its IMU at the CoG (the twin needs no lever arm)."""
    v = vehicle.copy()
    v[[Veh.IMU_X, Veh.IMU_Y, Veh.IMU_Z]] = 0.0
    return v


def matrices(vx: float, v: np.ndarray):
    m, iz, a, b = v[Veh.MASS], v[Veh.YAW_INERTIA], v[Veh.LF], v[Veh.LR]
    cf, cr = v[Veh.CORNERING_STIFFNESS_F], v[Veh.CORNERING_STIFFNESS_R]
    A = np.array([[-(cf + cr) / (m * vx), -vx - (cf * a - cr * b) / (m * vx)],
                  [-(cf * a - cr * b) / (iz * vx), -(cf * a * a + cr * b * b) / (iz * vx)]])
    B = np.array([cf / m, cf * a / iz])
    C = np.array([[-(cf + cr) / (m * vx), -(cf * a - cr * b) / (m * vx)], [0.0, 1.0]])
    D = np.array([cf / m, 0.0])
    return A, B, C, D


def single_track_drive(v: np.ndarray, n: int, speed: float = 20.0, seed: int = 0):
    """The linear model itself driven by a sine steer, its measurements with sensor noise:
    (U, true vy)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    steer = 0.02 * np.sin(2 * math.pi * 0.4 * t)
    x = np.zeros(2)
    U = np.zeros((n, U_LEN))
    vy = np.zeros(n)
    for k in range(n):
        A, B, C, D = matrices(speed, v)
        y = C @ x + D * steer[k]
        U[k, In.AY] = y[0] + rng.normal(0.0, 0.02)
        U[k, In.YAW_RATE] = y[1] + rng.normal(0.0, math.radians(0.08))
        vy[k] = x[0]
        x = x + (A @ x + B * steer[k]) * DT
    U[:, In.STEER] = steer
    for ch in WHEEL_SPEEDS:
        U[:, ch] = speed
    # the front wheels roll along their steer and every wheel sees its yaw motion
    half_f, half_r = 0.5 * v[Veh.TRACK_F], 0.5 * v[Veh.TRACK_R]
    r = U[:, In.YAW_RATE]
    U[:, In.WHEEL_SPEED_FL] = (speed - half_f * r) / np.cos(steer)
    U[:, In.WHEEL_SPEED_FR] = (speed + half_f * r) / np.cos(steer)
    U[:, In.WHEEL_SPEED_RL] = speed - half_r * r
    U[:, In.WHEEL_SPEED_RR] = speed + half_r * r
    U[:, VALID : VALID + N_IN] = 1.0
    return U, vy


def twin(U: np.ndarray, v: np.ndarray, params: np.ndarray) -> np.ndarray:
    """The textbook linear KF (Rajamani's model, Euler step, Q = G q G', Joseph update) in numpy;
    returns [vy, r, P_vv] per tick once running (NaN while held)."""
    p = {f.name: params[f] for f in linear_kf.PARAMS}
    R = np.diag([p["SIGMA_AY"] ** 2, p["SIGMA_YAW_RATE"] ** 2])
    q = (p["SIGMA_STEER_WHEEL"] / v[Veh.STEER_RATIO]) ** 2
    half_f, half_r = 0.5 * v[Veh.TRACK_F], 0.5 * v[Veh.TRACK_R]
    result = np.full((len(U), 3), np.nan)
    x = P = prev_steer = prev_vx = None
    for k, u in enumerate(U):
        steer, r_meas, ay = u[In.STEER], u[In.YAW_RATE], u[In.AY]
        cos = math.cos(steer)
        vx = np.mean([u[In.WHEEL_SPEED_FL] * cos + half_f * r_meas,
                      u[In.WHEEL_SPEED_FR] * cos - half_f * r_meas,
                      u[In.WHEEL_SPEED_RL] + half_r * r_meas,
                      u[In.WHEEL_SPEED_RR] - half_r * r_meas])
        if x is None:
            x, P = np.array([0.0, r_meas]), np.diag([p["P0_VY"], p["P0_R"]])
            prev_steer, prev_vx = steer, vx
            continue
        A, B, _, _ = matrices(prev_vx, v)
        F, G = np.eye(2) + A * DT, B * DT
        x = F @ x + G * prev_steer
        P = F @ P @ F.T + q * np.outer(G, G)
        _, _, C, D = matrices(vx, v)
        S = C @ P @ C.T + R
        K = P @ C.T @ np.linalg.inv(S)
        x = x + K @ (np.array([ay, r_meas]) - C @ x - D * steer)
        J = np.eye(2) - K @ C
        P = J @ P @ J.T + K @ R @ K.T
        prev_steer, prev_vx = steer, vx
        result[k] = x[0], x[1], P[0, 0]
    return result


def run(U, v, overrides=None):
    method = registry.load("linear_kf", overrides)
    state = method.init(v)
    OUT = np.zeros((len(U), N_OUT))
    vy = np.full(len(U), np.nan)
    for k in range(len(U)):
        method.step(state, U[k], method.params, v, DT, OUT[k])
        vy[k] = state[linear_kf.S.VY]
    return OUT, vy, state, method.params


def test_the_kernel_is_the_textbook_filter(car):
    U, _ = single_track_drive(car, 1500)
    OUT, vy, _, params = run(U, car)
    ref = twin(U, car, params)
    running = np.isfinite(ref[:, 0])
    assert running[1:].all()
    np.testing.assert_allclose(vy[running], ref[running, 0], rtol=1e-9, atol=1e-12)
    vx = OUT[running, Out.VX]
    np.testing.assert_allclose(OUT[running, Out.BETA], np.arctan2(ref[running, 0], vx),
                               rtol=1e-9, atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(OUT[running, Out.SIGMA_BETA],
                               np.sqrt(ref[running, 2]) * vx / (vx**2 + ref[running, 0] ** 2),
                               rtol=1e-8)  # fmt: skip


def test_it_tracks_the_model_it_assumes_and_settles(car):
    U, vy_true = single_track_drive(car, 3000, seed=1)
    OUT, vy, _, _ = run(U, car)
    late = slice(1000, None)
    assert np.sqrt(np.mean((vy[late] - vy_true[late]) ** 2)) < 0.01  # m/s
    status = OUT[:, Out.STATUS].astype(int)
    assert np.all(status[:50] & ST_NOT_CONVERGED) and np.all(status[late] == 0)
    assert np.all(np.isnan(OUT[:, Out.MU])) and np.all(OUT[:, Out.FRICTION_CLASS] == 0)


def test_missing_inputs_hold_and_say_so(car):
    U, _ = single_track_drive(car, 1200, seed=2)
    U[400:450, VALID + In.AY] = 0.0
    U[400:450, In.AY] = np.nan
    U[600:620, VALID + In.WHEEL_SPEED_RL] = 0.0
    OUT, _, state, _ = run(U, car)
    status = OUT[:, Out.STATUS].astype(int)
    assert np.all(status[400:450] & ST_INPUT_TIMEOUT) and np.all(status[600:620] & ST_INPUT_TIMEOUT)
    assert np.all(np.isfinite(OUT[:, [Out.BETA, Out.BETA_RATE, Out.VX, Out.VY, Out.SIGMA_BETA]]))
    # standstill: held at beta 0, not converged
    U[900:, [*WHEEL_SPEEDS]] = 0.0
    OUT, _, _, _ = run(U, car)
    assert np.all(OUT[900:, Out.BETA] == 0.0)
    assert np.all(OUT[900:, Out.STATUS].astype(int) & ST_NOT_CONVERGED)


def test_a_non_finite_state_resets_and_says_so(car):
    U, _ = single_track_drive(car, 400, seed=3)
    method = registry.load("linear_kf")
    state = method.init(car)
    out = np.zeros(N_OUT)
    for k in range(300):
        method.step(state, U[k], method.params, car, DT, out)
    state[linear_kf.S.VY] = np.inf
    method.step(state, U[300], method.params, car, DT, out)
    assert int(out[Out.STATUS]) & ST_RESET and out[Out.BETA] == 0.0
    method.step(state, U[301], method.params, car, DT, out)
    assert np.isfinite(out[Out.BETA]) and not int(out[Out.STATUS]) & ST_RESET


def test_it_is_a_floor_between_zero_and_the_papers_on_the_codec_drives(codec_drives, profile):
    """On the step steer (dry, within the linear range) it must beat beta = 0; it is the
    classic baseline, not expected to beat the seed methods."""
    from slipd.pipeline import Pipeline
    from slipd.sim.writer import START_EPOCH

    drive = codec_drives["step_steer"]
    t = drive.truth["t"] + START_EPOCH  # the log's time axis
    beta_true = np.interp(drive.inputs.t, t, drive.truth["beta"])
    fast = np.interp(drive.inputs.t, t, drive.truth["speed"]) > 20 / 3.6
    rms = {}
    for name in ("zero", "linear_kf"):
        out = Pipeline(name, profile).run(drive.inputs.U)
        rms[name] = np.degrees(np.sqrt(np.mean((out[fast, Out.BETA] - beta_true[fast]) ** 2)))
    assert rms["linear_kf"] < 0.6 * rms["zero"], rms
