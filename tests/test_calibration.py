"""The profile's [calibration] table (slipd identify's output) and its correction where the
codec samples the latch: the kernel and its plain twin agree, the identity leaves the inputs
untouched, a sensor with the simulator's mounting and offsets reads the body's values after
the correction, and a bad table is a load error naming the key."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipd.channels import N_IN, U_LEN, WHEEL_SPEEDS, G, In
from slipd.codec.calibration import (
    CAL_ACTIVE,
    calibrate,
    calibrate_ticks,
    calibration_vector,
    mounting_rotation,
)
from slipd.errors import ConfigError
from slipd.profile import Calibration, load_profile
from tests.test_profile import _variant

SOME = Calibration(imu_mounting_deg=(1.2, -0.8, 2.5), accel_offset=(0.1, -0.2, 0.05),
                   gyro_offset=(0.3, -0.1, 0.2), steer_offset_deg=3.0,
                   wheel_radius_scale=(1.01, 0.99, 1.0, 1.005), steer_divisor=16.0)


def _inputs(rng: np.random.Generator, n: int, valid_share: float) -> np.ndarray:
    U = np.zeros((n, U_LEN))
    U[:, :N_IN] = rng.normal(0.0, 3.0, (n, N_IN))
    U[:, N_IN:2 * N_IN] = (rng.random((n, N_IN)) < valid_share).astype(float)
    U[:, 2 * N_IN] = np.arange(n) * 0.01
    return U


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), valid_share=st.sampled_from([0.0, 0.5, 0.9, 1.0]))
def test_the_kernel_and_its_plain_twin_agree(seed, valid_share):
    rng = np.random.default_rng(seed)
    U = _inputs(rng, 50, valid_share)
    cal = calibration_vector(SOME)
    expected = calibrate_ticks(cal, U)
    for k in range(len(U)):
        u = U[k].copy()
        calibrate(cal, u)
        np.testing.assert_allclose(u, expected[k], rtol=0, atol=1e-12)


def test_no_table_leaves_every_input_byte_for_byte():
    cal = calibration_vector(Calibration())
    assert cal[CAL_ACTIVE] == 0.0
    U = _inputs(np.random.default_rng(1), 20, 0.7)
    for k in range(len(U)):
        u = U[k].copy()
        calibrate(cal, u)
        assert u.tobytes() == U[k].tobytes()
    assert load_profile("default").calibration.is_identity


def test_the_correction_undoes_the_simulators_mounting_and_offsets():
    """A sensor mounted as slipd.sim mounts it (rows R^T v) with offsets b reads R^T v + b;
    the correction gives back v, the steer's offset comes off at the ratio and each wheel
    speed is scaled."""
    from slipd.sim.sensors import _rx, _ry, _rz

    roll, pitch, yaw = (math.radians(a) for a in SOME.imu_mounting_deg)
    sim_rotation = _rz(np.array([yaw]))[0] @ _ry(np.array([pitch]))[0] @ _rx(np.array([roll]))[0]
    np.testing.assert_allclose(mounting_rotation(roll, pitch, yaw), sim_rotation, atol=1e-15)
    f_body, w_body = np.array([1.5, -2.0, G]), np.array([0.05, -0.02, 0.3])
    u = np.zeros(U_LEN)
    u[N_IN:2 * N_IN] = 1.0
    u[[In.AX, In.AY, In.AZ]] = f_body @ sim_rotation + np.array(SOME.accel_offset)
    u[[In.ROLL_RATE, In.PITCH_RATE, In.YAW_RATE]] = (
        w_body @ sim_rotation + np.radians(SOME.gyro_offset))
    u[In.STEER] = 0.01 + math.radians(SOME.steer_offset_deg) / 16.0
    u[[int(c) for c in WHEEL_SPEEDS]] = 20.0
    calibrate(calibration_vector(SOME), u)
    np.testing.assert_allclose(u[[In.AX, In.AY, In.AZ]], f_body, atol=1e-12)
    np.testing.assert_allclose(u[[In.ROLL_RATE, In.PITCH_RATE, In.YAW_RATE]], w_body,
                               atol=1e-12)
    assert u[In.STEER] == pytest.approx(0.01, abs=1e-15)
    np.testing.assert_allclose(u[[int(c) for c in WHEEL_SPEEDS]],
                               20.0 * np.array(SOME.wheel_radius_scale))


def test_a_calibration_table_loads_with_the_steer_channels_ratio(tmp_path):
    path = _variant(tmp_path, "[vehicle.tyre]", "[calibration]\n"
                    "imu_mounting_deg = [0.5, -0.25, 1.0]\nsteer_offset_deg = 2.5\n"
                    "wheel_radius_scale = [1.0, 1.002, 0.998, 1.0]\n\n[vehicle.tyre]")
    cal = load_profile(path).calibration
    assert cal.imu_mounting_deg == (0.5, -0.25, 1.0) and cal.steer_offset_deg == 2.5
    assert cal.gyro_offset == (0.0, 0.0, 0.0) and cal.steer_divisor == 16.0
    assert not cal.is_identity


@pytest.mark.parametrize(("line", "match"), [
    ("imu_mounting_deg = [0.5, 0.5]", r"\[calibration\] imu_mounting_deg .*3 numbers"),
    ("imu_mounting_deg = [0.5, 0.5, 40.0]", r"imu_mounting_deg .*within \+-15"),
    ("gyro_offset = [0.1, nan, 0.0]", r"gyro_offset .*3 numbers"),
    ("wheel_radius_scale = [1.0, 1.0, 1.0, 1.5]", r"wheel_radius_scale .*within 0.2 of 1"),
    ("steer_offset_deg = 120.0", r"steer_offset_deg"),
    ("accel_offset = [true, 0.0, 0.0]", r"accel_offset"),
    ("yaw_offset = 1.0", r"yaw_offset"),
])
def test_a_bad_calibration_value_is_a_load_error_naming_the_key(tmp_path, line, match):
    path = _variant(tmp_path, "[vehicle.tyre]", f"[calibration]\n{line}\n\n[vehicle.tyre]")
    with pytest.raises(ConfigError, match=match):
        load_profile(path)
