"""The daemon's frame writer (slipd.daemon.transmit): the bytes it writes are python-can's for
the same message, on SocketCAN and on slipd_unix, and send errors keep their meaning."""

from __future__ import annotations

import socket
import threading

import can
import numpy as np
import pytest
from can.interfaces.socketcan import SocketcanBus
from can.interfaces.socketcan.socketcan import build_can_frame
from hypothesis import given
from hypothesis import strategies as st

from slipd.daemon.loop import Daemon, DaemonConfig
from slipd.daemon.transmit import PAYLOAD, frame_buffer, frame_writer
from slipd.profile import load_profile

PROFILE = load_profile("default")


@given(frame_id=st.integers(0, 0x7FF), extended=st.booleans(),
       payload=st.binary(min_size=0, max_size=8), high_id=st.integers(0, 0x1FFFFFFF))
def test_frame_buffer_is_python_cans_struct_can_frame(frame_id, extended, payload, high_id):
    frame_id = high_id if extended else frame_id
    frame = frame_buffer(frame_id, extended, len(payload))
    frame[8:8 + len(payload)] = np.frombuffer(payload, dtype=np.uint8)
    message = can.Message(arbitration_id=frame_id, is_extended_id=extended, data=payload)
    assert frame.tobytes() == build_can_frame(message)


def test_frame_buffer_refuses_a_length_over_8():
    with pytest.raises(ValueError, match="0..8"):
        frame_buffer(0x100, length=9)


def _socketcan_bus_on(sock: socket.socket, channel: str) -> SocketcanBus:
    """A SocketcanBus whose socket is ``sock`` (this machine has no CAN in its kernel; the
    VM tests run the real thing)."""
    bus = SocketcanBus.__new__(SocketcanBus)
    bus.socket = sock
    bus.channel = channel
    return bus


def test_socketcan_writer_sends_the_buffer_as_is_without_waiting():
    ours, peer = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        assert frame_writer(_socketcan_bus_on(ours, "")) is None  # unbound: python-can's send
        write = frame_writer(_socketcan_bus_on(ours, "can0"))
        frame = frame_buffer(0x3A0)
        frame[PAYLOAD] = np.arange(8, dtype=np.uint8)
        write(frame)
        expected = can.Message(arbitration_id=0x3A0, is_extended_id=False, data=bytes(range(8)))
        assert peer.recv(64) == build_can_frame(expected)
        ours.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1024)
        with pytest.raises(BlockingIOError):  # a full socket: an error at once, never a wait
            for _ in range(10_000):
                write(frame)
    finally:
        ours.close()
        peer.close()


def test_virtual_bus_has_no_writer_and_slipd_unix_writes_what_python_can_would(tmp_path):
    virtual = can.Bus(interface="virtual", channel="transmit-test")
    sender = can.Bus(interface="slipd_unix", channel=str(tmp_path / "bus"))
    receiver = can.Bus(interface="slipd_unix", channel=str(tmp_path / "bus"))
    try:
        assert frame_writer(virtual) is None
        write = frame_writer(sender)
        frame = frame_buffer(0x1234567, extended=True, length=3)
        frame[8:11] = (1, 2, 3)
        write(frame)
        received = receiver.recv(1.0)
        expected = can.Message(arbitration_id=0x1234567, is_extended_id=True, data=b"\x01\x02\x03")
        assert received.equals(expected, timestamp_delta=None, check_channel=False,
                               check_direction=False)
    finally:
        for bus in (virtual, sender, receiver):
            bus.shutdown()


def test_daemon_sends_its_recorded_frames_through_the_writer(tmp_path):
    """On slipd_unix the daemon writes frame buffers; a listener sees exactly the frames the
    flight recorder logged as sent (the recorder's replay equivalence is tested elsewhere)."""
    channel = str(tmp_path / "bus")
    listener = can.Bus(interface="slipd_unix", channel=channel)
    config = DaemonConfig(profile=PROFILE, estimator="zero", interface="slipd_unix",
                          channel=channel, duration=1.2, recorder=tmp_path / "recorder.log")
    daemon = Daemon(config, log=lambda *_: None)
    received = []
    finished = threading.Event()

    def listen():  # as it arrives: a unix datagram queue holds only a few frames
        # until the daemon has stopped (a cold numba cache compiles for seconds before the
        # first frame), then what is still queued
        while True:
            stopped = finished.is_set()
            message = listener.recv(0.2)
            if message is not None:
                received.append(f"{message.arbitration_id:03X}#{message.data.hex().upper()}")
            elif stopped:
                return

    reader = threading.Thread(target=listen)
    reader.start()
    try:
        assert daemon._write_frame is not None
        final = daemon.run()
    finally:
        finished.set()
        reader.join()
        listener.shutdown()
    assert daemon.bus.dropped == 0
    logged = [line.split()[2] for line in (tmp_path / "recorder.log").read_text().splitlines()
              if line.endswith(" T")]
    # two frames per tick that ran (a loaded machine skips ticks: counted as misses), and the
    # 1 Hz diagnostics
    assert final["counters"]["ticks"] > 0 and len(logged) >= 2 * final["counters"]["ticks"]
    assert received == logged


class _FailingBus:
    """A python-can bus whose send fails as python-can reports it (errno in error_code)."""

    def __init__(self, error_code: int) -> None:
        self.error_code = error_code

    def recv(self, timeout=None):
        return None

    def send(self, message, timeout=None):
        raise can.CanOperationError("Failed to transmit", self.error_code)


@pytest.mark.parametrize(("error_code", "bus_failed"), [(105, False), (11, False), (100, True)])
def test_a_full_transmit_queue_loses_the_frame_a_failed_bus_is_reported(error_code, bus_failed):
    daemon = Daemon(DaemonConfig(profile=PROFILE, interface="virtual", channel="unused"),
                    bus=_FailingBus(error_code), log=lambda *_: None)
    daemon.tick(1.0)
    assert daemon.stats.counters["tx_errors"] >= 1
    assert (daemon.bus_down_since is not None) == bus_failed
