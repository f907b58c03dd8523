"""The real-time loop: absolute 10 ms ticks on CLOCK_MONOTONIC, one thread.

Between ticks the loop receives frames and decodes each into the latch
(:meth:`slipd.codec.Codec.decode`); at each tick it samples the latch, steps the estimator,
supervises the inputs, encodes SLIPD_STATE and SLIPD_AUX and sends them. Everything else
(1 Hz diagnostics frame, stats requests, systemd notifications, persistence, the live view)
runs in the slack after a tick's frames are on the bus. No other thread does work, because a
busy Python thread delays every cycle by ~5 ms here (shared/notes/realtime-python.md).
"""

from __future__ import annotations

import gc
import math
import signal
import socket
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slipd.channels import N_OUT, ST_INPUT_TIMEOUT, ST_VALID, In, Out, new_u
from slipd.codec import N_TX, Codec, DecodeState, Tx
from slipd.codec.kernels import ERROR_NAMES, LATCH_SET, LATCH_TIME
from slipd.codec.plan import OUTPUT_MESSAGES
from slipd.codec.tx import fill_tx
from slipd.daemon.recorder import FlightRecorder
from slipd.daemon.service import (
    RealtimeOptions,
    StateStore,
    SystemdNotifier,
    apply_realtime,
    plausible_state,
    release_compiler_pages,
)
from slipd.daemon.stats import (
    Stats,
    StatsLayout,
    StatsServer,
    check_stats_socket,
    clear,
    parse_prometheus,
    summarize,
)
from slipd.daemon.transmit import QUEUE_FULL, frame_buffer, frame_writer, payload
from slipd.errors import ConfigError
from slipd.estimators import registry
from slipd.estimators.consistency import Flag
from slipd.pipeline import TICK_DT, Pipeline, catch_up_steps
from slipd.profile import Profile

#: the monitor's verdicts counted per tick, and three checks counted on their own (which
#: one cleared VALID: the filter's innovation test, a calibrated sigma beyond what VALID
#: promises, or a dynamic witness not tracking)
CONSISTENCY_COUNTED = (
    (int(Flag.FAIL), "consistency_fail_ticks"), (int(Flag.WARN), "consistency_warn_ticks"),
    (int(Flag.INNOVATION), "consistency_innovation_ticks"),
    (int(Flag.IMPRECISE), "consistency_imprecise_ticks"),
    (int(Flag.WITNESS), "consistency_witness_ticks"),
)
REOPEN_INTERVAL = 1.0  # s between attempts to reopen a vanished interface
PERSIST_INTERVAL = 60.0  # s
LATE_DRAIN_MAX = 64  # frames taken from the socket queue before a tick that is already late
#: s: a change of (wall clock - CLOCK_MONOTONIC) beyond this is a step of the wall clock (NTP
#: or GNSS setting it, date -s). Slewing moves both clocks alike, so the difference changes
#: only by steps; the readings around it jitter by well under a microsecond.
CLOCK_STEP_MIN_S = 1e-3
CLOCK_READ_MAX_S = 50e-6  # monotonic readings further apart: preempted, measure next tick
SOCKET_RECEIVE_BUFFER = 1 << 20  # bytes: ~1 s of a full bus queued while the loop is busy
IFF_UP = 0x1
SO_MEMINFO = getattr(socket, "SO_MEMINFO", 55)  # linux/socket.h
SK_MEMINFO_DROPS, SK_MEMINFO_VARS = 8, 9  # linux/sock_diag.h: u32[SK_MEMINFO_VARS]
EVENTS_KEPT = 50  # bus and tool events listed in the snapshot (the newest; older counted)
TICK_MESSAGES = ("SLIPD_STATE", "SLIPD_AUX")  # sent every tick; SLIPD_DIAG once a second
WARM_UP_ALLOWANCE_S = 300.0  # start-up time asked of systemd while numba compiles (cold cache)


@dataclass
class DaemonConfig:
    profile: Profile
    estimator: str = registry.DEFAULT_ESTIMATOR
    interface: str = "socketcan"
    channel: str = "can0"
    #: profile bus name -> channel (``--bus chassis=can0``); a one-bus profile needs none
    buses: dict[str, str] = field(default_factory=dict)
    fd: bool | None = None  # CAN FD frames on the sockets; None: where the profile needs them
    bitrate: int | None = None
    bus_kwargs: dict = field(default_factory=dict)  # more python-can Bus() arguments
    listen_only: bool = False  # estimate and record, send nothing (also [outputs] listen_only)
    recorder: Path | None = None
    recorder_max_bytes: int = 256 * 1024 * 1024
    recorder_keep: int = 10  # rotated files kept (slipd.daemon.recorder)
    recorder_compress: bool = True
    stats_socket: str | None = None
    stats_socket_mode: int = 0o660  # owner and group (the unit's `slipd` group) may query
    prometheus: str | int | None = None  # HOST:PORT or a port (loopback)
    prometheus_public: bool = False  # a non-loopback Prometheus address is allowed
    state_file: Path | None = None
    realtime: RealtimeOptions = field(default_factory=RealtimeOptions)
    duration: float | None = None  # s; None = until SIGTERM/SIGINT
    silence_warning_s: float = 5.0  # warn when a bus delivers no frame for this long


def bus_channels(config: DaemonConfig) -> dict[str, str]:
    """Each of the profile's buses (inputs and outputs) -> its interface channel."""
    names = config.profile.buses
    unknown = sorted(set(config.buses) - set(names))
    if unknown:
        raise ConfigError(f"--bus {unknown[0]}=...: profile {config.profile.name} has no bus "
                          f"{unknown[0]!r}; its buses: {list(names)}")
    if len(names) == 1:
        return {names[0]: config.buses.get(names[0], config.channel)}
    missing = [n for n in names if n not in config.buses]
    if missing:
        raise ConfigError(f"profile {config.profile.name} reads buses {list(names)}; give "
                          f"each its interface: " + " ".join(f"--bus {n}=CHANNEL"
                                                            for n in missing))
    channels = {n: config.buses[n] for n in names}
    if len(set(channels.values())) != len(channels):
        raise ConfigError(f"--bus: two profile buses on one channel {channels}; a channel "
                          "carries one bus")
    return channels


def open_bus(config: DaemonConfig, plan_ids: list[tuple[int, bool]], channel: str | None = None,
             fd: bool = False):
    """A python-can bus with kernel RX filters for the profile's input IDs (CAN FD frames
    enabled with ``fd``: CAN_RAW_FD_FRAMES on SocketCAN)."""
    import can

    filters = [{"can_id": frame_id, "can_mask": 0x1FFFFFFF if ext else 0x7FF, "extended": ext}
               for frame_id, ext in plan_ids]
    if not filters:  # a bus slipd only sends on: receive nothing
        filters = [{"can_id": 0, "can_mask": 0x1FFFFFFF, "extended": True}]
    kwargs = {**config.bus_kwargs, "interface": config.interface,
              "channel": channel if channel is not None else config.channel,
              "can_filters": filters}
    if fd:
        kwargs["fd"] = True
    if config.bitrate is not None:
        kwargs["bitrate"] = config.bitrate
    if config.interface == "socketcan":
        kwargs["ignore_rx_error_frames"] = True
    bus = can.Bus(**kwargs)
    if config.interface == "socketcan":
        _enlarge_receive_buffer(bus.socket)
        if fd:
            _require_fd(bus, kwargs["channel"])
    return bus


def _require_fd(bus, channel: str) -> None:
    """python-can only logs a refused CAN_RAW_FD_FRAMES; a profile with FD frames needs it."""
    sol_can_raw, can_raw_fd_frames = 101, 5  # <linux/can/raw.h>
    try:
        enabled = bus.socket.getsockopt(sol_can_raw, can_raw_fd_frames)
    except OSError as exc:
        enabled, why = 0, exc.strerror
    else:
        why = "the socket refused CAN_RAW_FD_FRAMES"
    if not enabled:
        bus.shutdown()
        raise ConfigError(f"{channel}: CAN FD frames are needed (the profile has frames over "
                          f"8 bytes or FD outputs) but {why}; is the interface FD-capable "
                          f"(mtu 72)?")


def open_bus_at_start(config: DaemonConfig, plan_ids: list[tuple[int, bool]], channel: str,
                      fd: bool = False):
    """:func:`open_bus`, with a refusal explained as a ConfigError (an unknown interface, a
    kernel without CAN, a missing CAN device) instead of python-can's traceback."""
    import errno

    import can

    where = f"{config.interface}:{channel}"
    try:
        return open_bus(config, plan_ids, channel, fd)
    except can.CanInterfaceNotImplementedError as exc:
        raise ConfigError(f"--interface {config.interface!r}: {exc}; python-can knows "
                          f"{', '.join(sorted(can.VALID_INTERFACES))}") from exc
    except OSError as exc:
        if exc.errno == errno.EAFNOSUPPORT:
            raise ConfigError(f"{where}: this kernel has no CAN sockets (AF_CAN: "
                              f"{exc.strerror}); load the can and can_raw modules, or use "
                              "--interface slipd_unix or virtual without a CAN bus") from exc
        if exc.errno == errno.ENODEV:
            raise ConfigError(f"{where}: no such network interface (`ip link` lists them)"
                              ) from exc
        raise ConfigError(f"{where}: cannot open the bus: {exc}") from exc
    except (can.CanError, ValueError, TypeError) as exc:
        raise ConfigError(f"{where}: cannot open the bus: {exc}") from exc


def receive_overflows(bus) -> int | None:
    """Frames the kernel dropped because the bus socket's receive queue was full: the
    socket's ``sk_drops``, the counter SO_RXQ_OVFL reports, read with SO_MEMINFO (one
    getsockopt, once a second; python-can's receive asks for the timestamp control message
    only, so SO_RXQ_OVFL's per-frame message would be cut off there). None when the bus has
    no kernel socket (virtual) or the kernel lacks SO_MEMINFO."""
    sock = getattr(bus, "socket", None)
    if sock is None or not hasattr(sock, "getsockopt"):
        return None
    try:
        info = sock.getsockopt(socket.SOL_SOCKET, SO_MEMINFO, SK_MEMINFO_VARS * 4)
    except OSError:
        return None
    if len(info) < SK_MEMINFO_VARS * 4:
        return None
    return struct.unpack_from("=I", info, SK_MEMINFO_DROPS * 4)[0]


def _enlarge_receive_buffer(sock) -> None:
    """A deeper kernel queue, so a burst while the loop computes is not dropped (SocketCAN
    drops silently on overflow). SO_RCVBUFFORCE passes rmem_max with CAP_NET_ADMIN; without
    it SO_RCVBUF gets what rmem_max allows."""
    import socket

    for option in (getattr(socket, "SO_RCVBUFFORCE", 33), socket.SO_RCVBUF):
        try:
            sock.setsockopt(socket.SOL_SOCKET, option, SOCKET_RECEIVE_BUFFER)
            return
        except OSError:
            continue


def _microseconds(t: float) -> float:
    """A time on the microsecond grid the recorder writes, so a replay sees the same values."""
    return round(t * 1e6) / 1e6


def _log_line(line: str) -> None:
    """The daemon's default log: one line to stdout, flushed at once (under systemd stdout is
    a pipe to the journal, block-buffered by Python: a bus failure would show up kilobytes
    of log later)."""
    print(line, flush=True)


def _recv_any(buses, timeout: float):
    """The first frame of several buses: select() on their file descriptors where each has
    one, else a polling loop (0.2 ms sleeps) for buses without (python-can's virtual bus)."""
    import select

    deadline = time.monotonic() + timeout
    try:
        fds = [bus.fileno() for bus in buses]
    except (AttributeError, NotImplementedError, OSError):
        fds = None
    if fds is not None and not all(isinstance(fd, int) and fd >= 0 for fd in fds):
        fds = None
    while True:
        for index, bus in enumerate(buses):  # frames python-can already holds first
            message = bus.recv(timeout=0.0)
            if message is not None:
                return message, index
        remaining = deadline - time.monotonic()
        if remaining <= 0.0:
            return None, -1
        if fds is None:
            time.sleep(min(remaining, 0.0002))
        elif not select.select(fds, [], [], remaining)[0]:
            return None, -1


def interface_is_up(channel: str) -> bool | None:
    """IFF_UP of a network interface from sysfs; None when it does not exist."""
    try:
        flags = int(Path(f"/sys/class/net/{channel}/flags").read_text(), 16)
    except (OSError, ValueError):
        return None
    return bool(flags & IFF_UP)


class Daemon:
    """One estimator on one bus. ``run()`` blocks until stopped."""

    def __init__(self, config: DaemonConfig, bus=None,
                 on_second: Callable[[Daemon], None] | None = None, log=None):
        import can

        self.can = can
        self.config = config
        self.log = log or _log_line
        self.codec = Codec(config.profile)
        self.pipeline = Pipeline(config.estimator, config.profile)
        self.state = self.pipeline.new_state()
        self.store = StateStore(config.state_file)
        self.u = new_u()
        self.out = np.zeros(N_OUT)
        self.tx = np.zeros(N_TX)
        serve_stats = bool(config.stats_socket or config.prometheus)
        if config.stats_socket:
            check_stats_socket(config.stats_socket)
        prometheus = (parse_prometheus(config.prometheus, config.prometheus_public)
                      if config.prometheus else None)
        errors = (*self.codec.inputs.message_names, "unknown")
        layout = StatsLayout(rows=errors, columns=ERROR_NAMES, only={"unknown": ("unknown_id",)})
        self.stats = Stats.in_shared_memory(layout) if serve_stats else Stats()
        self.notifier = SystemdNotifier()
        self.on_second = on_second
        self.running = False
        self.last_status = 0
        self.steps = 1  # estimator steps at the next tick (pipeline.catch_up_steps)
        self._gc_started = 0.0
        self._dry_state = self.state.copy()
        self._dry_u, self._dry_out, self._dry_tx = new_u(), np.zeros(N_OUT), np.zeros(N_TX)
        self._dry_frame = frame_buffer(0)
        self._dry_payload = payload(self._dry_frame)
        self._dry_decode = DecodeState.new(self.codec.inputs.n_messages)
        self._last_message = None  # the newest received frame, decoded again by dry runs
        self.spin = config.realtime.spin_us * 1e-6
        self._deferred = None  # a frame received after a tick's time, decoded after it
        self._first_dry_cost = 0.0  # s, the last spin window's first dry run (_receive_until)
        # Dry runs in a spin window also send the frame through a private socket pair: the
        # send syscall's path is then warm too (measured: a unix datagram send after 10 ms
        # idle 51 us median, 24 us with such sends before it, 7 us back to back).
        self._syscall_warmer = (socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
                                if self.spin > 0 else None)
        plan = self.codec.inputs
        profile = config.profile
        self.bus_names = plan.buses  # profile bus order: the codec's bus indices
        self.channels = bus_channels(config) if bus is None or isinstance(bus, dict) else {
            name: config.buses.get(name, config.channel) for name in self.bus_names}
        outputs = self.codec.outputs
        self.output_bus = self.bus_names.index(profile.outputs.bus)
        self.listen_only = config.listen_only or profile.outputs.listen_only
        fd_needed = [any(plan.is_fd(n) for n in plan.message_names if plan.bus(n) == name)
                     or (name == profile.outputs.bus and profile.outputs.fd)
                     for name in self.bus_names]
        self.fd = [config.fd if config.fd is not None else need for need in fd_needed]
        for name, need, on in zip(self.bus_names, fd_needed, self.fd, strict=True):
            if need and not on:
                raise ConfigError(f"bus {name!r} carries CAN FD frames (the profile's), but "
                                  "--fd is off")
        self.plan_ids = [plan.ids_on(name) for name in self.bus_names]
        if bus is None or isinstance(bus, dict):
            given = bus or {}
            self.buses = []
            try:
                for k, name in enumerate(self.bus_names):
                    self.buses.append(given.get(name) or open_bus_at_start(
                        config, self.plan_ids[k], self.channels[name], self.fd[k]))
            except BaseException:
                for opened in self.buses:
                    if bus is None:
                        opened.shutdown()
                raise
        else:  # one bus object for every profile bus (tests, the demo)
            self.buses = [bus] * len(self.bus_names)
        self._owns_bus = bus is None
        self.bus = self.buses[self.output_bus]
        self._write_frame = frame_writer(self.bus)
        self._frame_ids = {name: outputs.frame_id(name) for name in OUTPUT_MESSAGES}
        self._frames = {name: frame_buffer(outputs.frame_id(name), outputs.is_extended(name),
                                           outputs.dlc(name), outputs.is_fd(name))
                        for name in OUTPUT_MESSAGES}
        self._payloads = {name: payload(frame) for name, frame in self._frames.items()}
        # for buses without a frame writer (python-can's virtual bus of the demo and tests)
        self._messages = {name: can.Message(arbitration_id=outputs.frame_id(name),
                                            is_extended_id=outputs.is_extended(name),
                                            is_fd=outputs.is_fd(name),
                                            bitrate_switch=outputs.is_fd(name),
                                            data=bytes(outputs.dlc(name)))
                          for name in OUTPUT_MESSAGES}
        self.bus_down_since: float | None = None
        self._next_reopen = 0.0
        self.started_at = 0.0  # monotonic, set when the loop starts
        self.bus_events: list[str] = []  # the newest EVENTS_KEPT
        self.tool_events: list[str] = []  # recorder, stats server: faults of the tools
        self.events_dropped = 0
        self._text_version = 0  # bumped when the snapshot's words change (events)
        self._text_sent = -1
        #: monotonic time of the last frame received on each bus (None: none yet)
        self.last_frame_at: list[float | None] = [None] * len(self.bus_names)
        # The daemon's time base (ticks, input ages, the recording): the wall clock at start
        # plus CLOCK_MONOTONIC's elapsed time. Frames come stamped by the kernel's wall clock;
        # a step of it since the start (measured once a tick) is taken off their stamps.
        self._wall_offset = time.time() - time.monotonic()
        self._clock_shift = 0.0  # s, the wall clock's steps since the start, summed
        self._newest_stamp = [-math.inf] * len(self.bus_names)  # per bus, on the time base
        self._silence_reported = [False] * len(self.bus_names)
        self._overflow_base = 0  # drops of the sockets before the current ones (reopens)
        self._overflow_last = 0
        self.recorder = (FlightRecorder(config.recorder, config.recorder_max_bytes,
                                        self.channels[profile.outputs.bus],
                                        keep=config.recorder_keep,
                                        compress=config.recorder_compress,
                                        log=self._tool_fault, on_error=self._recorder_failed)
                         if config.recorder else None)
        try:
            self.server = StatsServer(config.stats_socket, prometheus, self.stats,
                                      log=self._tool_fault,
                                      socket_mode=config.stats_socket_mode)
        except BaseException:
            self._close_owned()
            raise
        self.first_frame_at: float | None = None
        self._next_miss_log = 0.0  # monotonic time before which a miss is counted, not logged
        self._unlogged_misses = 0
        self.ready = threading.Event()  # set with READY=1 (tests and the demo wait on it)

    # ---- start-up -------------------------------------------------------------------------
    def warm_up(self) -> float:
        """Run every kernel once on dummy data so numba has compiled/loaded them (before
        READY=1); returns the seconds it took."""
        started = time.perf_counter()
        self._dry_tick(0.0)  # sample, step, supervise, fill_tx, encode
        # decode from bytes, as a received frame is (Codec.decode makes a read-only payload,
        # which numba types apart from a writable array: measured, a cold cache compiled it
        # in the first tick, a 1.6 s stall), into a throwaway state, so the real latch and
        # counters stay untouched
        self.codec.decode(0x7FF, bytes(8), 0.0, False, state=self._dry_decode)
        return time.perf_counter() - started

    def _dry_tick(self, t_wall: float) -> None:
        """The tick's kernels on scratch copies (nothing sent, no counter advanced): warms
        numba at start and, with a spin window, the caches just before each tick. Measured
        on this project's VMs: a tick after 9 ms asleep takes 80-160 us against 7 us back to
        back; the code and data simply are not in the caches any more."""

        last = self._last_message
        if last is not None:  # a frame just before the tick then decodes hot
            message, index = last
            self.codec.decode(message.arbitration_id, message.data, t_wall,
                              message.is_extended_id, state=self._dry_decode, bus=index)
        self._dry_state[:] = self.state
        self._estimate(t_wall, self._dry_state, self._dry_u, self._dry_out, self._dry_tx, 1)
        for name in TICK_MESSAGES:  # the send path's encode, alive counters untouched
            self.codec.encode_output(name, self._dry_tx, self._dry_payload,
                                     advance_counter=False)
        if self._syscall_warmer is not None:
            sender, receiver = self._syscall_warmer
            sender.send(self._dry_frame)
            receiver.recv(64)

    def restore_state(self) -> str:
        """The persisted elements of the state saved at the last stop (by name; a file saved
        under another state layout is reported and ignored)."""
        slots = self.pipeline.persistent_slots
        if not slots:
            return "state persistence: the estimator keeps nothing across restarts"
        values, message = self.store.load(self.config.estimator, self.pipeline.persistence_hash)
        values, rejected = plausible_state({k: v for k, v in values.items() if k in slots})
        for name, value in values.items():
            self.state[slots[name]] = value
        if rejected:  # a tool's fault: listed in the snapshot too
            reasons = "; ".join(rejected)
            self._remember(self.tool_events, f"state file {self.store.path}: {len(rejected)} "
                           f"saved value(s) rejected, their slots start fresh: {reasons}")
            message = f"{message}; {len(rejected)} of them rejected (start fresh): {reasons}"
        return message

    def save_state(self) -> None:
        slots = self.pipeline.persistent_slots
        if not slots:
            return
        values = {name: float(self.state[index]) for name, index in slots.items()}
        try:
            self.store.save(self.config.estimator, self.pipeline.persistence_hash, values)
        except OSError as exc:
            self.log(f"slipd: cannot save state to {self.store.path}: {exc}")

    # ---- the loop -------------------------------------------------------------------------
    def _on_frame(self, message, index: int = 0) -> None:
        """Decode one frame received on the profile's bus ``index``."""
        if message.is_error_frame or message.is_remote_frame:
            return
        stats = self.stats
        stats.counters["rx_frames"] += 1
        now = time.monotonic()
        self.last_frame_at[index] = now
        frame_id = message.arbitration_id
        stats.count_frame(frame_id)
        timestamp = _microseconds(self._on_time_base(message.timestamp, now, index))
        self.codec.decode(frame_id, message.data, timestamp, message.is_extended_id, bus=index)
        self._last_message = (message, index)
        if self.recorder is not None:
            self.recorder.frame(timestamp, frame_id, message.is_extended_id, message.data,
                                rx=True, channel=self.channels[self.bus_names[index]],
                                fd=message.is_fd, brs=message.bitrate_switch)

    def _on_time_base(self, stamp: float, now: float, index: int) -> float:
        """A kernel receive stamp (wall clock) on the daemon's time base. Around a step of the
        wall clock a stamp can be on either side of it (stamped before the step, read after
        the tick measured it; or the other way round): it is then bounded by what is certain,
        received by ``now`` and not before the bus's previous frame (a socket's stamps are
        in order), so an input's age is never negative and the recording stays in order."""
        t = stamp - self._clock_shift
        newest = now + self._wall_offset
        if t > newest:
            t = newest
        elif t < self._newest_stamp[index]:
            t = self._newest_stamp[index]
        self._newest_stamp[index] = t
        return t

    def _follow_wall_clock(self) -> None:
        """Once a tick: measure the wall clock against CLOCK_MONOTONIC; a step of it is
        counted (clock_steps), reported, and taken off the frames' stamps from now on. Before,
        the start-up offset was used for good: after a step forward every frame looked fresh
        for as long as the step (a stale input VALID), after a step back none ever again."""
        before = time.monotonic()
        wall = time.time()
        after = time.monotonic()
        if after - before > CLOCK_READ_MAX_S:
            return
        shift = wall - 0.5 * (before + after) - self._wall_offset
        step = shift - self._clock_shift
        if abs(step) > CLOCK_STEP_MIN_S:
            self._clock_shift = shift
            self.stats.counters["clock_steps"] += 1
            self._bus_event(f"the wall clock stepped {step:+.3f} s; ticks, input ages and the "
                            f"recording stay on slipd's monotonic time base ({shift:+.3f} s "
                            "from the wall clock now)")

    def _receive_until(self, deadline: float, t_tick: float) -> None:
        """Receive and decode frames until ``deadline`` (CLOCK_MONOTONIC; ``t_tick`` is the
        same instant on the daemon's time base, _on_time_base). A tick that is already
        late still takes what the socket has queued (at most LATE_DRAIN_MAX frames), so after
        an overrun the tick latches the newest inputs instead of starving them; a frame whose
        receive timestamp is after the tick's time waits for the next tick (``_deferred``).

        With a spin window (``RealtimeOptions.spin_us``) the wait ends ``spin`` seconds early
        and the socket is polled without sleeping until the deadline, with a dry run of the
        tick whenever it is empty, so the tick starts on time and hot. One dry run at the start
        of the window was not enough: measured on this project's VMs, 100 us of polling after
        it left the tick as slow as after a sleep, while dry runs up to the deadline brought a
        tick-sized Python workload from 119 to 8 us (median)."""
        if self._deferred is not None:
            (message, index), self._deferred = self._deferred, None
            self._on_frame(message, index)
        recv = self._recv
        late_frames = 0
        spin_from = deadline - self.spin
        # No dry run starts that would overrun the tick: the first in a window runs on cold
        # caches (measured ~160 us against ~20 once warm), so its guard is the last window's
        # first run, halved after each window where it kept every run out (a run stretched
        # by a preemption must not switch the warming off for good).
        dry_cost = self._first_dry_cost
        first_dry = True
        while True:
            now = time.monotonic()
            remaining = deadline - now
            if self.bus_down_since is not None:
                self._try_reopen(deadline)
                return
            if remaining <= 0.0:
                if late_frames >= LATE_DRAIN_MAX:
                    return
                late_frames += 1
                timeout = 0.0
            elif now < spin_from:
                timeout = spin_from - now
            else:
                timeout = 0.0
            try:
                message, index = recv(timeout)
            except (self.can.CanOperationError, OSError) as exc:
                self._bus_failed(exc)
                continue
            if message is not None:
                if remaining <= 0.0 and _microseconds(
                        message.timestamp - self._clock_shift) > t_tick:
                    # Received after the tick's time: it is the next tick's, as a replay of a
                    # bus log latches it, and draining a burst still arriving delayed ticks
                    # by up to a millisecond (measured).
                    self._deferred = (message, index)
                    return
                self._on_frame(message, index)
            elif remaining <= 0.0:
                if first_dry:
                    self._first_dry_cost *= 0.5
                return
            elif timeout == 0.0 and remaining > dry_cost:
                started = time.monotonic()
                self._dry_tick(t_tick)
                dry_cost = time.monotonic() - started
                if first_dry:
                    self._first_dry_cost = dry_cost
                    first_dry = False

    def _recv(self, timeout: float):
        """(message, bus index) from whichever bus has a frame first, or (None, -1) after
        ``timeout``. One bus: its recv. Several: select() on their sockets (SocketCAN,
        slipd_unix), else polling them in turn with short sleeps (python-can's virtual bus)."""
        buses = self.buses
        if len(buses) == 1 or all(b is buses[0] for b in buses):
            return buses[0].recv(timeout=timeout), 0
        return _recv_any(buses, timeout)

    def _bus_failed(self, exc: Exception) -> None:
        if self.bus_down_since is None:
            self.bus_down_since = time.monotonic()
            self._next_reopen = self.bus_down_since + REOPEN_INTERVAL
            names = ", ".join(self.channels.values())
            event = f"bus {names} failed: {exc}; outputs invalid until it is back"
            self._bus_event(event)
            self.notifier.notify(f"STATUS={event}")

    def _try_reopen(self, deadline: float) -> None:
        """After a bus failure: once a second, if the interface exists and is up, reopen it
        (a new socket on the interface as it now is: after a delete and re-create its index
        has changed); meanwhile sleep to the tick."""
        now = time.monotonic()
        if now >= self._next_reopen and self._owns_bus:
            self._next_reopen = now + REOPEN_INTERVAL
            link = all(interface_is_up(c) for c in self.channels.values()) \
                if self.config.interface == "socketcan" else True
            if link:
                for old in self.buses:
                    try:
                        old.shutdown()
                    except Exception:  # noqa: BLE001 - the old socket may already be gone
                        pass
                try:
                    self.buses = [open_bus(self.config, self.plan_ids[k], self.channels[name],
                                           self.fd[k]) for k, name in enumerate(self.bus_names)]
                    self.bus = self.buses[self.output_bus]
                    self._write_frame = frame_writer(self.bus)
                    down = now - self.bus_down_since
                    names = ", ".join(self.channels.values())
                    self._overflow_base += self._overflow_last  # new sockets count from 0
                    self._overflow_last = 0
                    self._bus_event(f"bus {names} reopened after {down:.1f} s")
                    self.bus_down_since = None
                    return
                except (self.can.CanError, OSError, ValueError):
                    pass
        remaining = deadline - time.monotonic()
        if remaining > 0:
            time.sleep(remaining)

    def _send(self, name: str, t_record: float) -> None:
        """Encode output message ``name`` into its frame buffer and send it: written as a
        ``struct can_frame`` where the bus allows it (slipd.daemon.transmit), else as a
        python-can Message."""
        payload = self._payloads[name]
        self.codec.encode_output(name, self.tx, payload)
        if self.listen_only:
            pass  # estimate and record only: nothing goes on the bus
        elif self.bus_down_since is None:
            try:
                if self._write_frame is not None:
                    self._write_frame(self._frames[name])
                else:
                    message = self._messages[name]
                    message.data[:] = payload.tobytes()
                    message.timestamp = t_record
                    self.bus.send(message)
            except (self.can.CanOperationError, OSError) as exc:
                self.stats.counters["tx_errors"] += 1
                # python-can puts the errno in error_code; a full queue loses this frame only
                code = getattr(exc, "errno", None) or getattr(exc, "error_code", None)
                if code not in QUEUE_FULL:
                    self._bus_failed(exc)
        else:
            self.stats.counters["tx_errors"] += 1
        if self.recorder is not None:
            message = self._messages[name]
            self.recorder.frame(t_record, self._frame_ids[name], message.is_extended_id, payload,
                                rx=False, fd=message.is_fd, brs=message.bitrate_switch)

    def _estimate(self, t_wall: float, state: np.ndarray, u: np.ndarray, out: np.ndarray,
                  tx: np.ndarray, steps: int) -> None:
        """Latch -> ``steps`` estimator steps -> supervise -> output slots, on the live arrays
        (tick) or on scratch copies (_dry_tick)."""
        self.codec.sample(t_wall, u)
        self.pipeline.tick(state, u, out, steps)  # steps > 1 after skipped ticks
        if self.bus_down_since is not None:
            out[Out.STATUS] = float((int(out[Out.STATUS]) & ~ST_VALID) | ST_INPUT_TIMEOUT)
        fill_tx(out, self.pipeline.wire_id, tx)

    def tick(self, t_wall: float) -> None:
        """One cycle's work after the wake-up: latch -> step -> supervise -> encode -> send."""
        out = self.out
        self._estimate(t_wall, self.state, self.u, out, self.tx, self.steps)
        self.steps = 1
        verdict = self.pipeline.consistency_flags(self.state)
        if verdict:
            for bit, counter in CONSISTENCY_COUNTED:
                if verdict & bit:
                    self.stats.counters[counter] += 1
        for name in TICK_MESSAGES:
            self._send(name, t_wall)
        status = int(out[Out.STATUS])
        if status & ST_INPUT_TIMEOUT and not self.last_status & ST_INPUT_TIMEOUT:
            self.stats.counters["input_timeouts"] += 1
            self.stats.interval_timeouts += 1
        if status & ST_VALID:
            self.stats.counters["valid_ticks"] += 1
        self.last_status = status

    def _report_miss(self, woke: float, sent: float, cycle_us: float, skipped: int) -> None:
        """Log a deadline miss (in the slack after the tick): when it happened and whether
        the loop woke late or the tick ran long, which tells a stall of the machine from one
        of slipd's. At most one line a second; the misses in between are counted in the next."""
        if sent < self._next_miss_log:
            self._unlogged_misses += 1 + skipped
            return
        self._next_miss_log = sent + 1.0
        earlier = (f"; {self._unlogged_misses} more since the last report"
                   if self._unlogged_misses else "")
        self._unlogged_misses = 0
        tick_ms = (sent - woke) * 1e3
        self.log(f"slipd: deadline miss {sent - self.started_at:.3f} s after start: frames "
                 f"sent {cycle_us / 1e3:.2f} ms after the tick (woke "
                 f"{cycle_us / 1e3 - tick_ms:.2f} ms late, tick {tick_ms:.2f} ms), "
                 f"{skipped} tick(s) skipped{earlier}")

    def _second(self, rx_rejected_before: int) -> int:
        """1 Hz housekeeping: SLIPD_DIAG, systemd status/watchdog, the bus's health (kernel
        drops, silence) and the tools'. Returns the rejected total."""
        stats, tx = self.stats, self.tx
        rejected = self.codec.rejected_total()
        interval = summarize(stats.interval)
        tx[Tx.DEADLINE_MISSES] = min(stats.interval_misses, 63)
        tx[Tx.LATENCY_P50_US] = interval["p50"]
        tx[Tx.LATENCY_P99_US] = interval["p99"]
        tx[Tx.LATENCY_MAX_US] = interval["max"]
        tx[Tx.INPUT_TIMEOUTS] = min(stats.interval_timeouts, 63)
        tx[Tx.RX_ERRORS] = min(rejected - rx_rejected_before, 63)
        self._send("SLIPD_DIAG", time.monotonic() + self._wall_offset)
        status_line = (f"STATUS=beta {math.degrees(self.out[Out.BETA]):+.2f} deg, "
                       f"status {self.last_status:#04x}, cycle p99 "
                       f"{interval['p99']} us, misses "
                       f"{stats.counters['deadline_misses']}")
        healthy = (stats.interval_misses < 50 and self.bus_down_since is None)
        self.notifier.notify(status_line + ("\nWATCHDOG=1" if healthy else ""))
        clear(stats.interval)
        stats.interval_misses = 0
        stats.interval_timeouts = 0
        self._check_bus_health()
        self.server.poll_health()
        if self.recorder is not None:
            self.recorder.maybe_rotate()
        if self.on_second is not None:
            self.on_second(self)
        return rejected

    def _check_bus_health(self) -> None:
        """Frames the kernel dropped (receive queues full), malformed datagrams, and a bus
        that has delivered nothing for ``silence_warning_s``: each logged when it starts."""
        stats = self.stats
        sockets = list({id(bus): bus for bus in self.buses}.values())
        drops = [receive_overflows(bus) for bus in sockets]
        if any(d is not None for d in drops):
            now_dropped = sum(d for d in drops if d is not None)
            total = self._overflow_base + now_dropped
            if total > stats.counters["rx_overflows"]:
                names = ", ".join(self.channels.values())
                self._bus_event(f"bus {names}: the kernel dropped "
                                f"{total - stats.counters['rx_overflows']} frame(s), the "
                                "receive queue was full")
            stats.counters["rx_overflows"] = total
            self._overflow_last = now_dropped
        malformed = sum(getattr(bus, "malformed", 0) for bus in sockets)
        if malformed > stats.counters["rx_malformed"]:
            self._bus_event(f"bus {', '.join(self.channels.values())}: {malformed} received "
                            "datagram(s) were no CAN frame and were dropped")
            stats.counters["rx_malformed"] = malformed
        limit = self.config.silence_warning_s
        if not limit or self.bus_down_since is not None:
            return
        now = time.monotonic()
        for index, name in enumerate(self.bus_names):
            if not self.plan_ids[index]:
                continue  # a bus slipd only sends on
            seen = self.last_frame_at[index]
            last = seen if seen is not None else self.started_at
            channel = self.channels[name]
            if now - last >= limit and not self._silence_reported[index]:
                self._silence_reported[index] = True
                since = ("since start" if seen is None else
                         f"since {seen - self.started_at:.1f} s after start")
                self._bus_event(f"bus {channel}: no frames for {now - last:.0f} s ({since});"
                                " outputs say INPUT_TIMEOUT")
            elif now - last < limit and self._silence_reported[index]:
                self._silence_reported[index] = False
                self._bus_event(f"bus {channel}: frames again")

    def _bus_event(self, event: str) -> None:
        self._remember(self.bus_events, event)
        self.log(f"slipd: {event}")

    def _tool_fault(self, line: str) -> None:
        """A line from a tool (recorder, stats server): logged and listed in the snapshot."""
        self._remember(self.tool_events, line.removeprefix("slipd: "))
        self.log(line)

    def _remember(self, events: list[str], event: str) -> None:
        self._text_version += 1
        events.append(f"{time.monotonic() - self.started_at:.1f} s: {event}"
                      if self.started_at else event)
        if len(events) > EVENTS_KEPT:
            del events[0]
            self.events_dropped += 1

    def _recorder_failed(self) -> None:
        self.stats.counters["recorder_errors"] += 1

    def _text_document(self) -> dict:
        """The snapshot's words (the numbers travel through the shared block)."""
        recorder = None if self.recorder is None else {
            "path": str(self.recorder.path), "status": self.recorder.status}
        return {"estimator": self.config.estimator, "bus_events": list(self.bus_events),
                "tool_events": list(self.tool_events), "events_dropped": self.events_dropped,
                "recorder": recorder}

    def _publish(self, fresh: bool) -> bytes:
        """Answer the stats server (StatsServer.poll): the live numbers into the block's
        published area; the words only when they changed since the last answer (or the
        server is new)."""
        text = None
        if fresh or self._text_sent != self._text_version:
            text = self._text_document()
            self._text_sent = self._text_version
        return self.stats.publish(self.codec.state.errors, text)

    def snapshot(self) -> dict:
        """The whole snapshot, computed here (at the end of a run; tests)."""
        self.stats.decode_errors = self.codec.error_counts()
        return self.stats.snapshot(self._text_document())  # gauges as of the last tick

    def _on_gc(self, phase: str, info: dict) -> None:
        """gc.callbacks hook: every collector pause into the gc_pause_us histogram, so a
        stall in a run without --gc-freeze can be told apart from the machine's."""
        if phase == "start":
            self._gc_started = time.perf_counter()
            return
        self.stats.record("gc_pause_us", (time.perf_counter() - self._gc_started) * 1e6)
        if info.get("generation") == 2:
            self.stats.counters["gc_full_collections"] += 1

    def request_stop(self, *_args) -> None:
        self.running = False

    def run(self) -> dict:
        """Start up, run ticks until stopped, shut down; returns the final snapshot."""
        try:
            self._start_up()
        except BaseException:
            self._close_owned()
            raise
        previous_handlers = self._take_signals()
        gc.callbacks.append(self._on_gc)
        try:
            self._loop()
        finally:
            gc.callbacks.remove(self._on_gc)
            self._shut_down(previous_handlers)
        return self.snapshot()

    def _start_up(self) -> None:
        """Real-time settings, saved state, numba warm-up, the stats server's sockets."""
        config = self.config
        for line in apply_realtime(config.realtime):
            self.log(f"slipd: real-time: {line}")
        self.log(f"slipd: {self.restore_state()}")
        self.notifier.extend_timeout(WARM_UP_ALLOWANCE_S)  # a cold numba cache compiles
        warm = self.warm_up()
        released = release_compiler_pages()
        self.server.wait_ready()
        where = ", ".join(f"{name}={channel}{' (FD)' if fd else ''}" for (name, channel), fd
                          in zip(self.channels.items(), self.fd, strict=True))
        self.log(f"slipd: estimator {config.estimator} on {config.interface} {where}"
                 f"{', listen-only: sending nothing' if self.listen_only else ''}"
                 f", numba warm-up {warm * 1e3:.0f} ms, {released / 2**20:.0f} MB of LLVM "
                 "code released from memory")

    def _take_signals(self) -> dict:
        previous = {}
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGTERM, signal.SIGINT):
                previous[signum] = signal.signal(signum, self.request_stop)
        return previous

    def _loop(self) -> None:
        """Ticks on the absolute 10 ms grid until stopped: receive until the tick, the tick,
        its measurements, then the slack work (after the tick's frames are on the bus)."""
        self.notifier.notify("READY=1\nSTATUS=running")
        self.running = True
        self.ready.set()
        monotonic = time.monotonic
        self.started_at = monotonic()
        wall_offset = self._wall_offset = time.time() - self.started_at
        self._clock_shift = 0.0
        next_tick = self.started_at + TICK_DT
        end = self.started_at + self.config.duration if self.config.duration else math.inf
        slack = _SlackClock(self.started_at)
        while self.running and next_tick <= end:
            self._follow_wall_clock()
            t_tick = _microseconds(next_tick + wall_offset)
            self._receive_until(next_tick, t_tick)
            woke = monotonic()
            self.tick(t_tick)
            sent = monotonic()
            self._measure(next_tick, woke, sent, wall_offset)
            next_tick = self._next_tick(next_tick, woke, sent)
            self._slack_work(sent, slack)

    def _measure(self, tick: float, woke: float, sent: float, wall_offset: float) -> None:
        """One tick into the histograms: cycle (tick -> sent), compute, wake-up lateness and
        the age of the newest yaw-rate frame."""
        stats = self.stats
        if self.first_frame_at is None:
            self.first_frame_at = sent
        stats.counters["ticks"] += 1
        cycle_us = (sent - tick) * 1e6
        stats.record("cycle_latency_us", cycle_us)
        stats.interval.record_value(min(max(1, int(cycle_us)), 60_000_000))
        stats.record("compute_us", (sent - woke) * 1e6)
        stats.record("wakeup_lateness_us", (woke - tick) * 1e6)
        latch = self.codec.state.latch
        if latch[LATCH_SET, In.YAW_RATE] > 0.5:
            stats.record("input_age_us",
                         (tick + wall_offset - latch[LATCH_TIME, In.YAW_RATE]) * 1e6)
        out = self.out  # the snapshot's gauges, written as they change: see SharedStats
        stats.set_gauges(self.last_status, math.degrees(out[Out.BETA]), out[Out.VX],
                         sent - self.started_at)

    def _next_tick(self, tick: float, woke: float, sent: float) -> float:
        """The next tick's time. A tick whose frames were not out before the next tick is a
        miss; ticks whose time has already passed are skipped and counted, never bunched up,
        and the next tick steps the estimator once per elapsed tick."""
        next_tick = tick + TICK_DT
        if sent > next_tick:
            stats = self.stats
            behind = int((sent - next_tick) / TICK_DT)
            stats.counters["deadline_misses"] += 1 + behind
            stats.interval_misses += 1 + behind
            next_tick += behind * TICK_DT
            self.steps = int(catch_up_steps(behind))
            self._report_miss(woke, sent, (sent - tick) * 1e6, behind)
        return next_tick

    def _slack_work(self, sent: float, slack: _SlackClock) -> None:
        """After the tick's frames are out: 1 Hz housekeeping, the stats server's requests,
        the state file every PERSIST_INTERVAL."""
        if sent >= slack.next_second:
            slack.rejected = self._second(slack.rejected)
            slack.next_second += 1.0
        started = time.perf_counter()
        if self.server.poll(self._publish):  # measured: what a snapshot costs the loop
            self.stats.record("stats_answer_us", (time.perf_counter() - started) * 1e6)
        if sent >= slack.next_persist:
            self.save_state()
            slack.next_persist += PERSIST_INTERVAL

    def _shut_down(self, previous_handlers: dict) -> None:
        self.running = False  # also when the loop ended by --duration
        if self._deferred is not None:  # decoded and recorded like every received frame
            self._on_frame(*self._deferred)
            self._deferred = None
        self.save_state()
        for signum, handler in previous_handlers.items():
            signal.signal(signum, handler)
        self.notifier.notify("STOPPING=1")
        self._close_owned()

    def _close_owned(self) -> None:
        """Close what the daemon opened: the stats server, the recorder, the bus."""
        server = getattr(self, "server", None)
        if server is not None:
            server.close()
        if self.recorder is not None:
            self.recorder.close()
        if self._owns_bus:
            for bus in {id(bus): bus for bus in self.buses}.values():
                bus.shutdown()
            self._owns_bus = False
        for end in self._syscall_warmer or ():
            end.close()
        self._syscall_warmer = None


@dataclass
class _SlackClock:
    """When the loop's periodic slack work is next due."""

    started_at: float
    next_second: float = 0.0
    next_persist: float = 0.0
    rejected: int = 0  # input frames rejected up to the last second (SLIPD_DIAG's RX_ERRORS)

    def __post_init__(self) -> None:
        self.next_second = self.started_at + 1.0
        self.next_persist = self.started_at + PERSIST_INTERVAL
