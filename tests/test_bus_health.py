"""What the daemon tells about its bus besides failures: frames the kernel dropped from a
full receive queue (sk_drops, as SO_RXQ_OVFL reports them), datagrams that are no frame, and
a bus that has gone silent."""

from __future__ import annotations

import socket
import time

import can

from slipd.daemon.loop import Daemon, DaemonConfig, receive_overflows
from slipd.profile import load_profile

PROFILE = load_profile("default")


def _overflowing_socket() -> tuple[socket.socket, int]:
    """A loopback UDP socket whose receive queue overflowed: the kernel counts the frames
    it dropped in sk_drops as for a CAN raw socket (this machine's kernel has no CAN)."""
    receiver = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    receiver.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 2048)
    receiver.bind(("127.0.0.1", 0))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
        for _ in range(500):
            sender.sendto(bytes(16), receiver.getsockname())
    return receiver, receive_overflows(type("Bus", (), {"socket": receiver})())


def test_the_kernels_receive_drops_are_read():
    receiver, drops = _overflowing_socket()
    receiver.close()
    assert drops is not None and 0 < drops < 500
    assert receive_overflows(type("Bus", (), {})()) is None  # python-can's virtual bus


class _SocketBus:
    """python-can's virtual bus with a kernel socket to count drops on (as SocketCAN has)."""

    def __init__(self, channel: str, sock: socket.socket) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.socket = sock
        self.malformed = 0

    def recv(self, timeout=None):
        return self.bus.recv(timeout)

    def send(self, message, timeout=None):
        self.bus.send(message, timeout)

    def shutdown(self):
        self.bus.shutdown()


def test_drops_malformed_datagrams_and_silence_are_counted_and_logged():
    receiver, drops = _overflowing_socket()
    bus = _SocketBus("health", receiver)
    bus.malformed = 2
    logged: list[str] = []
    config = DaemonConfig(profile=PROFILE, estimator="zero", interface="virtual",
                          channel="health", duration=2.5, silence_warning_s=1.0)
    daemon = Daemon(config, bus=bus, log=logged.append)
    try:
        final = daemon.run()
    finally:
        bus.shutdown()
        receiver.close()
    assert final["counters"]["rx_overflows"] == drops > 0
    assert final["counters"]["rx_malformed"] == 2
    events = final["bus_events"]
    assert any(f"the kernel dropped {drops} frame(s)" in e for e in events), events
    assert any("2 received datagram(s) were no CAN frame" in e for e in events), events
    silent = [e for e in events if "no frames for" in e]
    assert len(silent) == 1 and "since start" in silent[0], events  # once, not every second
    assert any("no frames for" in line for line in logged)


def test_frames_again_after_a_silence_is_logged():
    import threading

    feeder = can.Bus(interface="virtual", channel="health-again")
    bus = can.Bus(interface="virtual", channel="health-again")
    logged: list[str] = []
    config = DaemonConfig(profile=PROFILE, estimator="zero", interface="virtual",
                          channel="health-again", duration=4.0, silence_warning_s=1.0)
    daemon = Daemon(config, bus=bus, log=logged.append)

    def feed_late() -> None:  # silent for 2 s, then a frame every 10 ms
        daemon.ready.wait(60)
        time.sleep(2.0)
        while daemon.running:
            feeder.send(can.Message(arbitration_id=0x100, data=bytes(8), is_extended_id=False))
            time.sleep(0.01)

    thread = threading.Thread(target=feed_late)
    thread.start()
    try:
        final = daemon.run()
    finally:
        thread.join()
        bus.shutdown()
        feeder.shutdown()
    events = final["bus_events"]
    silent = [k for k, e in enumerate(events) if "no frames for" in e]
    again = [k for k, e in enumerate(events) if "frames again" in e]
    assert silent and again and silent[0] < again[0], events
