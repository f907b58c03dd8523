"""``slipd run``: the real-time daemon (or ``--demo`` on a virtual bus with a simulated drive)."""

from __future__ import annotations

import argparse
import sys
import tomllib
from pathlib import Path

from slipd.estimators import registry

SYSTEM_CONFIG = Path("/etc/slipd/slipd.toml")
#: config-file keys (same names as the options, with underscores)
CONFIG_KEYS = {"profile", "interface", "channel", "estimator", "recorder", "stats_socket",
               "prometheus", "state_file", "sched_fifo", "cpu", "mlockall", "timer_slack_ns",
               "gc_freeze", "spin_us", "buses", "bitrate", "fd", "bus_kwargs", "listen_only"}


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
    parser.add_argument("--estimator", help=f"method (default {registry.DEFAULT_ESTIMATOR})")
    parser.add_argument("--duration", type=float, help="stop after S seconds")
    parser.add_argument("--recorder", type=Path, help="flight-recorder candump log")
    parser.add_argument("--stats-socket", help="unix socket for `slipd stats`")
    parser.add_argument("--prometheus", metavar="HOST:PORT",
                        help="serve Prometheus metrics (loopback by default, e.g. 127.0.0.1:9464)")
    parser.add_argument("--state-file", type=Path, help="persisted offsets/mu (JSON)")
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


def _settings(args: argparse.Namespace) -> dict:
    from slipd.errors import ConfigError

    settings = {"profile": "default", "interface": "socketcan", "channel": "can0",
                "estimator": registry.DEFAULT_ESTIMATOR, "sched_fifo": 0, "mlockall": False,
                "gc_freeze": False}
    path = args.config or (SYSTEM_CONFIG if SYSTEM_CONFIG.exists() else None)
    document_keys: set[str] = set()
    if path is not None:
        try:
            document = tomllib.loads(Path(path).read_text())
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise ConfigError(f"{path}: cannot read config: {exc}") from exc
        unknown = set(document) - CONFIG_KEYS
        if unknown:
            raise ConfigError(f"{path}: unknown key(s) {sorted(unknown)}; expected "
                              f"{sorted(CONFIG_KEYS)}")
        settings.update(document)
        document_keys = set(document)
    for key in CONFIG_KEYS:
        value = getattr(args, key, None)
        if value is not None:
            settings[key] = value
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


def run(args: argparse.Namespace) -> int:
    if args.demo:
        from slipd.daemon.demo import run_demo

        return run_demo(args)
    _skip_numba_blas_probe()
    from slipd.daemon.loop import Daemon, DaemonConfig
    from slipd.daemon.service import RealtimeOptions
    from slipd.profile import load_profile

    s = _settings(args)
    config = DaemonConfig(
        profile=load_profile(s["profile"]), estimator=s["estimator"],
        interface=s["interface"], channel=str(s["channel"]), buses=dict(s.get("buses") or {}),
        fd=s.get("fd"), bitrate=s.get("bitrate"), bus_kwargs=dict(s.get("bus_kwargs") or {}),
        listen_only=bool(s.get("listen_only")),
        recorder=Path(s["recorder"]) if s.get("recorder") else None,
        stats_socket=s.get("stats_socket"), prometheus=s.get("prometheus"),
        state_file=Path(s["state_file"]) if s.get("state_file") else None,
        realtime=RealtimeOptions(sched_fifo=int(s["sched_fifo"]), cpu=s.get("cpu"),
                                 mlockall=bool(s["mlockall"]),
                                 timer_slack_ns=s.get("timer_slack_ns"),
                                 gc_freeze=bool(s["gc_freeze"]),
                                 spin_us=int(s.get("spin_us") or 0)),
        duration=args.duration,
    )
    daemon = Daemon(config)
    snapshot = daemon.run()
    c = snapshot["counters"]
    lat = snapshot["cycle_latency_us"]
    print(f"slipd: stopped after {c['ticks']} ticks: {c['deadline_misses']} deadline misses, "
          f"cycle latency us p50 {lat['p50']} p99 {lat['p99']} max {lat['max']}")
    return 0
