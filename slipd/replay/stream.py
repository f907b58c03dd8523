"""Streaming replay: a log read, decoded, latched and estimated chunk by chunk.

The batch engine (:mod:`slipd.replay.engine`) holds a whole log in memory; this module runs the
same kernels on pieces of it, in four stages a chunk passes through in turn::

    frame_chunks (read)  ->  Latcher (decode, latch, tick)  ->  MethodRuns (estimate)  ->  sinks

and carries across every chunk boundary what the whole-log run carries from one frame or tick
to the next, so each chunk's rows are the whole-log run's rows for its ticks, bit for bit
(tests/test_stream.py):

* the codec's decode state (latch, per-message counters and times, error counts): one
  :class:`~slipd.codec.Codec` per log;
* the tick grid of :func:`~slipd.replay.engine.tick_grid`: tick ``k`` at ``t0 + dt + k dt``
  (``t0`` the log's first frame). A chunk latches the ticks whose frames have all been read
  (tick time strictly before the newest frame read, as a later frame may share the newest
  time); the frames after the last latched tick wait for the next chunk. At the end, the
  grid's own count decides the last ticks;
* a flight recorder's ticks (its SLIPD_STATE lines, as :func:`~slipd.replay.engine.
  recorded_ticks`): the input lines below a chunk's last tick wait for the next one, and the
  previous tick time gives the first tick's catch-up steps (``pipeline.steps_per_tick``);
* every method's state array (``Pipeline.run`` on the chunk with the carried state);
* the log channel -> profile bus choice (:func:`~slipd.replay.engine.channel_buses`), made on
  the channels seen so far and checked not to change as more appear (a log whose channel
  picture changes after its first chunk is an error that asks for ``--bus``, not a silently
  different replay).

Memory is bounded by the chunk (``chunk_bytes`` of log text, CHUNK_BYTES by default), never
by the log. Two whole-log decisions are made on the first chunk instead: whether the log is a
flight recording (its ticks start in the first second), and, as above, the bus choice; each
is checked on every later chunk and a contradiction is a clear error.
"""

from __future__ import annotations

import gzip
import hashlib
import itertools
import os
import threading
import zlib
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slipd.channels import N_OUT, U_LEN
from slipd.codec import Codec, kernels
from slipd.errors import ConfigError, LogFormatError
from slipd.pipeline import TICK_DT, Pipeline, RawRuns, steps_per_tick
from slipd.profile import Profile, load_profile
from slipd.replay.ahead import ahead, ahead_map, replay_threads
from slipd.replay.candump import (
    FLAG_TX,
    MAX_CHANNELS,
    Frames,
    count_newlines,
    parse_candump,
)
from slipd.replay.engine import (
    Inputs,
    _channels_carrying,
    _reads_carrying,
    channel_buses,
    recorded_ticks,
)

#: Log text per chunk: ~45,000 frames of a candump log, ~1 minute of the default profile's
#: bus. Measured on the endurance drive with every method and --out x.parquet (benchmarks/
#: fleet.py): a 16 MB chunk peaked at ~640 MB RSS, 4 MB at ~440 MB (of which ~290 MB are the
#: loaded kernels), at the same speed. 2 MB: a 10-minute log's stages overlap on more chunks
#: (its replay 5-10 % faster on 2 cores than with 4 MB, the 1 h log's as fast or faster:
#: benchmarks/replay.py); 1 MB chunks were slower again.
CHUNK_BYTES = 2 << 20
#: Threads parsing a candump log's blocks at once (line blocks are independent; the parse
#: kernel releases the GIL): two, measured on 2 cores, and never more than the replay's
#: threads (slipd.replay.ahead.replay_threads).
PARSE_WORKERS = 2
#: Bytes of a candump line, for sizing chunks of the formats read message by message.
_LINE_BYTES = 36


#: glibc's allocator, once slipd's replay commands call keep_freed_memory(): freed memory is
#: returned to the system only above this much at the heap's top, and arrays up to
#: MMAP_THRESHOLD_BYTES (its maximum) come from the heap instead of mappings of their own.
TRIM_THRESHOLD_BYTES = 128 << 20
MMAP_THRESHOLD_BYTES = 32 << 20
_KEPT = False


def keep_freed_memory() -> bool:
    """Let this process reuse the memory a streamed chunk frees for the next chunk (glibc's
    ``mallopt``; elsewhere nothing: returns False). A chunk's arrays (frames, inputs,
    outputs, tables: a few MB) are freed when it is written; by default glibc hands such
    blocks back to the kernel and the next chunk's first touch of fresh pages faults and
    clears them again. Measured (benchmarks/replay.py's 10-minute replay, best of 5, four
    runs each): 47-50 ms by default, 41-44 ms with both settings; the trim threshold alone
    was slower (58-63 ms: it also fixes the mmap threshold at 128 KB), the mmap threshold
    alone no faster. The cost: up to TRIM_THRESHOLD_BYTES freed memory stays in the process
    (a replay's peak is the peak either way). Called by the replay and eval commands and in
    the workers of a ``--dask local`` cluster (slipd.replay.dask_forkserver), not by the
    library nor in the workers of a user's cluster: a process-wide setting is its program's
    to make."""
    global _KEPT
    if _KEPT:
        return True
    import ctypes
    import ctypes.util
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3  # malloc.h
    _KEPT = bool(mallopt(m_mmap_threshold, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(m_trim_threshold, TRIM_THRESHOLD_BYTES))
    return _KEPT


# ---------------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------------


def line_blocks(path: Path, chunk_bytes: int = CHUNK_BYTES, digest=None, buffers: int = 1
                ) -> Iterator[tuple[np.ndarray, int, int]]:
    """Whole lines of a text file (``.gz`` decompressed) in blocks of about ``chunk_bytes``:
    (uint8 view of the block, line number of its first line, newlines in it). A ring of
    ``buffers`` buffers is reused: a block is valid until ``buffers`` more have been asked
    for. ``digest`` (a hashlib object) is fed the file's bytes as they are read (gzip: the
    decompressed text)."""
    path = Path(path)
    if not path.exists():
        raise LogFormatError(f"{path}: no such file")
    opener = gzip.open if path.suffix == ".gz" else open
    size = max(int(chunk_bytes), 1 << 12)
    ring = [np.empty(size, dtype=np.uint8) for _ in range(max(1, buffers))]
    turn = 0
    buf = ring[0]
    carry = 0
    line = 1
    with opener(path, "rb") as handle:
        while True:
            if carry == len(buf):  # a line longer than the buffer: grow it
                buf = ring[turn] = np.concatenate([buf, np.empty(len(buf), dtype=np.uint8)])
            view = memoryview(buf)[carry:]
            try:
                got = handle.readinto(view)
            except (OSError, EOFError, zlib.error) as exc:  # BadGzipFile is an OSError
                raise LogFormatError(f"{path}: not a readable gzip file "
                                     f"({exc or 'truncated'})") from exc
            if digest is not None and got:
                digest.update(view[:got])
            end = carry + got
            if got == 0:
                if carry:
                    yield buf[:carry], line, count_newlines(buf[:carry])
                return
            cut = _after_last_newline(buf, carry, end)
            if cut == 0:  # no line ends in the buffer yet
                carry = end
                continue
            block = buf[:cut]
            newlines = count_newlines(block)
            yield block, line, newlines
            line += newlines
            carry = end - cut
            turn = (turn + 1) % len(ring)  # the tail starts the next buffer of the ring
            if len(ring[turn]) < carry:
                ring[turn] = np.empty(len(buf), dtype=np.uint8)
            ring[turn][:carry] = buf[cut:end]
            buf = ring[turn]


def _after_last_newline(buf: np.ndarray, start: int, end: int) -> int:
    """Index after the last newline in ``buf[start:end]`` (0: none); searches the tail first."""
    tail = 1 << 16
    lo = end
    while lo > start:
        lo, hi = max(start, lo - tail), lo
        hits = np.flatnonzero(buf[lo:hi] == 10)
        if len(hits):
            return lo + int(hits[-1]) + 1
        tail *= 4
    return 0


@dataclass
class ReadStats:
    """What a chunked read saw of a log: frames, skipped lines, channel names, checksum."""

    source: str
    frames: int = 0
    bad_lines: int = 0
    bad_line_numbers: list[int] = field(default_factory=list)
    channels: list[str] = field(default_factory=list)
    sha256: str = ""

    def adopt(self, frames: Frames) -> Frames:
        """``frames`` (a chunk with its own channel list) with the log's channel indices
        (first appearance over the chunks so far, as a whole-log read numbers them)."""
        index = np.zeros(max(len(frames.channels), 1), dtype=np.uint8)
        for local, name in enumerate(frames.channels):
            if name not in self.channels:
                if len(self.channels) >= MAX_CHANNELS:
                    raise LogFormatError(f"{self.source}: more than {MAX_CHANNELS} distinct "
                                         f"channel names (at {name!r})")
                self.channels.append(name)
            index[local] = self.channels.index(name)
        self.frames += len(frames)
        self.bad_lines += frames.bad_lines
        room = 100 - len(self.bad_line_numbers)
        self.bad_line_numbers += frames.bad_line_numbers[:max(room, 0)]
        frames.channel = index[frames.channel] if len(frames) else frames.channel
        frames.channels = list(self.channels)
        frames.bad_lines, frames.bad_line_numbers = 0, []
        return frames


def frame_chunks(path: str | Path, skip_bad: bool = False, chunk_bytes: int = CHUNK_BYTES,
                 stats: ReadStats | None = None, checksum: bool = False) -> Iterator[Frames]:
    """The frames of any log :func:`~slipd.replay.readers.read_frames` reads, chunk by chunk,
    with the log's channel numbering (``channels`` lists the names seen so far). ``stats``
    (updated as chunks are read) ends with the frame and skipped-line counts; with
    ``checksum`` also the file's SHA-256 (candump text: of the bytes read, else a pass of its
    own). A candump log is read in blocks of whole lines; a python-can format by
    ``chunk_bytes / 36`` messages; an MF4 bus log whole (asammdf reads its groups as whole
    arrays), then cut into chunks."""
    from slipd.replay import readers

    path = Path(path)
    stats = stats if stats is not None else ReadStats(str(path))
    suffixes = "".join(path.suffixes[-2:]) if path.suffix == ".gz" else path.suffix
    base_suffix = suffixes.removesuffix(".gz")
    if base_suffix in readers.CANDUMP_SUFFIXES or base_suffix == "":
        digest = hashlib.sha256() if checksum else None
        # blocks read by a thread of their own and parsed by PARSE_WORKERS threads (the
        # kernel releases the GIL); the caller (the latch thread) only takes the frames
        workers = min(PARSE_WORKERS, replay_threads())
        blocks = line_blocks(path, chunk_bytes, digest, buffers=workers + 2)

        def parse(block: tuple[np.ndarray, int, int]) -> Frames:
            text, first_line, newlines = block
            return parse_candump(text, str(path), skip_bad, first_line, newlines=newlines)

        parsed = ahead_map(parse, blocks, workers, workers + 1, f"parse {path}")
        for frames in ahead(parsed, 1, f"read {path}"):
            yield stats.adopt(frames)
        if digest is not None:
            stats.sha256 = digest.hexdigest()
        return
    if checksum:
        stats.sha256 = file_sha256(path)
    per_chunk = max(1, chunk_bytes // _LINE_BYTES)
    if suffixes == ".mf4" or base_suffix not in readers.LIBRARY_SUFFIXES:
        whole = readers.read_frames(path, skip_bad=skip_bad)  # MF4, or the suffix error
        for start in range(0, max(len(whole), 1), per_chunk):
            yield stats.adopt(_piece(whole, start, start + per_chunk))
        return
    yield from (stats.adopt(f) for f in _python_can_chunks(path, per_chunk))


def _python_can_chunks(path: Path, per_chunk: int) -> Iterator[Frames]:
    import can

    from slipd.replay.messages import frames_from_messages
    from slipd.replay.readers import python_can_errors

    records = 0
    try:
        messages = iter(can.LogReader(str(path)))
        while True:
            batch = list(itertools.islice(messages, per_chunk))
            if not batch:
                return
            frames = frames_from_messages(batch, source=str(path))
            frames.line = np.arange(records + 1, records + len(frames) + 1, dtype=np.int64)
            records += len(frames)
            yield frames
    except python_can_errors() as exc:  # the errors the whole-log reader names too
        raise LogFormatError(f"{path}: python-can cannot read it: "
                             f"{type(exc).__name__}: {exc}") from exc


def file_sha256(path: str | Path, block: int = 1 << 22) -> str:
    """SHA-256 of a file's bytes, read in blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(block):
            digest.update(chunk)
    return digest.hexdigest()


def _piece(frames: Frames, start: int, stop: int, copy: bool = True) -> Frames:
    """Frames ``[start, stop)``: copies (so a small piece does not pin its parent's arrays),
    or views."""
    def cut(a: np.ndarray) -> np.ndarray:
        return a[start:stop].copy() if copy else a[start:stop]

    return Frames(cut(frames.t), cut(frames.frame_id), cut(frames.flags), cut(frames.dlc),
                  cut(frames.data), cut(frames.channel), list(frames.channels), frames.source,
                  frames.bad_lines if start == 0 else 0,
                  frames.bad_line_numbers if start == 0 else [])


def frames_empty(channels: list[str], source: str) -> Frames:
    """No frames (a chunk with none)."""
    return Frames(np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.uint8),
                  np.zeros(0, np.uint8), np.zeros((0, 8), np.uint8), np.zeros(0, np.uint8),
                  list(channels), source)


def concat_frames(first: Frames | None, second: Frames) -> Frames:
    """``first`` then ``second`` (the channel list of ``second``, which extends the first's)."""
    if first is None or not len(first):
        return second
    width = max(first.data.shape[1], second.data.shape[1])

    def wide(d: np.ndarray) -> np.ndarray:
        return d if d.shape[1] == width else np.pad(d, ((0, 0), (0, width - d.shape[1])))

    return Frames(np.concatenate([first.t, second.t]),
                  np.concatenate([first.frame_id, second.frame_id]),
                  np.concatenate([first.flags, second.flags]),
                  np.concatenate([first.dlc, second.dlc]),
                  np.concatenate([wide(first.data), wide(second.data)]),
                  np.concatenate([first.channel, second.channel]),
                  second.channels, second.source)


# ---------------------------------------------------------------------------------------------
# decode and latch
# ---------------------------------------------------------------------------------------------


class _BusChoice:
    """engine.frame_buses over a log read in chunks: the choice is made on the channels seen
    so far and must not change for a channel once made."""

    def __init__(self, codec: Codec, bus_map: dict[str, str] | None, source: str):
        self.codec, self.bus_map, self.source = codec, bus_map, source
        self.carrying: list[str] = []
        self.chosen: dict[str, int | None] = {}  # channel name -> bus index (None: unread)
        self.names: list[str] = []
        self.any_frames = False

    def buses(self, frames: Frames, first_frame: int) -> np.ndarray:
        """Bus index of each frame of a chunk (-1: a channel the profile does not read);
        ``first_frame`` is the chunk's first frame number in the log (for errors)."""
        names = list(frames.channels)
        self.names = names
        self.any_frames = self.any_frames or len(frames) > 0
        if _reads_carrying(self.codec, self.bus_map, names):
            found = _channels_carrying(frames, self.codec, skip=set(self.carrying))
            order = {name: k for k, name in enumerate(names)}
            self.carrying = sorted(set(self.carrying) | set(found), key=order.__getitem__)
        chosen = channel_buses(names, self.carrying, self.codec, self.bus_map, self.source,
                               self.any_frames, complete=False)
        for name in names:
            bus = chosen.get(name)
            if name in self.chosen and self.chosen[name] != bus:
                raise ConfigError(
                    f"{self.source}: from frame {first_frame + 1} on, log channel {name!r} "
                    f"would be read as {self._bus_name(bus)} where the frames before were "
                    f"read as {self._bus_name(self.chosen[name])} (channels seen: {names}); "
                    f"name each bus's channel with --bus BUS=CHANNEL")
            self.chosen[name] = bus
        result = np.full(len(frames), -1, dtype=np.int64)
        for name, bus in chosen.items():
            result[frames.channel == names.index(name)] = bus
        return result

    def _bus_name(self, bus: int | None) -> str:
        return "no bus" if bus is None else f"bus {self.codec.inputs.buses[bus]!r}"

    def finish(self) -> None:
        """The checks that need the whole log (a bus with no channel, --bus naming a channel
        the log lacks)."""
        channel_buses(self.names, self.carrying, self.codec, self.bus_map, self.source,
                      self.any_frames, complete=True)


@dataclass
class Latched:
    """One chunk's ticks: the latched inputs."""

    inputs: Inputs


class Latcher:
    """Decode and latch a log fed chunk by chunk, on exactly the ticks (and with exactly the
    latch) of :func:`~slipd.replay.engine.latch_log_or_recording` over the whole log.

    ``feed`` each chunk of frames (with the log's channel numbering, see
    :func:`frame_chunks`), then ``finish``; each returns the ticks it could latch (or None).
    ``errors`` (the codec's counters) is complete after ``finish``."""

    def __init__(self, profile: Profile, bus_map: dict[str, str] | None = None,
                 dt: float = TICK_DT, source: str = ""):
        self.profile, self.dt, self.source = profile, dt, source
        self.codec = Codec(profile)
        self.width = max(8, self.codec.inputs.max_dlc)
        self.state_id = Codec.output_plan(profile).frame_id("SLIPD_STATE")
        self.recording: bool | None = None
        self._buses = _BusChoice(self.codec, bus_map, source)
        self._pending: Frames | None = None
        self._pending_bus = np.zeros(0, dtype=np.int64)
        self._t0: float | None = None
        self._next_tick = 0
        self._last_time = -np.inf
        self._last_tick: float | None = None
        self.frames_fed = 0
        self.ticks = 0

    @property
    def errors(self) -> dict[str, dict[str, int]]:
        return self.codec.error_counts()

    def feed(self, frames: Frames) -> Latched | None:
        if not len(frames):
            return None
        first = self.frames_fed
        self.frames_fed += len(frames)
        if self.recording is None:
            self.recording = recorded_ticks(frames, self.profile) is not None
        if self.recording:
            return self._feed_recording(frames, first)
        self._check_grid_log(frames, first)
        bus = self._buses.buses(frames, first)
        pending = concat_frames(self._pending, frames)
        pending_bus = np.concatenate([self._pending_bus, bus])
        if self._t0 is None:
            self._t0 = float(pending.t[0])
        newest = pending.t[-1]
        ticks = self._grid(newest)
        ticks = ticks[ticks < newest]  # a later frame may still share the newest time
        return self._latch(pending, pending_bus, ticks)

    def finish(self) -> Latched | None:
        """The last ticks (the grid's count over the whole log), and the whole-log checks."""
        self._buses.finish()
        if self.recording or self._pending is None or not len(self._pending):
            return None
        ticks = self._grid(self._pending.t[-1])
        return self._latch(self._pending, self._pending_bus, ticks)

    def _grid(self, newest: float) -> np.ndarray:
        """Ticks from the next unlatched one up to the grid's end if ``newest`` were the
        log's last frame time (engine.tick_grid's arithmetic, so the same doubles)."""
        start = self._t0 + self.dt
        count = int(np.floor((newest - self._t0) / self.dt + 1e-9))
        return start + self.dt * np.arange(self._next_tick, max(count, self._next_tick))

    def _check_grid_log(self, frames: Frames, first: int) -> None:
        t = frames.t
        behind = np.flatnonzero(np.diff(np.concatenate([[self._last_time], t])) < 0)
        if len(behind):
            bad = int(behind[0])
            before = t[bad - 1] if bad else self._last_time
            raise LogFormatError(f"{self.source}: frame {first + bad + 1} goes back in time "
                                 f"({t[bad]:.6f} < {before:.6f}); sort the log")
        self._last_time = float(t[-1])
        sent_ticks = ((frames.flags & FLAG_TX) != 0) & (frames.frame_id == self.state_id)
        if sent_ticks.any():
            at = first + int(np.flatnonzero(sent_ticks)[0]) + 1
            raise LogFormatError(
                f"{self.source}: frame {at} is a SLIPD_STATE slipd sent (a flight-recorder "
                f"tick), but the log's first {first} frames had none: a recording starts with "
                f"its ticks, so this log cannot be replayed as one; cut it at that frame")

    def _feed_recording(self, frames: Frames, first: int) -> Latched | None:
        combined = concat_frames(self._pending, frames)
        recorded = recorded_ticks(combined, self.profile)
        if recorded is None:  # no tick in it: every line waits for the next one
            self._pending = combined
            return None
        inputs, tick_time, tick_until = recorded
        bus = self._buses.buses(inputs, first)
        before = [] if self._last_tick is None else [self._last_tick]
        steps = steps_per_tick(np.concatenate([before, tick_time]), self.dt)[len(before):]
        self._last_tick = float(tick_time[-1])
        return self._latch(inputs, bus, tick_time, tick_until, steps if np.any(steps > 1)
                           else None)

    def _latch(self, pending: Frames, bus: np.ndarray, ticks: np.ndarray,
               tick_until: np.ndarray | None = None,
               steps: np.ndarray | None = None) -> Latched | None:
        if tick_until is None:
            tick_until = np.searchsorted(pending.t, ticks, side="right").astype(np.int64)
        used = int(tick_until[-1]) if len(ticks) else 0
        if len(ticks):
            p, s = self.codec.inputs, self.codec.state
            data = pending.data if pending.data.shape[1] >= self.width else np.pad(
                pending.data, ((0, 0), (0, self.width - pending.data.shape[1])))
            U = np.zeros((len(ticks), U_LEN))
            kernels.latch_ticks(p.plan_i, p.plan_f, p.lookup, p.timeouts,
                                self.codec.channel_timeouts, self.codec.calibration, pending.t,
                                bus, pending.frame_id,
                                pending.flags, pending.dlc.astype(np.int64), data, ticks,
                                tick_until, s.latch, s.msg_state, s.errors, s.scratch, U)
        else:
            U = np.zeros((0, U_LEN))
        self._pending = _piece(pending, used, len(pending))
        self._pending_bus = bus[used:].copy()
        self._next_tick += len(ticks)
        self.ticks += len(ticks)
        if not len(ticks):
            return None
        return Latched(Inputs(ticks, U, {}, used, steps))


# ---------------------------------------------------------------------------------------------
# estimate
# ---------------------------------------------------------------------------------------------


class MethodRuns:
    """Methods stepping through a log's chunks: one Pipeline and one carried state each.

    A chunk's raw runs (each method, and its consistency witness, once per distinct run:
    :class:`~slipd.pipeline.RawRuns`) are independent until supervision, and their kernels
    release the GIL: with more than one replay thread (``parallel``, default
    ``replay_threads() > 1``) they run on a pool of that many threads, and
    each pipeline's supervision and monitor then take them in the caller's thread, in the
    methods' order: the same outputs, bit for bit, as one thread."""

    def __init__(self, profile: Profile, methods: Iterable[str],
                 overrides: dict[str, float] | None = None, dt: float = TICK_DT,
                 pipelines: dict[str, Pipeline] | None = None,
                 parallel: bool | None = None):
        """``pipelines``: ones built before for this profile, overrides and dt (a Pipeline
        keeps no state of a run: a worker replaying many logs builds each once)."""
        built = pipelines if pipelines is not None else {}
        self.pipelines = {name: built.get(name) or Pipeline(name, profile, overrides, dt)
                          for name in methods}
        self.states = {name: p.new_state() for name, p in self.pipelines.items()}
        #: raw runs more than one method needs (the witness): each made once per chunk
        self.shared = RawRuns.shared_keys(self.pipelines.values())
        self.threads = replay_threads()
        jobs = sum(1 for _ in self._jobs())
        wanted = pool_pays(jobs, self.threads) if parallel is None else parallel
        self.parallel = wanted and self.threads > 1

    def run(self, inputs: Inputs) -> dict[str, np.ndarray]:
        """Each method's supervised outputs [n_ticks, N_OUT] on a chunk's inputs."""
        if not len(inputs.t):
            return {name: np.zeros((0, N_OUT)) for name in self.pipelines}
        if self.parallel:
            raw = self._raw_on_threads(inputs)
        else:
            raw = RawRuns(self.shared) if self.shared else None
        return {name: p.run(inputs.U, inputs.steps, self.states[name], raw)
                for name, p in self.pipelines.items()}

    def _jobs(self) -> Iterator[tuple[tuple, Pipeline, object, np.ndarray]]:
        """Each distinct raw run of a chunk: (key, a pipeline that makes it, the method, its
        state part in that pipeline's carried state)."""
        seen = set()
        for name, pipeline in self.pipelines.items():
            for key, method, part in pipeline.raw_jobs(self.states[name]):
                if key not in seen:
                    seen.add(key)
                    yield key, pipeline, method, part

    def _raw_on_threads(self, inputs: Inputs) -> RawRuns:
        steps = inputs.steps
        stepped = inputs.U if steps is None else np.repeat(inputs.U, steps, axis=0)

        def run(job) -> tuple[tuple, np.ndarray, np.ndarray]:
            key, pipeline, method, part = job
            state = part.copy()  # every pipeline takes the state after from the RawRuns
            return key, pipeline.raw_run(method, state, stepped, steps), state

        raw = RawRuns(self.shared)  # the shared outputs are copied, the others handed over
        for key, out, state in _method_pool(self.threads).map(run, list(self._jobs())):
            raw.runs[key] = (out, state)
        return raw


def pool_pays(jobs: int, threads: int) -> bool:
    """Whether a chunk's ``jobs`` raw runs go to the method pool of ``threads`` threads. The
    streaming replay's other stages (parse, decode and latch, write) keep about a core busy
    on their own threads, so the pool only pays where it has cores of its own (more than
    two) or where the raw runs outnumber the cores (``--estimator all``: estimation is then
    most of the work). Measured on 2 cores (benchmarks/replay.py, 10-minute log, one method
    and its witness): the pool made the replay 5-8 % slower (the two jobs took the core the
    other stages needed, and the threads' hand-offs cost CPU); with ``all`` it is what keeps
    both cores estimating."""
    return jobs > 1 and (threads > 2 or jobs > threads)


_POOL: tuple[int, ThreadPoolExecutor] | None = None
_POOL_LOCK = threading.Lock()


def _method_pool(threads: int) -> ThreadPoolExecutor:
    """The process's pool for methods' raw runs (made on first use; a forked child, such as
    a Dask worker forked from slipd's forkserver, makes its own: a parent's pool threads do
    not exist in the child)."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None or _POOL[0] != threads:
            if _POOL is not None:
                _POOL[1].shutdown(wait=False)  # its queued runs still finish
            _POOL = (threads, ThreadPoolExecutor(threads, thread_name_prefix="slipd method"))
        return _POOL[1]


def _forget_pool() -> None:
    global _POOL, _POOL_LOCK
    _POOL, _POOL_LOCK = None, threading.Lock()  # the parent's lock may be held at the fork


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


@dataclass
class Chunk:
    """One chunk of a streamed log: the log's frames read for it (every frame, in file
    order: what a merged candump writes), its ticks' latched inputs and each method's outputs
    on them. The last chunk may have no tick (the frames after the log's last tick)."""

    inputs: Inputs
    frames: Frames
    outputs: dict[str, np.ndarray]


class LogStream:
    """A log streamed through the methods: iterate it for its :class:`Chunk` s; afterwards
    ``read`` (frames, skipped lines, channels, SHA-256 with ``checksum``), ``errors`` (the
    codec's counters) and ``ticks`` describe the whole log.

    >>> for chunk in LogStream("drive.log", "default", ["kinematic_heuristic"]):
    ...     writer.write("kinematic_heuristic", chunk.inputs.t, chunk.outputs[...])
    """

    def __init__(self, log: str | Path, profile: Profile | str, methods: Iterable[str] = (),
                 skip_bad: bool = False, bus_map: dict[str, str] | None = None,
                 chunk_bytes: int = CHUNK_BYTES, overrides: dict[str, float] | None = None,
                 checksum: bool = False, dt: float = TICK_DT,
                 pipelines: dict[str, Pipeline] | None = None):
        self.log = Path(log)
        self.profile = load_profile(profile) if isinstance(profile, str) else profile
        self.methods = list(methods)
        self.skip_bad, self.bus_map, self.chunk_bytes = skip_bad, bus_map, chunk_bytes
        self.checksum, self.dt = checksum, dt
        self.runs = MethodRuns(self.profile, self.methods, overrides, dt, pipelines)
        self.read = ReadStats(str(self.log))
        self.latcher = Latcher(self.profile, bus_map, dt, str(self.log))
        self.first_time: float | None = None

    @property
    def errors(self) -> dict[str, dict[str, int]]:
        return self.latcher.errors

    @property
    def ticks(self) -> int:
        return self.latcher.ticks

    def __iter__(self) -> Iterator[Chunk]:
        # read, decode and latch in a thread, a chunk ahead of the estimate (slipd.replay.ahead)
        for inputs, read in ahead(self._latched(), 1, f"latch {self.log}"):
            yield self._estimate(inputs, read)

    def _latched(self) -> Iterator[tuple[Inputs, Frames]]:
        """Each chunk's latched inputs and the frames read for it."""
        chunks = frame_chunks(self.log, self.skip_bad, self.chunk_bytes, self.read,
                              self.checksum)
        read: Frames | None = None  # frames read since the last chunk was handed out
        for frames in chunks:
            if self.first_time is None and len(frames):
                self.first_time = float(frames.t[0])
            read = concat_frames(read, frames)
            latched = self.latcher.feed(frames)
            if latched is not None:
                yield latched.inputs, read
                read = None
        latched = self.latcher.finish()
        if latched is not None or (read is not None and len(read)):
            inputs = latched.inputs if latched is not None else Inputs(
                np.zeros(0), np.zeros((0, U_LEN)), {}, 0)
            yield inputs, (read if read is not None else
                           frames_empty(self.read.channels, str(self.log)))

    def _estimate(self, inputs: Inputs, read: Frames) -> Chunk:
        return Chunk(inputs, read, self.runs.run(inputs))


def stream_inputs(log: str | Path, profile: Profile | str,
                  bus_map: dict[str, str] | None = None, skip_bad: bool = False,
                  chunk_bytes: int = CHUNK_BYTES) -> Iterator[Inputs]:
    """The streaming twin of ``latch_log_or_recording(read_frames(log), profile)``: the
    latched inputs chunk by chunk (their rows together are the whole-log Inputs' rows)."""
    for chunk in LogStream(log, profile, (), skip_bad, bus_map, chunk_bytes):
        yield chunk.inputs


def joined_inputs(parts: Iterable[Inputs]) -> Inputs:
    """Chunks' inputs as one (tests, small logs)."""
    parts = list(parts)
    if not parts:
        return Inputs(np.zeros(0), np.zeros((0, U_LEN)), {}, 0)
    steps = [p.steps if p.steps is not None else np.ones(len(p.t), np.int64) for p in parts]
    joined = np.concatenate(steps)
    return Inputs(np.concatenate([p.t for p in parts]), np.concatenate([p.U for p in parts]),
                  {}, sum(p.n_frames for p in parts), joined if np.any(joined > 1) else None)


def warm_kernels(methods: Iterable[str], profile: Profile | str = "default") -> None:
    """Load (or compile into numba's cache) every kernel a replay of ``methods`` calls: the
    candump parser, decode and latch, each method, supervision and the CSV formatter."""
    from slipd.replay import textformat

    text = b"(1.000000) can0 123#00\n(1.050000) can0 123#00\n"
    frames = parse_candump(np.frombuffer(text, dtype=np.uint8), "warm-up")
    profile = load_profile(profile) if isinstance(profile, str) else profile
    latcher = Latcher(profile, source="warm-up")
    latched = latcher.feed(frames)
    runs = MethodRuns(profile, methods)
    if latched is not None:
        runs.run(latched.inputs)
    textformat.format_csv(np.zeros((1, 2)), np.array([4, textformat.INTEGER]), "m", 1)
