"""Fleet scale: streaming replay's memory against the whole-log path, and many logs on Dask.

memory: peak RSS of ``slipd replay LOG --estimator all --out x.parquet`` (streaming, in chunks)
on the endurance drive (~1.1 h), on two of it back to back (~2.2 h) and on a 24 h log (22 of
it, each shifted in time to follow the one before), against the whole-log path (read the
whole log, latch it, run every method on it, write the table: what ``slipd replay`` did before
streaming) measured in this run on the 1.1 h and 2.2 h logs; the 24 h whole-log run is not
attempted (it needs ~20 GB) unless --whole-24h. The streamed and the whole-log Parquet files
are compared byte for byte.

dask: N simulated logs (the suite's scenarios in turn, seeds 0, 1, ...), then N drives of
--minutes each made of them back to back (fleet logs are drives, not 10-60 s manoeuvres; the
cluster's start is a fixed cost the short logs cannot amortise), replayed sequentially in one
process (``slipd.replay.fleet.run_fleet`` without a client: the same tasks one after the
other), with the replay's stage threads and with one (``SLIPD_REPLAY_THREADS=1``), against
``slipd replay LOGS --dask local:2`` (one replay thread per worker); wall time of each command
(process start, kernel loading and the cluster's start included), the ratios, the peak RSS per
worker, and the datasets compared table by table.

    .venv/bin/python -m benchmarks.fleet [--log ENDURANCE.log] [--logs 40] [--minutes 10]
        [--skip-24h]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from slipd.replay.ahead import THREADS_VARIABLE

SLIPD = [sys.executable, "-m", "slipd.cli"]


def measured(command: list[str], env: dict[str, str] | None = None
             ) -> tuple[float, float, str]:
    """Run ``command`` (with ``env`` added to this process's environment); (wall seconds,
    peak RSS in MB of that process alone, its stdout). A failure stops the benchmark with the
    command's stderr."""
    started = time.perf_counter()
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               env={**os.environ, **(env or {})})
    # wait4 gives this child's own rusage (RUSAGE_CHILDREN would be the max over all children)
    stdout, stderr = process.stdout.read(), process.stderr.read()
    _, status, usage = os.wait4(process.pid, 0)
    process.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - started
    if process.returncode != 0:
        sys.exit(f"{' '.join(command)} failed ({process.returncode}):\n{stderr.decode()}")
    peak = usage.ru_maxrss / 1024.0
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    if peak <= own:
        # Linux records the mm a process exec()s away from in its peak: a child started
        # from this process "peaks" at this process's own peak (measured: /bin/true after
        # 700 MB here reports 725 MB), so such a figure says nothing of the command
        print(f"warning: the peak RSS of {command[-1]!r} is hidden by this process's own "
              f"({own:.0f} MB)", file=sys.stderr)
    return wall, peak, stdout.decode()


def in_child(function, *args):
    """``function(*args)`` in a fresh process: the work that reads and writes whole logs
    must not raise this process's own peak RSS, which its children's peaks inherit."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(function, *args).result()


def whole_log_replay(log: str, out: str, methods: str) -> None:
    """The whole-log path (slipd replay before streaming): every frame, every tick and every
    method's outputs in memory at once, then the table written."""
    from slipd.estimators.registry import parse_names
    from slipd.profile import load_profile
    from slipd.replay import writers
    from slipd.replay.engine import latch_log_or_recording, run_method
    from slipd.replay.readers import read_frames

    profile = load_profile("default")
    names = parse_names(methods)
    frames = read_frames(Path(log))
    inputs = latch_log_or_recording(frames, profile)
    estimates = [run_method(inputs, profile, name) for name in names]
    start = float(frames.t[0]) if len(frames) else None
    writers.write_estimates(out, estimates, writers.RunInfo(names, profile.name, log, [], start))


def concatenated(source: Path, copies: int, path: Path, gap: float = 1.0) -> Path:
    """``copies`` of a candump log one after another (``joined``, in a child process)."""
    return in_child(joined, [source] * copies, path, gap)


def joined(sources: list[Path], path: Path, gap: float = 1.0) -> Path:
    """Candump logs one after another in ``path``, each shifted in time to start ``gap`` s
    after the previous one ends (counters and CRCs as recorded: the codec sees a jump at each
    seam, as at a recorder restart)."""
    from slipd.replay.candump import read_candump, write_candump

    path.unlink(missing_ok=True)
    end = None
    for k, source in enumerate(sources):
        frames = read_candump(source)
        shift = 0.0 if end is None else end + gap - float(frames.t[0])
        write_candump(path, frames.t + shift, frames.frame_id, frames.data, frames.dlc,
                      flags=frames.flags, channel=frames.channel, channels=frames.channels,
                      append=k > 0)
        end = float(frames.t[-1]) + shift
    return path


def drives(logs: list[Path], minutes: float, folder: Path) -> list[Path]:
    """As many logs as ``logs``, each a drive of ``minutes``: log k followed by k + 1, k + 2, ...
    (in turn) until it lasts that long. Fleet logs are drives of minutes to hours; the suite's
    scenarios last 10-60 s. Read and written in one child process."""
    spans = in_child(log_spans, logs)
    folder.mkdir(parents=True, exist_ok=True)
    out, missing = [], []
    for k in range(len(logs)):
        parts, total, j = [], 0.0, k
        while total < 60.0 * minutes:
            parts.append(logs[j % len(logs)])
            total += spans[j % len(logs)] + 1.0
            j += 1
        path = folder / f"drive{k:03d}.log"
        if not path.exists():
            missing.append((parts, path))
        out.append(path)
    if missing:
        in_child(join_each, missing)
    return out


def join_each(jobs: list[tuple[list[Path], Path]]) -> None:
    """``joined(sources, path)`` for each (sources, path)."""
    for sources, path in jobs:
        joined(sources, path)


def log_spans(logs: list[Path]) -> list[float]:
    """Each log's last minus first frame time, s."""
    from slipd.replay.candump import read_candump

    return [float(f.t[-1] - f.t[0]) for f in map(read_candump, logs)]


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def memory(log: Path, tmp: Path, methods: str, long_copies: int, skip_24h: bool,
           whole_24h: bool) -> None:
    hours = in_child(log_spans, [log])[0] / 3600.0
    logs = [(f"{hours:.1f} h", log, True), (f"{2 * hours:.1f} h",
                                           concatenated(log, 2, tmp / "double.log"), True)]
    if not skip_24h:
        logs.append((f"{long_copies * hours:.0f} h",
                     concatenated(log, long_copies, tmp / "day.log"), whole_24h))
    # warm the kernels of both code paths (a cold numba cache compiles once, not in a figure)
    measured(SLIPD + ["replay", str(log), "--estimator", methods, "--chunk-mb", "0.1",
                      "--out", str(tmp / "warm.parquet")])
    peaks = {}
    for label, path, whole_too in logs:
        streamed = tmp / "streamed.parquet"
        wall, rss, _ = measured(SLIPD + ["replay", str(path), "--estimator", methods,
                                         "--out", str(streamed)])
        size = path.stat().st_size / 1e6
        peaks[label] = rss
        line = (f"replay {label} log ({size:.0f} MB) --estimator {methods} --out x.parquet: "
                f"streaming peak RSS {rss:.0f} MB ({wall:.0f} s)")
        if whole_too:
            whole = tmp / "whole.parquet"
            code = ("import sys; from benchmarks.fleet import whole_log_replay; "
                    "whole_log_replay(*sys.argv[1:])")
            w_wall, w_rss, _ = measured([sys.executable, "-c", code, str(path), str(whole),
                                         methods])
            same = sha256(streamed) == sha256(whole)
            line += (f"; whole-log path {w_rss:.0f} MB ({w_wall:.0f} s): ratio "
                     f"{rss / w_rss:.2f}; files byte-identical: {same}")
            whole.unlink()
        else:
            line += "; whole-log path not run (--whole-24h runs it: ~20 GB)"
        print(line, flush=True)
        streamed.unlink()
    first, second = list(peaks)[:2]
    print(f"peak RSS {second} / {first}: {peaks[second] / peaks[first]:.3f} "
          f"(target <= 1.10)")
    if len(peaks) > 2:
        day = list(peaks)[2]
        print(f"peak RSS of the {day} log: {peaks[day]:.0f} MB (target <= 600 MB)")


def simulated_logs(folder: Path, count: int) -> list[Path]:
    """``count`` simulated drives: the suite's scenarios but the endurance drive in turn,
    seeds 0, 1, ... (two processes simulate); those in ``folder`` already are kept."""
    from concurrent.futures import ProcessPoolExecutor

    from slipd.commands.sim import simulate_to_files
    from slipd.sim import SCENARIOS

    names = [name for name in SCENARIOS if name != "endurance"]
    jobs, logs = [], []
    for k in range(count):
        out = folder / f"seed{k // len(names)}"
        out.mkdir(parents=True, exist_ok=True)
        logs.append(out / f"{names[k % len(names)]}.log")
        if not logs[-1].exists():
            jobs.append((names[k % len(names)], out, 2, k // len(names)))
    if jobs:
        with ProcessPoolExecutor(2) as pool:
            list(pool.map(simulate_to_files, *zip(*jobs, strict=True)))
    return logs


def sequential_fleet(out: str, methods: str, *logs: str) -> None:
    """The --dask run's tasks one after another in this process (run_fleet, no client), with
    the allocator setting of the local cluster's workers."""
    from slipd.estimators.registry import parse_names
    from slipd.replay.fleet import run_fleet
    from slipd.replay.stream import keep_freed_memory

    keep_freed_memory()

    records = run_fleet([Path(p) for p in logs], "default", parse_names(methods), Path(out))
    failed = [r for r in records if r.status != "ok"]
    if failed:
        sys.exit(f"{failed[0].log}: {failed[0].error}")


def same_datasets(a: Path, b: Path) -> bool:
    import pyarrow.parquet as pq

    parts = sorted(p.relative_to(a) for p in (a / "estimates").rglob("*.parquet"))
    if parts != sorted(p.relative_to(b) for p in (b / "estimates").rglob("*.parquet")):
        return False
    for part in parts:
        x, y = pq.read_table(a / part), pq.read_table(b / part)
        if x.schema.remove_metadata() != y.schema.remove_metadata():
            return False
        for name in x.column_names:
            cx, cy = x[name].combine_chunks(), y[name].combine_chunks()
            if hasattr(cx, "dictionary"):
                cx, cy = cx.dictionary_decode(), cy.dictionary_decode()
                if cx.to_pylist() != cy.to_pylist():
                    return False
            elif (cx.is_null().to_pylist() != cy.is_null().to_pylist()
                  or cx.fill_null(0).to_numpy().tobytes() != cy.fill_null(0).to_numpy().tobytes()):
                return False
    return True


def dask(tmp: Path, count: int, methods: str, workers: int, folder: Path | None,
         minutes: float) -> None:
    """The suite-length logs, then (``minutes`` > 0) drives of that length made of them."""
    started = time.perf_counter()
    logs = simulated_logs(folder or tmp / "logs", count)
    print(f"{len(logs)} simulated logs ({sum(p.stat().st_size for p in logs) / 1e6:.0f} MB) "
          f"in {time.perf_counter() - started:.0f} s", flush=True)
    sequential_against_dask(tmp / "suite-length", logs, methods, workers)
    if minutes > 0:
        started = time.perf_counter()
        long = drives(logs, minutes, (folder or tmp / "logs") / f"drives-{minutes:g}min")
        print(f"{len(long)} drives of {minutes:g} min, the suite's scenarios back to back "
              f"({sum(p.stat().st_size for p in long) / 1e6:.0f} MB) in "
              f"{time.perf_counter() - started:.0f} s", flush=True)
        sequential_against_dask(tmp / f"{minutes:g}min", long, methods, workers)


def sequential_against_dask(tmp: Path, logs: list[Path], methods: str, workers: int) -> None:
    import pyarrow.parquet as pq

    tmp.mkdir(parents=True)
    code = ("import sys; from benchmarks.fleet import sequential_fleet; "
            "sequential_fleet(*sys.argv[1:])")
    # warm the numba cache for these methods (every run then loads it)
    measured([sys.executable, "-c", code, str(tmp / "warm"), methods, str(logs[0])])
    # sequential with the replay's stage threads (what one `slipd replay LOGS` does on this
    # machine), and with one thread (the same stages in turn: a core's work)
    seq_wall, seq_rss, _ = measured([sys.executable, "-c", code, str(tmp / "seq"), methods,
                                     *map(str, logs)])
    one_wall, one_rss, _ = measured([sys.executable, "-c", code, str(tmp / "seq1"), methods,
                                     *map(str, logs)], {THREADS_VARIABLE: "1"})
    dask_wall, client_rss, _ = measured(SLIPD + ["replay", *map(str, logs), "--estimator",
                                                 methods, "--dask", f"local:{workers}",
                                                 "--out", str(tmp / "dask")])
    summary = pq.read_table(tmp / "dask" / "summary.parquet").to_pydict()
    frames = sum(summary["frames"])
    per_worker, cpu_per_worker = {}, {}
    for worker, seconds, cpu in zip(summary["worker"], summary["seconds"],
                                    summary["cpu_seconds"], strict=True):
        per_worker[worker] = per_worker.get(worker, 0.0) + seconds
        cpu_per_worker[worker] = cpu_per_worker.get(worker, 0.0) + cpu
    rss = worker_peaks(tmp / "dask")
    for name, wall, peak, folder in (("sequential", seq_wall, seq_rss, "seq"),
                                     ("sequential, one thread", one_wall, one_rss, "seq1")):
        tasks = pq.read_table(tmp / folder / "summary.parquet").to_pydict()
        print(f"{name} (one process, {frames} frames, {tasks['threads'][0]} replay "
              f"thread(s)): {wall:.1f} s, peak RSS {peak:.0f} MB; {sum(tasks['seconds']):.1f} s "
              f"in tasks ({sum(tasks['cpu_seconds']):.1f} CPU s), "
              f"{wall - sum(tasks['seconds']):.1f} s outside them (start, imports, kernels, "
              "summary)")
    print(f"--dask local:{workers} ({summary['threads'][0]} replay thread(s) per worker): "
          f"{dask_wall:.1f} s (client peak RSS {client_rss:.0f} MB; "
          f"per worker: " + ", ".join(f"{s:.1f} s of tasks ({cpu_per_worker[w]:.1f} CPU s)"
                                      for w, s in per_worker.items())
          + (f"; worker peak RSS {', '.join(f'{r:.0f}' for r in rss)} MB" if rss else "")
          + f"); {dask_wall - max(per_worker.values(), default=0.0):.1f} s outside the "
          "busiest worker's tasks (start, imports, cluster, kernels, close)")
    same = same_datasets(tmp / "seq", tmp / "dask") and same_datasets(tmp / "seq1",
                                                                       tmp / "dask")
    print(f"speed-up: {seq_wall / dask_wall:.2f}x the sequential run, {one_wall / dask_wall:.2f}x"
          f" the one-thread sequential run (target >= 1.7x on 2 cores); datasets identical: "
          f"{same}")


def worker_peaks(dataset: Path) -> list[float]:
    """Each worker's peak RSS (MB), as its tasks recorded it in their partitions."""
    import pyarrow.parquet as pq

    peaks: dict[str, float] = {}
    for part in (dataset / "estimates").rglob("*.parquet"):
        record = json.loads(pq.read_metadata(part).metadata[b"slipd_log"])
        if "peak_rss_mb" in record:
            peaks[record["worker"]] = max(peaks.get(record["worker"], 0.0),
                                          record["peak_rss_mb"])
    return list(peaks.values())


def write_endurance(path: Path) -> None:
    from slipd.profile import load_profile
    from slipd.sim import simulate
    from slipd.sim.writer import write_log

    write_log(path, simulate("endurance"), load_profile("default"))


def endurance_log(tmp: Path) -> Path:
    """The simulated endurance drive as a candump log, simulated in a child process: the
    simulation peaks near 1 GB, which this process's peak would carry into every replay's
    measured one (see :func:`measured`)."""
    path = tmp / "endurance.log"
    started = time.perf_counter()
    in_child(write_endurance, path)
    print(f"simulated the endurance drive in {time.perf_counter() - started:.0f} s")
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--log", type=Path, help="the endurance drive's candump log (default: "
                        "simulate it)")
    parser.add_argument("--estimator", default="all", help="methods of the memory figures")
    parser.add_argument("--day-copies", type=int, default=22,
                        help="copies of the log in the long log (22 x 4000 s = 24.4 h)")
    parser.add_argument("--skip-24h", action="store_true", help="no 24 h log")
    parser.add_argument("--whole-24h", action="store_true",
                        help="also run the whole-log path on the 24 h log (~20 GB)")
    parser.add_argument("--logs", type=int, default=40, help="simulated logs of the Dask run")
    parser.add_argument("--dask-estimator", default="all", help="methods of the Dask run")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--fleet-logs", type=Path, metavar="DIR",
                        help="keep the simulated logs of the Dask run here (and reuse them)")
    parser.add_argument("--minutes", type=float, default=10.0,
                        help="also run the Dask comparison on drives of this length made of "
                        "the simulated logs (0: not)")
    parser.add_argument("--only", choices=("memory", "dask"))
    args = parser.parse_args()
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    with tempfile.TemporaryDirectory(prefix="slipd-fleet-") as folder:
        tmp = Path(folder)
        if args.only != "dask":
            log = args.log or endurance_log(tmp)
            memory(log, tmp, args.estimator, args.day_copies, args.skip_24h, args.whole_24h)
        if args.only != "memory":
            dask(tmp, args.logs, args.dask_estimator, args.workers, args.fleet_logs,
                 args.minutes)


if __name__ == "__main__":
    main()
