"""The sensor-error correction of the profile's ``[calibration]`` table (slipd identify's output).

It acts in one place: :func:`slipd.codec.kernels.sample_latch`, the last step that fills a
tick's input vector ``u`` from the latch, for the daemon's per-tick path and the batch
``latch_ticks`` alike, so a replay of the daemon's recording stays exact. On the SI values of
the channels that are valid at the tick:

1. the IMU's offsets are subtracted (sensor axes: what it reads when the truth is zero);
2. the accelerometer and gyro vectors are rotated from the sensor's axes into the body's,
   v_body = R v_sensor with R = Rz(yaw) Ry(pitch) Rx(roll) of ``imu_mounting_deg`` (a sensor
   whose axes are the body's rotated by R reads R^T v_body: the inverse rotation undoes it);
3. the steering-angle offset (at the steering wheel, so divided by the ratio the channel is
   divided by) is subtracted from the road-wheel angle;
4. each wheel speed is multiplied by its relative rolling radius.

A component of the IMU vectors whose channel is not valid (unmapped, stale) enters the
rotation at its nominal value (az = +g, the others 0) and is itself left as latched, as is
every other invalid channel. A profile without the table (or with the identity) gives
``cal[CAL_ACTIVE] = 0`` and the kernel returns at once: inputs byte for byte as before.

``cal`` float64 [CAL_LEN]: :func:`calibration_vector` builds it once per profile.
"""

from __future__ import annotations

import math

import numpy as np

from slipd.channels import N_IN, WHEEL_SPEEDS, G, In
from slipd.numba_cache import nb
from slipd.profile import Calibration

CAL_ACTIVE = 0  # 1.0: correct, 0.0: identity (leave u untouched)
CAL_ROTATION = 1  # 9 values, row-major R (body from sensor)
CAL_ACCEL_OFFSET = 10  # ax, ay, az offsets, m/s^2
CAL_GYRO_OFFSET = 13  # roll, pitch, yaw rate offsets, rad/s
CAL_STEER_OFFSET = 16  # road-wheel angle offset, rad
CAL_WHEEL_SCALE = 17  # fl, fr, rl, rr
CAL_LEN = 21

_AX, _AY, _AZ = int(In.AX), int(In.AY), int(In.AZ)
_P, _Q, _R = int(In.ROLL_RATE), int(In.PITCH_RATE), int(In.YAW_RATE)
_STEER = int(In.STEER)
_WHEELS = np.array([int(c) for c in WHEEL_SPEEDS], dtype=np.int64)
_ACCEL = (_AX, _AY, _AZ)
_GYRO = (_P, _Q, _R)


def mounting_rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) (rad): the sensor's axes as the body's rotated by R, the
    convention of the simulator's misalignment (slipd.sim.sensors)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    return rz @ ry @ rx


def calibration_vector(calibration: Calibration) -> np.ndarray:
    """The kernel's float64 [CAL_LEN] form of a profile's calibration (SI, rad)."""
    cal = np.zeros(CAL_LEN, dtype=np.float64)
    if calibration.is_identity:
        cal[CAL_ROTATION:CAL_ROTATION + 9] = np.eye(3).ravel()
        cal[CAL_WHEEL_SCALE:CAL_WHEEL_SCALE + 4] = 1.0
        return cal
    cal[CAL_ACTIVE] = 1.0
    roll, pitch, yaw = (math.radians(v) for v in calibration.imu_mounting_deg)
    cal[CAL_ROTATION:CAL_ROTATION + 9] = mounting_rotation(roll, pitch, yaw).ravel()
    cal[CAL_ACCEL_OFFSET:CAL_ACCEL_OFFSET + 3] = calibration.accel_offset
    cal[CAL_GYRO_OFFSET:CAL_GYRO_OFFSET + 3] = [math.radians(v) for v in calibration.gyro_offset]
    cal[CAL_STEER_OFFSET] = math.radians(calibration.steer_offset_deg) / calibration.steer_divisor
    cal[CAL_WHEEL_SCALE:CAL_WHEEL_SCALE + 4] = calibration.wheel_radius_scale
    return cal


@nb.njit(cache=True, _nrt=False)
def _rotate_into(cal, offset, u, i0, i1, i2, n0, n1, n2):
    """u[i] <- (R (v - offset))[i] for the valid ones of the three channels; invalid ones
    enter at their nominal value n and keep their latched value."""
    n_in = (u.shape[0] - 1) // 2
    ok0 = u[n_in + i0] > 0.5
    ok1 = u[n_in + i1] > 0.5
    ok2 = u[n_in + i2] > 0.5
    v0 = u[i0] - cal[offset] if ok0 else n0
    v1 = u[i1] - cal[offset + 1] if ok1 else n1
    v2 = u[i2] - cal[offset + 2] if ok2 else n2
    r = CAL_ROTATION
    if ok0:
        u[i0] = cal[r] * v0 + cal[r + 1] * v1 + cal[r + 2] * v2
    if ok1:
        u[i1] = cal[r + 3] * v0 + cal[r + 4] * v1 + cal[r + 5] * v2
    if ok2:
        u[i2] = cal[r + 6] * v0 + cal[r + 7] * v1 + cal[r + 8] * v2


@nb.njit(cache=True, _nrt=False)
def calibrate(cal, u):
    """Correct one tick's input vector ``u`` [U_LEN] in place (see the module docstring).
    Allocates nothing; returns at once when ``cal[CAL_ACTIVE]`` is 0."""
    if cal[CAL_ACTIVE] == 0.0:
        return
    n_in = (u.shape[0] - 1) // 2
    _rotate_into(cal, CAL_ACCEL_OFFSET, u, _AX, _AY, _AZ, 0.0, 0.0, G)
    _rotate_into(cal, CAL_GYRO_OFFSET, u, _P, _Q, _R, 0.0, 0.0, 0.0)
    if u[n_in + _STEER] > 0.5:
        u[_STEER] -= cal[CAL_STEER_OFFSET]
    for k in range(4):
        ch = _WHEELS[k]
        if u[n_in + ch] > 0.5:
            u[ch] *= cal[CAL_WHEEL_SCALE + k]


def calibrate_ticks(cal: np.ndarray, U: np.ndarray) -> np.ndarray:
    """The plain twin of :func:`calibrate` over many ticks (numpy, vectorised): a corrected
    copy of ``U`` [n, U_LEN]. slipd identify corrects its data with it; the agreement test
    holds the two to 1e-12."""
    out = np.array(U, dtype=np.float64, copy=True)
    if cal[CAL_ACTIVE] == 0.0:
        return out
    rotation = cal[CAL_ROTATION:CAL_ROTATION + 9].reshape(3, 3)
    for channels, offset, nominal in ((_ACCEL, CAL_ACCEL_OFFSET, (0.0, 0.0, G)),
                                      (_GYRO, CAL_GYRO_OFFSET, (0.0, 0.0, 0.0))):
        idx = list(channels)
        ok = U[:, [N_IN + c for c in idx]] > 0.5
        v = np.where(ok, U[:, idx] - cal[offset:offset + 3], np.asarray(nominal))
        rotated = v @ rotation.T
        out[:, idx] = np.where(ok, rotated, U[:, idx])
    steer_ok = U[:, N_IN + _STEER] > 0.5
    out[:, _STEER] = np.where(steer_ok, U[:, _STEER] - cal[CAL_STEER_OFFSET], U[:, _STEER])
    for k, ch in enumerate(WHEEL_SPEEDS):
        ok = U[:, N_IN + ch] > 0.5
        out[:, ch] = np.where(ok, U[:, ch] * cal[CAL_WHEEL_SCALE + k], U[:, ch])
    return out
