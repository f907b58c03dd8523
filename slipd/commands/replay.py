"""``slipd replay``: logs offline through the estimators, or onto a bus in real time."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("logs", nargs="+", type=Path, metavar="LOG",
                        help="candump -L log(s) (.log, .log.gz) or .asc/.blf/.trc/.mf4/.csv")
    parser.add_argument("--profile", default="default",
                        help="vehicle profile name or TOML path (default: default)")
    parser.add_argument("--estimator", default="kinematic_heuristic",
                        help="method name, comma-separated names, or 'all' "
                             "(default: kinematic_heuristic)")
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
                        help="parallel processes for several logs (default: CPU count)")
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
               truth: Path | None = None) -> str:
    """Replay one log; returns the summary text."""
    import time

    from slipd.channels import Out, Status
    from slipd.estimators import registry
    from slipd.profile import load_profile
    from slipd.replay import outputs
    from slipd.replay.candump import write_candump
    from slipd.replay.engine import checked_log, latch_log_or_recording, run_method
    from slipd.replay.readers import read_frames

    started = time.perf_counter()
    profile = load_profile(profile_name)
    for name in methods:
        registry.load(name)  # unknown names fail before the log is read
    frames = checked_log(read_frames(log, skip_bad=skip_bad), skip_bad, profile)
    inputs = latch_log_or_recording(frames, profile, bus_map)
    estimates = [run_method(inputs, profile, name) for name in methods]
    elapsed = time.perf_counter() - started
    lines = [f"{log}: {len(frames)} frames, {len(inputs.t)} ticks, {elapsed:.2f} s "
             f"({len(frames) / max(elapsed, 1e-9) / 1e6:.2f} M frames/s)"]
    if frames.bad_lines:
        lines.append(f"  skipped {frames.bad_lines} malformed line(s), first at line(s) "
                     f"{frames.bad_line_numbers[:10]}")
    for name, counts in inputs.errors.items():
        rejected = {k: v for k, v in counts.items() if k != "accepted" and v}
        if rejected:
            lines.append(f"  {name}: rejected {rejected}")
    for estimate in estimates:
        status = estimate.out[:, Out.STATUS].astype(int)
        valid = ((status & Status.VALID) != 0).mean() if len(estimate.t) else 0.0
        lines.append(f"  {estimate.method}: {valid * 100:.1f} % of ticks valid")
    if out is not None:
        lines.append(_write_out(out, log, profile, methods, frames, inputs, estimates, truth))
    if candump is not None:
        channel = len(frames.channels)
        out_frames = outputs.output_frames(estimates[0], channel, profile=profile)
        merged = outputs.merge(frames, out_frames)
        write_candump(candump, merged.t, merged.frame_id, merged.data, merged.dlc,
                      flags=merged.flags, channel=merged.channel,
                      channels=frames.channels + ["slipd"])
        lines.append(f"  input + {estimates[0].method} output frames -> {candump}")
    return "\n".join(lines)


def _write_out(out: Path, log: Path, profile, methods: list[str], frames, inputs, estimates,
               truth: Path | None) -> str:
    """The --out file; an MCAP or MF4 also gets the inputs and the truth: ``truth``, else the
    log's LOG.truth.csv when it exists."""
    from slipd.errors import ConfigError
    from slipd.replay import writers
    from slipd.sim.writer import read_truth_csv, truth_path_of

    rich = out.suffix.lower() in (".mcap", ".mf4")
    if truth is not None and not truth.exists():
        raise ConfigError(f"--truth {truth}: no such file")
    if truth is None and rich and truth_path_of(log).exists():
        truth = truth_path_of(log)
    columns = None
    if rich and truth is not None:
        data, epoch = read_truth_csv(truth)
        columns = {**data, "t": data["t"] + epoch}
    starts = ([float(frames.t[0])] if len(frames) else []) + (
        [float(columns["t"][0])] if columns else [])
    info = writers.RunInfo(methods, profile.name, str(log),
                           sorted(profile.channels, key=int) if rich else [],
                           min(starts) if starts else None, str(truth) if columns else "")
    writers.write_estimates(out, estimates, info, inputs if rich else None, columns)
    added = f" (+ inputs, truth {truth})" if columns else " (+ inputs)" if rich else ""
    return f"  estimates -> {out}{added}"


def run(args: argparse.Namespace) -> int:
    from slipd.commands.run import parse_bus_map
    from slipd.errors import ConfigError

    if args.realtime:
        from slipd.replay.player import play_logs

        return play_logs(args)
    methods = _methods(args.estimator)
    if len(args.logs) > 1 and (args.candump or args.truth):
        raise ConfigError("--candump and --truth take one log at a time")
    targets = []
    for log in args.logs:
        out = args.out
        if out is not None and len(args.logs) > 1:
            out.mkdir(parents=True, exist_ok=True)
            out = out / (log.name.split(".")[0] + f".{args.format}")
        targets.append((log, args.profile, methods, out, args.candump, args.skip_bad,
                        parse_bus_map(args.bus) or None, args.truth))
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
