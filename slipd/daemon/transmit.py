"""The daemon's output frames as SocketCAN's ``struct can_frame``, written to the bus in one call.

Each output message owns a 16-byte frame buffer whose header (CAN ID, length) is filled once;
the codec's encode kernel writes the payload straight into its last 8 bytes
(:func:`frame_buffer`). On a SocketCAN bus the buffer goes to the socket as is
(:func:`frame_writer`): one ``send`` system call, non-blocking. python-can's
``SocketcanBus.send`` builds the same bytes from a ``can.Message`` and adds a ``select`` call,
a logger lookup and two debug-log calls per frame; the cycle latency is measured up to the
last send returning, so that path was in every tick. Other interfaces (python-can's
``virtual`` bus of the demo and tests) still go through ``bus.send`` with a ``can.Message``.

Errors keep python-can's meaning for the loop: an ``OSError`` whose errno is in
:data:`QUEUE_FULL` lost this frame only (the interface's transmit queue is full, ``ENOBUFS``,
or the socket's buffer, ``EAGAIN``); any other is a failed bus.
"""

from __future__ import annotations

import errno
import socket
import struct
from collections.abc import Callable

import numpy as np

CAN_EFF_FLAG = 0x80000000
CAN_FRAME_SIZE = 16  # struct can_frame: can_id, len, __pad, __res0, len8_dlc, data[8]
CANFD_FRAME_SIZE = 72  # struct canfd_frame: can_id, len, flags, __res0, __res1, data[64]
CANFD_BRS = 0x01  # bit rate switch: the data phase at the data bit rate
CANFD_FDF = 0x04  # marks a canfd_frame as an FD frame (python-can sets it; older kernels ignore)
PAYLOAD = slice(8, 16)
QUEUE_FULL = (errno.ENOBUFS, errno.EAGAIN)
_HEADER = struct.Struct("=IBB1xB")  # host byte order, as the kernel reads it; python-can's


def frame_buffer(frame_id: int, extended: bool = False, length: int = 8,
                 fd: bool = False) -> np.ndarray:
    """A ``struct can_frame`` (or, with ``fd``, a ``struct canfd_frame`` with the bit-rate
    switch set) for ``frame_id`` with a zero payload of ``length`` bytes, laid out as
    python-can's ``build_can_frame`` lays them out. :func:`payload` is its data view."""
    if not 0 <= length <= (64 if fd else 8):
        raise ValueError(f"CAN{' FD' if fd else ''} frame length {length}: expected "
                         f"0..{64 if fd else 8} bytes")
    frame = np.zeros(CANFD_FRAME_SIZE if fd else CAN_FRAME_SIZE, dtype=np.uint8)
    can_id = frame_id | (CAN_EFF_FLAG if extended else 0)
    # classic: len8_dlc repeats the length, as python-can's build_can_frame writes it (the
    # kernel reads it only for 8-byte frames with a DLC of 9..15); FD: the flags byte
    third = CANFD_FDF | CANFD_BRS if fd else 0
    fourth = 0 if fd else length
    frame[:8] = np.frombuffer(_HEADER.pack(can_id, length, third, fourth), dtype=np.uint8)
    return frame


def payload(frame: np.ndarray) -> np.ndarray:
    """The data bytes of a :func:`frame_buffer` (a view the encode kernel writes into)."""
    return frame[8:8 + int(frame[4])]


def frame_writer(bus) -> Callable[[np.ndarray], object] | None:
    """A function sending one :func:`frame_buffer` on ``bus`` in a single call, or None when
    ``bus`` has no such path (send a ``can.Message`` with ``bus.send`` instead).

    SocketCAN: a socket bound to one interface (python-can binds it unless ``channel`` is
    empty), written with MSG_DONTWAIT so a full socket buffer is an error, never a wait.
    slipd_unix (the benchmark's transport): its ``write_frame``, which takes the same bytes.
    """
    write_frame = getattr(bus, "write_frame", None)
    if write_frame is not None:
        return write_frame
    try:
        from can.interfaces.socketcan import SocketcanBus
    except ImportError:  # a python-can without the socketcan interface (non-Linux)
        return None
    if isinstance(bus, SocketcanBus) and bus.channel:
        send = bus.socket.send
        flags = socket.MSG_DONTWAIT

        def write_socketcan(frame: np.ndarray) -> int:
            return send(frame, flags)

        return write_socketcan
    return None
