"""Latency statistics and counters, and how they are served without disturbing the loop.

The loop records into HDR histograms (``hdrh``) whose counts live in one shared memory block
(:class:`SharedStats`, a memfd), where it also counts its counters, gauges and frames per
CAN ID as it goes. A stats server process (:mod:`slipd.daemon.stats_server`, started and
watched by the daemon through :class:`StatsServer`) answers ``slipd stats`` on a unix socket
and Prometheus scrapes through ``prometheus_client``. When it needs a fresh snapshot it
raises a number in the block; in its slack after a tick the loop copies its live numbers
and the codec's decode counts to the block's published area (:meth:`SharedStats.publish`,
two buffer copies: no JSON, no percentiles, no Python work per counter) and raises its
answer, plus a short JSON document over a socket only when its event lists changed. The
server summarises the histograms and builds the snapshot itself, and one answer serves every
client waiting for it. Before, the loop did all of it: 7-9 ms of pure Python once the
histograms had filled, a deadline miss per ``slipd stats --watch`` refresh; even the JSON of
the counters alone cost 90-140 us on a loaded 2-vCPU VM. A thread serving Prometheus in the
daemon's process would hold the GIL the loop needs (up to 5 ms a cycle,
shared/notes/realtime-python.md).

Percentiles are computed with numpy over the counts (:class:`HistogramTable`), with hdrh's
own rule (``get_value_at_percentile``), tested against it.
"""

from __future__ import annotations

import ctypes
import errno
import ipaddress
import json
import mmap
import os
import socket
import stat
import sys
import time
from collections.abc import Callable, Iterator, MutableMapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from hdrh.histogram import HdrHistogram

from slipd.daemon.service import HelperProcess, spawn_helper
from slipd.errors import ConfigError

HISTOGRAMS = ("cycle_latency_us", "compute_us", "input_age_us", "wakeup_lateness_us",
              "gc_pause_us", "stats_answer_us")  # the last: the loop's cost of a snapshot
HISTOGRAM_LOWEST, HISTOGRAM_HIGHEST, HISTOGRAM_DIGITS = 1, 60_000_000, 3  # 1 us .. 60 s
PERCENTILES = {"p50": 50.0, "p90": 90.0, "p99": 99.0, "p99.9": 99.9}
SOCKET_BACKLOG = 128  # `slipd stats` clients queued by the kernel while the server accepts
QUERY_RETRY_S = 0.005  # between connect attempts while the server's backlog is full


def new_histogram() -> HdrHistogram:
    return HdrHistogram(HISTOGRAM_LOWEST, HISTOGRAM_HIGHEST, HISTOGRAM_DIGITS)


class HistogramTable:
    """Per counts index of an :func:`new_histogram`: the values hdrh reports for it, so a
    summary of a counts array is a cumulative sum and a search (numpy) instead of hdrh's
    Python loop over 17,408 counts (~0.35 ms per percentile, 4.7 ms for three)."""

    def __init__(self) -> None:
        h = new_histogram()
        self.counts_len = h.counts_len
        index = np.arange(h.counts_len, dtype=np.int64)
        bucket = (index >> h.sub_bucket_half_count_magnitude) - 1
        sub_bucket = (index & (h.sub_bucket_half_count - 1)) + h.sub_bucket_half_count
        first = bucket < 0  # hdrh.get_value_from_index: bucket 0 uses its lower half too
        sub_bucket = np.where(first, sub_bucket - h.sub_bucket_half_count, sub_bucket)
        bucket = np.where(first, 0, bucket)
        shift = bucket + h.unit_magnitude
        self.lowest = sub_bucket << shift
        self.highest = self.lowest + (np.int64(1) << shift) - 1  # get_highest_equivalent_value
        self.median = self.lowest + ((np.int64(1) << shift) >> 1)  # _hdr_median_equiv_value

    def summary(self, counts: np.ndarray) -> dict:
        """count, p50/p90/p99/p99.9, max and sum (us) of a counts array, as hdrh gives them."""
        cumulative = np.cumsum(counts, dtype=np.int64)
        total = int(cumulative[-1])
        result = {"count": total}
        for key, percentile in PERCENTILES.items():
            if total == 0:
                result[key] = 0
                continue
            target = max(int(percentile * total / 100 + 0.5), 1)
            index = int(np.searchsorted(cumulative, target, side="left"))
            result[key] = int(self.highest[index])
        nonzero = np.flatnonzero(counts)
        result["max"] = int(self.highest[nonzero[-1]]) if len(nonzero) else 0
        result["sum"] = int(np.dot(counts[nonzero].astype(np.float64), self.median[nonzero]))
        return result


COUNTERS = ("ticks", "deadline_misses", "input_timeouts", "tx_errors", "rx_frames",
            "rx_overflows", "rx_malformed", "valid_ticks", "gc_full_collections",
            "recorder_errors", "stats_server_restarts", "clock_steps",
            "consistency_fail_ticks", "consistency_warn_ticks", "consistency_innovation_ticks",
            "consistency_imprecise_ticks", "consistency_witness_ticks")
#: counters of the running estimator's own (Prometheus gives them an ``estimator`` label)
PER_ESTIMATOR = ("consistency_fail_ticks", "consistency_warn_ticks",
                 "consistency_innovation_ticks", "consistency_imprecise_ticks",
                 "consistency_witness_ticks")
GAUGES = ("status", "beta_deg", "vx_mps", "uptime_s")
RX_IDS_KEPT = 512  # CAN IDs counted one by one in the block; the rest are summed


@dataclass(frozen=True)
class StatsLayout:
    """What the shared block holds besides the histograms: the decode-count table's row
    (message) and column (result) names, and for rows listed in ``only`` the columns kept."""

    rows: tuple[str, ...] = ()
    columns: tuple[str, ...] = ()
    only: dict[str, tuple[str, ...]] = field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps({"rows": self.rows, "columns": self.columns, "only": self.only})

    @classmethod
    def from_json(cls, text: str) -> StatsLayout:
        data = json.loads(text)
        return cls(tuple(data["rows"]), tuple(data["columns"]),
                   {k: tuple(v) for k, v in data["only"].items()})


class SharedCounters(MutableMapping):
    """The loop's counters by name, each an int64 word of the block's live area: the loop
    counts into the block as it goes (a memoryview item, as fast as a dict's), so its answer
    to the stats server copies the words instead of packing 16 Python ints."""

    __slots__ = ("_words",)
    _index = {name: i for i, name in enumerate(COUNTERS)}

    def __init__(self, words: memoryview) -> None:
        self._words = words

    def __getitem__(self, name: str) -> int:
        return self._words[self._index[name]]

    def __setitem__(self, name: str, value: int) -> None:
        self._words[self._index[name]] = value

    def __delitem__(self, name: str) -> None:
        raise TypeError("the loop's counters are fixed (COUNTERS)")

    def __iter__(self) -> Iterator[str]:
        return iter(COUNTERS)

    def __len__(self) -> int:
        return len(COUNTERS)


class SharedStats:
    """The loop's histograms, counters, gauges, decode counts and frames per CAN ID in one
    memory block: an anonymous memfd handed to the stats server process by descriptor (no
    file name to clean up, gone with the last process holding it), or ``private`` memory
    for a daemon that serves no stats.

    The numbers are there twice. The loop writes the *live* area as it goes (counters,
    gauges once a tick, a count word per CAN ID); its answer to the stats server copies the
    live area's used prefix to the *published* area in one buffer copy, and the decode
    counts (the codec's own array) beside it in another, whatever the number of counters or
    IDs: O(1) Python work on cold caches, where packing the counters, gauges and IDs cost
    p50 33 us (each Python object touched after ~10 ms asleep is a cache miss). The server
    reads only the published area, which the loop writes only when asked (one question
    outstanding at a time, see StatsServer), so what it reads is one instant of the loop.
    The histograms are single: hdrh counts into them in place; ``ticks_live`` lets the
    server check that its copy holds no tick after the published one (SnapshotSource)."""

    def __init__(self, layout: StatsLayout = StatsLayout(), fd: int | None = None,
                 private: bool = False) -> None:
        self.layout = layout
        self.counts_len = new_histogram().counts_len
        numbers = [("counters", np.int64, (len(COUNTERS),)),
                   ("gauges", np.float64, (len(GAUGES),)),
                   # (id, count) per CAN ID; the first: (-1, frames of the IDs not kept)
                   ("rx_ids", np.int64, (RX_IDS_KEPT + 1, 2))]
        sections = [("sequence", np.int64, (2,)),  # [requested, answered]: see StatsServer
                    ("histograms", np.uint64, (len(HISTOGRAMS), self.counts_len)),
                    *[("live_" + name, dtype, shape) for name, dtype, shape in numbers],
                    *numbers,  # published
                    ("decode", np.int64, (len(layout.rows), len(layout.columns)))]
        size = sum(8 * int(np.prod(shape)) for _, _, shape in sections)
        if private:
            self.fd = None
            self.memory = mmap.mmap(-1, size)
        else:
            self.fd = os.memfd_create("slipd-stats", os.MFD_CLOEXEC) if fd is None else fd
            if fd is None:
                os.ftruncate(self.fd, size)
            self.memory = mmap.mmap(self.fd, size)
        offset = 0
        offsets = {}
        for name, dtype, shape in sections:
            count = int(np.prod(shape))
            view = np.frombuffer(self.memory, dtype=dtype, count=count, offset=offset)
            setattr(self, name, view.reshape(shape))
            offsets[name] = offset
            offset += 8 * count
        view = memoryview(self.memory)
        #: [requested, answered] as Python ints without a numpy call: the loop reads it
        #: every tick (~50 ns)
        self.sequence_words = view[:16].cast("q")
        live, published = offsets["live_counters"], offsets["counters"]
        self.counter_words = view[live:offsets["live_gauges"]].cast("q")
        self.gauge_words = view[offsets["live_gauges"]:offsets["live_rx_ids"]].cast("d")
        self.rx_words = view[offsets["live_rx_ids"]:published].cast("q")
        self._live, self._published = view[live:published], view[published:]
        self._head = offsets["live_rx_ids"] - live + 16  # counters, gauges, the rest entry
        self._live_used = self._published_used = None
        self.rx_kept = 0  # IDs with an entry
        self._decode_bytes = view[offsets["decode"]:]
        self._decode_source: np.ndarray | None = None
        self._decode_view: memoryview | None = None
        if fd is None:
            self.live_rx_ids[:, 0] = -1  # no ID yet (0 is one)
            self.rx_ids[:, 0] = -1
        self._use_prefix()

    def _use_prefix(self) -> None:
        """The views publish() copies: the live area up to the last ID with an entry."""
        end = self._head + 16 * self.rx_kept
        self._live_used, self._published_used = self._live[:end], self._published[:end]

    def rx_slot(self, frame_id: int) -> int:
        """The index in ``rx_words`` of ``frame_id``'s count: a new entry while fewer than
        RX_IDS_KEPT IDs have one, else the rest's. The caller remembers it."""
        if self.rx_kept == RX_IDS_KEPT:
            return 1
        self.rx_kept += 1
        self.rx_words[2 * self.rx_kept] = frame_id
        self._use_prefix()
        return 2 * self.rx_kept + 1

    def counts(self, index: int) -> np.ndarray:
        """A numpy view of histogram ``index``'s counts (no copy)."""
        return self.histograms[index]

    def attach(self, index: int) -> HdrHistogram:
        """A histogram recording into the block (hdrh increments ``counts[i]`` in place)."""
        h = new_histogram()
        h.counts = (ctypes.c_uint64 * self.counts_len).from_buffer(
            self.histograms[index])
        return h

    def publish(self, decode: np.ndarray | None) -> None:
        """The loop's part of a snapshot: the live area's used prefix into the published
        area, and ``decode`` (C-contiguous int64 of the layout's shape, or None) beside it:
        two buffer copies (~1 KB), whatever the counters and IDs."""
        self._published_used[:] = self._live_used
        if decode is not self._decode_source:  # once: the codec keeps its array
            self._decode_source = decode
            self._decode_view = None
            if decode is not None and decode.nbytes == len(self._decode_bytes):
                self._decode_view = memoryview(decode).cast("B")
        if self._decode_view is not None:
            self._decode_bytes[:] = self._decode_view

    def ticks_live(self) -> int:
        """The loop's tick count now (the live area; the server's consistency check)."""
        return int(self.live_counters[COUNTERS.index("ticks")])

    def read(self, live: bool = False) -> dict:
        """The counters as the snapshot shows them: the published area (the stats server's
        side) or the live one (the loop's own snapshot)."""
        layout = self.layout
        decode = self.decode.copy()
        decode_errors = {}
        for row, message in enumerate(layout.rows):
            columns = layout.only.get(message, layout.columns)
            decode_errors[message] = {c: int(decode[row, layout.columns.index(c)])
                                      for c in columns}
        counters, gauges, rx = ((self.live_counters, self.live_gauges, self.live_rx_ids)
                                if live else (self.counters, self.gauges, self.rx_ids))
        rx = rx.copy()
        used = rx[1:][rx[1:, 0] >= 0]
        rx_per_id = {f"{int(i):#x}": int(n) for i, n in sorted(map(tuple, used))}
        if rx[0, 1]:
            rx_per_id["other"] = int(rx[0, 1])
        gauges = dict(zip(GAUGES, gauges.tolist(), strict=True))
        gauges["status"] = int(gauges["status"])
        return {"counters": dict(zip(COUNTERS, counters.tolist(), strict=True)),
                "rx_per_id": rx_per_id, "decode_errors": decode_errors, **gauges}


_TABLE: HistogramTable | None = None


def histogram_table() -> HistogramTable:
    global _TABLE
    if _TABLE is None:
        _TABLE = HistogramTable()
    return _TABLE


def summarize(h: HdrHistogram) -> dict:
    """:meth:`HistogramTable.summary` of an hdrh histogram's counts."""
    counts = np.frombuffer(h.counts, dtype=np.uint64, count=h.counts_len)
    return histogram_table().summary(counts.astype(np.int64))


def clear(h: HdrHistogram) -> None:
    """``h.reset()`` without hdrh's Python loop over every count (1-2 ms, once a second in
    the loop's slack before)."""
    ctypes.memset(h.counts, 0, h.counts_len * ctypes.sizeof(h.counts._type_))
    h.total_count = 0
    h.min_value = sys.maxsize
    h.max_value = 0


@dataclass
class Stats:
    """The loop's statistics, kept in a :class:`SharedStats` block (private memory unless
    made :meth:`in_shared_memory` for a stats server): ``counters`` by name, the histograms,
    :meth:`count_frame` per received frame, :meth:`set_gauges` once a tick."""

    shared: SharedStats | None = None
    histograms: dict[str, HdrHistogram] = field(default_factory=dict)
    interval: HdrHistogram = field(default_factory=new_histogram)  # cycle latency, last second
    decode_errors: dict[str, dict[str, int]] = field(default_factory=dict)
    interval_misses: int = 0
    interval_timeouts: int = 0
    interval_rx_errors: int = 0
    counters: SharedCounters = field(init=False)

    def __post_init__(self) -> None:
        if self.shared is None:
            self.shared = SharedStats(private=True)
        if not self.histograms:
            self.histograms = {name: self.shared.attach(i) for i, name in enumerate(HISTOGRAMS)}
        self.counters = SharedCounters(self.shared.counter_words)
        self._rx_words = self.shared.rx_words
        self._rx_slots: dict[int, int] = {}  # CAN ID -> its count's index in _rx_words
        self._gauges = self.shared.gauge_words
        histogram_table()  # built now, not in the loop's first use of it

    @classmethod
    def in_shared_memory(cls, layout: StatsLayout = StatsLayout()) -> Stats:
        return cls(shared=SharedStats(layout))

    def record(self, name: str, value_us: float) -> None:
        self.histograms[name].record_value(min(max(1, int(value_us)), HISTOGRAM_HIGHEST))

    def count_frame(self, frame_id: int) -> None:
        """One received frame of ``frame_id`` (frames per CAN ID; the first RX_IDS_KEPT IDs
        one by one, the rest summed)."""
        slot = self._rx_slots.get(frame_id)
        if slot is None:
            slot = self._rx_slots[frame_id] = self.shared.rx_slot(frame_id)
        self._rx_words[slot] += 1

    @property
    def rx_per_id(self) -> dict[int, int]:
        """Frames per CAN ID counted so far (IDs beyond RX_IDS_KEPT are not listed)."""
        words = self._rx_words
        return {frame_id: words[slot] for frame_id, slot in self._rx_slots.items()
                if slot != 1}

    def set_gauges(self, status: float, beta_deg: float, vx_mps: float,
                   uptime_s: float) -> None:
        """The latest values of GAUGES (the loop, once a tick after its frames are out)."""
        gauges = self._gauges
        gauges[0], gauges[1], gauges[2], gauges[3] = status, beta_deg, vx_mps, uptime_s

    def publish(self, decode: np.ndarray | None, text: dict | None) -> bytes:
        """The loop's answer to the stats server: its numbers into the block's published
        area (SharedStats.publish, two buffer copies), and the bytes to send besides
        (``text`` as JSON, the part that is not numbers)."""
        self.shared.publish(decode)
        return json.dumps(text).encode() if text else b""

    def snapshot(self, extra: dict | None = None) -> dict:
        """The whole snapshot in this process (the end of a run, tests): the stats server
        builds the same document from the shared block."""
        live = self.shared.read(live=True)  # the gauges as the loop set them last
        result = {**live, "decode_errors": self.decode_errors}
        if extra:
            result.update(extra)
        for name, h in self.histograms.items():
            result[name] = summarize(h)
        return result


# ---- configuration checks (in the daemon's process, before anything is started) ----------

def parse_prometheus(value: object, public: bool = False) -> tuple[str, int]:
    """``HOST:PORT``, ``[V6]:PORT`` or a bare port (loopback) -> (host, port). A host that is
    not a loopback address needs ``public`` (``--prometheus-public``): a metrics endpoint on
    every interface of a car's PC is a choice to make on purpose."""
    if isinstance(value, bool) or not isinstance(value, int | str):
        raise ConfigError(f"prometheus = {value!r}: expected \"HOST:PORT\" or a port number")
    text = str(value).strip()
    host, sep, port_text = text.rpartition(":")
    if not sep:
        host, port_text = "127.0.0.1", text
    host = host.strip("[]") or "127.0.0.1"
    try:
        port = int(port_text)
    except ValueError:
        port = -1
    if not 0 <= port <= 65535:
        raise ConfigError(f"prometheus {text!r}: port {port_text!r} is not a number in "
                          "0..65535 (expected HOST:PORT, e.g. 127.0.0.1:9464)")
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError as exc:
        raise ConfigError(f"prometheus {text!r}: {host!r} is not an IP address or "
                          "localhost") from exc
    if not loopback and not public:
        raise ConfigError(f"prometheus {text!r} would serve metrics on a non-loopback "
                          "address: pass --prometheus-public (prometheus_public = true) to "
                          "mean it, or use 127.0.0.1")
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:  # in use? say so now, by name
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as exc:
            raise ConfigError(f"prometheus {text!r}: cannot listen there: {exc.strerror}"
                              ) from exc
    return host, port


def check_stats_socket(path: str) -> None:
    """Refuse a stats socket path that would destroy something: an existing file that is not
    a socket, or the socket of a daemon that still answers on it (a second daemon must not
    take it over and remove it on exit). A socket nobody answers on is stale and replaced."""
    target = Path(path)
    if not target.parent.is_dir():
        raise ConfigError(f"--stats-socket {path}: directory {target.parent} does not exist")
    try:
        mode = os.lstat(target).st_mode
    except FileNotFoundError:
        return
    if not stat.S_ISSOCK(mode):
        raise ConfigError(f"--stats-socket {path}: exists and is not a socket; refusing to "
                          "replace it")
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        probe.settimeout(0.5)
        try:
            probe.connect(path)
        except (ConnectionRefusedError, FileNotFoundError):
            return  # stale: the server that bound it is gone
        except OSError as exc:
            if exc.errno != errno.EAGAIN:  # EAGAIN: a live server with a full backlog
                return
    raise ConfigError(f"--stats-socket {path}: another slipd answers there; stop it first "
                      "or choose another socket")


# ---- the loop's end of the stats server ----------------------------------------------------

class StatsServer:
    """Starts and watches the stats server process; ``poll`` answers its requests.

    The server binds the unix socket and the Prometheus address itself and reports ``ready``
    (with the bound addresses) or an error over a SOCK_SEQPACKET pair; ``wait_ready`` reads
    that once, before the loop starts. Requests and answers are two numbers in the shared
    block (``sequence``: requested, answered): the server raises ``requested``; the loop's
    ``poll``, every tick, compares it with what it last answered (a memory read, no system
    call) and when they differ publishes its numbers in the block and sets ``answered``
    (the server polls it). The pair carries only what is not a number, and only when it
    changed (the loop's words: events, recorder status). Measured on this project's VMs, a
    socket round trip cost the loop p50 64 us in the running daemon (cold caches after
    ~9 ms of sleep), the shared-memory answer a few us. A server that exits is reported and
    started again after RESTART_DELAY_S (``poll_health``, once a second); the loop never
    waits for it.
    """

    RESTART_DELAY_S = 5.0
    READY_TIMEOUT_S = 600.0  # a python start: ~0.3 s here, minutes in the TCG VM tests

    def __init__(self, unix_path: str | None, prometheus: tuple[str, int] | None,
                 stats: Stats, log: Callable[[str], None] = print,
                 socket_mode: int = 0o660) -> None:
        self.unix_path = unix_path
        self.prometheus = prometheus
        self.http_address: tuple[str, int] | None = None
        self.stats = stats
        self.log = log
        self.socket_mode = socket_mode
        self.process: HelperProcess | None = None
        self.control: socket.socket | None = None
        self.answered = 0
        self._restart_at: float | None = None
        self._ready = False
        self._fresh = True
        self._restarted = False
        self.enabled = bool(unix_path or prometheus)
        if self.enabled:
            if stats.shared.fd is None:
                raise ValueError("the stats server needs Stats.in_shared_memory()")
            self._sequence = stats.shared.sequence_words
            self._start()

    def _start(self) -> None:
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        command = [sys.executable, "-m", "slipd.daemon.stats_server",
                   "--memory-fd", str(self.stats.shared.fd), "--control-fd", str(theirs.fileno()),
                   "--socket-mode", oct(self.socket_mode),
                   "--layout", self.stats.shared.layout.to_json()]
        if self.unix_path:
            command += ["--unix", self.unix_path]
        if self.prometheus:
            command += ["--prometheus", f"[{self.prometheus[0]}]:{self.prometheus[1]}"]
        try:
            self.process = spawn_helper(command, pass_fds=(self.stats.shared.fd,
                                                           theirs.fileno()))
        finally:
            theirs.close()
        self.control = ours
        self._ready = False

    def wait_ready(self) -> None:
        """Block until the server has bound its sockets (once, before the loop starts); a
        refusal is a ConfigError naming the reason."""
        if not self.enabled or self._ready:
            return
        self.control.settimeout(self.READY_TIMEOUT_S)
        try:
            message = self.control.recv(65536)
        except OSError as exc:
            message = f"error:no answer in {self.READY_TIMEOUT_S:.0f} s ({exc})".encode()
        if not message.startswith(b"ready"):
            text = message.decode(errors="replace").removeprefix("error:")
            if not text:
                text = f"exited with code {self.process.wait(5)}"
            self.close()
            raise ConfigError(f"stats server: {text}")
        self._on_ready(message)

    def _on_ready(self, message: bytes) -> None:
        bound = json.loads(message[len(b"ready"):] or b"{}")
        if bound.get("prometheus"):
            self.http_address = tuple(bound["prometheus"])
        self.control.setblocking(False)
        if self._restarted:
            self.log("slipd: stats server started again")
        self._ready = True
        self._fresh = True

    def poll(self, publish: Callable[[bool], bytes]) -> int:
        """Answer the server's request, if it made one since the last answer: ``publish(
        fresh)`` publishes the loop's numbers in the shared block and returns the words to
        send besides (JSON, or b"" when they did not change; ``fresh``: the server is new).
        Returns 1 when it answered. Never blocks; no system call unless there are words."""
        if not self._ready:
            return 0
        sequence = self._sequence
        if sequence[0] == sequence[1]:
            return 0
        requested = sequence[0]
        words = publish(self._fresh)
        if words:
            try:
                self.control.send(words)
                self._fresh = False
            except (BlockingIOError, InterruptedError):
                pass  # sent again with the next answer (still not fresh)
            except OSError:
                self._lost("it stopped reading")
                return 0
        else:
            self._fresh = False
        sequence[1] = requested  # after the block is written: the server reads it then
        self.answered += 1
        return 1

    def _lost(self, why: str) -> None:
        if self.control is None:
            return
        self.control.close()
        self.control = None
        self._ready = False
        code = self.process.poll() if self.process else None
        self.log(f"slipd: stats server stopped ({why}; exit code {code}); starting it again "
                 f"in {self.RESTART_DELAY_S:.0f} s; estimation goes on")
        self._restart_at = time.monotonic() + self.RESTART_DELAY_S

    def poll_health(self) -> None:
        """Once a second, in the slack: notice a server that exited and start a new one
        RESTART_DELAY_S later (its ``ready`` is read by ``poll``, never waited for)."""
        if not self.enabled:
            return
        if self.control is not None and self.process is not None and \
                self.process.poll() is not None:
            self._lost("it exited")
        if self.control is not None and not self._ready:  # a new server's ready, or error
            try:
                message = self.control.recv(65536)
            except (BlockingIOError, InterruptedError):
                message = None
            except OSError:
                message = b""
            if message is not None:
                if message.startswith(b"ready"):
                    self._on_ready(message)
                else:
                    self._lost(message.decode(errors="replace").removeprefix("error:")
                               or "it exited")
        if self._restart_at is not None and time.monotonic() >= self._restart_at:
            self._restart_at = None
            if self.process is not None:
                self.process.wait()
            self.stats.counters["stats_server_restarts"] += 1
            self._restarted = True
            self._start()
            self.control.setblocking(False)

    def close(self) -> None:
        if self.control is not None:
            self.control.close()  # the server exits on end of file, removing its socket
            self.control = None
        if self.process is not None:
            try:
                self.process.wait(5)
            except TimeoutError:
                self.process.kill()
                self.process.wait()
            self.process = None


def query(unix_path: str, timeout: float = 2.0) -> dict:
    """Read one snapshot from a running daemon's stats socket. While the server's listen
    backlog is full the connection is retried (a unix socket refuses with EAGAIN then)
    until ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        client = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            client.settimeout(max(deadline - time.monotonic(), 0.001))
            try:
                client.connect(unix_path)
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    raise
                time.sleep(QUERY_RETRY_S)
                continue
            chunks = []
            while True:
                chunk = client.recv(65536)
                if not chunk:
                    break
                chunks.append(chunk)
        finally:
            client.close()
        if not chunks:  # accepted, then closed: the daemon (and its server) stopping
            raise OSError(errno.ECONNRESET, "the stats server closed the connection without "
                                            "an answer (is the daemon stopping?)")
        document = json.loads(b"".join(chunks))
        if "error" in document and "counters" not in document:
            raise OSError(errno.EIO, document["error"])
        return document
