"""The simulator's product: the truth, the sensor messages as the bus carries them, and the
per-tick input matrix an estimator consumes (the latch semantics of DESIGN.md)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from slipd.channels import U_LEN, U_TIME, VALID, In


@dataclass(frozen=True)
class MessageSpec:
    """One input message: the fields of the profile's ``MessageMap`` the simulator needs."""

    name: str
    frame_id: int
    rate_hz: float
    channels: tuple[In, ...]


#: The input messages of slipd.dbc, used when no vehicle profile can be loaded (same names, IDs
#: and rates as the DBC's comments).
DEFAULT_MESSAGES: tuple[MessageSpec, ...] = (
    MessageSpec("IMU_ACCEL", 0x100, 100.0, (In.AX, In.AY, In.AZ)),
    MessageSpec("IMU_RATE", 0x101, 100.0, (In.YAW_RATE, In.ROLL_RATE, In.PITCH_RATE)),
    MessageSpec("WHEEL_SPEEDS", 0x110, 100.0, (
        In.WHEEL_SPEED_FL, In.WHEEL_SPEED_FR, In.WHEEL_SPEED_RL, In.WHEEL_SPEED_RR)),
    MessageSpec("STEERING", 0x120, 100.0, (In.STEER, In.STEER_RATE)),
    MessageSpec("GNSS_VELOCITY", 0x130, 10.0, (In.GNSS_VN, In.GNSS_VE, In.GNSS_VU, In.GNSS_FIX)),
    MessageSpec("MAGNETOMETER", 0x140, 50.0, (In.MAG_X, In.MAG_Y, In.MAG_Z)),
    MessageSpec("WHEEL_DRIVE_TORQUE", 0x150, 100.0, (
        In.DRIVE_TORQUE_FL, In.DRIVE_TORQUE_FR, In.DRIVE_TORQUE_RL, In.DRIVE_TORQUE_RR)),
    MessageSpec("WHEEL_BRAKE_TORQUE", 0x151, 100.0, (
        In.BRAKE_TORQUE_FL, In.BRAKE_TORQUE_FR, In.BRAKE_TORQUE_RL, In.BRAKE_TORQUE_RR)),
)


@dataclass
class MessageSamples:
    """One message's transmissions: bus timestamps (s, increasing) and channel values."""

    spec: MessageSpec
    t: np.ndarray
    values: dict[In, np.ndarray]


def sample_messages(
    grid_t: np.ndarray,
    channels: dict[In, np.ndarray],
    specs: tuple[MessageSpec, ...] | list,
    rng: np.random.Generator,
    latency_base: float,
    latency_spacing: float,
    latency_jitter: float,
    delays: tuple[float, ...] | list | None = None,
) -> dict[str, MessageSamples]:
    """Sample the channels per message at its rate; timestamp = sample time + latency.

    Message ``i`` (bus order) leaves ``latency_base + i * latency_spacing`` after its sensor
    sampled, plus |N(0, latency_jitter)|; timestamps of one message stay increasing.
    ``delays[i]`` (s, default 0) makes message ``i`` carry the values of that much earlier
    (the sensor's or gateway's processing age) while it keeps its schedule: a multiple of the
    grid step takes the earlier sample, anything else interpolates linearly between two; before
    the first sample the first value is held.
    """
    dt = grid_t[1] - grid_t[0] if len(grid_t) > 1 else 0.01
    result: dict[str, MessageSamples] = {}
    for i, spec in enumerate(specs):
        stride = int(round(1.0 / (spec.rate_hz * dt)))
        if stride < 1 or abs(stride * spec.rate_hz * dt - 1.0) > 1e-6:
            from slipd.errors import ConfigError

            raise ConfigError(
                f"message {spec.name}: rate {spec.rate_hz} Hz does not divide the simulator's "
                f"{1.0 / dt:.0f} Hz grid"
            )
        idx = np.arange(0, len(grid_t), stride)
        latency = latency_base + i * latency_spacing
        jitter = np.abs(rng.normal(0.0, latency_jitter, len(idx)))
        t = grid_t[idx] + latency + jitter
        values = {}
        for ch in spec.channels:
            if ch not in channels:
                from slipd.errors import ConfigError

                raise ConfigError(f"message {spec.name}: the simulator has no model for {ch.name}")
            delay = float(delays[i]) if delays is not None else 0.0
            values[ch] = np.ascontiguousarray(
                _delayed(channels[ch], idx, delay / dt) if delay else channels[ch][idx],
                dtype=np.float64,
            )
        result[spec.name] = MessageSamples(spec=spec, t=t, values=values)
    return result


def _delayed(signal: np.ndarray, idx: np.ndarray, steps: float) -> np.ndarray:
    """``signal`` at the fractional grid positions ``idx - steps`` (held at the first sample)."""
    whole = round(steps)
    if abs(steps - whole) < 1e-9:
        return signal[np.maximum(idx - whole, 0)]
    pos = np.maximum(idx - steps, 0.0)
    lo = np.minimum(np.floor(pos).astype(np.int64), len(signal) - 1)
    hi = np.minimum(lo + 1, len(signal) - 1)
    frac = pos - lo
    return signal[lo] * (1.0 - frac) + signal[hi] * frac


@dataclass
class SimResult:
    """``truth``: column name -> float64 array on the 100 Hz grid (SI, ISO 8855; see
    :data:`slipd.sim.sensors.TRUTH_UNITS`). ``sensors``: message name -> its samples.
    ``scenario``/``vehicle``/``seed`` say what made it."""

    scenario: str
    vehicle: int
    seed: int
    truth: dict[str, np.ndarray]
    sensors: dict[str, MessageSamples]
    meta: dict = field(default_factory=dict)

    @property
    def duration(self) -> float:
        return float(self.truth["t"][-1])

    def ticks(self, dt: float = 0.01) -> np.ndarray:
        """Per-tick inputs (n, U_LEN): the newest value of every channel received at or before
        each tick (sample and hold), validity 1.0 once a value exists, ``u[U_TIME]`` the tick
        time. Ticks run from 0 to the end of the truth every ``dt`` s.

        This is the latch without the codec: values are not quantised and never stale-flagged.
        """
        tick_t = np.arange(0.0, self.duration + 1e-9, dt)
        U = np.zeros((len(tick_t), U_LEN), dtype=np.float64)
        U[:, U_TIME] = tick_t
        for msg in self.sensors.values():
            idx = np.searchsorted(msg.t, tick_t, side="right") - 1
            have = idx >= 0
            safe = np.maximum(idx, 0)
            for ch, values in msg.values.items():
                U[:, ch] = np.where(have, values[safe], 0.0)
                U[:, VALID + ch] = have.astype(np.float64)
        return U

    def frames(self) -> tuple[np.ndarray, list[tuple[str, int]]]:
        """All transmissions time-sorted: (timestamps, [(message name, sample index)])."""
        stamps, keys = [], []
        for name, msg in self.sensors.items():
            stamps.append(msg.t)
            keys.extend((name, k) for k in range(len(msg.t)))
        t = np.concatenate(stamps) if stamps else np.zeros(0)
        order = np.argsort(t, kind="stable")
        return t[order], [keys[i] for i in order]
