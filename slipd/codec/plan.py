"""Compile (DBC, profile) into the array plan the codec kernels execute.

cantools parses the DBC once; the plan keeps, per signal, where its bits are (start bit,
length, byte order), how to read them (signedness, IEEE float) and how to scale them
(DBC scale/offset, then the profile's unit factor to SI). Everything that can be wrong with
the combination is found here, at load time, with the file and the name in the message.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from pathlib import Path

import cantools
import numpy as np

from slipd.channels import N_IN, In, Out
from slipd.codec import kernels as K
from slipd.errors import CodecError
from slipd.profile import E2E_SCHEMES, MessageMap, Profile

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

    @property
    def n_messages(self) -> int:
        return len(self.message_names)

    def frame_id(self, name: str) -> int:
        return int(self.plan_i[self.message_rows[name], K.M_FRAME_ID])

    def dlc(self, name: str) -> int:
        return int(self.plan_i[self.message_rows[name], K.M_DLC])

    def is_extended(self, name: str) -> bool:
        return bool(self.plan_i[self.message_rows[name], K.M_EXTENDED])


def load_dbc(path: Path):
    """Load a DBC with cantools; production DBCs (opendbc) need ``strict=False``."""
    try:
        return cantools.database.load_file(str(path), strict=False)
    except Exception as exc:  # cantools raises several parser error types
        raise CodecError(f"{path}: cannot parse DBC: {exc}") from exc


def _signal_row(signal, where: str) -> tuple[list[int], list[float]]:
    if signal.length > 64:
        raise CodecError(f"{where}: signal {signal.name} is {signal.length} bits; at most 64")
    if signal.is_float and signal.length not in (32, 64):
        raise CodecError(f"{where}: float signal {signal.name} must be 32 or 64 bits")
    start, length = signal.start, signal.length
    if signal.byte_order == "little_endian":
        shift, big = start, 0
        if start + length > 64:
            raise CodecError(f"{where}: signal {signal.name} extends past byte 8")
    else:
        msb = (start // 8) * 8 + (7 - start % 8)
        shift, big = 64 - msb - length, 1
        if shift < 0:
            raise CodecError(f"{where}: signal {signal.name} extends past byte 8")
    row_i = [0] * K.I_COLS
    row_i[K.S_SHIFT] = shift
    row_i[K.S_LENGTH] = length
    row_i[K.S_BIG_ENDIAN] = big
    row_i[K.S_SIGNED] = int(bool(signal.is_signed))
    row_i[K.S_FLOAT] = int(bool(signal.is_float))
    row_i[K.S_SLOT] = -1
    row_i[K.S_CRC_BYTE] = start // 8
    row_f = [0.0] * K.F_COLS
    row_f[K.F_SCALE] = float(signal.scale)
    row_f[K.F_OFFSET] = float(signal.offset)
    minimum = signal.minimum if signal.minimum is not None else 0.0
    maximum = signal.maximum if signal.maximum is not None else 0.0
    row_f[K.F_MIN] = float(minimum)
    row_f[K.F_MAX] = float(maximum)
    row_f[K.F_FACTOR] = 1.0
    return row_i, row_f


def _build(dbc_path: Path, specs: list[tuple[str, MessageMap | None, dict]]) -> Plan:
    """specs: (message name, its MessageMap or None for outputs, {signal: (slot, factor,
    min, max, check_range, accumulate)})."""
    db = load_dbc(dbc_path)
    msg_rows_i: list[list[int]] = []
    sig_rows_i: list[list[int]] = []
    sig_rows_f: list[list[float]] = []
    names: list[str] = []
    timeouts: list[float] = []
    n_msg = len(specs)
    for name, mmap, signals in specs:
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
        if message.length > 8:
            raise CodecError(f"{where} is {message.length} bytes; the codec handles up to 8")
        by_name = {s.name: s for s in message.signals}
        row = [0] * K.I_COLS
        row[K.M_FRAME_ID] = message.frame_id
        row[K.M_DLC] = message.length
        row[K.M_EXTENDED] = int(message.is_extended_frame)
        row[K.M_SIG_FIRST] = n_msg + len(sig_rows_i)
        row[K.M_CRC_ROW] = -1
        row[K.M_COUNTER_ROW] = -1
        row[K.M_MAX_DELTA] = mmap.max_counter_delta if mmap else 1
        e2e = mmap.e2e if mmap else "slipd_crc8"
        crc_signal = mmap.crc_signal if mmap else f"{name}_CRC"
        counter_signal = mmap.counter_signal if mmap else f"{name}_Counter"
        row[K.M_E2E] = E2E_SCHEMES[e2e]
        if mmap and mmap.data_ids:
            row[K.M_DATA_IDS:K.M_DATA_IDS + 16] = list(mmap.data_ids)
        for sig_name in signals:
            if sig_name not in by_name:
                raise CodecError(
                    f"{where} has no signal {sig_name!r}; it has {sorted(by_name)}"
                )
        role_rows = {}
        for role, sig_name in (("crc", crc_signal), ("counter", counter_signal)):
            if e2e == "none" or (role == "counter" and e2e == "toyota_checksum"):
                continue
            if sig_name not in by_name:
                raise CodecError(f"{where}: {role} signal {sig_name!r} not in the DBC")
            sig = by_name[sig_name]
            if role == "crc" and (sig.length != 8 or sig.start % 8 != (7 if
                                  sig.byte_order == "big_endian" else 0)):
                raise CodecError(f"{where}: CRC signal {sig_name} must be one whole byte")
            role_rows[role] = sig_name
        first = len(sig_rows_i)
        ordered = list(signals) + [s for s in role_rows.values() if s not in signals]
        for sig_name in ordered:
            row_i, row_f = _signal_row(by_name[sig_name], where)
            if sig_name in signals:
                slot, factor, minimum, maximum, check, accumulate = signals[sig_name]
                row_i[K.S_SLOT] = int(slot)
                row_i[K.S_ACCUMULATE] = int(accumulate)
                row_i[K.S_CHECK_RANGE] = int(check)
                row_f[K.F_FACTOR] = factor
                if minimum is not None:
                    row_f[K.F_MIN] = minimum
                if maximum is not None:
                    row_f[K.F_MAX] = maximum
            index = n_msg + len(sig_rows_i)
            for role, role_name in role_rows.items():
                if role_name == sig_name:
                    row[K.M_CRC_ROW if role == "crc" else K.M_COUNTER_ROW] = index
            sig_rows_i.append(row_i)
            sig_rows_f.append(row_f)
        row[K.M_SIG_COUNT] = len(sig_rows_i) - first
        msg_rows_i.append(row)
        names.append(name)
        timeouts.append(mmap.timeout if mmap else 1.0)
    plan_i = np.array(msg_rows_i + sig_rows_i, dtype=np.int64).reshape(-1, K.I_COLS)
    plan_f = np.zeros((len(plan_i), K.F_COLS), dtype=np.float64)
    if sig_rows_f:
        plan_f[n_msg:] = np.array(sig_rows_f, dtype=np.float64)
    standard = np.full(2048, -1, dtype=np.int64)
    extended: list[tuple[int, int]] = []
    for index, row in enumerate(msg_rows_i):
        if row[K.M_EXTENDED]:
            extended.append((row[K.M_FRAME_ID], index))
        else:
            if standard[row[K.M_FRAME_ID]] >= 0:
                raise CodecError(f"{dbc_path}: frame ID {row[K.M_FRAME_ID]:#x} mapped twice")
            standard[row[K.M_FRAME_ID]] = index
    extended.sort()
    lookup = np.concatenate(
        [standard, np.array([e[0] for e in extended] + [e[1] for e in extended], dtype=np.int64)]
    )
    return Plan(plan_i, plan_f, lookup, tuple(names), {n: i for i, n in enumerate(names)},
                np.array(timeouts, dtype=np.float64), dbc_path)


def compile_input_plan(profile: Profile) -> Plan:
    """The decode plan of a profile's input messages (slots are ``In`` channels)."""
    specs = []
    for name, mmap in profile.messages.items():
        signals: dict[str, tuple] = {}
        for channel in mmap.channels:
            cmap = profile.channels[channel]
            for position, smap in enumerate(cmap.signals):
                if smap.name in signals:
                    raise CodecError(
                        f"{profile.path}: signal {name}.{smap.name} feeds two channels"
                    )
                signals[smap.name] = (int(channel), smap.factor, smap.minimum, smap.maximum,
                                      smap.check_range, position > 0)
        specs.append((name, mmap, signals))
    return _build(profile.dbc_path, specs)


def compile_output_plan(dbc_path: Path = SLIPD_DBC) -> Plan:
    """The encode plan of slipd's output frames (slots are ``Tx`` values)."""
    db = load_dbc(dbc_path)
    specs = []
    for name in OUTPUT_MESSAGES:
        message = db.get_message_by_name(name)
        signals = {}
        for signal in message.signals:
            if signal.name in OUTPUT_SIGNALS:
                slot, factor = OUTPUT_SIGNALS[signal.name]
                signals[signal.name] = (int(slot), factor, None, None, True, False)
        specs.append((name, None, signals))
    return _build(dbc_path, specs)


def channel_timeouts(profile: Profile) -> np.ndarray:
    """float64 [N_IN]: each channel's timeout (unmapped channels: never valid)."""
    timeouts = np.full(N_IN, -1.0, dtype=np.float64)
    for channel, cmap in profile.channels.items():
        timeouts[channel] = cmap.timeout
    return timeouts


__all__ = ["Plan", "Tx", "N_TX", "compile_input_plan", "compile_output_plan",
           "channel_timeouts", "In"]
