"""Bounded fuzzing of the codec and the candump reader (hypothesis; the long runs are
benchmarks/fuzz.py): whatever the bytes, a result or a LogFormatError, never another
exception, and what comes out is something a bus can carry."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from slipd.channels import N_IN
from slipd.codec import Codec
from slipd.codec.kernels import LATCH_SET, LATCH_VALUE
from slipd.errors import LogFormatError
from slipd.profile import load_profile
from slipd.replay.candump import FLAG_ERROR, FLAG_FD, FLAG_REMOTE, read_candump

PROFILES = {name: load_profile(name) for name in ("default", "toyota_prius")}
FD_LENGTHS = {0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64}
FUZZ = settings(max_examples=150, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow])

# pieces real lines are made of, so mutations reach deep into the parser
PIECES = ["(", ")", " ", ".", "#", "##", "R", "T", "r", "\t", "\r", "\n", "can0", "vcan1",
          "123", "7FF", "800", "1FFFFFFF", "20000080", "C0000000", "0", "00", "FF", "A5" * 8,
          "1436509052", "249713", "9" * 20, "-", "x", "\x00", "\xff"]


def _check_frames(frames) -> None:
    n = len(frames)
    assert len(frames.frame_id) == len(frames.flags) == len(frames.dlc) == n
    assert frames.line is not None and np.all(np.diff(frames.line) > 0)
    assert np.all(np.isfinite(frames.t)) and np.all(frames.t >= 0)
    for k in range(n):
        flags, dlc = int(frames.flags[k]), int(frames.dlc[k])
        if flags & FLAG_ERROR:
            assert frames.frame_id[k] == 0
            continue
        assert 0 <= frames.frame_id[k] <= 0x1FFFFFFF
        if flags & FLAG_FD:
            assert dlc in FD_LENGTHS and not flags & FLAG_REMOTE
        else:
            assert dlc <= 8
        if not flags & 1:  # standard ID
            assert frames.frame_id[k] <= 0x7FF


@FUZZ
@given(st.binary(max_size=400))
def test_random_bytes_read_or_fail_cleanly(tmp_path, content):
    path = tmp_path / "fuzz.log"
    path.write_bytes(content)
    try:
        _check_frames(read_candump(path))
    except LogFormatError as exc:
        assert str(path) in str(exc)
    _check_frames(read_candump(path, skip_bad=True))  # skipping never raises


@FUZZ
@given(st.lists(st.lists(st.sampled_from(PIECES), max_size=14).map("".join), max_size=20))
def test_line_shaped_garbage_reads_or_fails_cleanly(tmp_path, lines):
    path = tmp_path / "fuzz.log"
    path.write_bytes("\n".join(lines).encode("utf-8", "surrogateescape"))
    try:
        frames = read_candump(path)
        _check_frames(frames)
    except LogFormatError as exc:
        assert f"{path}:" in str(exc)
    skipped = read_candump(path, skip_bad=True)
    _check_frames(skipped)
    assert skipped.bad_lines == len(skipped.bad_line_numbers) or skipped.bad_lines > 100


@FUZZ
@given(profile=st.sampled_from(sorted(PROFILES)),
       frames=st.lists(st.tuples(st.integers(0, 0x1FFFFFFF), st.booleans(),
                                 st.binary(max_size=64), st.floats(0, 1e4)), max_size=60))
def test_the_codec_decodes_any_frame_without_failing(profile, frames):
    codec = Codec(PROFILES[profile])
    ids = [codec.inputs.frame_id(name) for name in codec.inputs.message_names]
    for k, (frame_id, extended, data, t) in enumerate(frames):
        if k % 2:  # half of them on the profile's IDs, where the checks run
            frame_id, extended = ids[frame_id % len(ids)], False
        result = codec.decode(frame_id, data, t, extended)
        assert result >= -2
    latch = codec.state.latch
    set_ = latch[LATCH_SET] > 0.5
    assert np.all(np.isfinite(latch[LATCH_VALUE][set_]))
    counts = codec.error_counts()
    total = sum(v for name, c in counts.items() for v in c.values())
    assert total == len(frames)
    u = codec.sample(1e4, np.zeros(2 * N_IN + 1))
    assert all(math.isfinite(x) for x in u)
