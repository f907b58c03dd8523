"""Recorded signals (data-logger CSV, MATLAB .mat) -> a candump log through the codec.

Every frame is encoded by the same codec as the simulator and the daemon (counters, CRCs, the
DBC's quantisation and range), so an imported data set replays and evaluates like a bus log.

Rules (nothing is made up):

* A message is written at the rows where all of its channels have a finite value; a message
  whose channels are not all in the data is left out and the report says which channels would
  bring it in. ``constants`` (user-declared fixed values, e.g. az = 9.81 m/s^2 on a logger
  without a vertical accelerometer) and ``--derive wheel-speeds`` fill channels only when the
  user asks, and the sidecar ``LOG.meta.json`` records it. The candump file itself carries
  frames only: a comment line breaks canplayer and python-can's LogReader.
* Values outside a signal's DBC range are clamped by the encoder; they are counted per channel
  and reported, never silently changed.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slipd.channels import In
from slipd.errors import ConfigError, DependencyError, LogFormatError
from slipd.profile import UNITS, Profile

TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
TIME_COLUMNS = ("t", "time", "timestamp", "Time", "TIME", "Timestamp")


@dataclass(frozen=True)
class ColumnMap:
    """``column=channel[:unit]``; a leading '-' on the channel flips the sign."""

    column: str
    channel: In
    unit: str
    sign: float

    @property
    def factor(self) -> float:
        return UNITS[self.unit] * self.sign

    def spec(self) -> str:
        sign = "-" if self.sign < 0 else ""
        unit = f":{self.unit}" if self.unit else ""
        return f"{self.column}={sign}{self.channel.name.lower()}{unit}"


def parse_map(entries: list[str]) -> list[ColumnMap]:
    """Parse ``--map`` entries (each may hold several comma-separated items)."""
    maps: list[ColumnMap] = []
    for entry in entries:
        for item in filter(None, (part.strip() for part in entry.split(","))):
            column, sep, target = item.rpartition("=")
            if not sep or not column or not target:
                raise ConfigError(f"--map {item!r}: expected COLUMN=CHANNEL[:UNIT], e.g. "
                                  "yaw_rate_dps=yaw_rate:deg/s")
            channel_name, _, unit = target.partition(":")
            sign = 1.0
            if channel_name.startswith("-"):
                sign, channel_name = -1.0, channel_name[1:]
            channel = channel_of(channel_name, f"--map {item!r}")
            if unit not in UNITS:
                raise ConfigError(f"--map {item!r}: unknown unit {unit!r}; expected one of "
                                  f"{sorted(u for u in UNITS if u)}")
            maps.append(ColumnMap(column, channel, unit, sign))
    seen: dict[In, str] = {}
    for m in maps:
        if m.channel in seen:
            raise ConfigError(f"--map: channel {m.channel.name.lower()} is mapped twice "
                              f"({seen[m.channel]!r} and {m.column!r})")
        seen[m.channel] = m.column
    return maps


def channel_of(name: str, where: str) -> In:
    try:
        return In[name.upper()]
    except KeyError:
        raise ConfigError(f"{where}: unknown channel {name!r}; expected one of "
                          f"{[c.name.lower() for c in In]}") from None


def parse_constants(entries: list[str]) -> dict[In, float]:
    """``--constant channel=value[:unit]`` -> SI values."""
    constants: dict[In, float] = {}
    for entry in entries:
        for item in filter(None, (part.strip() for part in entry.split(","))):
            name, sep, rest = item.partition("=")
            value_text, _, unit = rest.partition(":")
            channel = channel_of(name, f"--constant {item!r}")
            try:
                value = float(value_text)
            except ValueError:
                raise ConfigError(f"--constant {item!r}: expected CHANNEL=NUMBER[:UNIT]") from None
            if not sep or not math.isfinite(value) or unit not in UNITS:
                raise ConfigError(f"--constant {item!r}: expected CHANNEL=NUMBER[:UNIT] with a "
                                  f"finite number and a unit of {sorted(u for u in UNITS if u)}")
            constants[channel] = value * UNITS[unit]
    return constants


#: Truth columns ``slipd import --truth`` accepts (the simulator's truth CSV names, SI).
TRUTH_CHANNELS = {"beta": "rad", "vx": "m/s", "vy": "m/s", "speed": "m/s",
                  "yaw_rate": "rad/s", "roll": "rad", "pitch": "rad", "ax": "m/s^2",
                  "ay": "m/s^2", "mu": "", "steer": "rad"}


@dataclass(frozen=True)
class TruthMap:
    """``--truth name=column[:unit]``: a reference-sensor column as a truth column."""

    name: str
    column: str
    unit: str
    sign: float

    def spec(self) -> str:
        sign = "-" if self.sign < 0 else ""
        return f"{self.name}={sign}{self.column}" + (f":{self.unit}" if self.unit else "")


def parse_truth(entries: list[str]) -> list[TruthMap]:
    """Parse ``--truth`` entries: ``beta=beta_rad,vx=vx_mps,...``; beta and vx are required
    (eval scores beta and needs the speed to select the ticks)."""
    maps: list[TruthMap] = []
    for entry in entries:
        for item in filter(None, (part.strip() for part in entry.split(","))):
            name, sep, target = item.partition("=")
            column, _, unit = target.partition(":")
            sign = 1.0
            if column.startswith("-"):
                sign, column = -1.0, column[1:]
            if not sep or not column or name not in TRUTH_CHANNELS:
                raise ConfigError(f"--truth {item!r}: expected NAME=COLUMN[:UNIT] with NAME one "
                                  f"of {sorted(TRUTH_CHANNELS)}")
            if unit not in UNITS:
                raise ConfigError(f"--truth {item!r}: unknown unit {unit!r}; expected one of "
                                  f"{sorted(u for u in UNITS if u)}")
            maps.append(TruthMap(name, column, unit, sign))
    names = [m.name for m in maps]
    if maps and not {"beta", "vx"} <= set(names):
        raise ConfigError(f"--truth {','.join(entries)}: needs at least beta and vx (eval scores "
                          "beta where the speed is above its threshold)")
    if len(set(names)) != len(names):
        raise ConfigError(f"--truth: a truth column is given twice: {names}")
    return maps


# ---- reading tables


def read_table(path: Path, columns: set[str] | None = None,
               raster: float | None = None) -> dict[str, np.ndarray]:
    """Columns of a CSV (header row; ',', ';' or tab), a .mat file or a signal-level .mf4 as
    float64 arrays (an MF4: only ``columns``, on their time stamps' union or on ``raster``;
    slipd.replay.mf4.read_mf4_signals)."""
    if not path.exists():
        raise LogFormatError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".mf4":
        from slipd.replay.mf4 import read_mf4_signals

        return read_mf4_signals(path, columns, raster)
    if raster is not None:
        raise ConfigError(f"--raster: {path} is a table already; it resamples MF4 channels")
    if suffix == ".mat":
        return _read_mat(path)
    if suffix in (".csv", ".txt", ".tsv"):
        return _read_csv(path)
    raise LogFormatError(f"{path}: unknown table format {suffix!r}; expected .csv, .mat or "
                         ".mf4")


def _read_csv(path: Path) -> dict[str, np.ndarray]:
    try:
        return _parse_csv(path)
    except UnicodeDecodeError as exc:
        raise LogFormatError(f"{path}: not UTF-8 text (byte {exc.object[exc.start]:#04x} at "
                             f"offset {exc.start} of a read block); export the CSV as UTF-8"
                             ) from None


def _parse_csv(path: Path) -> dict[str, np.ndarray]:
    with open(path, newline="", encoding="utf-8-sig") as handle:
        sample = handle.read(65536)
        handle.seek(0)
        try:
            dialect = csv.Sniffer().sniff(sample, delimiters=",;\t")
        except csv.Error:
            dialect = csv.excel
        reader = csv.reader(handle, dialect)
        header = next(reader, None)
        if not header:
            raise LogFormatError(f"{path}: empty file (expected a header row of column names)")
        header = [name.strip() for name in header]
        duplicates = sorted({n for n in header if header.count(n) > 1})
        if duplicates:
            raise LogFormatError(f"{path}:1: duplicate column name(s) {duplicates}")
        rows: list[list[float]] = []
        for line_no, row in enumerate(reader, start=2):
            if not row or all(not cell.strip() for cell in row):
                continue
            if len(row) != len(header):
                raise LogFormatError(f"{path}:{line_no}: {len(row)} values, the header has "
                                     f"{len(header)} columns")
            values = []
            for column, cell in zip(header, row, strict=True):
                cell = cell.strip()
                if not cell or cell.lower() in ("nan", "na", "null"):
                    values.append(math.nan)
                    continue
                try:
                    value = float(cell)
                except ValueError:
                    raise LogFormatError(f"{path}:{line_no}: column {column!r}: {cell!r} is not "
                                         "a number (empty or NaN marks a missing value)") from None
                if math.isinf(value):  # was dropped later with its row, unreported
                    raise LogFormatError(f"{path}:{line_no}: column {column!r}: {cell!r} is "
                                         "not a measurement (empty or NaN marks a missing "
                                         "value)")
                values.append(value)
            rows.append(values)
    data = np.array(rows, dtype=np.float64).reshape(len(rows), len(header))
    return {name: data[:, i] for i, name in enumerate(header)}


def _read_mat(path: Path) -> dict[str, np.ndarray]:
    try:
        from scipy.io import loadmat
    except ImportError as exc:
        raise DependencyError("reading .mat files needs scipy: pip install 'slipd[sim]'") from exc
    try:
        contents = loadmat(str(path), squeeze_me=True, struct_as_record=False)
    except NotImplementedError as exc:  # MATLAB v7.3 files are HDF5
        raise LogFormatError(f"{path}: MATLAB v7.3 (HDF5) files are not supported; save with "
                             "save(..., '-v7') or export a CSV") from exc
    except (ValueError, TypeError, OSError) as exc:
        raise LogFormatError(f"{path}: not a readable MATLAB file: {exc}") from exc
    columns: dict[str, np.ndarray] = {}

    def collect(prefix: str, value) -> None:
        if hasattr(value, "_fieldnames"):  # a struct: its fields as prefix.field
            for name in value._fieldnames:
                collect(f"{prefix}.{name}", getattr(value, name))
            return
        array = np.asarray(value)
        if array.dtype.kind in "fiub" and array.ndim <= 2 and 1 in (array.ndim, min(array.shape)):
            columns[prefix] = array.astype(np.float64).ravel()
        elif array.dtype.kind in "fiub" and array.ndim == 2:
            for i in range(array.shape[1]):  # a matrix: one column per channel
                columns[f"{prefix}[{i}]"] = array[:, i].astype(np.float64)

    for name, value in contents.items():
        if not name.startswith("__"):
            collect(name, value)
    return columns


# ---- import


@dataclass
class ImportReport:
    frames: int = 0
    rows: int = 0
    messages: dict[str, int] = field(default_factory=dict)
    left_out: dict[str, list[str]] = field(default_factory=dict)
    clamped: dict[str, int] = field(default_factory=dict)
    derived: dict[str, str] = field(default_factory=dict)
    rate_notes: list[str] = field(default_factory=list)
    truth_rows: int = 0
    truth_path: str = ""

    def summary(self) -> str:
        lines = [f"{self.rows} rows -> {self.frames} frames"]
        for name, count in self.messages.items():
            lines.append(f"  {name:<22} {count:>9} frames")
        for name, missing in self.left_out.items():
            lines.append(f"  {name:<22} left out: no data for {', '.join(missing)}")
        for note in self.rate_notes:
            lines.append(f"  note: {note}")
        for channel, count in self.clamped.items():
            lines.append(f"  warning: {count} value(s) of {channel} outside the DBC range were "
                         "clamped")
        for channel, how in self.derived.items():
            lines.append(f"  derived on request: {channel} = {how}")
        if self.truth_path:
            lines.append(f"  truth: {self.truth_rows} rows -> {self.truth_path}")
        return "\n".join(lines)


def _time_column(table: dict[str, np.ndarray], spec: str | None, path: Path) -> np.ndarray:
    if spec:
        name, _, unit = spec.partition(":")
        unit = unit or "s"
    else:
        name = next((c for c in TIME_COLUMNS if c in table), "")
        unit = "s"
        if not name:
            raise ConfigError(f"{path}: no time column among {list(TIME_COLUMNS)}; name it with "
                              "--time COLUMN[:s|ms|us|ns]")
    if unit not in TIME_UNITS:
        raise ConfigError(f"--time {spec!r}: unit {unit!r}; expected one of {list(TIME_UNITS)}")
    if name not in table:
        raise ConfigError(f"--time: {path} has no column {name!r}; columns: {sorted(table)}")
    t = table[name] * TIME_UNITS[unit]
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise LogFormatError(f"{path}: time column {name!r} has no value at data row "
                             f"{int(bad[0]) + 1}")
    back = np.flatnonzero(np.diff(t) < 0)
    if back.size:
        raise LogFormatError(f"{path}: time column {name!r} goes backwards at data row "
                             f"{int(back[0]) + 2} ({t[back[0]]} -> {t[back[0] + 1]})")
    return t


def derive_wheel_speeds(speed: np.ndarray, values: dict[In, np.ndarray], vehicle: np.ndarray
                        ) -> tuple[dict[In, np.ndarray], str]:
    """Wheel-centre speeds from the vehicle speed, for logs without wheel-speed sensors.

    Rigid-body kinematics with zero sideslip (the one assumption, stated in the sidecar): the
    wheel at (x_i, y_i) moves at vx - r y_i along the body x axis and r x_i across it; the
    front wheels are turned by the steer angle delta: v_i = (vx - r y_i) cos(delta) + r x_i
    sin(delta). Without yaw rate (or steer) in the data those terms are zero.
    """
    from slipd.channels import Veh

    yaw_rate = values.get(In.YAW_RATE)
    steer = values.get(In.STEER)
    # yaw rate and steer sampled on other rows are held from their newest earlier row (what
    # the latch does on the bus); before their first sample the wheel speeds stay NaN
    r = _hold(yaw_rate) if yaw_rate is not None else np.zeros_like(speed)
    delta = _hold(steer) if steer is not None else np.zeros_like(speed)
    lf = vehicle[Veh.LF]
    half_f, half_r = vehicle[Veh.TRACK_F] / 2, vehicle[Veh.TRACK_R] / 2
    out = {
        In.WHEEL_SPEED_FL: (speed - r * half_f) * np.cos(delta) + r * lf * np.sin(delta),
        In.WHEEL_SPEED_FR: (speed + r * half_f) * np.cos(delta) + r * lf * np.sin(delta),
        In.WHEEL_SPEED_RL: speed - r * half_r,
        In.WHEEL_SPEED_RR: speed + r * half_r,
    }
    used = [name for name, v in (("yaw_rate", yaw_rate), ("steer", steer)) if v is not None]
    how = ("rigid-body kinematics from the vehicle speed with zero sideslip"
           + (f", using {' and '.join(used)}" if used else ", no yaw rate or steer in the data:"
              " all four equal the vehicle speed"))
    return out, how


def _hold(values: np.ndarray) -> np.ndarray:
    """Forward-fill NaN gaps with the newest earlier finite value."""
    index = np.where(np.isfinite(values), np.arange(len(values)), -1)
    np.maximum.accumulate(index, out=index)
    held = values[np.maximum(index, 0)]
    held[index < 0] = np.nan
    return held


def import_table(source: Path, profile: Profile, maps: list[ColumnMap], out: Path,
                 time_spec: str | None = None, epoch: float = 0.0,
                 constants: dict[In, float] | None = None, derive: list[str] | None = None,
                 speed_spec: str | None = None, interface: str = "can0",
                 truth: list[TruthMap] | None = None, raster: float | None = None
                 ) -> ImportReport:
    """Encode the mapped columns of ``source`` into the candump log ``out`` (+ sidecar), and
    the ``truth`` columns into the truth CSV beside it (:func:`truth_path`)."""
    from slipd.codec import Codec
    from slipd.replay.candump import write_candump

    wanted = {m.column for m in maps} | {m.column for m in truth or []}
    wanted |= {spec.partition(":")[0] for spec in (time_spec, speed_spec) if spec}
    table = read_table(source, wanted, raster)
    t = _time_column(table, time_spec, source) + epoch
    n = len(t)
    constants = dict(constants or {})
    derive = list(derive or [])
    report = ImportReport(rows=n)

    values: dict[In, np.ndarray] = {}
    for m in maps:
        if m.column not in table:
            raise ConfigError(f"--map {m.spec()}: {source} has no column {m.column!r}; "
                              f"columns: {sorted(table)}")
        if m.channel not in profile.channels:
            raise ConfigError(f"--map {m.spec()}: profile {profile.name} carries no "
                              f"{m.channel.name.lower()} on its bus; it maps "
                              f"{sorted(c.name.lower() for c in profile.channels)}")
        values[m.channel] = table[m.column] * m.factor
    for channel, value in constants.items():
        if channel in values:
            raise ConfigError(f"--constant {channel.name.lower()}: the channel is also mapped "
                              "from a column")
        values[channel] = np.full(n, value)
        report.derived[channel.name.lower()] = f"constant {value} (SI), --constant"

    for what in derive:
        if what != "wheel-speeds":
            raise ConfigError(f"--derive {what!r}: expected wheel-speeds")
        speed = _speed_column(table, speed_spec, maps, source)
        wheel, how = derive_wheel_speeds(speed, values, profile.vehicle)
        for channel, array in wheel.items():
            if channel in values:
                raise ConfigError(f"--derive wheel-speeds: {channel.name.lower()} is already "
                                  "mapped from the data")
            values[channel] = array
            report.derived[channel.name.lower()] = how

    from slipd.codec.plan import load_dbc

    codec = Codec.from_profile(profile)
    db = load_dbc(profile.dbc_path)  # production DBCs load non-strictly, as the codec's
    stamps, ids, payloads, dlcs, rank = [], [], [], [], []
    for order, (name, mmap) in enumerate(profile.messages.items()):
        channels = mmap.channels
        missing = [c.name.lower() for c in channels if c not in values]
        if missing:
            if len(missing) < len(channels):  # partly in the data: say what would complete it
                report.left_out[name] = missing
            continue
        rows = np.ones(n, dtype=bool)
        for c in channels:
            rows &= np.isfinite(values[c])
        if not rows.any():
            report.left_out[name] = ["(no row has all of its channels)"]
            continue
        selected = {c: values[c][rows] for c in channels}
        _count_clamped(db, profile, name, selected, report)
        frame_id, data = codec.encode_channels(name, selected, first_counter=0)
        count = int(rows.sum())
        padded = np.zeros((count, max(8, data.shape[1])), dtype=np.uint8)
        padded[:, : data.shape[1]] = data
        stamps.append(t[rows])
        ids.append(np.full(count, frame_id, dtype=np.int64))
        payloads.append(padded)
        dlcs.append(np.full(count, data.shape[1], dtype=np.uint8))
        rank.append(np.full(count, order))
        report.messages[name] = count
        if count > 1:
            rate = (count - 1) / (t[rows][-1] - t[rows][0]) if t[rows][-1] > t[rows][0] else 0.0
            if rate and not 0.5 * mmap.rate_hz <= rate <= 2.0 * mmap.rate_hz:
                report.rate_notes.append(f"{name} is at {rate:.1f} Hz in the data; the "
                                         f"profile's bus carries it at {mmap.rate_hz:g} Hz")
    if not stamps:
        raise ConfigError(f"{source}: no message of profile {profile.name} has all its channels "
                          f"in the data; incomplete: {report.left_out}")
    width = max(p.shape[1] for p in payloads)
    payloads = [np.pad(p, ((0, 0), (0, width - p.shape[1]))) for p in payloads]
    all_t = np.round(np.concatenate(stamps) * 1e6) / 1e6
    order = np.lexsort((np.concatenate(rank), all_t))
    report.frames = write_candump(out, all_t[order], np.concatenate(ids)[order],
                                  np.concatenate(payloads)[order], np.concatenate(dlcs)[order],
                                  interface=interface)
    if truth:
        _write_truth(out, source, table, t - epoch, epoch, truth, report)
    _write_sidecar(out, source, profile, maps, time_spec, epoch, report, truth or [], raster)
    return report


def _write_truth(out: Path, source: Path, table: dict[str, np.ndarray], t: np.ndarray,
                 epoch: float, truth: list[TruthMap], report: ImportReport) -> None:
    from slipd.sim.writer import truth_path_of, write_truth_columns

    columns = {"t": t}
    for m in truth:
        if m.column not in table:
            raise ConfigError(f"--truth {m.spec()}: {source} has no column {m.column!r}; "
                              f"columns: {sorted(table)}")
        columns[m.name] = table[m.column] * UNITS[m.unit] * m.sign
    rows = np.ones(len(t), dtype=bool)
    for values in columns.values():
        rows &= np.isfinite(values)
    if not rows.any():
        raise ConfigError(f"--truth: no row of {source} has every truth column")
    path = truth_path_of(out)
    write_truth_columns(path, {k: v[rows] for k, v in columns.items()}, epoch, [
        f"slipd import truth: source={source.name}",
        "reference sensor columns, SI units, ISO 8855 axes: " + ", ".join(m.spec() for m in truth),
    ])
    report.truth_rows = int(rows.sum())
    report.truth_path = str(path)


def _speed_column(table, speed_spec: str | None, maps: list[ColumnMap], source: Path
                  ) -> np.ndarray:
    if speed_spec:
        column, _, unit = speed_spec.partition(":")
        if column not in table:
            raise ConfigError(f"--speed {speed_spec!r}: {source} has no column {column!r}")
        if unit not in UNITS:
            raise ConfigError(f"--speed {speed_spec!r}: unknown unit {unit!r}")
        return table[column] * UNITS[unit]
    ref = next((m for m in maps if m.channel == In.SPEED_REF), None)
    if ref is None:
        raise ConfigError("--derive wheel-speeds needs the vehicle speed: --speed COLUMN[:UNIT] "
                          "(e.g. --speed v_kmh:km/h)")
    return table[ref.column] * ref.factor


def _count_clamped(db, profile: Profile, message: str, values: dict[In, np.ndarray],
                   report: ImportReport) -> None:
    """Count values the encoder will clamp: outside the DBC range of their signal."""
    dbc_message = db.get_message_by_name(message)
    for channel, array in values.items():
        cmap = profile.channels[channel]
        if len(cmap.signals) != 1:
            continue  # summed signals: the range is the sum's; the codec fills in order
        smap = cmap.signals[0]
        signal = dbc_message.get_signal_by_name(smap.name)
        physical = array / smap.factor
        low, high = signal.minimum, signal.maximum
        outside = 0
        if low is not None:
            outside += int(np.count_nonzero(physical < low - abs(signal.scale) / 2))
        if high is not None:
            outside += int(np.count_nonzero(physical > high + abs(signal.scale) / 2))
        if outside:
            report.clamped[channel.name.lower()] = outside


def _write_sidecar(out: Path, source: Path, profile: Profile, maps: list[ColumnMap],
                   time_spec: str | None, epoch: float, report: ImportReport,
                   truth: list[TruthMap], raster: float | None = None) -> None:
    from slipd.cli import _version

    digest = hashlib.sha256(source.read_bytes()).hexdigest()
    meta = {
        "created_by": _version(),
        "source": str(source),
        "source_sha256": digest,
        "profile": profile.name,
        "time": time_spec or "auto",
        "epoch": epoch,
        "map": [m.spec() for m in maps],
        "truth": [m.spec() for m in truth],
        "truth_file": report.truth_path or None,
        "raster": (f"{raster} s: each MF4 channel's newest sample at or before each instant"
                   if raster else None),
        "derived_on_request": report.derived,
        "messages": report.messages,
        "left_out": report.left_out,
        "clamped": report.clamped,
        "rate_notes": report.rate_notes,
        "frames": report.frames,
    }
    sidecar_path(out).write_text(json.dumps(meta, indent=2) + "\n")


def sidecar_path(log: Path) -> Path:
    return log.with_name(log.name + ".meta.json")
