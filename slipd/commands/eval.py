"""``slipd eval``: run estimators on logs and score them against ground truth.

    slipd eval LOG --truth TRUTH [--estimator NAME|all] [--min-speed KPH] [--json] [--plot PNG]
    slipd eval --suite DIR [--estimator ...] [--json]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from slipd.errors import ConfigError
from slipd.eval.metrics import KPH, Errors, Scores, errors, format_table, pooled


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", nargs="?", type=Path, help="candump -L log")
    parser.add_argument("--truth", type=Path, help="truth CSV of the log (slipd sim)")
    parser.add_argument("--suite", type=Path, metavar="DIR",
                        help="evaluate every DIR/*.log with its DIR/*.truth.csv")
    parser.add_argument("--estimator", default="all",
                        help="estimator name, comma-separated names, or 'all' (default)")
    parser.add_argument("--min-speed", type=float, default=20.0, metavar="KPH",
                        help="score only samples with truth speed above this (default 20 km/h)")
    parser.add_argument("--profile", default="default", help="vehicle profile of the log")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--plot", type=Path, metavar="PNG",
                        help="write beta-vs-time and error-CDF plots (single log)")


def _methods(spec: str) -> list[str]:
    from slipd.estimators.base import available

    names = available()
    if spec == "all":
        return names
    chosen = [s.strip() for s in spec.split(",") if s.strip()]
    unknown = [c for c in chosen if c not in names]
    if unknown:
        raise ConfigError(f"unknown estimator(s) {unknown}; available: {', '.join(names)}")
    return chosen


def evaluate_log(log: Path, truth_path: Path, methods: list[str], profile,
                 min_speed_kph: float) -> tuple[dict[str, Errors], dict]:
    """Errors per method on one log, plus what the plot needs."""
    from slipd.replay.engine import run_log
    from slipd.sim.writer import read_truth_csv

    if not log.exists():
        raise ConfigError(f"{log}: no such log")
    if not truth_path.exists():
        raise ConfigError(f"{truth_path}: no such truth file")
    truth, epoch = read_truth_csv(truth_path)
    truth_t = truth["t"] + epoch
    speed = truth.get("speed")
    estimates = run_log(log, profile, methods)
    result: dict[str, Errors] = {}
    series = {}
    for name in methods:
        est = estimates[name]
        result[name] = errors(est.t, est.out, truth_t, truth["beta"], truth["vx"], speed,
                              min_speed=min_speed_kph * KPH)
        series[name] = (est.t - epoch, est.out[:, 0])
    return result, {"truth_t": truth["t"], "truth_beta": truth["beta"], "series": series}


def _as_json(rows: dict[str, Scores]) -> dict:
    def clean(d: dict) -> dict:
        return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in d.items()}

    return {"estimators": {name: clean(s.as_dict()) for name, s in rows.items()}}


def _truth_of(log: Path) -> Path:
    return log.with_name(log.name[: -len(".log")] + ".truth.csv")


def run(args: argparse.Namespace) -> int:
    from slipd.profile import load_profile

    methods = _methods(args.estimator)
    profile = load_profile(args.profile)
    if args.suite is not None:
        if args.log is not None:
            raise ConfigError("give either a LOG or --suite DIR, not both")
        logs = sorted(p for p in args.suite.glob("*.log") if _truth_of(p).exists())
        if not logs:
            raise ConfigError(f"{args.suite}: no *.log with a matching *.truth.csv")
        per_scenario: dict[str, dict[str, Scores]] = {}
        parts: dict[str, list[Errors]] = {m: [] for m in methods}
        for log in logs:
            errs, _ = evaluate_log(log, _truth_of(log), methods, profile, args.min_speed)
            per_scenario[log.stem] = {m: e.scores() for m, e in errs.items()}
            for m, e in errs.items():
                parts[m].append(e)
        overall = {m: pooled(parts[m]) for m in methods}
        if args.json:
            doc = {"scenarios": {s: _as_json(rows) for s, rows in per_scenario.items()},
                   "overall": _as_json(overall)}
            print(json.dumps(doc, indent=2))
        else:
            for scen, rows in per_scenario.items():
                print(format_table(rows, title=f"== {scen}"))
                print()
            print(format_table(overall, title="== overall (all scored samples pooled)"))
        return 0
    if args.log is None:
        raise ConfigError("name a LOG (with --truth TRUTH) or use --suite DIR")
    truth_path = args.truth or _truth_of(args.log)
    errs, plot_data = evaluate_log(args.log, truth_path, methods, profile, args.min_speed)
    rows = {m: e.scores() for m, e in errs.items()}
    if args.json:
        print(json.dumps(_as_json(rows), indent=2))
    else:
        print(format_table(rows, title=f"== {args.log.name} (truth speed > {args.min_speed:g} "
                                       f"km/h)"))
        skipped = {m: e.rejected_nonfinite for m, e in errs.items() if e.rejected_nonfinite}
        if skipped:
            print(f"not scored (non-finite estimate): {skipped}")
    if args.plot is not None:
        from slipd.eval.plots import plot_evaluation

        plot_evaluation(args.plot, plot_data["truth_t"], plot_data["truth_beta"],
                        plot_data["series"], errs, title=args.log.name)
    return 0
