"""Compile (DBC, profile) into the array plan the codec kernels execute.

cantools parses the DBC once; the plan keeps, per signal, where its bits are (start bit,
length, byte order), how to read them (signedness, IEEE float) and how to scale them
(DBC scale/offset, then the profile's unit factor to SI), which signals qualify it (a sign
bit, a qualifier, the value table's "not available" codes), and on which bus the message is.
Everything that can be wrong with the combination is found here, at load time, with the file
and the name in the message.
"""

from __future__ import annotations

import enum
import functools
import math
import re
from dataclasses import dataclass
from pathlib import Path

import cantools
import numpy as np

from slipd.channels import N_IN, In, Out
from slipd.codec import kernels as K
from slipd.errors import CodecError, ConfigError
from slipd.profile import (
    CHANNEL_DIMENSION,
    E2E_SCHEMES,
    UNIT_TABLE,
    MessageMap,
    OutputMap,
    Profile,
    dbc_unit,
)

SLIPD_DBC = Path(__file__).resolve().parent.parent / "dbc" / "slipd.dbc"


@enum.unique
class Tx(enum.IntEnum):
    """Value slots of slipd's output frames (SI), the first ones equal to ``Out``."""

    BETA = Out.BETA
    BETA_RATE = Out.BETA_RATE
    VX = Out.VX
    VY = Out.VY
    MU = Out.MU
    SIGMA_BETA = Out.SIGMA_BETA
    ROLL = Out.ROLL
    FRICTION_CLASS = Out.FRICTION_CLASS
    STATUS = Out.STATUS
    MU_VALID = 9
    ESTIMATOR_ID = 10
    DEADLINE_MISSES = 11
    LATENCY_P50_US = 12
    LATENCY_P99_US = 13
    LATENCY_MAX_US = 14
    INPUT_TIMEOUTS = 15
    RX_ERRORS = 16


N_TX = len(Tx)
DEG = math.pi / 180.0
#: Output signal -> (slot, SI factor: physical = SI / factor).
OUTPUT_SIGNALS: dict[str, tuple[Tx, float]] = {
    "STATUS": (Tx.STATUS, 1.0),
    "BETA": (Tx.BETA, DEG),
    "BETA_RATE": (Tx.BETA_RATE, DEG),
    "VX": (Tx.VX, 1.0),
    "VY": (Tx.VY, 1.0),
    "FRICTION_CLASS": (Tx.FRICTION_CLASS, 1.0),
    "MU_VALID": (Tx.MU_VALID, 1.0),
    "MU": (Tx.MU, 1.0),
    "ESTIMATOR_ID": (Tx.ESTIMATOR_ID, 1.0),
    "ROLL": (Tx.ROLL, DEG),
    "SIGMA_BETA": (Tx.SIGMA_BETA, DEG),
    "DEADLINE_MISSES": (Tx.DEADLINE_MISSES, 1.0),
    "LATENCY_P50": (Tx.LATENCY_P50_US, 1.0),
    "LATENCY_P99": (Tx.LATENCY_P99_US, 1.0),
    "LATENCY_MAX": (Tx.LATENCY_MAX_US, 1.0),
    "INPUT_TIMEOUTS": (Tx.INPUT_TIMEOUTS, 1.0),
    "RX_ERRORS": (Tx.RX_ERRORS, 1.0),
}
OUTPUT_MESSAGES = ("SLIPD_STATE", "SLIPD_AUX", "SLIPD_DIAG")
#: Value-table names that mean "no valid value" (init, fault, signal not available, ...).
NOT_AVAILABLE = re.compile(
    r"init|not[ _-]?avail|unavail|n/a|\bsna\b|invalid|ung(ue|ü)ltig|fehler|error|fault|"
    r"undefined|signal[ _-]?not|no[ _-]?signal|no[ _-]?data|\bunknown\b|ersatz", re.IGNORECASE)
#: CRC/checksum field per scheme: bits, and where it must sit ("last", "first", "any").
CRC_FIELDS = {"slipd_crc8": (8, "any"), "autosar_crc8": (8, "any"),
              "toyota_checksum": (8, "last"), "honda_checksum": (4, "last"),
              "hkg_canfd_crc16": (16, "first"), "subaru_checksum": (8, "first"),
              "tesla_checksum": (8, "any")}


@dataclass(frozen=True)
class Plan:
    """A compiled plan: the kernel arrays plus the names to report with."""

    plan_i: np.ndarray
    plan_f: np.ndarray
    lookup: np.ndarray
    message_names: tuple[str, ...]
    message_rows: dict[str, int]
    timeouts: np.ndarray  # float64 [n_msg], s
    dbc_path: Path
    buses: tuple[str, ...] = ("main",)

    @property
    def n_messages(self) -> int:
        return len(self.message_names)

    def frame_id(self, name: str) -> int:
        return int(self.plan_i[self.message_rows[name], K.M_FRAME_ID])

    def dlc(self, name: str) -> int:
        return int(self.plan_i[self.message_rows[name], K.M_DLC])

    def is_extended(self, name: str) -> bool:
        return bool(self.plan_i[self.message_rows[name], K.M_EXTENDED])

    def is_fd(self, name: str) -> bool:
        return bool(self.plan_i[self.message_rows[name], K.M_FD])

    def bus(self, name: str) -> str:
        return self.buses[int(self.plan_i[self.message_rows[name], K.M_BUS])]

    @property
    def max_dlc(self) -> int:
        return int(self.plan_i[: self.n_messages, K.M_DLC].max()) if self.n_messages else 8

    def ids_on(self, bus: str) -> list[tuple[int, bool]]:
        """(frame ID, extended) of every message on bus ``bus`` (kernel receive filters)."""
        return [(self.frame_id(n), self.is_extended(n)) for n in self.message_names
                if self.bus(n) == bus]


def load_dbc(path: Path):
    """Load a DBC with cantools; production DBCs (opendbc) need ``strict=False``. Parsed
    once per file version (a profile check and its codec share it)."""
    path = Path(path)
    try:
        stat = path.stat()
    except OSError as exc:
        raise CodecError(f"{path}: cannot read DBC: {exc.strerror}") from exc
    return _load_dbc(str(path), stat.st_mtime_ns, stat.st_size)


@functools.lru_cache(maxsize=8)
def _load_dbc(path: str, _mtime_ns: int, _size: int):
    try:
        return cantools.database.load_file(path, strict=False)
    except Exception as exc:  # cantools raises several parser error types
        first = exc
    # opendbc's generated DBCs carry a few comments cantools' grammar refuses (``CM_ SG_ 304
    # "text"`` without a signal name); comments never change how a frame decodes, so such
    # lines are dropped and the file parsed again.
    try:
        lines = Path(path).read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        lines = []
    for _ in range(50):
        match = re.search(r"at line (\d+)", str(first))
        if not match or not lines[int(match.group(1)) - 1].lstrip().startswith("CM_"):
            break
        del lines[int(match.group(1)) - 1]
        try:
            return cantools.database.load_string("\n".join(lines) + "\n",
                                                 database_format="dbc", strict=False)
        except Exception as exc:  # noqa: BLE001 - the next unparsable comment, or worse
            first = exc
    raise CodecError(f"{path}: cannot parse DBC: {first}") from first


def _signal_row(signal, where: str, length_bytes: int) -> tuple[list[int], list[float]]:
    if signal.length < 1 or signal.length > 64:
        raise CodecError(f"{where}: signal {signal.name} is {signal.length} bits; 1..64")
    if signal.is_float and signal.length not in (32, 64):
        raise CodecError(f"{where}: float signal {signal.name} must be 32 or 64 bits")
    if not math.isfinite(signal.scale) or signal.scale == 0.0:
        raise CodecError(f"{where}: signal {signal.name} has scale {signal.scale!r}; a DBC "
                         "scale must be a finite number other than 0")
    if not math.isfinite(signal.offset):
        raise CodecError(f"{where}: signal {signal.name} has offset {signal.offset!r}")
    start, length = signal.start, signal.length
    if signal.byte_order == "little_endian":
        position, big, last = start, 0, start + length - 1
    else:
        position = (start // 8) * 8 + (7 - start % 8)  # MSB, counted from byte 0 bit 7 down
        big, last = 1, position + length - 1
    if last >= 8 * length_bytes:
        raise CodecError(f"{where}: signal {signal.name} extends past byte {length_bytes} of "
                         "the message")
    row_i = [0] * K.I_COLS
    row_i[K.S_START] = position
    row_i[K.S_LENGTH] = length
    row_i[K.S_BIG_ENDIAN] = big
    row_i[K.S_SIGNED] = int(bool(signal.is_signed))
    row_i[K.S_FLOAT] = int(bool(signal.is_float))
    row_i[K.S_SLOT] = -1
    row_i[K.S_CRC_BYTE] = start // 8
    row_i[K.S_SIGN_ROW] = -1
    row_i[K.S_VALID_ROW] = -1
    row_f = [0.0] * K.F_COLS
    row_f[K.F_SCALE] = float(signal.scale)
    row_f[K.F_OFFSET] = float(signal.offset)
    minimum = signal.minimum if signal.minimum is not None else 0.0
    maximum = signal.maximum if signal.maximum is not None else 0.0
    row_f[K.F_MIN] = float(minimum)
    row_f[K.F_MAX] = float(maximum)
    row_f[K.F_FACTOR] = 1.0
    return row_i, row_f


@dataclass(frozen=True)
class SignalSpec:
    """What the plan needs of one signal that feeds a slot."""

    slot: int
    factor: float = 1.0
    minimum: float | None = None
    maximum: float | None = None
    check_range: bool = True
    accumulate: bool = False
    sign_signal: str | None = None
    valid_signal: str | None = None
    valid_values: tuple[int, ...] = ()
    invalid_values: tuple[int, ...] | None = ()  # None: the DBC value table's codes


def not_available_codes(signal) -> tuple[int, ...]:
    """Raw values of ``signal``'s DBC value table whose names mean "not available"."""
    choices = signal.choices or {}
    return tuple(sorted(int(raw) for raw, label in choices.items()
                        if NOT_AVAILABLE.search(str(label))))


def _check_crc_field(where: str, e2e: str, sig, length_bytes: int) -> None:
    bits, place = CRC_FIELDS[e2e]
    if sig.length != bits:
        raise CodecError(f"{where}: {e2e} needs a {bits}-bit checksum; {sig.name} is "
                         f"{sig.length} bits")
    if bits >= 8:
        aligned = sig.start % 8 == (0 if sig.byte_order == "little_endian" else 7)
        if not aligned:
            raise CodecError(f"{where}: checksum {sig.name} must fill whole bytes")
    byte = sig.start // 8
    if place == "last" and byte != length_bytes - 1:
        raise CodecError(f"{where}: {e2e} keeps its checksum in the last byte; {sig.name} "
                         f"is in byte {byte}")
    if place == "first" and byte != 0:
        raise CodecError(f"{where}: {e2e} keeps its checksum at byte 0; {sig.name} is in "
                         f"byte {byte}")
    if e2e == "hkg_canfd_crc16" and sig.byte_order != "little_endian":
        raise CodecError(f"{where}: the Hyundai/Kia CRC-16 is little-endian in bytes 0-1")


def _build(dbc_path: Path, specs: list[tuple[str, MessageMap | None, dict]],
           buses: tuple[str, ...] = ("main",), where_profile: str = "") -> Plan:
    """specs: (message name, its MessageMap or None for outputs, {signal: SignalSpec or the
    tuple (slot, factor, min, max, check_range, accumulate)})."""
    db = load_dbc(dbc_path)
    msg_rows_i: list[list[int]] = []
    sig_rows_i: list[list[int]] = []
    sig_rows_f: list[list[float]] = []
    names: list[str] = []
    timeouts: list[float] = []
    n_msg = len(specs)
    for name, mmap, signals in specs:
        signals = {k: v if isinstance(v, SignalSpec) else SignalSpec(
            int(v[0]), v[1], v[2], v[3], v[4], v[5]) for k, v in signals.items()}
        where = f"{dbc_path.name}: message {name}"
        try:
            message = db.get_message_by_name(name)
        except KeyError:
            raise CodecError(f"{dbc_path}: no message {name!r} (the profile maps it)") from None
        if message.is_multiplexed():
            raise CodecError(
                f"{where} is multiplexed; slipd's codec does not decode multiplexed messages "
                "(map a non-multiplexed message or extend the codec)"
            )
        if message.length > K.MAX_PAYLOAD or message.length not in K.FD_LENGTHS:
            raise CodecError(f"{where} is {message.length} bytes; a CAN frame has 0..8 bytes "
                             f"and a CAN FD frame one of {K.FD_LENGTHS[9:]}")
        by_name = {s.name: s for s in message.signals}
        row = [0] * K.I_COLS
        row[K.M_FRAME_ID] = message.frame_id
        row[K.M_DLC] = message.length
        row[K.M_EXTENDED] = int(message.is_extended_frame)
        row[K.M_FD] = int(message.length > 8 or bool(getattr(message, "is_fd", False)))
        row[K.M_SIG_FIRST] = n_msg + len(sig_rows_i)
        row[K.M_CRC_ROW] = -1
        row[K.M_COUNTER_ROW] = -1
        row[K.M_MAX_DELTA] = mmap.max_counter_delta if mmap else 1
        bus_name = mmap.bus if mmap else buses[0]
        row[K.M_BUS] = buses.index(bus_name)
        e2e = mmap.e2e if mmap else "slipd_crc8"
        crc_signal = mmap.crc_signal if mmap else f"{name}_CRC"
        counter_signal = mmap.counter_signal if mmap else f"{name}_Counter"
        row[K.M_E2E] = E2E_SCHEMES[e2e]
        if mmap and mmap.data_ids:
            row[K.M_DATA_IDS:K.M_DATA_IDS + 16] = list(mmap.data_ids)
        for sig_name, spec in signals.items():
            for what, needed in (("signal", sig_name), ("sign_signal", spec.sign_signal),
                                 ("valid_signal", spec.valid_signal)):
                if needed is not None and needed not in by_name:
                    raise CodecError(
                        f"{where_profile}{where} has no {what} {needed!r}; it has "
                        f"{sorted(by_name)}")
            if spec.sign_signal is not None and by_name[spec.sign_signal].length != 1:
                raise CodecError(f"{where}: sign_signal {spec.sign_signal} is "
                                 f"{by_name[spec.sign_signal].length} bits; a sign is 1 bit")
            if spec.valid_signal is not None:
                qualifier = by_name[spec.valid_signal]
                if qualifier.length > 6:
                    raise CodecError(f"{where}: valid_signal {spec.valid_signal} is "
                                     f"{qualifier.length} bits; a qualifier has at most 6")
                outside = [v for v in spec.valid_values if v >= 1 << qualifier.length]
                if outside:
                    raise CodecError(f"{where}: valid_values {outside} do not fit the "
                                     f"{qualifier.length}-bit {spec.valid_signal}")
        role_rows: dict[str, str] = {}
        if e2e != "none":
            if crc_signal not in by_name:
                raise CodecError(f"{where}: crc signal {crc_signal!r} not in the DBC")
            _check_crc_field(where, e2e, by_name[crc_signal], message.length)
            role_rows["crc"] = crc_signal
        if counter_signal is not None and (mmap is None or mmap.counter_signal is not None):
            if counter_signal not in by_name:
                raise CodecError(f"{where}: counter signal {counter_signal!r} not in the DBC")
            modulus = 1 << by_name[counter_signal].length
            if mmap and not 1 <= mmap.max_counter_delta <= modulus - 2:
                raise CodecError(f"{where}: max_counter_delta = {mmap.max_counter_delta} with "
                                 f"the {modulus}-value counter {counter_signal}; expected "
                                 f"1..{modulus - 2}")
            role_rows["counter"] = counter_signal
        extra = []
        for spec in signals.values():
            for helper in (spec.sign_signal, spec.valid_signal):
                if helper is not None and helper not in signals and helper not in extra:
                    extra.append(helper)
        first = len(sig_rows_i)
        ordered = list(signals) + [s for s in list(role_rows.values()) + extra
                                   if s not in signals]
        ordered = list(dict.fromkeys(ordered))
        row_of = {sig_name: n_msg + first + k for k, sig_name in enumerate(ordered)}
        for sig_name in ordered:
            signal = by_name[sig_name]
            row_i, row_f = _signal_row(signal, where, message.length)
            spec = signals.get(sig_name)
            if spec is not None:
                row_i[K.S_SLOT] = spec.slot
                row_i[K.S_ACCUMULATE] = int(spec.accumulate)
                row_i[K.S_CHECK_RANGE] = int(spec.check_range)
                row_f[K.F_FACTOR] = spec.factor
                if spec.minimum is not None:
                    row_f[K.F_MIN] = spec.minimum
                if spec.maximum is not None:
                    row_f[K.F_MAX] = spec.maximum
                if spec.sign_signal is not None:
                    row_i[K.S_SIGN_ROW] = row_of[spec.sign_signal]
                if spec.valid_signal is not None:
                    row_i[K.S_VALID_ROW] = row_of[spec.valid_signal]
                    row_i[K.S_VALID_MASK] = sum(1 << v for v in spec.valid_values)
                codes = (not_available_codes(signal) if spec.invalid_values is None
                         else spec.invalid_values)
                if len(codes) > K.MAX_INVALID:
                    raise CodecError(f"{where}: signal {sig_name} has {len(codes)} "
                                     f"not-available values; at most {K.MAX_INVALID}")
                row_i[K.S_N_INVALID] = len(codes)
                row_i[K.S_INVALID:K.S_INVALID + len(codes)] = list(codes)
            sig_rows_i.append(row_i)
            sig_rows_f.append(row_f)
        if "crc" in role_rows:
            row[K.M_CRC_ROW] = row_of[role_rows["crc"]]
        if "counter" in role_rows:
            row[K.M_COUNTER_ROW] = row_of[role_rows["counter"]]
        row[K.M_SIG_COUNT] = len(sig_rows_i) - first
        msg_rows_i.append(row)
        names.append(name)
        timeouts.append(mmap.timeout if mmap else 1.0)
    plan_i = np.array(msg_rows_i + sig_rows_i, dtype=np.int64).reshape(-1, K.I_COLS)
    plan_f = np.zeros((len(plan_i), K.F_COLS), dtype=np.float64)
    if sig_rows_f:
        plan_f[n_msg:] = np.array(sig_rows_f, dtype=np.float64)
    lookup = _lookup(msg_rows_i, names, buses, dbc_path)
    return Plan(plan_i, plan_f, lookup, tuple(names), {n: i for i, n in enumerate(names)},
                np.array(timeouts, dtype=np.float64), dbc_path, tuple(buses))


def _lookup(msg_rows_i: list[list[int]], names: list[str], buses: tuple[str, ...],
            dbc_path: Path) -> np.ndarray:
    """The kernels' (bus, ID) -> message row table (see slipd.codec.kernels)."""
    standard = np.full(2048 * len(buses), -1, dtype=np.int64)
    extended: dict[int, int] = {}
    for index, row in enumerate(msg_rows_i):
        frame_id, bus = row[K.M_FRAME_ID], row[K.M_BUS]
        if row[K.M_EXTENDED]:
            key = (bus << K.BUS_KEY_SHIFT) | frame_id
            if key in extended:
                raise CodecError(f"{dbc_path}: messages {names[extended[key]]} and "
                                 f"{names[index]} share frame ID {frame_id:#x} on bus "
                                 f"{buses[bus]!r}")
            extended[key] = index
        else:
            if standard[bus * 2048 + frame_id] >= 0:
                other = names[standard[bus * 2048 + frame_id]]
                raise CodecError(f"{dbc_path}: messages {other} and {names[index]} share "
                                 f"frame ID {frame_id:#x} on bus {buses[bus]!r}")
            standard[bus * 2048 + frame_id] = index
    keys = sorted(extended)
    return np.concatenate([
        np.array([len(buses), len(keys)], dtype=np.int64), standard,
        np.array(keys + [extended[k] for k in keys], dtype=np.int64)])


def input_signal_specs(profile: Profile) -> list[tuple[str, MessageMap, dict]]:
    specs = []
    for name, mmap in profile.messages.items():
        signals: dict[str, SignalSpec] = {}
        for channel in mmap.channels:
            cmap = profile.channels[channel]
            for position, smap in enumerate(cmap.signals):
                if smap.name in signals:
                    raise CodecError(
                        f"{profile.path}: signal {name}.{smap.name} feeds two channels"
                    )
                signals[smap.name] = SignalSpec(
                    int(channel), smap.factor, smap.minimum, smap.maximum, smap.check_range,
                    position > 0, smap.sign_signal, smap.valid_signal, smap.valid_values,
                    smap.invalid_values)
        specs.append((name, mmap, signals))
    return specs


def compile_input_plan(profile: Profile) -> Plan:
    """The decode plan of a profile's input messages (slots are ``In`` channels)."""
    return _build(profile.dbc_path, input_signal_specs(profile), profile.buses,
                  f"{profile.path}: ")


def compile_output_plan(dbc_path: Path = SLIPD_DBC, outputs: OutputMap | None = None) -> Plan:
    """The encode plan of slipd's output frames (slots are ``Tx`` values), with the profile's
    output IDs and frame format (``outputs``; None: slipd.dbc's IDs, classic frames).
    Compiled once per DBC file version and output layout, as the DBC is parsed once (a
    replay asked for it six times: profile check, codec, supervision, the recorder's
    SLIPD_STATE ID, 0.3 ms each); the plan is shared, its arrays are only read."""
    path = Path(dbc_path)
    try:
        stat = path.stat()
    except OSError as exc:
        raise CodecError(f"{path}: cannot read DBC: {exc.strerror}") from exc
    layout = None if outputs is None else (tuple(sorted(outputs.frame_ids.items())),
                                           outputs.extended, outputs.bus, outputs.fd)
    return _output_plan(str(path), stat.st_mtime_ns, stat.st_size, layout)


@functools.lru_cache(maxsize=16)
def _output_plan(dbc_path: str, _mtime_ns: int, _size: int, layout: tuple | None) -> Plan:
    dbc_path = Path(dbc_path)
    outputs = None if layout is None else OutputMap(frame_ids=dict(layout[0]),
                                                    extended=layout[1], bus=layout[2],
                                                    fd=layout[3])
    db = load_dbc(dbc_path)
    specs = []
    bus = outputs.bus if outputs is not None else "main"
    for name in OUTPUT_MESSAGES:
        message = db.get_message_by_name(name)
        signals = {}
        for signal in message.signals:
            if signal.name in OUTPUT_SIGNALS:
                slot, factor = OUTPUT_SIGNALS[signal.name]
                signals[signal.name] = SignalSpec(int(slot), factor)
        specs.append((name, None, signals))
    plan = _build(dbc_path, specs, (bus,))
    if outputs is None or not (outputs.frame_ids or outputs.fd or outputs.extended):
        return plan
    plan_i = plan.plan_i.copy()
    rows = []
    for name in OUTPUT_MESSAGES:
        row = plan.message_rows[name]
        plan_i[row, K.M_FRAME_ID] = outputs.frame_ids.get(name, plan.frame_id(name))
        plan_i[row, K.M_EXTENDED] = int(outputs.extended)
        plan_i[row, K.M_FD] = int(outputs.fd)
        rows.append(list(plan_i[row]))
    names = list(plan.message_names)
    lookup = _lookup(rows, names, (bus,), dbc_path)
    return Plan(plan_i, plan.plan_f, lookup, plan.message_names, plan.message_rows,
                plan.timeouts, dbc_path, (bus,))


def channel_timeouts(profile: Profile) -> np.ndarray:
    """float64 [N_IN]: each channel's timeout (unmapped channels: never valid)."""
    timeouts = np.full(N_IN, -1.0, dtype=np.float64)
    for channel, cmap in profile.channels.items():
        timeouts[channel] = cmap.timeout
    return timeouts


def check_profile(profile: Profile) -> Plan:
    """Check a profile against its DBC (load_profile calls it): the codec compiles, every
    channel's unit agrees with its signal's DBC unit, and no input frame uses an ID of slipd's
    own output frames on the output bus. Returns the input plan."""
    plan = compile_input_plan(profile)
    db = load_dbc(profile.dbc_path)
    for channel, cmap in profile.channels.items():
        key = f"{profile.path}: [channels] {channel.name.lower()}"
        message = db.get_message_by_name(cmap.message)
        dimension = CHANNEL_DIMENSION[channel]
        for smap in cmap.signals:
            signal = message.get_signal_by_name(smap.name)
            said = dbc_unit(signal.unit)
            if smap.unit is None:
                if dimension == "1":
                    continue
                if said is not None:
                    raise ConfigError(
                        f"{key}: unit is missing; the DBC gives {cmap.message}.{smap.name} in "
                        f"{signal.unit!r} ({said}): write unit = \"{said}\"")
                fitting = sorted(u for u, (_, d) in UNIT_TABLE.items() if d == dimension)
                raise ConfigError(
                    f"{key}: unit is missing and the DBC does not say it ({cmap.message}."
                    f"{smap.name} has unit {signal.unit or ''!r}); a {dimension} needs one "
                    f"of {fitting}")
            if said is not None and UNIT_TABLE[said] != UNIT_TABLE[smap.unit]:
                raise ConfigError(
                    f"{key}: unit = {smap.unit!r}, but the DBC gives {cmap.message}."
                    f"{smap.name} in {signal.unit!r} ({said})")
    outputs = compile_output_plan(outputs=profile.outputs)
    for name in outputs.message_names:
        clash = [n for n in plan.message_names if plan.bus(n) == profile.outputs.bus
                 and plan.frame_id(n) == outputs.frame_id(name)
                 and plan.is_extended(n) == outputs.is_extended(name)]
        if clash:
            raise ConfigError(
                f"{profile.path}: input message {clash[0]} has frame ID "
                f"{outputs.frame_id(name):#x} on bus {profile.outputs.bus!r}, which is slipd's "
                f"own {name}; move the outputs ([outputs] {name.removeprefix('SLIPD_').lower()}"
                "_id) or the output bus")
    return plan


__all__ = ["Plan", "Tx", "N_TX", "compile_input_plan", "compile_output_plan",
           "channel_timeouts", "check_profile", "In"]
