"""Latency statistics and counters, and the ways they are served without threads.

The loop records into HDR histograms (``hdrh``); :class:`StatsServer` answers ``slipd stats``
on a unix socket and Prometheus scrapes on a loopback TCP socket, both non-blocking and
polled by the loop in its slack after a tick, so a reader never preempts a tick.
"""

from __future__ import annotations

import json
import os
import socket
from dataclasses import dataclass, field

from hdrh.histogram import HdrHistogram

HISTOGRAMS = ("cycle_latency_us", "compute_us", "input_age_us", "wakeup_lateness_us")


def _histogram() -> HdrHistogram:
    return HdrHistogram(1, 60_000_000, 3)  # 1 us .. 60 s, 3 significant digits


@dataclass
class Stats:
    histograms: dict[str, HdrHistogram] = field(
        default_factory=lambda: {name: _histogram() for name in HISTOGRAMS})
    interval: HdrHistogram = field(default_factory=_histogram)  # cycle latency, last second
    counters: dict[str, int] = field(default_factory=lambda: {
        "ticks": 0, "deadline_misses": 0, "input_timeouts": 0, "tx_errors": 0,
        "rx_frames": 0, "valid_ticks": 0})
    rx_per_id: dict[int, int] = field(default_factory=dict)
    decode_errors: dict[str, dict[str, int]] = field(default_factory=dict)
    interval_misses: int = 0
    interval_timeouts: int = 0
    interval_rx_errors: int = 0

    def record(self, name: str, value_us: float) -> None:
        self.histograms[name].record_value(min(max(1, int(value_us)), 60_000_000))

    def snapshot(self, extra: dict | None = None) -> dict:
        result = {"counters": dict(self.counters),
                  "rx_per_id": {f"{k:#x}": v for k, v in sorted(self.rx_per_id.items())},
                  "decode_errors": self.decode_errors}
        for name, h in self.histograms.items():
            result[name] = {
                "count": h.get_total_count(), "p50": h.get_value_at_percentile(50),
                "p99": h.get_value_at_percentile(99), "p99.9": h.get_value_at_percentile(99.9),
                "max": h.get_max_value(),
            }
        if extra:
            result.update(extra)
        return result


def prometheus_text(snapshot: dict) -> bytes:
    """The snapshot in Prometheus' text exposition format."""
    lines = []
    for name, value in snapshot["counters"].items():
        lines += [f"# TYPE slipd_{name}_total counter", f"slipd_{name}_total {value}"]
    for name in HISTOGRAMS:
        h = snapshot[name]
        lines.append(f"# TYPE slipd_{name} summary")
        for q, key in (("0.5", "p50"), ("0.99", "p99"), ("0.999", "p99.9"), ("1", "max")):
            lines.append(f'slipd_{name}{{quantile="{q}"}} {h[key]}')
        lines.append(f"slipd_{name}_count {h['count']}")
    for message, counts in snapshot["decode_errors"].items():
        for kind, value in counts.items():
            lines.append(f'slipd_rx_frames_total{{message="{message}",result="{kind}"}} {value}')
    return ("\n".join(lines) + "\n").encode()


class StatsServer:
    """Non-blocking unix-socket (JSON) and loopback-HTTP (Prometheus) endpoints."""

    def __init__(self, unix_path: str | None, prometheus: str | None):
        self.unix = None
        self.http = None
        self.unix_path = unix_path
        if unix_path:
            if os.path.exists(unix_path):
                os.unlink(unix_path)
            self.unix = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            self.unix.bind(unix_path)
            self.unix.listen(4)
            self.unix.setblocking(False)
        if prometheus:
            host, _, port = prometheus.rpartition(":")
            host = host or "127.0.0.1"
            self.http = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            self.http.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self.http.bind((host, int(port)))
            self.http.listen(4)
            self.http.setblocking(False)

    def poll(self, snapshot_fn) -> int:
        """Answer pending requests (at most a few); returns how many were served."""
        served = 0
        for server, kind in ((self.unix, "json"), (self.http, "http")):
            if server is None:
                continue
            for _ in range(4):
                try:
                    conn, _ = server.accept()
                except (BlockingIOError, InterruptedError):
                    break
                with conn:
                    conn.settimeout(0.05)
                    snapshot = snapshot_fn()
                    try:
                        if kind == "json":
                            conn.sendall(json.dumps(snapshot).encode() + b"\n")
                        else:
                            conn.recv(4096)
                            body = prometheus_text(snapshot)
                            conn.sendall(b"HTTP/1.0 200 OK\r\nContent-Type: text/plain; "
                                         b"version=0.0.4\r\nContent-Length: "
                                         + str(len(body)).encode() + b"\r\n\r\n" + body)
                    except OSError:
                        pass
                served += 1
        return served

    def close(self) -> None:
        for server in (self.unix, self.http):
            if server is not None:
                server.close()
        if self.unix_path and os.path.exists(self.unix_path):
            os.unlink(self.unix_path)


def query(unix_path: str, timeout: float = 2.0) -> dict:
    """Read one snapshot from a running daemon's stats socket."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as client:
        client.settimeout(timeout)
        client.connect(unix_path)
        chunks = []
        while True:
            chunk = client.recv(65536)
            if not chunk:
                break
            chunks.append(chunk)
    return json.loads(b"".join(chunks))
