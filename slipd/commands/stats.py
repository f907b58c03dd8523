"""``slipd stats``: a running daemon's latency statistics and counters (unix socket)."""

from __future__ import annotations

import argparse
import json
import time


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--socket", default="/run/slipd/stats.sock",
                        help="the daemon's --stats-socket (default /run/slipd/stats.sock)")
    parser.add_argument("--json", action="store_true", help="print the raw snapshot")
    parser.add_argument("--watch", type=float, nargs="?", const=1.0, metavar="S",
                        help="refresh every S seconds (default 1)")


def _table(snapshot: dict) -> str:
    c = snapshot["counters"]
    lines = [f"slipd {snapshot.get('estimator', '?')}: beta "
             f"{snapshot.get('beta_deg', 0):+.2f} deg, status {snapshot.get('status', 0):#04x}, "
             f"up {snapshot.get('uptime_s', 0):.0f} s",
             f"{'histogram (us)':<22}{'count':>9}{'p50':>8}{'p99':>8}{'p99.9':>8}{'max':>8}"]
    from slipd.daemon.stats import HISTOGRAMS

    for name in HISTOGRAMS:
        h = snapshot.get(name)
        if h is None:  # a daemon of an older version
            continue
        lines.append(f"{name:<22}{h['count']:>9}{h['p50']:>8}{h['p99']:>8}{h['p99.9']:>8}"
                     f"{h['max']:>8}")
    lines.append("counters: " + ", ".join(f"{k} {v}" for k, v in c.items()))
    for message, counts in snapshot.get("decode_errors", {}).items():
        bad = {k: v for k, v in counts.items() if k != "accepted" and v}
        if bad:
            lines.append(f"  {message}: {bad}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """One snapshot, or one every ``--watch`` seconds. While watching, a daemon that does not
    answer (restarting, say) is reported on the screen and asked again, not the end."""
    from slipd.daemon.stats import query
    from slipd.errors import SlipdError

    if args.watch is not None and not args.watch > 0:
        raise SlipdError(f"--watch {args.watch}: expected a number of seconds > 0")
    while True:
        try:
            snapshot = query(args.socket)
            text = json.dumps(snapshot, indent=1) if args.json else _table(snapshot)
        except (OSError, ValueError) as exc:
            if not args.watch:
                raise SlipdError(f"no daemon answers on {args.socket}: {exc}") from exc
            text = f"no daemon answers on {args.socket}: {exc} (asking again)"
        print(text, flush=True)
        if not args.watch:
            return 0
        time.sleep(args.watch)
        print("\033[2J\033[H", end="")
