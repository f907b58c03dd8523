"""The fixed vocabularies every part of slipd shares: input channels, outputs, status bits
and the vehicle-parameter vector.

Everything inside slipd is SI with ISO 8855 axes (x forward, y left, z up; yaw rate positive
turning left; beta = atan2(vy, vx)). The codec converts at the edge, estimators never see
degrees, km/h or another car's sign convention.

Layouts are integer enums so numba kernels can index plain float64 arrays with names that
say what the element is (``u[In.YAW_RATE]``) while the arrays stay cheap to pass.
"""

from __future__ import annotations

import enum

import numpy as np


@enum.unique
class In(enum.IntEnum):
    """Canonical input channels (SI, ISO 8855). Index into the per-tick input vector ``u``."""

    AX = 0  # m/s^2, longitudinal acceleration at the IMU (includes gravity components)
    AY = 1  # m/s^2, lateral acceleration at the IMU, positive to the left
    AZ = 2  # m/s^2, vertical acceleration at the IMU (+9.81 at rest)
    YAW_RATE = 3  # rad/s, positive turning left (counter-clockwise seen from above)
    ROLL_RATE = 4  # rad/s, positive right side down (ISO 8855 x axis)
    PITCH_RATE = 5  # rad/s, positive nose down (ISO 8855 y axis)
    STEER = 6  # rad, front road-wheel steer angle (steering-wheel angle / ratio), + left
    STEER_RATE = 7  # rad/s, front road-wheel steer rate
    WHEEL_SPEED_FL = 8  # m/s, linear wheel speed omega * r_eff
    WHEEL_SPEED_FR = 9
    WHEEL_SPEED_RL = 10
    WHEEL_SPEED_RR = 11
    GNSS_VN = 12  # m/s, velocity north
    GNSS_VE = 13  # m/s, velocity east
    GNSS_VU = 14  # m/s, velocity up
    GNSS_FIX = 15  # 1 = 3D fix with valid velocity, 0 = none
    MAG_X = 16  # uT, magnetometer along the body x axis
    MAG_Y = 17
    MAG_Z = 18
    DRIVE_TORQUE_FL = 19  # Nm at the wheel, positive accelerating
    DRIVE_TORQUE_FR = 20
    DRIVE_TORQUE_RL = 21
    DRIVE_TORQUE_RR = 22
    BRAKE_TORQUE_FL = 23  # Nm at the wheel, positive decelerating
    BRAKE_TORQUE_FR = 24
    BRAKE_TORQUE_RL = 25
    BRAKE_TORQUE_RR = 26
    SPEED_REF = 27  # m/s, the car's own reference speed (ESC/ABS), where the bus carries one


N_IN = len(In)
#: Offset of the validity flags in ``u``: ``u[N_IN + ch]`` is 1.0 when channel ``ch`` holds a
#: fresh, E2E-checked value and 0.0 when it is missing, stale or failed its check.
VALID = N_IN
#: ``u[U_TIME]`` is the tick time in seconds (log time axis in replay, monotonic in the daemon).
U_TIME = 2 * N_IN
#: Length of the per-tick input vector ``u``.
U_LEN = 2 * N_IN + 1

WHEEL_SPEEDS = (In.WHEEL_SPEED_FL, In.WHEEL_SPEED_FR, In.WHEEL_SPEED_RL, In.WHEEL_SPEED_RR)
#: The channels every estimator needs; without them the output is invalid.
CORE_CHANNELS = (In.AX, In.AY, In.YAW_RATE, In.STEER, *WHEEL_SPEEDS)


@enum.unique
class Out(enum.IntEnum):
    """Estimator outputs, written by ``step`` into ``out`` (SI)."""

    BETA = 0  # rad, sideslip angle at the CoG
    BETA_RATE = 1  # rad/s
    VX = 2  # m/s, longitudinal velocity at the CoG
    VY = 3  # m/s, lateral velocity at the CoG
    MU = 4  # -, estimated road friction (NaN where the method does not estimate it)
    SIGMA_BETA = 5  # rad, 1-sigma of beta (or the method's quality figure mapped to rad)
    ROLL = 6  # rad, body roll angle
    FRICTION_CLASS = 7  # 0 unknown, 1 low (ice/snow), 2 medium (wet), 3 high (dry)
    STATUS = 8  # bit field of Status, stored as a float
    NIS = 9  # -, the method's Kalman filter innovation test: its normalised innovation squared
    #          averaged over ~1 s and divided by the measurements' count (about 1 while the
    #          filter's model explains its measurements); NaN for a method without a filter


N_OUT = len(Out)


@enum.unique
class Status(enum.IntEnum):
    """Status bits of an estimate; the same bits go into SLIPD_STATE.Status."""

    VALID = 1  # every bit below is clear and the values are finite and in range
    DEGRADED = 2  # an optional input is missing; the estimate is usable with care
    INPUT_TIMEOUT = 4  # a required input is stale, invalid or failed its E2E check
    NOT_CONVERGED = 8  # the estimator has not settled since start or reset
    UNAVAILABLE = 16  # the method cannot run on this car's inputs (missing sensor)
    RESET = 32  # the estimator reset its state this tick (non-finite state, recovery)


# Plain ints for numba kernels (numba cannot convert an IntEnum member to float).
ST_VALID = int(Status.VALID)
ST_DEGRADED = int(Status.DEGRADED)
ST_INPUT_TIMEOUT = int(Status.INPUT_TIMEOUT)
ST_NOT_CONVERGED = int(Status.NOT_CONVERGED)
ST_UNAVAILABLE = int(Status.UNAVAILABLE)
ST_RESET = int(Status.RESET)


@enum.unique
class Veh(enum.IntEnum):
    """Vehicle parameters, loaded from the profile's [vehicle] table (SI)."""

    MASS = 0  # kg
    YAW_INERTIA = 1  # kg m^2, Iz
    ROLL_INERTIA = 2  # kg m^2, Ix about the roll axis
    LF = 3  # m, CoG to front axle
    LR = 4  # m, CoG to rear axle
    TRACK_F = 5  # m
    TRACK_R = 6  # m
    H_COG = 7  # m, CoG height above ground
    H_ROLL_AXIS = 8  # m, roll axis height under the CoG
    WHEEL_RADIUS = 9  # m, effective rolling radius
    STEER_RATIO = 10  # -, steering-wheel angle / road-wheel angle
    IMU_X = 11  # m, IMU position relative to the CoG (ISO 8855 body axes)
    IMU_Y = 12
    IMU_Z = 13
    ROLL_STIFFNESS = 14  # Nm/rad, total
    ROLL_DAMPING = 15  # Nm s/rad, total
    CORNERING_STIFFNESS_F = 16  # N/rad, front axle (both tyres)
    CORNERING_STIFFNESS_R = 17  # N/rad, rear axle
    LONGITUDINAL_STIFFNESS = 18  # N per unit slip, one tyre
    MU_NOMINAL = 19  # -, dry-road peak friction of the tyre data
    WHEEL_INERTIA = 20  # kg m^2, one wheel
    TYRE_B = 21  # Pacejka magic formula coefficients of the lateral force (one set for all)
    TYRE_C = 22
    TYRE_E = 23
    ACCEL_LEVEL = 24  # 1: the accelerometers are levelled, gravity removed (an INS; the
    # profile's IMU message frame = "level"), 0: body frame (ESC units)


N_VEH = len(Veh)
G = 9.81  # m/s^2


def new_u() -> np.ndarray:
    """A zeroed per-tick input vector (all channels invalid)."""
    return np.zeros(U_LEN, dtype=np.float64)


#: SI unit of each estimator output (the comments of :class:`Out`).
OUT_UNITS: dict[Out, str] = {
    Out.BETA: "rad", Out.BETA_RATE: "rad/s", Out.VX: "m/s", Out.VY: "m/s", Out.MU: "1",
    Out.SIGMA_BETA: "rad", Out.ROLL: "rad", Out.FRICTION_CLASS: "1", Out.STATUS: "bits",
    Out.NIS: "1",
}
