"""Latency statistics and counters, and the ways they are served without threads.

The loop records into HDR histograms (``hdrh``); :class:`StatsServer` answers ``slipd stats``
on a unix socket and Prometheus scrapes on a loopback TCP socket, both non-blocking and
polled by the loop in its slack after a tick, so a reader never preempts a tick.
"""

from __future__ import annotations

import json
import os
import socket
import time
from dataclasses import dataclass, field

from hdrh.histogram import HdrHistogram

HISTOGRAMS = ("cycle_latency_us", "compute_us", "input_age_us", "wakeup_lateness_us",
              "gc_pause_us")


def _histogram() -> HdrHistogram:
    return HdrHistogram(1, 60_000_000, 3)  # 1 us .. 60 s, 3 significant digits


@dataclass
class Stats:
    histograms: dict[str, HdrHistogram] = field(
        default_factory=lambda: {name: _histogram() for name in HISTOGRAMS})
    interval: HdrHistogram = field(default_factory=_histogram)  # cycle latency, last second
    counters: dict[str, int] = field(default_factory=lambda: {
        "ticks": 0, "deadline_misses": 0, "input_timeouts": 0, "tx_errors": 0,
        "rx_frames": 0, "valid_ticks": 0, "gc_full_collections": 0})
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
    """The snapshot in Prometheus' text exposition format (one group per metric family)."""
    lines = []

    def family(name: str, kind: str, help_text: str, samples: list[tuple[str, object]]) -> None:
        """``samples``: (suffix-and-labels, value), e.g. ('{quantile="0.5"}', 3), ('_count', 9)."""
        lines.extend([f"# HELP {name} {help_text}", f"# TYPE {name} {kind}"])
        lines.extend(f"{name}{suffix} {value}" for suffix, value in samples)

    for name, value in snapshot["counters"].items():
        family(f"slipd_{name}_total", "counter", name.replace("_", " "), [("", value)])
    family("slipd_rx_frames_by_id_total", "counter", "received frames per CAN ID",
           [(f'{{id="{frame_id}"}}', count)
            for frame_id, count in snapshot.get("rx_per_id", {}).items()])
    family("slipd_decode_frames_total", "counter", "input frames per message and decode result",
           [(f'{{message="{message}",result="{kind}"}}', value)
            for message, counts in snapshot["decode_errors"].items()
            for kind, value in counts.items()])
    for name in HISTOGRAMS:
        h = snapshot[name]
        family(f"slipd_{name}", "summary", f"{name.replace('_', ' ')} (HDR histogram)",
               [(f'{{quantile="{q}"}}', h[key])
                for q, key in (("0.5", "p50"), ("0.99", "p99"), ("0.999", "p99.9"))]
               + [("_count", h["count"])])
        family(f"slipd_{name}_max", "gauge", f"largest {name.replace('_', ' ')}",
               [("", h["max"])])
    for key, help_text in (("beta_deg", "latest sideslip estimate, deg"),
                           ("status", "latest status bits"),
                           ("uptime_s", "seconds since the loop started")):
        if isinstance(snapshot.get(key), int | float):
            family(f"slipd_{key}", "gauge", help_text, [("", snapshot[key])])
    return ("\n".join(lines) + "\n").encode()


HTTP_HEADER_LIMIT = 8192
HTTP_CLIENT_PATIENCE = 1.0  # s a scraper may take to send its request before it is dropped


class StatsServer:
    """Non-blocking unix-socket (JSON) and loopback-HTTP (Prometheus) endpoints.

    ``poll`` never waits: a scraper whose request has not fully arrived is kept and looked at
    again after the next tick (dropped after HTTP_CLIENT_PATIENCE), so a slow or silent
    client cannot delay the loop.
    """

    def __init__(self, unix_path: str | None, prometheus: str | None):
        self.unix = None
        self.http = None
        self.unix_path = unix_path
        self.http_address: tuple[str, int] | None = None
        self._pending: list[tuple[socket.socket, bytes, float]] = []
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
            self.http_address = self.http.getsockname()

    def poll(self, snapshot_fn) -> int:
        """Answer pending requests (at most a few); returns how many were served."""
        served = 0
        if self.unix is not None:
            for _ in range(4):
                try:
                    conn, _ = self.unix.accept()
                except (BlockingIOError, InterruptedError):
                    break
                with conn:
                    conn.setblocking(False)
                    try:
                        conn.sendall(json.dumps(snapshot_fn()).encode() + b"\n")
                    except OSError:
                        pass
                served += 1
        if self.http is not None:
            now = time.monotonic()
            for _ in range(4):
                try:
                    conn, _ = self.http.accept()
                except (BlockingIOError, InterruptedError):
                    break
                conn.setblocking(False)
                self._pending.append((conn, b"", now))
            still_waiting = []
            for conn, request, since in self._pending:
                try:
                    chunk = conn.recv(4096)
                    request += chunk
                    complete = b"\r\n\r\n" in request or b"\n\n" in request or not chunk
                except BlockingIOError:
                    complete = False
                except OSError:
                    conn.close()
                    continue
                if complete or len(request) > HTTP_HEADER_LIMIT:
                    self._answer_http(conn, request, snapshot_fn)
                    served += 1
                elif now - since > HTTP_CLIENT_PATIENCE:
                    conn.close()
                else:
                    still_waiting.append((conn, request, since))
            self._pending = still_waiting
        return served

    @staticmethod
    def _answer_http(conn: socket.socket, request: bytes, snapshot_fn) -> None:
        with conn:
            if request.startswith(b"GET /metrics") or request.startswith(b"GET / "):
                body = prometheus_text(snapshot_fn())
                head = (b"HTTP/1.0 200 OK\r\nContent-Type: text/plain; version=0.0.4\r\n"
                        b"Content-Length: " + str(len(body)).encode() + b"\r\n\r\n")
            else:
                body = b"slipd serves GET /metrics\n"
                head = (b"HTTP/1.0 404 Not Found\r\nContent-Type: text/plain\r\n"
                        b"Content-Length: " + str(len(body)).encode() + b"\r\n\r\n")
            try:
                conn.sendall(head + body)
            except OSError:
                pass

    def close(self) -> None:
        for conn, _, _ in self._pending:
            conn.close()
        self._pending = []
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
