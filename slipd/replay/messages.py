"""python-can Messages -> :class:`~slipd.replay.candump.Frames` (the batch engine's arrays).

For anything that yields ``can.Message`` objects: python-can's log readers, a recording held
in memory, a notebook's list of messages. The flags follow python-can's fields one for one
(CAN FD payloads up to 64 bytes, BRS, ESI, error and remote frames, the direction).
"""

from __future__ import annotations

from collections.abc import Iterable

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
)


def message_flags(message) -> int:
    """The Frames flag byte of one python-can Message."""
    f = FLAG_EXTENDED if message.is_extended_id else 0
    f |= FLAG_REMOTE if message.is_remote_frame else 0
    f |= FLAG_ERROR if message.is_error_frame else 0
    f |= FLAG_FD if message.is_fd else 0
    f |= FLAG_BRS if message.bitrate_switch else 0
    f |= FLAG_ESI if message.error_state_indicator else 0
    f |= 0 if message.is_rx else FLAG_TX | FLAG_DIRECTION
    return f


def frames_from_messages(messages: Iterable, source: str = "messages") -> Frames:
    """Every message of ``messages`` in order. A message's channel (python-can's
    ``channel``: a name or a number; None = ``can0``) becomes a Frames channel index.
    Anything that is not a Message is a LogFormatError naming its position."""
    t, ids, flags, dlc, rows, chan = [], [], [], [], [], []
    names: list[str] = []
    for position, message in enumerate(messages):
        try:
            name = str(message.channel) if message.channel is not None else "can0"
            flag = message_flags(message)
            payload = bytes(message.data or b"")
            timestamp = float(message.timestamp)
            frame_id = int(message.arbitration_id)
            length = len(message.data) if message.data is not None else int(message.dlc)
        except (AttributeError, TypeError, ValueError) as exc:
            raise LogFormatError(f"{source}: item {position} is not a python-can Message "
                                 f"({type(message).__name__}: {exc})") from exc
        if name not in names:
            names.append(name)
        t.append(timestamp)
        ids.append(frame_id)
        flags.append(flag)
        dlc.append(length)
        rows.append(payload)
        chan.append(names.index(name))
    width = max([8] + [len(r) for r in rows])
    data = np.zeros((len(rows), width), dtype=np.uint8)
    for i, row in enumerate(rows):
        data[i, : len(row)] = np.frombuffer(row, dtype=np.uint8)
    return Frames(np.array(t, np.float64), np.array(ids, np.int64), np.array(flags, np.uint8),
                  np.array(dlc, np.uint8), data, np.array(chan, np.uint8), names or ["can0"],
                  source)
