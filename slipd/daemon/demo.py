"""``slipd run --demo``: the daemon on a python-can virtual bus fed by a simulated drive.

The simulated drive (``slipd sim``) is made once and cached in ``.slipd-demo/``. The
real-time player runs in a thread of this process because the virtual bus only connects
buses of one process; it only sleeps between frames (no spinning), yet its sends still share
the GIL with the loop, so the demo's latency figures are an upper bound of a real
deployment's (socketcan, player in another process: benchmarks/daemon_latency.py).
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from slipd.channels import ST_VALID, Out
from slipd.estimators import registry

DEMO_DIR = Path(".slipd-demo")


def _simulated_drive(scenario: str) -> tuple[Path, Path]:
    log = DEMO_DIR / f"{scenario}.log"
    truth = DEMO_DIR / f"{scenario}.truth.csv"
    if not (log.exists() and truth.exists()):
        print(f"demo: simulating {scenario} (once; cached in {DEMO_DIR}/) ...", flush=True)
        subprocess.run([sys.executable, "-m", "slipd", "sim", scenario, "--out", str(DEMO_DIR)],
                       check=True)
    return log, truth


def _truth(path: Path, first_frame_time: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Truth time (s since the first frame), beta and vx."""
    from slipd.sim.writer import read_truth_csv

    table, log_epoch = read_truth_csv(path)
    return table["t"] + log_epoch - first_frame_time, table["beta"], table["vx"]


def run_demo(args: argparse.Namespace) -> int:
    import can

    from slipd.daemon.loop import Daemon, DaemonConfig
    from slipd.daemon.stats import summarize
    from slipd.profile import load_profile
    from slipd.replay.player import play, to_messages
    from slipd.replay.readers import read_frames

    log, truth_path = _simulated_drive(args.scenario)
    frames = read_frames(log)
    channel = "slipd-demo"
    messages = to_messages(frames)
    log_start = messages[0].timestamp
    truth_t, truth_beta, truth_vx = _truth(truth_path, log_start)
    profile = load_profile(args.profile or "default")
    estimator = args.estimator or registry.DEFAULT_ESTIMATOR
    duration = args.duration or (messages[-1].timestamp - log_start + 0.5)
    daemon_bus = can.Bus(interface="virtual", channel=channel)
    player_bus = can.Bus(interface="virtual", channel=channel)
    config = DaemonConfig(profile=profile, estimator=estimator, interface="virtual",
                          channel=channel, duration=duration,
                          stats_socket=args.stats_socket, prometheus=args.prometheus)
    errors: list[float] = []
    play_started = threading.Event()
    clock = {"start": 0.0}

    def live_view(daemon: Daemon) -> None:
        out = daemon.out
        t_log = time.monotonic() - clock["start"]
        true_beta = float(np.interp(t_log, truth_t, truth_beta))
        h = summarize(daemon.stats.histograms["cycle_latency_us"])  # numpy, not hdrh's loops
        valid = int(out[Out.STATUS]) & ST_VALID
        print(f"t {t_log:6.1f} s  beta {math.degrees(out[Out.BETA]):+6.2f} deg  truth "
              f"{math.degrees(true_beta):+6.2f} deg  vx {out[Out.VX]:5.1f} m/s  "
              f"{'VALID  ' if valid else 'invalid'} status {int(out[Out.STATUS]):#04x}  "
              f"cycle us p50 {h['p50']} p99 {h['p99']} max {h['max']}", flush=True)

    daemon = Daemon(config, bus=daemon_bus, on_second=live_view)
    original_tick = daemon.tick

    def tick_and_score(t_wall: float) -> None:
        original_tick(t_wall)
        if play_started.is_set() and int(daemon.out[Out.STATUS]) & ST_VALID:
            t_log = time.monotonic() - clock["start"]
            speed = float(np.interp(t_log, truth_t, truth_vx))
            if speed > 20 / 3.6:
                true_beta = float(np.interp(t_log, truth_t, truth_beta))
                errors.append(daemon.out[Out.BETA] - true_beta)

    daemon.tick = tick_and_score

    def feeder() -> None:
        clock["start"] = time.monotonic()
        play_started.set()
        report = play(messages, player_bus, spin=False)
        print(f"demo: player: {report.summary()}", flush=True)

    print(f"demo: {estimator} on virtual bus {channel!r}, {len(messages)} frames of "
          f"{args.scenario} ({duration:.0f} s)", flush=True)
    def start_when_ready() -> None:
        daemon.ready.wait()
        time.sleep(0.2)
        feeder()

    player = threading.Thread(target=start_when_ready, daemon=True)
    player.start()
    snapshot = daemon.run()
    player.join()
    player_bus.shutdown()
    daemon_bus.shutdown()
    c = snapshot["counters"]
    lat = snapshot["cycle_latency_us"]
    rms = math.degrees(math.sqrt(np.mean(np.square(errors)))) if errors else float("nan")
    print(f"\ndemo summary: {c['ticks']} ticks, {c['valid_ticks']} valid, "
          f"{c['deadline_misses']} deadline misses, rx {c['rx_frames']} frames\n"
          f"  cycle latency us: p50 {lat['p50']} p99 {lat['p99']} p99.9 {lat['p99.9']} "
          f"max {lat['max']} (player thread in-process: upper bound)\n"
          f"  beta error vs truth (valid frames, > 20 km/h): RMS {rms:.2f} deg over "
          f"{len(errors)} ticks")
    return 0
