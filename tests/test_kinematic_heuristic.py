"""Tests of the Selmanaj kinematic observer ``kinematic_heuristic``.

Synthetic rigid-body manoeuvres check the observer exactly where the kinematic model holds;
the simulator suite (``slipd.sim``) checks the paper's claims on an independent plant.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from slipd.channels import (
    N_IN,
    N_OUT,
    N_VEH,
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
from slipd.estimators.registry import load, make_params
from slipd.estimators.selmanaj2017 import kinematic_heuristic as kh

DT = 0.01
REPO = Path(__file__).resolve().parents[1]


def bmw_vehicle() -> np.ndarray:
    """The profile's vehicle vector if the profile loads, else the BMW 320i numbers."""
    try:
        from slipd.profile import load_profile

        return np.asarray(load_profile("default").vehicle, dtype=np.float64)
    except Exception:  # profile not available in this checkout: same numbers by hand
        v = np.zeros(N_VEH)
        v[Veh.MASS], v[Veh.YAW_INERTIA], v[Veh.ROLL_INERTIA] = 1093.3, 1791.6, 207.3
        v[Veh.LF], v[Veh.LR], v[Veh.TRACK_F], v[Veh.TRACK_R] = 1.156, 1.423, 1.387, 1.364
        v[Veh.H_COG], v[Veh.H_ROLL_AXIS], v[Veh.WHEEL_RADIUS] = 0.575, 0.575, 0.344
        v[Veh.STEER_RATIO], v[Veh.ROLL_STIFFNESS], v[Veh.ROLL_DAMPING] = 16.0, 41780.0, 3250.0
        return v


#: The paper's input pre-processing (the steady hold tested alone): eq. 16's roll model with
#: the profile's roll data, no vibration low-pass.
PAPER_INPUTS = {"roll_gain_learning": 0.0, "accel_lowpass_hz": 0.0}


def run(U: np.ndarray, overrides: dict[str, float] | None = None, vehicle=None) -> np.ndarray:
    vehicle = bmw_vehicle() if vehicle is None else vehicle
    params = make_params(kh, overrides)
    state = kh.init(params, vehicle)
    OUT = np.zeros((U.shape[0], N_OUT))
    kh.run_ticks(state, U, params, vehicle, DT, OUT)
    return OUT


def rigid_body_inputs(vx, vy, yaw_rate, steer, vehicle, ay_offset=0.0, yaw_offset=0.0):
    """Inputs of a planar rigid body with the IMU at the CoG, no roll, no tyre slip on the
    wheels (rear wheels roll along x, front along their steer): the kinematic model (eq. 1)
    holds exactly, so the observer has nothing to be wrong about but its own dynamics."""
    n = len(vx)
    vx_dot = np.gradient(vx, DT)
    vy_dot = np.gradient(vy, DT)
    U = np.zeros((n, U_LEN))
    U[:, VALID : VALID + N_IN] = 1.0
    U[:, U_TIME] = np.arange(n) * DT
    U[:, In.AX] = vx_dot - yaw_rate * vy  # eq. 1
    U[:, In.AY] = vy_dot + yaw_rate * vx + ay_offset
    U[:, In.AZ] = G
    U[:, In.YAW_RATE] = yaw_rate + yaw_offset
    U[:, In.STEER] = steer
    half_f, half_r = 0.5 * vehicle[Veh.TRACK_F], 0.5 * vehicle[Veh.TRACK_R]
    U[:, In.WHEEL_SPEED_FL] = (vx - yaw_rate * half_f) / np.cos(steer)
    U[:, In.WHEEL_SPEED_FR] = (vx + yaw_rate * half_f) / np.cos(steer)
    U[:, In.WHEEL_SPEED_RL] = vx - yaw_rate * half_r
    U[:, In.WHEEL_SPEED_RR] = vx + yaw_rate * half_r
    return U


def imu_at_cog(vehicle: np.ndarray) -> np.ndarray:
    v = vehicle.copy()
    v[Veh.IMU_X] = v[Veh.IMU_Y] = v[Veh.IMU_Z] = 0.0
    v[Veh.ROLL_STIFFNESS] = 0.0  # no roll model: the rigid body does not roll
    return v


# --------------------------------------------------------------------------- synthetic


def test_registered_and_defaults_are_table_1() -> None:
    method = load("kinematic_heuristic")
    assert method.module is kh
    p = method.params
    assert (p[kh.PARAMS.ALPHA_0], p[kh.PARAMS.ALPHA_1], p[kh.PARAMS.ALPHA_2]) == (10, 5, 10)
    assert p[kh.PARAMS.SIGMA_YAW_RATE] == 0.18 and p[kh.PARAMS.SIGMA_BETA_RATE] == 0.06
    assert p[kh.PARAMS.AX_THRESHOLD] == 1.0 and p[kh.PARAMS.SIGMA_W1] == 4.5
    assert kh.TABLE_1["sigma_yaw_acc"] == 0.18 and kh.TABLE_1["sigma_beta_acc"] == 0.3
    # The only departures from Table 1: the eq. 7 derivative widths, set by the paper's
    # noise rule (section 2.1) for this profile's sensors (module docstring).
    differ = {k for k, v in kh.TABLE_1.items() if kh.DEFAULTS[k] != v}
    assert differ == {"sigma_yaw_acc", "sigma_steer_rate", "sigma_beta_acc"}


def _noisy_straight(vehicle, ay_offset, seed=1):
    """60 s straight at 20 m/s with the default profile's sensor noise (0.1 deg steering-wheel
    angle, 0.08 deg/s gyro, 0.02 m/s^2 accelerometer, white at 100 Hz) and an ay offset."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 60.0, DT)
    zeros = np.zeros_like(t)
    U = rigid_body_inputs(np.full_like(t, 20.0), zeros, zeros, zeros, vehicle, ay_offset=ay_offset)
    U[:, In.STEER] += rng.normal(0.0, math.radians(0.1), len(t)) / vehicle[Veh.STEER_RATIO]
    U[:, In.YAW_RATE] += rng.normal(0.0, math.radians(0.08), len(t))
    U[:, In.AY] += rng.normal(0.0, 0.02, len(t))
    U[:, In.AX] += rng.normal(0.0, 0.02, len(t))
    return t, U


def _mean_f(U, overrides, vehicle) -> float:
    params = make_params(kh, overrides)
    state = kh.init(params, vehicle)
    out = np.zeros((1, N_OUT))
    f = np.zeros(len(U))
    for k in range(len(U)):
        kh.run_ticks(state, U[k : k + 1], params, vehicle, DT, out)
        f[k] = state[kh.S.F]
    return float(np.mean(f[len(U) // 6 :]))


def test_sensor_noise_does_not_switch_the_heuristic_off_on_a_straight() -> None:
    # Issue 4 (handling_low_mu): with Table 1's derivative widths the 10 Hz derivatives of
    # the noisy steering-wheel angle, yaw rate and ay kept F near 0.3 of F_max on straights,
    # so an ay bias integrated into vy (vy ~ ay_offset / F). Section 2.1's rule (bells wider
    # than the noise) keeps F ~ F_max. Measured (seed 1): mean F 0.89 with the defaults,
    # 0.48 with Table 1; mean |beta| 0.44 vs 0.83 deg.
    vehicle = imu_at_cog(bmw_vehicle())
    t, U = _noisy_straight(vehicle, ay_offset=0.15)
    table_1 = dict(kh.TABLE_1, accel_lowpass_hz=0.0)  # the paper: no vibration low-pass
    assert _mean_f(U, None, vehicle) > 0.8
    assert _mean_f(U, table_1, vehicle) < 0.6
    late = t > 10.0
    beta_default = np.degrees(np.abs(run(U, vehicle=vehicle)[late, Out.BETA]))
    beta_table_1 = np.degrees(np.abs(run(U, table_1, vehicle=vehicle)[late, Out.BETA]))
    assert np.mean(beta_default) < 0.5
    assert np.mean(beta_table_1) > 1.5 * np.mean(beta_default)


def test_tracks_a_transient_cornering_sideslip_of_a_rigid_body() -> None:
    # Slalom-like: yaw rate and vy oscillate at 0.5 Hz, beta up to ~3 deg at 20 m/s.
    vehicle = imu_at_cog(bmw_vehicle())
    t = np.arange(0.0, 20.0, DT)
    w = 2 * math.pi * 0.5
    on = np.clip(t - 2.0, 0.0, 1.0)
    yaw_rate = 0.4 * on * np.sin(w * t)
    vy = -1.0 * on * np.sin(w * t - 0.5)
    vx = np.full_like(t, 20.0)
    steer = 0.03 * on * np.sin(w * t + 0.2)
    OUT = run(rigid_body_inputs(vx, vy, yaw_rate, steer, vehicle), vehicle=vehicle)
    beta_true = np.arctan2(vy, vx)
    err = OUT[:, Out.BETA] - beta_true
    assert np.degrees(np.sqrt(np.mean(err[t > 5.0] ** 2))) < 0.3
    assert np.allclose(OUT[t > 5.0, Out.VX], 20.0, atol=0.05)


def test_heuristic_holds_beta_on_a_straight_with_an_ay_offset_pure_kinematics_drifts() -> None:
    vehicle = imu_at_cog(bmw_vehicle())
    t = np.arange(0.0, 60.0, DT)
    zeros = np.zeros_like(t)
    U = rigid_body_inputs(np.full_like(t, 25.0), zeros, zeros, zeros, vehicle, ay_offset=0.15)
    with_f = np.degrees(run(U, vehicle=vehicle)[:, Out.BETA])
    pure = {"f_gain": 0.0, "steady_gain": 0.0}  # eq. 5 with F = 0 and no steady-state hold
    without_f = np.degrees(run(U, pure, vehicle=vehicle)[:, Out.BETA])
    # Heuristic: vy settles at ay_offset / F = 0.15 m/s -> 0.34 deg, then the ay-offset
    # estimator slowly removes even that. Pure kinematics: vy = 0.15 t -> > 15 deg at 60 s.
    assert np.max(np.abs(with_f)) < 0.4
    assert abs(without_f[-1]) > 15.0


def _banked_steady_corner(vehicle, bias=0.5, yaw_rate_max=0.25, steer_sign=1.0):
    """10 s straight, 2 s turn-in, 48 s steady corner at 20 m/s of a rigid body (true vy = 0)
    whose ay carries a bias that ramps in with the corner, like a banked curve's g sin(bank)."""
    t = np.arange(0.0, 60.0, DT)
    on = np.clip((t - 10.0) / 2.0, 0.0, 1.0)
    vx = np.full_like(t, 20.0)
    yaw_rate = yaw_rate_max * on
    wheelbase = vehicle[Veh.LF] + vehicle[Veh.LR]
    steer = steer_sign * wheelbase * yaw_rate / vx  # kinematic steer (countersteer if < 0)
    U = rigid_body_inputs(vx, np.zeros_like(t), yaw_rate, steer, vehicle, ay_offset=bias * on)
    return t, U


def test_steady_hold_bounds_the_vy_ramp_of_an_ay_bias_in_a_steady_corner() -> None:
    vehicle = imu_at_cog(bmw_vehicle())
    t, U = _banked_steady_corner(vehicle)
    beta_on = np.degrees(run(U, PAPER_INPUTS, vehicle=vehicle)[:, Out.BETA])
    beta_paper = np.degrees(run(U, {**PAPER_INPUTS, "steady_gain": 0.0},
                                vehicle=vehicle)[:, Out.BETA])
    # Paper (eq. 8, F ~ 0): e_y -> (a0 + a1 w) b / ((a2 + 1) w^2) = 8 m/s (~22 deg) with a
    # 16 s time constant: > 10 deg after 48 s. Extension: the turn-in is a transient (bias
    # integrated, ~1.5 deg), then the hold stops the ramp, the bias is learnt and the a2
    # correction brings the estimate back.
    assert np.max(np.abs(beta_paper[t > 40.0])) > 10.0
    assert np.max(np.abs(beta_on)) < 2.0
    assert np.max(np.abs(beta_on[t > 55.0])) < 0.5


def test_steady_bias_of_a_banked_corner_fades_on_the_straight_before_a_flat_one() -> None:
    # A banked left corner (ay bias 0.5 m/s^2, learnt as the steady bias), 2 s of straight,
    # then a flat right corner: the bank is the first corner's, not the road's. Held (the
    # bias time constant alone, forget = 0) it is subtracted through the second turn-in
    # (1.33 deg off); faded on the straight with F it is gone before the turn-in (0.24 deg).
    vehicle = imu_at_cog(bmw_vehicle())
    t = np.arange(0.0, 70.0, DT)

    def ramp(start, end):
        return np.clip((t - start) / (end - start), 0.0, 1.0)

    banked = ramp(10.0, 12.0) - ramp(32.0, 34.0)
    flat = ramp(36.0, 38.0) - ramp(66.0, 68.0)
    yaw_rate = 0.25 * (banked - flat)
    vx = np.full_like(t, 20.0)
    steer = (vehicle[Veh.LF] + vehicle[Veh.LR]) * yaw_rate / vx
    U = rigid_body_inputs(vx, np.zeros_like(t), yaw_rate, steer, vehicle, ay_offset=0.5 * banked)
    held = np.degrees(run(U, {**PAPER_INPUTS, "steady_bias_straight_forget": 0.0},
                          vehicle=vehicle)[:, Out.BETA])
    faded = np.degrees(run(U, PAPER_INPUTS, vehicle=vehicle)[:, Out.BETA])
    second = t > 36.0
    assert np.max(np.abs(held[second])) > 1.0
    assert np.max(np.abs(faded[second])) < 0.4
    assert np.max(np.abs(faded[t < 34.0])) < 2.0  # the banked corner itself as before


def test_steady_jerk_bell_widens_to_a_vibrating_accelerometers_noise() -> None:
    # The banked steady corner with 1 m/s^2 of white vibration on ay (a raw IMU's, as on the
    # real revs_250lm run): through the 5 Hz low-pass and the detector's 1 Hz derivative the
    # jerk on the 10 s straight is ~0.3 m/s^3 RMS, whose peaks keep knocking the fixed 3.2
    # m/s^3 bell shut, so the hold flickers and the bias ramps in (3.0 deg); the width at 12 x
    # the noise measured on the straight lets it hold (1.65 deg).
    vehicle = imu_at_cog(bmw_vehicle())
    t, U = _banked_steady_corner(vehicle)
    U[:, In.AY] += np.random.default_rng(3).standard_normal(len(t))
    inputs = {"roll_gain_learning": 0.0}
    fixed = np.degrees(run(U, {**inputs, "steady_jerk_noise_width": 0.0},
                           vehicle=vehicle)[:, Out.BETA])
    params = make_params(kh, inputs)
    state = kh.init(params, vehicle)
    OUT = np.zeros((U.shape[0], N_OUT))
    kh.run_ticks(state, U, params, vehicle, DT, OUT)
    widened = np.degrees(OUT[:, Out.BETA])
    assert np.isfinite(state[kh.S.JERK_NOISE])
    assert 12.0 * math.sqrt(state[kh.S.JERK_NOISE]) > params[kh.PARAMS.SIGMA_STEADY_JERK]
    assert np.max(np.abs(fixed)) > 2.5
    assert np.max(np.abs(widened)) < 2.0


def test_steady_hold_is_off_in_a_countersteered_drift() -> None:
    # The same steady (Ay - omega_z Vx), but steering against the yaw rate: a drift, whose slow
    # sideslip change is real. The hold must let the observer integrate it (as the paper).
    vehicle = imu_at_cog(bmw_vehicle())
    t, U = _banked_steady_corner(vehicle, steer_sign=-1.0)
    beta_on = np.degrees(run(U, PAPER_INPUTS, vehicle=vehicle)[:, Out.BETA])
    beta_paper = np.degrees(run(U, {**PAPER_INPUTS, "steady_gain": 0.0},
                                vehicle=vehicle)[:, Out.BETA])
    assert abs(beta_paper[-1]) > 15.0
    assert np.allclose(beta_on, beta_paper, atol=0.5)


def test_steady_gain_zero_is_the_paper() -> None:
    vehicle = bmw_vehicle()
    t, U = _banked_steady_corner(vehicle)
    params = make_params(kh, {"steady_gain": 0.0})
    state = kh.init(params, vehicle)
    OUT = np.zeros((U.shape[0], N_OUT))
    kh.run_ticks(state, U, params, vehicle, DT, OUT)
    assert state[kh.S.STEADY] == 0.0 and state[kh.S.STEADY_BIAS] == 0.0


def test_status_not_converged_at_start_then_clear() -> None:
    vehicle = bmw_vehicle()
    t = np.arange(0.0, 5.0, DT)
    zeros = np.zeros_like(t)
    OUT = run(rigid_body_inputs(np.full_like(t, 10.0), zeros, zeros, zeros, vehicle))
    status = OUT[:, Out.STATUS].astype(int)
    settle = kh.DEFAULTS["settle_time"]
    assert np.all(status[t < settle - 2 * DT] & ST_NOT_CONVERGED)
    assert np.all(status[t > settle + 2 * DT] == 0)
    assert np.all(np.isnan(OUT[:, Out.MU])) and np.all(np.isnan(OUT[:, Out.NIS]))  # no filter
    assert np.all(np.isfinite(np.delete(OUT, [Out.MU, Out.NIS], axis=1)))


def test_invalid_imu_is_held_not_integrated_and_flagged() -> None:
    vehicle = bmw_vehicle()
    t = np.arange(0.0, 6.0, DT)
    zeros = np.zeros_like(t)
    U = rigid_body_inputs(np.full_like(t, 15.0), zeros, zeros, zeros, vehicle)
    gap = (t >= 3.0) & (t < 4.0)
    U[gap, In.AY] = 1e6  # garbage behind an invalid flag
    U[gap, In.YAW_RATE] = np.nan
    U[gap, VALID + In.AY] = 0.0
    U[gap, VALID + In.YAW_RATE] = 0.0
    OUT = run(U)
    k0 = np.argmax(gap)
    assert np.all(OUT[gap, Out.VY] == OUT[k0 - 1, Out.VY])
    assert np.all(OUT[gap, Out.STATUS].astype(int) & ST_INPUT_TIMEOUT)
    assert np.all(np.isfinite(OUT[:, Out.BETA])) and np.max(np.abs(OUT[:, Out.BETA])) < 1e-3


def test_lost_wheel_speeds_run_open_loop_and_lost_steer_is_held() -> None:
    vehicle = bmw_vehicle()
    t = np.arange(0.0, 6.0, DT)
    zeros = np.zeros_like(t)
    vx = 15.0 + 0.5 * t  # accelerating at 0.5 m/s^2
    U = rigid_body_inputs(vx, zeros, zeros, zeros, vehicle)
    gap = (t >= 3.0) & (t < 4.0)
    for ch in WHEEL_SPEEDS:
        U[gap, ch] = 0.0
        U[gap, VALID + ch] = 0.0
    U[gap, VALID + In.STEER] = 0.0
    U[gap, In.STEER] = 1e3
    OUT = run(U)
    # Integrating ax alone keeps vx on the ramp through the 1 s outage.
    assert np.max(np.abs(OUT[gap, Out.VX] - vx[gap])) < 0.05
    assert np.max(np.abs(np.degrees(OUT[:, Out.BETA]))) < 0.05


def test_non_finite_state_resets_and_says_so() -> None:
    vehicle = bmw_vehicle()
    params = make_params(kh)
    state = kh.init(params, vehicle)
    t = np.arange(0.0, 1.0, DT)
    zeros = np.zeros_like(t)
    U = rigid_body_inputs(np.full_like(t, 10.0), zeros, zeros, zeros, vehicle)
    out = np.zeros(N_OUT)
    kh.step(state, U[0], params, vehicle, DT, out)
    state[kh.S.VY_HAT] = np.nan
    kh.step(state, U[1], params, vehicle, DT, out)
    assert int(out[Out.STATUS]) & ST_RESET
    assert np.isfinite(out[Out.BETA]) and np.isfinite(out[Out.VX])


# --------------------------------------------------------------------------- numba


def _run_script(code: str, env_extra: dict[str, str]) -> str:
    env = dict(os.environ)
    env.update(env_extra)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        cwd=REPO,
    )
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.strip().splitlines()[-1]


_ALLOC_SCRIPT = """
import numpy as np
from numba.core.runtime import rtsys
from slipd.channels import N_OUT, U_LEN, VALID, N_IN, U_TIME, In, WHEEL_SPEEDS, N_VEH, Veh
from slipd.estimators.selmanaj2017 import kinematic_heuristic as kh
from slipd.estimators.registry import make_params

vehicle = np.zeros(N_VEH)
vehicle[Veh.MASS], vehicle[Veh.H_ROLL_AXIS], vehicle[Veh.ROLL_STIFFNESS] = 1093.3, 0.57, 41780.0
vehicle[Veh.TRACK_F] = vehicle[Veh.TRACK_R] = 1.37
vehicle[Veh.STEER_RATIO] = 16.0
vehicle[Veh.IMU_X], vehicle[Veh.IMU_Z] = 0.25, -0.25
params = make_params(kh)
state = kh.init(params, vehicle)
n = 5000
rng = np.random.default_rng(0)
U = np.zeros((n, U_LEN))
U[:, VALID:VALID + N_IN] = 1.0
U[:, In.AY] = 3.0 * np.sin(np.arange(n) * 0.01)
U[:, In.YAW_RATE] = 0.2 * np.sin(np.arange(n) * 0.01)
U[:, In.ROLL_RATE] = 0.01 * rng.standard_normal(n)
for ch in WHEEL_SPEEDS:
    U[:, ch] = 20.0 + 0.05 * rng.standard_normal(n)
U[::7, VALID + In.WHEEL_SPEED_RL] = 0.0
U[1000:1100, VALID + In.AX] = 0.0
OUT = np.zeros((n, N_OUT))
kh.run_ticks(state, U[:10], params, vehicle, 0.01, OUT[:10])  # compile
out = OUT[0]
kh.step(state, U[0], params, vehicle, 0.01, out)


def allocations(n_ticks):
    before = rtsys.get_allocation_stats()
    kh.run_ticks(state, U[:n_ticks], params, vehicle, 0.01, OUT[:n_ticks])
    after = rtsys.get_allocation_stats()
    return after.alloc - before.alloc, after.mi_alloc - before.mi_alloc


# Calling a kernel from Python boxes each array argument (a fixed few NRT allocations per
# call, measured in ../shared/notes/realtime-python.md); per-step allocations would scale
# with the number of ticks.
one = allocations(1)
many = allocations(n)
print(one[0], one[1], many[0], many[1])
"""


def test_run_ticks_allocates_nothing_per_step() -> None:
    # NUMBA_NRT_STATS must be set before numba is imported: a fresh process.
    one_alloc, one_mi, many_alloc, many_mi = map(
        int, _run_script(_ALLOC_SCRIPT, {"NUMBA_NRT_STATS": "1"}).split()
    )
    assert one_alloc < 10  # the call's own argument boxing, not the kernel
    assert (many_alloc, many_mi) == (one_alloc, one_mi)  # 5000 ticks cost what 1 tick costs


_CACHE_SCRIPT = """
import numpy as np
from slipd.channels import N_OUT, U_LEN, N_VEH
from slipd.estimators.selmanaj2017 import kinematic_heuristic as kh
from slipd.estimators.registry import make_params

params = make_params(kh)
vehicle = np.zeros(N_VEH)
state = kh.init(params, vehicle)
kh.run_ticks(state, np.zeros((3, U_LEN)), params, vehicle, 0.01, np.zeros((3, N_OUT)))
kh.step(state, np.zeros(U_LEN), params, vehicle, 0.01, np.zeros(N_OUT))
print(sum(kh.run_ticks.stats.cache_misses.values()) + sum(kh.step.stats.cache_misses.values()),
      sum(kh.run_ticks.stats.cache_hits.values()) + sum(kh.step.stats.cache_hits.values()))
"""


@pytest.mark.slow
def test_numba_cache_second_process_loads_without_compiling(tmp_path: Path) -> None:
    env = {"NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")}
    misses, _ = _run_script(_CACHE_SCRIPT, env).split()
    assert int(misses) > 0  # a fresh cache directory: the first process compiles
    misses, hits = _run_script(_CACHE_SCRIPT, env).split()
    assert int(misses) == 0 and int(hits) == 2


# --------------------------------------------------------------------------- simulator


def _simulate(scenario: str, duration: float | None = None):
    sim = pytest.importorskip("slipd.sim")
    return sim.simulate(scenario, vehicle=2, seed=0, duration=duration)


def _beta_error_deg(result, overrides=None, method: str | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(estimate - truth) in deg on the ticks where the truth speed exceeds 20 km/h, and OUT;
    of kinematic_heuristic, or of registered ``method``."""
    U = result.ticks()
    if method is None:
        OUT = run(U, overrides)
    else:
        other, vehicle = load(method, overrides), bmw_vehicle()
        OUT = np.zeros((U.shape[0], N_OUT))
        other.run_ticks(other.init(vehicle), U, other.params, vehicle, DT, OUT)
    n = min(len(U), len(result.truth["t"]))
    fast = result.truth["speed"][:n] > 20.0 / 3.6
    err = np.degrees(OUT[:n, Out.BETA] - result.truth["beta"][:n])
    return err[fast], OUT


def test_heuristic_holds_beta_on_straight_with_offsets_where_pure_kinematics_drifts() -> None:
    # Selmanaj section 2 remark 2 / Fig. 19, and issue 4: on the simulator's whole 300 s
    # straight with IMU offsets (0.15 / 0.25 m/s^2, 0.5 deg/s on top of the random ones) the
    # heuristic holds beta where the pure kinematic integrator (F = 0, no steady hold) and
    # k_kf drift. Measured (seed 0): heuristic max |error| 0.09 deg; integrator 3.7 deg;
    # k_kf 7.0 deg. (60 s was too short for the contrast: the integrator had drifted 0.4.)
    result = _simulate("straight_offsets", duration=300.0)
    err_heuristic, _ = _beta_error_deg(result)
    err_kinematic, _ = _beta_error_deg(result, {"f_gain": 0.0, "steady_gain": 0.0})
    assert np.max(np.abs(err_heuristic)) < 0.4
    assert np.max(np.abs(err_kinematic)) > 4.0 * np.max(np.abs(err_heuristic))
    assert np.max(np.abs(err_kinematic)) > 1.5
    err_k_kf, _ = _beta_error_deg(result, method="k_kf")
    assert np.nanmax(np.abs(err_k_kf)) > 4.0 * np.max(np.abs(err_heuristic))


#: Issue 4's target: beta RMS <= 1.1 deg on every scenario but snow_drift. Where the measured
#: number misses it the test is a strict xfail carrying the measurement (an improvement
#: turns it into an XPASS failure, so the list cannot go stale silently).
KNOWN_MISSES: dict[str, str] = {}
# Until the steady-state hold extension (module docstring) the paper-faithful observer missed
# banked_road (7.28 deg, road bank), loaded_vehicle (2.47, static roll model at the nominal
# mass) and endurance (6.45, banks and grades). With it, measured 2026-11-26 on
# slipd.sim.simulate(vehicle=2, seed=0): banked_road 1.03, loaded_vehicle 0.31, endurance 1.00
# (steady_gain = 0: 7.28, 2.47, 6.45).
TARGET_SCENARIOS = [
    "step_steer",
    "double_lane_change",
    "slalom",
    "j_turn",
    "sine_steer",
    "handling_high_mu",
    "handling_low_mu",
    "mu_jump",
    "straight_offsets",
    "banked_road",
    "loaded_vehicle",
    "endurance",
]


@pytest.mark.slow
@pytest.mark.parametrize(
    "scenario",
    [
        pytest.param(s, marks=pytest.mark.xfail(strict=True, reason=KNOWN_MISSES[s]))
        if s in KNOWN_MISSES
        else s
        for s in TARGET_SCENARIOS
    ],
)
def test_beta_rms_target_on_the_simulator_suite(scenario: str) -> None:
    err, OUT = _beta_error_deg(_simulate(scenario))
    assert np.all(np.isfinite(np.delete(OUT, [Out.MU, Out.NIS], axis=1)))
    assert np.sqrt(np.mean(err**2)) <= 1.1


@pytest.mark.slow
def test_no_nan_and_no_divergence_on_snow_drift() -> None:
    # Out of the RMS target (beta > 10 deg on snow) but it must stay finite and bounded.
    err, OUT = _beta_error_deg(_simulate("snow_drift"))
    assert np.all(np.isfinite(np.delete(OUT, [Out.MU, Out.NIS], axis=1)))
    assert np.max(np.abs(np.degrees(OUT[:, Out.BETA]))) < 90.0


# ---------------------------------------------------------------------------------------------
# plain twin of the observer's two stages (eq. 5 and F, eq. 6-7)
# ---------------------------------------------------------------------------------------------


def plain_heuristic(f_gain, signals, sigmas):
    """F = F_gain prod_i exp(-(x_i^2 / s_i^2 + dx_i^2 / s_di^2) / 2), eq. 7 written out."""
    value = f_gain
    for (x, dx), (s, ds) in zip(signals, sigmas, strict=True):
        value *= math.exp(-0.5 * ((x / s) ** 2 + (dx / ds) ** 2))
    return value


def plain_observer(x, vx_meas, have_vx, yaw_rate, ax, ay, a0, a1, a2, f, hold, hold_c):
    """Eq. 5 in matrix form: x' = A(omega) x + [Ax, Ay] - K (x1 - Vx) with
    A = [[0, omega], [-omega, -F]], K = [a0 + a1 |omega|, a2 omega] (0 without Vx), and the
    steady-state extension scaling the open-loop lateral integrand and the a2 term."""
    gains = np.array([a0 + a1 * abs(yaw_rate), a2 * yaw_rate]) if have_vx else np.zeros(2)
    error = x[0] - vx_meas if have_vx else 0.0
    x_dot = np.array([yaw_rate * x[1] + ax - gains[0] * error,
                      (1 - hold) * (ay - yaw_rate * x[0]) - (1 - hold * hold_c) * gains[1] * error
                      - f * x[1]])
    return x_dot, gains[0]


def test_the_heuristic_and_the_observer_agree_with_their_plain_twins():
    rng = np.random.default_rng(17)
    for _ in range(400):
        signals = rng.normal(0.0, [0.1, 0.3, 0.05, 0.3, 0.04, 0.6]).reshape(3, 2)
        sigmas = rng.uniform(0.05, 1.0, 6).reshape(3, 2)
        f_gain = rng.uniform(0.0, 2.0)
        f = kh.straight_heuristic(f_gain, *signals.ravel(), *sigmas.ravel())
        assert f == pytest.approx(plain_heuristic(f_gain, signals, sigmas), rel=1e-12, abs=1e-300)
        x = rng.normal([20.0, 0.0], [5.0, 1.0])
        args = (rng.normal(20.0, 5.0), bool(rng.random() < 0.8), rng.normal(0.0, 0.3),
                rng.normal(0.0, 2.0), rng.normal(0.0, 4.0), 10.0, 5.0, 10.0, f,
                rng.uniform(0.0, 1.0), 0.5)
        vx_dot, vy_dot, gain_x = kh.observer_derivatives(x[0], x[1], *args)
        x_dot, gain_ref = plain_observer(x, *args)
        np.testing.assert_allclose([vx_dot, vy_dot], x_dot, rtol=1e-12, atol=1e-12)
        assert gain_x == pytest.approx(gain_ref, rel=1e-15)
