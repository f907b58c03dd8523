"""The daemon's statistics: percentiles against hdrh, the stats server process (unix socket
and Prometheus through prometheus_client), what a snapshot costs the loop, hostile clients and
sockets that must not be taken over or destroyed."""

from __future__ import annotations

import os
import socket
import stat
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from hdrh.histogram import HdrHistogram
from hypothesis import given, settings
from hypothesis import strategies as st
from prometheus_client.parser import text_string_to_metric_families

from slipd.daemon.stats import (
    HISTOGRAMS,
    RX_IDS_KEPT,
    HistogramTable,
    SharedStats,
    Stats,
    StatsLayout,
    StatsServer,
    check_stats_socket,
    clear,
    new_histogram,
    parse_prometheus,
    query,
    summarize,
)
from slipd.errors import ConfigError

TABLE = HistogramTable()


def test_table_gives_hdrhs_values_for_every_index():
    h = new_histogram()
    sample = np.unique(np.concatenate([np.arange(0, 5000), np.linspace(0, h.counts_len - 1,
                                                                      3000).astype(int)]))
    for index in sample:
        value = h.get_value_from_index(int(index))
        assert TABLE.lowest[index] == value
        assert TABLE.highest[index] == h.get_highest_equivalent_value(value)
        assert TABLE.median[index] == h._hdr_median_equiv_value(value)


@settings(max_examples=60, deadline=None)
@given(values=st.lists(st.integers(1, 60_000_000), min_size=0, max_size=300),
       heavy=st.integers(1, 2_000_000))
def test_summary_equals_hdrh(values, heavy):
    h = new_histogram()
    for value in values:
        h.record_value(value)
    h.record_value(heavy, 50)  # a bulk of one value, as a steady loop records
    ours = summarize(h)
    assert ours["count"] == h.get_total_count()
    for key, percentile in (("p50", 50), ("p90", 90), ("p99", 99), ("p99.9", 99.9)):
        assert ours[key] == h.get_value_at_percentile(percentile), key
    assert ours["max"] == h.get_max_value()
    assert ours["sum"] == pytest.approx(h.get_mean_value() * h.get_total_count(), rel=1e-9)
    clear(h)
    assert summarize(h)["count"] == 0 and h.get_max_value() == 0


def test_the_shared_block_carries_the_snapshot_to_another_mapping():
    layout = StatsLayout(rows=("IMU", "unknown"), columns=("accepted", "unknown_id"),
                         only={"unknown": ("unknown_id",)})
    stats = Stats.in_shared_memory(layout)
    for value in (100, 200, 300, 40_000):
        stats.record("cycle_latency_us", value)
    stats.counters["ticks"] = 42
    for frame_id in [0x100] * 7 + [0x1ABCDEF0] * 2:
        stats.count_frame(frame_id)
    stats.set_gauges(5, -1.5, 20.0, 9.0)
    other = SharedStats(layout, fd=stats.shared.fd)  # what the server process maps
    assert other.read()["counters"]["ticks"] == 0  # nothing published yet
    stats.publish(np.array([[11, 0], [0, 3]]), None)
    counts = other.counts(HISTOGRAMS.index("cycle_latency_us")).astype(np.int64)
    assert TABLE.summary(counts) == summarize(stats.histograms["cycle_latency_us"])
    assert TABLE.summary(counts)["count"] == 4
    read = other.read()
    assert read["counters"]["ticks"] == 42 and read["status"] == 5 and read["beta_deg"] == -1.5
    assert read["decode_errors"] == {"IMU": {"accepted": 11, "unknown_id": 0},
                                     "unknown": {"unknown_id": 3}}
    assert read["rx_per_id"] == {"0x100": 7, "0x1abcdef0": 2}
    assert stats.snapshot()["rx_per_id"] == read["rx_per_id"]
    assert stats.rx_per_id == {0x100: 7, 0x1ABCDEF0: 2}


def test_frames_of_more_ids_than_the_block_keeps_are_summed():
    stats = Stats.in_shared_memory()
    for frame_id in range(RX_IDS_KEPT + 10):
        stats.count_frame(frame_id)
    stats.count_frame(RX_IDS_KEPT + 3)  # a summed ID again
    stats.publish(None, None)
    read = SharedStats(fd=stats.shared.fd).read()
    assert len(read["rx_per_id"]) == RX_IDS_KEPT + 1 and read["rx_per_id"]["other"] == 11
    assert read["rx_per_id"][f"{RX_IDS_KEPT - 1:#x}"] == 1
    assert stats.snapshot()["rx_per_id"] == read["rx_per_id"]


def test_the_published_numbers_change_only_when_the_loop_answers():
    """The server reads the published area while the loop counts on: the loop's counting
    (live area) never shows there until its next answer, which copies all of it at once."""
    stats = Stats.in_shared_memory()
    other = SharedStats(fd=stats.shared.fd)
    stats.counters["ticks"] = 5
    stats.count_frame(0x123)
    stats.publish(None, None)
    stats.counters["ticks"] += 1
    stats.counters["valid_ticks"] += 1
    stats.count_frame(0x123)
    stats.count_frame(0x456)  # a new ID: the published area gets it with the next answer
    stats.set_gauges(1, 2.0, 3.0, 4.0)
    read = other.read()
    assert read["counters"]["ticks"] == 5 and read["counters"]["valid_ticks"] == 0
    assert read["rx_per_id"] == {"0x123": 1} and read["uptime_s"] == 0.0
    assert other.ticks_live() == 6
    stats.publish(None, None)
    read = other.read()
    assert read["counters"]["ticks"] == 6 and read["counters"]["valid_ticks"] == 1
    assert read["rx_per_id"] == {"0x123": 2, "0x456": 1} and read["uptime_s"] == 4.0


def _opcodes_run(call) -> int:
    """Python bytecodes ``call()`` executes (sys.settrace, per opcode)."""
    count = 0

    def trace(frame, event, _arg):
        nonlocal count
        frame.f_trace_opcodes = True
        if event == "opcode":
            count += 1
        return trace

    sys.settrace(trace)
    try:
        call()
    finally:
        sys.settrace(None)
    return count


def test_the_loops_answer_is_the_same_python_work_however_many_ids_and_counts():
    """O(1) in what it copies: the answer is a fixed handful of bytecodes (two buffer
    copies), not Python work per counter, gauge or CAN ID (packing them cost the loop p50
    33 us on cold caches: every Python object touched is a cache miss there)."""
    decode = np.zeros((3, 4), dtype=np.int64)
    runs = []
    for ids in (3, 300):
        stats = Stats.in_shared_memory(StatsLayout(rows=("a", "b", "c"),
                                                   columns=("w", "x", "y", "z")))
        for frame_id in range(ids):
            stats.count_frame(frame_id)
        stats.counters["ticks"] = 7
        stats.publish(decode, None)  # binds the decode source once
        decode[1, 2] = ids
        runs.append(_opcodes_run(lambda stats=stats: stats.publish(decode, None)))
        read = SharedStats(stats.shared.layout, fd=stats.shared.fd).read()
        assert len(read["rx_per_id"]) == ids and read["counters"]["ticks"] == 7
        assert read["decode_errors"]["b"]["y"] == ids
    assert runs[0] == runs[1] and runs[0] < 60, runs


class _Loop:
    """The loop's side of the stats server, polled the way the daemon's slack does."""

    def __init__(self, tmp_path: Path, prometheus: str | None = None, name: str = "stats.sock"):
        self.stats = Stats.in_shared_memory()
        self.path = str(tmp_path / name)
        self.lines: list[str] = []
        self.server = StatsServer(self.path, parse_prometheus(prometheus) if prometheus else None,
                                  self.stats, log=self.lines.append)
        self.server.wait_ready()
        self.documents = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._poll, daemon=True)
        self.thread.start()

    def document(self, fresh: bool) -> bytes:
        self.documents += 1
        self.stats.set_gauges(1, 0.5, 20.0, 1.0)
        return self.stats.publish(None, {"estimator": "zero"} if fresh else None)

    def _poll(self) -> None:
        while not self.stop.is_set():
            self.server.poll(self.document)
            self.server.poll_health()
            time.sleep(0.01)  # a tick

    def close(self) -> None:
        self.stop.set()
        self.thread.join()
        self.server.close()


@pytest.fixture
def loop(tmp_path):
    running = _Loop(tmp_path, prometheus="127.0.0.1:0")
    yield running
    running.close()


def test_the_loops_answer_never_summarises_a_histogram(loop, monkeypatch):
    """A snapshot cost the loop 7-9 ms once the histograms had filled (hdrh's Python loops
    in the loop's thread); now the loop sends the counters only and the server process reads
    the histograms from shared memory."""
    for name in HISTOGRAMS:
        for value in np.random.default_rng(0).lognormal(5, 1, 2000):
            loop.stats.record(name, value)
    query(loop.path)  # the first answer carries the words (estimator, events) once
    time.sleep(0.05)  # older than the server shares

    def forbidden(*_args, **_kwargs):
        raise AssertionError("the loop summarised a histogram")

    for method in ("get_value_at_percentile", "get_percentile_to_value_dict",
                   "get_max_value", "get_mean_value"):
        monkeypatch.setattr(HdrHistogram, method, forbidden)
    monkeypatch.setattr("slipd.daemon.stats.summarize", forbidden)
    monkeypatch.setattr("json.dumps", forbidden)  # nor encoded its counters as JSON
    loop.documents = 0
    snapshot = query(loop.path)
    assert snapshot["cycle_latency_us"]["count"] == 2000
    assert snapshot["counters"]["ticks"] == 0 and snapshot["estimator"] == "zero"
    assert loop.documents >= 1


def test_snapshots_taken_during_a_burst_of_updates_are_each_one_instant(tmp_path):
    """A loop that counts frames, ticks and histogram records as the daemon's does (new
    CAN IDs appearing as it goes) while 8 clients ask over and over: every snapshot served
    is one instant of it, between two ticks. Its counters agree with each other and the
    frames per ID, and the histograms hold exactly the ticks counted (the server copies
    them before the loop's next tick, or asks again)."""
    stats = Stats.in_shared_memory()
    path = str(tmp_path / "burst.sock")
    server = StatsServer(path, None, stats, log=lambda _line: None)
    server.wait_ready()
    stop = threading.Event()

    def loop() -> None:
        tick = 0
        while not stop.is_set():
            tick += 1
            for k in range(3):  # frames received before the tick
                stats.count_frame(0x100 + (3 * tick + k) % 97)
                stats.counters["rx_frames"] += 1
            stats.counters["ticks"] += 1  # as Daemon._measure: the count, then the records
            for name in ("cycle_latency_us", "compute_us", "wakeup_lateness_us"):
                stats.record(name, 100 + tick % 50)
            stats.counters["valid_ticks"] += 1
            stats.set_gauges(1, 0.0, 0.0, float(tick))
            server.poll(lambda fresh: stats.publish(None, {"estimator": "x"} if fresh else None))
            time.sleep(0.004)

    snapshots: list[dict] = []

    def client() -> None:
        while not stop.is_set():
            snapshots.append(query(path, timeout=10))

    threads = [threading.Thread(target=loop)] + [threading.Thread(target=client)
                                                for _ in range(8)]
    try:
        for thread in threads:
            thread.start()
        time.sleep(4.0)
    finally:
        stop.set()
        for thread in threads:
            thread.join()
        server.close()
    assert len(snapshots) > 50
    ids_seen = set()
    for snapshot in snapshots:
        c = snapshot["counters"]
        assert c["valid_ticks"] == c["ticks"] == snapshot["uptime_s"], c
        assert c["rx_frames"] == 3 * c["ticks"] == sum(snapshot["rx_per_id"].values()), c
        for name in ("cycle_latency_us", "compute_us", "wakeup_lateness_us"):
            assert snapshot[name]["count"] == c["ticks"], (name, snapshot[name], c)
        ids_seen.update(snapshot["rx_per_id"])
    assert len(ids_seen) == 97 and snapshots[-1]["counters"]["ticks"] > 100


def test_a_snapshot_carries_the_words_sent_with_its_answer():
    """The loop sends its words (estimator, events) before it answers; the server's main
    thread and its collector both read the control socket. The main thread had received
    them and not yet stored them when the collector built the snapshot: a Prometheus scrape
    labelled the estimator ''. Slowed down here, that window is 0.3 s wide."""
    from slipd.daemon.stats_server import SnapshotSource

    shared = SharedStats()
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    source = SnapshotSource(theirs, shared)
    store = source._store_words

    def slow_store(message: bytes) -> None:
        time.sleep(0.3)
        store(message)

    source._store_words = slow_store
    threading.Thread(target=source.run, daemon=True).start()
    stop = threading.Event()

    def loop() -> None:  # StatsServer.poll's protocol: words first, then the answer
        sequence = shared.sequence_words
        while not stop.is_set():
            if sequence[0] != sequence[1]:
                requested = sequence[0]
                if requested == 1:
                    ours.send(b'{"estimator": "kinematic_heuristic"}')
                shared.publish(None)
                sequence[1] = requested
            time.sleep(0.002)

    thread = threading.Thread(target=loop)
    thread.start()
    try:
        assert source.get()["estimator"] == "kinematic_heuristic"
    finally:
        stop.set()
        thread.join()
        ours.close()


def test_a_hundred_concurrent_clients_all_get_an_answer_and_share_the_loops(loop):
    """100 `slipd stats` at once: 93 failed with EAGAIN on a listen backlog of 4; now they
    queue, and the loop answers a handful of times for all of them."""
    results: list[object] = []

    def one() -> None:
        try:
            results.append(query(loop.path, timeout=10.0))
        except OSError as exc:
            results.append(exc)

    threads = [threading.Thread(target=one) for _ in range(100)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    failures = [r for r in results if isinstance(r, Exception)]
    assert not failures, failures[:3]
    assert len(results) == 100
    assert loop.documents <= 30  # answers are shared, not one per client


def test_prometheus_through_prometheus_client_in_seconds(loop):
    for value in (100, 200, 300, 400):
        loop.stats.record("cycle_latency_us", value)
    loop.stats.counters["ticks"] = 7
    host, port = loop.server.http_address
    with urllib.request.urlopen(f"http://{host}:{port}/metrics", timeout=5) as reply:
        text = reply.read().decode()
    families = {f.name: f for f in text_string_to_metric_families(text)}
    assert families["slipd_ticks"].samples[0].value == 7  # slipd_ticks_total
    cycle = families["slipd_cycle_latency_seconds"]
    assert cycle.type == "summary"
    quantiles = {s.labels["quantile"]: s.value for s in cycle.samples if "quantile" in s.labels}
    assert set(quantiles) == {"0.5", "0.9", "0.99", "0.999"}
    assert quantiles["0.5"] == pytest.approx(200e-6, rel=1e-3)
    count = [s.value for s in cycle.samples if s.name.endswith("_count")]
    assert count == [4]
    assert families["slipd_cycle_latency_max_seconds"].samples[0].value == pytest.approx(
        400e-6, rel=1e-3)
    assert families["slipd_beta_radians"].samples[0].value == pytest.approx(np.radians(0.5))
    assert "slipd_decode_frames" in families


def test_the_stats_socket_is_group_readable(loop):
    mode = os.stat(loop.path).st_mode
    assert stat.S_ISSOCK(mode) and stat.S_IMODE(mode) == 0o660


def test_a_killed_stats_server_is_reported_and_started_again(loop):
    old = loop.server.process.pid
    os.kill(old, 9)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        if loop.server.process.pid != old and loop.server._ready:
            break
        time.sleep(0.05)
    assert loop.server.process.pid != old
    assert query(loop.path)["counters"]["stats_server_restarts"] == 1
    assert any("stats server stopped" in line for line in loop.lines)
    assert any("started again" in line for line in loop.lines)


def test_the_socket_is_removed_when_the_daemon_dies(tmp_path):
    """SIGKILL of the daemon: its stats server sees the control socket close and removes
    its socket file, so the next start finds no stale one."""
    script = f"""
import time
from slipd.daemon.stats import Stats, StatsServer
server = StatsServer({str(tmp_path / 's.sock')!r}, None, Stats.in_shared_memory())
server.wait_ready()
print(server.process.pid, flush=True)
time.sleep(60)
"""
    daemon = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    helper = int(daemon.stdout.readline())
    assert (tmp_path / "s.sock").exists()
    daemon.kill()
    daemon.wait()
    deadline = time.monotonic() + 10
    while (tmp_path / "s.sock").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not (tmp_path / "s.sock").exists()
    with pytest.raises(OSError):
        for _ in range(200):  # the helper is gone too (reaped by init)
            os.kill(helper, 0)
            time.sleep(0.05)


def test_the_stats_socket_never_replaces_a_file(tmp_path):
    """`--stats-socket FILE` deleted whatever FILE was."""
    precious = tmp_path / "notes.txt"
    precious.write_text("keep me")
    with pytest.raises(ConfigError, match="exists and is not a socket"):
        check_stats_socket(str(precious))
    assert precious.read_text() == "keep me"
    with pytest.raises(ConfigError, match="does not exist"):
        check_stats_socket("/nonexistent/dir/sock")


def test_a_second_daemon_does_not_take_over_a_socket_the_first_answers_on(loop, tmp_path):
    with pytest.raises(ConfigError, match="another slipd answers there"):
        check_stats_socket(loop.path)
    assert query(loop.path)["estimator"] == "zero"  # the first still answers


def test_a_stale_socket_is_replaced(tmp_path):
    path = tmp_path / "stale.sock"
    left = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    left.bind(str(path))
    left.close()  # bound, never listening: what a killed daemon leaves
    check_stats_socket(str(path))
    running = _Loop(tmp_path, name="stale.sock")
    try:
        assert query(str(path))["estimator"] == "zero"
    finally:
        running.close()
    assert not path.exists()


@pytest.mark.parametrize(("value", "public", "expected"), [
    ("127.0.0.1:0", False, ("127.0.0.1", 0)),
    (0, False, ("127.0.0.1", 0)),  # a bare port (TOML `prometheus = 9464`) is loopback
    ("localhost:0", False, ("localhost", 0)),
    ("[::1]:0", False, ("::1", 0)),
])
def test_prometheus_addresses(value, public, expected):
    assert parse_prometheus(value, public) == expected


@pytest.mark.parametrize(("value", "match"), [
    ("127.0.0.1:abc", "is not a number"),
    ("127.0.0.1:70000", "is not a number in 0..65535"),
    ("0.0.0.0:0", "--prometheus-public"),
    ("10.1.2.3:0", "--prometheus-public"),
    ("nohost:0", "not an IP address"),
    (True, "expected"),
    (9.5, "expected"),
])
def test_bad_prometheus_values_are_clear_errors(value, match):
    with pytest.raises(ConfigError, match=match):
        parse_prometheus(value)


def test_a_port_in_use_is_a_clear_error():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        with pytest.raises(ConfigError, match="cannot listen there"):
            parse_prometheus(f"127.0.0.1:{port}")


def test_slipd_stats_into_a_pipe_closed_early(loop):
    """`slipd stats --json | head -1`: a BrokenPipeError traceback before."""
    slipd = str(Path(sys.executable).with_name("slipd"))
    shell = subprocess.run(f"{slipd} stats --socket {loop.path} --json | head -1",
                           shell=True, capture_output=True, text=True, timeout=60)
    assert shell.stdout.strip() == "{"
    assert "Traceback" not in shell.stderr and "BrokenPipe" not in shell.stderr


def test_slipd_stats_without_a_daemon_says_so(tmp_path):
    slipd = str(Path(sys.executable).with_name("slipd"))
    result = subprocess.run([slipd, "stats", "--socket", str(tmp_path / "none.sock")],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "no daemon answers" in result.stderr


def _run_with_client(daemon, client, *buses) -> None:
    """daemon.run() with ``client`` in a thread of its own (it ends the run); then the
    buses are shut down."""
    thread = threading.Thread(target=client)
    thread.start()
    try:
        daemon.run()
    finally:
        thread.join()
        for bus in buses:
            bus.shutdown()


def test_the_served_snapshot_is_the_daemons_own(tmp_path):
    """The document the stats server builds from the shared block equals the one the
    daemon computes itself (Daemon.snapshot), key for key."""
    import can

    from slipd.daemon.loop import Daemon, DaemonConfig
    from slipd.profile import load_profile

    bus = can.Bus(interface="virtual", channel="served")
    feeder = can.Bus(interface="virtual", channel="served")
    path = str(tmp_path / "d.sock")
    daemon = Daemon(DaemonConfig(profile=load_profile("default"), estimator="zero",
                                 interface="virtual", channel="served", duration=60,
                                 stats_socket=path), bus=bus, log=lambda _line: None)
    served: list[dict] = []

    def second(d: Daemon) -> None:  # the loop's thread, in its slack
        feeder.send(can.Message(arbitration_id=0x123, data=b"\x00", is_extended_id=False))
        if not d.bus_events:
            d._bus_event("an event for the words")

    def ask() -> None:  # a client, as `slipd stats` is
        daemon.ready.wait(60)
        deadline = time.monotonic() + 30
        while not daemon.bus_events and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)
        served.append(query(path))
        daemon.request_stop()

    daemon.on_second = second
    _run_with_client(daemon, ask, bus, feeder)
    assert served, "no snapshot served"
    local = daemon.snapshot()  # after the run: counters went on a little
    got = served[0]
    assert set(got) == set(local), set(got) ^ set(local)
    assert got["decode_errors"] == local["decode_errors"]
    assert got["bus_events"] == local["bus_events"] and got["rx_per_id"] == local["rx_per_id"]
    assert got["estimator"] == "zero" and got["recorder"] is None
    assert got["counters"]["ticks"] <= local["counters"]["ticks"]


def test_consistency_verdicts_are_counted_and_served_per_estimator(tmp_path):
    """The consistency monitor's FAIL and WARN ticks (Pipeline.consistency_flags) are
    counters of the snapshot and of Prometheus, labelled with the running estimator."""
    import can

    from slipd.daemon.loop import Daemon, DaemonConfig
    from slipd.estimators.consistency import Flag
    from slipd.profile import load_profile

    bus = can.Bus(interface="virtual", channel="verdicts")
    path = str(tmp_path / "d.sock")
    daemon = Daemon(DaemonConfig(profile=load_profile("default"),
                                 estimator="kinematic_heuristic", interface="virtual",
                                 channel="verdicts", duration=60, stats_socket=path,
                                 prometheus="127.0.0.1:0"), bus=bus, log=lambda _line: None)
    ticks = [0]

    def verdict(_state) -> int:  # 20 ticks FAIL (with WARN), 15 WARN, 7 FAIL (witness), then
        #                        consistent
        ticks[0] += 1
        k = ticks[0]
        if 10 <= k < 30:
            return Flag.CHECKED | Flag.FAIL | Flag.WARN | Flag.DYNAMIC | (
                Flag.IMPRECISE if k < 15 else 0)
        if 45 <= k < 52:
            return Flag.CHECKED | Flag.FAIL | Flag.WITNESS
        return Flag.CHECKED | (Flag.WARN | Flag.INNOVATION if 30 <= k < 45 else 0)

    daemon.pipeline.consistency_flags = verdict
    served: dict = {}  # filled by the client, as `slipd stats` and a scrape

    def ask() -> None:
        daemon.ready.wait(60)
        while ticks[0] < 60:
            time.sleep(0.05)
        served["snapshot"] = query(path)
        host, port = daemon.server.http_address
        with urllib.request.urlopen(f"http://{host}:{port}/metrics", timeout=5) as reply:
            served["metrics"] = reply.read().decode()
        daemon.request_stop()

    _run_with_client(daemon, ask, bus)
    counters = served["snapshot"]["counters"]
    assert counters["consistency_fail_ticks"] == 27
    assert counters["consistency_warn_ticks"] == 35
    assert counters["consistency_innovation_ticks"] == 15
    assert counters["consistency_imprecise_ticks"] == 5
    assert counters["consistency_witness_ticks"] == 7
    families = {f.name: f for f in text_string_to_metric_families(served["metrics"])}
    for name, value in (("slipd_consistency_fail_ticks", 27), ("slipd_consistency_warn_ticks", 35),
                        ("slipd_consistency_innovation_ticks", 15),
                        ("slipd_consistency_imprecise_ticks", 5),
                        ("slipd_consistency_witness_ticks", 7)):
        (sample,) = families[name].samples
        assert sample.labels == {"estimator": "kinematic_heuristic"} and sample.value == value


def test_clients_before_the_loops_first_answer_get_a_reason_and_no_traceback(tmp_path, capfd):
    """While the daemon warms up (numba compiles, 39 s in the 1-hour soak) its stats server
    already listens: every Prometheus scrape ended in a traceback of prometheus_client's
    server (the collector raised), and `slipd stats` said only that the loop did not answer."""
    stats = Stats.in_shared_memory()
    path = str(tmp_path / "stats.sock")
    server = StatsServer(path, ("127.0.0.1", 0), stats)
    server.wait_ready()
    try:  # no poll(): the loop has not started
        host, port = server.http_address
        with urllib.request.urlopen(f"http://{host}:{port}/metrics", timeout=10) as reply:
            assert reply.status == 200
            families = {f.name: f for f in text_string_to_metric_families(reply.read().decode())}
        assert families["slipd_loop_answering"].samples[0].value == 0
        assert "slipd_ticks" not in families
        with pytest.raises(OSError, match="no snapshot yet.*still starting"):
            query(path, timeout=10.0)
    finally:
        server.close()
    assert "Traceback" not in capfd.readouterr().err
