"""Rigid-body kinematics of the measurements: CoG translation, wheel-speed compensation, roll
and gravity, the kinematic sideslip rate.

From Selmanaj, Corno, Panzani, Savaresi (2017), sections 2.3, 3 and 3.1, and Righetti & Lenzo
(2025) section 3.1. Axes and signs are ISO 8855 (x forward, y left, z up; yaw rate + turning
left; roll rate + right side down; pitch rate + nose down); where a paper prints another sign
the docstring says how it was converted.
"""

from __future__ import annotations

import enum
import math

from slipd.channels import G, Veh
from slipd.numba_cache import nb


@nb.njit(cache=True, inline="always")
def translate_to_cog(
    ax, ay, az, roll_rate, pitch_rate, yaw_rate, roll_acc, pitch_acc, yaw_acc, imu_x, imu_y, imu_z
):
    """Accelerations at the CoG from those measured at the IMU (rigid body).

    a_cog = a_imu - omega_dot x r - omega x (omega x r), with r = (imu_x, imu_y, imu_z) the IMU
    position relative to the CoG, omega = (roll_rate, pitch_rate, yaw_rate) and omega_dot the
    angular accelerations (from ``filters.derivative_filter``). Righetti-Lenzo section 3.1
    writes the planar case with PG = -r: a_cog = a_P + r_dot k x PG - r^2 PG. Returns (ax, ay,
    az).
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


@nb.njit(cache=True, inline="always")
def translate_to_cog_planar(ax, ay, yaw_rate, yaw_acc, imu_x, imu_y):
    """Planar special case of ``translate_to_cog`` (Righetti-Lenzo section 3.1, eq. 21-23):
    ax_cog = ax + r_dot imu_y + r^2 imu_x,  ay_cog = ay - r_dot imu_x + r^2 imu_y."""
    yaw_rate_sq = yaw_rate * yaw_rate
    return (
        ax + yaw_acc * imu_y + yaw_rate_sq * imu_x,
        ay - yaw_acc * imu_x + yaw_rate_sq * imu_y,
    )


@nb.njit(cache=True, inline="always")
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


@nb.njit(cache=True, inline="always")
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


@nb.njit(cache=True, inline="always")
def vehicle_roll_gain(vehicle):
    """``roll_static_gain`` of the profile's mass, roll-axis height and roll stiffness."""
    return roll_static_gain(vehicle[Veh.MASS], vehicle[Veh.H_ROLL_AXIS],
                            vehicle[Veh.ROLL_STIFFNESS])


@nb.njit(cache=True, inline="always")
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


@nb.njit(cache=True, inline="always")
def compensate_gravity_ay(ay_cog, roll):
    """Selmanaj eq. 17: Ay_off = Ay_CG - g sin(theta). In ISO 8855 a body rolled by phi
    (right side down) senses +g sin(phi) on its y axis, which this removes."""
    return ay_cog - G * math.sin(roll)


#: Learning the gravity share of the measured ay online (``learn_gravity_share``): the time
#: constant of its moments (s of qualifying driving), the speed and yaw-acceleration limits of
#: quasi-steady driving, the prior's weight (as a variance of ay, (m/s^2)^2: the nominal value
#: counts as much as that much spread of data) and the bound. 0.15 is 8.6 deg of roll at 1 g,
#: above any road car's roll gradient (passenger cars 3-7 deg/g, Gillespie, Fundamentals of
#: Vehicle Dynamics, ch. 8); the lower bound 0 is a levelled (INS) accelerometer.
GRAVITY_SHARE_TIME_CONSTANT = 60.0
GRAVITY_SHARE_MIN_SPEED = 5.0
GRAVITY_SHARE_MAX_YAW_ACC = 0.1
GRAVITY_SHARE_PRIOR_VARIANCE = 1.0
GRAVITY_SHARE_MAX = 0.15


@enum.unique
class GravityMoments(enum.IntEnum):
    """Memory of ``learn_gravity_share``: exponentially forgotten moments of x = measured ay
    and e = ay - r vx over the quasi-steady ticks (W: the weight collected, 0 = no data)."""

    W = 0
    MX = 1
    ME = 2
    MXX = 3
    MXE = 4


@nb.njit(cache=True, inline="always")
def learn_gravity_share(buf, i, ay_measured, yaw_rate, yaw_acc, vx, dt, nominal_share):
    """The share s of the measured ay that is gravity from the body roll, learnt from the
    drive: Ay_meas = Ay + g sin(phi) (Selmanaj eq. 17) with the static roll phi ~ k Ay_meas
    (eq. 16), so e = Ay_meas - omega_z vx = dVy/dt + g k Ay_meas + offset. In quasi-steady
    driving (vx > GRAVITY_SHARE_MIN_SPEED, |yaw acc| < GRAVITY_SHARE_MAX_YAW_ACC) dVy/dt ~ 0
    and the slope of e over Ay_meas is s = g k: a least-squares line with an intercept (the
    offset and a bank average out of the slope) on moments forgotten with
    GRAVITY_SHARE_TIME_CONSTANT, shrunk to ``nominal_share`` (the profile's roll model) with
    the weight GRAVITY_SHARE_PRIOR_VARIANCE, bounded to [0, GRAVITY_SHARE_MAX]. A body-frame
    ESC sensor learns its car's roll gradient, an unknown roll stiffness is corrected, and an
    accelerometer that is already levelled learns s ~ 0. ``buf[i:]``: GravityMoments."""
    if vx > GRAVITY_SHARE_MIN_SPEED and abs(yaw_acc) < GRAVITY_SHARE_MAX_YAW_ACC:
        a = dt / GRAVITY_SHARE_TIME_CONSTANT
        e = ay_measured - yaw_rate * vx
        buf[i + GravityMoments.W] += a * (1.0 - buf[i + GravityMoments.W])
        buf[i + GravityMoments.MX] += a * (ay_measured - buf[i + GravityMoments.MX])
        buf[i + GravityMoments.ME] += a * (e - buf[i + GravityMoments.ME])
        buf[i + GravityMoments.MXX] += a * (ay_measured * ay_measured - buf[i + GravityMoments.MXX])
        buf[i + GravityMoments.MXE] += a * (ay_measured * e - buf[i + GravityMoments.MXE])
    w = buf[i + GravityMoments.W]
    if w <= 0.0:
        share = nominal_share
    else:
        # the started averages divided by w are unbiased (as in ensemble's moments)
        mx = buf[i + GravityMoments.MX] / w
        me = buf[i + GravityMoments.ME] / w
        var_x = buf[i + GravityMoments.MXX] / w - mx * mx
        cov_xe = buf[i + GravityMoments.MXE] / w - mx * me
        share = ((w * cov_xe + GRAVITY_SHARE_PRIOR_VARIANCE * nominal_share)
                 / (w * var_x + GRAVITY_SHARE_PRIOR_VARIANCE))
    if share < 0.0:
        share = 0.0
    elif share > GRAVITY_SHARE_MAX:
        share = GRAVITY_SHARE_MAX
    return share


@nb.njit(cache=True, inline="always")
def remove_roll_gravity(buf, i, ay_cog, roll_rate, roll_rate_valid, dt, vehicle, gravity_in_ay,
                        time_constant, learn_at, yaw_rate, yaw_acc, vx):  # fmt: skip
    """ay without the gravity component of the body roll: the roll of
    ``roll_complementary_filter`` (memory ``buf[i]``), then eq. 17. Not in Righetti-Lenzo,
    Carnier or Chen; slipd adds it to their pre-processing (each method's docstring says why).

    The static roll gain is the profile's (``vehicle_roll_gain``, Selmanaj eq. 16) when
    ``learn_at`` < 0, else learnt from the drive (``learn_gravity_share``, memory
    GravityMoments at ``buf[learn_at]``; a slipd departure, the methods' ``roll_gain_learning``
    parameter). An accelerometer without gravity in its a_y (``gravity_in_ay`` False:
    ``common.inputs.accel_carries_gravity``, a levelled INS) gets ay back as it is."""
    if not gravity_in_ay:
        return ay_cog
    gain = vehicle_roll_gain(vehicle)
    if learn_at >= 0:
        gain = learn_gravity_share(buf, learn_at, ay_cog, yaw_rate, yaw_acc, vx, dt,
                                   G * gain) / G  # fmt: skip
    roll = roll_complementary_filter(buf, i, ay_cog, roll_rate, roll_rate_valid, dt, gain,
                                     time_constant)  # fmt: skip
    return compensate_gravity_ay(ay_cog, roll)


@nb.njit(cache=True, inline="always")
def kinematic_beta_rate(vx, vy, ax, ay, yaw_rate):
    """d/dt atan2(vy, vx) with the kinematic model vx' = ax + r vy, vy' = ay - r vx:
    (vx vy' - vy vx') / V^2 = (vx ay - vy ax) / V^2 - r, from the accelerations without
    differentiating a noisy estimate; 0 below 1 m/s, where the direction is noise."""
    speed2 = vx * vx + vy * vy
    return (vx * ay - vy * ax) / speed2 - yaw_rate if speed2 > 1.0 else 0.0
