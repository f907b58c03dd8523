"""Log readers by file suffix: candump (fast path) or python-can's LogReader for the rest."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slipd.errors import LogFormatError
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
    read_candump,
)

CANDUMP_SUFFIXES = (".log", ".candump")
LIBRARY_SUFFIXES = (".asc", ".blf", ".trc", ".mf4", ".csv")


def read_frames(path: str | Path, skip_bad: bool = False) -> Frames:
    """Read any supported log into :class:`Frames` (candump natively, others via python-can)."""
    path = Path(path)
    suffixes = "".join(path.suffixes[-2:]) if path.suffix == ".gz" else path.suffix
    base_suffix = suffixes.removesuffix(".gz")
    if base_suffix in CANDUMP_SUFFIXES or base_suffix == "":
        return read_candump(path, skip_bad=skip_bad)
    if suffixes == ".mf4":  # bus-logging MF4 as whole arrays (slipd.replay.mf4)
        from slipd.replay.mf4 import read_mf4

        return read_mf4(path)
    if base_suffix in LIBRARY_SUFFIXES:
        return _read_with_python_can(path)
    raise LogFormatError(f"{path}: unknown log format {suffixes!r}; expected "
                         f"{CANDUMP_SUFFIXES + LIBRARY_SUFFIXES} (optionally .gz)")


def _read_with_python_can(path: Path) -> Frames:
    import can

    t, ids, flags, dlc, rows, chan = [], [], [], [], [], []
    names: list[str] = []
    try:
        for message in can.LogReader(str(path)):
            f = 0
            f |= FLAG_EXTENDED if message.is_extended_id else 0
            f |= FLAG_REMOTE if message.is_remote_frame else 0
            f |= FLAG_ERROR if message.is_error_frame else 0
            f |= FLAG_FD if message.is_fd else 0
            f |= FLAG_BRS if message.bitrate_switch else 0
            f |= FLAG_ESI if message.error_state_indicator else 0
            f |= 0 if message.is_rx else FLAG_TX | FLAG_DIRECTION
            name = str(message.channel) if message.channel is not None else "can0"
            if name not in names:
                names.append(name)
            t.append(message.timestamp)
            ids.append(message.arbitration_id)
            flags.append(f)
            dlc.append(len(message.data) if message.data is not None else message.dlc)
            rows.append(bytes(message.data or b""))
            chan.append(names.index(name))
    except (ValueError, OSError) as exc:
        raise LogFormatError(f"{path}: python-can cannot read it: {exc}") from exc
    width = max([8] + [len(r) for r in rows])
    data = np.zeros((len(rows), width), dtype=np.uint8)
    for i, row in enumerate(rows):
        data[i, : len(row)] = np.frombuffer(row, dtype=np.uint8)
    return Frames(np.array(t, np.float64), np.array(ids, np.int64), np.array(flags, np.uint8),
                  np.array(dlc, np.uint8), data, np.array(chan, np.uint8), names or ["can0"],
                  str(path))
