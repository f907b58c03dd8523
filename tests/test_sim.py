"""The simulator: plant physics and signs, sensor models, scenarios, determinism, files."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("vehiclemodels")
pytest.importorskip("scipy")

from simkit import QUIET  # noqa: E402
from simkit import synthetic as _synthetic

from slipd.channels import U_LEN, U_TIME, VALID, In, Veh  # noqa: E402
from slipd.sim import SCENARIOS, simulate  # noqa: E402
from slipd.sim.core import _standstill  # noqa: E402
from slipd.sim.driver import steer_step  # noqa: E402
from slipd.sim.plant import (  # noqa: E402
    N_MB,
    OMEGA_FL,
    VX,
    VY,
    YAW_RATE,
    Driver,
    Plant,
    PlantOutput,
    Road,
    vehicle_parameters,
)
from slipd.sim.sensors import SensorConfig, sensor_channels  # noqa: E402
from slipd.sim.vehicle_data import derived, single_track_steady_state  # noqa: E402

G = 9.81
DEG = math.pi / 180.0

def _circle(speed: float, steer: float, duration: float = 5.0) -> PlantOutput:
    driver = Driver(steer=steer_step(0.5, steer, 0.3), speed_target=lambda t, s: speed)
    return Plant(vehicle_parameters(2), Road(), driver).run(duration, speed)


# --- plant physics and sign conventions ---------------------------------------------------


def test_left_turn_signs_iso8855():
    """A left turn at 20 m/s: yaw rate, ay and roll positive (ISO 8855: roll right side down);
    beta negative (the rear slides out at speed); at 5 m/s beta is positive (geometry)."""
    fast = _circle(20.0, 0.02)
    r, vy = fast.x[-1, YAW_RATE], fast.x[-1, VY]
    ay = fast.dx[-1, VY] + r * fast.x[-1, VX]
    assert r > 0.1 and ay > 2.0 and vy < 0.0
    from slipd.sim.sensors import truth

    tr = truth(fast, vehicle_parameters(2))
    assert tr["roll"][-1] > 0.01  # body leans out of the turn: right side down
    assert tr["beta"][-1] < 0.0
    slow = _circle(5.0, 0.05)
    assert slow.x[-1, YAW_RATE] > 0.0 and slow.x[-1, VY] > 0.0


def test_wheel_speeds_carry_iso_left_and_right():
    """In a left turn the left (inner) wheels are the slower ones, by r * track / 2 (the MB
    model's own "left" wheels sit at ISO y = -T/2; the sensor and truth labels must not)."""
    p = vehicle_parameters(2)
    fast = _circle(20.0, 0.02)
    from slipd.sim.sensors import truth

    tr = truth(fast, p)
    r, vx = tr["yaw_rate"][-1], tr["vx"][-1]
    rear_left, rear_right = tr["wheel_speed_rl"][-1], tr["wheel_speed_rr"][-1]
    assert tr["wheel_speed_fl"][-1] < tr["wheel_speed_fr"][-1] and rear_left < rear_right
    # free-rolling rear wheels: vx -/+ r T_r / 2 up to the small longitudinal slip
    assert abs(rear_left - (vx - r * p.T_r / 2)) < 0.02 * vx
    assert abs(rear_right - (vx + r * p.T_r / 2)) < 0.02 * vx
    channels = sensor_channels(fast, p, SensorConfig(), np.random.default_rng(0))
    assert channels[In.WHEEL_SPEED_RL][-1] < channels[In.WHEEL_SPEED_RR][-1]


def test_steady_state_matches_linear_single_track_at_small_slip():
    """Yaw rate within 3 % of r = v delta / (L + K_us v^2); sideslip within 0.1 deg of the
    linear formula (the multi-body car's camber and compliance terms shift it slightly)."""
    out = _circle(20.0, 0.01, duration=5.0)
    last = slice(-100, None)
    r = out.x[last, YAW_RATE].mean()
    beta = math.atan2(out.x[last, VY].mean(), out.x[last, VX].mean())
    r_lin, beta_lin = single_track_steady_state(2, out.x[last, VX].mean(), 0.01)
    assert r == pytest.approx(r_lin, rel=0.03)
    assert abs(beta - beta_lin) < 0.1 * DEG


def test_friction_scales_the_limit():
    """A J-turn beyond the limit: lateral acceleration saturates near mu g."""
    for mu in (0.3, 0.8):
        driver = Driver(steer=steer_step(0.5, 0.12, 0.5), speed_target=lambda t, s: 12.0)
        out = Plant(vehicle_parameters(2), Road(mu=np.array([mu])), driver).run(5.0, 12.0)
        ay = out.dx[:, VY] + out.x[:, YAW_RATE] * out.x[:, VX]
        assert 0.75 * mu * G < np.abs(ay[-100:]).mean() < 1.15 * mu * G


def test_energy_coasting_and_braking():
    """Coasting (no torque) the car cannot gain energy (the model has no drag, tyre rolling
    losses are tiny); braking at 3 m/s^2 removes kinetic energy at m a v."""
    coast = Driver(steer=lambda t, x, s: 0.0, speed_target=lambda t, s: 0.0,
                   accel_override=lambda t, x: 0.0)
    out = Plant(vehicle_parameters(2), Road(), coast).run(3.0, 20.0)
    speed = np.hypot(out.x[:, VX], out.x[:, VY])
    assert speed[-1] <= speed[0] + 1e-6 and speed[-1] > 0.99 * speed[0]
    brake = Driver(steer=lambda t, x, s: 0.0, speed_target=lambda t, s: 0.0,
                   accel_override=lambda t, x: -3.0)
    out = Plant(vehicle_parameters(2), Road(), brake).run(2.0, 20.0)
    # the tyres need ~0.1 s to build the slip for 3 m/s^2: ~0.3 m/s less speed lost
    assert out.x[-1, VX] == pytest.approx(20.0 - 3.0 * 2.0, abs=0.5)


def test_snow_drift_exceeds_10_deg():
    res = simulate("snow_drift", duration=9.0)
    assert np.degrees(np.abs(res.truth["beta"])).max() > 10.0
    assert np.all(res.truth["vx"] > 0.0)


def test_plant_reports_where_the_integrator_gives_up():
    """snow_drift on the front-driven vehicle 1: its throttle holds the rear wheels' slip, which
    a front-driven car never builds, so the fronts spin up until LSODA gives up (~23.6 s). The
    zeros odeint leaves after the failure must not reach the model (they raised
    ZeroDivisionError in the RHS, a traceback from `slipd sim snow_drift --vehicle 1`)."""
    from slipd.sim.core import run_plan
    from slipd.sim.plant import SimulationError

    with pytest.raises(SimulationError, match=r"could not be integrated past t = 2\d\.\d\d s"):
        run_plan("snow_drift", 1)


def test_standstill_sensors_read_gravity_and_zero_speed():
    """A parked car: az = +g, wheel speeds exactly 0, gyros only their bias and noise."""
    moving = _synthetic(10)
    out = _standstill(0.0, 1000, moving.x[-1], 0.0, moving)
    cfg = SensorConfig()
    ch = sensor_channels(out, vehicle_parameters(2), cfg, np.random.default_rng(1))
    assert np.mean(ch[In.AZ]) == pytest.approx(G, abs=0.4)
    for w in (In.WHEEL_SPEED_FL, In.WHEEL_SPEED_FR, In.WHEEL_SPEED_RL, In.WHEEL_SPEED_RR):
        assert np.all(ch[w] == 0.0)
    assert np.std(ch[In.YAW_RATE]) == pytest.approx(cfg.gyro_noise, rel=0.2)


# --- sensor models -------------------------------------------------------------------------


def test_imu_noise_level_and_bias_sizes():
    """White noise 0.02 m/s^2 / 0.08 deg/s (Yoon 2016 Table 1) and offsets of the configured
    size across seeds."""
    out = _synthetic(3000)
    p = vehicle_parameters(2)
    cfg = SensorConfig(accel_drift=0.0, gyro_drift=0.0, imu_misalignment=0.0)
    ch = sensor_channels(out, p, cfg, np.random.default_rng(3))
    assert np.std(ch[In.AY]) == pytest.approx(0.02, rel=0.1)
    assert np.std(ch[In.YAW_RATE]) == pytest.approx(0.08 * DEG, rel=0.1)
    biases = [np.mean(sensor_channels(out, p, cfg, np.random.default_rng(s))[In.AY])
              for s in range(30)]
    assert np.std(biases) == pytest.approx(cfg.accel_bias, rel=0.35)


def test_imu_lever_arm_centripetal_and_tangential():
    """IMU 1 m ahead of the CoG on a circle: ax = -r^2 x_imu; with yaw acceleration
    ay gains r_dot x_imu (omega x (omega x rho) and omega_dot x rho)."""
    p = vehicle_parameters(2)
    r = 0.5
    out = _synthetic(400, vx=10.0, yaw_rate=r)
    out.dx[:, VY] = 0.0  # steady circle: ay = r vx
    cfg = SensorConfig(**QUIET, imu_position=(1.0, 0.0, 0.0))
    ch = sensor_channels(out, p, cfg, np.random.default_rng(0))
    mid = slice(50, 350)
    assert np.mean(ch[In.AX][mid]) == pytest.approx(-(r**2) * 1.0, abs=1e-3)
    assert np.mean(ch[In.AY][mid]) == pytest.approx(r * 10.0, abs=1e-3)
    out2 = _synthetic(400, vx=10.0, yaw_rate=0.0, yaw_acc=0.2)
    out2.dx[:, VY] = -out2.x[:, YAW_RATE] * 10.0  # no lateral acceleration at the CoG
    ch2 = sensor_channels(out2, p, cfg, np.random.default_rng(0))
    assert np.mean(ch2[In.AY][mid]) == pytest.approx(0.2 * 1.0, abs=2e-3)


def test_gravity_on_bank_and_grade():
    """Road bank +0.1 rad (right edge lower) reads ay = +g sin(0.1); an uphill grade reads
    ax = +g sin(grade) (ISO 8855 specific force)."""
    p = vehicle_parameters(2)
    cfg = SensorConfig(**QUIET, imu_position=(0.0, 0.0, 0.0))
    banked = sensor_channels(_synthetic(200, bank=0.1), p, cfg, np.random.default_rng(0))
    assert np.mean(banked[In.AY]) == pytest.approx(G * math.sin(0.1), abs=1e-6)
    uphill = sensor_channels(_synthetic(200, grade=0.05), p, cfg, np.random.default_rng(0))
    assert np.mean(uphill[In.AX]) == pytest.approx(G * math.sin(0.05), abs=1e-6)
    assert np.mean(uphill[In.AZ]) == pytest.approx(G * math.cos(0.05), abs=1e-6)


def test_gnss_is_delayed_and_10hz():
    p = vehicle_parameters(2)
    out = _synthetic(300)
    out.x[:, VX] = 10.0 + 0.01 * np.arange(300)  # speed ramps 1 m/s per second
    cfg = SensorConfig(**QUIET, gnss_delay=0.4)
    ch = sensor_channels(out, p, cfg, np.random.default_rng(0), heading0=0.0)
    assert np.all(ch[In.GNSS_FIX][:40] == 0.0) and np.all(ch[In.GNSS_FIX][40:] == 1.0)
    # at 2.05 s the newest solution is the epoch 1.6 s (delivered at 2.0 s)
    assert ch[In.GNSS_VE][205] == pytest.approx(out.x[160, VX], abs=1e-9)


def test_wheel_speeds_show_slip():
    """Under full throttle on ice the driven (rear) wheels spin faster than the car moves."""
    driver = Driver(steer=lambda t, x, s: 0.0, speed_target=lambda t, s: 10.0,
                    accel_override=lambda t, x: 3.0)
    out = Plant(vehicle_parameters(2), Road(mu=np.array([0.15])), driver).run(2.0, 10.0)
    p = vehicle_parameters(2)
    rear = out.x[-1, OMEGA_FL + 2] * p.R_w
    front = out.x[-1, OMEGA_FL] * p.R_w
    assert rear > 1.5 * out.x[-1, VX]
    assert front == pytest.approx(out.x[-1, VX], rel=0.05)  # undriven: rolls with the car


# --- scenarios, results, files ---------------------------------------------------------------


def test_limit_scenarios_are_outside_the_suite_and_found_by_name():
    """The limits block's manoeuvres run by name like any scenario but not in --suite."""
    from slipd.sim.scenarios import LIMIT_SCENARIOS, find_scenario

    assert set(LIMIT_SCENARIOS) == {"wet_handling", "skidpad_wet", "skidpad_dry",
                                    "wet_sine_steer", "wet_lane_change", "snow_slalom",
                                    "icy_sine_steer", "wet_step_steer"}
    assert not set(LIMIT_SCENARIOS) & set(SCENARIOS)
    for name, scen in LIMIT_SCENARIOS.items():
        assert find_scenario(name) is scen and len(scen.description) > 20
        assert scen.build(2).legs
    assert find_scenario("step_steer") is SCENARIOS["step_steer"]
    assert find_scenario("nope") is None


def test_scenario_suite_is_complete_and_documented():
    expected = {"step_steer", "double_lane_change", "slalom", "j_turn", "sine_steer",
                "handling_high_mu", "handling_low_mu", "mu_jump", "straight_offsets",
                "banked_road", "loaded_vehicle", "snow_drift", "endurance"}
    assert set(SCENARIOS) == expected
    for scen in SCENARIOS.values():
        assert "20" in scen.paper and len(scen.description) > 20
    assert SCENARIOS["endurance"].duration >= 4000


def test_ticks_sample_and_hold():
    res = simulate("step_steer", duration=1.0)
    U = res.ticks(0.01)
    assert U.shape == (101, U_LEN)
    assert np.allclose(U[:, U_TIME], np.arange(101) * 0.01)
    imu = res.sensors["IMU_ACCEL"]
    k = 50
    newest = np.searchsorted(imu.t, U[k, U_TIME], side="right") - 1
    assert U[k, In.AX] == imu.values[In.AX][newest]
    assert U[0, VALID + In.AX] == 0.0 and U[k, VALID + In.AX] == 1.0
    assert U[k, VALID + In.SPEED_REF] == 0.0  # no message carries it in the default profile


def test_same_seed_same_log_bytes(tmp_path):
    from slipd.commands.sim import simulate_to_files

    for d in ("a", "b"):
        simulate_to_files("sine_steer", tmp_path / d, seed=7, duration=2.0)
    simulate_to_files("sine_steer", tmp_path / "c", seed=8, duration=2.0)
    a = (tmp_path / "a" / "sine_steer.log").read_bytes()
    assert a == (tmp_path / "b" / "sine_steer.log").read_bytes()
    assert a != (tmp_path / "c" / "sine_steer.log").read_bytes()
    first = a.splitlines()[0].decode()
    assert first.startswith("(1700000000.") and " can0 " in first


def test_log_decodes_back_to_the_sensor_values(tmp_path):
    """Through the codec and the replay reader: what the log carries is what the sensors said,
    to the DBC's resolution."""
    from slipd.commands.sim import simulate_to_files
    from slipd.replay.engine import latch_log
    from slipd.replay.readers import read_frames
    from slipd.sim.writer import START_EPOCH

    simulate_to_files("step_steer", tmp_path, duration=1.0)
    from slipd.profile import load_profile

    inputs = latch_log(read_frames(tmp_path / "step_steer.log"), load_profile("default"))
    ref = simulate("step_steer", duration=1.0)
    imu = ref.sensors["IMU_ACCEL"]
    k = 50
    newest = np.searchsorted(imu.t + START_EPOCH, inputs.t[k], side="right") - 1
    assert inputs.U[k, VALID + In.AY] == 1.0
    assert inputs.U[k, In.AY] == pytest.approx(imu.values[In.AY][newest], abs=1e-3)
    wheels = ref.sensors["WHEEL_SPEEDS"]
    newest = np.searchsorted(wheels.t + START_EPOCH, inputs.t[k], side="right") - 1
    assert inputs.U[k, In.WHEEL_SPEED_RL] == pytest.approx(
        wheels.values[In.WHEEL_SPEED_RL][newest], abs=0.01)


def test_truth_csv_roundtrip(tmp_path):
    from slipd.sim.writer import read_truth_csv, write_truth_csv

    res = simulate("j_turn", duration=1.0)
    write_truth_csv(tmp_path / "t.csv", res)
    cols, epoch = read_truth_csv(tmp_path / "t.csv")
    assert epoch == 1_700_000_000.0
    assert np.allclose(cols["beta"], res.truth["beta"], rtol=1e-8, atol=1e-12)
    assert np.allclose(np.diff(cols["t"]), 0.01)


# --- the vehicle profile describes the simulated car -----------------------------------------


def test_default_profile_describes_parameter_set_2():
    from slipd.profile import load_profile

    veh = load_profile("default").vehicle
    d = derived(2)
    for key in ("MASS", "YAW_INERTIA", "LF", "LR", "TRACK_F", "TRACK_R", "H_COG",
                "WHEEL_RADIUS", "CORNERING_STIFFNESS_F", "CORNERING_STIFFNESS_R",
                "LONGITUDINAL_STIFFNESS", "MU_NOMINAL", "TYRE_B", "TYRE_C", "ROLL_DAMPING"):
        assert veh[Veh[key]] == pytest.approx(d[key], rel=0.01), key


def test_profile_roll_stiffness_matches_a_steady_state_circle():
    from slipd.profile import load_profile
    from slipd.sim.vehicle_data import steady_state_test

    measured = steady_state_test(2, 20.0, 0.02)
    assert load_profile("default").vehicle[Veh.ROLL_STIFFNESS] == pytest.approx(
        measured["roll_stiffness"], rel=0.03)


@pytest.mark.slow
def test_endurance_legs_join_continuously():
    res = simulate("endurance", duration=300.0)
    tr = res.truth
    assert np.allclose(np.diff(tr["t"]), 0.01)
    step = np.hypot(np.diff(tr["pos_x"]), np.diff(tr["pos_y"]))
    assert step.max() < 0.5  # 0.5 m per 10 ms = 50 m/s
    assert np.any(tr["speed"] == 0.0)  # it stopped
    assert np.abs(np.diff(np.unwrap(tr["yaw"]))).max() < 0.02


def test_simulator_imports_no_estimator_code(tmp_path):
    """The truth is independent: simulating and writing a log never loads slipd.estimators."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "from slipd.commands.sim import simulate_to_files\n"
        f"simulate_to_files('j_turn', __import__('pathlib').Path(r'{tmp_path}'), duration=0.5)\n"
        "bad = [m for m in sys.modules if m.startswith('slipd.estimators')]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_fast_transcription_equals_the_package():
    """slipd.sim.mb_fast computes what vehiclemodels.vehicle_dynamics_mb computes, on random
    states in both branches (kinematic below 0.1 m/s and dynamic), and raises where it raises."""
    from vehiclemodels.vehicle_dynamics_mb import vehicle_dynamics_mb

    from slipd.sim import mb_fast

    p = vehicle_parameters(2)
    packed, tire = mb_fast.pack(p), mb_fast.pack_tire(p.tire)
    plant = Plant(p, Road(), Driver(steer=lambda t, x, s: 0.0, speed_target=lambda t, s: 20.0))
    x0 = plant.initial_state(20.0, settle=0.0)[:N_MB]
    rng = np.random.default_rng(0)
    for k in range(300):
        x = x0 + rng.normal(0, 1, N_MB) * np.abs(x0) * 0.05 + rng.normal(0, 0.01, N_MB)
        if k % 3 == 0:
            x[VX] = rng.uniform(0.0, 0.12)
        u = rng.normal(0, [0.5, 4.0])
        try:
            ref = np.array(vehicle_dynamics_mb(list(x), list(u), p))
        except ZeroDivisionError:
            with pytest.raises(ZeroDivisionError):
                mb_fast.vehicle_dynamics_mb(x, u[0], u[1], packed, tire)
            continue
        fast = mb_fast.vehicle_dynamics_mb(x, u[0], u[1], packed, tire)
        np.testing.assert_allclose(fast, ref, rtol=1e-9, atol=1e-9)


def test_fast_and_package_plants_agree_on_a_manoeuvre():
    driver = Driver(steer=steer_step(0.2, 0.03, 0.2), speed_target=lambda t, s: 15.0)
    road = Road(mu=np.array([0.5]))
    a = Plant(vehicle_parameters(2), road, driver, fast=True).run(1.5, 15.0)
    b = Plant(vehicle_parameters(2), road, driver, fast=False).run(1.5, 15.0)
    np.testing.assert_allclose(a.x[:, YAW_RATE], b.x[:, YAW_RATE], atol=1e-6)
    np.testing.assert_allclose(a.x[:, VY], b.x[:, VY], atol=1e-6)


def test_a_suite_scenario_the_plant_cannot_run_is_reported_and_the_rest_written(
        tmp_path, monkeypatch, capsys):
    """`slipd sim --suite --vehicle 1`: snow_drift's rear-slip throttle on the front-driven car
    makes LSODA give up; the suite writes every other scenario, names the one it could not
    simulate with the plant's reason, and exits 1 (it used to stop at it)."""
    import slipd.sim as sim_package
    from slipd.commands import sim as sim_command
    from slipd.sim.plant import SimulationError

    picked = {name: SCENARIOS[name] for name in ("step_steer", "snow_drift")}
    monkeypatch.setattr(sim_package, "SCENARIOS", picked)

    def fake(scenario, outputs, *args, **kwargs):
        if scenario == "snow_drift":
            raise SimulationError("the multi-body model could not be integrated past t = 23.56 s")
        return [{"scenario": scenario, "variant": None, "duration": 6.0, "frames": 10,
                 "wall": 0.1}]

    monkeypatch.setattr(sim_command, "simulate_variants_to_files", fake)
    assert sim_command.run_suite(tmp_path, 1, 0, "default", jobs=1) == 1
    captured = capsys.readouterr()
    assert "step_steer" in captured.out and "suite: 1 of 2 scenarios" in captured.out
    assert "snow_drift on vehicle 1 not simulated" in captured.err
    assert "integrated past t = 23.56 s" in captured.err
