"""What the daemon needs from its host: systemd notification, real-time settings, state files.

No threads: everything here is called from the loop's thread at start, at 1 Hz or at exit.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import gc
import json
import math
import os
import re
import signal
import socket
import stat
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slipd.errors import ConfigError

PR_SET_TIMERSLACK = 29
MCL_CURRENT, MCL_FUTURE, MCL_ONFAULT = 1, 2, 4
MADV_DONTNEED = 4
#: shared objects only needed to compile or load kernels, not to run them
COMPILER_LIBRARIES = ("libllvmlite.so",)


LOOP_CPU_ENV = "SLIPD_LOOP_CPU"  # the loop's pinned CPU, for helper processes to avoid


class HelperProcess:
    """A child started by :func:`spawn_helper` (a ``subprocess.Popen``-like handle)."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
            if pid:
                self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            if deadline is not None and time.monotonic() >= deadline:
                raise TimeoutError(f"process {self.pid} still running after {timeout} s")
            time.sleep(0.01)
        return self.returncode

    def kill(self) -> None:
        if self.poll() is None:
            os.kill(self.pid, signal.SIGKILL)


def spawn_helper(argv: list[str], pass_fds: tuple[int, ...] = ()) -> HelperProcess:
    """Start a helper process (stats server, recorder compressor) from the loop's process.

    ``posix_spawn`` (vfork and exec: no copy of the daemon's page tables, which a fork of a
    90 MB process with locked memory would make inside the loop's slack) with normal
    scheduling: a child of a SCHED_FIFO loop would otherwise start at the loop's priority,
    on its CPU, and run its whole Python start-up before the loop could run again. The child
    lowers its policy further and leaves the loop's CPU itself (:func:`step_aside`).
    """
    for fd in pass_fds:
        os.set_inheritable(fd, True)
    try:
        pid = os.posix_spawn(argv[0], argv, os.environ,
                             scheduler=(os.SCHED_OTHER, os.sched_param(0)))
    finally:
        for fd in pass_fds:
            os.set_inheritable(fd, False)
    return HelperProcess(pid)


def step_aside(policy: int = os.SCHED_BATCH) -> None:
    """In a helper process: a scheduling policy below the loop's, and off the loop's CPU when
    the loop is pinned (``$SLIPD_LOOP_CPU``, set by :func:`apply_realtime`). SCHED_BATCH never
    preempts a task on waking (the stats server); SCHED_IDLE runs only on an otherwise idle
    CPU (the recorder's compressor). Not nice(2): the unit's system-call filter forbids
    setpriority, and a forbidden call kills the process."""
    try:
        os.sched_setscheduler(0, policy, os.sched_param(0))
    except OSError:
        pass
    loop_cpu = os.environ.get(LOOP_CPU_ENV, "")
    if loop_cpu.isdigit():
        others = set(range(os.cpu_count() or 1)) - {int(loop_cpu)}
        try:
            if others:
                os.sched_setaffinity(0, others & os.sched_getaffinity(0) or others)
        except OSError:
            pass


class SystemdNotifier:
    """sd_notify(3) over $NOTIFY_SOCKET; silent no-op when not started by systemd."""

    def __init__(self) -> None:
        address = os.environ.get("NOTIFY_SOCKET")
        self.socket = None
        self.address = None
        if address:
            if address.startswith("@"):
                address = "\0" + address[1:]
            self.address = address
            self.socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        usec = os.environ.get("WATCHDOG_USEC")
        self.watchdog_interval = int(usec) / 2e6 if usec and usec.isdigit() else None

    @property
    def enabled(self) -> bool:
        return self.socket is not None

    def extend_timeout(self, seconds: float) -> None:
        """EXTEND_TIMEOUT_USEC: the start-up (or stop) may take ``seconds`` more from now,
        so a numba warm-up on a cold cache does not run into TimeoutStartSec."""
        self.notify(f"EXTEND_TIMEOUT_USEC={int(seconds * 1e6)}")

    def notify(self, text: str) -> None:
        if self.socket is None:
            return
        try:
            self.socket.sendto(text.encode(), self.address)
        except OSError as exc:
            print(f"slipd: sd_notify failed: {exc}", file=sys.stderr)


@dataclass
class RealtimeOptions:
    sched_fifo: int = 0  # priority, 0 = off
    cpu: int | None = None
    mlockall: bool = False
    timer_slack_ns: int | None = None
    gc_freeze: bool = False
    # us before each tick from which the loop polls the socket without sleeping, after a dry
    # run of the tick on scratch arrays (0 = sleep until the tick). See Daemon._receive_until.
    spin_us: int = 0


def apply_realtime(options: RealtimeOptions) -> list[str]:
    """Apply each requested setting; returns report lines; a refused one raises ConfigError."""
    report = []
    libc = ctypes.CDLL("libc.so.6", use_errno=True)
    if options.timer_slack_ns is not None:
        if libc.prctl(PR_SET_TIMERSLACK, ctypes.c_ulong(options.timer_slack_ns), 0, 0, 0) != 0:
            raise ConfigError(f"timer slack {options.timer_slack_ns} ns refused: "
                              f"{os.strerror(ctypes.get_errno())}")
        report.append(f"timer slack {options.timer_slack_ns} ns")
    if options.cpu is not None:
        try:
            os.sched_setaffinity(0, {options.cpu})
        except OSError as exc:
            raise ConfigError(f"CPU affinity {{{options.cpu}}} refused: {exc}") from exc
        os.environ[LOOP_CPU_ENV] = str(options.cpu)  # helper processes keep off it
        report.append(f"pinned to CPU {options.cpu}")
    if options.mlockall:
        # MCL_ONFAULT locks pages as they are touched instead of faulting in every mapped
        # page at once: measured, plain MCL_CURRENT took the daemon from 168 MB to 462 MB
        # resident (all of LLVM and BLAS). The warm-up runs every kernel before the loop, so
        # the loop's pages are resident and locked when it starts.
        if libc.mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT) == 0:
            report.append("memory locked as touched (mlockall MCL_ONFAULT)")
        elif ctypes.get_errno() == errno.EINVAL and libc.mlockall(MCL_CURRENT | MCL_FUTURE) == 0:
            report.append("memory locked (mlockall; kernel without MCL_ONFAULT)")
        else:
            raise ConfigError(f"mlockall refused: {os.strerror(ctypes.get_errno())} "
                              "(needs CAP_IPC_LOCK or LimitMEMLOCK=infinity)")
    if options.sched_fifo:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(options.sched_fifo))
        except OSError as exc:
            raise ConfigError(f"SCHED_FIFO priority {options.sched_fifo} refused: {exc} "
                              "(needs CAP_SYS_NICE or an RLIMIT_RTPRIO)") from exc
        report.append(f"SCHED_FIFO priority {options.sched_fifo}")
    if options.gc_freeze:
        gc.collect()
        gc.freeze()
        gc.disable()
        report.append("gc frozen and disabled (no collector pauses in the loop)")
    if options.spin_us:
        if not 0 < options.spin_us < 5000:
            raise ConfigError(f"spin window {options.spin_us} us: expected 1..4999 us "
                              "(a tick is 10,000 us)")
        report.append(f"tick warmed and polled for the last {options.spin_us} us before it "
                      f"(one core busy {options.spin_us / 100:.0f} % of the time)")
    return report or ["no real-time settings (best effort scheduling)"]


def release_compiler_pages(libraries: tuple[str, ...] = COMPILER_LIBRARIES) -> int:
    """Drop LLVM's code pages from the resident set once every kernel is loaded; returns
    the bytes released.

    numba needs LLVM to compile a kernel or load it from the cache, never to run it: the
    compiled code lives in anonymous memory of its own and calls numba's helpers, not LLVM.
    Loading the cache touches ~68 MB of libllvmlite's code and read-only data, which would
    otherwise stay resident (and locked, under mlockall) for the life of the daemon.
    Only file-backed mappings that are not writable and hold no private (copied-on-write)
    page are released, so every dropped page is an unmodified page of the file: the page
    cache keeps it, and it faults back in should anything compile later. Locked mappings
    are unlocked first (madvise refuses locked pages); those pages are not locked again.
    """
    try:
        smaps = Path("/proc/self/smaps").read_text()
    except OSError:
        return 0
    libc = ctypes.CDLL("libc.so.6", use_errno=True)
    libc.munlock.argtypes = [ctypes.c_void_p, ctypes.c_size_t]
    libc.madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    released = 0
    for start, end, perms, path, fields in _smaps_entries(smaps):
        if "w" in perms or not path.endswith(libraries) or fields.get("Anonymous", 1) != 0:
            continue
        length = end - start
        if fields.get("Locked", 0):
            libc.munlock(start, length)
        if libc.madvise(start, length, MADV_DONTNEED) == 0:
            released += fields.get("Rss", 0) * 1024
    return released


def _smaps_entries(smaps: str):
    """(start, end, perms, path, {field: kB}) per mapping of a /proc/PID/smaps text."""
    entry = None
    for line in smaps.splitlines():
        head, _, rest = line.partition(" ")
        if "-" in head and not head.endswith(":"):
            if entry is not None:
                yield entry
            parts = line.split(None, 5)
            low, high = head.split("-")
            entry = (int(low, 16), int(high, 16), parts[1],
                     parts[5].strip() if len(parts) > 5 else "", {})
        elif entry is not None and rest.endswith("kB"):
            entry[4][head.rstrip(":")] = int(rest.split()[0])
    if entry is not None:
        yield entry


STATE_FILE_LIMIT = 1 << 20  # bytes: a state file is ~1 kB; anything this big is not one
TEMPORARY_MARK = ".tmp-"  # .<name>.tmp-XXXX beside the state file while it is written
LEGACY_TEMPORARY = ".slipd-state-"  # the temporaries' prefix before, for any one state file
ABANDONED_AFTER_S = 60.0  # a legacy temporary this old was left by a killed writer


class StateFileError(ValueError):
    """A state file that cannot be used (the reason names the file)."""


def read_state_document(path: Path) -> dict | None:
    """The JSON object in a state file, None when there is none; StateFileError when it
    cannot be one: not a regular file (a directory; a FIFO, which would block start-up),
    larger than STATE_FILE_LIMIT, not UTF-8, not JSON, nested too deeply, not an object.
    Integers are read as floats, so a 400-digit one is inf (rejected by the caller as
    non-finite), not an OverflowError."""
    try:
        info = os.stat(path)
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise StateFileError(f"cannot stat it: {exc.strerror}") from exc
    if not stat.S_ISREG(info.st_mode):
        kind = "a directory" if stat.S_ISDIR(info.st_mode) else \
            "a FIFO" if stat.S_ISFIFO(info.st_mode) else "not a regular file"
        raise StateFileError(f"it is {kind}")
    try:  # O_NONBLOCK: a FIFO put there after the stat cannot block start-up either
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        raise StateFileError(f"cannot open it: {exc.strerror}") from exc
    with os.fdopen(fd, "rb") as handle:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise StateFileError("it is not a regular file")
        raw = handle.read(STATE_FILE_LIMIT + 1)
    if len(raw) > STATE_FILE_LIMIT:
        raise StateFileError(f"it is larger than {STATE_FILE_LIMIT} bytes")
    try:
        document = json.loads(raw.decode("utf-8"), parse_int=float)
    except UnicodeDecodeError as exc:
        raise StateFileError(f"not UTF-8 ({exc.reason} at byte {exc.start})") from exc
    except RecursionError as exc:
        raise StateFileError("nested too deeply") from exc
    except ValueError as exc:
        raise StateFileError(f"not JSON ({exc})") from exc
    if not isinstance(document, dict):
        raise StateFileError(f"expected a JSON object, found {type(document).__name__}")
    return document


def write_state_document(path: Path, document: dict) -> None:
    """Write atomically: a temporary beside ``path``, fsync, rename, fsync of the directory.
    A failure (ENOSPC) removes the temporary and raises the OSError."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}{TEMPORARY_MARK}")
    try:
        with os.fdopen(fd, "w") as handle:
            json.dump(document, handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(temporary)
        raise
    with contextlib.suppress(OSError):
        directory = os.open(path.parent, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(directory)
        finally:
            os.close(directory)


def remove_stale_temporaries(path: Path) -> int:
    """Remove what killed writers (SIGKILL, a full disk) left beside ``path``: its own
    temporaries, and legacy ones older than ABANDONED_AFTER_S. Returns how many."""
    removed = 0
    now = time.time()
    try:
        entries = list(os.scandir(path.parent))
    except OSError:
        return 0
    for entry in entries:
        ours = entry.name.startswith(f".{path.name}{TEMPORARY_MARK}")
        legacy = entry.name.startswith(LEGACY_TEMPORARY)
        try:
            if not (ours or legacy) or not entry.is_file(follow_symlinks=False):
                continue
            if legacy and now - entry.stat(follow_symlinks=False).st_mtime < ABANDONED_AFTER_S:
                continue
            os.unlink(entry.path)
            removed += 1
        except OSError:
            continue
    return removed


#: Physically plausible bounds of the learnt values the daemon restores, by element name (an
#: ensemble member's prefix, ``KINEMATIC_HEURISTIC.``, aside): a value beyond its bound, or not
#: finite, is not one a sensor could have taught (a corrupt file, one edited by hand, or one of
#: another car), and its slot starts fresh. Every persistent element needs a bound here
#: (tests/test_state_file.py checks the registry's methods).
#: rad/s: gyro offsets and biases. Automotive MEMS gyros' zero-rate offsets are specified
#: within a few deg/s over temperature; 10 deg/s is past any of them.
GYRO_OFFSET_LIMIT = math.radians(10.0)
#: m/s^2: accelerometer offsets. A few 0.01 m/s^2 of sensor offset plus mounting tilt and a
#: permanent road bank (which the Ay offset absorbs, Selmanaj eq. 21): 2 m/s^2 is ~12 deg.
ACCEL_OFFSET_LIMIT = 2.0
#: uT: magnetometer calibration terms (Yoon's C, field components with soft and hard iron):
#: past a MEMS magnetometer's full scale (+-1300 uT), which no learnt term can exceed.
MAG_FIELD_LIMIT = 1300.0
#: the consistency monitor's innovation levels: a forgotten sum of ln NIS and of its weights
#: (level = exp(sum / weight), weight < 1). A level of 1e6 per measurement (innovations 1000
#: sigma) is one no filter that tracks keeps; a weight beyond 1 no sum of forgotten weights
#: reaches. A sum restored without its weight (or the reverse) leaves the level at the prior
#: or nearer to it: stricter, never more lenient.
LOG_NIS_LEVEL_LIMIT = math.log(1e6)
PLAUSIBLE_STATE = (
    # (element name, bound, unit, what it is)
    (re.compile(r"OFFSETS\.(YAW|ROLL|PITCH)_RATE|YAW_RATE_BIAS"), GYRO_OFFSET_LIMIT, "rad/s",
     "a gyro offset"),
    (re.compile(r"OFFSETS\.A[XY]"), ACCEL_OFFSET_LIMIT, "m/s^2", "an accelerometer offset"),
    (re.compile(r"CAL_C\[[0-8]\]"), MAG_FIELD_LIMIT, "uT", "a magnetometer calibration term"),
    (re.compile(r"CAL_P\[[0-8]\]"), MAG_FIELD_LIMIT ** 2, "uT^2",
     "a calibration covariance term"),
    (re.compile(r"CONSISTENCY\.(WITNESS_)?LOG_NIS_SUM"), LOG_NIS_LEVEL_LIMIT, "ln(NIS)",
     "an innovation level's sum of ln NIS"),
    (re.compile(r"CONSISTENCY\.(WITNESS_)?LOG_NIS_WEIGHT"), 1.0, "(weight)",
     "an innovation level's weight"),
)
#: 3 x 3 covariance blocks (row-major): restored whole, symmetric and positive semidefinite,
#: or not at all (a half-restored or indefinite covariance breaks the least squares).
COVARIANCE_BLOCK = re.compile(r"(?P<block>(.*\.)?CAL_P)\[(?P<index>[0-8])\]$")


def plausible_bound(name: str) -> tuple[float, str, str] | None:
    """(bound, unit, what) of persistent element ``name``; None when none is known."""
    suffixes = [name.split(".", k)[-1] for k in range(name.count(".") + 1)]  # a.b.c, b.c, c
    for pattern, bound, unit, what in PLAUSIBLE_STATE:
        if any(pattern.fullmatch(suffix) for suffix in suffixes):
            return bound, unit, what
    return None


def plausible_state(values: dict[str, float]) -> tuple[dict[str, float], list[str]]:
    """The restored values that are finite and within their PLAUSIBLE_STATE bound (a plug-in
    method's element without one: finite), and a reason for each one rejected (its slot then
    starts fresh)."""
    accepted: dict[str, float] = {}
    rejected: list[str] = []
    for name, value in values.items():
        known = plausible_bound(name)
        if not math.isfinite(value):
            rejected.append(f"{name} = {value!r} is not a finite number")
        elif known is not None and abs(value) > known[0]:
            bound, unit, what = known
            rejected.append(f"{name} = {value:.6g} {unit} is beyond +-{bound:.6g} {unit}, "
                            f"implausible for {what}")
        else:
            accepted[name] = value
    blocks: dict[str, dict[int, str]] = {}
    for name in list(accepted):
        match = COVARIANCE_BLOCK.match(name)
        if match:
            blocks.setdefault(match["block"], {})[int(match["index"])] = name
    for block, names in blocks.items():
        reason = _covariance_problem([accepted.get(names.get(i, ""), math.nan)
                                      for i in range(9)])
        if reason:
            for name in names.values():
                del accepted[name]
            rejected.append(f"{block} is {reason}")
    return accepted, rejected


def _covariance_problem(entries: list[float]) -> str | None:
    if not all(math.isfinite(v) for v in entries):
        return "not complete"
    matrix = np.array(entries).reshape(3, 3)
    scale = max(float(np.abs(matrix).max()), 1e-300)
    if np.abs(matrix - matrix.T).max() > 1e-6 * scale:
        return "not symmetric"
    if np.linalg.eigvalsh(0.5 * (matrix + matrix.T)).min() < -1e-9 * scale:
        return "not positive semidefinite"
    return None


class StateStore:
    """Persisted estimator state (learnt offsets, calibrations) as JSON, written atomically.

    The file names the method, its state layout's hash and each value's state element by name
    (``{"method": ..., "layout": ..., "state": {"OFFSETS.YAW_RATE": ...}}``), so that a value is
    never restored into a slot that means something else: a file of another method or another
    layout is reported and ignored, never fatal.
    """

    def __init__(self, path: Path | None):
        self.path = path

    def load(self, method: str, layout: str) -> tuple[dict[str, float], str]:
        """Saved {element name: value} for ``method`` under state layout hash ``layout``."""
        if self.path is None:
            return {}, "state persistence off"
        cleaned = remove_stale_temporaries(self.path)
        note = f" ({cleaned} temporary file(s) of killed writers removed)" if cleaned else ""
        try:
            document = read_state_document(self.path)
            if document is None:
                return {}, f"no saved state at {self.path}{note}"
            if document.get("method") != method:
                return {}, (f"saved state in {self.path} is for {document.get('method')!r}, "
                            f"not {method!r}: ignored{note}")
            if document.get("layout") != layout:
                return {}, (f"saved state in {self.path} has state layout "
                            f"{document.get('layout')!r}, this slipd's {method} has {layout!r} "
                            f"(saved by another version): ignored{note}")
            # floats, finite or not: plausible_state judges each one (one bad value costs
            # its own slot, not the others)
            values = {str(k): float(v) for k, v in document["state"].items()}
            return values, f"restored {len(values)} state values from {self.path}{note}"
        except (ValueError, KeyError, TypeError, AttributeError, OverflowError) as exc:
            return {}, f"state file {self.path} is corrupt ({exc}): ignored{note}"

    def save(self, method: str, layout: str, values: dict[str, float]) -> None:
        if self.path is None or not values:
            return
        document = {"method": method, "layout": layout,
                    "state": {name: value for name, value in values.items()
                              if math.isfinite(value)}}
        write_state_document(self.path, document)
