"""slipd's unix-datagram CAN bus (python-can plugin ``slipd_unix``), used by the latency
benchmark to feed the daemon from another process on machines without vcan."""

from __future__ import annotations

import os
import time

import can
import pytest

from slipd.daemon.unixbus import UnixDatagramBus


@pytest.fixture
def bus_dir(tmp_path):
    return str(tmp_path / "bus")


def test_every_participant_sees_the_others_frames(bus_dir):
    a, b, c = (can.Bus(interface="slipd_unix", channel=bus_dir) for _ in range(3))
    try:
        assert isinstance(a, UnixDatagramBus)
        sent = [
            can.Message(arbitration_id=0x123, data=b"\x01\x02", is_extended_id=False),
            can.Message(arbitration_id=0x1ABCDEF0, data=bytes(range(8))),
            can.Message(arbitration_id=0x7FF, is_remote_frame=True, dlc=4, is_extended_id=False),
            can.Message(arbitration_id=0x100, data=bytes(range(64)), is_fd=True,
                        bitrate_switch=True, is_extended_id=False),
        ]
        for message in sent:
            a.send(message)
        for receiver in (b, c):
            got = [receiver.recv(1.0) for _ in sent]
            for message, received in zip(sent, got, strict=True):
                assert received is not None
                assert received.equals(message, timestamp_delta=None, check_channel=False,
                                       check_direction=False)
            assert receiver.recv(0.0) is None
        assert a.recv(0.0) is None  # not its own frames
    finally:
        for bus in (a, b, c):
            bus.shutdown()
    assert os.listdir(bus_dir) == []  # each participant removes its socket file


def test_filters_timeout_and_a_participant_that_vanished(bus_dir):
    sender = can.Bus(interface="slipd_unix", channel=bus_dir)
    receiver = can.Bus(interface="slipd_unix", channel=bus_dir,
                       can_filters=[{"can_id": 0x100, "can_mask": 0x7FF, "extended": False}])
    crashed = can.Bus(interface="slipd_unix", channel=bus_dir)
    crashed.socket.close()  # died without cleaning up: its socket file stays behind
    try:
        sender.send(can.Message(arbitration_id=0x200, data=b"\x00", is_extended_id=False))
        sender.send(can.Message(arbitration_id=0x100, data=b"\x01", is_extended_id=False))
        received = receiver.recv(1.0)
        assert received.arbitration_id == 0x100
        assert receiver.recv(0.05) is None
    finally:
        sender.shutdown()
        receiver.shutdown()


def test_a_full_receiver_loses_frames_and_the_sender_counts_them(bus_dir):
    sender = can.Bus(interface="slipd_unix", channel=bus_dir)
    receiver = can.Bus(interface="slipd_unix", channel=bus_dir)
    try:
        total = 5000
        for k in range(total):
            sender.send(can.Message(arbitration_id=k & 0x7FF, data=b"\x00", is_extended_id=False))
        received = 0
        while receiver.recv(0.0) is not None:
            received += 1
        assert sender.dropped > 0
        assert received + sender.dropped == total
    finally:
        sender.shutdown()
        receiver.shutdown()


def test_filters_act_at_the_sender_like_kernel_filters(bus_dir):
    """A receiver is not even sent the frames its filters reject (as SocketCAN filters in the
    kernel), including after it changes its filters; python-can's own rule decides."""
    standard_only = [{"can_id": 0x100, "can_mask": 0x7F0, "extended": False}]
    receiver = can.Bus(interface="slipd_unix", channel=bus_dir, can_filters=standard_only)
    sender = can.Bus(interface="slipd_unix", channel=bus_dir)
    frames = [can.Message(arbitration_id=i, data=b"\x00", is_extended_id=ext)
              for i, ext in ((0x100, False), (0x10F, False), (0x110, False), (0x100, True),
                             (0x7FF, False))]

    def raw_ids() -> list[tuple[int, bool]]:
        """What reached the socket, read below python-can's software filter."""
        got = []
        while True:
            try:
                datagram = receiver.socket.recv(100)
            except BlockingIOError:
                return got
            message = receiver._decode(datagram, 0.0)
            got.append((message.arbitration_id, message.is_extended_id))

    try:
        for frame in frames:
            sender.send(frame)
        expected = [(f.arbitration_id, f.is_extended_id) for f in frames
                    if receiver._matches_filters(f)]
        assert expected == [(0x100, False), (0x10F, False)]
        assert raw_ids() == expected

        receiver.set_filters([{"can_id": 0x7FF, "can_mask": 0x7FF}])  # either ID format
        time.sleep(0.25)  # past the sender's peer refresh interval
        for frame in frames:
            sender.send(frame)
        assert raw_ids() == [(0x7FF, False)]

        receiver.set_filters(None)  # no filters: everything
        time.sleep(0.25)
        for frame in frames:
            sender.send(frame)
        assert len(raw_ids()) == len(frames)
    finally:
        sender.shutdown()
        receiver.shutdown()
    assert os.listdir(bus_dir) == []


def test_a_send_only_participant_binds_no_socket_file(bus_dir):
    receiver = can.Bus(interface="slipd_unix", channel=bus_dir)
    feeder = can.Bus(interface="slipd_unix", channel=bus_dir, receive=False)
    try:
        assert sorted(os.listdir(bus_dir)) == sorted([receiver.path.name,
                                                       receiver.filter_path.name])
        feeder.send(can.Message(arbitration_id=0x123, data=b"\x07", is_extended_id=False))
        assert receiver.recv(1.0).data == b"\x07"
        receiver.send(can.Message(arbitration_id=0x124, data=b"\x08", is_extended_id=False))
        with pytest.raises(can.CanOperationError, match="send-only"):
            feeder.recv(0.0)
    finally:
        feeder.shutdown()
        receiver.shutdown()
    assert os.listdir(bus_dir) == []


def test_a_frame_read_late_carries_the_time_it_arrived(bus_dir):
    """Kernel receive timestamps, as SocketCAN's: the daemon tells a frame that arrived
    before a tick from one that arrived after it by this stamp, however late it reads it."""
    receiver = can.Bus(interface="slipd_unix", channel=bus_dir)
    sender = can.Bus(interface="slipd_unix", channel=bus_dir)
    try:
        sent_at = time.time()
        sender.send(can.Message(arbitration_id=0x10, data=b"\x01", is_extended_id=False))
        time.sleep(0.2)
        received = receiver.recv(1.0)
        assert abs(received.timestamp - sent_at) < 0.05  # not the read time, 0.2 s later
    finally:
        sender.shutdown()
        receiver.shutdown()


def test_participants_that_leave_and_join_after_the_sender_connected(bus_dir):
    """The sender keeps a socket connected to each peer; one that leaves (cleanly or by
    dying) costs no error, and one that joins later is found at the next refresh."""
    from slipd.daemon.unixbus import PEER_REFRESH_S

    sender = can.Bus(interface="slipd_unix", channel=bus_dir)
    stays = can.Bus(interface="slipd_unix", channel=bus_dir)
    leaves = can.Bus(interface="slipd_unix", channel=bus_dir)
    dies = can.Bus(interface="slipd_unix", channel=bus_dir)
    joins = None
    frame = can.Message(arbitration_id=0x100, data=b"\x01", is_extended_id=False)
    try:
        sender.send(frame)
        for receiver in (stays, leaves, dies):
            assert receiver.recv(1.0) is not None
        leaves.shutdown()
        dies.socket.close()  # its socket file stays behind
        sender.send(frame)
        sender.send(frame)
        assert stays.recv(1.0) is not None and stays.recv(1.0) is not None
        assert len(sender._peers) == 1
        joins = can.Bus(interface="slipd_unix", channel=bus_dir)
        time.sleep(PEER_REFRESH_S + 0.05)
        sender.send(frame)
        assert joins.recv(1.0) is not None
        assert stays.recv(1.0) is not None
    finally:
        for bus in (sender, stays, joins):
            if bus is not None:
                bus.shutdown()


def test_a_datagram_that_is_no_can_frame_is_counted_not_a_bus_failure(bus_dir):
    """A 5-byte datagram on slipd_unix made recv() raise, which the daemon took for a failed
    bus (outputs invalid until a reopen)."""

    receiver = can.Bus(interface="slipd_unix", channel=bus_dir)
    sender = can.Bus(interface="slipd_unix", channel=bus_dir)
    try:
        _send_junk(receiver, b"\x01\x02\x03\x04\x05", bytes(100),
                   bytes([0] * 4 + [15] + [0] * 11))
        sender.send(can.Message(arbitration_id=0x123, data=b"\x01", is_extended_id=False))
        received = receiver.recv(1.0)
        assert received is not None and received.arbitration_id == 0x123
        assert receiver.malformed == 3
    finally:
        receiver.shutdown()
        sender.shutdown()


def _send_junk(receiver, *datagrams: bytes) -> None:
    """Datagrams that are no CAN frame, from a socket of no slipd_unix bus."""
    import socket

    stray = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    for junk in datagrams:
        stray.sendto(junk, str(receiver.path))
    stray.close()


def test_frames_behind_a_malformed_datagram_are_read_at_once(bus_dir):
    """A poll (timeout 0) must not stop at a malformed datagram: the frames queued behind it
    would wait for the next poll (the daemon's late drain took that as an empty queue)."""

    receiver = can.Bus(interface="slipd_unix", channel=bus_dir)
    sender = can.Bus(interface="slipd_unix", channel=bus_dir)
    try:
        _send_junk(receiver, b"\x05")
        sender.send(can.Message(arbitration_id=0x7, data=b"\x01", is_extended_id=False))
        time.sleep(0.05)
        received = receiver.recv(0.0)
        assert received is not None and received.arbitration_id == 0x7
        assert receiver.malformed == 1
    finally:
        receiver.shutdown()
        sender.shutdown()
