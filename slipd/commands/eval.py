"""``slipd eval``: run estimators on logs and score them against ground truth.

    slipd eval LOG [--truth TRUTH] [--estimator NAME,...|all] [--profile P] [--min-speed KPH]
               [--mismatch all|CASE,...] [--json] [--out FILE.json] [--plot FILE.png|.pdf|.svg]
    slipd eval --suite DIR [same options]

Without ``--mismatch`` every log is scored with the profile as given; with it, the nominal
profile first and then each mismatch case (slipd.eval.mismatch), one at a time, every log of
the run each time, and a table per case plus the cases pooled.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

from slipd.errors import ConfigError
from slipd.eval.metrics import KPH, Accumulator, Errors, Scores, errors, format_table

NOMINAL = "nominal"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", nargs="?", type=Path, help="candump -L log")
    parser.add_argument("--truth", type=Path,
                        help="truth CSV of the log (default LOG without .log + .truth.csv)")
    parser.add_argument("--suite", type=Path, metavar="DIR",
                        help="evaluate every DIR/*.log with its DIR/*.truth.csv")
    parser.add_argument("--estimator", default="all",
                        help="estimator name, comma-separated names, or 'all' (default)")
    parser.add_argument("--min-speed", type=float, default=20.0, metavar="KPH",
                        help="score only samples with truth speed above this (default 20 km/h)")
    parser.add_argument("--profile", default="default", help="vehicle profile of the log")
    parser.add_argument("--mismatch", metavar="all|CASE,...",
                        help="also evaluate with the profile perturbed against the car, one "
                             "case at a time (see slipd.eval.mismatch; 'list' prints them)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of tables")
    parser.add_argument("--out", type=Path, metavar="FILE.json",
                        help="write the whole result as JSON (tables still print)")
    parser.add_argument("--plot", type=Path, metavar="FILE",
                        help="a single log: beta over time and the error CDF; a suite or "
                             "--mismatch: a summary bar chart (PNG, PDF or SVG by suffix)")


def _methods(spec: str) -> list[str]:
    from slipd.estimators.base import available

    names = available()
    if spec == "all":
        return names
    chosen = [s.strip() for s in spec.split(",") if s.strip()]
    unknown = [c for c in chosen if c not in names]
    if unknown or not chosen:
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
        series[name] = (est.t - epoch, est.out)
    return result, {"truth_t": truth["t"], "truth_beta": truth["beta"], "series": series}


def _truth_of(log: Path) -> Path:
    return log.with_name(log.name[: -len(".log")] + ".truth.csv") if log.name.endswith(
        ".log") else log.with_name(log.name + ".truth.csv")


@dataclass
class CaseResult:
    """Scores of one profile (nominal or a mismatch case) over the run's logs."""

    name: str
    description: str
    logs: dict[str, dict[str, Scores]] = field(default_factory=dict)
    pooled: dict[str, Accumulator] = field(default_factory=dict)

    def overall(self) -> dict[str, Scores]:
        return {m: acc.scores() for m, acc in self.pooled.items()}


def _jsonable(rows: dict[str, Scores]) -> dict:
    def clean(d: dict) -> dict:
        return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in d.items()}

    return {"estimators": {name: clean(s.as_dict()) for name, s in rows.items()}}


def _evaluate_case(name: str, description: str, logs: list[tuple[str, Path, Path]],
                   methods: list[str], profile, min_speed: float, keep_plot: bool
                   ) -> tuple[CaseResult, dict | None, dict[str, Errors] | None]:
    case = CaseResult(name, description, pooled={m: Accumulator() for m in methods})
    plot_data = single = None
    for log_name, log, truth in logs:
        errs, plot_data = evaluate_log(log, truth, methods, profile, min_speed)
        case.logs[log_name] = {m: e.scores() for m, e in errs.items()}
        for m, e in errs.items():
            case.pooled[m].add(e)
        single = errs if keep_plot else None
    return case, (plot_data if keep_plot else None), single


def run(args: argparse.Namespace) -> int:
    from slipd.eval.mismatch import CASES, parse_cases
    from slipd.profile import load_profile

    if args.mismatch == "list":
        for case in CASES.values():
            print(f"{case.name:20s} {case.description}")
        return 0
    methods = _methods(args.estimator)
    cases = parse_cases(args.mismatch) if args.mismatch else []
    if not math.isfinite(args.min_speed) or args.min_speed < 0:
        raise ConfigError(f"--min-speed {args.min_speed}: expected a speed >= 0 km/h")
    if args.suite is not None:
        if args.log is not None:
            raise ConfigError("give either a LOG or --suite DIR, not both")
        if not args.suite.is_dir():
            raise ConfigError(f"--suite {args.suite}: not a directory")
        found = sorted(p for p in args.suite.glob("*.log") if _truth_of(p).exists())
        if not found:
            raise ConfigError(f"{args.suite}: no *.log with a matching *.truth.csv")
        logs = [(p.name[: -len(".log")], p, _truth_of(p)) for p in found]
    else:
        if args.log is None:
            raise ConfigError("name a LOG (with --truth TRUTH) or use --suite DIR")
        logs = [(args.log.name, args.log, args.truth or _truth_of(args.log))]
    single_plot = args.plot is not None and args.suite is None and not cases

    nominal, plot_data, single = _evaluate_case(
        NOMINAL, "the profile as given", logs, methods, load_profile(args.profile),
        args.min_speed, single_plot)
    results = [nominal]
    for case in cases:
        print(f"mismatch {case.name}: {case.description}", file=sys.stderr)
        perturbed = load_profile(args.profile, edit=case.edit())
        results.append(_evaluate_case(case.name, case.description, logs, methods, perturbed,
                                      args.min_speed, False)[0])
    mismatch_pooled = {m: Accumulator() for m in methods}
    for case in results[1:]:
        for m in methods:
            mismatch_pooled[m].merge(case.pooled[m])

    doc = _document(args, methods, logs, results, mismatch_pooled if cases else None)
    if args.out is not None:
        try:
            args.out.write_text(json.dumps(doc, indent=2) + "\n")
        except OSError as exc:
            raise ConfigError(f"--out {args.out}: cannot write: {exc.strerror}") from exc
    if args.json:
        print(json.dumps(doc, indent=2))
    else:
        _print_tables(args, logs, results, mismatch_pooled if cases else None, single)
    if args.plot is not None:
        _plot(args, logs, results, mismatch_pooled if cases else None, plot_data, single)
    return 0


def _document(args, methods, logs, results: list[CaseResult], mismatch_pooled) -> dict:
    nominal = results[0]
    doc: dict = {"profile": str(args.profile), "min_speed_kph": args.min_speed,
                 "estimators_evaluated": methods}
    if args.suite is None and len(logs) == 1:
        doc.update(_jsonable(nominal.overall()))
        doc["log"] = str(logs[0][1])
    else:
        doc["scenarios"] = {name: _jsonable(rows) for name, rows in nominal.logs.items()}
        doc["overall"] = _jsonable(nominal.overall())
    if mismatch_pooled is not None:
        doc["mismatch"] = {
            "cases": {c.name: {"description": c.description, **_jsonable(c.overall()),
                               "scenarios": {n: _jsonable(r) for n, r in c.logs.items()}}
                      for c in results[1:]},
            "pooled": _jsonable({m: a.scores() for m, a in mismatch_pooled.items()}),
        }
    return doc


def _print_tables(args, logs, results: list[CaseResult], mismatch_pooled, single) -> None:
    nominal = results[0]
    speed = f"truth speed > {args.min_speed:g} km/h"
    if args.suite is None and len(logs) == 1:
        print(format_table(nominal.overall(), title=f"== {logs[0][0]} ({speed})"))
        skipped = {m: e.rejected_nonfinite for m, e in (single or {}).items()
                   if e.rejected_nonfinite}
        if skipped:
            print(f"not scored (non-finite estimate): {skipped}")
    else:
        for name, rows in nominal.logs.items():
            print(format_table(rows, title=f"== {name}"))
            print()
        print(format_table(nominal.overall(), title=f"== overall (all scored samples pooled, "
                                                    f"{speed})"))
    if mismatch_pooled is None:
        return
    for case in results[1:]:
        print()
        print(format_table(case.overall(), title=f"== mismatch {case.name}: {case.description}"
                                                 f" (logs pooled)"))
    print()
    print(format_table({m: a.scores() for m, a in mismatch_pooled.items()},
                       title=f"== mismatch: all {len(results) - 1} cases pooled"))
    print("V = VALID ticks only; V>2deg/V>5deg = share of VALID ticks off by more; "
          "2sig cov = share of VALID ticks with |error| <= 2 sigma_beta")


def _plot(args, logs, results: list[CaseResult], mismatch_pooled, plot_data, single) -> None:
    from slipd.eval import plots

    if plot_data is not None and single is not None:
        plots.plot_evaluation(args.plot, plot_data["truth_t"], plot_data["truth_beta"],
                              plot_data["series"], single, title=logs[0][0])
        return
    groups = {name: rows for name, rows in results[0].logs.items()}
    if mismatch_pooled is not None:
        groups = {c.name: c.overall() for c in results}
        title = f"mismatch cases ({len(logs)} log(s) pooled per case)"
    else:
        title = f"suite {args.suite}" if args.suite is not None else logs[0][0]
    plots.plot_summary(args.plot, groups, title=title)
