"""The stats server: the process that answers ``slipd stats`` and Prometheus for the daemon.

Started by the daemon (:class:`slipd.daemon.stats.StatsServer`), never by hand::

    python -m slipd.daemon.stats_server --memory-fd N --control-fd M \\
        [--unix PATH] [--prometheus [HOST]:PORT] [--socket-mode 0o660]

It reads the loop's histograms from the shared memory block (``--memory-fd``) and, when it
needs a fresh snapshot, asks the loop through the block (``requested``) to copy its counters
there; the loop sets ``answered`` when it has, and sends a JSON document of its words
(events, recorder status) over ``--control-fd`` only when they changed. At most one
question is outstanding, and every client waiting meanwhile gets the same answer, so 100
clients at once cost the loop one answer.
Clients of the unix socket get the snapshot as one JSON line (as
:func:`slipd.daemon.stats.query` reads it); Prometheus gets it through
``prometheus_client`` (latencies in seconds, as Prometheus' conventions say). Threads are
fine here: this process has its own GIL. It runs at a lower priority than the loop, off the
loop's CPU when the loop is pinned, and ends when the daemon closes its end of the control
socket (or dies), removing its socket file.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import select
import signal
import socket
import socketserver
import sys
import threading
import time
from collections.abc import Iterator

import numpy as np

from slipd.daemon.service import step_aside
from slipd.daemon.stats import (
    HISTOGRAMS,
    PER_ESTIMATOR,
    PERCENTILES,
    SOCKET_BACKLOG,
    SharedStats,
    StatsLayout,
    check_stats_socket,
    histogram_table,
)
from slipd.errors import ConfigError

SHARE_AGE_S = 0.02  # a snapshot at most this old is given to a new client as is
LOOP_PATIENCE_S = 1.0  # how long a client waits for the loop's answer
CONSISTENT_ATTEMPTS = 5  # answers asked for until the histograms' copy missed no tick

COUNTER_HELP = {
    "ticks": "ticks run (100 Hz)",
    "deadline_misses": "ticks whose frames were not sent before the next tick",
    "input_timeouts": "transitions into the INPUT_TIMEOUT status",
    "tx_errors": "output frames not sent",
    "rx_frames": "input frames received",
    "rx_overflows": "frames the kernel dropped from the daemon's full receive queue",
    "rx_malformed": "received datagrams that are no CAN frame (dropped)",
    "valid_ticks": "ticks whose SLIPD_STATE said VALID",
    "gc_full_collections": "full garbage collections in the daemon",
    "recorder_errors": "flight-recorder write failures (recording stopped)",
    "stats_server_restarts": "times this stats server was started again",
    "clock_steps": "steps of the wall clock the daemon measured (its time base is monotonic)",
    "consistency_fail_ticks": "ticks the consistency monitor failed the estimate (VALID cleared)",
    "consistency_warn_ticks": "ticks the consistency monitor warned (DEGRADED)",
    "consistency_innovation_ticks": "ticks the estimator's Kalman filter innovation test was "
                                    "beyond its level (DEGRADED, VALID cleared far beyond)",
    "consistency_imprecise_ticks": "ticks the calibrated sigma_beta was beyond what VALID "
                                   "promises (VALID cleared)",
    "consistency_witness_ticks": "ticks the dynamic witness was not tracking (its own "
                                 "innovation test far beyond its level): VALID cleared",
}


class SnapshotSource:
    """The latest snapshot, asked for from the loop when a client needs a fresh one.

    Clients call :meth:`get`; one collector thread makes the requests (the shared block's
    ``requested`` number), waits for the loop's ``answered`` and builds the snapshot, so a
    crowd of clients costs the loop one answer. :meth:`run` (the main thread) reads the
    loop's words from the control socket until the daemon closes it."""

    ANSWER_POLL_S = 0.0005

    def __init__(self, control: socket.socket, shared: SharedStats) -> None:
        self.control = control
        self.shared = shared
        self.words: dict = {}  # the loop's last words (estimator, events, recorder)
        self.table = histogram_table()
        self.changed = threading.Condition()
        self.latest: dict | None = None
        self.latest_at = -1.0
        self.wanted = threading.Event()
        self.reading = threading.Lock()  # the control socket: one reader at a time
        threading.Thread(target=self._collect, daemon=True).start()

    def get(self) -> dict:
        """A snapshot no older than SHARE_AGE_S, or the newest one with ``stale_s`` when the
        loop does not answer within LOOP_PATIENCE_S; TimeoutError when there is none."""
        with self.changed:
            now = time.monotonic()
            if self.latest is not None and now - self.latest_at <= SHARE_AGE_S:
                return self.latest
            self.wanted.set()
            self.changed.wait_for(lambda: self.latest_at >= now, timeout=LOOP_PATIENCE_S)
            if self.latest_at >= now:
                return self.latest
            if self.latest is not None:
                return dict(self.latest, stale_s=round(time.monotonic() - self.latest_at, 3))
            raise TimeoutError(f"no snapshot yet: the daemon's loop did not answer within "
                               f"{LOOP_PATIENCE_S} s (still starting: numba warm-up; or "
                               "stalled)")

    def _collect(self) -> None:
        while True:
            self.wanted.wait()
            self.wanted.clear()
            document = None
            for _attempt in range(CONSISTENT_ATTEMPTS):
                if not self._ask_loop():
                    break  # the loop is stalled (or stopped): clients get the stale one
                document, consistent = self._build()
                if consistent:
                    break
            if document is None:
                continue
            with self.changed:
                self.latest = document
                self.latest_at = time.monotonic()
                self.changed.notify_all()

    def _ask_loop(self) -> bool:
        """Ask the loop to publish its numbers; True once it has (within LOOP_PATIENCE_S)."""
        sequence = self.shared.sequence_words
        target = sequence[0] + 1
        sequence[0] = target  # the loop answers in its slack after the next tick
        deadline = time.monotonic() + LOOP_PATIENCE_S
        while sequence[1] != target and time.monotonic() < deadline:
            time.sleep(self.ANSWER_POLL_S)
        return sequence[1] == target

    def _build(self) -> tuple[dict, bool]:
        """The snapshot from the published numbers and the histograms, and whether it is
        one instant: the histograms, which the loop records into in place, are copied
        before its next tick (the live tick count is still the published one), so they
        hold exactly the ticks counted."""
        self._drain_words()
        document = {**self.shared.read(), **self.words}
        counts = [self.shared.counts(index).astype(np.int64)
                  for index in range(len(HISTOGRAMS))]
        # the loop counts a tick before it records the tick's values (Daemon._measure), and
        # x86 keeps stores in order and loads in order: a record seen in the copy means the
        # tick count read after it is ahead (weakly ordered CPUs give no such promise
        # without a fence, which Python cannot issue: there the check is best effort)
        consistent = self.shared.ticks_live() == document["counters"]["ticks"]
        for name, histogram in zip(HISTOGRAMS, counts, strict=True):
            document[name] = self.table.summary(histogram)
        return document, consistent

    def _drain_words(self) -> None:
        """Words the loop sent with this answer (it sends them before it sets answered).
        The main thread (run) may be reading them at the same time: under ``reading``
        either has stored them before the snapshot is built (a snapshot without the
        estimator's name was served when run had received them and not yet stored them)."""
        with self.reading:
            while True:
                try:
                    message = self.control.recv(1 << 22, socket.MSG_DONTWAIT)
                except OSError:  # BlockingIOError: none waiting
                    return
                if not message:
                    return
                self._store_words(message)

    def _store_words(self, message: bytes) -> None:
        words = json.loads(message)
        with self.changed:
            self.words = words

    def run(self) -> None:
        """Read the loop's words until the daemon closes the control socket (or dies)."""
        while True:
            try:
                select.select([self.control], [], [])
            except InterruptedError:
                continue
            except (OSError, ValueError):
                return
            with self.reading:
                try:
                    message = self.control.recv(1 << 22, socket.MSG_DONTWAIT)
                except (BlockingIOError, InterruptedError):
                    continue  # the collector took them
                except OSError:
                    return
                if not message:
                    return
                self._store_words(message)


class UnixStatsServer(socketserver.ThreadingMixIn, socketserver.UnixStreamServer):
    """One JSON line per connection; SOCKET_BACKLOG connections queue in the kernel."""

    daemon_threads = True
    request_queue_size = SOCKET_BACKLOG

    def __init__(self, path: str, mode: int, source: SnapshotSource) -> None:
        self.source = source
        check_stats_socket(path)  # again: after a restart the old server's file is there
        if os.path.lexists(path):
            os.unlink(path)  # stale (checked above): nobody answers on it
        super().__init__(path, _StatsRequest)
        os.chmod(path, mode)
        info = os.stat(path)
        self.identity = (info.st_dev, info.st_ino)

    def remove_socket_file(self) -> None:
        """Unlink the socket file only if it is still the one bound here."""
        try:
            info = os.stat(self.server_address)
        except OSError:
            return
        if (info.st_dev, info.st_ino) == self.identity:
            os.unlink(self.server_address)


class _StatsRequest(socketserver.BaseRequestHandler):
    def handle(self) -> None:
        try:
            document = self.server.source.get()
        except TimeoutError as exc:
            document = {"error": str(exc)}
        try:
            self.request.sendall(json.dumps(document).encode() + b"\n")
        except OSError:
            pass  # the client left


class SlipdCollector:
    """prometheus_client collector over the latest snapshot (SI units: seconds)."""

    def __init__(self, source: SnapshotSource) -> None:
        self.source = source

    def collect(self) -> Iterator:
        from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

        answering = "slipd_loop_answering"
        about = "1 while the daemon's loop answers the stats server (0: starting or stalled)"
        try:
            snapshot = self.source.get()
        except TimeoutError:
            # Before the loop's first answer (its numba warm-up at start): no figures yet;
            # raised, prometheus_client's server printed a traceback for every scrape.
            yield GaugeMetricFamily(answering, about, value=0)
            return
        yield GaugeMetricFamily(answering, about, value=0 if "stale_s" in snapshot else 1)
        for name, value in snapshot["counters"].items():
            if name in PER_ESTIMATOR:
                family = CounterMetricFamily(f"slipd_{name}", COUNTER_HELP.get(name, name),
                                             labels=["estimator"])
                family.add_metric([str(snapshot.get("estimator", ""))], value)
                yield family
            else:
                yield CounterMetricFamily(f"slipd_{name}", COUNTER_HELP.get(name, name),
                                          value=value)
        by_id = CounterMetricFamily("slipd_rx_frames_by_id", "input frames received per CAN ID",
                                    labels=["id"])
        for frame_id, count in snapshot.get("rx_per_id", {}).items():
            by_id.add_metric([frame_id], count)
        yield by_id
        decoded = CounterMetricFamily("slipd_decode_frames",
                                      "input frames per message and decode result",
                                      labels=["message", "result"])
        for message, counts in snapshot.get("decode_errors", {}).items():
            for result, count in counts.items():
                decoded.add_metric([message, result], count)
        yield decoded
        for name in HISTOGRAMS:
            h = snapshot[name]
            base = f"slipd_{name.removesuffix('_us')}_seconds"
            summary = Metric(base, f"{name.removesuffix('_us').replace('_', ' ')} (HDR "
                             "histogram since start)", "summary")
            for key, percentile in PERCENTILES.items():
                summary.add_sample(base, {"quantile": f"{percentile / 100:g}"}, h[key] * 1e-6)
            summary.add_sample(f"{base}_count", {}, h["count"])
            summary.add_sample(f"{base}_sum", {}, h["sum"] * 1e-6)
            yield summary
            yield GaugeMetricFamily(f"{base.removesuffix('_seconds')}_max_seconds",
                                    f"largest {name.removesuffix('_us').replace('_', ' ')}",
                                    value=h["max"] * 1e-6)
        gauges = (("beta_deg", "slipd_beta_radians", "latest sideslip estimate", np.radians),
                  ("vx_mps", "slipd_vx_meters_per_second", "latest longitudinal speed", None),
                  ("status", "slipd_status", "latest SLIPD_STATE status bits", None),
                  ("uptime_s", "slipd_uptime_seconds", "seconds since the loop started", None))
        for key, metric, help_text, convert in gauges:
            value = snapshot.get(key)
            if isinstance(value, int | float):
                yield GaugeMetricFamily(metric, help_text,
                                        value=float(convert(value)) if convert else value)


def _parse_address(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    return host.strip("[]") or "127.0.0.1", int(port)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m slipd.daemon.stats_server",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--memory-fd", type=int, required=True)
    parser.add_argument("--control-fd", type=int, required=True)
    parser.add_argument("--unix")
    parser.add_argument("--prometheus")
    parser.add_argument("--socket-mode", type=lambda text: int(text, 0), default=0o660)
    parser.add_argument("--layout", default=StatsLayout().to_json())
    args = parser.parse_args(argv)
    # The daemon stops this process by closing the control socket; a terminal's Ctrl-C or
    # systemd's stop signal to the whole group must not remove the socket under it first.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    step_aside()
    control = socket.socket(fileno=args.control_fd)
    source = SnapshotSource(control, SharedStats(StatsLayout.from_json(args.layout),
                                                 fd=args.memory_fd))
    unix_server = http_server = None
    bound: dict = {}
    try:
        if args.unix:
            unix_server = UnixStatsServer(args.unix, args.socket_mode, source)
            bound["unix"] = args.unix
        if args.prometheus:
            from prometheus_client import CollectorRegistry, start_http_server

            registry = CollectorRegistry(auto_describe=False)
            registry.register(SlipdCollector(source))
            host, port = _parse_address(args.prometheus)
            http_server, _ = start_http_server(port, addr=host, registry=registry)
            bound["prometheus"] = list(http_server.server_address[:2])
    except (OSError, ConfigError) as exc:
        where = args.unix if unix_server is None and args.unix else args.prometheus
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        with contextlib.suppress(OSError):  # the daemon may be gone already
            control.send(f"error:cannot serve on {where}: {reason}".encode())
        if unix_server is not None:
            unix_server.remove_socket_file()
        return 1
    try:
        control.send(b"ready" + json.dumps(bound).encode())
    except OSError:  # the daemon stopped before this server was up
        if unix_server is not None:
            unix_server.remove_socket_file()
        return 0
    if unix_server is not None:
        threading.Thread(target=unix_server.serve_forever, daemon=True).start()
    try:
        source.run()
    finally:
        if unix_server is not None:
            unix_server.remove_socket_file()
        sys.stdout.flush()
    os._exit(0)  # server threads may still be writing to clients that left


if __name__ == "__main__":
    sys.exit(main())
