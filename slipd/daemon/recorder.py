"""The flight recorder: every received and sent frame as ``candump -L`` lines.

Received frames carry their kernel timestamps and `` R``; slipd's own frames carry the tick
time and `` T``. File order is processing order, so ``slipd replay`` of a recording latches
each tick exactly the frames the daemon had (see ``replay.engine.recorded_ticks``) and
reproduces every output frame byte for byte.

Files: ``PATH`` (say ``flight.log``) is the file being written. It rotates by size into
``flight.1.log.gz``, ``flight.2.log.gz``, ... (at most ``keep`` of them; the oldest goes), and
a recording found at ``PATH`` when the daemon starts (the run before, say the one that
crashed and made systemd restart it) is rotated the same way, never overwritten. Rotated
files are compressed by a child process at SCHED_IDLE, off the loop: gzip of a 256 MB
file takes seconds of CPU. An interrupted compression leaves the plain ``flight.1.log``,
which replays as well.

A write that fails (a full disk: ENOSPC, an unplugged USB stick: EIO) stops the recording;
the daemon goes on estimating, and reports it (its log, ``recorder_errors`` and ``recorder``
in ``slipd stats``). A new file is tried every RETRY_S.
"""

from __future__ import annotations

import argparse
import gzip
import os
import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path

from slipd.daemon.service import spawn_helper, step_aside

RETRY_S = 60.0
COMPRESSED = ".gz"
PARTIAL = ".partial"  # a compression in progress (removed at start if one was cut short)


def rotated_name(path: Path, index: int, compressed: bool = True) -> Path:
    """``flight.log`` -> ``flight.3.log.gz``: the suffix stays a log suffix slipd reads."""
    suffix = path.suffix or ".log"
    name = f"{path.stem if path.suffix else path.name}.{index}{suffix}"
    return path.with_name(name + (COMPRESSED if compressed else ""))


class FlightRecorder:
    def __init__(self, path: Path, max_bytes: int, channel: str, keep: int = 10,
                 compress: bool = True, log: Callable[[str], None] = print,
                 on_error: Callable[[], None] | None = None) -> None:
        self.path = Path(path)
        self.max_bytes = max_bytes
        self.channel = channel
        self.keep = keep
        self.compress = compress
        self.log = log
        self.on_error = on_error
        self.file = None
        self.status = "starting"
        self.errors = 0
        self._retry_at: float | None = None
        self._compressors: list = []
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            self._failed(exc, "create the directory of")
            return
        self._remove_partial_compressions()
        self._open()

    # ---- the loop's calls -----------------------------------------------------------------
    def frame(self, t: float, frame_id: int, extended: bool, data, rx: bool,
              channel: str | None = None, fd: bool = False, brs: bool = False) -> None:
        """One line; ``channel``: the interface the frame was on (default: the recorder's),
        ``fd``/``brs``: a CAN FD frame (``ID##F`` with the flags nibble, as candump writes)."""
        if self.file is None:
            return
        ident = f"{frame_id:08X}" if extended else f"{frame_id:03X}"
        separator = f"##{1 if brs else 0:X}" if fd else "#"
        try:
            self.file.write(f"({t:.6f}) {channel or self.channel} {ident}{separator}"
                            f"{bytes(data).hex().upper()} {'R' if rx else 'T'}\n")
        except (OSError, ValueError) as exc:  # ValueError: the file was closed under us
            self._failed(exc, "write")

    def maybe_rotate(self) -> None:
        """Once a second, in the loop's slack: rotate by size; after a failure, try again
        every RETRY_S; reap finished compressors."""
        self._compressors = [c for c in self._compressors if c.poll() is None]
        if self._compressors:
            return  # .1 is still being compressed under its name: rotate once it is done
        if self.file is None:
            if self._retry_at is not None and time.monotonic() >= self._retry_at:
                self._open()
            return
        try:
            # tell() flushes the buffer too: a crash loses at most the last second
            if self.file.tell() < self.max_bytes:
                return
            self.file.close()
        except (OSError, ValueError) as exc:
            self._failed(exc, "write")
            return
        self.file = None
        self._open()

    def close(self) -> None:
        if self.file is not None:
            try:
                self.file.close()
            except OSError as exc:
                self.file = None
                self._failed(exc, "flush")
            self.file = None
        if self.status == "recording":
            self.status = "closed"

    # ---- files ----------------------------------------------------------------------------
    def _open(self) -> None:
        """Rotate what is at PATH (a recording is never overwritten), then open it anew."""
        try:
            if self.path.exists() and self.path.stat().st_size > 0:
                self._rotate()
            self.file = open(self.path, "w", encoding="ascii", buffering=1 << 16)  # noqa: SIM115
        except OSError as exc:
            self.file = None
            self._failed(exc, "open")
            return
        if self._retry_at is not None:
            self.log(f"slipd: flight recorder: recording again to {self.path}")
        self._retry_at = None
        self.status = "recording"

    def _rotate(self) -> None:
        """PATH -> .1, .1 -> .2, ..., the one beyond ``keep`` removed; .1 then compressed."""
        for index in range(self.keep, 0, -1):
            for compressed in (True, False):
                older = rotated_name(self.path, index, compressed)
                if not older.exists():
                    continue
                if index == self.keep:
                    older.unlink()
                else:
                    os.replace(older, rotated_name(self.path, index + 1, compressed))
        if self.keep <= 0:
            self.path.unlink()
            return
        first = rotated_name(self.path, 1, compressed=False)
        os.replace(self.path, first)
        if self.compress:
            self._start_compressor(first)

    def _start_compressor(self, source: Path) -> None:
        command = [sys.executable, "-m", "slipd.daemon.recorder", "compress", str(source)]
        try:
            self._compressors.append(spawn_helper(command))
        except OSError as exc:  # left uncompressed: still a recording
            self.log(f"slipd: flight recorder: cannot start compressing {source}: {exc}")

    def _remove_partial_compressions(self) -> None:
        for index in range(1, self.keep + 2):
            partial = rotated_name(self.path, index).with_name(
                rotated_name(self.path, index).name + PARTIAL)
            plain = rotated_name(self.path, index, compressed=False)
            try:
                partial.unlink(missing_ok=True)
                if plain.exists() and rotated_name(self.path, index).exists():
                    plain.unlink()  # compressed completely, cut short before the unlink
            except OSError:
                pass

    def _failed(self, exc: Exception, action: str) -> None:
        self.errors += 1
        self.status = f"stopped: cannot {action} {self.path}: {exc}"
        if self.file is not None:
            try:
                self.file.close()
            except (OSError, ValueError):
                pass
            self.file = None
        self._retry_at = time.monotonic() + RETRY_S
        self.log(f"slipd: flight recorder {self.status}; recording stopped, estimation goes "
                 f"on; trying a new file in {RETRY_S:.0f} s")
        if self.on_error is not None:
            self.on_error()


def compress(source: Path) -> int:
    """``flight.1.log`` -> ``flight.1.log.gz`` (through a ``.partial`` file renamed when
    complete, so a cut-short run never leaves a truncated .gz), then remove the source."""
    step_aside(os.SCHED_IDLE)  # compress only when nothing else wants the CPU
    target = source.with_name(source.name + COMPRESSED)
    partial = target.with_name(target.name + PARTIAL)
    try:
        with open(source, "rb") as plain, gzip.open(partial, "wb", compresslevel=6) as packed:
            shutil.copyfileobj(plain, packed, 1 << 20)
        os.replace(partial, target)
        source.unlink()
    except OSError as exc:
        partial.unlink(missing_ok=True)
        print(f"slipd: flight recorder: {source} left uncompressed: {exc}", file=sys.stderr)
        return 1
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m slipd.daemon.recorder")
    parser.add_argument("action", choices=["compress"])
    parser.add_argument("file", type=Path)
    args = parser.parse_args(argv)
    return compress(args.file)


if __name__ == "__main__":
    sys.exit(main())
