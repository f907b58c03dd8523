"""``slipd sim``: simulate scenarios into candump logs and truth CSVs.

    slipd sim SCENARIO [--vehicle 1|2|3] [--seed N] [--duration S] --out DIR
    slipd sim --list
    slipd sim --suite --out DIR [--jobs 2]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from slipd.errors import ConfigError, DependencyError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", nargs="?", help="scenario name (see --list)")
    parser.add_argument("--list", action="store_true", help="list the scenarios and exit")
    parser.add_argument("--suite", action="store_true", help="simulate every scenario")
    parser.add_argument("--vehicle", type=int, choices=(1, 2, 3), default=2,
                        help="CommonRoad parameter set: 1 Ford Escort, 2 BMW 320i, 3 VW Vanagon")
    parser.add_argument("--seed", type=int, default=0, help="sensor noise seed (default 0)")
    parser.add_argument("--duration", type=float, default=None,
                        help="cut (or stretch a one-manoeuvre scenario) to S seconds")
    parser.add_argument("--profile", default="default",
                        help="vehicle profile for the bus layout (default: default)")
    parser.add_argument("--gnss-delay", type=float, default=None, metavar="S",
                        help="GNSS velocity latency (default 0.4 s, as in Yoon et al. 2016)")
    parser.add_argument("--out", type=Path, help="output directory")
    parser.add_argument("--jobs", type=int, default=2,
                        help="parallel processes for --suite (default 2)")


def _require_sim() -> None:
    try:
        import scipy  # noqa: F401
        import vehiclemodels  # noqa: F401
    except ImportError as exc:
        raise DependencyError(
            f"slipd sim needs {exc.name}: pip install 'slipd[sim]'"
        ) from exc


def simulate_to_files(scenario: str, out_dir: Path, vehicle: int = 2, seed: int = 0,
                      duration: float | None = None, profile: str = "default",
                      workers: int = 1, progress=None, sensor: dict | None = None) -> dict:
    """Simulate ``scenario`` and write OUT/SCENARIO.log and OUT/SCENARIO.truth.csv."""
    from slipd.profile import load_profile
    from slipd.sim import simulate
    from slipd.sim.writer import write_log, write_truth_csv

    start = time.perf_counter()
    prof = load_profile(profile)
    result = simulate(scenario, vehicle=vehicle, seed=seed, duration=duration, profile=prof,
                      workers=workers, progress=progress, sensor=sensor)
    out_dir.mkdir(parents=True, exist_ok=True)
    frames = write_log(out_dir / f"{scenario}.log", result, prof)
    write_truth_csv(out_dir / f"{scenario}.truth.csv", result)
    return {"scenario": scenario, "duration": result.duration, "frames": frames,
            "wall": time.perf_counter() - start}


def _suite_job(job: tuple) -> dict:
    return simulate_to_files(*job)


def run_suite(out_dir: Path, vehicle: int, seed: int, profile: str, jobs: int) -> int:
    """Every scenario, ``jobs`` processes at a time; the long drive's legs share the pool."""
    from concurrent.futures import ProcessPoolExecutor

    from tqdm import tqdm

    from slipd.sim import SCENARIOS

    names = list(SCENARIOS)
    total = sum(SCENARIOS[n].duration for n in names)
    done = []
    with tqdm(total=round(total), unit="sim s", desc="slipd sim --suite",
              file=sys.stderr) as bar:
        # the long drive first, its legs spread over the workers; then the rest in a pool
        long_runs = [n for n in names if SCENARIOS[n].duration > 1000]
        for name in long_runs:
            reached = [0]
            limit = round(SCENARIOS[name].duration)

            def advance(t_sim: float, reached: list = reached, limit: int = limit) -> None:
                step = min(round(t_sim), limit) - reached[0]
                if step > 0:
                    bar.update(step)
                    reached[0] += step

            info = simulate_to_files(name, out_dir, vehicle, seed, None, profile, workers=jobs,
                                     progress=advance)
            done.append(info)
            bar.update(limit - reached[0])
        short = [(n, out_dir, vehicle, seed, None, profile, 1) for n in names
                 if n not in long_runs]
        if jobs > 1:
            with ProcessPoolExecutor(max_workers=jobs) as pool:
                for info in pool.map(_suite_job, short):
                    done.append(info)
                    bar.update(round(SCENARIOS[info["scenario"]].duration))
        else:
            for job in short:
                info = _suite_job(job)
                done.append(info)
                bar.update(round(SCENARIOS[info["scenario"]].duration))
    for info in done:
        print(f"{info['scenario']:20s} {info['duration']:8.1f} s simulated  "
              f"{info['frames']:8d} frames  {info['wall']:6.1f} s wall")
    return 0


def run(args: argparse.Namespace) -> int:
    from slipd.sim.scenarios import SCENARIOS

    if args.list:
        width = max(len(n) for n in SCENARIOS)
        for name, scen in SCENARIOS.items():
            print(f"{name:{width}s}  {scen.duration:6.0f} s  {scen.paper}: {scen.description}")
        return 0
    if args.out is None:
        raise ConfigError("--out DIR is required")
    _require_sim()
    if args.suite:
        if args.scenario:
            raise ConfigError("give either a SCENARIO or --suite, not both")
        return run_suite(args.out, args.vehicle, args.seed, args.profile, max(1, args.jobs))
    if not args.scenario:
        raise ConfigError("name a SCENARIO (see slipd sim --list) or use --suite")
    if args.scenario not in SCENARIOS:
        raise ConfigError(f"unknown scenario {args.scenario!r}; see slipd sim --list")
    sensor = {} if args.gnss_delay is None else {"gnss_delay": args.gnss_delay}
    if args.gnss_delay is not None and args.gnss_delay < 0:
        raise ConfigError("--gnss-delay must be >= 0")
    info = simulate_to_files(args.scenario, args.out, args.vehicle, args.seed, args.duration,
                             args.profile, workers=max(1, args.jobs), sensor=sensor)
    print(f"{args.out / (args.scenario + '.log')}: {info['frames']} frames, "
          f"{info['duration']:.1f} s simulated in {info['wall']:.1f} s")
    return 0
