"""``slipd decode LOG --profile P --out inputs.csv|.parquet``: slipd's SI input channels per
tick (as ``cantools decode`` shows raw signals): what the estimators are given."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", type=Path, metavar="LOG")
    parser.add_argument("--profile", default="default", help="profile name or TOML path")
    parser.add_argument("--out", type=Path, required=True, metavar="inputs.csv|.parquet")
    parser.add_argument("--bus", action="append", default=[], metavar="BUS=CHANNEL",
                        help="read the profile's bus BUS from the log's channel CHANNEL")
    parser.add_argument("--skip-bad", action="store_true",
                        help="count and skip malformed log lines instead of failing")


def run(args: argparse.Namespace) -> int:
    from slipd.commands.run import parse_bus_map
    from slipd.profile import load_profile
    from slipd.profile_tools.decode import decode_log, write_inputs

    profile = load_profile(args.profile)
    inputs = decode_log(args.log, profile, args.skip_bad, parse_bus_map(args.bus) or None)
    rows = write_inputs(args.out, inputs, profile)
    rejected = {name: {k: v for k, v in counts.items() if k not in ("accepted",) and v}
                for name, counts in inputs.errors.items()}
    rejected = {k: v for k, v in rejected.items() if v}
    print(f"{args.log} -> {args.out}: {rows} ticks of {len(profile.channels)} channels"
          + (f"; rejected or unavailable: {rejected}" if rejected else ""))
    return 0
