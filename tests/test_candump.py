"""The fast candump reader against python-can's LogReader, its errors, and the writer.

The reference is ``can.LogReader`` (CanutilsLogReader): every file here is read by both and
the frames compared field by field. Files come from three places: hand-written lines in the
shapes real tools write (candump -L, python-can's logger, cansniffer-style FD and error
frames), hypothesis-generated files mixing every frame kind, and the simulator's output.
"""

from __future__ import annotations

import gzip
import re
from pathlib import Path

import can
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from slipd.errors import LogFormatError
from slipd.replay.candump import (
    ERROR_REASONS,
    FLAG_BRS,
    FLAG_DIRECTION,
    FLAG_ERROR,
    FLAG_ESI,
    FLAG_EXTENDED,
    FLAG_FD,
    FLAG_REMOTE,
    FLAG_TX,
    count_newlines,
    parse_candump,
    read_candump,
    write_candump,
)
from slipd.replay.readers import read_frames


def assert_equal_to_library(path: Path, reference: Path | None = None) -> int:
    """Compare read_candump(path) with can.LogReader(reference or path); returns the count."""
    ours = read_candump(path)
    theirs = list(can.LogReader(str(reference or path)))
    assert len(ours) == len(theirs), f"{path}: {len(ours)} frames, LogReader {len(theirs)}"
    for k, message in enumerate(theirs):
        where = f"{path} frame {k}: {message}"
        flags = int(ours.flags[k])
        assert ours.t[k] == message.timestamp, where  # exact: same double as float(text)
        assert bool(flags & FLAG_ERROR) == message.is_error_frame, where
        if message.is_error_frame:
            # LogReader keeps nothing else of an error frame (no ID, data or channel)
            assert ours.dlc[k] == 0 and not ours.data[k].any(), where
            continue
        assert ours.frame_id[k] == message.arbitration_id, where
        assert bool(flags & FLAG_EXTENDED) == message.is_extended_id, where
        assert bool(flags & FLAG_REMOTE) == message.is_remote_frame, where
        assert bool(flags & FLAG_FD) == message.is_fd, where
        assert bool(flags & FLAG_BRS) == message.bitrate_switch, where
        assert bool(flags & FLAG_ESI) == message.error_state_indicator, where
        assert bool(flags & FLAG_TX) == (not message.is_rx), where
        assert ours.dlc[k] == message.dlc, where
        if not message.is_remote_frame:
            assert bytes(ours.data[k, : ours.dlc[k]]) == bytes(message.data), where
            assert not ours.data[k, ours.dlc[k] :].any(), where
        assert ours.channels[ours.channel[k]] == str(message.channel), where
    return len(ours)


# Lines in the shapes real tools write, one kind per line.
VARIED_LINES = [
    "(1436509052.249713) vcan0 044#2A366C2BBA",  # candump -L, standard ID
    "(1436509052.449847) vcan0 0F6#",  # zero-length data
    "(1436509052.650004) vcan0 1C5D2B0E#1122334455667788",  # extended ID
    "(1436509052.850042) can1 123#R",  # remote frame
    "(1436509053.050081) can1 123#R5",  # remote frame with DLC (python-can, candump -L)
    "(1436509053.250096) can0 12345678#r",  # extended remote, lower-case r
    "(1436509053.450118) can0 20000080#0000000000000000",  # error frame (bus error class)
    "(1436509053.650148) can0 200000C4#0004000000000000",  # error frame, other classes too
    "(1436509053.850172) can0 123##0",  # CAN FD, no payload
    "(1436509054.050187) can0 123##1" + "A5" * 12,  # FD with BRS, 12 bytes
    "(1436509054.250199) can0 1ABCDEF0##3" + "5A" * 64,  # FD BRS+ESI, 64 bytes, ext ID
    "(1436509054.450212) can0 7FF#deadbeef R",  # python-can logger: rx marker, lower-case hex
    "(1436509054.650227) can0 000#00 T",  # python-can logger: tx marker
    "(0.000001) 0 001#8d00100100820100",  # numeric channel (python-can gives an int)
    "(1.5) slcan0 100#01",  # short fraction
    "(1700000000.123456789) can0 101#02",  # nanosecond fraction: 19 digits, exact fallback
    "(99999999999.999999) can0 102#03",  # large seconds
    "(12.000000) can0 0123#04",  # 4-digit ID: LogReader calls any ID longer than 3 extended
]


def write_lines(path: Path, lines: list[str], newline: str = "\n", final: bool = True) -> Path:
    text = newline.join(lines) + (newline if final else "")
    path.write_bytes(text.encode("ascii"))
    return path


def test_varied_lines_equal_logreader(tmp_path):
    assert assert_equal_to_library(write_lines(tmp_path / "varied.log", VARIED_LINES)) == len(
        VARIED_LINES
    )


def test_crlf_blank_lines_and_no_final_newline(tmp_path):
    lines = VARIED_LINES[:5] + ["", "   "] + VARIED_LINES[5:]
    path = write_lines(tmp_path / "crlf.log", lines, newline="\r\n", final=False)
    assert assert_equal_to_library(path) == len(VARIED_LINES)


def test_gzip_equals_the_plain_file(tmp_path):
    plain = write_lines(tmp_path / "plain.log", VARIED_LINES)
    packed = tmp_path / "plain.log.gz"
    packed.write_bytes(gzip.compress(plain.read_bytes()))
    assert assert_equal_to_library(packed, reference=plain) == len(VARIED_LINES)
    via_dispatch = read_frames(packed)
    assert np.array_equal(via_dispatch.frame_id, read_candump(plain).frame_id)


def test_empty_file(tmp_path):
    path = tmp_path / "empty.log"
    path.write_bytes(b"")
    assert assert_equal_to_library(path) == 0


def test_simulated_drive_equals_logreader(tmp_path):
    from slipd.profile import load_profile
    from slipd.sim import simulate
    from slipd.sim.writer import write_log

    result = simulate("step_steer", duration=3.0)
    path = tmp_path / "drive.log"
    write_log(path, result, load_profile("default"))
    assert assert_equal_to_library(path) > 1000


# ---- hypothesis: random files mixing every frame kind

channel_names = st.sampled_from(["can0", "can1", "vcan0", "slcan0", "0", "7"])
hex_case = st.sampled_from([str.upper, str.lower])
FD_LENGTHS = [0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64]


@st.composite
def timestamps(draw) -> str:
    seconds = draw(st.integers(0, 10**11))
    digits = draw(st.sampled_from([1, 3, 6, 6, 6, 9]))
    fraction = draw(st.integers(0, 10**digits - 1))
    return f"({seconds}.{fraction:0{digits}d})"


@st.composite
def frame_texts(draw) -> str:
    case = draw(hex_case)
    kind = draw(st.sampled_from(["std", "ext", "fd", "remote", "error"]))
    extended = kind == "ext" or (kind in ("fd", "remote") and draw(st.booleans()))
    ident = draw(st.integers(0, 0x1FFFFFFF if extended else 0x7FF))
    id_text = f"{ident:08X}" if extended else f"{ident:03X}"
    if kind == "error":
        error_id = 0x20000080 | draw(st.integers(0, 0x7F)) | (draw(st.integers(0, 0xFF)) << 8)
        data = draw(st.binary(min_size=8, max_size=8))
        return case(f"{error_id:08X}#{data.hex()}")
    if kind == "remote":
        dlc = draw(st.one_of(st.just(""), st.integers(0, 8).map(str)))
        return case(f"{id_text}#R{dlc}")
    if kind == "fd":
        size = draw(st.sampled_from(FD_LENGTHS))
        fd_flags = draw(st.integers(0, 3))
        return case(f"{id_text}##{fd_flags}{draw(st.binary(min_size=size, max_size=size)).hex()}")
    return case(f"{id_text}#{draw(st.binary(max_size=8)).hex()}")


@st.composite
def log_lines(draw) -> str:
    marker = draw(st.sampled_from(["", "", " R", " T"]))
    return f"{draw(timestamps())} {draw(channel_names)} {draw(frame_texts())}{marker}"


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    lines=st.lists(log_lines(), min_size=1, max_size=40), newline=st.sampled_from(["\n", "\r\n"])
)
def test_random_files_equal_logreader(tmp_path, lines, newline):
    path = write_lines(tmp_path / "random.log", lines, newline=newline)
    assert assert_equal_to_library(path) == len(lines)


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    frames=st.lists(
        st.tuples(
            st.integers(0, 2**40),  # microseconds
            st.booleans(),  # extended
            st.integers(0, 0x1FFFFFFF),
            st.binary(max_size=8),
            st.sampled_from([0, FLAG_DIRECTION, FLAG_DIRECTION | FLAG_TX]),
            st.integers(0, 2),  # channel index
        ),
        min_size=1,
        max_size=30,
    )
)
def test_writer_round_trips_through_both_readers(tmp_path, frames):
    micros = np.array([f[0] for f in frames], dtype=np.int64)
    flags = np.array([(FLAG_EXTENDED if f[1] else 0) | f[4] for f in frames], dtype=np.uint8)
    ids = np.array([f[2] if f[1] else f[2] & 0x7FF for f in frames], dtype=np.int64)
    dlc = np.array([len(f[3]) for f in frames], dtype=np.uint8)
    data = np.zeros((len(frames), 8), dtype=np.uint8)
    for k, f in enumerate(frames):
        data[k, : len(f[3])] = np.frombuffer(f[3], dtype=np.uint8)
    channel = np.array([f[5] for f in frames], dtype=np.uint8)
    path = tmp_path / "written.log"
    write_candump(
        path,
        micros / 1e6,
        ids,
        data,
        dlc=dlc,
        flags=flags,
        channel=channel,
        channels=["can0", "can1", "vcan0"],
    )
    assert assert_equal_to_library(path) == len(frames)
    back = read_candump(path)
    assert np.array_equal(np.round(back.t * 1e6).astype(np.int64), micros)
    assert np.array_equal(back.frame_id, ids)
    assert np.array_equal(back.data, data)
    assert np.array_equal(back.flags, flags)


# ---- malformed input: the error names the file, the line and what was expected

MALFORMED = {
    1: "1436509052.249713) can0 123#00",
    2: "(1436509052,249713) can0 123#00",
    3: "(1436509052.249713)can0 123#00",
    4: "(1436509052.249713) can0",
    5: "(1436509052.249713) can0 12G#00",
    6: "(1436509052.249713) can0 123456789#00",
    7: "(1436509052.249713) can0 123#0",
    8: "(1436509052.249713) can0 123##0" + "00" * 65,
    9: "(1436509052.249713) can0 123#00 X",
    11: "(1436509052.249713) can0 123##G00",
    12: "(1436509052.249713) can0 123#R99",
    13: "(14365090522497130000000000000.0) can0 123#00",  # a 29-digit timestamp
    14: "(1436509052.249713) can0 FFF#00",  # no standard ID is above 7FF
    15: "(1436509052.249713) can0 C0000123#00",  # EFF|RTR flags written into the ID
    16: "(1436509052.249713) can0 123##0" + "00" * 9,  # CAN FD has no 9-byte frames
    17: "(1436509052.249713) can0 123#" + "00" * 10,  # a classic frame of 10 bytes
}


@pytest.mark.parametrize("code", sorted(MALFORMED))
def test_malformed_line_names_file_line_and_expectation(tmp_path, code):
    lines = [VARIED_LINES[0], VARIED_LINES[1], MALFORMED[code], VARIED_LINES[2]]
    path = write_lines(tmp_path / "bad.log", lines)
    with pytest.raises(LogFormatError) as failure:
        read_candump(path)
    message = str(failure.value)
    assert f"{path}:3:" in message
    assert ERROR_REASONS[code] in message
    assert MALFORMED[code][:20] in message

    skipped = read_candump(path, skip_bad=True)
    assert skipped.bad_lines == 1 and skipped.bad_line_numbers == [3]
    good = write_lines(tmp_path / "good.log", lines[:2] + lines[3:])
    assert_equal_to_library(good)
    reference = read_candump(good)
    assert np.array_equal(skipped.frame_id, reference.frame_id)
    assert np.array_equal(skipped.data, reference.data)
    assert np.array_equal(skipped.t, reference.t)


def test_too_many_channels_is_an_error(tmp_path):
    lines = [f"(1.000000) can{k} 123#00" for k in range(65)]
    path = write_lines(tmp_path / "channels.log", lines)
    with pytest.raises(LogFormatError, match=rf"{path}:65: {ERROR_REASONS[10]}"):
        read_candump(path)


def test_skip_bad_keeps_exact_timestamps_of_long_lines_after_bad_ones(tmp_path):
    # a skipped line starting with '(' must not shift which line a long timestamp is re-read
    # from (the exact re-parse is by line number)
    lines = ["(5.0) can0 123#0", "(1700000000.123456789) can0 101#02", "(7.5) can0 102#03"]
    path = write_lines(tmp_path / "mixed.log", lines)
    frames = read_candump(path, skip_bad=True)
    assert frames.bad_line_numbers == [1]
    assert frames.t.tolist() == [1700000000.123456789, 7.5]


def test_more_long_timestamps_than_the_kernel_keeps_are_all_exact(tmp_path):
    """The kernel keeps the first 64 frames whose timestamp it cannot convert exactly (19+
    digits: nanoseconds); a block with more is parsed again with room for all of them."""
    stamps = [f"1700000000.{k:09d}" for k in range(0, 300_000_000, 1_000_003)]
    lines = [f"({s}) can0 101#{k % 256:02X}" for k, s in enumerate(stamps)]
    frames = read_candump(write_lines(tmp_path / "nanoseconds.log", lines))
    assert len(stamps) > 64 and frames.t.tolist() == [float(s) for s in stamps]
    assert frames.line.tolist() == list(range(1, len(lines) + 1))


@settings(max_examples=200, deadline=None)
@given(text=st.binary(max_size=200).map(lambda b: b.replace(b"\x00", b"\n")),
       newline_heavy=st.booleans(), start=st.integers(0, 9))
def test_newlines_counted_by_words_are_numpy_s_count(text, newline_heavy, start):
    """The 8-byte count at every alignment (a slice's start), on every byte value next to
    newlines (0x0A +- 1, 0x8A: the bits the word trick looks at)."""
    if newline_heavy:
        text = bytes(b if b % 3 else 10 for b in text) + b"\x0b\x09\x8a\n"
    buf = np.frombuffer(bytes(20) + text, dtype=np.uint8)[20 - start:]
    assert count_newlines(buf) == np.count_nonzero(buf == 10)


def test_missing_file_and_unknown_format(tmp_path):
    with pytest.raises(LogFormatError, match="no such file"):
        read_candump(tmp_path / "absent.log")
    (tmp_path / "x.xyz").write_text("")
    with pytest.raises(LogFormatError, match="unknown log format"):
        read_frames(tmp_path / "x.xyz")


def test_replay_command_reports_the_bad_line(tmp_path, capsys):
    from slipd.cli import main

    path = write_lines(tmp_path / "bad.log", [VARIED_LINES[0], MALFORMED[7]])
    assert main(["replay", str(path), "--estimator", "zero"]) == 2
    err = capsys.readouterr().err
    assert f"{path}:2:" in err and "--skip-bad" in err


def test_other_formats_go_through_python_can(tmp_path):
    asc = tmp_path / "drive.asc"
    messages = [
        can.Message(
            timestamp=1.0 + k / 100,
            arbitration_id=0x100 + k % 3,
            data=bytes([k] * 4),
            is_extended_id=False,
            channel=0,
        )
        for k in range(20)
    ]
    with can.Logger(str(asc)) as writer:
        for message in messages:
            writer.on_message_received(message)
    frames = read_frames(asc)
    assert len(frames) == 20
    assert frames.frame_id.tolist() == [m.arbitration_id for m in messages]
    assert [bytes(row[:4]) for row in frames.data] == [bytes(m.data) for m in messages]


@pytest.mark.parametrize(("line", "code"), [
    ("(1.000000) can0 123#R64", 12),  # a remote frame's DLC is 0..8
    ("(1.000000) can0 123#R9", 12),
    ("(1.000000) can0 123##0R", 12),  # CAN FD has no remote frames
    ("(1.000000) can0 123##0" + "00" * 13, 16),
    ("(1.000000) can0 123##0" + "00" * 65, 8),
    ("(1.000000) can0 40000123#00", 15),
    ("(1.000000) can0 800#00", 14),
    ("(1.000000) can0 123##8" + "00" * 8, 11),  # flags nibble: BRS, ESI and FDF only
])
def test_frames_no_bus_can_carry_are_malformed(tmp_path, line, code):
    """These were accepted silently (10-byte classic frames, FD lengths 9 or 13, RTR DLC 64,
    standard ID FFF, flag bits masked off an ID)."""
    path = write_lines(tmp_path / "impossible.log", [VARIED_LINES[0], line])
    with pytest.raises(LogFormatError, match=rf":2: {re.escape(ERROR_REASONS[code])}"):
        read_candump(path)
    assert read_candump(path, skip_bad=True).bad_line_numbers == [2]


def test_the_fdf_flag_linux_writes_on_fd_frames_is_read(tmp_path):
    """Linux 6.x sets CANFD_FDF (0x04) in every FD frame's flags, so candump on an FD vcan
    writes ``##5`` for a BRS frame: refused as a bad flags nibble, it failed the VM's
    candump logs of the Hyundai CAN FD profile."""
    lines = ["(1796166122.150084) vcan0 300##58945000000000000",
             "(1796166122.160084) vcan0 301##40011223344556677"]
    path = write_lines(tmp_path / "fdf.log", lines)
    frames = read_candump(path)
    expected = list(can.CanutilsLogReader(str(path)))
    assert len(frames) == len(expected) == 2
    for k, message in enumerate(expected):
        assert frames.flags[k] & FLAG_FD and message.is_fd
        assert bool(frames.flags[k] & FLAG_BRS) == message.bitrate_switch
        assert bytes(frames.data[k, :frames.dlc[k]]) == bytes(message.data)


def test_the_error_flag_makes_an_error_frame_whatever_its_class(tmp_path):
    """SocketCAN's CAN_ERR_FLAG marks an error frame; python-can's reader also wants the
    bus-error class and reads 20000004 (a controller problem) as a data frame with ID 4."""
    path = write_lines(tmp_path / "errors.log", ["(1.000000) can0 20000004#0004000000000000"])
    frames = read_candump(path)
    assert frames.flags[0] & FLAG_ERROR and frames.frame_id[0] == 0


def test_frames_know_their_line_numbers(tmp_path):
    lines = [VARIED_LINES[0], "", "garbage", VARIED_LINES[1], VARIED_LINES[2]]
    frames = read_candump(write_lines(tmp_path / "lines.log", lines), skip_bad=True)
    assert frames.line.tolist() == [1, 4, 5]
    assert frames.where(1).endswith("lines.log:4")


# ---- the one-pass scan of the common line against the general stages

def _mutations(draw_line: str, cut: int, junk: str) -> str:
    """A line with ``junk`` put in at ``cut``: near-miss shapes the one-pass scan must hand
    to the general stages (blanks, CR, markers, odd digits, long IDs, bad bytes)."""
    cut = min(cut, len(draw_line))
    return draw_line[:cut] + junk + draw_line[cut:]


@settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    lines=st.lists(
        st.one_of(
            log_lines(),
            st.sampled_from(list(MALFORMED.values()) + VARIED_LINES),
            st.builds("{} can0 {}#{}".format, timestamps(),
                      st.sampled_from(["123", "7FF", "800", "1ABCDEF0", "1234", "123456789"]),
                      st.binary(max_size=10).map(bytes.hex)),
            st.builds(_mutations, log_lines(), st.integers(0, 60),
                      st.sampled_from([" ", "\t", "\r", "0", "#", "R", "G", ")", ".", "\x00",
                                       "00", "12345678", "\r\n"])),
        ),
        min_size=1,
        max_size=30,
    ),
    final=st.booleans(),
)
def test_one_pass_scan_reads_what_the_general_stages_read(lines, final):
    text = ("\n".join(lines) + ("\n" if final else "")).encode("ascii")
    assert_scans_agree(text)


def assert_scans_agree(text: bytes) -> None:
    """The general stages, the one-pass scan alone and with the known-shape scan (the
    default) read ``text`` to the same frames, skipped lines and errors."""
    buf = np.frombuffer(text, dtype=np.uint8)
    general = parse_candump(buf, "x.log", skip_bad=True, one_pass=False)
    fast = parse_candump(buf, "x.log", skip_bad=True, one_pass=True)
    plain = parse_candump(buf, "x.log", skip_bad=True, known_shape=False)
    counted = parse_candump(buf, "x.log", skip_bad=True, newlines=text.count(b"\n"))
    for other in (fast, plain, counted):
        for name in ("t", "frame_id", "flags", "dlc", "data", "channel", "line"):
            assert np.array_equal(getattr(other, name), getattr(general, name)), name
        assert other.channels == general.channels
        assert (other.bad_lines, other.bad_line_numbers) == (general.bad_lines,
                                                             general.bad_line_numbers)
    errors = set()
    for one_pass, known_shape in ((False, False), (True, False), (True, True)):
        try:
            parse_candump(buf, "x.log", one_pass=one_pass, known_shape=known_shape)
            errors.add(None)
        except LogFormatError as exc:
            errors.add(str(exc))
    assert len(errors) == 1


@settings(max_examples=150, deadline=None)
@given(
    base=st.builds("{} {} {}#{}".format, timestamps(), channel_names,
                   st.sampled_from(["123", "7FF", "800", "1ABCDEF0", "3FFFFFFF", "1234"]),
                   st.binary(max_size=9).map(bytes.hex)),
    changes=st.lists(st.tuples(st.integers(0, 60), st.sampled_from(
        ["", "", " ", "\t", "\r", "0", "9", "A", "g", "#", "R", ")", ".", "(", "\x00", "00",
         "12345678", "\r\n", "\n"])), min_size=1, max_size=25),
    final=st.booleans(),
)
def test_the_known_shape_scan_reads_what_the_general_stages_read(base, changes, final):
    """Runs of one line's shape, each copy changed by a byte or a few at any place: the
    known-shape scan (lines shaped as the one before) hands every near miss on."""
    lines = [base] + [_mutations(base, cut, junk) for cut, junk in changes]
    assert_scans_agree(("\n".join(lines) + ("\n" if final else "")).encode("ascii"))
