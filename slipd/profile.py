"""Vehicle profiles: the car's parameters and how its CAN bus maps onto slipd's channels.

A profile is a TOML file (see ``slipd/dbc/default.toml`` for the annotated reference).
Loading validates every key and fails with a :class:`ConfigError` that names the file, the
key and what was expected; nothing unknown is silently ignored (a typo in a key would
otherwise leave a default in force on a car).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slipd.channels import CORE_CHANNELS, N_VEH, In, Veh
from slipd.errors import ConfigError

PROFILE_DIR = Path(__file__).resolve().parent / "dbc"

#: Unit name -> (factor to SI, dimension). The channel's SI unit follows from the channel.
UNIT_TABLE: dict[str, tuple[float, str]] = {
    "1": (1.0, "1"),
    "m/s^2": (1.0, "acceleration"),
    "m/s2": (1.0, "acceleration"),
    "g": (9.80665, "acceleration"),
    "rad": (1.0, "angle"),
    "deg": (math.pi / 180.0, "angle"),
    "rad/s": (1.0, "angular rate"),
    "deg/s": (math.pi / 180.0, "angular rate"),
    "rpm": (2.0 * math.pi / 60.0, "angular rate"),
    "m/s": (1.0, "speed"),
    "km/h": (1.0 / 3.6, "speed"),
    "mph": (0.44704, "speed"),
    "uT": (1.0, "magnetic field"),
    "T": (1.0e6, "magnetic field"),
    "Nm": (1.0, "torque"),
}
#: Unit name -> factor to SI (the import command's units).
UNITS: dict[str, float] = {"": 1.0, **{name: f for name, (f, _) in UNIT_TABLE.items()}}
#: Each channel's physical dimension (its SI unit in slipd.channels.In).
CHANNEL_DIMENSION: dict[In, str] = {
    **dict.fromkeys((In.AX, In.AY, In.AZ), "acceleration"),
    **dict.fromkeys((In.YAW_RATE, In.ROLL_RATE, In.PITCH_RATE, In.STEER_RATE), "angular rate"),
    In.STEER: "angle",
    **dict.fromkeys((In.WHEEL_SPEED_FL, In.WHEEL_SPEED_FR, In.WHEEL_SPEED_RL,
                     In.WHEEL_SPEED_RR, In.GNSS_VN, In.GNSS_VE, In.GNSS_VU, In.SPEED_REF),
                    "speed"),
    In.GNSS_FIX: "1",
    **dict.fromkeys((In.MAG_X, In.MAG_Y, In.MAG_Z), "magnetic field"),
    **dict.fromkeys((In.DRIVE_TORQUE_FL, In.DRIVE_TORQUE_FR, In.DRIVE_TORQUE_RL,
                     In.DRIVE_TORQUE_RR, In.BRAKE_TORQUE_FL, In.BRAKE_TORQUE_FR,
                     In.BRAKE_TORQUE_RL, In.BRAKE_TORQUE_RR), "torque"),
}
#: Unit strings production DBCs write (case-insensitive) -> slipd's unit name. A DBC unit
#: not listed here is not checked (the profile's unit is then taken as written).
DBC_UNIT_ALIASES: dict[str, str] = {
    "m/s^2": "m/s^2", "m/s2": "m/s^2", "m/s²": "m/s^2", "mps2": "m/s^2",
    "unit_meterperseconsquar": "m/s^2",
    "g": "g", "unit_forceofgravi": "g",
    "deg": "deg", "degree": "deg", "degrees": "deg", "°": "deg", "unit_degreofarc": "deg",
    "rad": "rad", "radian": "rad", "radians": "rad",
    "deg/s": "deg/s", "degree/s": "deg/s", "degrees/second": "deg/s", "°/s": "deg/s",
    "º/s": "deg/s", "dps": "deg/s", "unit_degreofarcperseconseco": "deg/s",
    "unit_degreofarcpersecon": "deg/s",
    "rad/s": "rad/s", "radians/second": "rad/s", "rad/sec": "rad/s",
    "rpm": "rpm", "rev/min": "rpm", "1/min": "rpm", "unit_minutinver": "rpm",
    "m/s": "m/s", "mps": "m/s", "unit_meterpersecon": "m/s",
    "km/h": "km/h", "kph": "km/h", "kmh": "km/h", "kmph": "km/h",
    "unit_kilometerperhour": "km/h",
    "mph": "mph", "unit_milesperhour": "mph",
    "nm": "Nm", "unit_newtometer": "Nm",
    "ut": "uT", "µt": "uT",
}
#: Where a profile's values can be (beyond this the value is a typo, not a car).
IMU_POSITION_LIMIT = 10.0  # m from the CoG
MAX_TIMEOUT = 60.0  # s: a channel older than a minute is never fresh
MAX_RATE_HZ = 10_000.0
DEFAULT_BUS = "main"
#: slipd's output frames in slipd.dbc (input messages of these names are refused)
OUTPUT_MESSAGE_NAMES = ("SLIPD_STATE", "SLIPD_AUX", "SLIPD_DIAG")


def dbc_unit(unit: str | None) -> str | None:
    """slipd's name for a DBC unit string, or None when slipd does not know it."""
    return DBC_UNIT_ALIASES.get((unit or "").strip().lower())


#: Accelerometer frames an IMU message may declare (``frame`` in [messages.X]).
ACCEL_FRAMES: dict[str, str] = {
    "body": "specific force along the body axes, gravity included: ESC sensor clusters",
    "level": "levelled, gravity-compensated accelerations: an INS's output",
}
ACCEL_CHANNELS = (In.AX, In.AY, In.AZ)

#: E2E schemes the codec implements. Their ids are what the kernels switch on.
E2E_SCHEMES: dict[str, int] = {
    "none": 0,
    "slipd_crc8": 1,  # CRC-8/SAE-J1850 over bytes 1..n-1 + frame-id low byte; 4-bit counter
    "toyota_checksum": 2,  # (dlc + id bytes + sum(data[:-1])) & 0xFF in the last byte
    "autosar_crc8": 3,  # AUTOSAR CRC8H2F over bytes 1..n-1 + data_ids[counter] (VW MQB)
    "honda_checksum": 4,  # 4-bit nibble sum in the last byte's low nibble; 2-bit counter
    "hkg_canfd_crc16": 5,  # Hyundai/Kia CAN FD: CRC-16/XMODEM from byte 2 + ID, in bytes 0-1
    "subaru_checksum": 6,  # (ID bytes + sum(data[1:])) & 0xFF in byte 0
    "tesla_checksum": 7,  # (ID low + ID high + sum(data but the checksum byte)) & 0xFF
}
#: Schemes whose message carries an alive counter the profile must name.
E2E_NEEDS_COUNTER = {"slipd_crc8", "autosar_crc8"}

#: [vehicle] keys -> Veh index. Tyre keys live in [vehicle.tyre].
VEHICLE_KEYS: dict[str, Veh] = {
    "mass": Veh.MASS,
    "yaw_inertia": Veh.YAW_INERTIA,
    "roll_inertia": Veh.ROLL_INERTIA,
    "cog_to_front_axle": Veh.LF,
    "cog_to_rear_axle": Veh.LR,
    "track_front": Veh.TRACK_F,
    "track_rear": Veh.TRACK_R,
    "cog_height": Veh.H_COG,
    "roll_axis_height": Veh.H_ROLL_AXIS,
    "wheel_radius": Veh.WHEEL_RADIUS,
    "steering_ratio": Veh.STEER_RATIO,
    "roll_stiffness": Veh.ROLL_STIFFNESS,
    "roll_damping": Veh.ROLL_DAMPING,
    "wheel_inertia": Veh.WHEEL_INERTIA,
}
TYRE_KEYS: dict[str, Veh] = {
    "cornering_stiffness_front": Veh.CORNERING_STIFFNESS_F,
    "cornering_stiffness_rear": Veh.CORNERING_STIFFNESS_R,
    "longitudinal_stiffness": Veh.LONGITUDINAL_STIFFNESS,
    "peak_friction": Veh.MU_NOMINAL,
    "pacejka_b": Veh.TYRE_B,
    "pacejka_c": Veh.TYRE_C,
    "pacejka_e": Veh.TYRE_E,
}
#: Parameters that must be strictly positive.
POSITIVE = set(VEHICLE_KEYS) | set(TYRE_KEYS) - {"pacejka_e"}
#: [calibration] keys -> (length, limit of |value| (or of |value - 1| for the scales), unit).
#: Beyond a limit the value is a fault of the sensor or the mapping, not an offset.
CALIBRATION_KEYS: dict[str, tuple[int, float, str]] = {
    "imu_mounting_deg": (3, 15.0, "deg"),
    "accel_offset": (3, 3.0, "m/s^2"),
    "gyro_offset": (3, 10.0, "deg/s"),
    "steer_offset_deg": (1, 90.0, "deg"),
    "wheel_radius_scale": (4, 0.2, "relative"),
}


@dataclass(frozen=True)
class SignalMap:
    """One DBC signal feeding one channel: si = physical * factor (summed when several).

    ``sign_signal``: a 1-bit signal that makes the value negative when set (sign-magnitude,
    as VW's ``ESP_VZ_Gierrate``). ``valid_signal``/``valid_values``: a qualifier whose raw
    value must be one of ``valid_values`` for the value to be used (VW ``ESP_QBit_*``: 0).
    ``invalid_values``: raw values that mean "not available" (the DBC's value table fills
    them where its names say so, see slipd.codec.plan.NOT_AVAILABLE)."""

    name: str
    factor: float
    minimum: float | None = None  # physical (DBC units); None = the DBC's own range
    maximum: float | None = None
    check_range: bool = True
    sign_signal: str | None = None
    valid_signal: str | None = None
    valid_values: tuple[int, ...] = ()
    invalid_values: tuple[int, ...] | None = None  # None: from the DBC's value table
    unit: str | None = None  # the profile's unit (None: not given)


@dataclass(frozen=True)
class ChannelMap:
    channel: In
    message: str
    signals: tuple[SignalMap, ...]
    timeout: float  # s; older values are invalid at a tick
    required: bool
    divide_by: str = ""  # the [vehicle] key the value is divided by ("" none)


@dataclass(frozen=True)
class MessageMap:
    name: str
    e2e: str
    rate_hz: float
    timeout: float
    channels: tuple[In, ...]
    crc_signal: str | None = None
    counter_signal: str | None = None
    data_ids: tuple[int, ...] = ()
    max_counter_delta: int = 1
    frame_id: int = -1  # filled from the DBC by the codec
    bus: str = DEFAULT_BUS
    frame: str | None = None  # accelerometer frame of an IMU message (ACCEL_FRAMES); None: body


@dataclass(frozen=True)
class OutputMap:
    """Where slipd's own frames go: IDs (None = slipd.dbc's), bus, CAN FD or classic, or
    nowhere (``listen_only``: estimate and record, send nothing)."""

    frame_ids: dict[str, int] = field(default_factory=dict)  # message name -> ID override
    extended: bool = False
    bus: str = DEFAULT_BUS
    fd: bool = False
    listen_only: bool = False


@dataclass(frozen=True)
class Calibration:
    """The car's sensor errors (the profile's ``[calibration]`` table, slipd identify's output),
    corrected where the codec samples the latch (slipd.codec.calibration), so the daemon and
    the replay see the same corrected inputs. Each offset is what its sensor reads when the
    true value is zero (ISO 8855 axes, sensor axes for the IMU) and is subtracted.

    ``imu_mounting_deg``: the IMU's axes as the body axes rotated by roll, pitch, yaw
    (R = Rz(yaw) Ry(pitch) Rx(roll); a sensor reads R^T v of a body vector v).
    ``accel_offset`` (m/s^2, ax ay az) and ``gyro_offset`` (deg/s, roll pitch yaw rate).
    ``steer_offset_deg``: of the steer signal's own angle, at the steering wheel where the
    channel divides by ``steering_ratio`` (``steer_divisor``, from the channel map).
    ``wheel_radius_scale``: each wheel's rolling radius relative to the one its speed signal
    assumes (fl, fr, rl, rr); true speed = signal x scale."""

    imu_mounting_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    accel_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gyro_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    steer_offset_deg: float = 0.0
    wheel_radius_scale: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    steer_divisor: float = 1.0  # not a key: steering_ratio when the steer channel divides by it

    @property
    def is_identity(self) -> bool:
        """No correction at all (the codec then leaves every input untouched)."""
        return (not any(self.imu_mounting_deg) and not any(self.accel_offset)
                and not any(self.gyro_offset) and self.steer_offset_deg == 0.0
                and all(s == 1.0 for s in self.wheel_radius_scale))


@dataclass(frozen=True)
class Profile:
    path: Path
    name: str
    dbc_path: Path
    vehicle: np.ndarray
    channels: dict[In, ChannelMap]
    messages: dict[str, MessageMap]
    description: str = ""
    extra: dict = field(default_factory=dict)
    outputs: OutputMap = field(default_factory=OutputMap)
    calibration: Calibration = field(default_factory=Calibration)

    @property
    def input_messages(self) -> list[MessageMap]:
        return list(self.messages.values())

    @property
    def buses(self) -> tuple[str, ...]:
        """Bus names in order: the input messages' buses, then the output bus."""
        names: list[str] = []
        for mmap in self.messages.values():
            if mmap.bus not in names:
                names.append(mmap.bus)
        if self.outputs.bus not in names:
            names.append(self.outputs.bus)
        return tuple(names)

    @property
    def accel_frame(self) -> str:
        """The accelerometers' frame (ACCEL_FRAMES): the ay message's ``frame``, else body."""
        return self.messages[self.channels[In.AY].message].frame or "body"

    @property
    def required_channels(self) -> tuple[In, ...]:
        return tuple(c for c, m in self.channels.items() if m.required)


def resolve_profile_path(name_or_path: str | Path) -> Path:
    """A shipped profile by name (``default``) or a path to a TOML file."""
    candidate = Path(name_or_path)
    if candidate.suffix == ".toml" or candidate.exists():
        if not candidate.exists():
            raise ConfigError(f"profile file {candidate} does not exist")
        return candidate.resolve()
    shipped = PROFILE_DIR / f"{name_or_path}.toml"
    if shipped.exists():
        return shipped
    names = sorted(p.stem for p in PROFILE_DIR.glob("*.toml"))
    raise ConfigError(
        f"unknown profile {name_or_path!r}: not a file, and shipped profiles are {names}"
    )


class _Reader:
    """Typed access to one TOML table with errors naming file and key."""

    def __init__(self, path: Path, table: dict, prefix: str):
        self.path, self.table, self.prefix = path, table, prefix
        self.used: set[str] = set()

    def where(self, key: str) -> str:
        return f"{self.path}: [{self.prefix}] {key}" if self.prefix else f"{self.path}: {key}"

    def get(self, key, kind, default=..., what: str = ""):
        self.used.add(key)
        if key not in self.table:
            if default is ...:
                raise ConfigError(f"{self.where(key)} is missing; expected {what or kind.__name__}")
            return default
        value = self.table[key]
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
            raise ConfigError(
                f"{self.where(key)} = {value!r}; expected {what or kind.__name__}"
            )
        return value

    def number(self, key, default=..., positive=False, maximum: float | None = None) -> float:
        value = self.get(key, float, default, "a number")
        if value is not None and value is not ... and not math.isfinite(value):
            raise ConfigError(f"{self.where(key)} = {value!r}; expected a finite number")
        if positive and value is not None and value <= 0.0:
            raise ConfigError(f"{self.where(key)} = {value!r}; expected a number > 0")
        if maximum is not None and value is not None and abs(value) > maximum:
            raise ConfigError(f"{self.where(key)} = {value!r}; expected at most {maximum:g}")
        return value

    def name_of(self, key, default=None, what: str = "a signal name") -> str | None:
        value = self.get(key, str, default, what)
        if value is not None and not value.strip():
            raise ConfigError(f"{self.where(key)} is empty; expected {what}")
        return value

    def raw_values(self, key, default=None, what: str = "a list of raw integer values"):
        values = self.get(key, list, default, what)
        if values is None:
            return None
        if not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in values):
            raise ConfigError(f"{self.where(key)} = {values!r}; expected {what} (>= 0)")
        return tuple(values)

    def no_unknown(self, allowed=None) -> None:
        allowed = self.used if allowed is None else set(allowed) | self.used
        unknown = sorted(set(self.table) - allowed)
        if unknown:
            raise ConfigError(
                f"{self.path}: [{self.prefix}] has unknown key(s) {unknown}; "
                f"expected only {sorted(allowed)}"
            )


def _load_vehicle(path: Path, doc: dict) -> np.ndarray:
    table = doc.get("vehicle")
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: [vehicle] table is missing; expected the vehicle parameters")
    vehicle = np.full(N_VEH, np.nan, dtype=np.float64)
    reader = _Reader(path, table, "vehicle")
    for key, index in VEHICLE_KEYS.items():
        vehicle[index] = reader.number(key, positive=key in POSITIVE)
    imu = reader.get("imu_position", list, what="[x, y, z] in m relative to the CoG")
    if len(imu) != 3 or not all(
        isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
        and abs(v) <= IMU_POSITION_LIMIT for v in imu
    ):
        raise ConfigError(f"{reader.where('imu_position')} = {imu!r}; expected [x, y, z]: "
                          f"three finite numbers in m, each within {IMU_POSITION_LIMIT:g} m "
                          "of the CoG")
    vehicle[Veh.IMU_X], vehicle[Veh.IMU_Y], vehicle[Veh.IMU_Z] = (float(v) for v in imu)
    tyre = reader.get("tyre", dict, what="a [vehicle.tyre] table")
    tyre_reader = _Reader(path, tyre, "vehicle.tyre")
    for key, index in TYRE_KEYS.items():
        vehicle[index] = tyre_reader.number(key, positive=key in POSITIVE)
    tyre_reader.no_unknown()
    reader.no_unknown()
    return vehicle


def _parse_channel(path: Path, name: str, spec: dict, vehicle: np.ndarray, messages: dict):
    try:
        channel = In[name.upper()]
    except KeyError:
        raise ConfigError(
            f"{path}: [channels] {name} is not a slipd channel; expected one of "
            f"{[c.name.lower() for c in In]}"
        ) from None
    if not isinstance(spec, dict):
        raise ConfigError(f"{path}: [channels] {name} = {spec!r}; expected an inline table")
    reader = _Reader(path, spec, f"channels.{name}")
    message = reader.get("message", str, what="a message name of the DBC")
    if message not in messages:
        raise ConfigError(
            f"{reader.where('message')} = {message!r} has no [messages.{message}] table "
            "(every mapped message needs its E2E scheme)"
        )
    signal_spec = reader.get("signal", (str, list), what="a signal name or a list to sum")
    signal_names = [signal_spec] if isinstance(signal_spec, str) else list(signal_spec)
    if not signal_names or not all(isinstance(s, str) for s in signal_names):
        raise ConfigError(f"{reader.where('signal')} = {signal_spec!r}; expected signal names")
    unit = reader.get("unit", str, None, what=f"one of {sorted(UNIT_TABLE)}")
    dimension = CHANNEL_DIMENSION[channel]
    # a wheel's angular rate times its radius is a speed (Ford's wheel speeds are rad/s)
    per_radius = spec.get("multiply_by") == "wheel_radius" and dimension == "speed"
    if unit is not None:
        if unit not in UNIT_TABLE:
            raise ConfigError(f"{reader.where('unit')} = {unit!r}; expected one of "
                              f"{sorted(UNIT_TABLE)}")
        if per_radius and UNIT_TABLE[unit][1] == "angular rate":
            pass
        elif UNIT_TABLE[unit][1] != dimension:
            fitting = sorted(u for u, (_, d) in UNIT_TABLE.items() if d == dimension)
            raise ConfigError(f"{reader.where('unit')} = {unit!r} is a unit of "
                              f"{UNIT_TABLE[unit][1]}, but {name} is a {dimension}; expected "
                              f"one of {fitting}")
    sign = reader.number("sign", 1.0)
    if sign not in (1.0, -1.0):
        raise ConfigError(f"{reader.where('sign')} = {sign!r}; expected 1 or -1")
    factor = (UNIT_TABLE[unit][0] if unit is not None else 1.0) * sign
    sign_signal = reader.name_of("sign_signal", what="the 1-bit sign signal of a "
                                 "sign-magnitude value (1 = negative)")
    valid_signal = reader.name_of("valid_signal", what="a qualifier signal of the value")
    valid_values = reader.raw_values("valid_values", None,
                                     what="the qualifier's raw values that mean valid")
    if valid_signal is not None and not valid_values:
        raise ConfigError(f"{reader.where('valid_values')} is missing; valid_signal = "
                          f"{valid_signal!r} needs the raw values that mean valid, e.g. [0]")
    if valid_values and valid_signal is None:
        raise ConfigError(f"{reader.where('valid_values')} needs valid_signal")
    if valid_values and max(valid_values) > 62:
        raise ConfigError(f"{reader.where('valid_values')} = {list(valid_values)}; "
                          "a qualifier's valid values must be 0..62")
    invalid_values = reader.raw_values("invalid_values", None,
                                       what="raw values that mean not available")
    divide_by = reader.get("divide_by", str, "", what="a [vehicle] key, e.g. steering_ratio")
    multiply_by = reader.get("multiply_by", str, "", what="a [vehicle] key, e.g. wheel_radius")
    for op, key in (("divide_by", divide_by), ("multiply_by", multiply_by)):
        if key and key not in VEHICLE_KEYS:
            raise ConfigError(
                f"{reader.where(op)} = {key!r}; expected a [vehicle] key: {sorted(VEHICLE_KEYS)}"
            )
    if divide_by:
        factor /= vehicle[VEHICLE_KEYS[divide_by]]
    if multiply_by:
        factor *= vehicle[VEHICLE_KEYS[multiply_by]]
    minimum = reader.number("min", None)
    maximum = reader.number("max", None)
    if minimum is not None and maximum is not None and minimum >= maximum:
        raise ConfigError(f"{reader.where('min')} = {minimum} is not below max = {maximum}")
    check_range = reader.get("check_range", bool, True)
    timeout = reader.number("timeout", messages[message].timeout, positive=True,
                            maximum=MAX_TIMEOUT)
    required = reader.get("required", bool, channel in CORE_CHANNELS)
    reader.no_unknown()
    signals = tuple(
        SignalMap(s, factor, minimum, maximum, check_range, sign_signal, valid_signal,
                  valid_values or (), invalid_values, unit)
        for s in signal_names
    )
    return ChannelMap(channel, message, signals, timeout, required, divide_by)


def _parse_message(path: Path, name: str, spec: dict) -> MessageMap:
    if not isinstance(spec, dict):
        raise ConfigError(f"{path}: [messages] {name} = {spec!r}; expected a table")
    reader = _Reader(path, spec, f"messages.{name}")
    e2e = reader.get("e2e", str, what=f"one of {sorted(E2E_SCHEMES)}")
    if e2e not in E2E_SCHEMES:
        raise ConfigError(
            f"{reader.where('e2e')} = {e2e!r} is not an end-to-end scheme slipd implements; "
            f"expected one of {sorted(E2E_SCHEMES)}"
        )
    rate_hz = reader.number("rate_hz", positive=True, maximum=MAX_RATE_HZ)
    timeout = reader.number("timeout", min(5.0 / rate_hz, MAX_TIMEOUT), positive=True,
                            maximum=MAX_TIMEOUT)
    crc_signal = reader.name_of("crc_signal")
    counter_signal = reader.name_of("counter_signal")
    data_ids = reader.get("data_ids", list, [], what="16 data-ID bytes, one per counter value")
    max_delta = reader.get("max_counter_delta", int, 1)
    bus = reader.name_of("bus", DEFAULT_BUS, what="a bus name, e.g. chassis")
    frame = reader.get("frame", str, None, what=f"one of {list(ACCEL_FRAMES)}")
    if frame is not None and frame not in ACCEL_FRAMES:
        raise ConfigError(f"{reader.where('frame')} = {frame!r}; expected one of "
                          f"{list(ACCEL_FRAMES)} ({'; '.join(ACCEL_FRAMES.values())})")
    if e2e in E2E_NEEDS_COUNTER and (crc_signal is None or counter_signal is None):
        raise ConfigError(
            f"{path}: [messages.{name}] e2e = {e2e!r} needs crc_signal and counter_signal"
        )
    if e2e != "none" and crc_signal is None:
        raise ConfigError(f"{path}: [messages.{name}] e2e = {e2e!r} needs crc_signal")
    if e2e == "none" and crc_signal is not None:
        raise ConfigError(f"{reader.where('crc_signal')}: e2e = 'none' checks no CRC; name "
                          f"the scheme (one of {sorted(E2E_SCHEMES)})")
    if e2e == "autosar_crc8":
        if len(data_ids) != 16 or not all(isinstance(d, int) and not isinstance(d, bool)
                                          and 0 <= d <= 255 for d in data_ids):
            raise ConfigError(
                f"{reader.where('data_ids')} = {data_ids!r}; expected 16 integers 0..255"
            )
    elif data_ids:
        raise ConfigError(f"{reader.where('data_ids')} only applies to e2e = 'autosar_crc8'")
    if not 1 <= max_delta <= 14:
        raise ConfigError(f"{reader.where('max_counter_delta')} = {max_delta}; expected 1..14")
    reader.no_unknown()
    return MessageMap(
        name, e2e, rate_hz, timeout, (), crc_signal, counter_signal, tuple(data_ids), max_delta,
        bus=bus, frame=frame,
    )


def _parse_outputs(path: Path, table) -> OutputMap:
    """[outputs]: IDs, bus, FD and listen-only of slipd's own frames."""
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: [outputs] = {table!r}; expected a table")
    reader = _Reader(path, table, "outputs")
    extended = reader.get("extended", bool, False)
    limit = 0x1FFFFFFF if extended else 0x7FF
    frame_ids = {}
    for name in OUTPUT_MESSAGE_NAMES:
        key = f"{name.removeprefix('SLIPD_').lower()}_id"
        value = reader.get(key, int, None, what=f"the CAN ID of {name}")
        if value is None:
            continue
        if not 0 <= value <= limit:
            raise ConfigError(f"{reader.where(key)} = {value:#x}; expected a "
                              f"{'29' if extended else '11'}-bit ID 0..{limit:#x}")
        frame_ids[name] = value
    if len(set(frame_ids.values())) != len(frame_ids):
        raise ConfigError(f"{path}: [outputs] gives two output messages the same ID: "
                          f"{ {k: hex(v) for k, v in frame_ids.items()} }")
    if extended and len(frame_ids) != len(OUTPUT_MESSAGE_NAMES):
        raise ConfigError(f"{path}: [outputs] extended = true needs all of state_id, aux_id "
                          "and diag_id")
    bus = reader.name_of("bus", DEFAULT_BUS, what="the bus the outputs are sent on")
    fd = reader.get("fd", bool, False)
    listen_only = reader.get("listen_only", bool, False)
    reader.no_unknown()
    return OutputMap(frame_ids, extended, bus, fd, listen_only)


def _parse_calibration(path: Path, table, channels: dict[In, ChannelMap],
                       vehicle: np.ndarray) -> Calibration:
    """[calibration]: the sensor errors slipd identify finds (all optional, identity default)."""
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: [calibration] = {table!r}; expected a table")
    reader = _Reader(path, table, "calibration")
    values: dict = {}
    for key, (length, limit, unit) in CALIBRATION_KEYS.items():
        scale = key == "wheel_radius_scale"
        if length == 1:
            value = reader.number(key, None, maximum=limit)
            if value is not None:
                values[key] = value
            continue
        what = (f"{length} numbers ({unit}), each within {limit:g} of 1" if scale else
                f"{length} numbers ({unit}), each within +-{limit:g}")
        items = reader.get(key, list, None, what=what)
        if items is None:
            continue
        if len(items) != length or not all(
                isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
                and abs(v - (1.0 if scale else 0.0)) <= limit for v in items):
            raise ConfigError(f"{reader.where(key)} = {items!r}; expected {what}")
        values[key] = tuple(float(v) for v in items)
    reader.no_unknown()
    steer = channels.get(In.STEER)
    divisor = 1.0
    if steer is not None and steer.divide_by == "steering_ratio":
        divisor = float(vehicle[Veh.STEER_RATIO])
    return Calibration(**values, steer_divisor=divisor)


def load_profile(name_or_path: str | Path = "default", edit=None,
                 check_dbc: bool = True) -> Profile:
    """Load and validate a vehicle profile (a shipped name or a TOML path).

    ``edit``, when given, is called with the parsed TOML document before it is validated and
    may change it in place: how ``slipd eval --mismatch`` gives an estimator a wrong car
    (every derived value, e.g. the steering-ratio factor of the steer channel, follows).

    With ``check_dbc`` (the default) the profile is also compiled against its DBC
    (slipd.codec.plan.check_profile): every signal, unit, range and ID it names is checked
    there, so a profile that loads is one the codec can run."""
    path = resolve_profile_path(name_or_path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start}: {exc.reason}); a "
                          "profile is a TOML file") from exc
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the profile: {exc.strerror}") from exc
    if edit is not None:
        edit(doc)
    top = _Reader(path, doc, "")
    head = _Reader(path, top.get("profile", dict, what="a [profile] table"), "profile")
    name = head.get("name", str)
    description = head.get("description", str, "")
    dbc_name = head.get("dbc", str, what="the DBC file, relative to the profile")
    head.no_unknown()
    dbc_path = (path.parent / dbc_name).resolve()
    if not dbc_path.exists() and (PROFILE_DIR / dbc_name).is_file():
        dbc_path = PROFILE_DIR / dbc_name  # a shipped DBC (slipd.dbc) by name, from anywhere
    if not dbc_path.exists():
        raise ConfigError(f"{path}: [profile] dbc = {dbc_name!r}: {dbc_path} does not exist "
                          f"(nor is it a shipped DBC: "
                          f"{sorted(p.name for p in PROFILE_DIR.glob('*.dbc'))})")
    vehicle = _load_vehicle(path, doc)
    top.used.add("vehicle")
    message_table = top.get("messages", dict, what="a [messages.NAME] table per input message")
    for mname in message_table:
        if mname in OUTPUT_MESSAGE_NAMES:
            raise ConfigError(f"{path}: [messages.{mname}] is slipd's own output message; "
                              "slipd cannot estimate from its own frames")
    messages = {n: _parse_message(path, n, s) for n, s in message_table.items()}
    channel_table = top.get("channels", dict, what="a [channels] table")
    channels: dict[In, ChannelMap] = {}
    for cname, spec in channel_table.items():
        cmap = _parse_channel(path, cname, spec, vehicle, messages)
        channels[cmap.channel] = cmap
    missing = [c.name.lower() for c in CORE_CHANNELS if c not in channels]
    if missing:
        raise ConfigError(
            f"{path}: [channels] lacks {missing}; every estimator needs IMU ax/ay, yaw rate, "
            "steer and the four wheel speeds"
        )
    for mname, mmap in list(messages.items()):
        used = tuple(c for c, m in channels.items() if m.message == mname)
        if not used:
            raise ConfigError(f"{path}: [messages.{mname}] feeds no channel; remove it or map one")
        if mmap.frame is not None and not set(used) & set(ACCEL_CHANNELS):
            raise ConfigError(f"{path}: [messages.{mname}] frame = {mmap.frame!r}: the message "
                              "carries no accelerometer channel (ax, ay, az)")
        messages[mname] = MessageMap(**{**mmap.__dict__, "channels": used})
    frames = {messages[channels[c].message].frame or "body" for c in ACCEL_CHANNELS
              if c in channels}
    if len(frames) > 1:
        raise ConfigError(f"{path}: the accelerometer channels' messages declare different "
                          f"frames {sorted(frames)}; ax, ay and az must share one")
    vehicle[Veh.ACCEL_LEVEL] = 1.0 if frames == {"level"} else 0.0
    outputs = _parse_outputs(path, top.get("outputs", dict, {}, what="an [outputs] table"))
    calibration = _parse_calibration(
        path, top.get("calibration", dict, {}, what="a [calibration] table"), channels, vehicle)
    top.no_unknown()
    profile = Profile(path, name, dbc_path, vehicle, channels, messages, description,
                      outputs=outputs, calibration=calibration)
    if check_dbc:
        from slipd.codec.plan import check_profile

        check_profile(profile)
    return profile
