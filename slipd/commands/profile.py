"""``slipd profile``: the first tools on a new car.

    slipd profile scaffold DBC --out P.toml     propose a profile from the DBC (REVIEW marks)
    slipd profile check LOG --profile P         signs, units, rates, E2E on a real log
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    scaffold = sub.add_parser("scaffold", help="propose a profile from a DBC's signal names, "
                              "units and comments, every guess marked for review")
    scaffold.add_argument("dbc", type=Path, metavar="DBC")
    scaffold.add_argument("--out", type=Path, required=True, metavar="P.toml")
    scaffold.add_argument("--name", help="profile name (default: the file's stem)")
    scaffold.add_argument("--force", action="store_true", help="overwrite --out")
    check = sub.add_parser("check", help="check a profile on a real log without ground truth: "
                           "signs, units, rates and timeouts, E2E, stuck or missing signals")
    check.add_argument("log", type=Path, metavar="LOG")
    check.add_argument("--profile", required=True, help="profile name or TOML path")
    check.add_argument("--bus", action="append", default=[], metavar="BUS=CHANNEL",
                       help="read the profile's bus BUS from the log's channel CHANNEL")
    check.add_argument("--skip-bad", action="store_true",
                       help="count and skip malformed log lines instead of failing")


def run(args: argparse.Namespace) -> int:
    from slipd.errors import ConfigError

    if args.action == "scaffold":
        from slipd.profile_tools.scaffold import scaffold_text

        if not args.dbc.exists():
            raise ConfigError(f"{args.dbc}: no such DBC file")
        if args.out.exists() and not args.force:
            raise ConfigError(f"--out {args.out} exists; use --force to overwrite it")
        text = scaffold_text(args.dbc, args.out, args.name or args.out.stem)
        args.out.write_text(text, encoding="utf-8")
        reviews = text.count("REVIEW")
        print(f"{args.out}: proposed from {args.dbc.name}, {reviews} REVIEW mark(s) to "
              f"confirm; then drive and run: slipd profile check LOG --profile {args.out}")
        return 0
    from slipd.commands.run import parse_bus_map
    from slipd.profile import load_profile
    from slipd.profile_tools.check import check_profile_on_log
    from slipd.replay.readers import read_frames

    profile = load_profile(args.profile)
    report = check_profile_on_log(read_frames(args.log, skip_bad=args.skip_bad), profile,
                                  parse_bus_map(args.bus) or None)
    print(f"{args.log} with profile {profile.name}: {report.text()}")
    return 0 if report.passed else 1
