"""Sensor variants: named sets of :class:`~slipd.sim.sensors.SensorConfig` overrides that make
the simulated sensors look like a particular real installation (issue 15, item 4).

The baseline suite has ESC-grade sensors; each variant adds one real-world effect on top, with
the sizes cited (or said to be assumed) in its ``sources``. A variant only adds its effect: its
random draws come from a stream of their own (see slipd.sim.sensors.sensor_channels), so the
same seed gives the baseline's noise, biases and misalignment plus the variant's effect.

    from slipd.sim import simulate
    from slipd.sim.variants import VARIANTS
    for name in VARIANTS:
        result = simulate("slalom", seed=0, variant=name)

``slipd sim --suite --variant NAME --out DIR`` writes a suite with one; ``NAME,NAME`` combines
several in one simulation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from slipd.errors import ConfigError

DEG = math.pi / 180.0

#: Where the revs_250lm measurements come from (the repository's real-data folder).
_REVS = ("measured: ../shared/realdata/revs_250lm (Stanford Revs Ferrari 250 LM, INS at "
         "100 Hz), 4th-order high-pass at 5 Hz: ay 0.90 m/s^2 RMS at 15-25 m/s (1.0 over the "
         "run, 1.24 at 45-65 m/s), ax 0.40 at 15-25 m/s, yaw rate 0.3 deg/s at every speed; "
         "flat floor 5-50 Hz with a line near 21 Hz")


@dataclass(frozen=True)
class Variant:
    """``overrides``: SensorConfig field -> value (SI, rad). ``sources``: where each size comes
    from, and which are assumed."""

    name: str
    description: str
    overrides: dict = field(default_factory=dict)
    sources: tuple[str, ...] = ()

    def summary(self) -> str:
        """``key=value`` of every override, for logs and file headers."""
        return " ".join(
            f"{key}={format_value(value)}" for key, value in sorted(self.overrides.items()))


def format_value(value) -> str:
    """A setting as written in file headers (floats to 6 significant digits)."""
    if isinstance(value, tuple):
        return "(" + ",".join(format_value(v) for v in value) + ")"
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


VARIANTS: dict[str, Variant] = {}


def _register(variant: Variant) -> None:
    VARIANTS[variant.name] = variant


_register(Variant(
    name="vibration",
    description="raw-IMU body vibration: road broadband, wheel hop, engine orders 2 and 4, "
                "wheel order 1; ax/ay/az 0.5/0.9/1.2 m/s^2, gyros 0.5/0.5/0.3 deg/s RMS at "
                "20 m/s",
    overrides={
        "vibration_accel": (0.5, 0.9, 1.2),
        "vibration_gyro": (0.5 * DEG, 0.5 * DEG, 0.3 * DEG),
    },
    sources=(
        "ay, ax and yaw-rate levels and the spectrum's shape: " + _REVS,
        "speed scaling sqrt(v) of the road part: ISO 8608 road profiles (displacement PSD "
        "~ n^-2 gives a white velocity input with PSD ~ v)",
        "az 1.2 m/s^2 and roll/pitch rate 0.5 deg/s: assumed (not in the real data; vertical is "
        "the axis the road drives directly)",
        "engine orders, gearbox, wheel hop 12 Hz, variance shares 0.6/0.1/0.25/0.05: assumed "
        "(slipd.sim.vibration)",
    ),
))

_register(Variant(
    name="level_frame",
    description="INS-style accelerometers: levelled heading frame, gravity removed (no "
                "g sin(roll), no bank term in ay; az ~ 0)",
    overrides={"accel_frame": "level"},
    sources=(
        "INS outputs of this kind: SBG Ellipse 'INS accelerations free from gravity' "
        "(sbg_driver SbgEkfRotAccel), iXblue 'acceleration compensated from gravity' "
        "(ixblue_stdbin_decoder AccelerationVesselFrame)",
        "the revs_250lm run's INS accelerations (frame not stated by the source)",
    ),
))

_register(Variant(
    name="misalignment",
    description="IMU mounted 1.5 deg off in roll, pitch and yaw at once (fixed, on top of the "
                "random 0.3 deg per axis)",
    overrides={"imu_mounting": (1.5 * DEG, 1.5 * DEG, 1.5 * DEG)},
    sources=(
        "1-2 deg per axis: issue 15 (a retrofitted IMU or INS without a mounting "
        "calibration); assumed. ESC units learn a mounting bias (GM EBCM service text: 'the "
        "sensor bias compensates for sensor mounting alignment errors'), an added IMU does not",
    ),
))

_register(Variant(
    name="skew",
    description="messages carry older values than their bus time: IMU 10 ms, steering 20 ms, "
                "wheel speeds 30 ms",
    overrides={"imu_delay": 0.010, "steer_delay": 0.020, "wheel_delay": 0.030},
    sources=(
        "10-30 ms: issue 15; assumed. Wheel speeds are a mean over the ABS unit's edge "
        "interval (US patent 4,799,178) and often cross a gateway; the steering angle comes "
        "from its own control unit (e.g. BMW E9x: the steering angle every 20 ms on PT-CAN, "
        "every 100 ms on K-CAN, superwofy/E9X-M-CAN-Integration-Module issue 6)",
    ),
))

_register(Variant(
    name="abs_tone_wheel",
    description="wheel speeds from a 48-tooth tone wheel, edge timing per 10 ms loop: mean "
                "over the edge interval, held between edges, 0 below 0.45 m/s",
    overrides={"wheel_teeth": 48, "wheel_speed_method": "edge_timing",
               "wheel_edge_timeout": 0.1},
    sources=(
        "the edge-timing computation: Delco Electronics, US patent 4,799,178 (1989)",
        "tooth counts of production tone wheels: 44 (Hyundai Tiburon service manual, wheel "
        "speed sensor specification), 29 (Saab 900 TCS description); 48 from issue 15",
        "0.1 s edge timeout (0 below 1.6 km/h): assumed",
    ),
))

_register(Variant(
    name="steer_offset",
    description="steering-angle sensor 3 deg off at the steering wheel (fixed, on top of the "
                "random 1 deg): 0.19 deg at the road wheels",
    overrides={"swa_bias": 3.0 * DEG},
    sources=(
        "a few degrees: commaai/opendbc pull request 149 ('On the Subaru I see 2-3 deg random "
        "offset' of the steering angle sensor at start-up); ESC units re-learn the centre "
        "after ~10 s of straight driving (GM EBCM 'steering angle centering'), a logger "
        "reading the raw sensor does not. 3 deg: assumed from these",
    ),
))


def resolve(spec: str | None) -> tuple[str | None, dict]:
    """The name and the merged overrides of ``spec``: None, a variant name, or names joined by
    commas (all applied in one simulation; two that set one field differently are refused)."""
    if spec is None or not str(spec).strip():
        return None, {}
    names = [part.strip() for part in str(spec).split(",") if part.strip()]
    merged: dict = {}
    owner: dict[str, str] = {}
    for name in names:
        if name not in VARIANTS:
            raise ConfigError(
                f"unknown sensor variant {name!r}; available: {', '.join(VARIANTS)}")
        for key, value in VARIANTS[name].overrides.items():
            if key in merged and merged[key] != value:
                raise ConfigError(f"sensor variants {owner[key]!r} and {name!r} both set {key}")
            merged[key] = value
            owner[key] = name
    return ",".join(names), merged
