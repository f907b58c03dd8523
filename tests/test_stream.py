"""Streaming replay (slipd.replay.stream): a log in chunks gives the whole-log run's rows bit for
bit (every method, grid logs and a flight recording with skipped ticks), the files the CLI
writes do not depend on the chunk size, errors name the log's own lines, and the exact
formatters and sums it rests on agree with Python's."""

from __future__ import annotations

import gzip
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipd.channels import N_OUT
from slipd.cli import main
from slipd.errors import ConfigError, LogFormatError
from slipd.estimators.registry import available
from slipd.pipeline import Pipeline
from slipd.replay import outputs, textformat, writers
from slipd.replay.ahead import THREADS_VARIABLE
from slipd.replay.candump import read_candump, write_candump
from slipd.replay.engine import Estimate, latch_log_or_recording
from slipd.replay.readers import read_frames
from slipd.replay.stream import LogStream, MethodRuns, joined_inputs, line_blocks

#: chunk sizes in bytes: a few lines, a few hundred lines, the whole log
CHUNKS = (1 << 12, 1 << 16, 1 << 30)


def whole_run(log, profile, methods):
    """The whole-log path: read, latch (or a recording's ticks), Pipeline.run."""
    inputs = latch_log_or_recording(read_frames(log), profile)
    return inputs, {m: Pipeline(m, profile).run(inputs.U, inputs.steps) for m in methods}


def assert_stream_is_whole(log, profile, methods, chunk_bytes):
    inputs, outs = whole_run(log, profile, methods)
    stream = LogStream(log, profile, methods, chunk_bytes=chunk_bytes)
    chunks = list(stream)
    joined = joined_inputs(c.inputs for c in chunks)
    assert np.array_equal(joined.t, inputs.t)
    assert np.array_equal(joined.U, inputs.U, equal_nan=True)
    if inputs.steps is None:
        assert joined.steps is None
    else:
        assert np.array_equal(joined.steps, inputs.steps)
    for m in methods:
        streamed = np.concatenate([c.outputs[m] for c in chunks])
        assert np.array_equal(streamed, outs[m], equal_nan=True), m
    assert stream.errors == inputs.errors
    assert stream.read.frames == len(read_frames(log)) == sum(len(c.frames) for c in chunks)
    return chunks


@pytest.mark.parametrize("chunk_bytes", CHUNKS[:2])
@pytest.mark.parametrize("threads", ["1", "2"])
def test_every_method_streamed_equals_the_whole_log_run(codec_drives, profile, chunk_bytes,
                                                        threads, monkeypatch):
    """The codec drives (a corner, friction jumps, a drift), every registered method incl.
    the ensemble: chunk boundaries fall between ticks, between a tick and the frames that
    share its time, and inside every method's settling. With one replay thread (every stage
    in turn) and with two (stages and the methods' raw runs on threads)."""
    monkeypatch.setenv(THREADS_VARIABLE, threads)
    for drive in codec_drives.values():
        chunks = assert_stream_is_whole(drive.log, profile, available(), chunk_bytes)
        assert len(chunks) > 3


@pytest.fixture(scope="module")
def recording(tmp_path_factory, codec_drives, profile):
    """A flight-recorder log with skipped ticks: a drive merged with its SLIPD_STATE/AUX
    frames (sent, marked T) as the recorder writes them, with ticks taken out as an overrun
    skips them (5 ticks, a second, and three seconds: past the catch-up limit)."""
    drive = codec_drives["step_steer"]
    frames = read_frames(drive.log)
    inputs = latch_log_or_recording(frames, profile)
    estimate = Estimate("kinematic_heuristic", inputs.t,
                        Pipeline("kinematic_heuristic", profile).run(inputs.U))
    sent = outputs.output_frames(estimate, len(frames.channels), profile=profile)
    tick = np.repeat(np.arange(len(inputs.t)), 2)
    skipped = ((tick >= 200) & (tick < 205)) | ((tick >= 400) & (tick < 500)) | (
        (tick >= 800) & (tick < 1100))
    merged = outputs.merge(frames, sent.select(~skipped))
    path = tmp_path_factory.mktemp("recording") / "recorder.log"
    write_candump(path, merged.t, merged.frame_id, merged.data, merged.dlc, flags=merged.flags,
                  channel=merged.channel, channels=frames.channels + ["slipd"])
    return path


@pytest.mark.parametrize("chunk_bytes", CHUNKS)
def test_a_flight_recording_with_skipped_ticks_streams_as_it_replays(recording, profile,
                                                                    chunk_bytes):
    inputs, _ = whole_run(recording, profile, [])
    assert inputs.steps is not None and inputs.steps.max() == 101 and (inputs.steps == 6).any()
    assert_stream_is_whole(recording, profile, ["kinematic_heuristic", "ensemble", "zero"],
                           chunk_bytes)


def test_cli_files_do_not_depend_on_the_chunk(codec_drives, tmp_path, monkeypatch):
    """CSV bytes (the text Python's f-strings wrote before the kernel), Parquet bytes (fixed
    row groups, the methods one after another) and the merged candump, streamed in 4 KB
    chunks and in one. The small chunks' Parquet writer spills the later methods to files
    part-way (a small HOLD_BYTES), the whole run's holds them in memory."""
    pq = pytest.importorskip("pyarrow.parquet")
    monkeypatch.setattr(writers, "ROW_GROUP_TICKS", 700)  # several groups per method
    log = codec_drives["mu_jump"].log
    methods = ["zero", "kinematic_heuristic", "ensemble"]
    files = {}
    spilled, spill = [], writers.ParquetWriter._spill
    monkeypatch.setattr(writers.ParquetWriter, "_spill", lambda self, method, table: (
        spilled.append(method), spill(self, method, table)))
    for name, mb, hold in (("small", "0.004", 50_000), ("whole", "1000", writers.HOLD_BYTES)):
        monkeypatch.setattr(writers, "HOLD_BYTES", hold)
        spilled.clear()
        for suffix in (".csv", ".parquet"):
            out = tmp_path / f"{name}{suffix}"
            assert main(["replay", str(log), "--estimator", ",".join(methods), "--out",
                         str(out), "--chunk-mb", mb]) == 0
            files[name, suffix] = out.read_bytes()
        assert bool(spilled) == (name == "small"), spilled[:3]
        merged = tmp_path / f"{name}.merged.log"
        assert main(["replay", str(log), "--estimator", "dk_ekf", "--candump", str(merged),
                     "--chunk-mb", mb]) == 0
        files[name, "candump"] = merged.read_bytes()
    for kind in (".csv", ".parquet", "candump"):
        assert files["small", kind] == files["whole", kind], kind
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []
    # the CSV is the text of the per-row f-strings the writer used before
    inputs, outs = whole_run(log, load("default"), methods)
    expected = [",".join(writers.TABLE_COLUMNS) + "\n"]
    for m in methods:
        c = writers._table_values(inputs.t, outs[m])
        values = np.column_stack([c[k] for k in writers.TABLE_COLUMNS if k != "estimator"])
        expected += [textformat.python_row(row, writers.CsvWriter.DECIMALS, m, 1)
                     for row in values]
    assert files["small", ".csv"].decode() == "".join(expected)
    table = pq.read_table(tmp_path / "small.parquet")
    assert pq.ParquetFile(tmp_path / "small.parquet").num_row_groups == 3 * math.ceil(
        len(inputs.t) / 700)
    assert table["estimator"].to_pylist() == [m for m in methods for _ in inputs.t]
    assert np.array_equal(table["beta_deg"].to_numpy(),
                          np.concatenate([np.degrees(outs[m][:, 0]) for m in methods]))
    # the merged candump is the whole-log merge
    frames = read_frames(log)
    sent = outputs.output_frames(Estimate("dk_ekf", inputs.t, Pipeline(
        "dk_ekf", load("default")).run(inputs.U)), len(frames.channels), profile=load("default"))
    merged = outputs.merge(frames, sent)
    reference = tmp_path / "reference.log"
    write_candump(reference, merged.t, merged.frame_id, merged.data, merged.dlc,
                  flags=merged.flags, channel=merged.channel, channels=frames.channels + ["slipd"])
    assert files["small", "candump"] == reference.read_bytes()


def test_line_blocks_keep_a_ring_of_buffers_valid(codec_drives, tmp_path):
    """The parallel parse holds blocks while later ones are read: with a ring of k buffers a
    block stays as it was until k more have been read; the blocks are the file's lines,
    numbered, whatever the ring."""
    text = codec_drives["mu_jump"].log.read_bytes()
    path = tmp_path / "long_line.log"
    path.write_bytes(text[:5000] + b"(1.0) can0 " + b"1" * 9000 + b"\n" + text[5000:60_000])
    whole = path.read_bytes()
    for buffers in (1, 3, 4):
        held, copies = [], []
        for block, first_line, newlines in line_blocks(path, 1 << 12, buffers=buffers):
            assert first_line == whole.count(b"\n", 0, sum(map(len, copies))) + 1
            assert newlines == bytes(block).count(b"\n")
            held.append(block)
            copies.append(bytes(block))
            for old, copy in zip(held[-buffers:], copies[-buffers:], strict=True):
                assert bytes(old) == copy
        assert b"".join(copies) == whole and len(copies) > 3


def test_methods_sharing_a_witness_step_it_once(profile, codec_drives, monkeypatch):
    """The paper's d_ekf (``consistency.WITNESS``) is every other method's consistency witness
    and a method itself: one replay steps it once per tick (RawRuns), and every method's rows
    are those of its own Pipeline run alone."""
    log = codec_drives["mu_jump"].log
    witness_name = "d_ekf:slip_friction=0"
    methods = ["kinematic_heuristic", witness_name, "d_ekf", "zero", "k_kf"]
    inputs, outs = whole_run(log, profile, methods)
    runs = []
    original = Pipeline._run_method
    monkeypatch.setattr(Pipeline, "_run_method", lambda self, method, *args: (
        runs.append(method.spec.name), original(self, method, *args))[1])
    stream = LogStream(log, profile, methods, chunk_bytes=1 << 16)
    chunks = list(stream)
    for m in methods:
        streamed = np.concatenate([c.outputs[m] for c in chunks])
        assert np.array_equal(streamed, outs[m], equal_nan=True), m
    ticked = [c for c in chunks if len(c.inputs.t)]
    # per chunk: the five methods, the witness shared with its run as a method, and linear_kf
    # (the witness of both d_ekf's) once: 6 runs, not 5 + 5 witnesses
    assert sorted(runs) == sorted(["kinematic_heuristic", witness_name, "d_ekf", "zero", "k_kf",
                                   "linear_kf"] * len(ticked))
    # d_ekf with other params (the default's own friction estimate among them) is not it
    witness = Pipeline("kinematic_heuristic", profile).witness_key
    assert Pipeline(witness_name, profile).method_key == witness
    assert Pipeline("d_ekf", profile).method_key != witness
    assert Pipeline(witness_name, profile, {"r_vx": 3e-3}).method_key != witness


def test_one_replay_thread_runs_every_stage_in_the_caller(codec_drives, profile,
                                                          monkeypatch):
    """SLIPD_REPLAY_THREADS=1 (a Dask worker with a core of its own): no stage thread, no
    method pool; the same rows as with threads."""
    import threading

    log = codec_drives["mu_jump"].log
    methods = ["kinematic_heuristic", "d_ekf"]
    threaded = [c.outputs for c in LogStream(log, profile, methods, chunk_bytes=1 << 16)]
    monkeypatch.setenv(THREADS_VARIABLE, "1")
    ran_on = set()  # the threads the methods ran on
    original = Pipeline._run_method
    monkeypatch.setattr(Pipeline, "_run_method", lambda self, *args: (
        ran_on.add(threading.current_thread()), original(self, *args))[1])
    before = set(threading.enumerate())  # (an earlier test's method pool may be idle here)
    stream = LogStream(log, profile, methods, chunk_bytes=1 << 16)
    assert not stream.runs.parallel
    alone, started = [], set()
    for chunk in stream:
        alone.append(chunk.outputs)
        started.update(set(threading.enumerate()) - before)
    assert ran_on == {threading.current_thread()}
    assert not started, started
    assert len(alone) == len(threaded) > 3
    for a, b in zip(alone, threaded, strict=True):
        for m in methods:
            assert np.array_equal(a[m], b[m], equal_nan=True)


def test_the_replay_threads_setting_is_checked(monkeypatch):
    from slipd.replay.ahead import replay_threads

    for bad in ("0", "two", "-1", "1.5"):
        monkeypatch.setenv(THREADS_VARIABLE, bad)
        with pytest.raises(ConfigError, match=f"{THREADS_VARIABLE}='{bad}': expected an integer"):
            replay_threads()
    monkeypatch.setenv(THREADS_VARIABLE, " 3 ")
    assert replay_threads() == 3


def test_the_replay_kernels_release_the_gil():
    """Every kernel a replay's stage threads run releases the GIL (numba nogil): one that
    does not holds the other stages' threads while it runs, and the threads only take turns."""
    from slipd.codec import kernels
    from slipd.estimators import consistency, registry, supervision
    from slipd.replay import candump

    dispatchers = {"parse": candump._parse, "latch_ticks": kernels.latch_ticks,
                   "supervise_ticks": supervision.supervise_ticks,
                   "monitor_ticks": consistency.monitor_ticks}
    dispatchers.update({f"{name}.run_ticks": registry.load(name).run_ticks
                        for name in available()})
    holding = [name for name, kernel in dispatchers.items()
               if not kernel.targetoptions.get("nogil")]
    assert not holding


def test_a_forked_child_steps_its_methods_on_threads_of_its_own(codec_drives, profile,
                                                               monkeypatch):
    """A Dask worker forked from slipd's forkserver after the parent ran methods on its pool:
    the parent's pool threads do not exist in the child, so the child makes its own pool
    (a pool inherited by fork would take its work and never run it)."""
    import multiprocessing

    monkeypatch.setenv(THREADS_VARIABLE, "2")
    log = codec_drives["mu_jump"].log
    methods = ["kinematic_heuristic", "k_kf"]
    parent = [c.outputs for c in LogStream(log, profile, methods, chunk_bytes=1 << 16)]
    context = multiprocessing.get_context("fork")
    results = context.Queue()

    def child() -> None:
        stream = LogStream(log, profile, methods, chunk_bytes=1 << 16)
        results.put((stream.runs.parallel, [c.outputs for c in stream]))

    process = context.Process(target=child)
    process.start()
    try:
        parallel, outputs = results.get(timeout=120)
    finally:
        process.join(10)
        if process.is_alive():
            process.kill()
    assert parallel and process.exitcode == 0
    for a, b in zip(outputs, parent, strict=True):
        for m in methods:
            assert np.array_equal(a[m], b[m], equal_nan=True)


def test_methods_run_on_threads_only_where_the_pool_has_cores_to_use(profile, monkeypatch):
    """On 2 cores the other stages take one: a method and its witness (two raw runs) stay in
    the estimate thread, three or more (here 3: two methods and the shared witness) go to the
    pool; with more cores any two do; with one thread none."""
    monkeypatch.setenv(THREADS_VARIABLE, "2")
    assert not MethodRuns(profile, ["kinematic_heuristic"]).parallel  # itself and its witness
    assert MethodRuns(profile, ["kinematic_heuristic"], parallel=True).parallel
    assert MethodRuns(profile, ["kinematic_heuristic", "k_kf"]).parallel
    assert not MethodRuns(profile, ["linear_kf"], parallel=False).parallel
    monkeypatch.setenv(THREADS_VARIABLE, "4")
    assert MethodRuns(profile, ["kinematic_heuristic"]).parallel
    monkeypatch.setenv(THREADS_VARIABLE, "1")
    assert not MethodRuns(profile, ["kinematic_heuristic", "k_kf"]).parallel
    assert not MethodRuns(profile, ["kinematic_heuristic"], parallel=True).parallel


def load(name):
    from slipd.profile import load_profile

    return load_profile(name)


def _damaged(tmp_path, source, line_no: int, text: str = "(1.5) can0 12G#00"):
    lines = source.read_text().splitlines(keepends=True)
    lines.insert(line_no - 1, text + "\n")
    path = tmp_path / "damaged.log"
    path.write_text("".join(lines))
    return path


def test_a_bad_line_deep_in_the_log_is_named_by_its_own_line_number(codec_drives, profile,
                                                                    tmp_path):
    log = _damaged(tmp_path, codec_drives["step_steer"].log, 5001)
    with pytest.raises(LogFormatError) as whole:
        read_candump(log)
    with pytest.raises(LogFormatError) as streamed:
        list(LogStream(log, profile, ["zero"], chunk_bytes=1 << 12))
    assert str(streamed.value) == str(whole.value) and ":5001:" in str(whole.value)
    skipping = LogStream(log, profile, ["zero"], skip_bad=True, chunk_bytes=1 << 12)
    list(skipping)
    assert skipping.read.bad_lines == 1 and skipping.read.bad_line_numbers == [5001]
    # the CLI fails with the line and leaves no half-written table behind
    out = tmp_path / "tables" / "est.csv"
    out.parent.mkdir()
    assert main(["replay", str(log), "--out", str(out), "--chunk-mb", "0.004"]) == 2
    assert list(out.parent.iterdir()) == []


def test_a_gzip_log_streams_as_the_plain_one(codec_drives, profile, tmp_path):
    log = codec_drives["snow_drift"].log
    packed = tmp_path / "drive.log.gz"
    packed.write_bytes(gzip.compress(log.read_bytes()))
    plain = np.concatenate([c.outputs["d_ekf"] for c in LogStream(log, profile, ["d_ekf"])])
    streamed = LogStream(packed, profile, ["d_ekf"], chunk_bytes=1 << 12, checksum=True)
    got = np.concatenate([c.outputs["d_ekf"] for c in streamed])
    assert np.array_equal(got, plain, equal_nan=True)
    import hashlib

    assert streamed.read.sha256 == hashlib.sha256(log.read_bytes()).hexdigest()


def test_whole_log_decisions_contradicted_later_are_errors(codec_drives, profile, tmp_path):
    """What a stream decides on its first chunk (recording or not, which channel is the
    bus) is checked on every later one: a contradiction is an error, never a different
    replay."""
    frames = read_frames(codec_drives["step_steer"].log)
    late = frames.t >= frames.t[0] + 3.0
    # the profile's frames on a second channel from 3 s on: the bus became ambiguous
    two = tmp_path / "two.log"
    write_candump(two, frames.t, frames.frame_id, frames.data, frames.dlc,
                  channel=late.astype(np.uint8), channels=["can0", "can1"])
    with pytest.raises(ConfigError, match="--bus"):
        latch_log_or_recording(read_frames(two), profile)
    with pytest.raises(ConfigError, match="--bus"):
        list(LogStream(two, profile, ["zero"], chunk_bytes=1 << 12))
    # a slipd tick (sent SLIPD_STATE) after the first chunk
    inputs = latch_log_or_recording(frames, profile)
    estimate = Estimate("zero", inputs.t, Pipeline("zero", profile).run(inputs.U))
    sent = outputs.output_frames(estimate, 1, profile=profile)
    merged = outputs.merge(frames, sent.select(sent.t >= frames.t[0] + 3.0))
    path = tmp_path / "late_ticks.log"
    write_candump(path, merged.t, merged.frame_id, merged.data, merged.dlc, flags=merged.flags,
                  channel=merged.channel, channels=["can0", "slipd"])
    with pytest.raises(LogFormatError, match="SLIPD_STATE"):
        list(LogStream(path, profile, ["zero"], chunk_bytes=1 << 12))


def test_eval_scores_streamed_are_the_whole_logs(profile, tmp_path):
    """Exact sums: the scores of a log in 4 KB chunks are those of the whole log at once
    (metrics.errors over every tick, scored in one piece)."""
    pytest.importorskip("vehiclemodels")
    from slipd.commands.sim import simulate_to_files
    from slipd.eval.runs import score_log
    from slipd.sim.writer import truth_path_of

    simulate_to_files("mu_jump", tmp_path, duration=12.0)
    log = tmp_path / "mu_jump.log"
    methods = ["zero", "hybrid_friction", "ensemble"]
    small = score_log(log, truth_path_of(log), methods, profile, chunk_bytes=1 << 12)
    whole = score_log(log, truth_path_of(log), methods, profile, chunk_bytes=1 << 30,
                      keep=True)
    assert small.scores() == whole.scores()
    assert small.rejected_nonfinite == whole.rejected_nonfinite
    for m in methods:
        assert whole.errors[m].scores() == small.scores()[m]
        assert small.scores()[m].samples > 500


@settings(max_examples=300, deadline=None)
@given(st.lists(st.one_of(st.floats(width=64), st.floats(-1e4, 1e4, width=64),
                          st.integers(-10**7, 10**7).map(lambda k: k / 2**7)),
                min_size=1, max_size=12),
       st.integers(0, 6), st.booleans(), st.integers(-32768, 32767))
def test_the_csv_kernel_writes_what_python_formats(values, decimals, empty_if_nan, whole):
    """Any float (NaN, inf, -0.0, huge, exact binary ties such as k / 128) with 0-6 decimals,
    a NaN as an empty cell, an integer column, a text column."""
    kinds = np.array([decimals + (textformat.EMPTY_IF_NAN if empty_if_nan else 0)] * len(values)
                     + [textformat.INTEGER])
    row = np.array([*values, float(whole)])
    expected = textformat.python_row(row, kinds, "method", 1)
    assert textformat.format_csv(row[None, :], kinds, "method", 1).decode() == expected


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 10**9), st.integers(0, 6))
def test_the_csv_kernel_writes_unix_tick_times_itself(tick, decimals):
    """A log's tick times (a Unix time plus k * 10 ms) are formatted by the kernel, not left
    to Python row by row (which made the CSV writer the replay's bottleneck), and exactly; it
    defers only an exact binary tie (a cell whose value times 10**d ends in exactly .5)."""
    from fractions import Fraction

    t = np.array([[1.7e9 + 0.01 + tick * 0.01, 1_700_000_123.456789]])
    kinds = np.full(2, decimals)
    out = np.empty(textformat.row_room(kinds, b""), dtype=np.uint8)
    python_rows = np.zeros(1, dtype=np.bool_)
    used, marked = textformat.format_rows(t, kinds, np.zeros(0, np.uint8), -1, out,
                                          python_rows, np.zeros(1, np.int64))
    expected = textformat.python_row(t[0], kinds, "", -1)
    ties = [Fraction(x) * 10**decimals % 1 == Fraction(1, 2) for x in t[0].tolist()]
    assert bool(marked) == any(ties)
    if not marked:
        assert out[:used].tobytes().decode() == expected
    assert textformat.format_csv(t, kinds).decode() == expected


def test_the_csv_kernel_on_ties_and_signed_zeros():
    values = np.array([[0.125, -0.0, 2.5e-6, -1e-7, 0.5, 1e30, 123456.5, -0.000005]])
    for d in range(7):
        kinds = np.full(values.shape[1], d)
        assert textformat.format_csv(values, kinds).decode() == textformat.python_row(
            values[0], kinds, "", -1)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(min_value=-1e300, max_value=1e300, width=64), max_size=60),
       st.lists(st.integers(0, 60), max_size=5))
def test_an_exact_sum_is_fsum_however_it_is_cut(values, cuts):
    from slipd.eval.exact_sum import ExactSum

    bounds = sorted({0, len(values), *[min(c, len(values)) for c in cuts]})
    pieces = [ExactSum().add(np.array(values[a:b])) for a, b in zip(bounds, bounds[1:],
                                                                     strict=False)]
    total = ExactSum()
    for piece in pieces:
        total.merge(piece)
    assert total.value() == math.fsum(values)


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_an_aborted_table_leaves_neither_the_file_nor_its_spills(tmp_path, monkeypatch, suffix):
    """A replay that fails after the later methods spilled: abort closes every spill writer
    and removes the spill files with the partial table; nothing is left in the directory."""
    pytest.importorskip("pyarrow")
    monkeypatch.setattr(writers, "HOLD_BYTES", 0)  # Parquet spills at once, as CSV does
    path = tmp_path / f"x{suffix}"
    methods = ["zero", "d_ekf", "linear_kf"]
    writer = writers.open_writer(path, writers.RunInfo(methods))
    t = np.arange(5) * 0.01
    for _ in range(2):
        for method in methods:
            writer.write(method, t, np.zeros((5, N_OUT)))
    assert len(list(tmp_path.iterdir())) == 3  # the partial table and two spills
    writer.abort()
    assert list(tmp_path.iterdir()) == []


def test_the_replay_command_keeps_freed_chunk_memory_for_the_next_chunk(codec_drives, tmp_path,
                                                                       monkeypatch):
    """``slipd replay`` sets glibc's trim and mmap thresholds once (stream.keep_freed_memory)
    so a chunk reuses the pages the one before freed; where there is no glibc it says so."""
    import ctypes
    import platform

    from slipd.replay import stream

    monkeypatch.setattr(stream, "_KEPT", False)
    calls = []
    real = ctypes.CDLL

    class Recording:
        def __init__(self, name):
            self._libc = real(name)

        def mallopt(self, option, value):
            calls.append((option, value))
            return self._libc.mallopt(option, value)

    if platform.libc_ver()[0] != "glibc":
        assert stream.keep_freed_memory() is False
        return
    monkeypatch.setattr(ctypes, "CDLL", Recording)
    log = codec_drives["mu_jump"].log
    assert main(["replay", str(log), "--estimator", "zero", "--out",
                 str(tmp_path / "x.csv")]) == 0
    assert sorted(calls) == [(-3, stream.MMAP_THRESHOLD_BYTES), (-1, stream.TRIM_THRESHOLD_BYTES)]
    assert stream.keep_freed_memory() is True and len(calls) == 2  # once per process
