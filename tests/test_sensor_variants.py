"""Sensor variants of the simulator (slipd.sim.variants): each does what it says, measured on the
simulated signals, and none disturbs the baseline."""

from __future__ import annotations

import dataclasses
import hashlib
import math

import numpy as np
import pytest

pytest.importorskip("vehiclemodels")
pytest.importorskip("scipy")

from simkit import QUIET  # noqa: E402
from simkit import synthetic as _synthetic

from slipd.channels import In  # noqa: E402
from slipd.errors import ConfigError  # noqa: E402
from slipd.sim import simulate  # noqa: E402
from slipd.sim.core import _standstill, simulate_variants  # noqa: E402
from slipd.sim.driver import steer_step  # noqa: E402
from slipd.sim.plant import Driver, Plant, PlantOutput, Road, vehicle_parameters  # noqa: E402
from slipd.sim.sensors import SensorConfig, sensor_channels, truth  # noqa: E402
from slipd.sim.tone_wheel import tone_wheel_speed  # noqa: E402
from slipd.sim.variants import VARIANTS, resolve  # noqa: E402
from slipd.sim.vibration import ENGINE_ORDERS, IDLE_RPM, REF_SPEED, engine_rpm  # noqa: E402

G = 9.81
DEG = math.pi / 180.0
P = vehicle_parameters(2)

#: The messages each variant may change; every other message must stay bit-identical.
TOUCHES = {
    "vibration": {"IMU_ACCEL", "IMU_RATE"},
    "level_frame": {"IMU_ACCEL"},
    "misalignment": {"IMU_ACCEL", "IMU_RATE"},
    "skew": {"IMU_ACCEL", "IMU_RATE", "WHEEL_SPEEDS", "STEERING"},
    "abs_tone_wheel": {"WHEEL_SPEEDS"},
    "steer_offset": {"STEERING"},
}

#: sha256 of logs and truth CSVs written by `slipd sim sine_steer --duration 3 --seed N` before
#: the sensor variants existed (main at deec598): the baseline must not move.
#: (seed, file) -> the digests of the toolchains the suite has run on: the simulator's
#: transcendental functions round differently on another CPU and libm (measured: this
#: project's machines until 2026-12-01, then a 2-vCPU Xeon with AVX-512 from 2026-12-02, whose
#: drives differ by ~1e-4 deg), so each machine kind's bytes are listed; a change of the code
#: changes them all.
BASELINE_SHA256 = {
    (0, "log"): ("7f92710a6039a5a7cbb6c28fd474648a667187da120416c4fb8b61562803053f",
                 "56dabbe19ae4b02b05a2518e95243ae0183c35b036fcd0a0a3c65d35644d9fab"),
    (0, "truth.csv"): ("80babb36b436a05c4578dd9409a763ecbc6736006dec8fee17936b33b668948e",
                       "e74e6fe56422af97d72999ca48f56c1e5c48c4f691ad8b4930a6911ce6c979dc"),
    (1, "log"): ("db6fc6daae53255a389d2fcd2983df8e267203fcf21f90f57684005e7686ffa5",
                 "85c430cfdfbf12ad61f02c3004ac4ac064ba4ecabd4a8b8e49fe1743d5c7cc69"),
    (1, "truth.csv"): ("0c87f51d3225a84b642a106f4544c5a27ea13de42b97207e4376216f0046b673",
                       "c60de593fb294235e63efd5600744669c5a1e62f415e5b0fe426820d36a56ab6"),
}


def _channels(out: PlantOutput, seed: int = 0, **settings) -> dict:
    cfg = SensorConfig(**{**QUIET, "imu_position": (0.0, 0.0, 0.0), **settings})
    return sensor_channels(out, P, cfg, np.random.default_rng(seed))


# --- registry, baseline ---------------------------------------------------------------------


def test_every_variant_is_documented_and_valid():
    fields = {f.name: f.default for f in dataclasses.fields(SensorConfig)}
    assert set(VARIANTS) == set(TOUCHES)
    for name, variant in VARIANTS.items():
        assert variant.name == name and len(variant.description) > 30 and variant.sources
        assert set(variant.overrides) <= set(fields), name
        assert any(fields[k] != v for k, v in variant.overrides.items()), name
        SensorConfig(**variant.overrides)


def test_combining_and_refusing_variants():
    name, overrides = resolve("skew, steer_offset")
    assert name == "skew,steer_offset"
    assert overrides == {**VARIANTS["skew"].overrides, **VARIANTS["steer_offset"].overrides}
    assert resolve(None) == (None, {})
    with pytest.raises(ConfigError, match="unknown sensor variant 'nope'.*vibration"):
        resolve("skew,nope")
    with pytest.raises(ConfigError, match="expected 'body' or 'level'"):
        SensorConfig(accel_frame="ned")
    with pytest.raises(ConfigError, match="wheel_teeth"):
        SensorConfig(wheel_teeth=-4)


def test_baseline_log_and_truth_are_byte_identical_to_before(tmp_path):
    """No variant: the same bytes as before the variants existed, for two seeds."""
    from slipd.commands.sim import simulate_to_files

    for seed in (0, 1):
        simulate_to_files("sine_steer", tmp_path / str(seed), seed=seed, duration=3.0)
        for suffix in ("log", "truth.csv"):
            data = (tmp_path / str(seed) / f"sine_steer.{suffix}").read_bytes()
            assert hashlib.sha256(data).hexdigest() in BASELINE_SHA256[seed, suffix], (
                f"the baseline simulation changed (seed {seed}, {suffix}): if on purpose, say "
                "so in the commit and update BASELINE_SHA256")


def test_a_variant_changes_only_its_messages_and_not_the_baseline_draws():
    """Same seed: the messages a variant does not touch are bit-identical to the baseline's,
    and every message keeps its bus schedule (the variant's draws have their own stream)."""
    names = list(VARIANTS)
    base, *variants = simulate_variants("j_turn", [None, *names], seed=3, duration=2.0)
    for name, res in zip(names, variants, strict=True):
        assert res.meta["variant"] == name
        changed = set()
        for msg, samples in res.sensors.items():
            ref = base.sensors[msg]
            np.testing.assert_array_equal(samples.t, ref.t)
            if any(not np.array_equal(samples.values[c], ref.values[c]) for c in ref.values):
                changed.add(msg)
        assert changed and changed <= TOUCHES[name], (name, changed)
        for col in ("beta", "ay", "wheel_speed_fl"):
            np.testing.assert_array_equal(res.truth[col], base.truth[col])


# --- level frame ----------------------------------------------------------------------------


def test_level_frame_ay_is_the_kinematic_acceleration_without_roll_gravity():
    """A steady left turn at 20 m/s with the body rolled ~1.5 deg: the level-frame ay equals
    dvy/dt + r vx at the IMU; the body frame reads g sin(roll) more; az reads ~0, not g."""
    driver = Driver(steer=steer_step(0.5, 0.02, 0.3), speed_target=lambda t, s: 20.0)
    out = Plant(P, Road(), driver).run(4.0, 20.0)
    tr = truth(out, P)
    level = _channels(out, accel_frame="level")
    body = _channels(out)
    last = slice(-100, None)
    np.testing.assert_allclose(level[In.AY], tr["ay"], atol=1e-9)
    np.testing.assert_allclose(level[In.AX], tr["ax"], atol=1e-9)
    roll = tr["roll"][last]
    assert roll.mean() > 0.5 * DEG
    # body frame: the lateral axis is tilted by the roll, so it reads ay cos + g sin(roll)
    expected_body = tr["ay"][last] * np.cos(roll) + G * np.sin(roll)
    np.testing.assert_allclose(body[In.AY][last], expected_body, atol=0.02)
    assert np.mean(body[In.AY][last] - level[In.AY][last]) > 0.15
    assert np.abs(level[In.AZ][last]).max() < 0.05 and body[In.AZ][last].mean() > 9.5


def test_level_frame_has_no_bank_or_grade_term():
    banked = _channels(_synthetic(200, bank=0.1), accel_frame="level")
    uphill = _channels(_synthetic(200, grade=0.05), accel_frame="level")
    for ch in (In.AX, In.AY, In.AZ):
        assert np.abs(banked[ch]).max() < 1e-9 and np.abs(uphill[ch]).max() < 1e-9
    body = _channels(_synthetic(200, bank=0.1))
    assert np.mean(body[In.AY]) == pytest.approx(G * math.sin(0.1), abs=1e-6)


# --- misalignment ---------------------------------------------------------------------------


def test_misalignment_rotates_the_static_gravity_vector():
    """Parked: the sensor sees (0, 0, g) rotated by the mounting angles, R^T g with
    R = Rz(yaw) Ry(pitch) Rx(roll); roll alone gives ay = g sin(roll)."""
    moving = _synthetic(10)
    parked = _standstill(0.0, 200, moving.x[-1], 0.0, moving)
    roll, pitch, yaw = VARIANTS["misalignment"].overrides["imu_mounting"]
    assert all(1.0 * DEG <= a <= 2.0 * DEG for a in (roll, pitch, yaw))
    ch = _channels(parked, imu_mounting=(roll, pitch, yaw))
    from scipy.spatial.transform import Rotation

    mounting = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()  # Rz Ry Rx
    expected = mounting.T @ np.array([0.0, 0.0, G])
    measured = np.array([ch[In.AX].mean(), ch[In.AY].mean(), ch[In.AZ].mean()])
    np.testing.assert_allclose(measured, expected, atol=1e-9)
    only_roll = _channels(parked, imu_mounting=(roll, 0.0, 0.0))
    assert only_roll[In.AY].mean() == pytest.approx(G * math.sin(roll), abs=1e-9)
    assert abs(only_roll[In.AX].mean()) < 1e-12


def test_yaw_misalignment_leaks_ay_into_ax():
    circle = _synthetic(300, vx=15.0, yaw_rate=0.4)  # ay = 6 m/s^2, flat road
    yaw = 1.5 * DEG
    ch = _channels(circle, imu_mounting=(0.0, 0.0, yaw))
    assert ch[In.AX].mean() == pytest.approx(6.0 * math.sin(yaw), abs=1e-9)
    assert ch[In.AY].mean() == pytest.approx(6.0 * math.cos(yaw), abs=1e-9)


# --- skew -----------------------------------------------------------------------------------


def _lag(reference: np.ndarray, signal: np.ndarray, max_lag: int = 10) -> int:
    """The shift (samples) that best aligns ``signal`` to ``reference``: least variance of the
    difference (a constant offset does not count)."""
    n = len(reference)
    return int(np.argmin([np.var(signal[k:] - reference[: n - k]) for k in range(max_lag)]))


def test_skew_delays_the_content_not_the_schedule():
    base, skew = simulate_variants("sine_steer", [None, "skew"], seed=2, duration=4.0)
    shifts = {"IMU_ACCEL": 1, "IMU_RATE": 1, "STEERING": 2, "WHEEL_SPEEDS": 3}
    for msg, k in shifts.items():
        for ch, values in skew.sensors[msg].values.items():
            np.testing.assert_array_equal(values[k:], base.sensors[msg].values[ch][:-k])
            assert np.all(values[:k] == base.sensors[msg].values[ch][0])
    # measured against the truth: the steering message lags the road-wheel angle by 20 ms
    steer_truth = skew.truth["steer"]
    assert _lag(steer_truth, base.sensors["STEERING"].values[In.STEER]) == 0
    assert _lag(steer_truth, skew.sensors["STEERING"].values[In.STEER]) == 2
    assert _lag(skew.truth["yaw_rate"], skew.sensors["IMU_RATE"].values[In.YAW_RATE]) in (1, 2)


def test_a_delay_between_grid_steps_interpolates():
    base = simulate("sine_steer", seed=2, duration=2.0)
    half = simulate("sine_steer", seed=2, duration=2.0, sensor={"steer_delay": 0.015})
    steer = base.sensors["STEERING"].values[In.STEER]
    np.testing.assert_allclose(half.sensors["STEERING"].values[In.STEER][2:],
                               0.5 * (steer[1:-1] + steer[:-2]), atol=1e-15)


# --- wheel-speed quantisation ---------------------------------------------------------------


def test_tone_wheel_edge_timing_is_exact_at_constant_speed_and_lags_in_a_stop():
    t = np.arange(0.0, 22.0, 0.01)
    teeth, radius = 48, P.R_w
    pitch = 2 * math.pi * radius / teeth
    steady = tone_wheel_speed(t, np.full(len(t), 20.0 / radius), teeth, 0.3) * radius
    np.testing.assert_allclose(steady, 20.0, rtol=1e-9)  # from the first sample on
    v = np.clip(20.0 - t, 0.0, None)  # 1 m/s^2 to a stop at 20 s
    stop = tone_wheel_speed(t, v / radius, teeth, 0.3, timeout=0.1) * radius
    moving = slice(100, 1900)
    # the mean over the last edge interval: behind by at most decel x (edge interval + gate)
    lag_bound = 1.0 * (pitch / v[moving] + 0.02)
    assert np.all(np.abs(stop[moving] - v[moving]) <= lag_bound)
    assert 0.0 < np.mean(stop[moving] - v[moving]) < 0.01  # lags: reads high while braking
    # low speed: 0 below pitch / timeout, never a value between 0 and that
    v_min = pitch / 0.1
    assert np.all((stop == 0.0) | (stop >= v_min - 1e-9))
    assert np.all(stop[v < 0.5 * v_min] == 0.0) and np.all(stop[v > 1.5 * v_min] > 0)
    # at ~1 m/s an edge comes every ~4.5 steps: the value moves in steps, the truth every step
    slow = slice(int(18.5 / 0.01), int(19.2 / 0.01))
    assert np.count_nonzero(np.diff(stop[slow])) < 0.5 * len(stop[slow])


def test_tone_wheel_count_method_values_lie_on_the_tooth_lattice():
    t = np.arange(0.0, 5.0, 0.01)
    teeth, radius = 48, P.R_w
    speed = np.linspace(3.0, 30.0, len(t))
    counted = tone_wheel_speed(t, speed / radius, teeth, 0.7, method="count") * radius
    resolution = 2 * math.pi * radius / (teeth * 0.01)
    steps = counted / resolution
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-9)
    assert abs(np.mean(counted[10:]) - np.mean(speed[10:])) < 0.1 * resolution


def test_abs_variant_wheel_speeds_through_the_sensor_model():
    """The variant's wheel speeds at a constant 20 m/s equal the ideal ones (noise-free) and a
    parked car reads exactly 0."""
    overrides = VARIANTS["abs_tone_wheel"].overrides
    cruise = _synthetic(300)
    ideal = _channels(cruise)
    abs_ch = _channels(cruise, **overrides)
    np.testing.assert_allclose(abs_ch[In.WHEEL_SPEED_RL], ideal[In.WHEEL_SPEED_RL],
                               rtol=1e-9)
    parked = _standstill(0.0, 100, cruise.x[-1], 0.0, cruise)
    assert np.all(_channels(parked, **overrides)[In.WHEEL_SPEED_FL] == 0.0)


# --- vibration ------------------------------------------------------------------------------


def _vibration_only(out: PlantOutput, **settings) -> dict:
    base = _channels(out, seed=5)
    vib = _channels(out, seed=5, **settings)
    return {ch: vib[ch] - base[ch] for ch in (In.AX, In.AY, In.AZ, In.ROLL_RATE,
                                               In.PITCH_RATE, In.YAW_RATE)}


def test_vibration_rms_per_axis_at_the_reference_speed():
    overrides = VARIANTS["vibration"].overrides
    vib = _vibration_only(_synthetic(6000, vx=REF_SPEED), **overrides)
    levels = (*overrides["vibration_accel"], *overrides["vibration_gyro"])
    for ch, level in zip(vib, levels, strict=True):
        assert np.std(vib[ch]) == pytest.approx(level, rel=0.08), ch.name
    assert 0.5 <= overrides["vibration_accel"][1] <= 2.0  # the brief's range on ay


def test_vibration_spectrum_engine_line_over_a_flat_floor_and_its_speed_law():
    """At 30 m/s the engine's 2nd order (~79 Hz) aliases to ~21 Hz and stands out of a flat
    broadband floor; parked, only the idling engine remains."""
    from scipy import signal

    accel = (0.0, 1.0, 0.0)
    vib = _vibration_only(_synthetic(12000, vx=30.0), vibration_accel=accel)[In.AY]
    f, psd = signal.welch(vib, fs=100.0, nperseg=1024)
    f2 = ENGINE_ORDERS[0][0] * float(engine_rpm(np.array([30.0]), P.R_w)[0]) / 60.0
    alias = abs(f2 - 100.0 * round(f2 / 100.0))
    line = psd[np.abs(f - alias) < 0.3].max()
    floor = np.median(psd[(f > 25) & (f < 45)])
    assert line > 20 * floor
    low, high = np.median(psd[(f > 2) & (f < 8)]), np.median(psd[(f > 30) & (f < 45)])
    assert 0.3 < low / high < 3.0  # broadband: flat, no roll-off
    moving = _synthetic(6000, vx=REF_SPEED)
    parked = _standstill(0.0, 6000, moving.x[-1], 0.0, moving)
    idle = _vibration_only(parked, vibration_accel=accel)[In.AY]
    shares = SensorConfig().vibration_shares
    rpm_ref = float(engine_rpm(np.array([REF_SPEED]), P.R_w)[0])
    expected = math.sqrt(shares[2] / sum(shares)) * IDLE_RPM / rpm_ref
    assert np.std(idle) == pytest.approx(expected, rel=0.05)


def test_steer_offset_adds_a_fixed_steering_wheel_angle():
    base, offset = simulate_variants("sine_steer", [None, "steer_offset"], seed=4, duration=1.0)
    ratio = base.meta["sensor_config"].steer_ratio
    diff = (offset.sensors["STEERING"].values[In.STEER]
            - base.sensors["STEERING"].values[In.STEER]) * ratio
    bias = VARIANTS["steer_offset"].overrides["swa_bias"]
    np.testing.assert_allclose(diff, bias, atol=1e-12)
    assert 2.0 * DEG <= bias <= 5.0 * DEG


# --- command line ---------------------------------------------------------------------------


def test_cli_writes_a_variant_and_records_it(tmp_path, capsys):
    from slipd.cli import main
    from slipd.sim.writer import read_truth_csv, read_truth_meta

    assert main(["sim", "j_turn", "--duration", "0.5", "--variant", "skew",
                 "--out", str(tmp_path / "one")]) == 0
    meta = read_truth_meta(tmp_path / "one" / "j_turn.truth.csv")
    assert meta["variant"] == "skew" and meta["seed"] == "0"
    assert "wheel_delay=0.03" in meta["sensor_overrides"]
    cols, _ = read_truth_csv(tmp_path / "one" / "j_turn.truth.csv")
    assert len(cols["t"]) == 51
    assert main(["sim", "j_turn", "--duration", "0.5", "--variant", "each",
                 "--variant", "skew,steer_offset", "--out", str(tmp_path / "many")]) == 0
    dirs = sorted(p.name for p in (tmp_path / "many").iterdir())
    assert dirs == sorted([*VARIANTS, "skew+steer_offset"])
    assert read_truth_meta(tmp_path / "many" / "skew+steer_offset" / "j_turn.truth.csv")[
        "variant"] == "skew,steer_offset"
    capsys.readouterr()
    assert main(["sim", "--list"]) == 0
    listed = capsys.readouterr().out
    assert all(name in listed for name in VARIANTS) and "step_steer" in listed
    assert main(["sim", "--list-variants"]) == 0
    assert "US patent 4,799,178" in capsys.readouterr().out
    assert main(["sim", "j_turn", "--variant", "bogus", "--out", str(tmp_path)]) == 2
    assert "unknown sensor variant 'bogus'" in capsys.readouterr().err
    assert main(["sim", "j_turn", "--sensor", "wheel_teeth=x", "--out", str(tmp_path)]) == 2
    assert main(["sim", "j_turn", "--duration", "0.5", "--sensor", "wheel_teeth=48",
                 "--sensor", "wheel_speed_method=count", "--out", str(tmp_path / "s")]) == 0
    assert "wheel_speed_method=count" in read_truth_meta(
        tmp_path / "s" / "j_turn.truth.csv")["sensor_overrides"]
