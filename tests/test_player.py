"""The real-time player on python-can's in-process virtual bus: what goes out comes back.

Cross-process players (canplayer, socketcan) are tested in the VM (tests/vm); here the
player's own contract: every frame, in order, with the log's timing and no drift.
"""

from __future__ import annotations

import threading
import time
import uuid

import can
import numpy as np
import pytest

from slipd.errors import ConfigError
from slipd.profile import load_profile
from slipd.replay.candump import FLAG_ERROR, read_candump, write_candump
from slipd.replay.player import BusRouter, parse_map, play, to_messages


@pytest.fixture(scope="module")
def drive_log(tmp_path_factory):
    """Two seconds of a simulated drive as the car's bus carries it (~1,500 frames)."""
    from slipd.sim import simulate
    from slipd.sim.writer import write_log

    path = tmp_path_factory.mktemp("player") / "drive.log"
    write_log(path, simulate("double_lane_change", duration=2.0), load_profile("default"))
    return path


def drain(bus: can.BusABC) -> list[can.Message]:
    received = []
    while (message := bus.recv(timeout=0.0)) is not None:
        received.append(message)
    return received


def test_played_log_recorded_back_equals_the_input(drive_log):
    frames = read_candump(drive_log)
    messages = to_messages(frames)
    channel = f"player-{uuid.uuid4()}"
    with (
        can.Bus(interface="virtual", channel=channel) as sender,
        can.Bus(interface="virtual", channel=channel) as recorder,
    ):
        report = play(messages, sender)
        received = drain(recorder)

    assert report.frames == len(frames) == len(received)
    assert [m.arbitration_id for m in received] == frames.frame_id.tolist()
    assert [bytes(m.data) for m in received] == [
        bytes(row[:n]) for row, n in zip(frames.data, frames.dlc, strict=True)
    ]
    # the log's timing, without drift: the receive span equals the log span
    log_span = frames.t[-1] - frames.t[0]
    received_span = received[-1].timestamp - received[0].timestamp
    assert abs(received_span - log_span) < 0.02, (received_span, log_span)
    relative_log = frames.t - frames.t[0]
    relative_rx = np.array([m.timestamp for m in received]) - received[0].timestamp
    assert np.percentile(np.abs(relative_rx - relative_log), 99) < 0.005
    p99 = report.lateness_us.get_value_at_percentile(99)
    print(f"\n{report.summary()} (lateness p99 {p99} us)")
    assert report.lateness_us.get_total_count() == len(frames)


def test_speed_scales_the_timing(drive_log):
    frames = read_candump(drive_log)
    messages = to_messages(frames)[:400]
    with can.Bus(interface="virtual", channel=f"player-{uuid.uuid4()}") as sender:
        started = time.monotonic()
        play(messages, sender, speed=4.0)
        elapsed = time.monotonic() - started
    span = messages[-1].timestamp - messages[0].timestamp
    assert span / 4.0 <= elapsed < span / 4.0 + 0.1


def test_loop_repeats_until_stopped(drive_log):
    messages = to_messages(read_candump(drive_log))[:50]
    stop = threading.Event()
    with can.Bus(interface="virtual", channel=f"player-{uuid.uuid4()}") as sender:
        timer = threading.Timer(0.5, stop.set)
        timer.start()
        report = play(messages, sender, speed=10.0, loop=True, stop=stop, spin=False)
        timer.join()
    assert report.frames > 2 * len(messages)


def test_error_frames_are_not_sent(tmp_path):
    path = tmp_path / "errors.log"
    path.write_text(
        "(1.000000) can0 123#01\n(1.001000) can0 20000080#0000000000000000\n"
        "(1.002000) can0 124#02\n"
    )
    frames = read_candump(path)
    assert int(np.count_nonzero(frames.flags & FLAG_ERROR)) == 1
    assert [m.arbitration_id for m in to_messages(frames)] == [0x123, 0x124]


def test_map_plays_each_logged_channel_on_its_bus(tmp_path):
    path = tmp_path / "two.log"
    t = np.array([0.0, 0.001, 0.002, 0.003])
    write_candump(
        path,
        t,
        np.array([1, 2, 3, 4]),
        np.zeros((4, 1), np.uint8),
        channel=np.array([0, 1, 2, 0], np.uint8),
        channels=["can0", "can1", "can2"],
    )
    suffix = uuid.uuid4()
    mapping = parse_map([f"a-{suffix}=can0", f"b-{suffix}=can1"])  # canplayer: WRITE=LOG
    router = BusRouter("virtual", "unused", mapping)
    try:
        with (
            can.Bus(interface="virtual", channel=f"a-{suffix}") as bus_a,
            can.Bus(interface="virtual", channel=f"b-{suffix}") as bus_b,
        ):
            report = play(to_messages(read_candump(path)), router)
            assert [m.arbitration_id for m in drain(bus_a)] == [1, 4]
            assert [m.arbitration_id for m in drain(bus_b)] == [2]
    finally:
        router.shutdown()
    assert report.frames == 4 and router.unmapped == 1  # can2 is not in the map


def test_bad_map_and_speed_are_clear_errors():
    with pytest.raises(ConfigError, match="expected WRITE=LOG as canplayer takes it"):
        parse_map(["vcan0"])
    with pytest.raises(ConfigError, match="expected a number > 0"):
        play([], None, speed=0.0)


def test_replay_realtime_command_on_the_virtual_bus(drive_log, capsys):
    from slipd.cli import main

    channel = f"cli-{uuid.uuid4()}"
    with can.Bus(interface="virtual", channel=channel) as recorder:
        code = main(
            [
                "replay",
                str(drive_log),
                "--realtime",
                "--interface",
                "virtual",
                "--channel",
                channel,
                "--speed",
                "4",
            ]
        )
        received = drain(recorder)
    assert code == 0
    assert len(received) == len(read_candump(drive_log))
    out = capsys.readouterr().out
    assert "lateness us: p50" in out and "p99" in out
