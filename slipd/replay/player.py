"""The real-time player: frames onto a bus with the log's timing (absolute deadlines).

Each frame's send time is ``start + (t_i - t_0) / speed`` on CLOCK_MONOTONIC, so a late
frame never shifts the ones after it (no drift). Lateness (send time - deadline) goes into an
HDR histogram reported at the end.
"""

from __future__ import annotations

import argparse
import errno
import threading
import time
from dataclasses import dataclass

import numpy as np
from hdrh.histogram import HdrHistogram

from slipd.errors import ConfigError
from slipd.replay.candump import (
    FLAG_BRS,
    FLAG_ERROR,
    FLAG_ESI,
    FLAG_EXTENDED,
    FLAG_FD,
    FLAG_REMOTE,
    Frames,
)

SPIN_BEFORE_DEADLINE = 200e-6  # s: sleep to here, then spin (measured: sleep alone ~70 us late)
QUEUE_FULL_RETRY_S = 0.002  # a full transmit queue (ENOBUFS) is tried again for this long
QUEUE_FULL = (errno.ENOBUFS, errno.EAGAIN)


@dataclass
class PlayReport:
    frames: int
    duration: float
    lateness_us: HdrHistogram
    dropped: int = 0  # frames not sent: the bus's transmit queue stayed full (ENOBUFS)

    def summary(self) -> str:
        h = self.lateness_us
        lost = (f"; {self.dropped} frame(s) dropped, the bus's transmit queue was full"
                if self.dropped else "")
        return (f"played {self.frames} frames in {self.duration:.2f} s; lateness us: "
                f"p50 {h.get_value_at_percentile(50)} p99 {h.get_value_at_percentile(99)} "
                f"max {h.get_max_value()}{lost}")


def _send(bus, message) -> bool:
    """Send one frame; a full transmit queue (python-can's error_code ENOBUFS/EAGAIN, as
    SocketCAN reports a txqueuelen overrun) is retried for QUEUE_FULL_RETRY_S, then the frame
    counts as dropped (False). Other errors are raised."""
    import can

    give_up = None
    while True:
        try:
            bus.send(message)
            return True
        except (can.CanOperationError, OSError) as exc:
            code = getattr(exc, "errno", None) or getattr(exc, "error_code", None)
            if code not in QUEUE_FULL:
                raise
        now = time.monotonic()
        give_up = give_up or now + QUEUE_FULL_RETRY_S
        if now >= give_up:
            return False
        time.sleep(0.0002)


def to_messages(frames: Frames) -> list:
    """python-can messages of every non-error frame (error frames cannot be sent), each with
    the channel it was logged on (BusRouter sends it to the bus that channel maps to)."""
    import can

    names = frames.channels
    messages = []
    for i in range(len(frames)):
        flags = int(frames.flags[i])
        if flags & FLAG_ERROR:
            continue
        name = names[frames.channel[i]] if frames.channel[i] < len(names) else None
        messages.append(can.Message(
            timestamp=float(frames.t[i]), arbitration_id=int(frames.frame_id[i]),
            is_extended_id=bool(flags & FLAG_EXTENDED), is_remote_frame=bool(flags & FLAG_REMOTE),
            is_fd=bool(flags & FLAG_FD), bitrate_switch=bool(flags & FLAG_BRS),
            error_state_indicator=bool(flags & FLAG_ESI), dlc=int(frames.dlc[i]),
            data=None if flags & FLAG_REMOTE else bytes(frames.data[i, :frames.dlc[i]]),
            channel=name,
        ))
    return messages


def play(messages: list, bus, speed: float = 1.0, loop: bool = False,
         stop: threading.Event | None = None, spin: bool = True) -> PlayReport:
    """Send ``messages`` on ``bus`` at their log times scaled by ``1/speed``.

    ``spin=False`` only sleeps (for a player thread beside the daemon in one process, where
    spinning would hold the GIL the daemon's loop needs).
    """
    if speed <= 0:
        raise ConfigError(f"--speed {speed}: expected a number > 0")
    lateness = HdrHistogram(1, 10_000_000, 3)
    sent = dropped = 0
    started = time.monotonic()
    if not messages:
        return PlayReport(0, 0.0, lateness)
    times = np.array([m.timestamp for m in messages])
    span = times[-1] - times[0] + (float(np.median(np.diff(times))) if len(times) > 1 else 0.0)
    cycle = 0
    while True:
        base = started + cycle * span / speed
        for message, t in zip(messages, times, strict=True):
            if stop is not None and stop.is_set():
                return PlayReport(sent, time.monotonic() - started, lateness, dropped)
            deadline = base + (t - times[0]) / speed
            remaining = deadline - time.monotonic()
            margin = SPIN_BEFORE_DEADLINE if spin else 0.0
            if remaining > margin:
                time.sleep(remaining - margin)
            while spin and time.monotonic() < deadline:
                pass
            late = time.monotonic() - deadline
            if _send(bus, message):
                sent += 1
            else:
                dropped += 1
            lateness.record_value(min(max(1, int(late * 1e6)), 10_000_000))
        cycle += 1
        if not loop:
            return PlayReport(sent, time.monotonic() - started, lateness, dropped)


def parse_map(entries: list[str]) -> dict[str, str]:
    """``--map WRITE=LOG`` entries, in canplayer's order (``canplayer vcan1=can0`` plays the
    frames logged on can0 onto vcan1) -> {log channel: bus channel}."""
    mapping = {}
    for entry in entries:
        target, sep, source = entry.partition("=")
        if not sep or not source or not target:
            raise ConfigError(f"--map {entry!r}: expected WRITE=LOG as canplayer takes it, "
                              "e.g. vcan1=can0 plays the frames logged on can0 onto vcan1")
        if source in mapping:
            raise ConfigError(f"--map: log channel {source!r} mapped twice")
        mapping[source] = target
    return mapping


class BusRouter:
    """Sends each message on the bus of its (mapped) channel, as ``canplayer FROM=TO`` does.

    With no map every frame goes to ``default_channel``. With a map only frames logged on a
    mapped channel are played (the others are counted in ``unmapped``), each on its own bus.
    """

    def __init__(self, interface: str, default_channel: str, mapping: dict[str, str],
                 fd: bool = False, bus_kwargs: dict | None = None) -> None:
        import can

        self.mapping = mapping
        self.unmapped = 0
        self.buses: dict[str, can.BusABC] = {}
        targets = sorted(set(mapping.values())) if mapping else [default_channel]
        try:
            for target in targets:
                self.buses[target] = can.Bus(**(bus_kwargs or {}), interface=interface,
                                             channel=target, **({"fd": True} if fd else {}))
        except (can.CanError, OSError, ValueError) as exc:
            self.shutdown()
            raise ConfigError(f"cannot open {interface} bus {target!r}: {exc}") from exc
        self.default = None if mapping else self.buses[default_channel]

    def send(self, message) -> None:
        if self.default is not None:
            self.default.send(message)
            return
        target = self.mapping.get(str(message.channel))
        if target is None:
            self.unmapped += 1
            return
        self.buses[target].send(message)

    def receivers_lost(self) -> int:
        """Frames the buses lost at their receivers since the last call (slipd_unix counts
        a receiver whose queue was full in ``dropped``; a SocketCAN sender cannot see that)."""
        total = sum(getattr(bus, "dropped", 0) for bus in self.buses.values())
        lost, self._lost_reported = total - getattr(self, "_lost_reported", 0), total
        return lost

    def shutdown(self) -> None:
        for bus in self.buses.values():
            bus.shutdown()


def play_logs(args: argparse.Namespace) -> int:
    """``slipd replay LOG --realtime``: play each log in turn onto the bus(es). Every log is
    read and checked first (malformed lines, times that go back or jump ahead), so a bad
    one stops nothing half-played; a bus's own losses are printed at the end."""
    from slipd.profile import load_profile
    from slipd.replay.engine import checked_log
    from slipd.replay.readers import read_frames

    profile = load_profile(args.profile) if getattr(args, "profile", None) else None
    logs = [(log, checked_log(read_frames(log, skip_bad=args.skip_bad), args.skip_bad,
                              profile)) for log in args.logs]
    router = BusRouter(args.interface, args.channel, parse_map(args.map),
                       fd=bool(getattr(args, "fd", False)))
    try:
        for log, frames in logs:
            if frames.bad_lines:
                print(f"{log}: skipped {frames.bad_lines} malformed line(s), first at line(s) "
                      f"{frames.bad_line_numbers[:10]}")
            fd_frames = int(np.count_nonzero(frames.flags & FLAG_FD))
            if fd_frames and not getattr(args, "fd", False):
                raise ConfigError(f"{log}: {fd_frames} CAN FD frame(s); play them with --fd "
                                  "on an FD-capable bus")
            errors = int(np.count_nonzero(frames.flags & FLAG_ERROR))
            if errors:
                print(f"{log}: {errors} error frame(s) in the log are not played (a bus "
                      "cannot send them)")
            router.unmapped = 0
            report = play(to_messages(frames), router, args.speed, args.loop)
            print(f"{log}: {report.summary()}")
            if router.unmapped:
                print(f"{log}: {router.unmapped} frame(s) on channels not named in --map were "
                      "not played")
            lost = router.receivers_lost()
            if lost:
                print(f"{log}: the bus dropped {lost} frame(s): a receiver's queue was full")
    except KeyboardInterrupt:
        pass
    finally:
        router.shutdown()
    return 0
