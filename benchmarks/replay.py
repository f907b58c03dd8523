"""Replay throughput: read + decode + estimate a 1-hour candump log, against the library path.

The log is the simulator's mixed endurance drive cut to --hours (every input message of the
default profile at its bus rate, counters and CRCs), or any candump log given with --log.

fast path: slipd.replay (numba candump reader -> codec latch_ticks -> run_ticks).
end to end: what ``slipd replay LOG --out x.csv`` / ``x.parquet`` runs (the streaming replay:
read, decode, estimate and write the file, chunk by chunk), timed in this process once its
kernels are loaded, as the command's own "M frames/s" figure.
library path: python-can LogReader + cantools decode_message + the same estimator's step
called per tick from Python (measured on the first minutes, reported per frame).

    .venv/bin/python -m benchmarks.replay [--hours 1] [--estimator kinematic_heuristic]
"""

from __future__ import annotations

import argparse
import math
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


def cli_rate(log: Path, method: str, out: Path, repeats: int = 3) -> float:
    """Frames per second of ``slipd replay LOG --estimator METHOD --out OUT`` (best of
    ``repeats``), the command's own function and figure."""
    from slipd.commands.replay import replay_one

    best = 0.0
    for _ in range(repeats):
        started = time.perf_counter()
        summary = replay_one(log, "default", [method], out, None, False)
        elapsed = time.perf_counter() - started
        frames = int(summary.split(": ", 1)[1].split(" frames", 1)[0])
        best = max(best, frames / elapsed)
        out.unlink()
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hours", type=float, default=1.0)
    parser.add_argument("--estimator", default="kinematic_heuristic")
    parser.add_argument("--library-frames", type=int, default=100_000)
    parser.add_argument("--log", type=Path, help="benchmark this candump log instead")
    parser.add_argument("--random", action="store_true",
                        help="random signal values instead of a simulated drive (no sim extra)")
    args = parser.parse_args()
    profile = load_profile("default")
    with tempfile.TemporaryDirectory() as tmp:
        log = args.log or Path(tmp) / "bus.log"
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
        size_mb = log.stat().st_size / 1e6
        # warm-up (compile or load the numba cache) on the first frames
        warm = read_candump(log)
        run_method(latch_log(warm.select(np.arange(len(warm)) < 1000), profile), profile,
                   args.estimator)
        del warm
        timings = []
        for _ in range(3):
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
        end_to_end = {suffix: cli_rate(log, args.estimator, Path(tmp) / f"x{suffix}")
                      for suffix in (".csv", ".parquet")}
    fast_rate, slow_rate = n / total, count / slow
    hours = (frames.t[-1] - frames.t[0]) / 3600.0
    print(f"log: {hours:.2f} h, {n} frames, {len(estimate.t)} ticks, {size_mb:.0f} MB")
    print(f"slipd replay (read {read_s:.2f} s + decode/latch {latch_s:.2f} s + "
          f"{args.estimator} {est_s:.2f} s = {total:.2f} s): {fast_rate / 1e6:.2f} M frames/s")
    print(f"library path (LogReader + cantools + step per tick, {count} frames): "
          f"{slow_rate / 1e6:.3f} M frames/s")
    for suffix, rate in end_to_end.items():
        print(f"slipd replay --out x{suffix} (end to end, file written): {rate / 1e6:.2f} M "
              f"frames/s ({rate / slow_rate:.0f}x the library path, {rate / fast_rate:.2f} of "
              f"the in-memory fast path; target >= 2 M)")
    print(f"ratio: {fast_rate / slow_rate:.0f}x; a day of driving (24 h) replays in "
          f"{24 / hours * total:.0f} s")
    assert math.isfinite(fast_rate)


if __name__ == "__main__":
    main()
