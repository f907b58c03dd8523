"""``slipd warmup``: compile the daemon's kernels into the numba cache, at install time.

On a fresh car PC the cache is empty and the first ``slipd run`` compiles every kernel of its
estimator before READY=1 (53 s measured for ``ensemble``, against the unit's 60 s
TimeoutStartSec: a restart loop on first boot). Run this once after installing or upgrading,
as the service's user and with the service's numba environment, so the daemon starts from a
warm cache (~1 s)::

    sudo -u slipd env NUMBA_CACHE_DIR=/var/cache/slipd/numba NUMBA_CPU_NAME=generic \\
        /opt/slipd/.venv/bin/slipd warmup --config /etc/slipd/slipd.toml

It runs exactly the daemon's warm-up (the tick's kernels and the decode path) for the
configured profile and estimator, on a private virtual bus, touching no CAN interface.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from slipd.commands.run import SYSTEM_CONFIG

    parser.add_argument("--config", type=Path, default=None,
                        help=f"the daemon's TOML config (default {SYSTEM_CONFIG} when it "
                             "exists): its profile and estimator")
    parser.add_argument("--profile", help="vehicle profile name or TOML path")
    parser.add_argument("--estimator",
                        help="method, comma-separated methods, or 'all' (default: the "
                             "config's, else the daemon's default)")


def run(args: argparse.Namespace) -> int:
    from slipd.commands.run import _settings, _skip_numba_blas_probe

    _skip_numba_blas_probe()  # the daemon's process does the same
    from slipd.daemon.loop import Daemon, DaemonConfig
    from slipd.estimators.registry import parse_names
    from slipd.profile import load_profile

    settings = _settings(args)
    profile = load_profile(settings["profile"])
    names = parse_names(settings["estimator"])
    cache = os.environ.get("NUMBA_CACHE_DIR", "numba's default cache directory")
    print(f"slipd warmup: profile {profile.name}, {len(names)} estimator(s), cache {cache}",
          flush=True)
    started = time.perf_counter()
    import can

    for name in names:
        channel = f"slipd-warmup-{os.getpid()}"
        config = DaemonConfig(profile=profile, estimator=name, interface="virtual",
                              channel=channel)
        bus = can.Bus(interface="virtual", channel=channel)  # one for all the profile's buses
        try:
            seconds = Daemon(config, bus=bus, log=lambda _line: None).warm_up()
        finally:
            bus.shutdown()
        print(f"  {name}: {seconds:.1f} s", flush=True)
    print(f"slipd warmup: done in {time.perf_counter() - started:.1f} s", flush=True)
    return 0
