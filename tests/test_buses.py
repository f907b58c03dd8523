"""Several buses, configurable outputs, listen-only and CAN FD in the daemon and the replay
(python-can's virtual bus; the real SocketCAN versions run in tests/vm/test_buses_vm.py)."""

from __future__ import annotations

import shutil
import threading
import time
from pathlib import Path

import can
import numpy as np
import pytest

from slipd.channels import In
from slipd.codec import Codec
from slipd.daemon.loop import Daemon, DaemonConfig
from slipd.errors import ConfigError
from slipd.profile import PROFILE_DIR, load_profile
from slipd.replay.candump import FLAG_FD, FLAG_TX, read_candump
from slipd.replay.engine import latch_log, latch_log_or_recording, run_method

WHEELS = (In.WHEEL_SPEED_FL, In.WHEEL_SPEED_FR, In.WHEEL_SPEED_RL, In.WHEEL_SPEED_RR)
CHASSIS = ("IMU_ACCEL", "IMU_RATE")


def two_bus_profile(directory: Path, outputs: str = "bus = \"pt\"\nstate_id = 0x700\n"
                    "aux_id = 0x701\ndiag_id = 0x702\n") -> Path:
    """slipd.dbc's car with its IMU on bus "chassis", the rest on "pt", outputs on "pt"."""
    text = (PROFILE_DIR / "default.toml").read_text()
    for name in ("IMU_ACCEL", "IMU_RATE", "WHEEL_SPEEDS", "STEERING", "GNSS_VELOCITY",
                 "MAGNETOMETER", "WHEEL_DRIVE_TORQUE", "WHEEL_BRAKE_TORQUE"):
        bus = "chassis" if name in CHASSIS else "pt"
        text = text.replace(f"[messages.{name}]\n", f"[messages.{name}]\nbus = \"{bus}\"\n")
    text = text.replace("[channels]", f"[outputs]\n{outputs}\n[channels]")
    shutil.copy(PROFILE_DIR / "slipd.dbc", directory / "slipd.dbc")
    path = directory / "two_bus.toml"
    path.write_text(text.replace('name = "default"', 'name = "two_bus"'))
    return path


def _frames(encoder, now):
    values = {
        "IMU_ACCEL": {In.AX: 0.1, In.AY: 2.0, In.AZ: 9.81},
        "IMU_RATE": {In.YAW_RATE: 0.1, In.ROLL_RATE: 0.0, In.PITCH_RATE: 0.0},
        "STEERING": {In.STEER: 0.02, In.STEER_RATE: 0.0},
        "WHEEL_SPEEDS": dict.fromkeys(WHEELS, 20.0 + 0.5 * np.sin(now)),
    }
    for name, channels in values.items():
        frame_id, data = encoder.encode_channels(name, {c: np.array([v])
                                                        for c, v in channels.items()})
        yield name, frame_id, bytes(data[0])


def _drive(daemon, feeders, profile, seconds, swap=False):
    daemon.ready.wait(60)
    time.sleep(0.1)
    encoder = Codec(profile)
    started = time.monotonic()
    k = 0
    while (now := time.monotonic() - started) < seconds:
        for name, frame_id, data in _frames(encoder, now):
            bus = "chassis" if (name in CHASSIS) != swap else "pt"
            feeders[bus].send(can.Message(arbitration_id=frame_id, data=data,
                                          is_extended_id=False))
        k += 1
        time.sleep(max(0.0, started + k * 0.01 - time.monotonic()))


def _run(tmp_path, profile, seconds=2.0, listen_only=False, swap=False, tag="t"):
    channels = {"chassis": f"chassis-{tag}", "pt": f"pt-{tag}"}
    daemon_buses = {n: can.Bus(interface="virtual", channel=c) for n, c in channels.items()}
    feeders = {n: can.Bus(interface="virtual", channel=c) for n, c in channels.items()}
    listeners = {n: can.Bus(interface="virtual", channel=c) for n, c in channels.items()}
    config = DaemonConfig(profile=profile, estimator="zero", interface="virtual",
                          buses=channels, duration=seconds + 0.5, listen_only=listen_only,
                          recorder=tmp_path / f"{tag}.log")
    daemon = Daemon(config, bus=daemon_buses, log=lambda *_: None)
    thread = threading.Thread(target=_drive, args=(daemon, feeders, profile, seconds, swap))
    thread.start()
    final = daemon.run()
    thread.join()
    heard = {n: [] for n in channels}
    for name, bus in listeners.items():
        while (message := bus.recv(timeout=0)) is not None:
            heard[name].append(message)
    for bus in [*daemon_buses.values(), *feeders.values(), *listeners.values()]:
        bus.shutdown()
    return final, heard, daemon


def test_two_buses_outputs_on_their_ids_and_bus(tmp_path):
    profile = load_profile(two_bus_profile(tmp_path))
    final, heard, daemon = _run(tmp_path, profile, tag="two")
    outputs = [m for m in heard["pt"] if m.arbitration_id in (0x700, 0x701, 0x702)]
    assert not [m for m in heard["chassis"] if m.arbitration_id >= 0x300]  # none on chassis
    assert {m.arbitration_id for m in outputs} >= {0x700, 0x701}
    assert not [m for m in heard["pt"] if m.arbitration_id in (0x300, 0x301, 0x302)]
    counts = daemon.codec.error_counts()
    assert counts["IMU_ACCEL"]["accepted"] > 150 and counts["WHEEL_SPEEDS"]["accepted"] > 150
    states = [m for m in outputs if m.arbitration_id == 0x700]
    status = [cantools.database.load_file(str(PROFILE_DIR / "slipd.dbc")).decode_message(
        0x300, bytes(m.data))["STATUS"] for m in states[-50:]]
    assert any(int(s) & 4 == 0 for s in status)  # inputs fresh on both buses
    # the flight recording names each frame's interface and replays on the profile's buses
    recording = read_candump(tmp_path / "two.log")
    assert set(recording.channels) == {"chassis-two", "pt-two"}
    bus_map = {"chassis": "chassis-two", "pt": "pt-two"}
    inputs = latch_log_or_recording(recording, profile, bus_map)
    assert inputs.errors["IMU_RATE"]["accepted"] == counts["IMU_RATE"]["accepted"]
    assert run_method(inputs, profile, "zero").out.shape[0] == final["counters"]["ticks"]


import cantools  # noqa: E402


def test_frames_on_the_wrong_bus_are_not_decoded(tmp_path):
    profile = load_profile(two_bus_profile(tmp_path))
    _, _, daemon = _run(tmp_path, profile, seconds=1.0, swap=True, tag="swap")
    counts = daemon.codec.error_counts()
    assert counts["IMU_ACCEL"]["accepted"] == 0 and counts["WHEEL_SPEEDS"]["accepted"] == 0
    assert counts["unknown"]["unknown_id"] > 100


def test_listen_only_sends_nothing_and_still_records(tmp_path):
    profile = load_profile(two_bus_profile(tmp_path))
    final, heard, _ = _run(tmp_path, profile, listen_only=True, tag="quiet")
    assert heard["pt"] and all(m.arbitration_id < 0x300 for m in heard["pt"])  # inputs only
    assert final["counters"]["ticks"] > 150
    recording = read_candump(tmp_path / "quiet.log")
    assert np.count_nonzero((recording.flags & FLAG_TX) != 0) >= final["counters"]["ticks"]


def test_a_two_bus_profile_needs_every_bus_mapped(tmp_path):
    profile = load_profile(two_bus_profile(tmp_path))
    with pytest.raises(ConfigError, match="--bus pt=CHANNEL"):
        Daemon(DaemonConfig(profile=profile, interface="virtual", buses={"chassis": "x"}))
    with pytest.raises(ConfigError, match="has no bus 'body'"):
        Daemon(DaemonConfig(profile=profile, interface="virtual",
                            buses={"chassis": "x", "pt": "y", "body": "z"}))


def test_replay_never_merges_two_channels_onto_one_bus(tmp_path):
    from slipd.replay.candump import write_candump

    encoder = Codec(load_profile("default"))
    rows = [(0.01 * k, frame_id, data) for k in range(50)
            for _, frame_id, data in _frames(encoder, 0.01 * k)]
    t = np.array([r[0] for r in rows])
    ids = np.array([r[1] for r in rows])
    data = np.array([np.frombuffer(r[2], np.uint8) for r in rows])
    log = tmp_path / "two_channels.log"
    write_candump(log, np.concatenate([t, t + 0.0001]), np.concatenate([ids, ids]),
                  np.concatenate([data, data]), channel=np.repeat([0, 1], len(t)),
                  channels=["can0", "can1"])
    frames = read_candump(log)
    order = np.argsort(frames.t, kind="stable")
    frames = frames.select(order)
    with pytest.raises(ConfigError, match=r"channels \['can0', 'can1'\] all carry .* --bus "
                                          "main=can0"):
        latch_log(frames, load_profile("default"))
    inputs = latch_log(frames, load_profile("default"), bus_map={"main": "can1"})
    assert inputs.errors["IMU_RATE"]["accepted"] >= 49  # the last one: after the last tick
    assert inputs.errors["IMU_RATE"]["counter_repeat"] == 0


def test_can_fd_profile_on_the_daemon_with_fd_outputs(tmp_path):
    """Hyundai's 16-32 byte frames in, SLIPD_* out as CAN FD frames, the recording replays."""
    from slipd.sim import simulate
    from slipd.sim.writer import encode_frames

    profile = load_profile("hyundai_ioniq_5")
    t, ids, data, dlc = encode_frames(simulate("step_steer", profile=profile, seed=0,
                                               duration=3.0), profile, epoch=0.0)
    bus_daemon = can.Bus(interface="virtual", channel="fd-bus")
    feeder = can.Bus(interface="virtual", channel="fd-bus")
    listener = can.Bus(interface="virtual", channel="fd-bus")
    config = DaemonConfig(profile=profile, estimator="zero", interface="virtual",
                          channel="fd-bus", duration=2.5, recorder=tmp_path / "fd.log")
    daemon = Daemon(config, bus=bus_daemon, log=lambda *_: None)

    def feed():
        daemon.ready.wait(60)
        started = time.monotonic()
        for k in range(len(t)):
            time.sleep(max(0.0, started + t[k] - t[0] - time.monotonic()))
            feeder.send(can.Message(arbitration_id=int(ids[k]), is_fd=True,
                                    bitrate_switch=True, is_extended_id=False,
                                    data=bytes(data[k, :dlc[k]])))
            if time.monotonic() - started > 2.0:
                break

    thread = threading.Thread(target=feed)
    thread.start()
    final = daemon.run()
    thread.join()
    out = []
    while (message := listener.recv(timeout=0)) is not None:
        out.append(message)
    for bus in (bus_daemon, feeder, listener):
        bus.shutdown()
    counts = daemon.codec.error_counts()
    assert counts["WHEEL_SPEEDS"]["accepted"] > 100 and counts["WHEEL_SPEEDS"]["e2e"] == 0
    assert counts["ESC_02_10ms"]["accepted"] > 100
    states = [m for m in out if m.arbitration_id == 0x300]
    assert states and all(m.is_fd and m.bitrate_switch and len(m.data) == 8 for m in states)
    recording = read_candump(tmp_path / "fd.log")
    assert np.all(recording.flags[recording.dlc > 8] & FLAG_FD)
    sent = (recording.flags & FLAG_TX) != 0
    assert np.all(recording.flags[sent] & FLAG_FD)  # the outputs as FD lines too
    inputs = latch_log_or_recording(recording, profile)
    assert inputs.errors["WHEEL_SPEEDS"]["accepted"] == counts["WHEEL_SPEEDS"]["accepted"]
    assert len(inputs.t) == final["counters"]["ticks"]


def test_run_options_follow_python_can_conventions(tmp_path, monkeypatch):
    from slipd.cli import build_parser
    from slipd.commands.run import _settings

    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", "from-env")
    parser = build_parser()
    args = parser.parse_args(["run", "--config", str(tmp_path / "none.toml")])
    (tmp_path / "none.toml").write_text("")
    settings = _settings(args)
    assert settings["interface"] == "virtual" and settings["channel"] == "from-env"
    args = parser.parse_args(["run", "--config", str(tmp_path / "none.toml"), "-i",
                              "socketcan", "-c", "can7", "--bitrate", "500000", "--fd",
                              "--bus-kwargs", "receive_own_messages=true", "sjw=2",
                              "--listen-only"])
    settings = _settings(args)
    assert (settings["interface"], settings["channel"], settings["bitrate"], settings["fd"],
            settings["listen_only"]) == ("socketcan", "can7", 500000, True, True)
    assert settings["bus_kwargs"] == {"receive_own_messages": True, "sjw": 2}
    (tmp_path / "buses.toml").write_text('[buses]\nchassis = "can0"\npt = "can1"\n')
    args = parser.parse_args(["run", "--config", str(tmp_path / "buses.toml"), "--bus",
                              "pt=can2"])
    assert _settings(args)["buses"] == {"pt": "can2"}
    (tmp_path / "bad.toml").write_text("bitrate = \"fast\"\n")
    with pytest.raises(ConfigError, match="bitrate = 'fast'[:;] expected (an )?int"):
        _settings(parser.parse_args(["run", "--config", str(tmp_path / "bad.toml")]))


def test_a_simulated_drive_on_two_buses_replays_without_a_map(tmp_path):
    """slipd sim writes a several-bus profile's frames on one channel per bus, named after
    the bus, so replay needs no --bus; the recorded output IDs are the profile's."""
    from slipd.commands.replay import replay_one
    from slipd.sim import simulate
    from slipd.sim.writer import write_log

    path = two_bus_profile(tmp_path)
    profile = load_profile(path)
    log = tmp_path / "drive.log"
    write_log(log, simulate("step_steer", profile=profile, seed=0, duration=3.0), profile)
    frames = read_candump(log)
    assert frames.channels == ["chassis", "pt"]
    inputs = latch_log(frames, profile)
    assert inputs.errors["IMU_RATE"]["accepted"] > 250
    assert inputs.errors["WHEEL_SPEEDS"]["accepted"] > 250
    merged = tmp_path / "merged.log"
    replay_one(log, str(path), ["zero"], None, merged, False)
    out = read_candump(merged)
    assert np.isin(out.frame_id, [0x700, 0x701]).sum() == 2 * len(inputs.t)
