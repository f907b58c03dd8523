"""``slipd identify``: the car's parameters and sensor errors from ordinary drives.

    slipd identify LOG... --profile P --out NEW.toml [--report DIR] [--only KEYS]
                   [--truth [CSV ...]] [--estimator NAME,...] [--bus BUS=CHANNEL]

Reads the logs through the codec (any format replay reads), finds each quantity from the
segments it is identifiable from (slipd.identify) and writes a copy of the profile with the
identified values, each commented with its method, data and 95 % interval; what the data
cannot support stays as it was and is listed with the reason. ``--truth`` (the truth CSV
beside each log, or one per log in order) adds a before/after table of the estimators on the
same logs (slipd.eval.runs.evaluate_logs).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from slipd.errors import ConfigError, DependencyError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from slipd.identify import QUANTITIES

    parser.add_argument("logs", nargs="+", type=Path, metavar="LOG",
                        help="drives recorded on the car's bus (candump, flight recorder, "
                             "anything replay reads)")
    parser.add_argument("--profile", default="default",
                        help="the car's profile to start from (name or path; default: default)")
    parser.add_argument("--out", type=Path, required=True, metavar="NEW.toml",
                        help="where to write the identified copy of the profile")
    parser.add_argument("--report", type=Path, metavar="DIR",
                        help="write summary.txt and the figures (handling diagram, fit "
                             "residuals, offsets over the drive) into DIR")
    parser.add_argument("--only", metavar="KEYS",
                        help=f"identify only these, comma-separated: {', '.join(QUANTITIES)}")
    parser.add_argument("--truth", nargs="*", type=Path, metavar="CSV",
                        help="evaluate the estimators before and after on the same logs: the "
                             "truth CSV beside each log (no value) or one per log, in order")
    parser.add_argument("--estimator", default=None, metavar="NAME,...",
                        help="estimators of the --truth table (default: d_ekf, the daemon's "
                             "default and linear_kf where it exists)")
    parser.add_argument("--bus", action="append", default=[], metavar="BUS=CHANNEL",
                        help="read the log's channel CHANNEL as the profile's bus BUS")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def _require() -> None:
    try:
        import scipy  # noqa: F401
        import tomlkit  # noqa: F401
    except ImportError as exc:
        raise DependencyError(
            f"slipd identify needs {exc.name}: pip install 'slipd[identify]'") from exc


def default_estimators() -> list[str]:
    """d_ekf, the daemon's default estimator and linear_kf where it exists."""
    import dataclasses

    from slipd.daemon.loop import DaemonConfig
    from slipd.estimators import available

    default = next(f.default for f in dataclasses.fields(DaemonConfig) if f.name == "estimator")
    names = available()
    chosen = [n for n in ("d_ekf", default, "linear_kf") if n in names]
    return list(dict.fromkeys(chosen))


def _estimators(spec: str | None) -> list[str]:
    from slipd.estimators import available

    if spec is None:
        return default_estimators()
    names = available()
    chosen = [s.strip() for s in spec.split(",") if s.strip()]
    unknown = [c for c in chosen if c not in names]
    if unknown or not chosen:
        raise ConfigError(f"--estimator {spec}: unknown {unknown}; available: "
                          f"{', '.join(names)}")
    return chosen


def truth_cases(logs: list[Path], truths: list[Path]):
    from slipd.eval.runs import LogCase, truth_of

    if truths and len(truths) != len(logs):
        raise ConfigError(f"--truth: {len(truths)} file(s) for {len(logs)} log(s); give one per "
                          "log, or none for the truth CSV beside each log")
    cases = []
    for i, log in enumerate(logs):
        truth = truths[i] if truths else truth_of(log)
        if not truth.exists():
            raise ConfigError(f"--truth: {truth} does not exist (the truth of {log})")
        cases.append(LogCase(log.name, log, truth))
    return cases


def before_after(cases, methods: list[str], before, after) -> tuple[list[str], dict]:
    """Beta RMS / p99 / VALID > 5 deg of each estimator with the old and the new profile."""
    from slipd.eval.runs import evaluate_logs

    old, _, _ = evaluate_logs(cases, methods, before, name="before")
    new, _, _ = evaluate_logs(cases, methods, after, name="after")
    rows = {"before": old.overall(), "after": new.overall()}
    lines = [f"estimators on the same logs (truth speed > 20 km/h), profile {before.name} "
             "before and after:",
             f"{'estimator':22s} {'RMS before':>10s} {'RMS after':>10s} {'change':>8s} "
             f"{'p99 before':>10s} {'p99 after':>10s} {'V>5deg b/a [%]':>15s}"]
    for m in methods:
        b, a = rows["before"][m], rows["after"][m]
        change = (a.beta_rms_deg / b.beta_rms_deg - 1.0) * 100.0 if b.beta_rms_deg else 0.0
        lines.append(f"{m:22s} {b.beta_rms_deg:10.3f} {a.beta_rms_deg:10.3f} {change:+7.1f}% "
                     f"{b.beta_p99_deg:10.3f} {a.beta_p99_deg:10.3f} "
                     f"{100 * b.valid_err_over_5deg:7.2f}/{100 * a.valid_err_over_5deg:<7.2f}")
    per_log = {name: {m: (s.beta_rms_deg, new.logs[name][m].beta_rms_deg)
                      for m, s in rows_.items()} for name, rows_ in old.logs.items()}
    return lines, {"overall": {k: {m: s.as_dict() for m, s in v.items()}
                               for k, v in rows.items()}, "per_log": per_log}


def run(args: argparse.Namespace) -> int:
    from slipd.commands.run import parse_bus_map
    from slipd.identify import identify, parse_only
    from slipd.profile import load_profile

    _require()
    only = parse_only(args.only)
    methods = _estimators(args.estimator) if args.truth is not None else []
    cases = truth_cases(list(args.logs), list(args.truth)) if args.truth is not None else []
    profile = load_profile(args.profile)
    if args.out.resolve() == profile.path.resolve():
        raise ConfigError(f"--out {args.out} is the profile itself; write the copy elsewhere")
    result = identify(args.logs, profile, only, progress=not args.quiet,
                      bus_map=parse_bus_map(args.bus) or None)
    from slipd.identify.profile_text import write_profile
    from slipd.identify.report import summary_lines, write_report

    write_profile(result, args.out)
    lines = summary_lines(result)
    print("\n".join(lines))
    print(f"\nwrote {args.out}")
    extra: list[str] = []
    if cases:
        print("evaluating the estimators before and after ...", file=sys.stderr)
        table, _ = before_after(cases, methods, profile, load_profile(args.out))
        print()
        print("\n".join(table))
        extra = ["", *table]
    if args.report is not None:
        files = write_report(result, args.report, extra)
        print(f"report: {', '.join(str(f) for f in files)}")
    return 0
