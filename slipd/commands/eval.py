"""``slipd eval``: run estimators on logs and score them against ground truth.

    slipd eval LOG [--truth TRUTH] [--estimator NAME,...|all] [--profile P] [--min-speed KPH]
               [--mismatch all|CASE,...] [--json] [--out FILE.json] [--plot FILE.png|.pdf|.svg]
    slipd eval --suite DIR [same options]
    slipd eval LOG... [--dask local[:N]|tcp://HOST:PORT] [same options]

Several logs (or a quoted glob) are scored like a suite, each with its LOG.truth.csv; with
``--dask`` one task per log (and mismatch case) on dask.distributed, pooled in the logs'
order, so the figures equal a run without it; a log that fails is reported and left out of
the pooled figures, and the command exits 1.

Without ``--mismatch`` every log is scored with the profile as given; with it, the nominal
profile first and then each mismatch case (slipd.eval.mismatch), one at a time, every log of
the run each time, and a table per case plus the cases pooled.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
from pathlib import Path

from slipd.errors import ConfigError
from slipd.eval.metrics import Accumulator, format_table
from slipd.eval.runs import CaseResult, LogCase, evaluate_logs, jsonable, suite_logs, truth_of

NOMINAL = "nominal"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", nargs="*", type=Path,
                        help="candump -L log(s), or a quoted glob ('logs/*.log')")
    parser.add_argument("--truth", type=Path,
                        help="truth CSV of the log (default LOG without .log + .truth.csv)")
    parser.add_argument("--suite", type=Path, metavar="DIR",
                        help="evaluate every DIR/*.log with its DIR/*.truth.csv")
    parser.add_argument("--estimator", default="all",
                        help="estimator name, comma-separated names, or 'all' (default); "
                             "METHOD:KEY=VALUE[:KEY=VALUE...] scores a method with parameters "
                             "set (kinematic_heuristic:steady_gain=0: the paper's observer)")
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
                        help="a single log: beta over time, VALID spans, error over time and "
                             "the error CDF (small multiples beyond 4 methods); a suite or "
                             "--mismatch: heatmaps of RMS and VALID > 5 deg per scenario or "
                             "case, and FILE's stem + .cdf: the pooled error CDFs (PNG, PDF or "
                             "SVG by suffix)")
    parser.add_argument("--plot-inputs", action="store_true",
                        help="a single log's plot also shows ay, yaw rate, steer and speed")
    parser.add_argument("--dask", metavar="local[:N]|tcp://HOST:PORT",
                        help="score one log per task on dask.distributed (a local cluster of "
                             "N workers, or a running scheduler)")
    parser.add_argument("--chunk-mb", type=float, default=None, metavar="MB",
                        help="log text decoded per chunk (default 2)")


def _methods(spec: str) -> list[str]:
    from slipd.estimators.registry import parse_names

    return parse_names(spec)


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
    from slipd.commands.replay import _chunk_bytes
    from slipd.replay.stream import keep_freed_memory

    keep_freed_memory()
    logs = _logs(args)
    single_plot = args.plot is not None and len(logs) == 1 and args.suite is None and not cases
    with contextlib.ExitStack() as stack:
        client = None
        if args.dask:
            from slipd.replay.fleet import dask_client

            client = stack.enter_context(dask_client(args.dask, methods, args.profile))
        options = dict(client=client, profile_spec=args.profile,
                       chunk_bytes=_chunk_bytes(args.chunk_mb))
        nominal, plot_data, single = evaluate_logs(logs, methods, load_profile(args.profile),
                                                   args.min_speed, keep_last=single_plot,
                                                   **options)
        results = [nominal]
        for case in cases:
            print(f"mismatch {case.name}: {case.description}", file=sys.stderr)
            perturbed = load_profile(args.profile, edit=case.edit())
            results.append(evaluate_logs(logs, methods, perturbed, args.min_speed, case.name,
                                         case.description, **options)[0])
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
    failed = {(case.name, log): error for case in results for log, error in case.failed.items()}
    for (case, log), error in failed.items():
        print(f"slipd eval: {log} ({case}) not scored: {error}", file=sys.stderr)
    if failed:
        print(f"slipd eval: {len({log for _, log in failed})} of {len(logs)} logs failed; the "
              "pooled figures leave them out", file=sys.stderr)
        return 1
    return 0


def _logs(args: argparse.Namespace) -> list[LogCase]:
    """The logs to score: --suite DIR's, or LOG... (globs expanded) with their truths."""
    from slipd.replay.fleet import expand_logs

    if args.suite is not None:
        if args.log:
            raise ConfigError("give either LOGs or --suite DIR, not both")
        return suite_logs(args.suite)
    if not args.log:
        raise ConfigError("name a LOG (with --truth TRUTH) or use --suite DIR")
    paths = expand_logs(args.log)
    if args.truth is not None and len(paths) > 1:
        raise ConfigError("--truth takes one log; several logs use their LOG.truth.csv")
    names = [p.name for p in paths]
    if len(set(names)) < len(names):  # the same file name in two folders: name by path
        names = [str(p) for p in paths]
    return [LogCase(name, p, args.truth or truth_of(p)) for name, p in zip(names, paths,
                                                                          strict=True)]


def _document(args, methods, logs, results: list[CaseResult], mismatch_pooled) -> dict:
    nominal = results[0]
    doc: dict = {"profile": str(args.profile), "min_speed_kph": args.min_speed,
                 "estimators_evaluated": methods}
    if args.suite is None and len(logs) == 1:
        doc.update(jsonable(nominal.overall()))
        doc["log"] = str(logs[0].log)
    else:
        doc["scenarios"] = {name: jsonable(rows) for name, rows in nominal.logs.items()}
        doc["overall"] = jsonable(nominal.overall())
    if mismatch_pooled is not None:
        doc["mismatch"] = {
            "cases": {c.name: {"description": c.description, **jsonable(c.overall()),
                               "scenarios": {n: jsonable(r) for n, r in c.logs.items()}}
                      for c in results[1:]},
            "pooled": jsonable({m: a.scores() for m, a in mismatch_pooled.items()}),
        }
    return doc


def _print_tables(args, logs, results: list[CaseResult], mismatch_pooled, single) -> None:
    nominal = results[0]
    speed = f"truth speed > {args.min_speed:g} km/h"
    if args.suite is None and len(logs) == 1:
        print(format_table(nominal.overall(), title=f"== {logs[0].name} ({speed})"))
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
        inputs = (_input_series(logs[0].log, args.profile, plot_data["series"])
                  if args.plot_inputs else None)
        plots.plot_evaluation(args.plot, plot_data["truth_t"], plot_data["truth_beta"],
                              plot_data["series"], single, title=logs[0].name, inputs=inputs)
        print(f"figure -> {args.plot}", file=sys.stderr)
        return
    nominal = results[0]
    if mismatch_pooled is not None:
        groups = {c.name: c.overall() for c in results}
        pooled, accumulators = {m: a.scores() for m, a in mismatch_pooled.items()}, \
            mismatch_pooled
        what = f"mismatch cases ({len(logs)} log(s) per case)"
        cdf_title = f"|beta error|, the {len(results) - 1} mismatch cases pooled"
    else:
        groups, pooled, accumulators = nominal.logs, nominal.overall(), nominal.pooled
        what = f"suite {args.suite}" if args.suite is not None else logs[0].name
        cdf_title = f"|beta error|, {what}, all logs pooled"
    plots.plot_summary(args.plot, groups, title=what, pooled=pooled)
    cdf = args.plot.with_name(args.plot.stem + ".cdf" + args.plot.suffix)
    plots.plot_summary_cdf(cdf, accumulators, title=cdf_title)
    print(f"figures -> {args.plot}, {cdf}", file=sys.stderr)


def _input_series(log: Path, profile: str, series: dict) -> dict:
    """ay, yaw rate, steer and wheel speeds of a log as the estimators saw them (latched), on
    the time axis of the plot's ``series`` (the truth's)."""
    from slipd.channels import VALID, In
    from slipd.eval.plots import input_series
    from slipd.profile import load_profile
    from slipd.replay.engine import latch_log_or_recording
    from slipd.replay.readers import read_frames

    inputs = latch_log_or_recording(read_frames(log), load_profile(profile))
    shown_t, _ = next(iter(series.values()))
    shift = inputs.t[0] - shown_t[0] if len(inputs.t) and len(shown_t) else 0.0

    def channel(name: str):
        ch = In[name.upper()]
        return inputs.U[:, ch], inputs.U[:, VALID + ch] > 0.5

    return input_series(inputs.t - shift, channel)
