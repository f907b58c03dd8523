"""Sensor models: what the car's ESC unit, EPS, wheel-speed sensors, GNSS receiver,
magnetometer and powertrain put on the bus, computed from the plant's true motion.

All channels come out on the plant's 100 Hz grid as the value the sensor would report if asked
at that instant (canonical SI, ISO 8855, slipd.channels.In). :func:`messages` then samples them
per CAN message at the message's rate with its transmission latency. Quantisation is the
codec's job (the DBC resolution); everything else a real sensor does to a signal is here.

Sizes are those of production sensors, cited where they are defined (:class:`SensorConfig`).
Random draws come from one ``numpy.random.Generator`` seeded by the caller, in a fixed order,
so a seed reproduces every number.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from slipd.channels import In
from slipd.numba_cache import nb as numba
from slipd.sim.plant import (
    ISO_WHEEL_STATES,
    PITCH,
    PITCH_RATE,
    PITCH_SIGN,
    POS_X,
    POS_Y,
    ROLL,
    ROLL_RATE,
    ROLL_SIGN,
    STEER,
    VX,
    VY,
    VZ_S,
    YAW,
    YAW_RATE,
    G,
    PlantOutput,
)
from slipd.sim.vehicle_data import DEFAULT_IMU_POSITION, DEFAULT_STEER_RATIO

DEG = math.pi / 180.0


@dataclass
class SensorConfig:
    """Noise, bias and timing of the simulated sensors (1-sigma values unless said otherwise)."""

    # IMU of a production ESC unit: white noise 0.02 m/s^2 and 0.08 deg/s (Yoon, Li, Ahn 2016,
    # Table 1, Delphi ESC unit).
    accel_noise: float = 0.02
    gyro_noise: float = 0.08 * DEG
    # Turn-on offsets: constant per drive. Selmanaj et al. 2017 (section 4, Fig. 13, Table 4)
    # estimate gyro and accelerometer offsets online because offsets of this order cost them 7-24 %
    # of RMS beta error; 0.1 m/s^2 and 0.3 deg/s are the order of a consumer-grade MEMS turn-on
    # offset after factory calibration (assumed, not from the papers).
    accel_bias: float = 0.1
    gyro_bias: float = 0.3 * DEG
    # Slow drift on top (temperature): first-order Gauss-Markov, time constant and stationary
    # 1-sigma (assumed: a few % of the offsets per 10 min).
    bias_tau: float = 600.0
    accel_drift: float = 0.02
    gyro_drift: float = 0.05 * DEG
    # Anti-aliasing / output filter of the sensor cluster, first order (assumed 20 Hz corner).
    imu_bandwidth_hz: float = 20.0
    # Mounting misalignment of the ESC unit (assumed, 0.3 deg per axis 1-sigma).
    imu_misalignment: float = 0.3 * DEG
    # Extra offsets added on purpose by a scenario (ax, ay, az m/s^2; roll, pitch, yaw rate rad/s).
    accel_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gyro_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # Wheel speeds: per-wheel rolling-radius error (tyre wear, pressure, load: +-0.5 % is
    # normal, assumed 0.3 % 1-sigma), noise from tooth-spacing errors (assumed 0.2 % + 0.01 m/s)
    # and the minimum speed an active sensor resolves (0.1 m/s).
    wheel_radius_error: float = 0.003
    wheel_noise_rel: float = 0.002
    wheel_noise_abs: float = 0.01
    wheel_min_speed: float = 0.1
    # Steering-angle sensor (at the steering wheel): offset after alignment (assumed 1 deg),
    # noise 0.1 deg, rate noise 2 deg/s.
    swa_offset: float = 1.0 * DEG
    swa_noise: float = 0.1 * DEG
    swa_rate_noise: float = 2.0 * DEG
    # GNSS: 10 Hz velocity, 0.05 m/s horizontal and 0.1 m/s vertical noise (single-antenna
    # automotive receiver), delivered 0.4 s late (the delay Yoon et al. 2016 inject, sec. 5);
    # antenna on the roof (body axes from the CoG, m).
    gnss_rate_hz: float = 10.0
    gnss_delay: float = 0.4
    gnss_noise_h: float = 0.05
    gnss_noise_v: float = 0.10
    gnss_antenna: tuple[float, float, float] = (-0.3, 0.0, 0.85)
    # Magnetometer: 50 Hz, noise 0.5 mG = 0.05 uT (Yoon et al. 2016, Table 1, Xsens MTi);
    # earth field of central Europe (WMM: 20.9 uT horizontal, 43.8 uT down, declination 3.5 deg);
    # hard-iron offset of the car body (assumed 5 uT per axis), soft-iron matrix error
    # (assumed 3 %), transient disturbances (bridges, trucks, tram lines: assumed one per minute,
    # 2-15 uT for 1-4 s).
    mag_rate_hz: float = 50.0
    mag_noise: float = 0.05
    earth_field_h: float = 20.9
    earth_field_down: float = 43.8
    declination: float = 3.5 * DEG
    mag_hard_iron: float = 5.0
    mag_soft_iron: float = 0.03
    mag_disturbance_rate: float = 1.0 / 60.0
    # Torques: drive torque is the powertrain's model estimate (assumed 5 % gain error, 5 Nm
    # noise); brake torque is pressure times a brake gain that varies with pad friction (assumed
    # 8 % gain error, 10 Nm noise).
    drive_gain_error: float = 0.05
    drive_noise: float = 5.0
    brake_gain_error: float = 0.08
    brake_noise: float = 10.0
    # Message timing: latency from sampling to the bus timestamp, message i gets
    # base + i * spacing (bus order), plus jitter.
    latency_base: float = 0.0008
    latency_spacing: float = 0.0004
    latency_jitter: float = 0.0001
    # IMU position relative to the CoG and steering ratio: simulate() sets them from the
    # vehicle profile; these defaults are the same constants it falls back to (one source).
    imu_position: tuple[float, float, float] = DEFAULT_IMU_POSITION
    steer_ratio: float = DEFAULT_STEER_RATIO
    extra: dict = field(default_factory=dict)

    # --- sensor realism (off by default; slipd.sim.variants names sets of these) ----------
    # Accelerometer frame: "body" (an ESC unit: specific force in body axes, gravity and body
    # roll included) or "level" (an INS: acceleration in the levelled heading frame, gravity
    # removed, so ay carries no g sin(roll) and no bank term; only the yaw part of the
    # mounting rotation remains, the INS's attitude takes out roll and pitch).
    accel_frame: str = "body"
    # Fixed mounting angles of the IMU (roll, pitch, yaw, rad), on top of the random
    # ``imu_misalignment`` draw.
    imu_mounting: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # Body vibration as a raw IMU delivers it (slipd.sim.vibration): RMS per axis at the
    # reference speed (ax, ay, az in m/s^2; roll, pitch, yaw rate in rad/s), and the variance
    # shares of road broadband, wheel hop, engine orders and wheel order 1.
    vibration_accel: tuple[float, float, float] = (0.0, 0.0, 0.0)
    vibration_gyro: tuple[float, float, float] = (0.0, 0.0, 0.0)
    vibration_shares: tuple[float, float, float, float] = (0.6, 0.1, 0.25, 0.05)
    # Extra age of the values a message carries (s): the message goes out on its schedule but
    # holds the value sampled this long before (done in slipd.sim.result.sample_messages).
    imu_delay: float = 0.0
    wheel_delay: float = 0.0
    steer_delay: float = 0.0
    # ABS tone wheel (slipd.sim.tone_wheel): teeth per revolution (0 = the ideal speed), how the
    # unit turns edges into a speed ("edge_timing" or "count"), and the longest edge interval
    # it waits before reporting 0.
    wheel_teeth: int = 0
    wheel_speed_method: str = "edge_timing"
    wheel_edge_timeout: float = 0.1
    # Fixed steering-wheel angle offset (rad at the steering wheel), on top of the random
    # ``swa_offset`` draw.
    swa_bias: float = 0.0
    # Fixed relative rolling-radius errors of the wheels (fl, fr, rl, rr: the speed signal reads
    # (1 + error) x the true speed), on top of the random ``wheel_radius_error`` draw.
    wheel_radius_bias: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        from slipd.errors import ConfigError
        from slipd.sim.tone_wheel import METHODS

        if self.accel_frame not in ("body", "level"):
            raise ConfigError(
                f"sensor setting accel_frame={self.accel_frame!r}: expected 'body' or 'level'")
        if self.wheel_speed_method not in METHODS:
            raise ConfigError(f"sensor setting wheel_speed_method={self.wheel_speed_method!r}: "
                              f"expected one of {', '.join(METHODS)}")
        teeth = self.wheel_teeth
        if isinstance(teeth, bool) or not isinstance(teeth, (int, np.integer)) or teeth < 0:
            raise ConfigError(
                f"sensor setting wheel_teeth={self.wheel_teeth!r}: expected an integer >= 0")
        for name in ("imu_delay", "wheel_delay", "steer_delay"):
            if not getattr(self, name) >= 0.0:
                raise ConfigError(f"sensor setting {name}={getattr(self, name)!r}: expected "
                                  "a delay >= 0 s")
        if not self.wheel_edge_timeout > 0.0:
            raise ConfigError(f"sensor setting wheel_edge_timeout={self.wheel_edge_timeout!r}: "
                              "expected > 0 s")
        for name, size in (("imu_mounting", 3), ("vibration_accel", 3), ("vibration_gyro", 3),
                           ("vibration_shares", 4), ("wheel_radius_bias", 4)):
            value = getattr(self, name)
            if np.shape(value) != (size,):
                raise ConfigError(f"sensor setting {name}={value!r}: expected {size} numbers")


def _rx(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    rows = (np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1))
    return np.stack(rows, -2)


def _ry(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    rows = (np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1))
    return np.stack(rows, -2)


def _rz(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    rows = (np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1))
    return np.stack(rows, -2)


def _apply_t(r: np.ndarray, v: np.ndarray) -> np.ndarray:
    """R^T v for stacks of matrices (n, 3, 3) and vectors (n, 3)."""
    return np.einsum("nji,nj->ni", r, v)


@numba.njit(cache=True)
def _first_order(x, a, b, y0):
    """y[k] = a y[k-1] + b x[k] with y[-1] = y0, over the first axis of a 1-D or 2-D array."""
    y = np.empty_like(x)
    acc = y0.copy()
    for k in range(x.shape[0]):
        acc = a * acc + b * x[k]
        y[k] = acc
    return y


def _gauss_markov(rng: np.random.Generator, n: int, dt: float, tau: float, sigma: float):
    """First-order Gauss-Markov sequence with stationary 1-sigma ``sigma``."""
    phi = math.exp(-dt / tau)
    drive = rng.normal(0.0, sigma * math.sqrt(1.0 - phi * phi), (n, 1))
    start = np.array([rng.normal(0.0, sigma)])
    return _first_order(drive, phi, 1.0, start)[:, 0]


def _lowpass(x: np.ndarray, dt: float, corner_hz: float) -> np.ndarray:
    """First-order low-pass (exact discretisation of 1/(tau s + 1)), started settled at the first
    sample. ``x`` is (n, m)."""
    if corner_hz <= 0 or len(x) == 0:
        return x
    a = math.exp(-2.0 * math.pi * corner_hz * dt)
    return _first_order(np.ascontiguousarray(x), a, 1.0 - a, x[0].copy())


def truth(out: PlantOutput, p) -> dict[str, np.ndarray]:
    """The reference signals (SI, ISO 8855) on the plant grid; keys are the truth CSV columns."""
    x, dx = out.x, out.dx
    vx, vy, r = x[:, VX], x[:, VY], x[:, YAW_RATE]
    speed = np.hypot(vx, vy)
    wheels = x[:, list(ISO_WHEEL_STATES)] * p.R_w
    return {
        "t": out.t,
        "beta": np.arctan2(vy, np.maximum(vx, 1e-9)) * (speed > 1e-3),
        "vx": vx,
        "vy": vy,
        "speed": speed,
        "yaw_rate": r,
        "yaw": x[:, YAW],
        "roll": ROLL_SIGN * x[:, ROLL],
        "pitch": PITCH_SIGN * x[:, PITCH],
        "roll_rate": ROLL_SIGN * x[:, ROLL_RATE],
        "pitch_rate": PITCH_SIGN * x[:, PITCH_RATE],
        "ax": dx[:, VX] - r * vy,
        "ay": dx[:, VY] + r * vx,
        "steer": x[:, STEER],
        "wheel_speed_fl": wheels[:, 0],
        "wheel_speed_fr": wheels[:, 1],
        "wheel_speed_rl": wheels[:, 2],
        "wheel_speed_rr": wheels[:, 3],
        "mu": out.mu,
        "bank": out.bank,
        "grade": out.grade,
        "s": out.s,
        "pos_x": x[:, POS_X],
        "pos_y": x[:, POS_Y],
        "accel_demand": out.accel_demand,
    }


#: Units of the truth columns for the CSV header.
TRUTH_UNITS = {
    "t": "s", "beta": "rad", "vx": "m/s", "vy": "m/s", "speed": "m/s", "yaw_rate": "rad/s",
    "yaw": "rad", "roll": "rad", "pitch": "rad", "roll_rate": "rad/s", "pitch_rate": "rad/s",
    "ax": "m/s^2", "ay": "m/s^2", "steer": "rad", "wheel_speed_fl": "m/s",
    "wheel_speed_fr": "m/s", "wheel_speed_rl": "m/s", "wheel_speed_rr": "m/s", "mu": "-",
    "bank": "rad", "grade": "rad", "s": "m", "pos_x": "m", "pos_y": "m", "accel_demand": "m/s^2",
}


def body_motion(out: PlantOutput):
    """Attitude (roll, pitch: body on road plus road bank/grade) and body angular velocity and
    acceleration, (n, 3) each, ISO 8855.

    Euler kinematics (ISO 8855 yaw-pitch-roll): p = phi' - psi' sin(theta),
    q = theta' cos(phi) + psi' sin(phi) cos(theta), r = psi' cos(theta) cos(phi) - theta' sin(phi).
    The road's bank and grade add to the body's roll and pitch (small-angle composition).
    """
    t = out.t
    dt = t[1] - t[0] if len(t) > 1 else 0.01
    phi = ROLL_SIGN * out.x[:, ROLL] + out.bank
    theta = PITCH_SIGN * out.x[:, PITCH] - out.grade  # uphill = nose up = negative ISO pitch
    road_phi_rate = np.gradient(out.bank, dt) if len(t) > 1 else np.zeros_like(t)
    road_theta_rate = -np.gradient(out.grade, dt) if len(t) > 1 else np.zeros_like(t)
    phi_dot = ROLL_SIGN * out.x[:, ROLL_RATE] + road_phi_rate
    theta_dot = PITCH_SIGN * out.x[:, PITCH_RATE] + road_theta_rate
    psi_dot = out.x[:, YAW_RATE]
    omega = np.stack(
        [
            phi_dot - psi_dot * np.sin(theta),
            theta_dot * np.cos(phi) + psi_dot * np.sin(phi) * np.cos(theta),
            psi_dot * np.cos(theta) * np.cos(phi) - theta_dot * np.sin(phi),
        ],
        -1,
    )
    omega_dot = np.gradient(omega, dt, axis=0) if len(t) > 1 else np.zeros_like(omega)
    return phi, theta, omega, omega_dot


def imu_specific_force(out: PlantOutput, imu_position) -> tuple[np.ndarray, np.ndarray]:
    """True specific force at the IMU (n, 3) in body axes, and the body angular velocity (n, 3).

    f = R_b^T (a_road - R_road^T g), a_road the CoG acceleration in the road frame (the model's
    longitudinal, lateral and heave equations), g = (0, 0, -9.81); plus the lever-arm terms
    omega_dot x rho + omega x (omega x rho) for the IMU at rho from the CoG.
    """
    x, dx = out.x, out.dx
    vx, vy, r = x[:, VX], x[:, VY], x[:, YAW_RATE]
    a_road = np.stack([dx[:, VX] - r * vy, dx[:, VY] + r * vx, -dx[:, VZ_S]], -1)
    road_rot = np.einsum("nij,njk->nik", _ry(-out.grade), _rx(out.bank))
    gravity = np.zeros_like(a_road)
    gravity[:, 2] = -G
    f_road = a_road - _apply_t(road_rot, gravity)
    body_rot = np.einsum(
        "nij,njk->nik", _ry(PITCH_SIGN * x[:, PITCH]), _rx(ROLL_SIGN * x[:, ROLL])
    )
    f_body = _apply_t(body_rot, f_road)
    _, _, omega, omega_dot = body_motion(out)
    rho = np.broadcast_to(np.asarray(imu_position, dtype=np.float64), omega.shape)
    f_imu = f_body + np.cross(omega_dot, rho) + np.cross(omega, np.cross(omega, rho))
    return f_imu, omega


def level_acceleration(out: PlantOutput, f_imu: np.ndarray) -> np.ndarray:
    """What an INS reports for the specific force ``f_imu`` (n, 3, body axes): the acceleration
    of the IMU point in the levelled heading frame (x the heading in the horizontal plane, y
    horizontal to the left, z up), gravity removed: R_att f + g_up with R_att the body's roll and
    pitch on the road and the road's bank and grade (the composition of imu_specific_force)."""
    x = out.x
    road_rot = np.einsum("nij,njk->nik", _ry(-out.grade), _rx(out.bank))
    body_rot = np.einsum(
        "nij,njk->nik", _ry(PITCH_SIGN * x[:, PITCH]), _rx(ROLL_SIGN * x[:, ROLL])
    )
    attitude = np.einsum("nij,njk->nik", road_rot, body_rot)
    a_level = np.einsum("nij,nj->ni", attitude, f_imu)
    a_level[:, 2] -= G
    return a_level


def sensor_channels(
    out: PlantOutput, p, cfg: SensorConfig, rng: np.random.Generator, heading0: float = 0.0,
    aux_rng: np.random.Generator | None = None, record: dict | None = None,
) -> dict[In, np.ndarray]:
    """Every input channel on the plant grid, as the sensors report it (before quantisation).

    ``rng`` draws the baseline sensor errors in a fixed order. The sensor-realism options
    (vibration, tone-wheel phases) draw from ``aux_rng`` (default: a child spawned from
    ``rng``, which leaves ``rng``'s own stream untouched), so switching them on never changes
    the baseline's draws: a variant differs from its baseline only by its own effect.
    ``record``, when given, receives the errors drawn (the truth of slipd identify's sensor
    errors, in its conventions): ``imu_mounting`` (roll, pitch, yaw, rad), ``accel_offset``
    (m/s^2) and ``gyro_offset`` (roll, pitch, yaw rate, rad/s) as the turn-on offset plus the
    drift's mean over the run, ``wheel_radius_error`` (fl, fr, rl, rr) and ``swa_offset``
    (rad at the steering wheel).
    """
    t = out.t
    n = len(t)
    dt = t[1] - t[0] if n > 1 else 0.01
    ch: dict[In, np.ndarray] = {}
    if aux_rng is None:
        aux_rng = rng.spawn(1)[0]

    # --- IMU (ESC sensor cluster) --------------------------------------------------------
    f_imu, omega = imu_specific_force(out, cfg.imu_position)
    mis = rng.normal(0.0, cfg.imu_misalignment, 3) + np.asarray(cfg.imu_mounting)
    m_rot = _rz(np.array([mis[2]]))[0] @ _ry(np.array([mis[1]]))[0] @ _rx(np.array([mis[0]]))[0]
    if cfg.accel_frame == "level":  # the INS levels its output: only the heading error stays
        f_imu = level_acceleration(out, f_imu) @ _rz(np.array([mis[2]]))[0]
    else:
        f_imu = f_imu @ m_rot  # rows: R^T v
    omega_imu = omega @ m_rot
    f_imu = _lowpass(f_imu, dt, cfg.imu_bandwidth_hz)
    omega_imu = _lowpass(omega_imu, dt, cfg.imu_bandwidth_hz)
    if any(cfg.vibration_accel) or any(cfg.vibration_gyro):
        from slipd.sim.vibration import vibration

        speed = np.hypot(out.x[:, VX], out.x[:, VY])
        wheel_omega = out.x[:, list(ISO_WHEEL_STATES)]
        f_imu = f_imu + vibration(aux_rng, t, speed, wheel_omega, p.R_w,
                                  tuple(cfg.vibration_accel), tuple(cfg.vibration_shares))
        omega_imu = omega_imu + vibration(aux_rng, t, speed, wheel_omega, p.R_w,
                                          tuple(cfg.vibration_gyro),
                                          tuple(cfg.vibration_shares))
    accel_bias = rng.normal(0.0, cfg.accel_bias, 3) + np.asarray(cfg.accel_offset)
    gyro_bias = rng.normal(0.0, cfg.gyro_bias, 3) + np.asarray(cfg.gyro_offset)
    accel_mean, gyro_mean = accel_bias.copy(), gyro_bias.copy()
    for i, channel in enumerate((In.AX, In.AY, In.AZ)):
        drift = _gauss_markov(rng, n, dt, cfg.bias_tau, cfg.accel_drift)
        accel_mean[i] += float(drift.mean()) if n else 0.0
        ch[channel] = f_imu[:, i] + accel_bias[i] + drift + rng.normal(0.0, cfg.accel_noise, n)
    for i, channel in enumerate((In.ROLL_RATE, In.PITCH_RATE, In.YAW_RATE)):
        drift = _gauss_markov(rng, n, dt, cfg.bias_tau, cfg.gyro_drift)
        gyro_mean[i] += float(drift.mean()) if n else 0.0
        ch[channel] = omega_imu[:, i] + gyro_bias[i] + drift + rng.normal(0.0, cfg.gyro_noise, n)

    # --- wheel speeds (omega * dynamic radius, unsigned) -------------------------------------
    radius_error = rng.normal(0.0, cfg.wheel_radius_error, 4) + np.asarray(cfg.wheel_radius_bias)
    if cfg.wheel_teeth:
        from slipd.sim.tone_wheel import tone_wheel_speed

        tooth_phase = aux_rng.uniform(0.0, 1.0, 4)
    for i, channel in enumerate(
        (In.WHEEL_SPEED_FL, In.WHEEL_SPEED_FR, In.WHEEL_SPEED_RL, In.WHEEL_SPEED_RR)
    ):
        wheel_omega = out.x[:, ISO_WHEEL_STATES[i]]
        if cfg.wheel_teeth:
            wheel_omega = tone_wheel_speed(t, wheel_omega, int(cfg.wheel_teeth), tooth_phase[i],
                                           cfg.wheel_speed_method, cfg.wheel_edge_timeout)
        true = wheel_omega * p.R_w * (1.0 + radius_error[i])
        noise = rng.normal(0.0, 1.0, n) * (cfg.wheel_noise_abs + cfg.wheel_noise_rel * true)
        meas = np.abs(true + noise)
        ch[channel] = np.where(true < cfg.wheel_min_speed, 0.0, meas)
    ch[In.SPEED_REF] = 0.25 * sum(ch[c] for c in (
        In.WHEEL_SPEED_FL, In.WHEEL_SPEED_FR, In.WHEEL_SPEED_RL, In.WHEEL_SPEED_RR))

    # --- steering (angle sensor at the steering wheel, reported as road-wheel angle) --------
    ratio = cfg.steer_ratio
    swa_offset = rng.normal(0.0, cfg.swa_offset) + cfg.swa_bias
    swa = out.x[:, STEER] * ratio + swa_offset + rng.normal(0.0, cfg.swa_noise, n)
    if record is not None:
        record.update(imu_mounting=tuple(float(v) for v in mis),
                      accel_offset=tuple(float(v) for v in accel_mean),
                      gyro_offset=tuple(float(v) for v in gyro_mean),
                      wheel_radius_error=tuple(float(v) for v in radius_error),
                      swa_offset=float(swa_offset))
    ch[In.STEER] = swa / ratio
    ch[In.STEER_RATE] = (out.dx[:, STEER] * ratio + rng.normal(0.0, cfg.swa_rate_noise, n)) / ratio

    # --- GNSS velocity (east = world x, north = world y), delayed --------------------------
    phi, theta, omega_b, _ = body_motion(out)
    v_body = np.stack([out.x[:, VX], out.x[:, VY], np.zeros(n)], -1)
    v_ant = v_body + np.cross(omega_b, np.asarray(cfg.gnss_antenna))
    heading = out.x[:, YAW] + heading0
    c, s = np.cos(heading), np.sin(heading)
    v_east = c * v_ant[:, 0] - s * v_ant[:, 1]
    v_north = s * v_ant[:, 0] + c * v_ant[:, 1]
    v_up = np.hypot(out.x[:, VX], out.x[:, VY]) * np.sin(out.grade) + v_ant[:, 2]
    stride = max(1, int(round(1.0 / (cfg.gnss_rate_hz * dt))))
    delay = int(round(cfg.gnss_delay / dt))
    # the epoch e (every ``stride`` samples) is delivered at e + delay: at grid point k the
    # newest delivered solution is that of epoch floor((k - delay) / stride) * stride
    src = (np.arange(n) - delay) // stride * stride
    has_fix = src >= 0
    src = np.clip(src, 0, n - 1)
    noise = rng.normal(0.0, 1.0, (n, 3))  # indexed by epoch: one draw per solution
    ch[In.GNSS_VN] = np.where(has_fix, v_north[src] + cfg.gnss_noise_h * noise[src, 0], 0.0)
    ch[In.GNSS_VE] = np.where(has_fix, v_east[src] + cfg.gnss_noise_h * noise[src, 1], 0.0)
    ch[In.GNSS_VU] = np.where(has_fix, v_up[src] + cfg.gnss_noise_v * noise[src, 2], 0.0)
    ch[In.GNSS_FIX] = has_fix.astype(np.float64)

    # --- magnetometer ---------------------------------------------------------------------
    b_world = np.array([
        cfg.earth_field_h * math.sin(cfg.declination),  # east
        cfg.earth_field_h * math.cos(cfg.declination),  # north
        -cfg.earth_field_down,  # up
    ])
    b_world = np.broadcast_to(b_world, (n, 3)).copy()
    n_events = rng.poisson(cfg.mag_disturbance_rate * (t[-1] - t[0] if n > 1 else 0.0))
    for _ in range(n_events):
        centre = rng.uniform(t[0], t[-1])
        width = rng.uniform(1.0, 4.0) / 4.0
        direction = rng.normal(0.0, 1.0, 3)
        direction /= np.linalg.norm(direction)
        amplitude = rng.uniform(2.0, 15.0)
        b_world += np.outer(np.exp(-0.5 * ((t - centre) / width) ** 2), amplitude * direction)
    attitude = np.einsum(
        "nij,njk->nik", np.einsum("nij,njk->nik", _rz(heading), _ry(theta)), _rx(phi)
    )
    b_body = _apply_t(attitude, b_world)
    soft = np.eye(3) + rng.normal(0.0, cfg.mag_soft_iron, (3, 3))
    hard = rng.normal(0.0, cfg.mag_hard_iron, 3)
    b_meas = b_body @ soft.T + hard + rng.normal(0.0, cfg.mag_noise, (n, 3))
    ch[In.MAG_X], ch[In.MAG_Y], ch[In.MAG_Z] = b_meas[:, 0], b_meas[:, 1], b_meas[:, 2]

    # --- drive and brake torques (vehicle_dynamics_mb's own split of the demand) -----------
    wheel_torque = p.m * p.R_w * out.accel_demand
    engine = np.maximum(wheel_torque, 0.0)
    brake = np.maximum(-wheel_torque, 0.0)
    drive_split = (0.5 * p.T_se, 0.5 * p.T_se, 0.5 * (1 - p.T_se), 0.5 * (1 - p.T_se))
    brake_split = (0.5 * p.T_sb, 0.5 * p.T_sb, 0.5 * (1 - p.T_sb), 0.5 * (1 - p.T_sb))
    drive_gain = 1.0 + rng.normal(0.0, cfg.drive_gain_error)
    brake_gain = 1.0 + rng.normal(0.0, cfg.brake_gain_error, 4)
    drive_ch = (In.DRIVE_TORQUE_FL, In.DRIVE_TORQUE_FR, In.DRIVE_TORQUE_RL, In.DRIVE_TORQUE_RR)
    brake_ch = (In.BRAKE_TORQUE_FL, In.BRAKE_TORQUE_FR, In.BRAKE_TORQUE_RL, In.BRAKE_TORQUE_RR)
    for i in range(4):
        drive = engine * drive_split[i]
        ch[drive_ch[i]] = np.where(
            drive > 0, drive * drive_gain + rng.normal(0.0, cfg.drive_noise, n), 0.0
        )
        b = brake * brake_split[i]
        ch[brake_ch[i]] = np.where(
            b > 0, np.maximum(b * brake_gain[i] + rng.normal(0.0, cfg.brake_noise, n), 0.0), 0.0
        )
    return ch
