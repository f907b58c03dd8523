"""Shared helpers of the simulator tests: a noise-free sensor set and prescribed motion."""

from __future__ import annotations

import numpy as np

from slipd.sim.plant import N_MB, OMEGA_FL, OMEGA_RR, VX, YAW_RATE, PlantOutput, vehicle_parameters

QUIET = dict(  # a sensor set without noise, offsets or disturbances: checks the geometry
    accel_noise=0.0, gyro_noise=0.0, accel_bias=0.0, gyro_bias=0.0, accel_drift=0.0,
    gyro_drift=0.0, imu_bandwidth_hz=0.0, imu_misalignment=0.0, wheel_radius_error=0.0,
    wheel_noise_rel=0.0, wheel_noise_abs=0.0, swa_offset=0.0, swa_noise=0.0,
    swa_rate_noise=0.0, gnss_noise_h=0.0, gnss_noise_v=0.0, mag_disturbance_rate=0.0,
    mag_noise=0.0, mag_hard_iron=0.0, mag_soft_iron=0.0,
)


def synthetic(n: int = 500, vx: float = 20.0, yaw_rate: float = 0.0, yaw_acc: float = 0.0,
              bank: float = 0.0, grade: float = 0.0) -> PlantOutput:
    """A plant output with prescribed motion (no integration): straight or steady circle."""
    p = vehicle_parameters(2)
    t = np.arange(n) * 0.01
    x = np.zeros((n, N_MB))
    dx = np.zeros((n, N_MB))
    x[:, VX] = vx
    x[:, YAW_RATE] = yaw_rate + yaw_acc * t
    dx[:, YAW_RATE] = yaw_acc
    x[:, OMEGA_FL : OMEGA_RR + 1] = vx / p.R_w
    return PlantOutput(t=t, x=x, dx=dx, s=vx * t, accel_demand=np.zeros(n),
                       mu=np.full(n, 1.0), bank=np.full(n, bank), grade=np.full(n, grade))
