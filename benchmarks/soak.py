"""Soak: the daemon for a long time under a full bus and all its tools, watching for growth.

``slipd run`` on slipd_unix (a process of its own) gets the latency benchmark's 4,000
frames/s feed from another process, records every frame (rotating every
``--recorder-max-mb``, so rotation and compression run many times), saves its state file
every minute, and serves stats readers from its loop's first answer on (after numba's
warm-up): ``slipd stats --watch 1``, a Prometheus scrape every second and a burst of 100
concurrent queries every minute. Every ``--sample`` seconds this process reads the daemon's
RSS (and its stats server's) and its counters. At the end it
prints the RSS growth (the last tenth of the run against the first tenth after
``--settle``), the fitted slope, deadline misses, and whether anything crashed (the daemon
exiting early or not 0, the stats server restarted, recorder errors, failed queries).

    .venv/bin/python -m benchmarks.soak --duration 3600      # the 1-hour figure
    .venv/bin/python -m benchmarks.soak --duration 300       # tests/test_soak.py (slow)
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np

from benchmarks.daemon_latency import _free_port, burst, feeder, process_figures

BURST_EVERY_S = 60.0
BURST_CLIENTS = 100


def _children(pid: int) -> list[int]:
    try:
        text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    except OSError:
        return []
    return [int(p) for p in text.split()]


def readers(stats_socket: str, prometheus: str, stop: threading.Event, result: dict) -> None:
    """This process's threads: a query a second (as --watch 1), a scrape a second, a burst
    of BURST_CLIENTS concurrent queries every BURST_EVERY_S."""
    from slipd.daemon.stats import query

    def one() -> None:
        try:
            query(stats_socket, timeout=10.0)
            result["queries"] += 1
        except (OSError, ValueError) as exc:
            result["failed"] += 1
            result["first_error"] = result["first_error"] or f"{type(exc).__name__}: {exc}"

    next_burst = time.monotonic() + 10.0
    while not stop.wait(1.0):
        one()
        try:
            with urllib.request.urlopen(f"http://{prometheus}/metrics", timeout=10) as reply:
                reply.read()
            result["scrapes"] += 1
        except OSError as exc:
            result["failed"] += 1
            result["first_error"] = result["first_error"] or f"scrape: {exc}"
        if time.monotonic() >= next_burst:
            next_burst += BURST_EVERY_S
            burst(one, BURST_CLIENTS)


def soak(duration: float, sample_s: float, settle_s: float, estimator: str, rate: float,
         recorder_max_mb: float, workdir: Path, realtime: bool = False) -> dict:
    from slipd.daemon.stats import query

    channel = str(workdir / "bus")
    ctx = mp.get_context("spawn")
    ready, report = ctx.Event(), ctx.Queue()
    feed = ctx.Process(target=feeder, args=("slipd_unix", channel, rate, duration + 60.0, None,
                                            100.0, ready, report))
    feed.start()
    if not ready.wait(120):
        raise SystemExit("feeder did not start")
    stats_socket = str(workdir / "stats.sock")
    prometheus = f"127.0.0.1:{_free_port()}"
    command = [str(Path(sys.executable).with_name("slipd")), "run", "--interface", "slipd_unix",
               "--channel", channel, "--estimator", estimator, "--stats-socket", stats_socket,
               "--prometheus", prometheus, "--recorder", str(workdir / "rec" / "flight.log"),
               "--recorder-max-mb", str(recorder_max_mb), "--recorder-keep", "3",
               "--state-file", str(workdir / "state.json"), "--duration", str(duration),
               "--config", str(workdir / "none.toml")]
    (workdir / "none.toml").write_text("")
    if realtime:
        command += ["--sched-fifo", "50", "--mlockall", "--timer-slack-ns", "1", "--gc-freeze"]
    log_path = workdir / "daemon.log"
    with open(log_path, "w") as log:
        daemon = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
    # The readers start with the loop's first answer: before it (numba's warm-up, 54 s on
    # a cold cache under load) every query is refused with "no snapshot yet", and the 1-hour
    # run counted those 118 as failures of the tools.
    deadline = time.monotonic() + 300
    loop_uptime = 0.0
    while daemon.poll() is None:
        if time.monotonic() > deadline:
            raise SystemExit("the daemon did not start")
        if os.path.exists(stats_socket):
            try:
                loop_uptime = float(query(stats_socket, timeout=2.0)["uptime_s"])
                break
            except (OSError, ValueError):
                pass
        time.sleep(0.2)
    started = time.monotonic()
    stop = threading.Event()
    result = {"queries": 0, "failed": 0, "scrapes": 0, "first_error": ""}
    reader = threading.Thread(target=readers, args=(stats_socket, prometheus, stop, result),
                              daemon=True)
    reader.start()
    samples = []  # (s since start, daemon RSS MB, server RSS MB, ticks, misses)
    last = None
    # readers stop before the daemon does: its --duration counts from its loop's start, which
    # was loop_uptime before the first answer (the 1-hour run counted 6 queries sent after
    # the daemon had gone, FileNotFoundError on its removed socket, as failures of the tools)
    readers_until = started - loop_uptime + duration - 5.0
    while daemon.poll() is None:
        time.sleep(sample_s)
        if time.monotonic() >= readers_until:
            stop.set()
        if daemon.poll() is not None:
            break
        try:
            figures = process_figures(daemon.pid)
            servers = [process_figures(pid)["rss_mb"] for pid in _children(daemon.pid)]
            snapshot = query(stats_socket, timeout=10.0)
        except (OSError, ValueError, KeyError):
            continue
        last = snapshot
        samples.append((time.monotonic() - started, figures["rss_mb"],
                        max(servers, default=0.0), snapshot["counters"]["ticks"],
                        snapshot["counters"]["deadline_misses"]))
    stop.set()
    reader.join(60)
    code = daemon.wait()
    feed.join(120)
    fed = report.get(timeout=10) if not report.empty() else {}
    if feed.is_alive():
        feed.terminate()
    log_text = log_path.read_text()
    return {"samples": samples, "exit": code, "last": last, "readers": result, "feeder": fed,
            "log": log_text, "settle_s": settle_s, "duration": duration,
            "recordings": sorted(p.name for p in (workdir / "rec").iterdir())}


def growth(samples: list, settle_s: float, column: int) -> tuple[float, float]:
    """(last tenth minus first tenth after settling, in MB; fitted slope, MB per hour)."""
    rows = np.array([s for s in samples if s[0] >= settle_s])
    if len(rows) < 4:
        return float("nan"), float("nan")
    tenth = max(1, len(rows) // 10)
    early, late = np.median(rows[:tenth, column]), np.median(rows[-tenth:, column])
    slope = np.polyfit(rows[:, 0] / 3600.0, rows[:, column], 1)[0]
    return float(late - early), float(slope)


def summarize(result: dict) -> dict:
    samples = result["samples"]
    last = result["last"] or {"counters": {}}
    c = last["counters"]
    rss_growth, rss_slope = growth(samples, result["settle_s"], 1)
    server_growth, server_slope = growth(samples, result["settle_s"], 2)
    crashed = (result["exit"] != 0 or c.get("stats_server_restarts", 0) > 0
               or "Traceback" in result["log"])
    return {"minutes": samples[-1][0] / 60 if samples else 0.0,
            "rss_first_mb": samples[0][1] if samples else float("nan"),
            "rss_last_mb": samples[-1][1] if samples else float("nan"),
            "rss_growth_mb": rss_growth, "rss_slope_mb_per_h": rss_slope,
            "server_rss_mb": samples[-1][2] if samples else float("nan"),
            "server_growth_mb": server_growth, "server_slope_mb_per_h": server_slope,
            "ticks": c.get("ticks", 0), "misses": c.get("deadline_misses", 0),
            "recorder_errors": c.get("recorder_errors", 0),
            "stats_server_restarts": c.get("stats_server_restarts", 0),
            "rx_overflows": c.get("rx_overflows", 0), "exit": result["exit"],
            "crashed": crashed, "queries": result["readers"]["queries"],
            "failed_queries": result["readers"]["failed"],
            "first_error": result["readers"]["first_error"],
            "cycle_p99_us": last.get("cycle_latency_us", {}).get("p99"),
            "stats_answer": last.get("stats_answer_us", {}),
            "recordings": result["recordings"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=3600.0, help="seconds")
    parser.add_argument("--sample", type=float, default=10.0, help="seconds between samples")
    parser.add_argument("--settle", type=float, default=120.0,
                        help="seconds before RSS counts (allocator arenas fill first)")
    parser.add_argument("--estimator", default="kinematic_heuristic")
    parser.add_argument("--rate", type=float, default=4000.0, help="bus frames/s")
    parser.add_argument("--recorder-max-mb", type=float, default=5.0)
    parser.add_argument("--realtime", action="store_true",
                        help="SCHED_FIFO, mlockall, timer slack 1 ns, gc freeze")
    parser.add_argument("--json", type=Path, help="also write the figures as JSON")
    args = parser.parse_args()
    workdir = Path(tempfile.mkdtemp(prefix="slipd-soak-"))
    try:
        print(f"soak: slipd run --estimator {args.estimator} on slipd_unix for "
              f"{args.duration:g} s at {args.rate:g} frames/s, recorder rotating every "
              f"{args.recorder_max_mb:g} MB, stats readers; {os.cpu_count()} CPUs", flush=True)
        result = soak(args.duration, args.sample, args.settle, args.estimator, args.rate,
                      args.recorder_max_mb, workdir, args.realtime)
        s = summarize(result)
        print(f"ran {s['minutes']:.1f} min, {s['ticks']:,} ticks, exit code {s['exit']}; "
              f"deadline misses {s['misses']} ({s['misses'] / max(s['ticks'], 1) * 1e6:.0f} "
              f"per million ticks), cycle p99 {s['cycle_p99_us']} us")
        print(f"daemon RSS {s['rss_first_mb']:.1f} -> {s['rss_last_mb']:.1f} MB; growth after "
              f"{args.settle:g} s: {s['rss_growth_mb']:+.2f} MB (slope "
              f"{s['rss_slope_mb_per_h']:+.2f} MB/h); stats server RSS "
              f"{s['server_rss_mb']:.1f} MB, growth {s['server_growth_mb']:+.2f} MB (slope "
              f"{s['server_slope_mb_per_h']:+.2f} MB/h)")
        print(f"tools: {s['queries']:,} queries answered, {s['failed_queries']} failed"
              f"{' (' + s['first_error'] + ')' if s['first_error'] else ''}; the loop's answers "
              f"{s['stats_answer']}; recorder errors {s['recorder_errors']}, files "
              f"{s['recordings']}; stats server restarts {s['stats_server_restarts']}; kernel "
              f"drops {s['rx_overflows']}")
        verdict = (not s["crashed"] and abs(s["rss_growth_mb"]) < 1.0)
        print(f"crashes {int(s['crashed'])}; RSS growth < 1 MB: "
              f"{'ok' if abs(s['rss_growth_mb']) < 1.0 else 'OVER'}; "
              f"{'ok' if verdict else 'FAILED'}")
        for line in result["log"].splitlines():
            if "Traceback" in line or "error" in line.lower():
                print(f"  daemon: {line}")
        if args.json:
            args.json.write_text(json.dumps({"summary": s, "samples": result["samples"]},
                                            indent=1))
    finally:
        shutil.rmtree(workdir, ignore_errors=True)


if __name__ == "__main__":
    main()
