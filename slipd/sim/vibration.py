"""Vibration of a car body as a raw 100 Hz IMU delivers it, on top of the vehicle's motion.

An ESC sensor cluster low-passes its signals (slipd.sim.sensors.SensorConfig.imu_bandwidth_hz);
a raw MEMS IMU or an INS logged at 100-200 Hz does not, and carries the body's vibration: road
excitation through the suspension, the engine's orders and the wheels' non-uniformity. Above
the 50 Hz Nyquist frequency of the output that content folds into the band (a MEMS sensor's own
bandwidth is a few hundred Hz), which is why a logged raw IMU shows a flat floor up to Nyquist
rather than a roll-off.

Measured on real data (``../shared/realdata/revs_250lm``, the Stanford Revs Ferrari 250 LM's
INS accelerations at 100 Hz, 550 s on a race track), 4th-order high-pass at 5 Hz:
ay 1.0 m/s^2 RMS (0.9 at 15-25 m/s, 1.24 at 45-65 m/s), ax 0.67 (0.40 at 15-25 m/s), yaw rate
0.3 deg/s at every speed; the spectrum is a flat floor of ~0.015 (m/s^2)^2/Hz from 5 to 50 Hz
with a line near 21 Hz and weaker lines that follow the speed. That is the shape modelled here:

- road broadband: white on the output grid (the folded floor), the road input of ISO 8608
  (displacement PSD ~ n^-2 of the spatial frequency n) makes the vertical velocity input white
  with a PSD proportional to the speed, so its RMS scales with ``sqrt(v / REF_SPEED)``;
- wheel hop: the unsprung mass on the tyre, a resonance at :data:`WHEEL_HOP_HZ` (assumed,
  sqrt(k_tyre / m_unsprung) / 2 pi with ~200 kN/m and ~40 kg), same speed scaling;
- engine: the 2nd and 4th orders of a four-cylinder four-stroke (the firing order and its
  harmonic, the inertial free forces of an inline four), engine speed from the vehicle speed
  through a five-speed gearbox (:data:`GEAR_RATIOS`, assumed), amplitude proportional to
  engine speed, idling at :data:`IDLE_RPM` at standstill. Its frequencies (40-130 Hz)
  alias into the band as lines that move with speed and jump at gear shifts;
- wheel order 1: the non-uniformity of each tyre at its rotation frequency, amplitude
  proportional to the square of the wheel speed (an imbalance force), capped at 4x.

Each component is normalised to unit variance at :data:`REF_SPEED` (and the engine speed
there), weighted by its variance share and scaled to the configured delivered RMS per axis; at
other speeds each scales as said. Every axis draws its own realisation.
"""

from __future__ import annotations

import math

import numpy as np

#: Speed (m/s) at which the configured RMS levels hold.
REF_SPEED = 20.0
#: Wheel-hop resonance (Hz) and its damping ratio (assumed).
WHEEL_HOP_HZ = 12.0
WHEEL_HOP_DAMPING = 0.3
#: Overall ratios (gearbox x final drive) of a five-speed passenger car (assumed: 3.67, 2.10,
#: 1.36, 1.00, 0.82 with a 3.46 final drive).
GEAR_RATIOS = tuple(r * 3.46 for r in (3.67, 2.10, 1.36, 1.00, 0.82))
#: The gearbox runs the highest gear that keeps the engine above this (rpm).
SHIFT_RPM = 1500.0
IDLE_RPM = 800.0
#: Variance shares of the engine orders (2nd, 4th).
ENGINE_ORDERS = ((2.0, 0.9), (4.0, 0.1))
#: Cap of the wheel-order amplitude (times its reference amplitude).
WHEEL_ORDER_CAP = 4.0


def engine_rpm(speed: np.ndarray, wheel_radius: float) -> np.ndarray:
    """Engine speed (rpm) for a vehicle speed (m/s): the highest gear above SHIFT_RPM (first gear
    otherwise), never below idle."""
    wheel_rpm = np.abs(np.asarray(speed, dtype=np.float64)) / wheel_radius * 60.0 / (2.0 * math.pi)
    rpm = wheel_rpm * GEAR_RATIOS[0]
    for ratio in GEAR_RATIOS[1:]:
        candidate = wheel_rpm * ratio
        rpm = np.where(candidate >= SHIFT_RPM, candidate, rpm)
    return np.maximum(rpm, IDLE_RPM)


def _unit_resonance(rng: np.random.Generator, n: int, dt: float, f0: float, zeta: float):
    """White noise through a second-order resonance at ``f0`` (bilinear band-pass), normalised to
    unit variance by the filter's exact noise gain."""
    from scipy import signal

    w0 = 2.0 * math.pi * f0
    b, a = signal.bilinear([2.0 * zeta * w0, 0.0], [1.0, 2.0 * zeta * w0, w0 * w0], fs=1.0 / dt)
    impulse = signal.lfilter(b, a, np.r_[1.0, np.zeros(4095)])
    gain = math.sqrt(float(np.sum(impulse**2)))
    return signal.lfilter(b, a, rng.normal(0.0, 1.0, n)) / gain


def vibration(
    rng: np.random.Generator,
    t: np.ndarray,
    speed: np.ndarray,
    wheel_omega: np.ndarray,
    wheel_radius: float,
    rms: tuple[float, float, float],
    shares: tuple[float, float, float, float],
) -> np.ndarray:
    """Vibration (n, 3) for three axes with delivered RMS ``rms`` at REF_SPEED.

    ``speed`` (n,) the vehicle speed, ``wheel_omega`` (n, 4) the wheels' angular speeds (rad/s),
    ``shares`` the variance shares of (road broadband, wheel hop, engine orders, wheel order 1).
    Draws from ``rng`` only where an axis has a non-zero level.
    """
    n = len(t)
    dt = float(t[1] - t[0]) if n > 1 else 0.01
    out = np.zeros((n, 3))
    total = float(sum(shares))
    if n == 0 or total <= 0.0 or not any(rms):
        return out
    w_road, w_hop, w_engine, w_wheel = (math.sqrt(s / total) for s in shares)
    road_scale = np.sqrt(np.abs(speed) / REF_SPEED)
    rpm = engine_rpm(speed, wheel_radius)
    rpm_ref = float(engine_rpm(np.array([REF_SPEED]), wheel_radius)[0])
    crank_angle = 2.0 * math.pi * np.concatenate(([0.0], np.cumsum(0.5 * (rpm[1:] + rpm[:-1]))))
    crank_angle *= dt / 60.0
    engine_amp = math.sqrt(2.0) * rpm / rpm_ref
    omega = np.abs(np.asarray(wheel_omega, dtype=np.float64))
    wheel_angle = np.vstack((np.zeros((1, omega.shape[1])),
                             np.cumsum(0.5 * (omega[1:] + omega[:-1]), axis=0) * dt))
    omega_ref = REF_SPEED / wheel_radius
    wheel_amp = math.sqrt(2.0 / omega.shape[1]) * np.minimum(
        (omega / omega_ref) ** 2, WHEEL_ORDER_CAP)
    for axis in range(3):
        if rms[axis] == 0.0:
            continue
        road = rng.normal(0.0, 1.0, n)
        hop = _unit_resonance(rng, n, dt, WHEEL_HOP_HZ, WHEEL_HOP_DAMPING)
        engine = np.zeros(n)
        for order, share in ENGINE_ORDERS:
            phase = rng.uniform(0.0, 2.0 * math.pi)
            engine += math.sqrt(share) * np.sin(order * crank_angle + phase)
        wheel_phase = rng.uniform(0.0, 2.0 * math.pi, omega.shape[1])
        wheels = np.sum(wheel_amp * np.sin(wheel_angle + wheel_phase), axis=1)
        out[:, axis] = rms[axis] * (
            road_scale * (w_road * road + w_hop * hop)
            + w_engine * engine_amp * engine
            + w_wheel * wheels
        )
    return out
