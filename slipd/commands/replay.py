"""``slipd replay``: logs offline through the estimators, or onto a bus in real time."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from slipd.estimators import registry


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("logs", nargs="+", type=Path, metavar="LOG",
                        help="candump -L log(s) (.log, .log.gz) or .asc/.blf/.trc/.mf4/.csv; "
                             "a quoted glob ('logs/**/*.log') is expanded by slipd")
    parser.add_argument("--profile", default="default",
                        help="vehicle profile name or TOML path (default: default)")
    parser.add_argument("--estimator", default=registry.DEFAULT_ESTIMATOR,
                        help="method name, comma-separated names, or 'all' "
                             f"(default: {registry.DEFAULT_ESTIMATOR}); "
                             "METHOD:KEY=VALUE[:KEY=VALUE...] runs a method with parameters "
                             "set (kinematic_heuristic:steady_gain=0: the paper's observer)")
    parser.add_argument("--out", type=Path,
                        help="write per-tick estimates to FILE.csv (+ FILE.csv.meta.json), "
                             "FILE.parquet, FILE.mcap (inputs, estimates and truth as topics, "
                             "for Foxglove) or FILE.mf4 (with several logs, a directory of one "
                             "file per log, see --format)")
    parser.add_argument("--format", choices=("csv", "parquet", "mcap", "mf4"), default="csv",
                        help="format of the per-log files when --out is a directory")
    parser.add_argument("--truth", type=Path, metavar="TRUTH.csv",
                        help="truth CSV to add to an MCAP or MF4 --out (default: the log's "
                             "LOG.truth.csv when it exists)")
    parser.add_argument("--candump", type=Path, metavar="OUT.log",
                        help="write the input merged with slipd's output frames")
    parser.add_argument("--skip-bad", action="store_true",
                        help="count and skip malformed log lines instead of failing")
    parser.add_argument("--jobs", type=int, default=0,
                        help="parallel processes for several logs on this machine, a file per "
                             "log in the --out directory (default: CPU count)")
    fleet = parser.add_argument_group("many logs on a Dask cluster (slipd.replay.fleet)")
    fleet.add_argument("--dask", metavar="local[:N]|tcp://HOST:PORT",
                       help="one task per log on dask.distributed: a local cluster of N "
                            "workers (default: one per CPU) or a running scheduler; --out DIR "
                            "gets a Parquet dataset (DIR/estimates/log=KEY/) and "
                            "DIR/summary.parquet")
    fleet.add_argument("--resume", action="store_true",
                       help="with --dask: skip the logs whose partition in --out DIR holds "
                            "this run of them already")
    parser.add_argument("--chunk-mb", type=float, default=None, metavar="MB",
                        help="log text decoded per chunk (default 2): replay memory is "
                             "bounded by the chunk, not the log")
    player = parser.add_argument_group("real-time player")
    player.add_argument("--realtime", action="store_true",
                        help="play the log onto a bus with its timing instead of estimating")
    player.add_argument("-i", "--interface", default="socketcan",
                        help="python-can interface (socketcan, virtual, ...)")
    player.add_argument("-c", "--channel", default="vcan0", help="bus channel (default vcan0)")
    player.add_argument("--fd", action="store_true", help="open the bus for CAN FD frames")
    player.add_argument("--speed", type=float, default=1.0, help="time scale (2 = twice as fast)")
    player.add_argument("--loop", action="store_true", help="repeat the log until interrupted")
    player.add_argument("--map", action="append", default=[], metavar="WRITE=LOG",
                        help="play frames logged on channel LOG onto bus channel WRITE "
                             "(canplayer's order: vcan1=can0)")
    parser.add_argument("--bus", action="append", default=[], metavar="BUS=CHANNEL",
                        help="estimate from the log's channel CHANNEL as the profile's bus BUS "
                             "(as slipd run --bus); two channels are never merged")


def _methods(name: str) -> list[str]:
    from slipd.estimators.registry import parse_names

    return parse_names(name)  # an unknown name fails here, naming the available ones


def replay_one(log: Path, profile_name: str, methods: list[str], out: Path | None,
               candump: Path | None, skip_bad: bool, bus_map: dict | None = None,
               truth: Path | None = None, chunk_bytes: int | None = None) -> str:
    """Replay one log, streaming (slipd.replay.stream: memory bounded by a chunk); returns
    the summary text. The figures are end to end: read, decode, estimate and write."""
    import time

    from slipd.estimators import registry
    from slipd.profile import load_profile
    from slipd.replay.ahead import ahead
    from slipd.replay.stream import CHUNK_BYTES, LogStream, keep_freed_memory

    keep_freed_memory()
    started = time.perf_counter()
    profile = load_profile(profile_name)
    for name in methods:
        registry.load(name)  # unknown names fail before the log is read
    stream = LogStream(log, profile, methods, skip_bad, bus_map, chunk_bytes or CHUNK_BYTES)
    sinks = _Sinks(log, profile, methods, out, candump, truth)
    try:
        for chunk in ahead(stream, 1, f"estimate {log}"):  # estimated a chunk ahead of
            sinks.add(chunk, stream)  # the files written here (pyarrow releases the GIL)
        if stream.read.frames == 0:  # a replay of nothing must not report success
            from slipd.replay.candump import LogFormatError

            raise LogFormatError(f"{log}: no CAN frames in it (empty"
                                 f"{', or every line skipped' if stream.read.bad_lines else ''})")
        sinks.close(stream)
    except BaseException:
        sinks.abort()
        raise
    elapsed = time.perf_counter() - started
    read = stream.read
    lines = [f"{log}: {read.frames} frames, {stream.ticks} ticks, {elapsed:.2f} s "
             f"({read.frames / max(elapsed, 1e-9) / 1e6:.2f} M frames/s)"]
    if read.bad_lines:
        lines.append(f"  skipped {read.bad_lines} malformed line(s), first at line(s) "
                     f"{read.bad_line_numbers[:10]}")
    for name, counts in stream.errors.items():
        rejected = {k: v for k, v in counts.items() if k != "accepted" and v}
        if rejected:
            lines.append(f"  {name}: rejected {rejected}")
    for name in methods:
        share = sinks.valid[name] / stream.ticks if stream.ticks else 0.0
        lines.append(f"  {name}: {share * 100:.1f} % of ticks valid")
    return "\n".join(lines + sinks.notes)


class _Sinks:
    """Where a streamed replay's chunks go: the --out writer (opened at the first chunk, when
    the log's first time is known), the --candump merge, the VALID counts."""

    def __init__(self, log: Path, profile, methods: list[str], out: Path | None,
                 candump: Path | None, truth: Path | None):
        from slipd.errors import ConfigError
        from slipd.sim.writer import truth_path_of

        self.log, self.profile, self.methods = log, profile, methods
        self.out, self.candump = out, candump
        self.valid = dict.fromkeys(methods, 0)
        self.notes: list[str] = []
        self.rich = out is not None and out.suffix.lower() in (".mcap", ".mf4")
        if truth is not None and not truth.exists():
            raise ConfigError(f"--truth {truth}: no such file")
        if truth is None and self.rich and truth_path_of(log).exists():
            truth = truth_path_of(log)
        self.truth = truth
        self.columns = None
        self.writer = None
        self.merge = None

    def add(self, chunk, stream) -> None:
        import numpy as np

        from slipd.channels import Out, Status

        if self.out is not None and self.writer is None:
            self.writer = self._open_writer(stream)
        if self.candump is not None and self.merge is None:
            self.merge = _CandumpMerge(self.candump, self.profile, self.methods[0])
        if self.writer is not None:
            if self.rich:
                self.writer.write_inputs(chunk.inputs.t, chunk.inputs.U)
            for name in self.methods:
                self.writer.write(name, chunk.inputs.t, chunk.outputs[name])
        for name in self.methods:
            status = chunk.outputs[name][:, Out.STATUS].astype(np.int64)
            self.valid[name] += int(np.count_nonzero(status & int(Status.VALID)))
        if self.merge is not None:
            self.merge.add(chunk, chunk.frames.channels)  # the names when it was read:
            # the reader runs chunks ahead, its list may have grown since

    def _open_writer(self, stream):
        from slipd.replay import writers
        from slipd.sim.writer import read_truth_csv

        if self.rich and self.truth is not None:
            data, epoch = read_truth_csv(self.truth)
            self.columns = {**data, "t": data["t"] + epoch}
        starts = ([stream.first_time] if stream.first_time is not None else []) + (
            [float(self.columns["t"][0])] if self.columns else [])
        info = writers.RunInfo(self.methods, self.profile.name, str(self.log),
                               sorted(self.profile.channels, key=int) if self.rich else [],
                               min(starts) if starts else None,
                               str(self.truth) if self.columns else "")
        return writers.open_writer(self.out, info)

    def close(self, stream) -> None:
        if self.out is not None:
            if self.writer is None:  # a log without ticks still gets its (empty) file
                self.writer = self._open_writer(stream)
            if self.columns is not None:
                self.writer.write_truth(self.columns)
            self.writer.close()
            added = (f" (+ inputs, truth {self.truth})" if self.columns else
                     " (+ inputs)" if self.rich else "")
            self.notes.append(f"  estimates -> {self.out}{added}")
        if self.merge is not None:
            self.merge.close(stream.read.channels)
            self.notes.append(f"  input + {self.methods[0]} output frames -> {self.candump}")

    def abort(self) -> None:
        if self.writer is not None:
            self.writer.abort()
        if self.merge is not None:
            self.merge.abort()


class _CandumpMerge:
    """--candump: the input frames with slipd's output frames of one method, in time order,
    written chunk by chunk (engine outputs.merge of the whole log, the same lines for a
    time-ordered log: a chunk writes what is due by its last tick, the rest waits)."""

    def __init__(self, path: Path, profile, method: str):
        from slipd.replay.writers import partial_path

        self.path, self.profile, self.method = path, profile, method
        self.partial = partial_path(path)
        self.partial.write_bytes(b"")
        self.waiting = None  # input frames after the last tick written
        self.ticks = 0

    def add(self, chunk, channels: list[str]) -> None:
        from slipd.replay import outputs
        from slipd.replay.engine import Estimate
        from slipd.replay.stream import concat_frames

        frames = concat_frames(self.waiting, chunk.frames)
        if not len(chunk.inputs.t):
            self.waiting = frames
            return
        estimate = Estimate(self.method, chunk.inputs.t, chunk.outputs[self.method])
        out = outputs.output_frames(estimate, len(channels), self.ticks, self.profile)
        self.ticks += len(chunk.inputs.t)
        due = frames.t <= chunk.inputs.t[-1]
        self._write(outputs.merge(frames.select(due), out), channels)
        self.waiting = frames.select(~due)

    def _write(self, merged, channels: list[str]) -> None:
        from slipd.replay.candump import write_candump

        if len(merged):
            write_candump(self.partial, merged.t, merged.frame_id, merged.data, merged.dlc,
                          flags=merged.flags, channel=merged.channel,
                          channels=channels + ["slipd"], append=True)

    def close(self, channels: list[str]) -> None:
        import os

        if self.waiting is not None:
            self._write(self.waiting, channels)
        os.replace(self.partial, self.path)

    def abort(self) -> None:
        self.partial.unlink(missing_ok=True)


def run(args: argparse.Namespace) -> int:
    from slipd.commands.run import parse_bus_map
    from slipd.errors import ConfigError

    if args.realtime:
        from slipd.replay.player import play_logs

        return play_logs(args)
    from slipd.replay.fleet import expand_logs

    methods = _methods(args.estimator)
    logs = expand_logs(args.logs)
    chunk_bytes = _chunk_bytes(args.chunk_mb)
    if args.dask:
        return _replay_on_dask(args, logs, methods, chunk_bytes)
    if args.resume:
        raise ConfigError("--resume goes with --dask (it skips the logs a dataset holds)")
    if len(logs) > 1 and (args.candump or args.truth):
        raise ConfigError("--candump and --truth take one log at a time")
    targets = []
    for log in logs:
        out = args.out
        if out is not None and len(args.logs) > 1:
            out.mkdir(parents=True, exist_ok=True)
            out = out / (log.name.split(".")[0] + f".{args.format}")
        targets.append((log, args.profile, methods, out, args.candump, args.skip_bad,
                        parse_bus_map(args.bus) or None, args.truth, chunk_bytes))
    if len(targets) == 1:
        print(replay_one(*targets[0]))
        return 0
    return _replay_batch(targets, args.jobs)


def _replay_batch(targets: list[tuple], jobs: int) -> int:
    """Several logs in parallel processes. A log that fails is reported and the others
    finish; the exit status is then 1. Any exception of a worker is caught here: one bad
    log's traceback must not abort a night's batch (a SlipdError prints as its message)."""
    from concurrent.futures import ProcessPoolExecutor

    from tqdm import tqdm

    from slipd.errors import SlipdError

    failed = []
    with ProcessPoolExecutor(max_workers=jobs or None) as pool:
        futures = [pool.submit(replay_one, *target) for target in targets]
        for (log, *_), future in zip(targets, tqdm(futures, desc="replay", unit="log",
                                                   file=sys.stderr), strict=True):
            try:
                print(future.result(), flush=True)
            except SlipdError as exc:
                failed.append(log)
                print(f"{log}: error: {exc}", file=sys.stderr, flush=True)
            except Exception as exc:  # noqa: BLE001 - reported with its type, batch goes on
                failed.append(log)
                print(f"{log}: error: {type(exc).__name__}: {exc}", file=sys.stderr,
                      flush=True)
    if failed:
        print(f"slipd replay: {len(failed)} of {len(targets)} logs failed: "
              f"{', '.join(str(log) for log in failed)}", file=sys.stderr)
        return 1
    return 0


def _chunk_bytes(chunk_mb: float | None) -> int | None:
    from slipd.errors import ConfigError

    if chunk_mb is None:
        return None
    if not chunk_mb > 0 or chunk_mb > 1 << 20:
        raise ConfigError(f"--chunk-mb {chunk_mb}: expected a size in MB above 0")
    return max(1 << 12, int(chunk_mb * (1 << 20)))


def _replay_on_dask(args: argparse.Namespace, logs: list[Path], methods: list[str],
                    chunk_bytes: int | None) -> int:
    """--dask: one task per log (slipd.replay.fleet); a failed log is reported and the others
    finish, the exit status is then 1."""
    from slipd.commands.run import parse_bus_map
    from slipd.errors import ConfigError
    from slipd.replay.fleet import dask_client, run_fleet, summary_lines

    if args.candump or args.truth:
        raise ConfigError("--candump and --truth take one log at a time, not --dask")
    if args.out is not None and args.out.suffix and not args.out.is_dir():
        raise ConfigError(f"--out {args.out}: with --dask, --out names a directory (the "
                          "dataset of one partition per log and summary.parquet)")
    if args.resume and args.out is None:
        raise ConfigError("--resume needs --out DIR (the dataset it resumes)")
    with dask_client(args.dask, methods, args.profile) as client:
        records = run_fleet(logs, args.profile, methods, args.out, client, args.skip_bad,
                            parse_bus_map(args.bus) or None, chunk_bytes, args.resume)
    failed = [r for r in records if r.status == "failed"]
    for record, line in zip(records, summary_lines(records), strict=True):
        print(line, file=sys.stderr if record.status == "failed" else sys.stdout, flush=True)
    if args.out is not None:
        print(f"dataset -> {args.out}/estimates, summary -> {args.out}/summary.parquet")
    if failed:
        print(f"slipd replay: {len(failed)} of {len(records)} logs failed: "
              f"{', '.join(r.log for r in failed)}", file=sys.stderr)
        return 1
    return 0
