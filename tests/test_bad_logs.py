"""Logs that are wrong in the ways real files are: each is an error naming the file and the
line (never a traceback, never a silent success), `--skip-bad` skips and counts, a batch
finishes the good logs, and the player neither plays what replay refuses nor hides losses."""

from __future__ import annotations

import errno
import gzip
import socket
import time
import tracemalloc

import can
import numpy as np
import pytest

from slipd.cli import main
from slipd.errors import LogFormatError
from slipd.profile import load_profile
from slipd.replay.engine import checked_log, run_log
from slipd.replay.player import play, to_messages
from slipd.replay.readers import MAX_GAP_S, read_frames

PROFILE = load_profile("default")


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    from slipd.sim import simulate
    from slipd.sim.writer import write_log

    path = tmp_path_factory.mktemp("bad") / "drive.log"
    write_log(path, simulate("step_steer", duration=2.0), PROFILE)
    return path


def _lines(path) -> list[str]:
    return path.read_text().splitlines()


def _write(path, lines: list[str]):
    path.write_text("\n".join(lines) + "\n")
    return path


def _replay(capsys, *argv) -> tuple[int, str, str]:
    code = main(["replay", *map(str, argv), "--estimator", "zero"])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return code, out, err


def test_a_timestamp_back_in_time_names_its_own_line(drive, tmp_path):
    """The error named a frame index (not the line), and --skip-bad neither skipped nor
    counted the frame."""
    lines = _lines(drive)
    back = lines[200].replace(lines[200][1:18], f"{float(lines[199][1:18]) - 0.5:.6f}")
    lines[200] = back
    path = _write(tmp_path / "back.log", ["", *lines])  # a blank first line: line != frame
    with pytest.raises(LogFormatError, match=r"back\.log:202: timestamp .* goes back in "
                                             r"time \(line 201 has"):
        checked_log(read_frames(path))
    kept = checked_log(read_frames(path, skip_bad=True), skip_bad=True)
    assert kept.bad_lines == 1 and kept.bad_line_numbers == [202]
    assert len(kept) == len(lines) - 1
    estimates = run_log(path, PROFILE, ["zero"], skip_bad=True)
    assert len(estimates["zero"].t) > 100


def test_one_frame_a_million_seconds_later_is_refused_without_allocating(drive, tmp_path):
    """It once asked for a 42 GiB tick grid."""
    lines = _lines(drive)
    last = float(lines[-1][1:18])
    lines.append(lines[-1].replace(lines[-1][1:18], f"{last + 1e6:.6f}"))
    path = _write(tmp_path / "jump.log", lines)
    tracemalloc.start()
    with pytest.raises(LogFormatError, match=rf"jump\.log:{len(lines)}: timestamp .* "
                                             rf"more than {MAX_GAP_S:.0f} s"):
        run_log(path, PROFILE, ["zero"])
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert peak < 200 << 20
    assert len(run_log(path, PROFILE, ["zero"], skip_bad=True)["zero"].t) < 1000


@pytest.mark.parametrize("content", [b"", b"\n\n  \n"])
def test_an_empty_log_is_an_error_not_zero_frames(tmp_path, capsys, content):
    path = tmp_path / "empty.log"
    path.write_bytes(content)
    code, _, err = _replay(capsys, path)
    assert code == 2 and "empty.log: no CAN frames in it" in err


def test_every_line_skipped_is_an_error_too(tmp_path, capsys):
    path = _write(tmp_path / "junk.log", ["junk", "more junk"])
    code, _, err = _replay(capsys, path, "--skip-bad")
    assert code == 2 and "every line skipped" in err


def test_truncated_and_fake_gzip_name_the_file(drive, tmp_path, capsys):
    packed = gzip.compress(drive.read_bytes())
    (tmp_path / "cut.log.gz").write_bytes(packed[: len(packed) // 2])
    (tmp_path / "fake.log.gz").write_bytes(b"not gzip at all\n")
    for name in ("cut.log.gz", "fake.log.gz"):
        code, _, err = _replay(capsys, tmp_path / name)
        assert code == 2 and f"{name}: not a readable gzip file" in err


def test_a_garbage_blf_names_the_file(tmp_path, capsys):
    for name, content in (("short.blf", b"garbage\x00\x01"), ("random.blf",
                                                              bytes(range(256)) * 3)):
        (tmp_path / name).write_bytes(content)
        code, _, err = _replay(capsys, tmp_path / name)
        assert code == 2 and f"{name}: python-can cannot read it" in err


def test_one_bad_log_does_not_abort_a_batch(drive, tmp_path, capsys):
    bad = _write(tmp_path / "bad.log", ["(1.0) can0 123#0"])
    other = tmp_path / "other.log"
    other.write_bytes(drive.read_bytes())
    code, out, err = _replay(capsys, drive, bad, other, "--jobs", "2",
                             "--out", tmp_path / "tables")
    assert code == 1
    assert f"{bad}: error: {bad}:1:" in err and "1 of 3 logs failed" in err
    assert out.count("frames,") == 2  # both good logs finished
    assert sorted(p.name for p in (tmp_path / "tables").iterdir()
                  if p.suffix == ".csv") == ["drive.csv", "other.csv"]


def test_the_player_refuses_and_skips_what_replay_refuses(drive, tmp_path, capsys):
    lines = _lines(drive)[:50]
    lines[20] = lines[20].replace(lines[20][1:18], f"{float(lines[19][1:18]) - 1:.6f}")
    path = _write(tmp_path / "back.log", lines)
    args = ["replay", str(path), "--realtime", "--interface", "virtual", "--channel",
            "bad-player", "--speed", "100"]
    assert main(args) == 2
    assert "back.log:21: timestamp" in capsys.readouterr().err
    assert main([*args, "--skip-bad"]) == 0
    out = capsys.readouterr().out
    assert "skipped 1 malformed line(s), first at line(s) [21]" in out
    assert "played 49 frames" in out


class _FullQueueBus:
    """A bus whose transmit queue stays full (SocketCAN's ENOBUFS, as python-can raises it)."""

    def __init__(self, full_every: int) -> None:
        self.sent = 0
        self.calls = 0
        self.full_every = full_every

    def send(self, message) -> None:
        self.calls += 1
        if self.calls % self.full_every == 0:
            raise can.CanOperationError("Failed to transmit: No buffer space available",
                                        error_code=errno.ENOBUFS)
        self.sent += 1


def test_the_player_counts_and_prints_what_its_bus_dropped(drive):
    """A full transmit queue was a traceback; now it is retried briefly, then counted."""
    messages = to_messages(read_frames(drive))[:40]
    for k, message in enumerate(messages):
        message.timestamp = k * 1e-4
    always_full = _FullQueueBus(full_every=1)
    started = time.monotonic()
    report = play(messages, always_full, spin=False)
    assert report.frames == 0 and report.dropped == 40
    assert "40 frame(s) dropped" in report.summary()
    assert time.monotonic() - started < 2.0  # a bounded retry per frame, no hang
    sometimes = _FullQueueBus(full_every=3)  # each retry succeeds
    report = play(messages, sometimes, spin=False)
    assert report.frames == 40 and report.dropped == 0


def test_the_player_prints_frames_a_receiver_of_its_bus_dropped(drive, tmp_path, capsys):
    """slipd_unix counts datagrams a full receiver lost; the player said nothing of them."""
    bus_dir = tmp_path / "bus"
    listener = can.Bus(interface="slipd_unix", channel=str(bus_dir))
    listener.socket.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # a tiny queue
    try:
        assert main(["replay", str(drive), "--realtime", "--interface", "slipd_unix",
                     "--channel", str(bus_dir), "--speed", "1000"]) == 0
    finally:
        listener.shutdown()
    out = capsys.readouterr().out
    assert "the bus dropped" in out and "a receiver's queue was full" in out
    dropped = int(out.split("the bus dropped ")[1].split()[0])
    assert 0 < dropped < len(read_frames(drive))


def test_frames_without_line_numbers_are_named_by_record(tmp_path):
    asc = tmp_path / "drive.asc"
    with can.Logger(str(asc)) as writer:
        for k, t in enumerate((1.0, 2.0, 1.5)):
            writer.on_message_received(can.Message(timestamp=t, arbitration_id=0x100 + k,
                                                   data=b"\x00", is_extended_id=False))
    frames = read_frames(asc)
    assert np.array_equal(frames.line, [1, 2, 3])
    with pytest.raises(LogFormatError, match=r"drive\.asc:3: timestamp"):
        checked_log(frames)
