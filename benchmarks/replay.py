"""Replay throughput on the same frames: slipd end to end against asammdf and the library path.

The logs are the simulator's mixed endurance drive cut to --hours (every input message of the
default profile at its bus rate, counters and CRCs), and its first --short-minutes as a second
log; or any candump log given with --log. Each log is also written as a bus-logging MF4
(python-can's layout, benchmarks.formats.write_bus_mf4) beforehand, untimed. On each log, in
one run:

slipd end to end: what ``slipd replay LOG --estimator M --out x.parquet`` (and ``x.csv``) runs
(the streaming replay: read, decode with the E2E checks, latch, estimate, write the file,
chunk by chunk), timed in this process once its kernels are loaded, for one method and for
``all``; and the same from the MF4 (``slipd replay LOG.mf4``).
asammdf: ``MDF(LOG.mf4).extract_bus_logging({"CAN": [(DBC, 0)]})`` (open and decode only: no
E2E checks, no latch, no estimate, no file written): the peer analysts use.
candump read: the streaming reader alone (slipd.replay.stream.frame_chunks: line blocks ->
parse kernel), MB/s of log text.
fast path: slipd.replay in memory (read_candump -> latch_log -> run_method), per stage.
library path: python-can LogReader + cantools decode_message + the same estimator's step
called per tick from Python (the long log's first --library-frames frames, per frame).

    .venv/bin/python -m benchmarks.replay [--hours 1] [--short-minutes 10]
        [--estimator kinematic_heuristic] [--profile]

Each figure is the best of --repeats runs; the ratios are of figures measured in this run.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import math
import pstats
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.codec import bus_frames
from slipd.channels import N_OUT, VALID, In, Out, new_u
from slipd.codec import Codec
from slipd.estimators import registry
from slipd.profile import load_profile
from slipd.replay.candump import read_candump, write_candump
from slipd.replay.engine import latch_log, run_method


def library_path(log: Path, profile, method_name: str, limit_frames: int) -> tuple[int, float]:
    import can
    import cantools

    db = cantools.database.load_file(str(profile.dbc_path))
    method = registry.load(method_name)
    state = method.init(profile.vehicle)
    out = np.zeros(N_OUT)
    u = new_u()
    by_signal = {}
    for channel, cmap in profile.channels.items():
        for smap in cmap.signals:
            by_signal[(cmap.message, smap.name)] = (channel, smap.factor)
    names = {m.frame_id: m.name for m in db.messages}
    started = time.perf_counter()
    next_tick = None
    count = 0
    for message in can.LogReader(str(log)):
        if next_tick is None:
            next_tick = message.timestamp + 0.01
        while message.timestamp > next_tick:
            u[2 * len(In)] = next_tick
            method.step(state, u, method.params, profile.vehicle, 0.01, out)
            next_tick += 0.01
        decoded = db.decode_message(message.arbitration_id, message.data)
        name = names[message.arbitration_id]
        for signal, value in decoded.items():
            target = by_signal.get((name, signal))
            if target is not None:
                u[target[0]] = value * target[1]
                u[VALID + target[0]] = 1.0
        count += 1
        if count >= limit_frames:
            break
    return count, time.perf_counter() - started


def best_of(repeats: int, run, after=None) -> float:
    """Shortest wall time of ``repeats`` calls of ``run()`` (``after()``, untimed, after each:
    the benchmark's own clean-up)."""
    best = math.inf
    for _ in range(repeats):
        started = time.perf_counter()
        run()
        best = min(best, time.perf_counter() - started)
        if after is not None:
            after()
    return best


def cli_seconds(log: Path, methods: list[str], out: Path | None, repeats: int) -> float:
    """Wall time of ``slipd replay LOG --estimator METHODS [--out OUT]`` (best of
    ``repeats``): the command's own function."""
    from slipd.commands.replay import replay_one

    def run() -> None:
        replay_one(log, "default", methods, out, None, False)

    def remove() -> None:  # the benchmark's, not the replay's: 2 ms of a 10-minute replay
        if out is not None:
            out.unlink()

    return best_of(repeats, run, remove)


def asammdf_seconds(mf4: Path, dbc: Path, repeats: int) -> float:
    """Wall time of asammdf opening the MF4 and decoding its bus logging with the DBC."""
    from asammdf import MDF

    def run() -> None:
        with MDF(str(mf4)) as mdf:
            decoded = mdf.extract_bus_logging({"CAN": [(str(dbc), 0)]})
            if not len(decoded.channels_db):
                raise RuntimeError(f"asammdf decoded nothing of {mf4}")
            decoded.close()

    return best_of(repeats, run)


def read_seconds(log: Path, repeats: int) -> tuple[float, int]:
    """Wall time of the streaming candump reader alone, and the frames it read."""
    from slipd.replay.stream import frame_chunks

    count = 0

    def run() -> None:
        nonlocal count
        count = sum(len(frames) for frames in frame_chunks(log))

    return best_of(repeats, run), count


def write_mf4_of(log: Path, mf4: Path) -> None:
    from benchmarks.formats import START, write_bus_mf4

    frames = read_candump(log)
    if frames.data.shape[1] > 8 or (frames.flags & ~np.uint8(64 | 128)).any():
        raise SystemExit(f"{log}: the MF4 copy holds classic standard-ID data frames only")
    write_bus_mf4(mf4, frames.t - START, frames.frame_id, frames.data)


def cut_minutes(log: Path, minutes: float, out: Path) -> None:
    """The log's first ``minutes`` of frames (whole lines) as a log of its own."""
    frames = read_candump(log)
    end = int(np.searchsorted(frames.t, frames.t[0] + 60.0 * minutes, side="right"))
    lines = int(frames.line[end - 1])
    with open(log, "rb") as source, open(out, "wb") as target:
        for _ in range(lines):
            target.write(source.readline())


def profile_replay(log: Path, method: str, out: Path) -> str:
    """cProfile of one end-to-end replay: the top functions by own time."""
    from slipd.commands.replay import replay_one

    profiler = cProfile.Profile()
    profiler.enable()
    replay_one(log, "default", [method], out, None, False)
    profiler.disable()
    out.unlink()
    text = io.StringIO()
    pstats.Stats(profiler, stream=text).sort_stats("tottime").print_stats(10)
    return "\n".join(line for line in text.getvalue().splitlines()
                     if line.strip() and not line.startswith(("   Ordered", "   List")))


def stage_profile(log: Path, method: str, tmp: Path, repeats: int) -> str:
    """Each stage of the streaming replay alone (one thread, wall clock, best of
    ``repeats``) on the log's chunks, then the end-to-end run's wall clock and CPU time: how
    far the stages overlap on the machine's cores."""
    import os
    import resource

    from slipd.commands.replay import replay_one
    from slipd.replay import writers
    from slipd.replay.candump import parse_candump
    from slipd.replay.stream import Latcher, MethodRuns, ReadStats, line_blocks

    profile = load_profile("default")

    def timed(run):
        best, result = math.inf, None
        for _ in range(repeats):
            started = time.perf_counter()
            result = run()
            best = min(best, time.perf_counter() - started)
        return best, result

    read_s, blocks = timed(lambda: [(b.copy(), line, n) for b, line, n in line_blocks(log)])
    parse_s, parsed = timed(lambda: [parse_candump(b, str(log), False, line, newlines=n)
                                     for b, line, n in blocks])

    def latch():
        stats, latcher = ReadStats(str(log)), Latcher(profile, source=str(log))
        done = [latcher.feed(stats.adopt(f)) for f in parsed]  # adopt again: the same
        done.append(latcher.finish())
        return [d.inputs for d in done if d is not None]

    latch_s, inputs = timed(latch)

    def estimate():
        runs = MethodRuns(profile, [method])
        return [runs.run(i)[method] for i in inputs]

    estimate_s, outs = timed(estimate)

    def write(suffix: str):
        info = writers.RunInfo([method], "default", str(log))
        with writers.open_writer(tmp / f"stage{suffix}", info) as writer:
            for i, out in zip(inputs, outs, strict=True):
                writer.write(method, i.t, out)

    parquet_s, _ = timed(lambda: write(".parquet"))
    csv_s, _ = timed(lambda: write(".csv"))
    total = read_s + parse_s + latch_s + estimate_s + parquet_s
    lines = [f"stages of --estimator {method} --out x.parquet on {log.name}, each alone in one "
             f"thread (load {os.getloadavg()[0]:.1f}):",
             f"  read {read_s:.2f} s, parse {parse_s:.2f} s, decode/latch {latch_s:.2f} s, "
             f"estimate (method + witness + monitor) {estimate_s:.2f} s, write Parquet "
             f"{parquet_s:.2f} s (CSV {csv_s:.2f} s): {total:.2f} s in sequence"]
    for _ in range(repeats):
        before = resource.getrusage(resource.RUSAGE_SELF)
        started = time.perf_counter()
        replay_one(log, "default", [method], tmp / "x.parquet", None, False)
        wall = time.perf_counter() - started
        after = resource.getrusage(resource.RUSAGE_SELF)
        (tmp / "x.parquet").unlink()
        cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        lines.append(f"  end to end: {wall:.2f} s wall, {cpu:.2f} s CPU ({cpu / wall:.2f} "
                     f"cores busy; the stages in sequence take {total / wall:.2f}x the wall "
                     f"clock; load {os.getloadavg()[0]:.1f})")
    return "\n".join(lines)


def measure_log(log: Path, mf4: Path, args, tmp: Path) -> dict:
    """Every end-to-end figure of one log (seconds), and its size."""
    profile = load_profile("default")
    r = args.repeats
    seconds = {
        "parquet": cli_seconds(log, [args.estimator], tmp / "x.parquet", r),
        "csv": cli_seconds(log, [args.estimator], tmp / "x.csv", r),
        "none": cli_seconds(log, [args.estimator], None, r),
        "all": cli_seconds(log, registry.parse_names("all"), tmp / "x.parquet", r),
        "mf4": cli_seconds(mf4, [args.estimator], tmp / "x.parquet", r),
        "asammdf": asammdf_seconds(mf4, profile.dbc_path, r),
    }
    seconds["read"], frames = read_seconds(log, r)
    return {"seconds": seconds, "frames": frames, "mb": log.stat().st_size / 1e6,
            "mf4_mb": mf4.stat().st_size / 1e6}


def report_log(name: str, figures: dict, estimator: str, target: float) -> None:
    s, n, mb = figures["seconds"], figures["frames"], figures["mb"]

    def rate(key: str) -> str:
        return f"{s[key]:7.3f} s  {n / s[key] / 1e6:5.2f} M frames/s"

    print(f"{name}: {n} frames, {mb:.0f} MB candump text, {figures['mf4_mb']:.0f} MB MF4")
    print(f"  slipd replay --estimator {estimator} --out x.parquet  {rate('parquet')}")
    print(f"  slipd replay --estimator {estimator} --out x.csv      {rate('csv')}")
    print(f"  slipd replay --estimator {estimator} (no --out)       {rate('none')}")
    print(f"  slipd replay --estimator all --out x.parquet          {rate('all')}")
    print(f"  slipd replay LOG.mf4 --estimator {estimator} --out x.parquet  {rate('mf4')}")
    print(f"  asammdf MDF + extract_bus_logging (decode only)       {rate('asammdf')}")
    print(f"  candump read (frame_chunks)  {s['read']:7.3f} s  {mb / s['read']:6.0f} MB/s "
          f"(target >= 1000 MB/s)")
    print(f"  ratio asammdf / slipd --out x.parquet: {s['asammdf'] / s['parquet']:.2f}x "
          f"(target >= {target:g}x); from the MF4: {s['asammdf'] / s['mf4']:.2f}x; "
          f"--estimator all: {s['asammdf'] / s['all']:.2f}x")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hours", type=float, default=1.0)
    parser.add_argument("--short-minutes", type=float, default=10.0)
    parser.add_argument("--estimator", default="kinematic_heuristic")
    parser.add_argument("--library-frames", type=int, default=100_000)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--log", type=Path, help="benchmark this candump log instead")
    parser.add_argument("--random", action="store_true",
                        help="random signal values instead of a simulated drive (no sim extra)")
    parser.add_argument("--profile", action="store_true",
                        help="print where an end-to-end replay of the long log spends its time: "
                             "each stage alone, the overlap, cProfile's top functions")
    args = parser.parse_args()
    profile = load_profile("default")
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        log = args.log or tmp / "bus.log"
        if args.log is None and args.random:
            t, ids, data = bus_frames(Codec(profile), args.hours * 3600.0,
                                      np.random.default_rng(0))
            write_candump(log, t + 1.7e9, ids, data)
        elif args.log is None:
            from slipd.sim import simulate
            from slipd.sim.writer import write_log

            started = time.perf_counter()
            write_log(log, simulate("endurance", duration=args.hours * 3600.0), profile)
            print(f"simulated endurance drive ({args.hours:g} h) in "
                  f"{time.perf_counter() - started:.0f} s")
        short = tmp / "short.log"
        cut_minutes(log, args.short_minutes, short)
        for path in (log, short):  # the MF4 copies, untimed
            write_mf4_of(path, path.with_suffix(".mf4"))
        # warm-up (compile or load the numba cache, imports) on the short log
        from slipd.replay.stream import warm_kernels

        warm_kernels([args.estimator, *registry.parse_names("all")])
        measure_log(short, short.with_suffix(".mf4"), argparse.Namespace(
            repeats=1, estimator=args.estimator), tmp)
        long_figures = measure_log(log, log.with_suffix(".mf4"), args, tmp)
        short_figures = measure_log(short, short.with_suffix(".mf4"), args, tmp)
        if args.profile:
            print(stage_profile(log, args.estimator, tmp, args.repeats))
            print(profile_replay(log, args.estimator, tmp / "x.parquet"))
        timings = []
        for _ in range(args.repeats):
            started = time.perf_counter()
            frames = read_candump(log)
            read_done = time.perf_counter()
            inputs = latch_log(frames, profile)
            latch_done = time.perf_counter()
            estimate = run_method(inputs, profile, args.estimator)
            done = time.perf_counter()
            timings.append((done - started, read_done - started, latch_done - read_done,
                            done - latch_done))
        total, read_s, latch_s, est_s = min(timings)
        assert not np.isnan(estimate.out[:, Out.BETA]).all()
        n = len(frames)
        count, slow = library_path(log, profile, args.estimator, args.library_frames)
    fast_rate, slow_rate = n / total, count / slow
    hours = (frames.t[-1] - frames.t[0]) / 3600.0
    report_log(f"long log ({hours:.2f} h)", long_figures, args.estimator, 3.0)
    report_log(f"short log ({args.short_minutes:g} min)", short_figures, args.estimator, 2.0)
    print(f"fast path in memory (read {read_s:.2f} s + decode/latch {latch_s:.2f} s + "
          f"{args.estimator} {est_s:.2f} s = {total:.2f} s): {fast_rate / 1e6:.2f} M frames/s")
    print(f"library path (LogReader + cantools + step per tick, {count} frames): "
          f"{slow_rate / 1e6:.3f} M frames/s")
    long_s = long_figures["seconds"]
    for key in ("csv", "parquet"):
        rate = long_figures["frames"] / long_s[key]
        print(f"slipd replay --out x.{key} (long log, end to end, file written): "
              f"{rate / 1e6:.2f} M frames/s ({rate / slow_rate:.0f}x the library path, "
              f"{rate / fast_rate:.2f} of the in-memory fast path; target >= 2 M)")
    print(f"a day of driving (24 h) replays with --out x.parquet in "
          f"{24 / hours * long_s['parquet']:.0f} s")
    assert math.isfinite(fast_rate)


if __name__ == "__main__":
    main()
