"""The ``slipd`` command: one entry point, one module per subcommand (slipd.commands.*).

Subcommand modules are imported lazily, only the one that runs, so ``slipd --help`` stays fast,
the daemon's process holds none of the others' imports, and a subcommand whose optional
dependency is missing says so instead of breaking the others.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import os
import sys

from slipd.errors import SlipdError

#: name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("slipd.commands.run", "run the real-time daemon on a CAN bus (or --demo)"),
    "replay": ("slipd.commands.replay", "replay logs offline through the estimators, or "
               "play them onto a bus in real time"),
    "sim": ("slipd.commands.sim", "simulate scenarios: candump log + ground truth"),
    "eval": ("slipd.commands.eval", "evaluate estimators on logs against ground truth"),
    "stats": ("slipd.commands.stats", "show a running daemon's latency statistics"),
    "warmup": ("slipd.commands.warmup", "compile the daemon's kernels into the numba cache "
               "(once at install time, so the service starts fast)"),
    "import": ("slipd.commands.import_log", "turn recorded signals (CSV, .mat) into a candump "
               "log through the codec"),
    "profile": ("slipd.commands.profile", "propose a profile from a DBC (scaffold) or check "
                "one on a real log (check)"),
    "decode": ("slipd.commands.decode", "decode a log into slipd's SI input channels per tick "
               "(CSV or Parquet)"),
    "identify": ("slipd.commands.identify", "identify the car's parameters and sensor errors "
                 "from ordinary drives into a profile copy"),
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser; ``command`` given, only that subcommand's module is imported (its
    arguments added) and the others are listed by their help text: the daemon's process
    must not load what eval, sim or identify import (numba before run's BLAS guard, scipy;
    measured +15 MB RSS). ``None``: every subcommand's arguments."""
    parser = argparse.ArgumentParser(
        prog="slipd",
        description="Real-time vehicle sideslip estimation: CAN in, sideslip frames out.",
    )
    parser.add_argument("--version", action="version", version=_version())
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module_name, help_text) in COMMANDS.items():
        command_parser = sub.add_parser(name, help=help_text, description=help_text)
        command_parser.set_defaults(_module=module_name)
        if command is not None and name != command:
            continue
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name and exc.name.startswith("slipd."):
                command_parser.set_defaults(_missing=f"{name} is not available in this build")
                continue
            command_parser.set_defaults(
                _missing=f"{name} needs {exc.name}: pip install 'slipd[dev]'")
            continue
        module.add_arguments(command_parser)
    return parser


def _command_in(argv: list[str]) -> str | None:
    """The subcommand named in ``argv`` (its first word that is not an option), or None."""
    first = next((word for word in argv if not word.startswith("-")), None)
    return first if first in COMMANDS else None


@functools.lru_cache(maxsize=1)
def _version() -> str:
    """What made a file (the writers' ``created_by``): read once a process, it took 6 ms of
    package metadata, an eighth of a 10-minute log's replay (benchmarks/replay.py)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return f"slipd {version('slipd')}"
    except PackageNotFoundError:
        return "slipd (not installed)"


def main(argv: list[str] | None = None) -> int:
    from slipd.numba_cache import use_keyed_cache

    use_keyed_cache()  # before any kernel module is imported (the daemon's too)
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(_command_in(argv) or "")  # "": no subcommand's module imported
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    if getattr(args, "_missing", None):
        print(f"slipd: {args._missing}", file=sys.stderr)
        return 2
    module = importlib.import_module(args._module)
    try:
        return int(module.run(args) or 0)
    except SlipdError as exc:
        print(f"slipd {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # the reader left (`slipd stats --json | head -1`): not an error of slipd's; stdout
        # goes to /dev/null so the interpreter's final flush does not fail again
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
