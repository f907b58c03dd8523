"""``slipd import``: recorded signals (CSV, .mat) -> a candump log through the codec.

    slipd import drive.csv --profile default --time time_s:s \\
        --map ax_mps2=ax,ay_mps2=ay,yaw_dps=yaw_rate:deg/s,sw_deg=steer_wheel... --out drive.log
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", type=Path, metavar="FILE",
                        help="data-logger export: .csv (header row), .mat (MATLAB v5/v7) or a "
                             "signal-level .mf4 (its time column is t: s from the measurement "
                             "start)")
    parser.add_argument("--profile", default="default",
                        help="vehicle profile whose bus layout to write (default: default)")
    parser.add_argument("--map", action="append", default=[], required=True,
                        metavar="COLUMN=CHANNEL[:UNIT],...",
                        help="column to canonical channel with the column's unit (default SI); "
                             "'-' before the channel flips the sign (SAE y-right data); "
                             ".mat struct fields as a.b, matrix columns as m[0]")
    parser.add_argument("--time", metavar="COLUMN[:s|ms|us|ns]",
                        help="time column (default: the first of t, time, timestamp; seconds)")
    parser.add_argument("--epoch", type=float, default=0.0,
                        help="seconds added to the time column (e.g. the recording's Unix time)")
    parser.add_argument("--constant", action="append", default=[],
                        metavar="CHANNEL=VALUE[:UNIT]",
                        help="declare a channel the logger lacks as a constant (recorded in the "
                             "sidecar), e.g. az=9.81")
    parser.add_argument("--derive", action="append", default=[], choices=["wheel-speeds"],
                        help="derive wheel speeds from the vehicle speed (recorded in the "
                             "sidecar); needs --speed or a column mapped to speed_ref")
    parser.add_argument("--speed", metavar="COLUMN[:UNIT]",
                        help="vehicle speed column for --derive wheel-speeds")
    parser.add_argument("--truth", action="append", default=[], metavar="NAME=COLUMN[:UNIT],...",
                        help="reference-sensor columns to write as the log's truth CSV "
                             "(LOG.truth.csv, what slipd eval reads): beta and vx at least, "
                             "also vy, speed, yaw_rate, ...")
    parser.add_argument("--raster", type=float, metavar="S",
                        help="MF4 only: resample every channel onto an S-second grid by sample-"
                             "and-hold (default: the union of the channels' time stamps, each "
                             "channel only at its own samples); recorded in the sidecar")
    parser.add_argument("--interface", default="can0", help="interface name in the log")
    parser.add_argument("--out", type=Path, required=True, metavar="LOG",
                        help="candump -L log to write (LOG.meta.json is written beside it)")


def _raster(value: float | None) -> float | None:
    import math

    from slipd.errors import ConfigError

    if value is not None and not (math.isfinite(value) and value > 0):
        raise ConfigError(f"--raster {value}: expected a positive number of seconds")
    return value


def run(args: argparse.Namespace) -> int:
    import math

    from slipd.errors import ConfigError
    from slipd.profile import load_profile
    from slipd.replay.importer import (
        import_table,
        parse_constants,
        parse_map,
        parse_truth,
        sidecar_path,
    )

    if not math.isfinite(args.epoch):
        raise ConfigError(f"--epoch {args.epoch}: expected a finite number of seconds")
    report = import_table(
        args.source, load_profile(args.profile), parse_map(args.map), args.out,
        time_spec=args.time, epoch=args.epoch, constants=parse_constants(args.constant),
        derive=args.derive, speed_spec=args.speed, interface=args.interface,
        truth=parse_truth(args.truth), raster=_raster(args.raster),
    )
    print(f"{args.source} -> {args.out}: {report.summary()}")
    print(f"provenance: {sidecar_path(args.out)}")
    return 0
