"""A CAN bus between processes of one machine over unix datagram sockets (python-can plugin).

``can.Bus(interface="slipd_unix", channel="/run/slipd-bus")``: the channel is a directory;
every participant binds one socket file in it and sends each frame to every other socket
there, so all participants see each other's frames as on a CAN bus. Datagrams carry the
SocketCAN wire formats (``struct can_frame``, 16 bytes; ``struct canfd_frame``, 72 bytes);
receive timestamps are the kernel's (SO_TIMESTAMPNS, CLOCK_REALTIME, taken when the datagram
is queued), as SocketCAN stamps frames at reception.

Why it exists: this project's development machines have no CAN in the kernel, python-can's
``virtual`` bus is in-process only, and its ``udp_multicast`` leaves the machine. The
daemon's latency benchmark needs its bus feeder in another process (a feeder thread would
hold the GIL the loop needs), so it runs on this transport; cross-process tests of the real
thing run on vcan in the VM (tests/vm).

Receive filters act at the sender, as SocketCAN's act in the kernel: a participant publishes
its filters beside its socket (``<name>.filters``, JSON) and senders skip the datagram to a
peer none of whose filters match, so a receiver is not woken by frames it would drop (the
benchmark's bus carries ~6x more frames than the daemon's filters pass). python-can still
checks each received frame against the filters, so a sender that has not yet read a changed
filter file costs time, never a wrong frame.

A receiver whose socket buffer is full loses that frame, like a SocketCAN socket whose
receive queue overflows; the sender counts such losses in ``dropped``. A datagram that is
not a CAN frame (any process may write to the directory's sockets) is dropped and counted in
``malformed``, never an error of the bus: a 5-byte datagram once failed the daemon's bus.
"""

from __future__ import annotations

import errno
import json
import os
import select
import socket
import struct
import time
from pathlib import Path

import can

from slipd.daemon.transmit import CAN_EFF_FLAG

CAN_RTR_FLAG = 0x40000000
CAN_ERR_FLAG = 0x20000000
CANFD_BRS = 0x01
CANFD_ESI = 0x02
CLASSIC = struct.Struct("<IB3x8s")  # struct can_frame
FD = struct.Struct("<IBB2x64s")  # struct canfd_frame
CAN_ID = struct.Struct("<I")  # the can_id both begin with
PEER_GONE = (errno.ECONNREFUSED, errno.ENOENT, errno.ENOTCONN)  # send errors: peer left
PEER_REFRESH_S = 0.2  # how often the directory is checked for participants that came or went
RECEIVE_BUFFER = 1 << 20
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # the socket module lacks it on 3.11
TIMESPEC = struct.Struct("@qq")  # struct timespec on 64-bit Linux
TIMESTAMP_SPACE = socket.CMSG_SPACE(TIMESPEC.size)


def _lengths_fit(datagram: bytes) -> bool:
    """The frame's length field fits its struct (at most 8, or 64 for CAN FD)."""
    length = datagram[4]
    return length <= (8 if len(datagram) == CLASSIC.size else 64)


def _filter_path(socket_path: Path) -> Path:
    """Where the participant bound at ``socket_path`` publishes its receive filters."""
    return socket_path.with_suffix(".filters")


class _Peer:
    """Another participant: a socket connected to its socket file (sending on it skips the
    path lookup a sendto(path) makes per datagram, as a SocketCAN socket sends on the
    interface it is bound to: measured 2 sends after 2 ms idle 26-32 us by path, 8-17 us
    connected) and its published receive filters."""

    __slots__ = ("path", "socket", "filters")

    def __init__(self, path: str, sock: socket.socket) -> None:
        self.path = path
        self.socket = sock
        self.filters: tuple | None = None

    @classmethod
    def connect(cls, path: str) -> _Peer | None:
        """None when the socket file is stale (its participant left without removing it)."""
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        sock.setblocking(False)
        try:
            sock.connect(path)
        except OSError:
            sock.close()
            return None
        return cls(path, sock)


class UnixDatagramBus(can.BusABC):
    """See the module docstring. ``channel``: the bus directory (created if missing)."""

    def __init__(self, channel: str, can_filters=None, receive_own_messages: bool = False,
                 receive: bool = True, **kwargs) -> None:
        """``receive=False``: a send-only participant (a feeder that never reads), which
        binds no socket file, so the others do not spend a send on it per frame."""
        self.directory = Path(channel)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.path = self.directory / f"{os.getpid()}-{id(self):x}.sock"
        self.filter_path = _filter_path(self.path)
        self.receive = receive
        self.socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        if receive:
            # published before the socket is bound: no sender sees this participant without them
            self._publish_filters(can_filters)
            self.socket.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER)
            # the kernel stamps each datagram as it is queued, as SocketCAN stamps a frame at
            # reception: a frame read late still carries the time it arrived
            self.socket.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            self.socket.bind(str(self.path))
        self.socket.setblocking(False)
        self.receive_own_messages = receive_own_messages
        self.channel_info = f"unix datagram bus {self.directory}"
        self.dropped = 0
        self.malformed = 0
        self._peers: list[_Peer] = []
        self._peers_read = 0.0
        self._directory_mtime = -1
        self._own: list[can.Message] = []
        super().__init__(channel=channel, can_filters=can_filters, **kwargs)

    def fileno(self) -> int:
        return self.socket.fileno()

    def _publish_filters(self, filters) -> None:
        """Write this participant's filters where senders read them (atomically: a rename,
        which also moves the directory's mtime so senders re-read)."""
        rows = [[int(f["can_id"]), int(f["can_mask"]), f.get("extended")]
                for f in filters or ()]
        temporary = self.filter_path.with_suffix(".filters-new")
        temporary.write_text(json.dumps(rows))
        os.replace(temporary, self.filter_path)

    def _apply_filters(self, filters) -> None:
        """python-can's hook for filtering below the bus object (kernel or hardware)."""
        if self.receive:
            self._publish_filters(filters)

    @staticmethod
    def _read_filters(socket_path: str) -> tuple | None:
        """A peer's published filters as (can_id & can_mask, can_mask, extended or None)
        rows; None (send it everything) when it has none or they cannot be read."""
        try:
            rows = json.loads(_filter_path(Path(socket_path)).read_text())
            filters = tuple((int(can_id) & int(mask), int(mask), extended)
                            for can_id, mask, extended in rows)
        except (OSError, ValueError, TypeError):
            return None
        return filters or None

    @staticmethod
    def _passes(filters: tuple | None, frame_id: int, extended: bool) -> bool:
        """python-can's filter rule (BusABC._matches_filters) on a peer's published rows."""
        if filters is None:
            return True
        for masked_id, mask, filter_extended in filters:
            if filter_extended is not None and filter_extended != extended:
                continue
            if frame_id & mask == masked_id:
                return True
        return False

    def _refresh_peers(self) -> None:
        """Re-list the participants when the directory changed (its mtime moves when a socket
        file is bound or removed): one stat per interval instead of a listing, which cost
        ~200 us every 0.2 s inside the sender's cycle."""
        self._peers_read = time.monotonic()
        mtime = os.stat(self.directory).st_mtime_ns
        if mtime == self._directory_mtime:
            return
        # mtimes tick with the kernel's coarse clock: a participant arriving within the same
        # tick as the listing would leave it unchanged, so a recent mtime is not trusted.
        recent = time.time_ns() - mtime < 100_000_000
        self._directory_mtime = -1 if recent else mtime
        own = str(self.path)
        with os.scandir(self.directory) as entries:
            paths = [entry.path for entry in entries
                     if entry.name.endswith(".sock") and entry.path != own]
        known = {peer.path: peer for peer in self._peers}
        peers = []
        for path in paths:
            peer = known.pop(path, None) or _Peer.connect(path)
            if peer is not None:
                peer.filters = self._read_filters(path)
                peers.append(peer)
        for peer in known.values():  # participants that left
            peer.socket.close()
        self._peers = peers

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        frame_id = msg.arbitration_id | (CAN_EFF_FLAG if msg.is_extended_id else 0)
        if msg.is_remote_frame:
            frame_id |= CAN_RTR_FLAG
        data = bytes(msg.data or b"")
        if msg.is_fd:
            flags = (CANFD_BRS if msg.bitrate_switch else 0) | (
                CANFD_ESI if msg.error_state_indicator else 0)
            self.write_frame(FD.pack(frame_id, len(data), flags, data))
        else:
            self.write_frame(CLASSIC.pack(frame_id, msg.dlc, data))

    def write_frame(self, frame) -> None:
        """Send a ``struct can_frame`` or ``struct canfd_frame`` (any bytes-like object) as
        is, as ``write()`` on a SocketCAN socket does: the daemon's fast transmit path
        (slipd.daemon.transmit)."""
        if time.monotonic() - self._peers_read > PEER_REFRESH_S:
            self._refresh_peers()
        (can_id,) = CAN_ID.unpack_from(frame)
        arbitration_id = can_id & 0x1FFFFFFF
        extended = bool(can_id & CAN_EFF_FLAG)
        gone = []
        passes = self._passes
        for peer in self._peers:
            if not passes(peer.filters, arbitration_id, extended):
                continue
            try:
                peer.socket.send(frame)
            except BlockingIOError:
                self.dropped += 1  # that receiver's queue is full: it loses this frame
            except OSError as exc:
                if exc.errno not in PEER_GONE:
                    raise
                gone.append(peer)  # a participant that left without removing its file
        if gone:
            for peer in gone:
                peer.socket.close()
            self._peers = [peer for peer in self._peers if peer not in gone]
            self._directory_mtime = -1  # list again at the next refresh: it may be back
        if self.receive_own_messages:
            self._own.append(self._decode(bytes(frame), time.time(), is_rx=False))

    def _recv_internal(self, timeout: float | None):
        if self.receive_own_messages and self._own:
            return self._own.pop(0), False
        if not self.receive:
            raise can.CanOperationError(f"{self.channel_info}: this participant was opened "
                                        "send-only (receive=False)")
        waited = False
        while True:
            try:
                datagram, ancillary, flags, _ = self.socket.recvmsg(FD.size + 1,
                                                                    TIMESTAMP_SPACE)
            except BlockingIOError:
                if waited or (timeout is not None and timeout <= 0):
                    return None, False
                readable, _, _ = select.select([self.socket], [], [], timeout)
                if not readable:
                    return None, False
                waited = True  # once: python-can's recv() owns the rest of the timeout
                continue
            if len(datagram) in (CLASSIC.size, FD.size) and not flags & socket.MSG_TRUNC \
                    and _lengths_fit(datagram):
                break
            self.malformed += 1  # and the next datagram, at once: frames may wait behind it
        stamp = time.time()
        for level, kind, value in ancillary:
            if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                seconds, nanoseconds = TIMESPEC.unpack(value)
                stamp = seconds + nanoseconds * 1e-9
        return self._decode(datagram, stamp), False

    def _decode(self, datagram: bytes, stamp: float, is_rx: bool = True) -> can.Message:
        if len(datagram) == FD.size:
            frame_id, length, flags, data = FD.unpack(datagram)
            fd, brs, esi = True, bool(flags & CANFD_BRS), bool(flags & CANFD_ESI)
        elif len(datagram) == CLASSIC.size:
            frame_id, length, data = CLASSIC.unpack(datagram)
            fd = brs = esi = False
        else:
            raise can.CanOperationError(
                f"{self.channel_info}: datagram of {len(datagram)} bytes; expected "
                f"{CLASSIC.size} (can_frame) or {FD.size} (canfd_frame)")
        remote = bool(frame_id & CAN_RTR_FLAG)
        return can.Message(
            timestamp=stamp, arbitration_id=frame_id & 0x1FFFFFFF,
            is_extended_id=bool(frame_id & CAN_EFF_FLAG), is_remote_frame=remote,
            is_error_frame=bool(frame_id & CAN_ERR_FLAG), is_fd=fd, bitrate_switch=brs,
            error_state_indicator=esi, dlc=length,
            data=None if remote else data[:length], channel=str(self.directory), is_rx=is_rx)

    def shutdown(self) -> None:
        super().shutdown()
        self.socket.close()
        for peer in self._peers:
            peer.socket.close()
        self._peers = []
        for path in (self.path, self.filter_path):
            try:
                path.unlink()
            except FileNotFoundError:
                pass

    @staticmethod
    def _detect_available_configs():
        return []

