"""Shared preprocessing blocks: the measurement conditioning every kinematic method needs.

The blocks come from Selmanaj, Corno, Panzani, Savaresi (2017), "Vehicle sideslip estimation: a
kinematic based approach" (sections 2.1, 2.3, 3, 3.1, 4) and Righetti & Lenzo (2025) section 3.1.
Every block is an ``@numba.njit(cache=True)`` function on scalars; blocks with memory keep it
in a caller-owned float64 buffer ``buf`` at offset ``i`` (``buf[i:i + <BLOCK>_LEN]``), so an
estimator packs all of them into its one state vector and nothing is allocated per tick.
A memory slot holding NaN means "not started": the block initialises itself from the first
sample it sees (no start-up spike), so a caller sets its slots to NaN at init/reset
(``reset_slots``).

Axes and signs are ISO 8855 throughout (x forward, y left, z up; yaw rate + turning left;
roll rate + right side down; pitch rate + nose down). Where a paper uses another sign the
docstring of the block says how it was converted.

Typical chain per tick (Selmanaj Fig. 6):

1. gyro offsets removed (``update_gyro_offset`` at standstill, section 4);
2. angular accelerations by ``derivative_filter`` (10 Hz, forward Euler, section 2.1);
3. accelerations moved to the CoG (``translate_to_cog``, section 3 / Righetti-Lenzo 3.1);
4. roll by ``roll_complementary_filter`` (eq. 16 + roll rate, Fig. 9) and gravity removed from
   ay (``compensate_gravity_ay``, eq. 17);
5. accelerometer offsets (``update_ax_offset``, ``update_ay_offset`` eq. 21, section 4);
6. vx from the wheels (``vx_from_wheels``, eq. 11-13, Fig. 4).
"""

from __future__ import annotations

import enum
import math

import numba as nb
import numpy as np

from slipd.channels import VALID, G, In, Veh

#: Cut-off of every derivative filter (Selmanaj section 2.1: "derivative filters with a cutoff
#: frequency of 10 Hz", designed in continuous time and discretised by forward Euler).
DERIVATIVE_CUTOFF_HZ = 10.0
#: Settling time of the gyro offset low-pass filters, s (Selmanaj section 4).
GYRO_OFFSET_SETTLING_S = 150.0
#: Settling time of the accelerometer offset low-pass filters, s (Selmanaj section 4).
ACCEL_OFFSET_SETTLING_S = 1500.0
#: Ax offset activation (Selmanaj section 4): |Ax_off| < 1 m/s^2 and |yaw rate| <= 5 deg/s.
AX_OFFSET_MAX_AX = 1.0
AX_OFFSET_MAX_YAW_RATE = math.radians(5.0)
#: First-order settling time (2 % band) = SETTLING_TIME_CONSTANTS * time constant. The paper
#: gives settling times, not time constants; e^-4 = 1.8 % is the usual 2 % criterion.
SETTLING_TIME_CONSTANTS = 4.0


# ---------------------------------------------------------------------------------------------
# Memory layouts (offsets inside a block's slice of the caller's buffer)
# ---------------------------------------------------------------------------------------------

#: ``derivative_filter`` / ``lowpass`` keep one value: the low-passed signal.
FILTER_LEN = 1
#: ``roll_complementary_filter`` keeps one value: the roll estimate, rad.
ROLL_LEN = 1


@enum.unique
class Offsets(enum.IntEnum):
    """Slots of the offset block (``OFFSETS_LEN`` values). Offsets are in SI units of their
    channel and are *subtracted* from the measurement."""

    YAW_RATE = 0  # rad/s
    ROLL_RATE = 1  # rad/s
    PITCH_RATE = 2  # rad/s
    AX = 3  # m/s^2, at the CoG after gravity compensation (Selmanaj Fig. 10)
    AY = 4  # m/s^2, at the CoG after gravity compensation (Selmanaj Fig. 11, eq. 21)
    STANDSTILL_TIME = 5  # s the car has been standing still without interruption


OFFSETS_LEN = len(Offsets)
# Plain ints for the kernels (numba cannot convert an IntEnum member to float).
_OFF_AX = int(Offsets.AX)
_OFF_AY = int(Offsets.AY)
_OFF_STANDSTILL = int(Offsets.STANDSTILL_TIME)


@enum.unique
class Wheels(enum.IntEnum):
    """Slots of the wheel-speed block (``WHEELS_LEN`` values): the derivative-filter memory of
    each compensated wheel speed (eq. 11) used by the weights of eq. 13."""

    FL = 0
    FR = 1
    RL = 2
    RR = 3


WHEELS_LEN = len(Wheels)
_W_FL, _W_FR, _W_RL, _W_RR = (int(w) for w in Wheels)


@enum.unique
class VxMode(enum.IntEnum):
    """Which branch of Selmanaj Fig. 4 produced vx (returned as a float by ``vx_from_wheels``)."""

    NONE = 0  # no valid wheel speed: vx is NaN
    MIN = 1  # accelerating: slowest wheel
    WEIGHTED_MEAN = 2  # |ax| below the threshold: eq. 12-13
    MAX = 3  # braking: fastest wheel
    MEDIAN = 4  # weighted mean with every weight ~0 (all wheels disagree): median fallback


_MODE_NONE = float(VxMode.NONE)
_MODE_MIN = float(VxMode.MIN)
_MODE_MEAN = float(VxMode.WEIGHTED_MEAN)
_MODE_MAX = float(VxMode.MAX)
_MODE_MEDIAN = float(VxMode.MEDIAN)


def reset_slots(buf: np.ndarray, start: int, length: int) -> None:
    """Mark ``buf[start:start + length]`` as not started (NaN); the blocks self-initialise."""
    buf[start : start + length] = np.nan


def reset_offsets(buf: np.ndarray, start: int) -> None:
    """Zero offsets and standstill timer (offsets are estimates, not filters: 0 is their prior;
    the daemon may overwrite them with the values persisted at the last key-off)."""
    buf[start : start + OFFSETS_LEN] = 0.0


# ---------------------------------------------------------------------------------------------
# Filters (Selmanaj section 2.1)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def lowpass(buf, i, signal, dt, time_constant):
    """First-order low-pass y' = (signal - y) / time_constant, forward Euler; returns y.

    ``buf[i]`` is y; NaN starts the filter at ``signal``. The Euler step is clipped at one
    time constant so a long tick gap cannot make the filter overshoot.
    """
    if not math.isfinite(buf[i]):
        buf[i] = signal
        return signal
    gain = dt / time_constant
    if gain > 1.0:
        gain = 1.0
    buf[i] += gain * (signal - buf[i])
    return buf[i]


@nb.njit(cache=True)
def derivative_filter(buf, i, signal, dt, cutoff_hz):
    """Real derivative filter H(s) = s / (1 + s / wc), wc = 2 pi cutoff_hz, forward Euler.

    Selmanaj section 2.1: cut-off 10 Hz, continuous design discretised by forward Euler (at
    100 Hz wc*dt = 0.63 < 2, so the discrete filter is stable and close to the continuous one).
    Realised as wc * (signal - x) with the low-pass state x' = wc (signal - x) in ``buf[i]``.
    NaN in ``buf[i]`` starts the filter at ``signal`` (derivative 0, no start-up spike).
    """
    wc = 2.0 * math.pi * cutoff_hz
    if not math.isfinite(buf[i]):
        buf[i] = signal
        return 0.0
    derivative = wc * (signal - buf[i])
    step = wc * dt
    if step > 1.0:  # a long gap: land on the signal instead of overshooting it
        step = 1.0
    buf[i] += step * (signal - buf[i])
    return derivative


@nb.njit(cache=True)
def offset_time_constant(settling_time):
    """Time constant of a first-order filter that settles (2 %) in ``settling_time`` seconds."""
    return settling_time / SETTLING_TIME_CONSTANTS


# ---------------------------------------------------------------------------------------------
# CoG translation (Selmanaj section 3; Righetti-Lenzo section 3.1)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def translate_to_cog(
    ax, ay, az, roll_rate, pitch_rate, yaw_rate, roll_acc, pitch_acc, yaw_acc, imu_x, imu_y, imu_z
):
    """Accelerations at the CoG from those measured at the IMU (rigid body).

    a_cog = a_imu - omega_dot x r - omega x (omega x r), with r = (imu_x, imu_y, imu_z) the IMU
    position relative to the CoG, omega = (roll_rate, pitch_rate, yaw_rate) and omega_dot the
    angular accelerations (from ``derivative_filter``). Righetti-Lenzo section 3.1 writes the
    planar case with PG = -r: a_cog = a_P + r_dot k x PG - r^2 PG. Returns (ax, ay, az).
    """
    # omega_dot x r
    ex = pitch_acc * imu_z - yaw_acc * imu_y
    ey = yaw_acc * imu_x - roll_acc * imu_z
    ez = roll_acc * imu_y - pitch_acc * imu_x
    # omega x r, then omega x (omega x r)
    cx = pitch_rate * imu_z - yaw_rate * imu_y
    cy = yaw_rate * imu_x - roll_rate * imu_z
    cz = roll_rate * imu_y - pitch_rate * imu_x
    qx = pitch_rate * cz - yaw_rate * cy
    qy = yaw_rate * cx - roll_rate * cz
    qz = roll_rate * cy - pitch_rate * cx
    return ax - ex - qx, ay - ey - qy, az - ez - qz


@nb.njit(cache=True)
def imu_at_cog(
    state,
    yaw_slot,
    roll_slot,
    pitch_slot,
    u,
    yaw_rate,
    roll_rate,
    pitch_rate,
    dt,
    cutoff_hz,
    vehicle,
):
    """The IMU's ax and ay at the CoG: the three rates' derivatives (derivative_filter, its
    memories in state[yaw_slot], [roll_slot], [pitch_slot]) and translate_to_cog with the
    profile's IMU position; an invalid acceleration enters as 0 (the caller decides the
    fallback). Returns (ax, ay, yaw_acc, ax_ok, ay_ok)."""
    yaw_acc = derivative_filter(state, yaw_slot, yaw_rate, dt, cutoff_hz)
    roll_acc = derivative_filter(state, roll_slot, roll_rate, dt, cutoff_hz)
    pitch_acc = derivative_filter(state, pitch_slot, pitch_rate, dt, cutoff_hz)
    ax_imu, ax_ok = channel(u, In.AX)
    ay_imu, ay_ok = channel(u, In.AY)
    ax, ay, _ = translate_to_cog(
        ax_imu if ax_ok else 0.0, ay_imu if ay_ok else 0.0, 0.0,
        roll_rate, pitch_rate, yaw_rate, roll_acc, pitch_acc, yaw_acc,
        vehicle[Veh.IMU_X], vehicle[Veh.IMU_Y], vehicle[Veh.IMU_Z],
    )  # fmt: skip
    return ax, ay, yaw_acc, ax_ok, ay_ok


@nb.njit(cache=True)
def translate_to_cog_planar(ax, ay, yaw_rate, yaw_acc, imu_x, imu_y):
    """Planar special case of ``translate_to_cog`` (Righetti-Lenzo section 3.1):
    ax_cog = ax + r_dot imu_y + r^2 imu_x,  ay_cog = ay - r_dot imu_x + r^2 imu_y."""
    yaw_rate_sq = yaw_rate * yaw_rate
    return (
        ax + yaw_acc * imu_y + yaw_rate_sq * imu_x,
        ay - yaw_acc * imu_x + yaw_rate_sq * imu_y,
    )


# ---------------------------------------------------------------------------------------------
# Roll and gravity compensation (Selmanaj section 3.1)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def roll_static_gain(mass, roll_arm, roll_stiffness):
    """Static roll per unit of *measured* lateral acceleration, rad / (m/s^2).

    Selmanaj eq. 16 is theta = -M h / (K_s L^2) * Ay in the paper's roll sign; in ISO 8855
    (roll + right side down, a left turn rolls the body to the right) the sign is +. With the
    total roll stiffness K_roll (Nm/rad) and the sprung mass at arm h above the roll axis, the
    steady roll balance is K_roll phi = M h (Ay + g phi). The accelerometer measures
    Ay_meas = Ay + g sin(phi) (eq. 17), so phi = M h / K_roll * Ay_meas exactly (small angle):
    using the measured ay keeps the gravity (jacking) moment without another parameter.
    """
    if roll_stiffness <= 0.0:
        return 0.0
    return mass * roll_arm / roll_stiffness


@nb.njit(cache=True)
def roll_complementary_filter(
    buf, i, ay_measured, roll_rate, roll_rate_valid, dt, static_gain, time_constant
):
    """Roll angle from the static model (eq. 16) and the roll rate (Selmanaj Fig. 9).

    Complementary filter phi' = p + (phi_static - phi) / tau: the high frequencies come from
    integrating the roll rate p, the low ones from the low-passed static model
    phi_static = static_gain * ay_measured (``roll_static_gain``); a gyro offset can only
    bias phi by p_offset * tau instead of drifting. When the roll rate is invalid the filter
    falls back to the low-passed static model. ``buf[i]`` is phi (NaN: start at phi_static).
    """
    phi_static = static_gain * ay_measured
    if not math.isfinite(buf[i]):
        buf[i] = phi_static
        return phi_static
    rate = roll_rate if roll_rate_valid else 0.0
    gain = dt / time_constant
    if gain > 1.0:
        gain = 1.0
    buf[i] += dt * rate + gain * (phi_static - buf[i])
    return buf[i]


@nb.njit(cache=True)
def compensate_gravity_ay(ay_cog, roll):
    """Selmanaj eq. 17: Ay_off = Ay_CG - g sin(theta). In ISO 8855 a body rolled by phi
    (right side down) senses +g sin(phi) on its y axis, which this removes."""
    return ay_cog - G * math.sin(roll)


# ---------------------------------------------------------------------------------------------
# Online offsets (Selmanaj section 4)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def update_standstill(buf, i, max_wheel_speed, all_wheels_valid, dt, speed_threshold):
    """Time the car has been standing still, kept in ``buf[i + Offsets.STANDSTILL_TIME]``.

    Standstill: every wheel speed valid and below ``speed_threshold``. Returns the time, s.
    """
    slot = i + _OFF_STANDSTILL
    if all_wheels_valid and max_wheel_speed < speed_threshold:
        buf[slot] += dt
    else:
        buf[slot] = 0.0
    return buf[slot]


@nb.njit(cache=True)
def _offset_filter(buf, slot, residual, active, dt, settling_time):
    # Selmanaj section 4: "When the logic is not active the filters are stopped and their
    # state held at the values of deactivation."
    if active and math.isfinite(residual):
        gain = dt / offset_time_constant(settling_time)
        if gain > 1.0:
            gain = 1.0
        buf[slot] += gain * (residual - buf[slot])
    return buf[slot]


@nb.njit(cache=True)
def update_gyro_offset(buf, i, slot, rate_measured, standstill, dt, settling_time):
    """Gyro offset of channel ``slot`` (Offsets.YAW_RATE/ROLL_RATE/PITCH_RATE).

    Selmanaj section 4: gyros are not affected by gravity, so at standstill the raw rate is
    the offset, whatever the attitude; low-pass with ``settling_time`` (paper: 150 s) while
    ``standstill`` holds, frozen otherwise. Returns the offset (subtract it from the rate).
    """
    return _offset_filter(buf, i + slot, rate_measured, standstill, dt, settling_time)


@nb.njit(cache=True)
def ax_offset_active(vx, ax_off, yaw_rate, min_speed):
    """Selmanaj section 4, conditions of Fig. 10: moving (vx > ``min_speed``, the paper's
    Vx > 0 with a margin for the wheel-speed resolution), |Ax_off| < 1 m/s^2 (pitch and slip
    small) and |yaw rate| <= 5 deg/s (no lateral dynamics)."""
    return (
        vx > min_speed
        and abs(ax_off) < AX_OFFSET_MAX_AX
        and abs(yaw_rate) <= AX_OFFSET_MAX_YAW_RATE
    )


@nb.njit(cache=True)
def update_ax_offset(buf, i, ax_off, dvx_dt, active, dt, settling_time):
    """Ax offset (Selmanaj Fig. 10): low-pass of Ax_off - dVx/dt in the selected conditions.

    ``ax_off`` is the CoG, gravity-compensated ax still carrying its offset; ``dvx_dt`` the
    derivative-filtered wheel-based vx (free of offsets by construction). Settling time
    1500 s in the paper. Returns the offset.
    """
    return _offset_filter(buf, i + _OFF_AX, ax_off - dvx_dt, active, dt, settling_time)


@nb.njit(cache=True)
def update_ay_offset(buf, i, ay_off, yaw_rate, vx, active, dt, settling_time):
    """Ay offset, Selmanaj eq. 21: Delta_Ay = LP[Ay_off - omega_z Vx].

    From the kinematic model (eq. 18-19) with E[dVy/dt] ~ 0 over a route that starts and ends
    straight (eq. 20). On a permanently banked road it also absorbs the bank's gravity
    component, which the paper calls the correct behaviour. Returns the offset.
    """
    return _offset_filter(buf, i + _OFF_AY, ay_off - yaw_rate * vx, active, dt, settling_time)


# ---------------------------------------------------------------------------------------------
# Vx from the wheel speeds (Selmanaj section 2.3)
# ---------------------------------------------------------------------------------------------


@nb.njit(cache=True)
def channel(u, ch):
    """(value, ok) of input channel ``ch``: ok when its validity flag is set and it is finite."""
    v = u[ch]
    return v, (u[VALID + ch] > 0.5 and math.isfinite(v))


@nb.njit(cache=True)
def gaussian_bell(a, sigma_a, b, sigma_b):
    """exp(-(a^2 / sigma_a^2 + b^2 / sigma_b^2) / 2): Selmanaj eq. 5-7's bivariate Gaussian, 1 at
    (0, 0), -> 0 when either argument grows (also Chen's straight-running weight)."""
    x = a / sigma_a
    y = b / sigma_b
    return math.exp(-0.5 * (x * x + y * y))


@nb.njit(cache=True)
def corner_speed_mean(u, steer, yaw_rate, vehicle):
    """Mean of the valid wheel speeds referred to the CoG (compensate_wheel_speeds; the corner
    velocities of Righetti-Lenzo eq. 5-6). Returns (vx [m/s], number of valid wheels); a wheel
    counts when its validity flag is set and its value is finite."""
    corner_fl, corner_fr, corner_rl, corner_rr = compensate_wheel_speeds(
        u[In.WHEEL_SPEED_FL], u[In.WHEEL_SPEED_FR], u[In.WHEEL_SPEED_RL], u[In.WHEEL_SPEED_RR],
        steer, yaw_rate, vehicle[Veh.TRACK_F], vehicle[Veh.TRACK_R],
    )  # fmt: skip
    total = 0.0
    count = 0
    if channel(u, In.WHEEL_SPEED_FL)[1]:
        total += corner_fl
        count += 1
    if channel(u, In.WHEEL_SPEED_FR)[1]:
        total += corner_fr
        count += 1
    if channel(u, In.WHEEL_SPEED_RL)[1]:
        total += corner_rl
        count += 1
    if channel(u, In.WHEEL_SPEED_RR)[1]:
        total += corner_rr
        count += 1
    if count == 0:
        return 0.0, 0
    return total / count, count


@nb.njit(cache=True)
def compensate_wheel_speeds(v_fl, v_fr, v_rl, v_rr, steer, yaw_rate, track_f, track_r):
    """Wheel speeds referred to the CoG's x velocity, Selmanaj eq. 11.

    The front wheels roll along their steer angle (cos delta); yaw moves each wheel by
    omega_z * y_wheel. In ISO 8855 the left wheels sit at y = +track/2 and move at
    vx - omega_z track/2 (the paper's eq. 11 prints the opposite sign in its own convention),
    so the left ones get + omega_z track/2 and the right ones - omega_z track/2. The paper
    assumes equal tracks; this keeps the front and rear ones apart.
    Returns (v_fl, v_fr, v_rl, v_rr) compensated.
    """
    cos_steer = math.cos(steer)
    half_f = 0.5 * track_f * yaw_rate
    half_r = 0.5 * track_r * yaw_rate
    return (
        v_fl * cos_steer + half_f,
        v_fr * cos_steer - half_f,
        v_rl + half_r,
        v_rr - half_r,
    )


@nb.njit(cache=True)
def wheel_weight(ax, wheel_accel, vx_prev, wheel_speed, sigma_w1, sigma_w2):
    """Reliability weight of one wheel, Selmanaj eq. 13 (bivariate Gaussian, Fig. 5):
    W = exp(-(Ax - dV_i/dt)^2 / (2 sigma_w1^2) - (vx_prev - V_i)^2 / (2 sigma_w2^2)).
    A non-finite ``vx_prev`` (first tick) drops the second term."""
    accel_error = ax - wheel_accel
    exponent = accel_error * accel_error / (2.0 * sigma_w1 * sigma_w1)
    if math.isfinite(vx_prev):
        speed_error = vx_prev - wheel_speed
        exponent += speed_error * speed_error / (2.0 * sigma_w2 * sigma_w2)
    return math.exp(-exponent)


@nb.njit(cache=True)
def _wheel_update(buf, slot, speed, valid, ax, vx_prev, dt, sigma_w1, sigma_w2):
    # The derivative filter only sees valid samples (an invalid one would be a step to 0).
    if not valid:
        return 0.0
    wheel_accel = derivative_filter(buf, slot, speed, dt, DERIVATIVE_CUTOFF_HZ)
    return wheel_weight(ax, wheel_accel, vx_prev, speed, sigma_w1, sigma_w2)


@nb.njit(cache=True)
def vx_from_wheels(
    buf,
    i,
    v_fl,
    v_fr,
    v_rl,
    v_rr,
    valid_fl,
    valid_fr,
    valid_rl,
    valid_rr,
    steer,
    yaw_rate,
    ax,
    vx_prev,
    track_f,
    track_r,
    dt,
    ax_threshold,
    sigma_w1,
    sigma_w2,
):
    """Longitudinal speed from the four wheel speeds, Selmanaj section 2.3 (Fig. 4, eq. 11-13).

    Wheel speeds are first compensated for steer and yaw (eq. 11, ``compensate_wheel_speeds``).
    Then by the ax thresholds of Fig. 4:
    - ax > ax_threshold (accelerating, wheels spin faster than the car): the slowest wheel;
    - ax < -ax_threshold (braking, wheels slower): the fastest wheel;
    - otherwise the weighted mean of eq. 12 with the weights of eq. 13 (``wheel_weight``),
      which drops a wheel whose derivative disagrees with ax or whose speed disagrees with
      the previous estimate ``vx_prev`` (a spinning or locking wheel). If every weight
      underflows (all wheels disagree with vx_prev, e.g. after an outage) the median of the
      valid wheels is used instead of dividing by ~0.
    Invalid wheels take no part in any branch; their derivative-filter memory is held.

    ``buf[i + Wheels.*]``: derivative-filter memory per wheel (NaN at start). ``ax``: the
    corrected CoG ax (m/s^2); ``vx_prev``: the previous vx estimate (NaN if none);
    table 1: ax_threshold 1 m/s^2, sigma_w1 4.5, sigma_w2 1.
    Returns (vx, mode) with mode a ``VxMode`` value as float; vx is NaN with no valid wheel.
    """
    c_fl, c_fr, c_rl, c_rr = compensate_wheel_speeds(
        v_fl, v_fr, v_rl, v_rr, steer, yaw_rate, track_f, track_r
    )
    w_fl = _wheel_update(buf, i + _W_FL, c_fl, valid_fl, ax, vx_prev, dt, sigma_w1, sigma_w2)
    w_fr = _wheel_update(buf, i + _W_FR, c_fr, valid_fr, ax, vx_prev, dt, sigma_w1, sigma_w2)
    w_rl = _wheel_update(buf, i + _W_RL, c_rl, valid_rl, ax, vx_prev, dt, sigma_w1, sigma_w2)
    w_rr = _wheel_update(buf, i + _W_RR, c_rr, valid_rr, ax, vx_prev, dt, sigma_w1, sigma_w2)

    n_valid = 0
    lowest = math.inf
    highest = -math.inf
    total = 0.0
    weight_sum = 0.0
    weighted = 0.0
    # Unrolled over the four wheels: no temporary arrays in the per-tick path.
    if valid_fl:
        n_valid += 1
        lowest = min(lowest, c_fl)
        highest = max(highest, c_fl)
        total += c_fl
        weight_sum += w_fl
        weighted += w_fl * c_fl
    if valid_fr:
        n_valid += 1
        lowest = min(lowest, c_fr)
        highest = max(highest, c_fr)
        total += c_fr
        weight_sum += w_fr
        weighted += w_fr * c_fr
    if valid_rl:
        n_valid += 1
        lowest = min(lowest, c_rl)
        highest = max(highest, c_rl)
        total += c_rl
        weight_sum += w_rl
        weighted += w_rl * c_rl
    if valid_rr:
        n_valid += 1
        lowest = min(lowest, c_rr)
        highest = max(highest, c_rr)
        total += c_rr
        weight_sum += w_rr
        weighted += w_rr * c_rr

    if n_valid == 0:
        return math.nan, _MODE_NONE
    if ax > ax_threshold:
        return lowest, _MODE_MIN
    if ax < -ax_threshold:
        return highest, _MODE_MAX
    if weight_sum > 1e-9:
        return weighted / weight_sum, _MODE_MEAN
    # Median of up to four values without sorting: drop the extremes, average the rest.
    if n_valid >= 3:
        return (total - lowest - highest) / (n_valid - 2), _MODE_MEDIAN
    return total / n_valid, _MODE_MEDIAN
