"""The flight recorder: a full disk stops the recording, never the daemon; a restart never
overwrites the last recording; rotation keeps a configured count of compressed files that
replay."""

from __future__ import annotations

import gzip
import time

import can
import numpy as np

from slipd.daemon.loop import Daemon, DaemonConfig
from slipd.daemon.recorder import FlightRecorder, compress, rotated_name
from slipd.profile import load_profile
from slipd.replay.readers import read_frames

PROFILE = load_profile("default")


def _wait_compressed(recorder: FlightRecorder, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while recorder._compressors and time.monotonic() < deadline:
        recorder._compressors = [c for c in recorder._compressors if c.poll() is None]
        time.sleep(0.05)
    assert not recorder._compressors


def _record(recorder: FlightRecorder, n: int, start: float = 1.0) -> None:
    for k in range(n):
        recorder.frame(start + k * 0.01, 0x100 + k % 3, False, bytes([k % 256] * 8), rx=True)


def test_a_full_disk_stops_the_recording_and_the_daemon_goes_on(tmp_path):
    """The recorder on ENOSPC killed the daemon. /dev/full fails every write with ENOSPC."""
    logged: list[str] = []
    bus = can.Bus(interface="virtual", channel="rec-full")
    config = DaemonConfig(profile=PROFILE, estimator="zero", interface="virtual",
                          channel="rec-full", duration=1.5, recorder="/dev/full")
    daemon = Daemon(config, bus=bus, log=logged.append)
    final = daemon.run()
    bus.shutdown()
    assert final["counters"]["ticks"] > 100  # ran to its end
    assert final["counters"]["recorder_errors"] == 1
    assert final["recorder"]["status"].startswith("stopped: cannot write /dev/full")
    assert "No space left on device" in final["recorder"]["status"]
    faults = [line for line in logged if "flight recorder" in line]
    assert len(faults) == 1 and "estimation goes on" in faults[0]
    assert final["tool_events"] and "flight recorder" in final["tool_events"][0]


def test_a_recorder_that_cannot_open_its_file_is_reported_not_fatal(tmp_path):
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("")
    lines: list[str] = []
    recorder = FlightRecorder(blocker / "flight.log", 1 << 20, "can0", log=lines.append)
    _record(recorder, 5)  # no exception
    assert recorder.file is None and recorder.errors == 1 and lines
    recorder.close()


def test_a_restart_never_overwrites_the_last_recording(tmp_path):
    """The recorder opened with "w": Restart=on-failure overwrote the crash's recording."""
    path = tmp_path / "flight.log"
    first = FlightRecorder(path, 1 << 20, "can0")
    _record(first, 50)
    first.close()
    crashed = path.read_bytes()
    second = FlightRecorder(path, 1 << 20, "can0")  # the daemon started again
    _record(second, 10, start=10.0)
    _wait_compressed(second)
    second.close()
    kept = rotated_name(path, 1)
    assert gzip.decompress(kept.read_bytes()) == crashed
    assert len(read_frames(kept)) == 50  # replays as a log
    assert len(read_frames(path)) == 10


def test_rotation_by_size_keeps_the_configured_count(tmp_path):
    path = tmp_path / "flight.log"
    recorder = FlightRecorder(path, 2000, "can0", keep=3)
    for round_ in range(6):
        _record(recorder, 60, start=100.0 * round_)
        recorder.file.flush()
        _wait_compressed(recorder)
        recorder.maybe_rotate()
    _wait_compressed(recorder)
    recorder.close()
    rotated = sorted(p.name for p in tmp_path.iterdir() if p.name != "flight.log")
    assert rotated == ["flight.1.log.gz", "flight.2.log.gz", "flight.3.log.gz"]
    newest_rotated = read_frames(tmp_path / "flight.1.log.gz")
    assert np.isclose(newest_rotated.t[0], 500.0)  # .1 is the newest, .3 the oldest kept
    assert np.isclose(read_frames(tmp_path / "flight.3.log.gz").t[0], 300.0)


def test_compression_cut_short_leaves_a_replayable_plain_file(tmp_path):
    plain = tmp_path / "flight.1.log"
    plain.write_text("(1.000000) can0 100#00 R\n")
    partial = tmp_path / "flight.1.log.gz.partial"
    partial.write_bytes(b"\x1f\x8b")  # what a killed compressor leaves
    recorder = FlightRecorder(tmp_path / "flight.log", 1 << 20, "can0")
    recorder.close()
    assert not partial.exists() and plain.exists()
    assert compress(plain) == 0
    assert not plain.exists() and len(read_frames(tmp_path / "flight.1.log.gz")) == 1


def test_a_daemon_whose_recorder_cannot_open_still_starts(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    bus = can.Bus(interface="virtual", channel="rec-open")
    logged: list[str] = []
    config = DaemonConfig(profile=PROFILE, estimator="zero", interface="virtual",
                          channel="rec-open", duration=0.5, recorder=blocker / "flight.log")
    try:
        final = Daemon(config, bus=bus, log=logged.append).run()
    finally:
        bus.shutdown()
    counters = final["counters"]
    # it estimated through its whole duration: every 10 ms tick of the 0.5 s either ran or,
    # on a loaded machine, was skipped and counted as a miss (a fixed tick count is timing)
    assert counters["ticks"] > 0 and counters["ticks"] + counters["deadline_misses"] >= 45
    assert counters["recorder_errors"] == 1
    assert final["recorder"]["status"].startswith("stopped: cannot create the directory of")
