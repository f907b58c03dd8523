"""Tests of the shared building blocks (slipd.estimators.common: filters, kinematics, inputs)
and of Selmanaj's Vx from the wheels (selmanaj2017.wheel_speed).

Each block is checked against physics built independently here (rigid-body kinematics with
numpy's cross product, a plain-Python reimplementation of eq. 11-13) rather than against
numbers copied from the implementation.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipd.channels import G, Veh
from slipd.estimators.common import filters, inputs, kinematics
from slipd.estimators.selmanaj2017 import wheel_speed

DT = 0.01
finite = st.floats(min_value=-5.0, max_value=5.0, allow_nan=False)


# ----------------------------------------------------------------------------- filters


def test_derivative_filter_starts_without_spike_and_follows_a_ramp() -> None:
    buf = np.full(1, np.nan)
    assert filters.derivative_filter(buf, 0, 100.0, DT, 10.0) == 0.0
    slope = 2.5
    derivative = 0.0
    for k in range(1, 100):
        derivative = filters.derivative_filter(buf, 0, 100.0 + slope * k * DT, DT, 10.0)
    assert derivative == pytest.approx(slope, rel=1e-9)


def test_derivative_filter_matches_the_continuous_10hz_filter_at_1hz() -> None:
    # |H(j w)| of s / (1 + s / wc) at 1 Hz: w / sqrt(1 + (w / wc)^2); Euler at 100 Hz is close.
    buf = np.full(1, np.nan)
    w = 2.0 * math.pi
    t = np.arange(0.0, 6.0, DT)
    out = np.array([filters.derivative_filter(buf, 0, math.sin(w * tk), DT, 10.0) for tk in t])
    amplitude = np.max(np.abs(out[t > 3.0]))
    expected = w / math.sqrt(1.0 + (w / (2.0 * math.pi * 10.0)) ** 2)
    assert amplitude == pytest.approx(expected, rel=0.05)


def test_lowpass_settles_with_its_time_constant() -> None:
    buf = np.zeros(1)
    tau = 0.5
    for _ in range(int(tau / DT)):
        filters.lowpass(buf, 0, 1.0, DT, tau)
    assert buf[0] == pytest.approx(1.0 - math.exp(-1.0), abs=0.01)


def test_noise_power_is_the_mean_square_of_the_sampled_ticks_only() -> None:
    # NaN until the first sampled tick; then the RMS of white noise of sigma 0.7 (the
    # driving in between, a 5.0 offset, never sampled, must not leak in).
    rng = np.random.default_rng(1)
    buf = np.full(1, np.nan)
    assert math.isnan(filters.noise_power(buf, 0, 5.0, False, DT, 10.0))
    sigma = 0.7
    for k in range(60_000):
        sampled = (k // 500) % 2 == 0
        value = sigma * rng.standard_normal() if sampled else 5.0
        power = filters.noise_power(buf, 0, value, sampled, DT, 10.0)
    assert math.sqrt(power) == pytest.approx(sigma, rel=0.1)


# ----------------------------------------------------------------------------- CoG


def _imu_acceleration(a_cog, omega, omega_dot, r):
    """Rigid body: a_imu = a_cog + omega_dot x r + omega x (omega x r)."""
    return a_cog + np.cross(omega_dot, r) + np.cross(omega, np.cross(omega, r))


def test_butterworth_lowpass_equals_scipy_and_starts_without_transient() -> None:
    """The kernel is scipy.signal.butter(2, ...) + lfilter, started in its steady state."""
    signal = pytest.importorskip("scipy.signal")
    rng = np.random.default_rng(7)
    x = 3.0 + rng.normal(0.0, 1.0, 2000) + np.sin(np.arange(2000) * DT * 2 * np.pi * 0.5)
    b, a = signal.butter(2, 5.0 / (0.5 / DT))
    want = signal.lfilter(b, a, x, zi=signal.lfilter_zi(b, a) * x[0])[0]
    buf = np.full(filters.BUTTERWORTH_SLOTS, np.nan)
    got = np.array([filters.butterworth_lowpass(buf, 0, v, DT, 5.0) for v in x])
    assert np.max(np.abs(got - want)) < 1e-9
    # vibration above the cut-off is removed, the 0.5 Hz motion kept
    assert np.std(np.diff(got)) < 0.1 * np.std(np.diff(x))


def _gravity_drive(share: float, seconds: float = 300.0, bias: float = 0.2):
    """Quasi-steady corners at 20 m/s: ay = r vx, the sensor adding share * its reading."""
    t = np.arange(0.0, seconds, DT)
    vx = 20.0
    ay_true = 6.0 * np.sin(2 * np.pi * t / 40.0)
    yaw_rate = ay_true / vx
    yaw_acc = np.gradient(yaw_rate, DT)
    ay_measured = ay_true / (1.0 - share) + bias  # ay_meas - share ay_meas = ay_true
    return ay_measured, yaw_rate, yaw_acc, vx


@pytest.mark.parametrize("share", [0.0, 0.03, 0.09])
def test_gravity_share_is_learnt_from_quasi_steady_driving(share: float) -> None:
    """A levelled accelerometer (0), a car's roll gradient (0.03 = 1.7 deg/g) and a soft one
    are found whatever the nominal value, and the offset stays out of the slope."""
    ay_measured, yaw_rate, yaw_acc, vx = _gravity_drive(share)
    buf = np.zeros(len(kinematics.GravityMoments))
    for nominal in (0.0, 0.05):
        buf[:] = 0.0
        for k in range(len(ay_measured)):
            learnt = kinematics.learn_gravity_share(buf, 0, ay_measured[k], yaw_rate[k],
                                                    yaw_acc[k], vx, DT, nominal)
        assert learnt == pytest.approx(share, abs=0.006)  # the prior shrinks it a little


def test_gravity_share_starts_at_the_nominal_value_and_stays_bounded() -> None:
    buf = np.zeros(len(kinematics.GravityMoments))
    assert kinematics.learn_gravity_share(buf, 0, 3.0, 0.1, 0.0, 1.0, DT, 0.02) == 0.02  # slow
    ay_measured, yaw_rate, yaw_acc, vx = _gravity_drive(0.0)
    for k in range(len(ay_measured)):  # an accelerometer reading 40 % high: not gravity
        learnt = kinematics.learn_gravity_share(buf, 0, 1.4 * ay_measured[k], yaw_rate[k],
                                                yaw_acc[k], vx, DT, 0.02)
    assert learnt == kinematics.GRAVITY_SHARE_MAX


def test_a_levelled_accelerometer_is_not_compensated() -> None:
    """Declared levelled (the profile's frame), or told by its az reading no gravity (an INS
    whose profile says nothing): ay comes back as it is. A body-fixed one (az ~ g, or no az
    on the bus) is compensated."""
    from slipd.channels import VALID, In, new_u
    from slipd.estimators.common.inputs import accel_carries_gravity

    vehicle = np.zeros(len(Veh))
    vehicle[Veh.MASS], vehicle[Veh.H_ROLL_AXIS], vehicle[Veh.ROLL_STIFFNESS] = 1500.0, 0.5, 8e4
    buf = np.full(1 + len(kinematics.GravityMoments), np.nan)
    u = new_u()

    def removed(u) -> float:
        buf[:] = np.nan
        return kinematics.remove_roll_gravity(buf, 0, 6.0, 0.0, False, DT, vehicle,
                                              accel_carries_gravity(u, vehicle), 0.5, -1, 0.3,
                                              0.0, 20.0)

    body = removed(u)  # no az on the bus
    assert body < 6.0 - 0.5
    u[In.AZ], u[VALID + In.AZ] = 9.81, 1.0
    assert removed(u) == body
    u[In.AZ] = 0.2  # a levelled sensor's az: no gravity
    assert removed(u) == 6.0
    u[In.AZ] = 9.81
    vehicle[Veh.ACCEL_LEVEL] = 1.0
    assert removed(u) == 6.0


@settings(max_examples=200, deadline=None)
@given(
    st.lists(finite, min_size=3, max_size=3),
    st.lists(finite, min_size=3, max_size=3),
    st.lists(finite, min_size=3, max_size=3),
    st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=3),
)
def test_translate_to_cog_inverts_rigid_body_kinematics(a_cog, omega, omega_dot, r) -> None:
    a_cog, omega, omega_dot, r = map(np.asarray, (a_cog, omega, omega_dot, r))
    a_imu = _imu_acceleration(a_cog, omega, omega_dot, r)
    got = kinematics.translate_to_cog(*a_imu, *omega, *omega_dot, *r)
    np.testing.assert_allclose(got, a_cog, atol=1e-9)


@settings(max_examples=100, deadline=None)
@given(finite, finite, finite, finite, st.floats(-2.0, 2.0), st.floats(-2.0, 2.0))
def test_planar_translation_is_the_full_one_without_roll_and_pitch(
    ax, ay, yaw_rate, yaw_acc, imu_x, imu_y
) -> None:
    full = kinematics.translate_to_cog(
        ax, ay, 0.0, 0.0, 0.0, yaw_rate, 0.0, 0.0, yaw_acc, imu_x, imu_y, 0.0
    )
    planar = kinematics.translate_to_cog_planar(ax, ay, yaw_rate, yaw_acc, imu_x, imu_y)
    assert planar == pytest.approx(full[:2], abs=1e-12)


def test_imu_ahead_of_cog_in_steady_turn_feels_centripetal_pull_backwards() -> None:
    # Sign check in words: IMU 1 m ahead, steady left turn at 0.5 rad/s: the IMU sees an extra
    # -r^2 x = -0.25 m/s^2 along x that the CoG does not have.
    ax_cog, ay_cog = kinematics.translate_to_cog_planar(-0.25, 0.0, 0.5, 0.0, 1.0, 0.0)
    assert ax_cog == pytest.approx(0.0)
    assert ay_cog == pytest.approx(0.0)


# ----------------------------------------------------------------------------- roll


def test_static_roll_gain_rolls_right_side_down_in_a_left_turn() -> None:
    gain = kinematics.roll_static_gain(1093.3, 0.5749, 41780.0)
    assert gain == pytest.approx(1093.3 * 0.5749 / 41780.0)
    assert gain > 0.0  # ay > 0 (left turn) -> roll > 0 (ISO: right side down)
    assert kinematics.roll_static_gain(1000.0, 0.5, 0.0) == 0.0


def test_static_roll_with_measured_ay_keeps_the_gravity_moment() -> None:
    # K phi = m h (ay + g phi) solved exactly vs the block fed with the measured ay.
    mass, arm, stiffness, ay = 1093.3, 0.5749, 41780.0, 8.0
    phi_true = mass * arm * ay / (stiffness - mass * arm * G)
    ay_measured = ay + G * math.sin(phi_true)
    phi = kinematics.roll_static_gain(mass, arm, stiffness) * ay_measured
    assert phi == pytest.approx(phi_true, rel=1e-3)


def test_complementary_filter_tracks_roll_dynamics_the_static_model_misses() -> None:
    # A roll oscillation at 2 Hz with no lateral acceleration (road input): the static model
    # says 0 (RMS error 0.71 amp), the roll rate carries it. With tau = 0.5 s the filter is a
    # high-pass 1 / (1 + 1 / (j w tau)) on this motion: |1 - H| = 0.16, RMS error 0.11 amp.
    buf = np.full(1, np.nan)
    w = 2.0 * math.pi * 2.0
    t = np.arange(0.0, 5.0, DT)
    amp = 0.02
    est = []
    for tk in t:
        roll_rate = amp * w * math.cos(w * tk)
        est.append(kinematics.roll_complementary_filter(buf, 0, 0.0, roll_rate, True, DT, 0.015,
                                                        0.5))
    est = np.array(est)
    truth = amp * np.sin(w * t)
    tail = t > 3.0
    assert np.sqrt(np.mean((est[tail] - truth[tail]) ** 2)) < 0.2 * amp


def test_complementary_filter_bounds_a_roll_rate_offset_and_converges_to_static() -> None:
    buf = np.full(1, np.nan)
    gain, tau, offset, ay = 0.015, 0.5, 0.01, 4.0
    for _ in range(1000):
        roll = kinematics.roll_complementary_filter(buf, 0, ay, offset, True, DT, gain, tau)
    # phi -> phi_static + offset * tau, not a ramp.
    assert roll == pytest.approx(gain * ay + offset * tau, rel=1e-3)
    # Roll rate invalid: the gyro (and its offset) is ignored.
    for _ in range(1000):
        roll = kinematics.roll_complementary_filter(buf, 0, ay, 5.0, False, DT, gain, tau)
    assert roll == pytest.approx(gain * ay, rel=1e-6)


def test_gravity_compensation_removes_the_roll_component() -> None:
    ay_true, roll = 3.0, 0.04
    measured = ay_true + G * math.sin(roll)
    assert kinematics.compensate_gravity_ay(measured, roll) == pytest.approx(ay_true)


# ----------------------------------------------------------------------------- offsets


def test_gyro_offset_settles_in_the_paper_time_at_standstill_and_freezes_when_moving() -> None:
    buf = np.zeros(len(inputs.Offsets))
    true_offset = 0.01
    rng = np.random.default_rng(0)
    n_settle = int(inputs.GYRO_OFFSET_SETTLING_S / DT)
    for _ in range(n_settle):
        measured = true_offset + 0.002 * rng.standard_normal()
        inputs.update_gyro_offset(buf, 0, inputs.Offsets.YAW_RATE, measured, True, DT, 150.0)
    # 2 % settling criterion (plus noise).
    assert buf[inputs.Offsets.YAW_RATE] == pytest.approx(true_offset, rel=0.03)
    held = buf[inputs.Offsets.YAW_RATE]
    for _ in range(1000):  # moving: a turning car's yaw rate must not leak in
        inputs.update_gyro_offset(buf, 0, inputs.Offsets.YAW_RATE, 0.5, False, DT, 150.0)
    assert buf[inputs.Offsets.YAW_RATE] == held


def test_standstill_timer_needs_all_wheels_valid_and_slow() -> None:
    buf = np.zeros(len(inputs.Offsets))
    for _ in range(50):
        inputs.update_standstill(buf, 0, 0.0, True, DT, 0.05)
    assert buf[inputs.Offsets.STANDSTILL_TIME] == pytest.approx(0.5)
    assert inputs.update_standstill(buf, 0, 0.0, False, DT, 0.05) == 0.0
    inputs.update_standstill(buf, 0, 0.0, True, DT, 0.05)
    assert inputs.update_standstill(buf, 0, 1.0, True, DT, 0.05) == 0.0


def test_ax_offset_activation_follows_the_paper_conditions() -> None:
    assert inputs.ax_offset_active(10.0, 0.5, 0.0, 1.0)
    assert not inputs.ax_offset_active(0.5, 0.5, 0.0, 1.0)  # not moving
    assert not inputs.ax_offset_active(10.0, 1.2, 0.0, 1.0)  # |ax| >= 1 m/s^2
    assert not inputs.ax_offset_active(10.0, 0.5, math.radians(6.0), 1.0)  # |r| > 5 deg/s
    assert inputs.ax_offset_active(10.0, -0.9, -math.radians(4.9), 1.0)


def test_ax_offset_converges_to_the_accelerometer_bias() -> None:
    buf = np.zeros(len(inputs.Offsets))
    bias = 0.2
    for k in range(int(1500.0 / DT)):
        dvx_dt = 0.5 * math.sin(0.3 * k * DT)  # gentle speed changes
        inputs.update_ax_offset(buf, 0, dvx_dt + bias, dvx_dt, True, DT, 1500.0)
    assert buf[inputs.Offsets.AX] == pytest.approx(bias, rel=0.03)
    inputs.update_ax_offset(buf, 0, 50.0, 0.0, False, DT, 1500.0)  # inactive: held
    assert buf[inputs.Offsets.AY] == 0.0
    assert buf[inputs.Offsets.AX] == pytest.approx(bias, rel=0.03)


def test_ay_offset_eq21_is_unbiased_in_a_steady_turn() -> None:
    # Steady circle: Ay = r vx exactly (vy' = 0); the measured ay carries a bias.
    buf = np.zeros(len(inputs.Offsets))
    bias, yaw_rate, vx = -0.15, 0.3, 15.0
    for _ in range(int(1500.0 / DT)):
        inputs.update_ay_offset(buf, 0, yaw_rate * vx + bias, yaw_rate, vx, True, DT, 1500.0)
    assert buf[inputs.Offsets.AY] == pytest.approx(bias, rel=0.03)


# ----------------------------------------------------------------------------- vx from wheels

TRACK_F, TRACK_R = 1.3868, 1.3640


def _rolling_wheel_speeds(vx, vy, yaw_rate, steer):
    """Wheel speeds of a car without longitudinal slip or tyre slip angle on the front.

    Rear wheels roll along x (speed = their x velocity); front wheels roll along their
    heading, so their x velocity is speed * cos(steer) (the assumption of eq. 11)."""
    speeds = []
    for y, front in (
        (TRACK_F / 2, True),
        (-TRACK_F / 2, True),
        (TRACK_R / 2, False),
        (-TRACK_R / 2, False),
    ):
        wheel_vx = vx - yaw_rate * y
        speeds.append(wheel_vx / math.cos(steer) if front else wheel_vx)
    return speeds


@settings(max_examples=100, deadline=None)
@given(
    st.floats(1.0, 60.0),
    st.floats(-1.0, 1.0),
    st.floats(-0.1, 0.1),
)
def test_eq11_compensation_recovers_vx_for_every_wheel(vx, yaw_rate, steer) -> None:
    wheels = _rolling_wheel_speeds(vx, 0.0, yaw_rate, steer)
    got = kinematics.compensate_wheel_speeds(*wheels, steer, yaw_rate, TRACK_F, TRACK_R)
    assert got == pytest.approx([vx] * 4, abs=1e-9)


def _run_vx(speeds_per_tick, ax, valid=(True, True, True, True), steer=0.0, yaw_rate=0.0):
    buf = np.full(len(wheel_speed.Wheels), np.nan)
    vx_prev = math.nan
    mode = math.nan
    for speeds in speeds_per_tick:
        vx_prev, mode = wheel_speed.vx_from_wheels(
            buf,
            0,
            *speeds,
            *valid,
            steer,
            yaw_rate,
            ax,
            vx_prev,
            TRACK_F,
            TRACK_R,
            DT,
            1.0,
            4.5,
            1.0,
        )
    return vx_prev, mode


def test_weighted_mean_discards_a_spinning_wheel_at_small_ax() -> None:
    # Cruising at 20 m/s (ax 0.3); the rear-left wheel starts spinning up on ice at 15 m/s^2.
    ticks = []
    for k in range(300):
        spin = max(0.0, (k - 100) * DT * 15.0)
        ticks.append((20.0, 20.0, 20.0 + spin, 20.0))
    vx, mode = _run_vx(ticks, ax=0.3)
    assert mode == wheel_speed.VxMode.WEIGHTED_MEAN
    assert vx == pytest.approx(20.0, abs=0.05)  # plain mean would read 20 + 30/4 = 27.5


def test_min_selection_discards_spinning_wheels_when_accelerating() -> None:
    vx, mode = _run_vx([(20.0, 20.1, 23.0, 24.0)] * 5, ax=2.0)
    assert mode == wheel_speed.VxMode.MIN and vx == pytest.approx(20.0)


def test_max_selection_discards_a_locked_wheel_when_braking() -> None:
    vx, mode = _run_vx([(20.0, 0.0, 19.9, 19.8)] * 5, ax=-6.0)
    assert mode == wheel_speed.VxMode.MAX and vx == pytest.approx(20.0)


def test_locked_wheel_is_also_dropped_by_the_weights_in_gentle_braking() -> None:
    ticks = [(20.0, 20.0, 20.0, 20.0)] * 50 + [
        (20.0, 20.0 - 2.0 * k, 20.0, 20.0) for k in range(10)
    ]
    ticks += [(20.0, 0.0, 20.0, 20.0)] * 50
    vx, mode = _run_vx(ticks, ax=-0.5)
    assert mode == wheel_speed.VxMode.WEIGHTED_MEAN and vx == pytest.approx(20.0, abs=0.05)


def test_invalid_wheels_take_no_part_and_none_valid_gives_nan() -> None:
    vx, _ = _run_vx([(20.0, 20.0, 0.0, 99.0)] * 5, ax=0.0, valid=(True, True, False, False))
    assert vx == pytest.approx(20.0)
    vx, mode = _run_vx([(20.0, 20.0, 20.0, 20.0)] * 5, ax=0.0, valid=(False,) * 4)
    assert math.isnan(vx) and mode == wheel_speed.VxMode.NONE


def test_median_fallback_when_every_weight_underflows() -> None:
    buf = np.full(len(wheel_speed.Wheels), np.nan)
    vx, mode = wheel_speed.vx_from_wheels(
        buf,
        0,
        10.0,
        11.0,
        12.0,
        40.0,
        True,
        True,
        True,
        True,
        0.0,
        0.0,
        0.0,
        500.0,
        TRACK_F,
        TRACK_R,
        DT,
        1.0,
        4.5,
        1.0,
    )
    assert mode == wheel_speed.VxMode.MEDIAN and vx == pytest.approx(11.5)


def _vx_reference(state, speeds, valid, steer, yaw_rate, ax, vx_prev, thr, s1, s2):
    """Plain-Python eq. 11-13 / Fig. 4 (second implementation for the 1e-12 comparison)."""
    wc = 2.0 * math.pi * filters.DERIVATIVE_CUTOFF_HZ
    comp = [
        speeds[0] * math.cos(steer) + yaw_rate * TRACK_F / 2,
        speeds[1] * math.cos(steer) - yaw_rate * TRACK_F / 2,
        speeds[2] + yaw_rate * TRACK_R / 2,
        speeds[3] - yaw_rate * TRACK_R / 2,
    ]
    used, weights = [], []
    for j in range(4):
        if not valid[j]:
            continue
        if math.isnan(state[j]):
            state[j], accel = comp[j], 0.0
        else:
            accel = wc * (comp[j] - state[j])
            state[j] += min(wc * DT, 1.0) * (comp[j] - state[j])
        e = (ax - accel) ** 2 / (2 * s1**2)
        if math.isfinite(vx_prev):
            e += (vx_prev - comp[j]) ** 2 / (2 * s2**2)
        used.append(comp[j])
        weights.append(math.exp(-e))
    if not used:
        return math.nan
    if ax > thr:
        return min(used)
    if ax < -thr:
        return max(used)
    if sum(weights) > 1e-9:
        return sum(w * v for w, v in zip(weights, used, strict=True)) / sum(weights)
    s = sorted(used)
    return s[len(s) // 2] if len(s) % 2 else 0.5 * (s[len(s) // 2 - 1] + s[len(s) // 2])


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.lists(st.floats(0.0, 40.0), min_size=4, max_size=4),
            st.lists(st.booleans(), min_size=4, max_size=4),
            st.floats(-0.2, 0.2),
            st.floats(-1.0, 1.0),
            st.floats(-8.0, 8.0),
        ),
        min_size=1,
        max_size=20,
    )
)
def test_vx_from_wheels_agrees_with_a_plain_reimplementation(ticks) -> None:
    buf = np.full(len(wheel_speed.Wheels), np.nan)
    ref_state = [math.nan] * 4
    vx_prev = ref_prev = math.nan
    for speeds, valid, steer, yaw_rate, ax in ticks:
        vx_prev, _ = wheel_speed.vx_from_wheels(
            buf,
            0,
            *speeds,
            *valid,
            steer,
            yaw_rate,
            ax,
            vx_prev,
            TRACK_F,
            TRACK_R,
            DT,
            1.0,
            4.5,
            1.0,
        )
        ref_prev = _vx_reference(
            ref_state, speeds, valid, steer, yaw_rate, ax, ref_prev, 1.0, 4.5, 1.0
        )
        if math.isnan(ref_prev):
            assert math.isnan(vx_prev)
        else:
            assert vx_prev == pytest.approx(ref_prev, abs=1e-12, rel=1e-12)
