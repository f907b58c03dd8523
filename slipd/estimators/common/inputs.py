"""Reading the per-tick input vector ``u``: channels with their validity, the wheel speeds,
the IMU at the CoG with fallbacks (the one reader), and the offsets learnt at standstill.

``u`` holds each canonical channel's value, its validity flag at ``VALID + ch`` and the tick
time (``slipd.channels``). A channel is usable when its flag is set and its value is finite.

Memory of the blocks that keep some lives in the caller's state at an offset (``ImuMemory``,
``Offsets``), so a method packs them into its one state vector (``layout.build_layout``).
"""

from __future__ import annotations

import enum
import math

import numpy as np

from slipd.channels import (
    ST_DEGRADED,
    ST_INPUT_TIMEOUT,
    VALID,
    G,
    In,
    Veh,
)
from slipd.estimators.common.filters import (
    butterworth_lowpass,
    derivative_filter,
)
from slipd.estimators.common.kinematics import (
    compensate_wheel_speeds,
    remove_roll_gravity,
    translate_to_cog,
    translate_to_cog_planar,
)
from slipd.numba_cache import nb


@nb.njit(cache=True, inline="always")
def channel(u, ch):
    """(value, ok) of input channel ``ch``: ok when its validity flag is set and it is finite."""
    v = u[ch]
    return v, (u[VALID + ch] > 0.5 and math.isfinite(v))


@nb.njit(cache=True, inline="always")
def accel_carries_gravity(u, vehicle):
    """Whether the accelerometer's a_y carries g sin(roll): not where the profile declares it
    levelled (``Veh.ACCEL_LEVEL``, an INS), nor where its az, when on the bus, reads no
    gravity (a levelled sensor's az is ~0, a body-fixed one's ~g), so an INS whose profile
    does not say so is still told apart."""
    if vehicle[Veh.ACCEL_LEVEL] > 0.5:
        return False
    az, az_ok = channel(u, In.AZ)
    return not az_ok or abs(az) > 0.5 * G


@nb.njit(cache=True, inline="always")
def wheel_speeds(u):
    """The four linear wheel speeds and their ``channel`` flags:
    (v_fl, v_fr, v_rl, v_rr, ok_fl, ok_fr, ok_rl, ok_rr)."""
    v_fl, ok_fl = channel(u, In.WHEEL_SPEED_FL)
    v_fr, ok_fr = channel(u, In.WHEEL_SPEED_FR)
    v_rl, ok_rl = channel(u, In.WHEEL_SPEED_RL)
    v_rr, ok_rr = channel(u, In.WHEEL_SPEED_RR)
    return v_fl, v_fr, v_rl, v_rr, ok_fl, ok_fr, ok_rl, ok_rr


@nb.njit(cache=True, inline="always")
def corner_speed_mean(u, steer, yaw_rate, vehicle):
    """Mean of the valid wheel speeds referred to the CoG (``compensate_wheel_speeds``; the
    corner velocities of Righetti-Lenzo eq. 5-6). Returns (vx [m/s], number of valid wheels)."""
    v_fl, v_fr, v_rl, v_rr, ok_fl, ok_fr, ok_rl, ok_rr = wheel_speeds(u)
    corner_fl, corner_fr, corner_rl, corner_rr = compensate_wheel_speeds(
        v_fl, v_fr, v_rl, v_rr, steer, yaw_rate, vehicle[Veh.TRACK_F], vehicle[Veh.TRACK_R]
    )
    total = 0.0
    count = 0
    if ok_fl:
        total += corner_fl
        count += 1
    if ok_fr:
        total += corner_fr
        count += 1
    if ok_rl:
        total += corner_rl
        count += 1
    if ok_rr:
        total += corner_rr
        count += 1
    if count == 0:
        return 0.0, 0
    return total / count, count


@nb.njit(cache=True, inline="always")
def wheel_accelerations(state, base, u, dt, cutoff_hz):
    """d V_wi / dt of the raw wheel speeds by derivative filters (memory: four slots at
    ``base``, FL FR RL RR); an invalid wheel's filter is held and its rate is 0.
    Returns (a_fl, a_fr, a_rl, a_rr, ok_fl, ok_fr, ok_rl, ok_rr)."""
    v_fl, v_fr, v_rl, v_rr, ok_fl, ok_fr, ok_rl, ok_rr = wheel_speeds(u)
    a_fl = derivative_filter(state, base, v_fl, dt, cutoff_hz) if ok_fl else 0.0
    a_fr = derivative_filter(state, base + 1, v_fr, dt, cutoff_hz) if ok_fr else 0.0
    a_rl = derivative_filter(state, base + 2, v_rl, dt, cutoff_hz) if ok_rl else 0.0
    a_rr = derivative_filter(state, base + 3, v_rr, dt, cutoff_hz) if ok_rr else 0.0
    return a_fl, a_fr, a_rl, a_rr, ok_fl, ok_fr, ok_rl, ok_rr


@nb.njit(cache=True, inline="always")
def hold_last(state, slot, value, ok):
    """``value`` when ``ok`` (and remembered in ``state[slot]``), else the last one remembered."""
    if ok:
        state[slot] = value
        return value
    return state[slot]


# ---------------------------------------------------------------------------------------------
# the IMU at the CoG (Selmanaj section 3; Righetti-Lenzo section 3.1)
# ---------------------------------------------------------------------------------------------


@enum.unique
class ImuMemory(enum.IntEnum):
    """Slots of ``read_inputs``'s memory block (NaN = filter not started, see ``reset_imu``)."""

    D_YAW_RATE = 0  # derivative filters of the rates: the angular accelerations of the
    D_ROLL_RATE = 1  # CoG translation
    D_PITCH_RATE = 2
    ROLL = 3  # rad, roll of the gravity compensation (kinematics.roll_complementary_filter)
    LAST_AX = 4  # m/s^2, last valid CoG ax (held while ax is invalid)
    LAST_STEER = 5  # rad, last valid road-wheel steer
    # moments of the learnt gravity share of ay (kinematics.GravityMoments; 0 = no data)
    GRAVITY_W = 6
    GRAVITY_MX = 7
    GRAVITY_ME = 8
    GRAVITY_MXX = 9
    GRAVITY_MXE = 10
    # the accelerometers' vibration low-pass (filters.butterworth_lowpass; NaN = not started)
    AX_LOWPASS = 11
    AX_LOWPASS_2 = 12
    AY_LOWPASS = 13
    AY_LOWPASS_2 = 14
    YAW_RATE_LOWPASS = 15  # the same filter on the yaw rate: vy' = ay - r vx needs both
    YAW_RATE_LOWPASS_2 = 16  # delayed alike


#: The ImuMemory slots of the three low-pass filters (ax, ay, yaw rate), [first, end): plain
#: ints, so a kernel that resets them (kinematic_heuristic) uses the same span.
LOWPASS_FIRST = int(ImuMemory.AX_LOWPASS)
LOWPASS_END = int(ImuMemory.YAW_RATE_LOWPASS_2) + 1


def reset_imu(state: np.ndarray, base: int) -> None:
    """The ImuMemory block at ``base`` before the first tick: filters not started, nothing
    held yet (0)."""
    state[base : base + ImuMemory.ROLL + 1] = np.nan
    state[base + ImuMemory.LAST_AX] = 0.0
    state[base + ImuMemory.LAST_STEER] = 0.0
    reset_accel_lowpass(state, base)


def reset_accel_lowpass(state: np.ndarray, base: int) -> None:
    """The accelerometer low-pass filters of the ImuMemory block at ``base``: not started."""
    state[base + LOWPASS_FIRST : base + LOWPASS_END] = np.nan


@nb.njit(cache=True, inline="always")
def imu_at_cog(state, base, u, yaw_rate_in, roll_rate, pitch_rate, dt, cutoff_hz, vehicle,
               lever_arm_3d, accel_lowpass_hz):  # fmt: skip
    """The IMU's ax and ay at the CoG, an invalid one entering as 0 (the caller decides the
    fallback). The rates' derivatives come from derivative filters (memory: ImuMemory at
    ``base``); ``lever_arm_3d`` takes the full rigid body (``translate_to_cog``), else the
    planar case of Righetti-Lenzo eq. 21-23 (the roll and pitch filters are then not run).
    ``accel_lowpass_hz`` > 0: the raw ax, ay and the yaw rate pass a Butterworth low-pass
    first (slipd, the methods' ``accel_lowpass_hz``: a raw IMU on a car body carries ~1 m/s^2
    of vibration above 5 Hz, benchmarks/MEASUREMENTS.md; the yaw rate alike so that the
    kinematic balance sees both with one delay; a filter is held while its channel is invalid).
    Returns (ax, ay, yaw_rate, yaw_acc, ax_ok, ay_ok), yaw_rate filtered or as given."""
    yaw_rate = yaw_rate_in
    if accel_lowpass_hz > 0.0:
        yaw_rate = butterworth_lowpass(state, base + ImuMemory.YAW_RATE_LOWPASS, yaw_rate_in, dt,
                                       accel_lowpass_hz)  # fmt: skip
    elif not math.isfinite(state[base + ImuMemory.AX_LOWPASS]):
        # unused filters hold 0, not "not started" (a state read back is finite everywhere)
        for k in range(base + LOWPASS_FIRST, base + LOWPASS_END):
            state[k] = 0.0
    yaw_acc = derivative_filter(state, base + ImuMemory.D_YAW_RATE, yaw_rate, dt, cutoff_hz)
    ax_imu, ax_ok = channel(u, In.AX)
    ay_imu, ay_ok = channel(u, In.AY)
    if accel_lowpass_hz > 0.0:
        if ax_ok:
            ax_imu = butterworth_lowpass(state, base + ImuMemory.AX_LOWPASS, ax_imu, dt,
                                         accel_lowpass_hz)  # fmt: skip
        if ay_ok:
            ay_imu = butterworth_lowpass(state, base + ImuMemory.AY_LOWPASS, ay_imu, dt,
                                         accel_lowpass_hz)  # fmt: skip
    ax_in = ax_imu if ax_ok else 0.0
    ay_in = ay_imu if ay_ok else 0.0
    if lever_arm_3d:
        roll_acc = derivative_filter(state, base + ImuMemory.D_ROLL_RATE, roll_rate, dt,
                                     cutoff_hz)  # fmt: skip
        pitch_acc = derivative_filter(state, base + ImuMemory.D_PITCH_RATE, pitch_rate, dt,
                                      cutoff_hz)  # fmt: skip
        ax, ay, _ = translate_to_cog(
            ax_in, ay_in, 0.0, roll_rate, pitch_rate, yaw_rate, roll_acc, pitch_acc, yaw_acc,
            vehicle[Veh.IMU_X], vehicle[Veh.IMU_Y], vehicle[Veh.IMU_Z],
        )  # fmt: skip
    else:
        ax, ay = translate_to_cog_planar(
            ax_in, ay_in, yaw_rate, yaw_acc, vehicle[Veh.IMU_X], vehicle[Veh.IMU_Y]
        )
    return ax, ay, yaw_rate, yaw_acc, ax_ok, ay_ok


@nb.njit(cache=True, inline="always")
def read_inputs(state, base, u, vehicle, yaw_fallback, cutoff_hz, roll_time_constant,
                lever_arm_3d, dt, learn_roll_gain, accel_lowpass_hz):  # fmt: skip
    """The pre-processed IMU and steer of one tick, with fallbacks for invalid channels.

    - yaw rate: an invalid one is replaced by ``yaw_fallback`` (the caller's: its previous
      value or its model's);
    - steer and ax: the last valid value (ImuMemory.LAST_STEER, LAST_AX);
    - ax, ay moved to the CoG (``imu_at_cog``, 3-D or planar); an invalid ay is returned as 0
      with ay_ok False (the caller substitutes its model's or a held value);
    - with ``roll_time_constant`` > 0 the gravity component of the body roll is removed from
      a valid ay (``kinematics.remove_roll_gravity``, memory ImuMemory.ROLL), with the static
      roll gain learnt from the drive when ``learn_roll_gain`` (memory ImuMemory.GRAVITY_*,
      the wheels' CoG speed as vx), else the profile's.

    ``status``: INPUT_TIMEOUT when the yaw rate, steer, ax or ay is not real; DEGRADED when a
    rate the pre-processing uses is missing (roll and pitch for the 3-D lever arm, roll for
    the roll compensation). Returns (ax, ay, yaw_rate, yaw_acc, steer, roll_rate, ax_ok,
    ay_ok, yaw_rate_ok, steer_ok, status); roll_rate is 0 where it is invalid.
    """
    status = 0
    yaw_rate, yaw_rate_ok = channel(u, In.YAW_RATE)
    if not yaw_rate_ok:
        yaw_rate = yaw_fallback
        status |= ST_INPUT_TIMEOUT
    steer, steer_ok = channel(u, In.STEER)
    steer = hold_last(state, base + ImuMemory.LAST_STEER, steer, steer_ok)
    if not steer_ok:
        status |= ST_INPUT_TIMEOUT
    roll_rate, roll_rate_ok = channel(u, In.ROLL_RATE)
    pitch_rate, pitch_rate_ok = channel(u, In.PITCH_RATE)
    if lever_arm_3d and not (roll_rate_ok and pitch_rate_ok):
        status |= ST_DEGRADED  # optional inputs: the translation falls back toward planar
    roll_rate = roll_rate if roll_rate_ok else 0.0
    pitch_rate = pitch_rate if pitch_rate_ok else 0.0
    ax, ay, yaw_rate, yaw_acc, ax_ok, ay_ok = imu_at_cog(
        state, base, u, yaw_rate, roll_rate, pitch_rate, dt, cutoff_hz, vehicle, lever_arm_3d,
        accel_lowpass_hz,
    )
    ax = hold_last(state, base + ImuMemory.LAST_AX, ax, ax_ok)
    if not ax_ok:
        status |= ST_INPUT_TIMEOUT
    if not ay_ok:
        ay = 0.0
        status |= ST_INPUT_TIMEOUT
    elif roll_time_constant > 0.0:
        if not roll_rate_ok:
            status |= ST_DEGRADED  # roll from the static model alone
        vx, _ = corner_speed_mean(u, steer, yaw_rate, vehicle)
        ay = remove_roll_gravity(state, base + ImuMemory.ROLL, ay, roll_rate, roll_rate_ok, dt,
                                 vehicle, accel_carries_gravity(u, vehicle), roll_time_constant,
                                 base + ImuMemory.GRAVITY_W if learn_roll_gain else -1,
                                 yaw_rate, yaw_acc, vx)  # fmt: skip
    return (ax, ay, yaw_rate, yaw_acc, steer, roll_rate, ax_ok, ay_ok, yaw_rate_ok, steer_ok,
            status)


# ---------------------------------------------------------------------------------------------
# offsets learnt online (Selmanaj section 4)
# ---------------------------------------------------------------------------------------------

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


@enum.unique
class Offsets(enum.IntEnum):
    """Slots of the offset block. Offsets are in SI units of their channel and are
    *subtracted* from the measurement; 0 is their prior (``reset_offsets``), and the daemon
    may restore the values persisted at the last key-off."""

    YAW_RATE = 0  # rad/s
    ROLL_RATE = 1  # rad/s
    PITCH_RATE = 2  # rad/s
    AX = 3  # m/s^2, at the CoG after gravity compensation (Selmanaj Fig. 10)
    AY = 4  # m/s^2, at the CoG after gravity compensation (Selmanaj Fig. 11, eq. 21)
    STANDSTILL_TIME = 5  # s the car has been standing still without interruption


#: The learnt offsets of the block, without the standstill timer: what persists.
LEARNT_OFFSETS = tuple(f"OFFSETS.{o.name}" for o in Offsets if o is not Offsets.STANDSTILL_TIME)


def reset_offsets(buf: np.ndarray, start: int) -> None:
    """Zero offsets and standstill timer."""
    buf[start : start + len(Offsets)] = 0.0


@nb.njit(cache=True, inline="always")
def offset_time_constant(settling_time):
    """Time constant of a first-order filter that settles (2 %) in ``settling_time`` seconds."""
    return settling_time / SETTLING_TIME_CONSTANTS


@nb.njit(cache=True, inline="always")
def update_standstill(buf, i, max_wheel_speed, all_wheels_valid, dt, speed_threshold):
    """Time the car has been standing still, kept in ``buf[i + Offsets.STANDSTILL_TIME]``.

    Standstill: every wheel speed valid and below ``speed_threshold``. Returns the time, s.
    """
    slot = i + Offsets.STANDSTILL_TIME
    if all_wheels_valid and max_wheel_speed < speed_threshold:
        buf[slot] += dt
    else:
        buf[slot] = 0.0
    return buf[slot]


@nb.njit(cache=True, inline="always")
def _offset_filter(buf, slot, residual, active, dt, settling_time):
    # Selmanaj section 4: "When the logic is not active the filters are stopped and their
    # state held at the values of deactivation."
    if active and math.isfinite(residual):
        gain = dt / offset_time_constant(settling_time)
        if gain > 1.0:
            gain = 1.0
        buf[slot] += gain * (residual - buf[slot])
    return buf[slot]


@nb.njit(cache=True, inline="always")
def update_gyro_offset(buf, i, slot, rate_measured, standstill, dt, settling_time):
    """Gyro offset of channel ``slot`` (Offsets.YAW_RATE/ROLL_RATE/PITCH_RATE).

    Selmanaj section 4: gyros are not affected by gravity, so at standstill the raw rate is
    the offset, whatever the attitude; low-pass with ``settling_time`` (paper: 150 s) while
    ``standstill`` holds, frozen otherwise. Returns the offset (subtract it from the rate).
    """
    return _offset_filter(buf, i + slot, rate_measured, standstill, dt, settling_time)


@nb.njit(cache=True, inline="always")
def ax_offset_active(vx, ax_off, yaw_rate, min_speed):
    """Selmanaj section 4, conditions of Fig. 10: moving (vx > ``min_speed``, the paper's
    Vx > 0 with a margin for the wheel-speed resolution), |Ax_off| < 1 m/s^2 (pitch and slip
    small) and |yaw rate| <= 5 deg/s (no lateral dynamics)."""
    return (
        vx > min_speed
        and abs(ax_off) < AX_OFFSET_MAX_AX
        and abs(yaw_rate) <= AX_OFFSET_MAX_YAW_RATE
    )


@nb.njit(cache=True, inline="always")
def update_ax_offset(buf, i, ax_off, dvx_dt, active, dt, settling_time):
    """Ax offset (Selmanaj Fig. 10): low-pass of Ax_off - dVx/dt in the selected conditions.

    ``ax_off`` is the CoG, gravity-compensated ax still carrying its offset; ``dvx_dt`` the
    derivative-filtered wheel-based vx (free of offsets by construction). Settling time
    1500 s in the paper. Returns the offset.
    """
    return _offset_filter(buf, i + Offsets.AX, ax_off - dvx_dt, active, dt, settling_time)


@nb.njit(cache=True, inline="always")
def update_ay_offset(buf, i, ay_off, yaw_rate, vx, active, dt, settling_time):
    """Ay offset, Selmanaj eq. 21: Delta_Ay = LP[Ay_off - omega_z Vx].

    From the kinematic model (eq. 18-19) with E[dVy/dt] ~ 0 over a route that starts and ends
    straight (eq. 20). On a permanently banked road it also absorbs the bank's gravity
    component, which the paper calls the correct behaviour. Returns the offset.
    """
    return _offset_filter(buf, i + Offsets.AY, ay_off - yaw_rate * vx, active, dt,
                          settling_time)  # fmt: skip
