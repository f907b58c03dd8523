"""Many logs on a real Dask cluster (slipd.replay.fleet): a scheduler and two workers started as
processes of their own on 127.0.0.1, no mocks. The dataset equals the logs replayed one by one,
a corrupt log among good ones is reported with its line while the others finish, --resume
skips what is done, and eval on the cluster scores as eval without it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from slipd.cli import main

pytest.importorskip("distributed")
pq = pytest.importorskip("pyarrow.parquet")
pytest.importorskip("vehiclemodels")

METHODS = "zero,kinematic_heuristic"
#: glibc's trim threshold as the test run was started (a nanny with dask's defaults would set
#: 65536 in this very process's environment, which the workers then inherit)
TRIM_THRESHOLD_OF_THE_SHELL = os.environ.get("MALLOC_TRIM_THRESHOLD_")


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """Three short drives with their truth, and a copy of one with a malformed line."""
    from slipd.commands.sim import simulate_to_files

    folder = tmp_path_factory.mktemp("fleet_logs")
    for name, seconds in (("step_steer", 4.0), ("sine_steer", 5.0), ("slalom", 6.0)):
        simulate_to_files(name, folder, duration=seconds)
    lines = (folder / "sine_steer.log").read_text().splitlines(keepends=True)
    lines.insert(1200, "(1700000005.000000) can0 1O1#0011\n")
    (folder / "corrupt.log").write_text("".join(lines))
    return folder


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """``dask scheduler`` and two ``dask worker`` processes on loopback; yields the address."""
    folder = tmp_path_factory.mktemp("dask")
    scheduler_file = folder / "scheduler.json"
    dask = [sys.executable, "-m", "dask"]
    env = {**os.environ, "DASK_DISTRIBUTED__WORKER__DAEMON": "False"}
    processes = [subprocess.Popen(
        dask + ["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                "--scheduler-file", str(scheduler_file)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)]
    try:
        deadline = time.monotonic() + 60
        while not scheduler_file.exists() and time.monotonic() < deadline:
            time.sleep(0.2)
        address = json.loads(scheduler_file.read_text())["address"]
        for k in range(2):
            processes.append(subprocess.Popen(
                dask + ["worker", address, "--host", "127.0.0.1", "--nthreads", "1",
                        "--no-dashboard", "--name", f"w{k}", "--local-directory",
                        str(folder / f"w{k}")],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env))
        from distributed import Client

        with Client(address, timeout=30) as client:
            client.wait_for_workers(2, timeout=90)
            assert len(client.scheduler_info()["workers"]) == 2
        yield address
    finally:
        for process in reversed(processes):
            process.terminate()
        for process in processes:
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()


def assert_same_rows(path: Path, other: Path) -> None:
    """The two Parquet files hold the same columns (units included), bit for bit (NaN too),
    and the same run description."""
    a, b = pq.read_table(path), pq.read_table(other)
    assert a.schema.remove_metadata() == b.schema.remove_metadata()
    assert a.schema.metadata[b"slipd"] == b.schema.metadata[b"slipd"]
    assert a.num_rows == b.num_rows > 0
    for name in a.column_names:
        x, y = a[name].combine_chunks(), b[name].combine_chunks()
        if hasattr(x, "dictionary"):
            assert x.dictionary_decode().to_pylist() == y.dictionary_decode().to_pylist()
        else:
            assert x.is_null().to_pylist() == y.is_null().to_pylist(), name
            assert x.fill_null(0).to_numpy().tobytes() == y.fill_null(0).to_numpy().tobytes(), name


def test_a_cluster_replays_each_log_as_one_run_and_reports_the_corrupt_one(
        logs, cluster, tmp_path, capsys):
    good = ["sine_steer", "slalom", "step_steer"]
    out = tmp_path / "dataset"
    pattern = str(logs / "*.log")
    assert main(["replay", pattern, "--estimator", METHODS, "--dask", cluster,
                 "--out", str(out)]) == 1
    captured = capsys.readouterr()
    assert "corrupt.log:1201: expected a hex CAN ID" in captured.err
    assert "1 of 4 logs failed" in captured.err
    parts = sorted(p.parent.name for p in (out / "estimates").glob("*/part-0.parquet"))
    assert parts == [f"log={name}" for name in good]
    assert not [p for p in out.rglob(".*")]  # no partial file left behind
    summary = pq.read_table(out / "summary.parquet").to_pydict()
    rows = {Path(log).stem: k for k, log in enumerate(summary["log"])}
    failed = rows["corrupt"]
    assert summary["status"][failed] == "failed" and ":1201:" in summary["error"][failed]
    workers = set()
    for name in good:
        # the partition is the table of that log replayed alone
        alone = tmp_path / f"{name}.parquet"
        assert main(["replay", str(logs / f"{name}.log"), "--estimator", METHODS,
                     "--out", str(alone)]) == 0
        partition = out / "estimates" / f"log={name}" / "part-0.parquet"
        assert_same_rows(partition, alone)
        record = json.loads(pq.read_metadata(partition).metadata[b"slipd_log"])
        k = rows[name]
        import hashlib

        digest = hashlib.sha256((logs / f"{name}.log").read_bytes()).hexdigest()
        assert record["sha256"] == summary["sha256"][k] == digest
        assert record["size_bytes"] == (logs / f"{name}.log").stat().st_size
        assert record["profile"] == "default" and len(record["profile_sha256"]) == 16
        assert summary["status"][k] == "ok" and summary["ticks"][k] > 300
        workers.add(summary["worker"][k])
    assert len(workers) == 2  # both workers took logs
    # the dataset reads as one table with the log as a column
    pd = pytest.importorskip("pandas")
    frame = pd.read_parquet(out / "estimates")
    assert sorted(frame["log"].unique()) == good
    # --resume: the three done logs are skipped, the corrupt one is tried (and fails) again
    assert main(["replay", pattern, "--estimator", METHODS, "--dask", cluster,
                 "--out", str(out), "--resume"]) == 1
    assert capsys.readouterr().out.count("done before (--resume)") == 3
    summary = pq.read_table(out / "summary.parquet").to_pydict()
    assert sorted(summary["status"]) == ["failed", "skipped", "skipped", "skipped"]


def test_eval_on_the_cluster_scores_as_eval_here(logs, cluster, tmp_path):
    good = [str(logs / f"{name}.log") for name in ("sine_steer", "slalom", "step_steer")]
    here, there = tmp_path / "here.json", tmp_path / "there.json"
    assert main(["eval", *good, "--estimator", METHODS, "--out", str(here)]) == 0
    assert main(["eval", *good, "--estimator", METHODS, "--out", str(there),
                 "--dask", cluster]) == 0
    assert json.loads(here.read_text()) == json.loads(there.read_text())
    scores = json.loads(here.read_text())
    assert set(scores["scenarios"]) == {Path(g).name for g in good}
    assert np.isfinite(scores["overall"]["estimators"]["kinematic_heuristic"]["beta_rms_deg"])


def test_a_local_cluster_forks_its_workers_from_a_server_that_loaded_the_kernels(logs,
                                                                                 tmp_path):
    """--dask local:N: the workers come from the forkserver that imported slipd and loaded
    the run's kernels (not interpreters of their own), and replay as the sequential run."""
    from slipd.replay import fleet

    methods = METHODS.split(",")
    names = ["slalom", "step_steer"]
    with fleet.dask_client("local:2", methods, "default") as client:
        preloaded = client.run(lambda: (
            "slipd.replay.dask_forkserver" in __import__("sys").modules,
            __import__("os").getppid()))
        # no statistical profiler sampling the workers' stacks (fleet.LOCAL_WORKER_CONFIG)
        profiling = client.run(lambda: __import__("dask").config.get(
            "distributed.worker.profile.enabled"))
        # nor glibc's trim threshold that makes every chunk's arrays fresh mmaps
        trim = client.run(lambda: __import__("os").environ.get("MALLOC_TRIM_THRESHOLD_"))
        # but slipd's own thresholds, set once in the forkserver (stream.keep_freed_memory)
        kept = client.run(lambda: __import__("slipd.replay.stream").replay.stream._KEPT)
        records = fleet.run_fleet([logs / f"{n}.log" for n in names], "default", methods,
                                  tmp_path / "dataset", client, progress=False)
    assert len(preloaded) == 2
    assert set(profiling.values()) == {False}
    assert set(trim.values()) == {TRIM_THRESHOLD_OF_THE_SHELL}
    if __import__("platform").libc_ver()[0] == "glibc":
        assert set(kept.values()) == {True}
    assert all(loaded for loaded, _ in preloaded.values())
    assert {parent for _, parent in preloaded.values()} != {os.getpid()}
    assert [r.status for r in records] == ["ok", "ok"]
    # two workers share the CPUs' replay threads (one each on 2 CPUs: stages in turn)
    assert [r.threads for r in records] == [max(1, len(os.sched_getaffinity(0)) // 2)] * 2
    for name in names:
        alone = tmp_path / f"{name}.parquet"
        assert main(["replay", str(logs / f"{name}.log"), "--estimator", METHODS,
                     "--out", str(alone)]) == 0
        assert_same_rows(tmp_path / "dataset" / "estimates" / f"log={name}" / "part-0.parquet",
                         alone)


def test_a_local_cluster_listens_on_loopback_only():
    """`--dask local:N` binds loopback only (the project's network rule): the scheduler and
    the HTTP server distributed starts even with dashboard_address=None (dask/distributed#8136)
    run in this process; every socket it listens on must be 127.0.0.1 or ::1."""
    import shutil

    from slipd.replay.fleet import dask_client

    if shutil.which("ss") is None:
        pytest.skip("needs ss (iproute2) to list this process's listening sockets")

    with dask_client("local:1", ["zero"], "default") as client:
        info = client.scheduler_info()
        listening = subprocess.run(["ss", "-ltnpH"], capture_output=True, text=True).stdout
    mine = [line.split()[3] for line in listening.splitlines() if f"pid={os.getpid()}," in line]
    assert info["address"].startswith("tcp://127.0.0.1:")
    assert mine and all(a.startswith(("127.0.0.1:", "[::1]:")) for a in mine), mine


def test_the_largest_logs_go_first_and_the_results_keep_the_logs_order():
    """Longest processing time first: a run's last tasks are its short logs, so no worker
    idles long at the end while another finishes a long one. One worker with one thread runs
    the tasks in the order they were submitted."""
    from slipd.replay.fleet import dask_client, run_tasks

    sizes = [10.0, 30.0, 20.0, 30.0, 5.0]
    with dask_client("local:1", ["zero"], "default") as client:
        results = run_tasks(client, lambda item: (item, __import__("time").monotonic_ns()),
                            list(range(len(sizes))), [f"log{k}" for k in range(len(sizes))],
                            progress=False, sizes=sizes)
    assert [error for _, error in results] == [None] * len(sizes)
    assert [item for (item, _), _ in results] == list(range(len(sizes)))
    started = sorted(range(len(sizes)), key=lambda k: results[k][0][1])
    assert started == [1, 3, 2, 0, 4]  # by size, equal sizes in the logs' order
