"""``slipd run``: the real-time daemon (or ``--demo`` on a virtual bus with a simulated drive)."""

from __future__ import annotations

import argparse
import math
import os
import sys
import tomllib
from collections.abc import Callable
from pathlib import Path

from slipd.estimators import registry

SYSTEM_CONFIG = Path("/etc/slipd/slipd.toml")


def _text(value: object) -> str:
    if not isinstance(value, str) or not value.strip():
        raise ValueError("expected a non-empty string")
    return value


def _flag(value: object) -> bool:
    """Only true or false: bool("false") is True, which once locked memory when asked not
    to (`mlockall = "false"`)."""
    if not isinstance(value, bool):
        raise ValueError("expected true or false (a TOML boolean, not a string)")
    return value


def _integer(low: int, high: int, note: str = "") -> Callable[[object], int]:
    def check(value: object) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            raise ValueError(f"expected an integer {low}..{high}{note}")
        return value
    return check


def _number(low: float, high: float, note: str = "") -> Callable[[object], float]:
    def check(value: object) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float) or \
                not math.isfinite(value) or not low <= value <= high:
            raise ValueError(f"expected a number {low:g}..{high:g}{note}")
        return float(value)
    return check


def _bus_table(value: object) -> dict[str, str]:
    if not isinstance(value, dict) or not all(isinstance(k, str) and isinstance(v, str)
                                              for k, v in value.items()):
        raise ValueError('expected a table NAME = "CHANNEL"')
    return value


def _table(value: object) -> dict:
    if not isinstance(value, dict):
        raise ValueError("expected a table KEY = VALUE")
    return value


def _prometheus(value: object) -> str | int:
    if isinstance(value, bool) or not isinstance(value, int | str):
        raise ValueError('expected "HOST:PORT" (e.g. "127.0.0.1:9464") or a port number')
    return value


#: config-file keys (the options' names, with underscores) and their checks
CONFIG_KEYS: dict[str, Callable[[object], object]] = {
    "profile": _text, "interface": _text, "channel": _text, "estimator": _text,
    "recorder": _text, "recorder_max_mb": _number(0.01, 1 << 20, " MB"),
    "recorder_keep": _integer(0, 10_000, " rotated files"), "recorder_compress": _flag,
    "stats_socket": _text, "stats_socket_mode": _integer(0, 0o777, " (e.g. 0o660)"),
    "prometheus": _prometheus, "prometheus_public": _flag, "state_file": _text,
    "sched_fifo": _integer(0, 99, " (0 = off)"), "cpu": _integer(0, 4095),
    "mlockall": _flag, "timer_slack_ns": _integer(1, 10_000_000, " ns (1 = no slack)"),
    "gc_freeze": _flag, "spin_us": _integer(0, 4999, " us (0 = off)"),
    "silence_warning_s": _number(0, 86400, " s (0 = off)"),
    "buses": _bus_table, "bitrate": _integer(1, 20_000_000, " bit/s"), "fd": _flag,
    "bus_kwargs": _table, "listen_only": _flag,
}
DEFAULTS = {"profile": "default", "interface": "socketcan", "channel": "can0",
            "estimator": registry.DEFAULT_ESTIMATOR, "sched_fifo": 0, "mlockall": False,
            "gc_freeze": False, "spin_us": 0, "recorder_max_mb": 256.0, "recorder_keep": 10,
            "recorder_compress": True, "stats_socket_mode": 0o660, "prometheus_public": False,
            "silence_warning_s": 5.0}


def parse_bus_map(entries: list[str]) -> dict[str, str]:
    """``--bus NAME=CHANNEL`` entries -> {profile bus name: interface channel}."""
    from slipd.errors import ConfigError

    mapping: dict[str, str] = {}
    for entry in entries:
        for item in filter(None, (part.strip() for part in entry.split(","))):
            name, sep, channel = item.partition("=")
            if not sep or not name or not channel:
                raise ConfigError(f"--bus {item!r}: expected BUS=CHANNEL, e.g. chassis=can0")
            if name in mapping:
                raise ConfigError(f"--bus {name}: given twice ({mapping[name]!r}, {channel!r})")
            mapping[name] = channel
    return mapping


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", type=Path, default=None,
                        help=f"TOML config file (default {SYSTEM_CONFIG} when it exists); "
                             "command-line options override it")
    parser.add_argument("--profile", help="vehicle profile name or TOML path (default: default)")
    bus = parser.add_argument_group(
        "CAN bus (python-can's conventions; its config file ~/can.conf or $CAN_INTERFACE/"
        "$CAN_CHANNEL fill what neither these options nor --config give)")
    bus.add_argument("-i", "--interface", help="python-can interface (default socketcan)")
    bus.add_argument("-c", "--channel", help="bus channel of a one-bus profile (default can0)")
    bus.add_argument("--bus", action="append", default=None, metavar="NAME=CHANNEL",
                     help="the channel of the profile's bus NAME, e.g. --bus chassis=can0 "
                          "--bus pt=can1")
    bus.add_argument("--bitrate", type=int, help="bit rate, for interfaces that set it")
    bus.add_argument("--fd", action="store_true", default=None,
                     help="CAN FD frames (on by itself where the profile has FD frames)")
    bus.add_argument("--bus-kwargs", nargs="+", default=None, metavar="KEY=VALUE",
                     help="more arguments for python-can's Bus(), e.g. receive_own_messages=1")
    bus.add_argument("--listen-only", action="store_true", default=None,
                     help="estimate and record, send nothing (a first drive on an unknown car)")
    parser.add_argument("--estimator", help=f"method (default {registry.DEFAULT_ESTIMATOR}); "
                        "METHOD:KEY=VALUE[:KEY=VALUE...] sets its parameters")
    parser.add_argument("--duration", type=float, help="stop after S seconds")
    parser.add_argument("--recorder", type=Path, help="flight-recorder candump log")
    parser.add_argument("--recorder-max-mb", type=float, metavar="MB",
                        help="rotate the recording at this size (default 256)")
    parser.add_argument("--recorder-keep", type=int, metavar="N",
                        help="rotated recordings kept, compressed (default 10)")
    parser.add_argument("--stats-socket", help="unix socket for `slipd stats`")
    parser.add_argument("--prometheus", metavar="HOST:PORT",
                        help="serve Prometheus metrics (loopback, e.g. 127.0.0.1:9464)")
    parser.add_argument("--prometheus-public", action="store_true", default=None,
                        help="allow --prometheus on a non-loopback address")
    parser.add_argument("--state-file", type=Path, help="persisted offsets/mu (JSON)")
    parser.add_argument("--silence-warning", type=float, dest="silence_warning_s",
                        metavar="S", help="warn when the bus delivers no frame for S seconds "
                                          "(default 5, 0 = off)")
    rt = parser.add_argument_group("real-time settings (each reported; refused = error)")
    rt.add_argument("--sched-fifo", type=int, metavar="PRIO", help="SCHED_FIFO priority")
    rt.add_argument("--cpu", type=int, help="pin to this CPU")
    rt.add_argument("--mlockall", action="store_true", default=None, help="lock memory")
    rt.add_argument("--timer-slack-ns", type=int, help="timer slack (1 = none)")
    rt.add_argument("--gc-freeze", action="store_true", default=None,
                    help="freeze and disable the garbage collector")
    rt.add_argument("--spin-us", type=int, metavar="US",
                    help="warm the tick's code and poll the bus without sleeping for the last "
                         "US microseconds before each tick (costs that share of a core)")
    demo = parser.add_argument_group("demo")
    demo.add_argument("--demo", action="store_true",
                      help="run on a python-can virtual bus fed by a simulated drive")
    demo.add_argument("--scenario", default="double_lane_change",
                      help="demo scenario (default double_lane_change)")


def read_config(path: Path) -> dict:
    """A config file's settings, each checked: a wrong key or value is a ConfigError naming
    the file, the key, the value and what was expected."""
    from slipd.errors import ConfigError

    try:
        document = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read config: {exc}") from exc
    unknown = set(document) - set(CONFIG_KEYS)
    if unknown:
        raise ConfigError(f"{path}: unknown key(s) {sorted(unknown)}; expected "
                          f"{sorted(CONFIG_KEYS)}")
    return {key: _checked(key, value, str(path)) for key, value in document.items()}


def _checked(key: str, value: object, source: str) -> object:
    from slipd.errors import ConfigError

    try:
        return CONFIG_KEYS[key](value)
    except ValueError as exc:
        raise ConfigError(f"{source}: {key} = {value!r}: {exc}") from exc


def _settings(args: argparse.Namespace) -> dict:
    settings = dict(DEFAULTS)
    path = args.config or (SYSTEM_CONFIG if SYSTEM_CONFIG.exists() else None)
    document_keys: set[str] = set()
    if path is not None:
        document = read_config(path)
        settings.update(document)
        document_keys = set(document)
    for key in CONFIG_KEYS:
        if key in ("buses", "bus_kwargs"):  # options of their own shape, parsed below
            continue
        value = getattr(args, key, None)
        if value is not None:
            option = "--" + key.replace("_", "-").removesuffix("-s")
            settings[key] = _checked(key, str(value) if isinstance(value, Path) else value,
                                     f"option {option}")
    if getattr(args, "bus", None):
        settings["buses"] = parse_bus_map(args.bus)
    if getattr(args, "bus_kwargs", None):
        settings["bus_kwargs"] = parse_bus_kwargs(args.bus_kwargs)
    _python_can_config(settings, given={k for k in ("interface", "channel", "bitrate", "fd")
                                        if getattr(args, k, None) is not None
                                        or (document_keys and k in document_keys)})
    _check_bus_settings(settings, path)
    return settings


def parse_bus_kwargs(entries: list[str]) -> dict:
    """``KEY=VALUE`` -> {key: value}, values as python-can's CLI reads them (int, float,
    true/false, else text)."""
    from slipd.errors import ConfigError

    result = {}
    for entry in entries:
        key, sep, text = entry.partition("=")
        if not sep or not key.isidentifier():
            raise ConfigError(f"--bus-kwargs {entry!r}: expected KEY=VALUE")
        value: object = text
        for cast in (int, float):
            try:
                value = cast(text)
                break
            except ValueError:
                continue
        if text.lower() in ("true", "false"):
            value = text.lower() == "true"
        result[key] = value
    return result


def _python_can_config(settings: dict, given: set[str]) -> None:
    """Fill interface/channel/bitrate/fd not given on the command line or in --config from
    python-can's own configuration (~/can.conf, ~/.canrc, can.ini, $CAN_INTERFACE, ...)."""
    try:
        import can

        found = can.util.load_config(config={k: settings[k] for k in given if k in settings})
    except Exception:  # noqa: BLE001 - no python-can config: slipd's defaults stand
        return
    for key in ("interface", "channel", "bitrate", "fd"):
        if key not in given and found.get(key) not in (None, ""):
            settings[key] = found[key]


def _check_bus_settings(settings: dict, path) -> None:
    from slipd.errors import ConfigError

    where = f"{path}: " if path else ""
    buses = settings.get("buses", {})
    if not isinstance(buses, dict) or not all(isinstance(k, str) and isinstance(v, str)
                                              for k, v in buses.items()):
        raise ConfigError(f"{where}buses = {buses!r}; expected a table NAME = \"CHANNEL\"")
    for key, kind in (("bitrate", int), ("fd", bool), ("listen_only", bool),
                      ("bus_kwargs", dict), ("channel", str), ("interface", str)):
        value = settings.get(key)
        if value is not None and (not isinstance(value, kind) or (
                kind is int and isinstance(value, bool))):
            raise ConfigError(f"{where}{key} = {value!r}; expected {kind.__name__}")


def daemon_config(args: argparse.Namespace):
    """The DaemonConfig of ``slipd run``'s options and config file, every value checked."""
    from slipd.daemon.loop import DaemonConfig
    from slipd.daemon.service import RealtimeOptions
    from slipd.errors import ConfigError
    from slipd.profile import load_profile

    s = _settings(args)
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise ConfigError(f"--duration {args.duration}: expected a number of seconds > 0")
    if s.get("cpu") is not None and s["cpu"] >= (os.cpu_count() or 1):
        raise ConfigError(f"cpu = {s['cpu']}: this machine has CPUs 0..{(os.cpu_count() or 1) - 1}")
    return DaemonConfig(
        profile=load_profile(s["profile"]), estimator=s["estimator"],
        interface=s["interface"], channel=str(s["channel"]), buses=dict(s.get("buses") or {}),
        fd=s.get("fd"), bitrate=s.get("bitrate"), bus_kwargs=dict(s.get("bus_kwargs") or {}),
        listen_only=bool(s.get("listen_only")),
        recorder=Path(s["recorder"]) if s.get("recorder") else None,
        recorder_max_bytes=int(s["recorder_max_mb"] * 2**20),
        recorder_keep=s["recorder_keep"], recorder_compress=s["recorder_compress"],
        stats_socket=s.get("stats_socket"), stats_socket_mode=s["stats_socket_mode"],
        prometheus=s.get("prometheus"), prometheus_public=s["prometheus_public"],
        state_file=Path(s["state_file"]) if s.get("state_file") else None,
        realtime=RealtimeOptions(sched_fifo=s["sched_fifo"], cpu=s.get("cpu"),
                                 mlockall=s["mlockall"], timer_slack_ns=s.get("timer_slack_ns"),
                                 gc_freeze=s["gc_freeze"], spin_us=s["spin_us"]),
        duration=args.duration, silence_warning_s=s["silence_warning_s"],
    )


def _skip_numba_blas_probe() -> None:
    """Keep numba from importing scipy.linalg in the daemon's process.

    numba probes for BLAS when it registers its array functions (numba.np.arraymath imports
    scipy.linalg.cython_blas whenever scipy is installed), which cost the daemon's start
    ~200 ms and 16 MB of peak RSS (measured) for BLAS and LAPACK it never calls: no kernel
    uses np.linalg or np.dot, and a vehicle install (no ``sim`` extra) has no scipy at all.
    Marking the module absent makes a workstation with scipy start the daemon as a vehicle
    does. A kernel that did need BLAS would fail to compile at the warm-up, before READY=1,
    with numba's "scipy 0.16+ is required for linear algebra".
    """
    if "numba" not in sys.modules:
        sys.modules.setdefault("scipy.linalg.cython_blas", None)


def _skip_mf4_reader() -> None:
    """Keep python-can from importing asammdf (and with it pandas, pyarrow, lxml, canmatrix)
    in the daemon's process.

    ``import can`` imports its MF4 reader and writer, which import asammdf when it is
    installed (the ``mf4`` extra, every dev install): 76 MB of the daemon's 185 MB running
    RSS (measured). The daemon reads a bus and records candump text; python-can treats a
    missing asammdf as an absent optional format and only disables its MF4 classes."""
    if "can" not in sys.modules:
        sys.modules.setdefault("asammdf", None)


def run(args: argparse.Namespace) -> int:
    if args.demo:
        from slipd.daemon.demo import run_demo

        return run_demo(args)
    _skip_numba_blas_probe()
    _skip_mf4_reader()
    from slipd.daemon.loop import Daemon

    daemon = Daemon(daemon_config(args))
    snapshot = daemon.run()
    c = snapshot["counters"]
    lat = snapshot["cycle_latency_us"]
    print(f"slipd: stopped after {c['ticks']} ticks: {c['deadline_misses']} deadline misses, "
          f"cycle latency us p50 {lat['p50']} p99 {lat['p99']} max {lat['max']}")
    return 0
