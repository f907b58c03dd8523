"""Many logs on a Dask cluster: one task per log, results in a partitioned Parquet dataset.

``slipd replay LOG... --dask local[:N] | tcp://SCHEDULER:8786 --out DIR`` (and ``slipd eval
LOG... --dask ...``) hands each log to dask.distributed as one task; slipd grows no scheduler
of its own. A log is one task, never split: every method's state runs through the log in
order (the streaming engine carries it from chunk to chunk on one worker), so a piece of a
log could only start from a state nobody has yet. What a run writes::

    DIR/estimates/log=KEY/part-0.parquet   one partition per log: the replay table (the
                                           columns of slipd replay --out FILE.parquet); its
                                           file metadata b"slipd_log": the log's record
    DIR/summary.parquet                    one row per log (done, skipped by --resume, failed)

KEY is the log's path relative to the logs' common folder without its suffix (URI-escaped in
the folder name, as pyarrow's hive partitioning expects: ``pandas.read_parquet(DIR /
"estimates")`` has a ``log`` column). A log's record (:data:`RECORD_FIELDS`): its path, size,
modification time and SHA-256, the profile (name, as given, and a SHA-256 of its TOML and
DBC), the methods, frames, ticks, skipped lines, rejected frames, the VALID share of each
method, the seconds it took and where (with that worker's peak RSS), and its status and error.

A partition is written to a hidden file and renamed when complete, so an interrupted run
leaves only whole partitions; ``--resume`` skips each log whose partition records the same
path, size, modification time, profile, methods and options. A log that fails (a malformed
line, a worker that died) is a summary row with its error; the others finish, and the command
exits 1.

Workers need slipd installed (and the logs and a profile path at the same place); each warms
numba's keyed cache (slipd.numba_cache) and the run's kernels once, through a worker plugin,
before its first task. A ``local`` cluster's workers are forked from a forkserver that has
loaded the kernels once (slipd.replay.dask_forkserver), so the plugin finds them loaded.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import socket
import sys
import time
import urllib.parse
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

from slipd.errors import ConfigError, SlipdError
from slipd.replay.ahead import THREADS_VARIABLE, replay_threads

ESTIMATES = "estimates"
SUMMARY = "summary.parquet"
PART = "part-0.parquet"
#: schema metadata key of a partition's record
RECORD_KEY = "slipd_log"
LOG_SUFFIXES = (".log", ".candump", ".asc", ".blf", ".trc", ".mf4", ".csv")
#: a --resume decision compares these fields of the record
SAME_RUN = ("log", "size_bytes", "mtime_ns", "profile", "profile_sha256", "methods",
            "options")
#: dask config of a ``local`` cluster (its scheduler, nannies and workers): no statistical
#: profiler. distributed samples every thread's stack each 10 ms by default
#: (distributed.worker.profile), which cannot see into slipd's numba kernels and took 5 % more
#: CPU per task: measured on 40 ten-minute drives with every method, the workers' tasks
#: 34.2-34.9 s with it, 32.0-33.2 s without. The event loops' health tick (20 ms by default),
#: system monitor (0.5 s) and the nannies' memory monitor (0.1 s) at 1 s, 5 s and 1 s: five
#: processes on two cores wake up less often beside the workers' tasks (the same drives: the
#: workers' tasks 30.0 s of wall clock for 29.5 CPU s, against 30.0-31.9 s for 29.0-30.9).
#: A cluster of your own: the README's dask config file.
LOCAL_WORKER_CONFIG = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "5s",
    "distributed.worker.memory.monitor-interval": "1s",
}
#: environment variables a ``local`` cluster's nannies do not set for the workers. dask sets
#: MALLOC_TRIM_THRESHOLD_=65536 (distributed.nanny.pre-spawn-environ) so that long-lived
#: workers give freed memory back to the OS; with it glibc fixes its mmap threshold at 128 kB
#: instead of raising it to the size of the blocks a process frees, so every chunk's arrays are
#: fresh mmaps, zero-filled page by page: measured on the endurance drive with every method, one
#: replay thread, 9.54-9.56 s (1.12 s system) with it against 9.12-9.18 s (0.55-0.64 s system)
#: without. A replay's memory is bounded by its chunk and a local cluster lives for one run.
#: The workers forked from the forkserver then take slipd's own thresholds from it
#: (stream.keep_freed_memory, set in slipd.replay.dask_forkserver); a worker its nanny
#: restarts is spawned, and keeps glibc's defaults.
LOCAL_WORKER_UNSET_ENVIRON = ("MALLOC_TRIM_THRESHOLD_",)


# ---------------------------------------------------------------------------------------------
# the cluster
# ---------------------------------------------------------------------------------------------


def parse_dask(spec: str) -> tuple[str, int | str]:
    """``local`` (a worker per CPU), ``local:N`` or a scheduler address (``tcp://HOST:PORT``,
    ``tls://...``, ``HOST:PORT``) -> ("local", N) or ("address", address)."""
    spec = spec.strip()
    if spec == "local" or spec.startswith("local:"):
        count = spec.partition(":")[2] or str(os.cpu_count() or 1)
        if not count.isdigit() or int(count) < 1:
            raise ConfigError(f"--dask {spec}: expected local, local:N (N >= 1 workers) or a "
                              "scheduler address such as tcp://HOST:8786")
        return "local", int(count)
    if "://" in spec or ":" in spec:
        return "address", spec
    raise ConfigError(f"--dask {spec}: expected local, local:N or a scheduler address such as "
                      "tcp://HOST:8786")


@contextlib.contextmanager
def dask_client(spec: str, methods: list[str], profile: str) -> Iterator:
    """A dask.distributed Client for ``--dask SPEC`` (a local cluster of single-threaded
    worker processes on 127.0.0.1, or the scheduler at an address), with the kernel warm-up
    registered on every worker."""
    try:
        from distributed import Client, LocalCluster

        from slipd.replay.dask_worker import KernelWarmup
    except ImportError as exc:
        from slipd.errors import DependencyError

        raise DependencyError("--dask needs dask.distributed: pip install 'slipd[dask]'"
                              ) from exc
    kind, value = parse_dask(spec)
    cluster = None
    try:
        if kind == "local":
            with _forkserver_with_kernels(methods, profile):
                cluster = LocalCluster(n_workers=int(value), threads_per_worker=1,
                                       processes=True, host="127.0.0.1",
                                       dashboard_address=None, silence_logs=40,
                                       env={THREADS_VARIABLE: str(_threads_each(int(value)))})
            client = Client(cluster)
        else:
            client = Client(str(value), timeout=30)
    except OSError as exc:
        if cluster is not None:
            cluster.close()
        raise ConfigError(f"--dask {spec}: cannot reach the scheduler: {exc}") from exc
    try:
        client.register_plugin(KernelWarmup(methods, profile), name="slipd-kernels")
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _threads_each(workers: int) -> int:
    """Replay threads of each of a local cluster's ``workers`` processes: the CPUs shared out
    (one each when there are as many workers as CPUs: their stages then run in turn in the
    worker's thread instead of taking turns on the cores with the other workers')."""
    return max(1, replay_threads() // max(workers, 1))


@contextlib.contextmanager
def _forkserver_with_kernels(methods: list[str], profile: str) -> Iterator[None]:
    """Local workers forked from a forkserver that has imported distributed and slipd and
    loaded the run's kernels (slipd.replay.dask_forkserver), instead of spawned interpreters
    that each import and load them again, with :data:`LOCAL_WORKER_CONFIG` (their nannies
    copy the dask config when the cluster creates them) and without the environment variables
    of :data:`LOCAL_WORKER_UNSET_ENVIRON`. The forkserver only for the workers
    started inside the block (a worker its nanny restarts later is spawned as usual and warmed
    by KernelWarmup)."""
    import dask
    from distributed.utils import get_mp_context

    from slipd.replay import dask_forkserver

    os.environ[dask_forkserver.KERNELS_VARIABLE] = f"{','.join(methods)}@{profile}"
    environ = {name: value for name, value in
               dask.config.get("distributed.nanny.pre-spawn-environ", {}).items()
               if name not in LOCAL_WORKER_UNSET_ENVIRON}
    with dask.config.set({"distributed.worker.multiprocessing-method": "forkserver",
                          "distributed.nanny.pre-spawn-environ": environ,
                          **LOCAL_WORKER_CONFIG}):
        get_mp_context().set_forkserver_preload(["distributed", dask_forkserver.__name__])
        yield


def run_tasks(client, function: Callable, items: list, names: list[str],
              progress: bool = True, sizes: list[float] | None = None
              ) -> list[tuple[object, BaseException | None]]:
    """``function(item)`` for every item as dask tasks (one each, ``names`` in their keys);
    returns (result, None) or (None, exception) per item, in the items' order. With ``sizes``
    (a log's bytes: its work) the largest are submitted first (dask runs tasks in submission
    order), so the last tasks of the run are short ones and no worker idles long while another
    finishes a long log (longest processing time first). Shows dask's progress bar on stderr
    when it is a terminal."""
    if not items:
        return []
    stamp = time.time_ns()
    keys = [f"slipd-{_slug(name)}-{stamp}-{k}" for k, name in enumerate(names)]
    order = list(range(len(items)))
    if sizes is not None:
        order.sort(key=lambda k: -sizes[k])  # stable: equal sizes keep the items' order
    futures: list = [None] * len(items)
    for k in order:
        futures[k] = client.submit(function, items[k], key=keys[k], pure=False)
    if progress and sys.stderr.isatty():
        from distributed import progress as progress_bar

        with contextlib.redirect_stdout(sys.stderr):
            progress_bar(futures)
            print(file=sys.stderr)
    results = []
    for future in futures:
        try:
            results.append((future.result(), None))
        except Exception as exc:  # noqa: BLE001 - a worker's failure is the log's error
            results.append((None, exc))
    return results


def file_sizes(paths: Iterable[str | Path]) -> list[float]:
    """Each file's size in bytes (0 for one that cannot be read: its task reports why)."""
    sizes = []
    for path in paths:
        try:
            sizes.append(float(os.stat(path).st_size))
        except OSError:
            sizes.append(0.0)
    return sizes


def _slug(text: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in text)[:40]


# ---------------------------------------------------------------------------------------------
# one log
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LogJob:
    """What a task needs to replay one log into its partition."""

    log: str
    key: str
    out_dir: str | None
    profile: str
    profile_sha256: str
    methods: tuple[str, ...]
    skip_bad: bool = False
    bus_map: tuple[tuple[str, str], ...] = ()
    chunk_bytes: int | None = None

    @property
    def options(self) -> str:
        return json.dumps({"skip_bad": self.skip_bad, "bus": dict(self.bus_map)},
                          sort_keys=True)


@dataclass
class LogRecord:
    """A log's row of the summary (and its partition's metadata)."""

    log: str
    key: str
    size_bytes: int = -1
    mtime_ns: int = -1
    sha256: str = ""
    profile: str = ""
    profile_name: str = ""
    profile_sha256: str = ""
    methods: str = ""
    options: str = ""
    frames: int = 0
    ticks: int = 0
    bad_lines: int = 0
    rejected_frames: int = 0
    valid_share: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0
    #: CPU seconds this process used while the log ran (its replay threads and, on a Dask
    #: worker, the worker's own threads: its event loop, heartbeats), beside the wall seconds
    cpu_seconds: float = 0.0
    worker: str = ""
    #: the threads the replay ran its stages on (slipd.replay.ahead.replay_threads)
    threads: int = 0
    #: the worker process's peak RSS so far (MB) when the log was done
    peak_rss_mb: float = 0.0
    status: str = "ok"  # ok | skipped (--resume: done before) | failed
    error: str = ""
    partition: str = ""

    def as_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)


RECORD_FIELDS = tuple(LogRecord.__dataclass_fields__)


def profile_sha256(profile) -> str:
    """SHA-256 (16 hex digits) of a profile's TOML and its DBC."""
    digest = hashlib.sha256()
    for path in (profile.path, profile.dbc_path):
        digest.update(Path(path).read_bytes())
    return digest.hexdigest()[:16]


def replay_log(job: LogJob) -> LogRecord:
    """Stream one log through the methods into its partition (when the job has an out_dir);
    never raises for the log's own faults: they are the record's error."""
    started = time.perf_counter()
    cpu_started = time.process_time()
    path = Path(job.log)
    record = LogRecord(job.log, job.key, profile=job.profile, methods=",".join(job.methods),
                       options=job.options, worker=f"{socket.gethostname()}:{os.getpid()}")
    try:
        record.threads = replay_threads()
        stat = path.stat()
        record.size_bytes, record.mtime_ns = stat.st_size, stat.st_mtime_ns
        _replay_into(job, record, started, cpu_started)
    except SlipdError as exc:
        record.status, record.error = "failed", str(exc)
    except FileNotFoundError as exc:
        record.status, record.error = "failed", f"{path}: no such file ({exc.strerror})"
    except Exception as exc:  # noqa: BLE001 - the batch goes on; the row says what happened
        record.status, record.error = "failed", f"{type(exc).__name__}: {exc}"
    _timed(record, started, cpu_started)
    return record


def _timed(record: LogRecord, started: float, cpu_started: float) -> None:
    record.seconds = round(time.perf_counter() - started, 3)
    record.cpu_seconds = round(time.process_time() - cpu_started, 3)
    record.peak_rss_mb = _peak_rss_mb()


def _peak_rss_mb() -> float:
    import resource

    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)


def _replay_into(job: LogJob, record: LogRecord, started: float, cpu_started: float) -> None:
    import numpy as np

    from slipd.channels import Out, Status
    from slipd.profile import load_profile
    from slipd.replay.stream import CHUNK_BYTES, LogStream
    from slipd.replay.writers import ParquetWriter, RunInfo

    profile, record.profile_sha256, pipelines = _loaded(job.profile, load_profile)
    record.profile_name = profile.name
    if job.profile_sha256 and record.profile_sha256 != job.profile_sha256:
        raise ConfigError(f"profile {job.profile} on {socket.gethostname()} differs from the "
                          f"one the run was started with (SHA-256 {record.profile_sha256} != "
                          f"{job.profile_sha256})")
    methods = list(job.methods)
    stream = LogStream(job.log, profile, methods, job.skip_bad, dict(job.bus_map) or None,
                       job.chunk_bytes or CHUNK_BYTES, checksum=True, pipelines=pipelines)
    pipelines.update(stream.runs.pipelines)
    writer = None
    target = None
    if job.out_dir is not None:
        target = partition_path(Path(job.out_dir), job.key)
        target.parent.mkdir(parents=True, exist_ok=True)
        writer = ParquetWriter(target, RunInfo(methods, profile.name, job.log))
    valid = dict.fromkeys(methods, 0)
    try:
        for chunk in stream:
            for name in methods:
                out = chunk.outputs[name]
                if writer is not None:
                    writer.write(name, chunk.inputs.t, out)
                status = out[:, Out.STATUS].astype(np.int64)
                valid[name] += int(np.count_nonzero(status & int(Status.VALID)))
        read = stream.read
        record.sha256 = read.sha256
        record.frames, record.ticks = read.frames, stream.ticks
        record.bad_lines = read.bad_lines
        record.rejected_frames = sum(v for counts in stream.errors.values()
                                     for k, v in counts.items() if k != "accepted")
        record.valid_share = {m: round(v / stream.ticks, 6) if stream.ticks else 0.0
                              for m, v in valid.items()}
        if writer is not None:
            record.partition = str(target)
            _timed(record, started, cpu_started)
            writer.add_metadata({RECORD_KEY: record.as_json()})
            writer.close()
    except BaseException:
        if writer is not None:
            writer.abort()
            with contextlib.suppress(OSError):
                target.parent.rmdir()  # the log's partition folder, when it holds nothing
        raise


#: this process's profiles and their methods' Pipelines: profile as given -> (the TOML's and
#: DBC's SHA-256 when loaded, Profile, {method: Pipeline}); a worker's later logs reuse them
#: (~85 ms of a short log with every method) while the files stay the same
_LOADED: dict[str, tuple[str, object, dict]] = {}


def _loaded(profile: str, load_profile: Callable) -> tuple[object, str, dict]:
    """(Profile, its SHA-256, its Pipelines so far) of ``profile``: loaded again when its
    files changed."""
    cached = _LOADED.get(profile)
    if cached is not None:
        fingerprint = profile_sha256(cached[1])
        if fingerprint == cached[0]:
            return cached[1], fingerprint, cached[2]
    loaded = load_profile(profile)
    _LOADED[profile] = (profile_sha256(loaded), loaded, {})
    return loaded, _LOADED[profile][0], _LOADED[profile][2]


def partition_path(out_dir: Path, key: str) -> Path:
    return out_dir / ESTIMATES / f"log={urllib.parse.quote(key, safe='')}" / PART


def log_keys(logs: list[Path]) -> list[str]:
    """Each log's partition key: its path relative to the logs' common folder, without the
    log suffixes (``carA/day1`` for ``/data/carA/day1.log.gz``)."""
    resolved = [p.resolve() for p in logs]
    root = Path(os.path.commonpath([str(p.parent) for p in resolved])) if resolved else Path()
    keys = []
    for path in resolved:
        relative = path.relative_to(root).as_posix()
        name = relative
        for suffix in (".gz", *LOG_SUFFIXES):
            name = name.removesuffix(suffix) if name.endswith(suffix) else name
        keys.append(name or relative)
    duplicates = {k for k in keys if keys.count(k) > 1}
    if duplicates:
        keys = [Path(p).relative_to(root).as_posix() for p in resolved]
    return keys


def expand_logs(patterns: Iterable[str | Path]) -> list[Path]:
    """Log paths from the command line: a path, or a glob pattern (``'logs/**/*.log'``,
    quoted so the shell leaves it to slipd) expanded in sorted order; a pattern that matches
    nothing is an error naming it."""
    import glob

    found: list[Path] = []
    for pattern in patterns:
        text = str(pattern)
        if any(c in text for c in "*?[") and not Path(text).exists():
            matches = sorted(glob.glob(text, recursive=True))
            if not matches:
                raise ConfigError(f"{text}: no log matches this pattern")
            found += [Path(m) for m in matches]
        else:
            found.append(Path(text))
    unique = list(dict.fromkeys(found))
    return unique


# ---------------------------------------------------------------------------------------------
# the run
# ---------------------------------------------------------------------------------------------


def done_before(job: LogJob) -> LogRecord | None:
    """The record of ``job``'s partition when it holds this very run of this log (--resume)."""
    if job.out_dir is None:
        return None
    target = partition_path(Path(job.out_dir), job.key)
    if not target.exists():
        return None
    try:
        import pyarrow.parquet as pq

        meta = pq.read_metadata(target).metadata or {}
        record = LogRecord(**json.loads(meta[RECORD_KEY.encode()]))
        stat = Path(job.log).stat()
    except (OSError, KeyError, ValueError, TypeError):
        return None
    now = {"log": job.log, "size_bytes": stat.st_size, "mtime_ns": stat.st_mtime_ns,
           "profile": job.profile, "profile_sha256": job.profile_sha256,
           "methods": ",".join(job.methods), "options": job.options}
    if any(getattr(record, name) != now[name] for name in SAME_RUN):
        return None
    record.status = "skipped"
    return record


def run_fleet(logs: list[Path], profile: str, methods: list[str], out_dir: Path | None,
              client=None, skip_bad: bool = False, bus_map: dict[str, str] | None = None,
              chunk_bytes: int | None = None, resume: bool = False,
              progress: bool = True) -> list[LogRecord]:
    """Replay ``logs`` (one task each on ``client``'s cluster; None: here, one after the
    other) into ``out_dir``'s dataset and summary; returns the records in the logs' order."""
    from slipd.profile import load_profile

    loaded = load_profile(profile)
    fingerprint = profile_sha256(loaded)
    keys = log_keys(logs)
    jobs = [LogJob(str(Path(log).resolve()), key, str(out_dir) if out_dir else None, profile,
                   fingerprint, tuple(methods), skip_bad, tuple(sorted((bus_map or {}).items())),
                   chunk_bytes) for log, key in zip(logs, keys, strict=True)]
    records: list[LogRecord | None] = [done_before(job) if resume else None for job in jobs]
    todo = [k for k, r in enumerate(records) if r is None]
    if client is None:
        for k in todo:
            records[k] = replay_log(jobs[k])
    else:
        results = run_tasks(client, replay_log, [jobs[k] for k in todo],
                            [jobs[k].key for k in todo], progress,
                            file_sizes(jobs[k].log for k in todo))
        for k, (result, error) in zip(todo, results, strict=True):
            records[k] = result if error is None else LogRecord(
                jobs[k].log, jobs[k].key, profile=profile, methods=",".join(methods),
                status="failed", error=f"{type(error).__name__}: {error}")
    done = [r for r in records if r is not None]
    if out_dir is not None:
        write_summary(out_dir / SUMMARY, done)
    return done


def write_summary(path: Path, records: list[LogRecord]) -> None:
    """The summary table: a row per log (valid shares as one column per method)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from slipd.replay.writers import partial_path

    methods = list(dict.fromkeys(m for r in records for m in r.valid_share))
    columns: dict[str, list] = {name: [] for name in RECORD_FIELDS if name != "valid_share"}
    for m in methods:
        columns[f"valid_share_{m}"] = []
    for record in records:
        row = asdict(record)
        shares = row.pop("valid_share")
        for name, value in row.items():
            columns[name].append(value)
        for m in methods:
            columns[f"valid_share_{m}"].append(shares.get(m))
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = partial_path(path)
    pq.write_table(pa.table(columns), str(partial), compression="zstd")
    os.replace(partial, path)


def summary_lines(records: list[LogRecord]) -> list[str]:
    """One line per log for the terminal."""
    lines = []
    for r in records:
        if r.status == "failed":
            lines.append(f"{r.log}: error: {r.error}")
            continue
        shares = ", ".join(f"{m} {100 * r.valid_share[m]:.1f} %"
                           for m in r.methods.split(",") if m in r.valid_share)
        done = "done before (--resume)" if r.status == "skipped" else f"{r.seconds:.2f} s"
        lines.append(f"{r.log}: {r.frames} frames, {r.ticks} ticks, {done}; valid: {shares}")
    return lines
