"""``slipd sim``: simulate scenarios into candump logs and truth CSVs.

    slipd sim SCENARIO [--vehicle 1|2|3] [--seed N] [--duration S] [--variant NAME] --out DIR
    slipd sim --list | --list-variants
    slipd sim --suite --out DIR [--jobs 2] [--variant NAME[,NAME]] [--variant ...]

``--variant`` applies a sensor variant (slipd.sim.variants); names joined by commas apply
together. Given more than once (or as ``each``: every variant), each goes to DIR/NAME/ and the
plant is integrated once per scenario for all of them.
"""

from __future__ import annotations

import argparse
import ast
import sys
import time
from pathlib import Path

from slipd.errors import ConfigError, DependencyError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", nargs="?", help="scenario name (see --list)")
    parser.add_argument("--list", action="store_true",
                        help="list the scenarios and the sensor variants and exit")
    parser.add_argument("--list-variants", action="store_true",
                        help="list the sensor variants with their settings and sources, exit")
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
    parser.add_argument("--variant", action="append", default=None, metavar="NAME[,NAME]",
                        help="sensor variant (see --list-variants); names joined by commas "
                             "apply together; repeat it (or give 'each') for one output "
                             "directory per variant, OUT/NAME/")
    parser.add_argument("--sensor", action="append", default=[], metavar="KEY=VALUE",
                        help="override one SensorConfig field (SI units, Python literal), "
                             "e.g. --sensor wheel_speed_method='count'; repeatable")
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


def simulate_variants_to_files(
    scenario: str, outputs: list[tuple[str | None, Path]], vehicle: int = 2, seed: int = 0,
    duration: float | None = None, profile: str = "default", workers: int = 1, progress=None,
    sensor: dict | None = None,
) -> list[dict]:
    """Simulate ``scenario`` once and write, per (variant, directory) of ``outputs``,
    DIR/SCENARIO.log and DIR/SCENARIO.truth.csv."""
    from slipd.profile import load_profile
    from slipd.sim.core import simulate_variants
    from slipd.sim.writer import write_log, write_truth_csv

    start = time.perf_counter()
    prof = load_profile(profile)
    results = simulate_variants(scenario, [spec for spec, _ in outputs], vehicle=vehicle,
                                seed=seed, duration=duration, profile=prof, workers=workers,
                                progress=progress, sensor=sensor)
    infos = []
    for (spec, out_dir), result in zip(outputs, results, strict=True):
        out_dir.mkdir(parents=True, exist_ok=True)
        frames = write_log(out_dir / f"{scenario}.log", result, prof)
        write_truth_csv(out_dir / f"{scenario}.truth.csv", result)
        infos.append({"scenario": scenario, "variant": spec, "duration": result.duration,
                      "frames": frames, "wall": time.perf_counter() - start})
    return infos


def simulate_to_files(scenario: str, out_dir: Path, vehicle: int = 2, seed: int = 0,
                      duration: float | None = None, profile: str = "default",
                      workers: int = 1, progress=None, sensor: dict | None = None,
                      variant: str | None = None) -> dict:
    """Simulate ``scenario`` and write OUT/SCENARIO.log and OUT/SCENARIO.truth.csv."""
    return simulate_variants_to_files(scenario, [(variant, out_dir)], vehicle, seed, duration,
                                      profile, workers, progress, sensor)[0]


def _suite_job(job: tuple) -> list[dict]:
    """One scenario of the suite; a scenario the plant cannot integrate on this car (e.g.
    snow_drift's rear-slip throttle on the front-driven vehicle 1) is reported, not fatal."""
    from slipd.sim.plant import SimulationError

    try:
        return simulate_variants_to_files(*job)
    except SimulationError as exc:
        return [{"scenario": job[0], "failed": str(exc)}]


def run_suite(out_dir: Path, vehicle: int, seed: int, profile: str, jobs: int,
              outputs: list[tuple[str | None, Path]] | None = None,
              sensor: dict | None = None) -> int:
    """Every scenario, ``jobs`` processes at a time; the long drive's legs share the pool.
    ``outputs``: (variant, directory) pairs, each written from the same plant run (default:
    the baseline into ``out_dir``)."""
    from concurrent.futures import ProcessPoolExecutor

    from tqdm import tqdm

    from slipd.sim import SCENARIOS

    outputs = outputs or [(None, out_dir)]
    start = time.perf_counter()
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

            done.extend(_suite_job((name, outputs, vehicle, seed, None, profile, jobs,
                                    advance, sensor)))
            bar.update(limit - reached[0])
        short = [(n, outputs, vehicle, seed, None, profile, 1, None, sensor) for n in names
                 if n not in long_runs]
        if jobs > 1:
            with ProcessPoolExecutor(max_workers=jobs) as pool:
                for infos in pool.map(_suite_job, short):
                    done.extend(infos)
                    bar.update(round(SCENARIOS[infos[0]["scenario"]].duration))
        else:
            for job in short:
                infos = _suite_job(job)
                done.extend(infos)
                bar.update(round(SCENARIOS[infos[0]["scenario"]].duration))
    failed = [info for info in done if "failed" in info]
    for info in done:
        if "failed" in info:
            continue
        tag = f"  [{info['variant']}]" if info["variant"] else ""
        print(f"{info['scenario']:20s} {info['duration']:8.1f} s simulated  "
              f"{info['frames']:8d} frames  {info['wall']:6.1f} s wall{tag}")
    simulated = sum(info["duration"] for info in done if "failed" not in info)
    print(f"suite: {len(names) - len(failed)} of {len(names)} scenarios x {len(outputs)} sensor "
          f"set(s), {simulated:.0f} s simulated in {time.perf_counter() - start:.1f} s wall "
          f"({jobs} jobs)")
    for info in failed:
        print(f"slipd sim: error: {info['scenario']} on vehicle {vehicle} not simulated (no "
              f"files written): {info['failed']}", file=sys.stderr)
    return 1 if failed else 0


def parse_sensor_overrides(items: list[str]) -> dict:
    """``KEY=VALUE`` strings -> SensorConfig overrides; names the bad item and what is valid."""
    import dataclasses

    from slipd.sim.sensors import SensorConfig

    fields = {f.name for f in dataclasses.fields(SensorConfig)}
    overrides = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or key not in fields:
            raise ConfigError(f"--sensor {item!r}: expected KEY=VALUE with KEY a SensorConfig "
                              f"field ({', '.join(sorted(fields))})")
        try:
            value = ast.literal_eval(text.strip())
        except (ValueError, SyntaxError):
            value = text.strip()  # a bare word: a string setting such as accel_frame=level
        overrides[key] = value
    return overrides


def variant_outputs(specs: list[str] | None, out_dir: Path) -> list[tuple[str | None, Path]]:
    """(variant, directory) pairs for the --variant arguments: one spec writes into ``out_dir``,
    several (or 'each') into ``out_dir/NAME``."""
    from slipd.sim.variants import VARIANTS, resolve

    if not specs:
        return [(None, out_dir)]
    expanded: list[str] = []
    for spec in specs:
        expanded.extend(VARIANTS if spec.strip() == "each" else [spec])
    resolved = [resolve(spec)[0] for spec in expanded]
    if len(resolved) == 1:
        return [(resolved[0], out_dir)]
    return [(name, out_dir / name.replace(",", "+")) for name in resolved]


def _print_variants(verbose: bool) -> None:
    from slipd.sim.variants import VARIANTS

    width = max(len(n) for n in VARIANTS)
    for name, variant in VARIANTS.items():
        print(f"{name:{width}s}  {variant.description}")
        if verbose:
            print(f"{'':{width}s}  settings: {variant.summary()}")
            for source in variant.sources:
                print(f"{'':{width}s}  - {source}")


def run(args: argparse.Namespace) -> int:
    from slipd.sim.scenarios import LIMIT_SCENARIOS, SCENARIOS, find_scenario

    if args.list or args.list_variants:
        if args.list:
            width = max(len(n) for n in (*SCENARIOS, *LIMIT_SCENARIOS))
            for name, scen in SCENARIOS.items():
                print(f"{name:{width}s}  {scen.duration:6.0f} s  {scen.paper}: "
                      f"{scen.description}")
            print("\nat the limit, not in --suite (benchmarks.accuracy's limits block):")
            for name, scen in LIMIT_SCENARIOS.items():
                print(f"{name:{width}s}  {scen.duration:6.0f} s  {scen.description}")
            print("\nsensor variants (--variant NAME; --list-variants for settings and sources):")
        _print_variants(verbose=args.list_variants)
        return 0
    if args.out is None:
        raise ConfigError("--out DIR is required")
    sensor = parse_sensor_overrides(args.sensor)
    if args.gnss_delay is not None:
        if args.gnss_delay < 0:
            raise ConfigError("--gnss-delay must be >= 0")
        sensor["gnss_delay"] = args.gnss_delay
    outputs = variant_outputs(args.variant, args.out)
    _require_sim()
    if args.suite:
        if args.scenario:
            raise ConfigError("give either a SCENARIO or --suite, not both")
        return run_suite(args.out, args.vehicle, args.seed, args.profile, max(1, args.jobs),
                         outputs=outputs, sensor=sensor)
    if not args.scenario:
        raise ConfigError("name a SCENARIO (see slipd sim --list) or use --suite")
    if find_scenario(args.scenario) is None:
        raise ConfigError(f"unknown scenario {args.scenario!r}; see slipd sim --list")
    infos = simulate_variants_to_files(args.scenario, outputs, args.vehicle, args.seed,
                                       args.duration, args.profile, workers=max(1, args.jobs),
                                       sensor=sensor)
    for (_, out_dir), info in zip(outputs, infos, strict=True):
        print(f"{out_dir / (args.scenario + '.log')}: {info['frames']} frames, "
              f"{info['duration']:.1f} s simulated in {info['wall']:.1f} s")
    return 0
