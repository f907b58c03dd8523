"""The flight recorder: every received and sent frame as ``candump -L`` lines.

Received frames carry their kernel timestamps and `` R``; slipd's own frames carry the tick
time and `` T``. File order is processing order, so ``slipd replay`` of a recording latches
each tick exactly the frames the daemon had (see ``replay.engine.recorded_ticks``) and
reproduces every output frame byte for byte. Files rotate by size (``.1`` .. ``.N``).
"""

from __future__ import annotations

import os
from pathlib import Path


class FlightRecorder:
    def __init__(self, path: Path, max_bytes: int, channel: str, keep: int = 5):
        self.path = Path(path)
        self.max_bytes = max_bytes
        self.channel = channel
        self.keep = keep
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.file = open(self.path, "w", encoding="ascii", buffering=1 << 16)  # noqa: SIM115

    def frame(self, t: float, frame_id: int, extended: bool, data, rx: bool,
              channel: str | None = None, fd: bool = False, brs: bool = False) -> None:
        """One line; ``channel``: the interface the frame was on (default: the recorder's),
        ``fd``/``brs``: a CAN FD frame (``ID##F`` with the flags nibble, as candump writes)."""
        ident = f"{frame_id:08X}" if extended else f"{frame_id:03X}"
        separator = f"##{1 if brs else 0:X}" if fd else "#"
        self.file.write(f"({t:.6f}) {channel or self.channel} {ident}{separator}"
                        f"{bytes(data).hex().upper()} {'R' if rx else 'T'}\n")

    def maybe_rotate(self) -> None:
        if self.file.tell() < self.max_bytes:
            return
        self.file.close()
        for index in range(self.keep - 1, 0, -1):
            older = self.path.with_name(f"{self.path.name}.{index}")
            if older.exists():
                os.replace(older, self.path.with_name(f"{self.path.name}.{index + 1}"))
        os.replace(self.path, self.path.with_name(f"{self.path.name}.1"))
        self.file = open(self.path, "w", encoding="ascii", buffering=1 << 16)  # noqa: SIM115

    def close(self) -> None:
        self.file.close()
