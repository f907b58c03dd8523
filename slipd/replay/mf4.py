"""ASAM MDF 4 (``.mf4``) in: CAN bus logging as frames, and signal-level channels as a table.

Bus logging (CSS CANedge, Vector, python-can's MF4Writer, asammdf) stores frames in channel
groups flagged as bus events from a CAN source, with the ASAM structure ``CAN_DataFrame``
(``.BusChannel``, ``.ID``, ``.IDE``, ``.DLC``, ``.DataLength``, ``.DataBytes``, ``.Dir``,
``.EDL``, ``.BRS``, ``.ESI``), ``CAN_ErrorFrame`` and ``CAN_RemoteFrame``; times are relative
to the header's start time. :func:`read_mf4` reads each group as whole arrays through asammdf
and gives exactly the frames python-can's ``MF4Reader`` yields (tested against it; the same
groups, fields and time order), CAN FD payloads up to 64 bytes included. It exists because
python-can builds one Message per frame: measured in ``benchmarks/formats.py``.

Signal-level MF4 (a logger's decoded channels) is a table for ``slipd import``:
:func:`read_mf4_signals` returns the requested channels on the union of their time stamps,
each NaN where it has no sample (nothing is interpolated), or resampled by sample-and-hold
onto a fixed raster when asked.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slipd.errors import DependencyError, LogFormatError
from slipd.replay.candump import (
    FLAG_BRS,
    FLAG_DIRECTION,
    FLAG_ERROR,
    FLAG_ESI,
    FLAG_EXTENDED,
    FLAG_FD,
    FLAG_REMOTE,
    FLAG_TX,
    Frames,
)

#: ASAM bus-logging structures and the Frames flags each implies.
STRUCTURES = {"CAN_DataFrame": 0, "CAN_ErrorFrame": FLAG_ERROR, "CAN_RemoteFrame": FLAG_REMOTE}
#: CAN FD DLC code -> data length in bytes.
DLC_LENGTHS = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64], dtype=np.int64)


def _asammdf():
    try:
        import asammdf
    except ImportError as exc:
        raise DependencyError("reading .mf4 needs asammdf: pip install 'slipd[mf4]'") from exc
    return asammdf


def _open(path: Path, **options):
    """asammdf's MDF of ``path`` (``options``: its keyword arguments)."""
    asammdf = _asammdf()
    if not path.exists():
        raise LogFormatError(f"{path}: no such file")
    try:
        return asammdf.MDF(str(path), **options)
    except Exception as exc:  # asammdf raises MdfException, ValueError, struct.error, ...
        raise LogFormatError(f"{path}: not a readable MDF file: {type(exc).__name__}: {exc}"
                             ) from exc


def _bus_groups(mdf) -> list[tuple[int, str]]:
    """(group index, structure name) of every CAN bus-logging group (python-can's rules)."""
    from asammdf.blocks.v4_constants import BUS_TYPE_CAN, FLAG_CG_BUS_EVENT, SOURCE_BUS

    found = []
    for index, group in enumerate(mdf.groups):
        cg = group.channel_group
        if not cg.flags & FLAG_CG_BUS_EVENT or cg.cycles_nr == 0:
            continue
        source = cg.acq_source
        if source is None or not source.source_type & SOURCE_BUS or source.bus_type != BUS_TYPE_CAN:
            continue
        names = [channel.name for channel in group.channels]
        structure = next((s for s in STRUCTURES if s in names), None)
        if structure is not None:
            found.append((index, structure))
    return found


def _field(samples, name: str, default=None):
    names = samples.dtype.names or ()
    if name in names:
        return samples[name]
    return default


def _group_frames(mdf, index: int, structure: str, start: float, path: Path) -> tuple:
    """Arrays (t, id, flags, dlc, data, bus channel) of one bus-logging group."""
    signal = mdf.get(structure, index, raw=False)
    samples = signal.samples
    n = len(samples)
    t = np.asarray(signal.timestamps, dtype=np.float64) + start
    frame_id = _field(samples, f"{structure}.ID")
    if frame_id is None:
        raise LogFormatError(f"{path}: group {index} {structure} has no {structure}.ID")
    frame_id = np.asarray(frame_id, dtype=np.int64) & 0x1FFFFFFF
    flags = np.full(n, STRUCTURES[structure], dtype=np.uint8)
    for suffix, bit in (("IDE", FLAG_EXTENDED), ("EDL", FLAG_FD), ("BRS", FLAG_BRS),
                        ("ESI", FLAG_ESI)):
        values = _field(samples, f"{structure}.{suffix}")
        if values is not None and not (structure == "CAN_RemoteFrame" and suffix != "IDE"):
            flags |= np.where(np.asarray(values).astype(bool), bit, 0).astype(np.uint8)
    direction = _field(samples, f"{structure}.Dir")
    if direction is not None:
        if np.asarray(direction).dtype.kind == "S":
            tx = np.asarray(direction) != b"Rx"
        else:
            tx = np.asarray(direction).astype(np.int64) != 0
        flags |= np.where(tx, FLAG_TX | FLAG_DIRECTION, 0).astype(np.uint8)
    bus = _field(samples, f"{structure}.BusChannel")
    bus = np.zeros(n, np.int64) if bus is None else np.asarray(bus, dtype=np.int64)
    data = np.zeros((n, 8), dtype=np.uint8)
    if structure == "CAN_RemoteFrame":
        length = np.asarray(_field(samples, f"{structure}.DLC", np.zeros(n)), dtype=np.int64)
    else:
        length = _field(samples, f"{structure}.DataLength")
        raw = _field(samples, f"{structure}.DataBytes")
        if length is None and raw is not None:
            dlc = np.asarray(_field(samples, f"{structure}.DLC", np.zeros(n)), dtype=np.int64)
            length = DLC_LENGTHS[np.clip(dlc, 0, 15)]
        length = np.zeros(n, np.int64) if length is None else np.asarray(length, np.int64)
        if raw is not None:
            data = _payloads(raw, length, path, index)
    return t, frame_id, flags, length, data, bus


def _payloads(raw, length: np.ndarray, path: Path, index: int) -> np.ndarray:
    """uint8 [n, width] payloads from fixed-size byte arrays or variable-length records."""
    raw = np.asarray(raw)
    if raw.dtype == np.uint8 and raw.ndim == 2:
        width = max(8, int(length.max()) if length.size else 8)
        if raw.shape[1] < width:
            raise LogFormatError(f"{path}: group {index}: DataLength up to {width} bytes but "
                                 f"DataBytes holds {raw.shape[1]}")
        data = np.array(raw[:, :width])
        columns = np.arange(width)
        data[columns[None, :] >= length[:, None]] = 0  # bytes past DataLength are not data
        return data
    rows = [bytes(r)[: int(n)] for r, n in zip(raw, length, strict=True)]
    width = max([8] + [len(r) for r in rows])
    data = np.zeros((len(rows), width), dtype=np.uint8)
    for i, row in enumerate(rows):
        data[i, : len(row)] = np.frombuffer(row, dtype=np.uint8)
    return data


def read_mf4(path: str | Path) -> Frames:
    """Every CAN frame of a bus-logging MF4, in time order (groups merged; ties keep the group
    order, as python-can's reader). Bus channel numbers become the channel names."""
    path = Path(path)
    # asammdf's own bus processing (at open: each group's IDs for DBC-attached decoding) is
    # not what is read here: ~0.25 s of a 1 h log's ~1 s
    mdf = _open(path, process_bus_logging=False)
    try:
        groups = _bus_groups(mdf)
        if not groups:
            raise LogFormatError(f"{path}: no CAN bus-logging channel group (CAN_DataFrame, "
                                 f"CAN_ErrorFrame or CAN_RemoteFrame from a CAN bus source); a "
                                 f"signal-level MF4 goes through 'slipd import'")
        start = mdf.header.start_time.timestamp()
        parts = [_group_frames(mdf, index, structure, start, path)
                 for index, structure in groups]
    finally:
        mdf.close()
    t = np.concatenate([p[0] for p in parts])
    order = np.argsort(t, kind="stable")
    width = max(p[4].shape[1] for p in parts)
    data = np.concatenate([np.pad(p[4], ((0, 0), (0, width - p[4].shape[1]))) for p in parts])
    bus = np.concatenate([p[5] for p in parts])[order]
    # bus numbers -> channel indices in order of first appearance (as frames_from_messages)
    numbers, first, inverse = np.unique(bus, return_index=True, return_inverse=True)
    channel = np.argsort(np.argsort(first))[inverse]
    by_appearance = numbers[np.argsort(first)]
    return Frames(t[order], np.concatenate([p[1] for p in parts])[order],
                  np.concatenate([p[2] for p in parts])[order],
                  np.concatenate([p[3] for p in parts])[order].astype(np.uint8),
                  data[order], channel.astype(np.uint8),
                  [str(int(b)) for b in by_appearance] or ["0"], str(path))


def read_mf4_signals(path: str | Path, columns: set[str] | None = None,
                     raster: float | None = None) -> dict[str, np.ndarray]:
    """Channels of a signal-level MF4 as float64 columns plus ``t`` (s from the header's
    start time): on the union of the channels' time stamps, NaN where a channel has no sample,
    or with ``raster`` (s) each channel's newest sample at or before each raster instant.
    ``columns``: the channel names wanted (default: every numeric one)."""
    path = Path(path)
    mdf = _open(path)
    try:
        available = {}  # name -> its first (group, index) that is not a time master
        for name, entries in mdf.channels_db.items():
            for group, index in entries:
                if mdf.masters_db.get(group) != index:
                    available.setdefault(name, (group, index))
                    break
        names = sorted(available) if columns is None else [c for c in columns if c != "t"]
        missing = [c for c in names if c not in available]
        if missing:
            raise LogFormatError(f"{path}: no channel(s) {missing}; channels: "
                                 f"{sorted(n for n in available if n)[:50]}")
        signals = {}
        for name in names:
            group, index = available[name]
            signal = mdf.get(name, group, index)
            if signal.samples.dtype.kind not in "fiub" or signal.samples.ndim != 1:
                if columns is None:
                    continue
                raise LogFormatError(f"{path}: channel {name!r} is not numeric "
                                     f"({signal.samples.dtype})")
            signals[name] = (np.asarray(signal.timestamps, dtype=np.float64),
                             np.asarray(signal.samples, dtype=np.float64))
    finally:
        mdf.close()
    if not signals:
        raise LogFormatError(f"{path}: no numeric channel")
    if raster is not None:
        first = min(ts[0] for ts, _ in signals.values() if ts.size)
        last = max(ts[-1] for ts, _ in signals.values() if ts.size)
        t = first + raster * np.arange(int(np.floor((last - first) / raster + 1e-9)) + 1)
    else:
        t = np.unique(np.concatenate([ts for ts, _ in signals.values()]))
    table = {"t": t}
    for name, (ts, values) in signals.items():
        if raster is None:
            column = np.full(len(t), np.nan)
            column[np.searchsorted(t, ts)] = values
        else:
            idx = np.searchsorted(ts, t + 1e-9, side="right") - 1
            column = np.where(idx >= 0, values[np.maximum(idx, 0)], np.nan)
        table[name] = column
    return table
