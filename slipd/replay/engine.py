"""The batch engine: a decoded log through the same kernels the daemon runs, at 100 Hz.

frames -> :func:`slipd.codec.kernels.latch_ticks` (decode, latch, sample-and-hold at each
tick) -> :meth:`slipd.pipeline.Pipeline.run` (the method's ``run_ticks``, then supervision).
The daemon calls ``decode_frame``/``sample_latch`` and ``Pipeline.tick`` one tick at a time on
the same arrays, so replaying its flight-recorder log with the recorded tick times gives its
outputs exactly.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slipd.channels import U_LEN
from slipd.codec import Codec, kernels
from slipd.codec.kernels import ERROR_NAMES
from slipd.errors import ConfigError, LogFormatError
from slipd.pipeline import TICK_DT, Pipeline, steps_per_tick
from slipd.profile import Profile, load_profile
from slipd.replay.candump import FLAG_TX, Frames
from slipd.replay.readers import check_time_axis, read_frames


@dataclass
class Inputs:
    """A log decoded and latched onto a tick grid."""

    t: np.ndarray  # tick times, s (log time axis)
    U: np.ndarray  # [n_ticks, U_LEN]
    errors: dict[str, dict[str, int]]
    n_frames: int
    #: estimator steps per tick (pipeline.steps_per_tick: more than one after ticks the daemon
    #: skipped in a recording); None = one each
    steps: np.ndarray | None = None


@dataclass
class Estimate:
    method: str
    t: np.ndarray
    out: np.ndarray  # [n_ticks, N_OUT]


def tick_grid(frames: Frames, dt: float = TICK_DT) -> np.ndarray:
    """Ticks every ``dt`` from the first frame's time to the last (the daemon's 100 Hz)."""
    if len(frames) == 0:
        return np.zeros(0)
    start = frames.t[0] + dt
    count = int(np.floor((frames.t[-1] - frames.t[0]) / dt + 1e-9))
    return start + dt * np.arange(count)


def recorded_ticks(frames: Frames, profile: Profile | None = None
                   ) -> tuple[Frames, np.ndarray, np.ndarray] | None:
    """Ticks of a slipd flight-recorder log: its sent SLIPD_STATE frames (marked T).

    Returns (input frames, tick times, frames latched before each tick), or None when the
    log holds no slipd output. In the recorder, file order is processing order, so a tick
    latches exactly the input lines above its SLIPD_STATE line.
    """
    state_id = Codec.output_plan(profile).frame_id("SLIPD_STATE")
    sent = (frames.flags & FLAG_TX) != 0
    is_output = _recorded_outputs(frames, profile)
    ticks = sent & (frames.frame_id == state_id)
    if not ticks.any():
        return None
    inputs_before = np.cumsum(~is_output) - (~is_output)  # inputs strictly above each line
    tick_until = inputs_before[ticks].astype(np.int64)
    return frames.select(~is_output), frames.t[ticks].copy(), tick_until


def frame_buses(frames: Frames, codec: Codec, bus_map: dict[str, str] | None = None
                ) -> np.ndarray:
    """Each frame's bus index in the profile (-1: a log channel the profile does not read).

    ``bus_map`` maps the profile's bus names to the log's channel names (``--bus
    chassis=can0``). Without one, a bus is the log channel of the same name; a one-bus profile
    reads the one log channel that carries its frames. Two log channels are never merged onto
    one bus (their counters and latches would mix), so an ambiguous log is an error that names
    the channels.
    """
    names = list(frames.channels)
    carrying = _channels_carrying(frames, codec) if _reads_carrying(codec, bus_map, names) \
        else []
    chosen = channel_buses(names, carrying, codec, bus_map, frames.source, len(frames) > 0)
    result = np.full(len(frames), -1, dtype=np.int64)
    for channel, bus in chosen.items():
        result[frames.channel == names.index(channel)] = bus
    return result


def _reads_carrying(codec: Codec, bus_map: dict[str, str] | None, names: list[str]) -> bool:
    """Whether the bus choice looks at which channels carry the profile's frames (a one-bus
    profile, no --bus, no log channel named like the bus)."""
    buses = codec.inputs.buses
    return not bus_map and len(buses) == 1 and buses[0] not in names


def channel_buses(names: list[str], carrying: list[str], codec: Codec,
                  bus_map: dict[str, str] | None, source: str, has_frames: bool,
                  complete: bool = True) -> dict[str, int]:
    """{log channel name: profile bus index} (:func:`frame_buses`'s rule) from the log's
    channel names and those that carry frames of the profile's input IDs. ``complete=False``:
    the log has been read only in part (a streaming replay), so a channel or bus not seen yet
    is not an error yet."""
    buses = codec.inputs.buses
    if bus_map:
        unknown = sorted(set(bus_map) - set(buses))
        if unknown:
            raise ConfigError(f"--bus {unknown[0]}=...: profile {codec.profile.name} has no "
                              f"bus {unknown[0]!r}; its buses: {list(buses)}")
        chosen = dict(bus_map)
    else:
        chosen = {bus: bus for bus in buses if bus in names}
    if len(buses) == 1 and buses[0] not in chosen:
        if len(carrying) > 1:
            raise ConfigError(
                f"{source}: channels {carrying} all carry frames of profile "
                f"{codec.profile.name}'s bus {buses[0]!r}; name the one to read: "
                f"--bus {buses[0]}={carrying[0]}")
        if len(names) == 1 or carrying:
            chosen[buses[0]] = carrying[0] if carrying else names[0]
    missing = [bus for bus in buses if bus not in chosen and bus in codec.profile.buses
               and any(codec.inputs.bus(m) == bus for m in codec.inputs.message_names)]
    if complete and missing and has_frames:
        raise ConfigError(
            f"{source}: no log channel for bus(es) {missing} of profile "
            f"{codec.profile.name}; the log's channels are {names}: map them with "
            f"--bus {missing[0]}=CHANNEL")
    result = {}
    for bus, channel in chosen.items():
        if channel not in names:
            if bus_map and complete:
                raise ConfigError(f"--bus {bus}={channel}: {source} has no channel "
                                  f"{channel!r}; its channels: {names}")
            continue
        result[channel] = buses.index(bus)
    return result


def _channels_carrying(frames: Frames, codec: Codec, skip: set[str] = frozenset()
                       ) -> list[str]:
    """Log channels (but ``skip``) with at least one frame of an input ID of the profile."""
    known = {(codec.inputs.frame_id(n), codec.inputs.is_extended(n))
             for n in codec.inputs.message_names}
    extended = (frames.flags & 1) != 0
    result = []
    for index, name in enumerate(frames.channels):
        if name in skip:
            continue
        on = frames.channel == index
        if any(np.any(on & (frames.frame_id == fid) & (extended == ext)) for fid, ext in known):
            result.append(name)
    return result


def checked_log(frames: Frames, skip_bad: bool = False,
                profile: Profile | None = None) -> Frames:
    """``frames`` with a time axis fit to latch or play (readers.check_time_axis): in a
    flight-recorder log only the received frames are checked, its own frames (``profile``'s
    output IDs) carry tick times (file order is processing order there). An empty log is an
    error: a replay of it would report success over nothing."""
    if len(frames) == 0:
        raise LogFormatError(f"{frames.source}: no CAN frames in it (empty"
                             f"{', or every line skipped' if frames.bad_lines else ''})")
    outputs = _recorded_outputs(frames, profile)
    return check_time_axis(frames, skip_bad, None if not outputs.any() else ~outputs)


def _recorded_outputs(frames: Frames, profile: Profile | None = None) -> np.ndarray:
    """Mask of slipd's own output frames (marked T, on ``profile``'s output IDs) in a log."""
    plan = Codec.output_plan(profile)
    outputs = [plan.frame_id(n) for n in plan.message_names]
    return ((frames.flags & FLAG_TX) != 0) & np.isin(frames.frame_id, outputs)


def latch_log(frames: Frames, profile: Profile, tick_time: np.ndarray | None = None,
              dt: float = TICK_DT, tick_until: np.ndarray | None = None,
              bus_map: dict[str, str] | None = None) -> Inputs:
    """Decode ``frames`` and sample the latch at every tick (``tick_time`` or the grid)."""
    if tick_until is None:
        check_time_axis(frames)  # raises naming the line that goes back or jumps ahead
    codec = Codec(profile)
    ticks = tick_grid(frames, dt) if tick_time is None else np.asarray(tick_time, np.float64)
    U = np.zeros((len(ticks), U_LEN))
    if tick_until is None:
        tick_until = np.searchsorted(frames.t, ticks, side="right").astype(np.int64)
    p, s = codec.inputs, codec.state
    width = max(8, p.max_dlc)
    data = frames.data if frames.data.shape[1] >= width else np.pad(
        frames.data, ((0, 0), (0, width - frames.data.shape[1])))
    buses = frame_buses(frames, codec, bus_map)
    kernels.latch_ticks(p.plan_i, p.plan_f, p.lookup, p.timeouts, codec.channel_timeouts,
                        codec.calibration, frames.t, buses, frames.frame_id, frames.flags,
                        frames.dlc.astype(np.int64), data, ticks, tick_until, s.latch,
                        s.msg_state, s.errors, s.scratch, U)
    return Inputs(ticks, U, codec.error_counts(), len(frames))


def latch_log_or_recording(frames: Frames, profile: Profile,
                           bus_map: dict[str, str] | None = None) -> Inputs:
    """Latch on the recorded ticks of a flight-recorder log, else on the 100 Hz grid."""
    recorded = recorded_ticks(frames, profile)
    if recorded is None:
        return latch_log(frames, profile, bus_map=bus_map)
    inputs, tick_time, tick_until = recorded
    latched = latch_log(inputs, profile, tick_time, tick_until=tick_until, bus_map=bus_map)
    steps = steps_per_tick(tick_time, TICK_DT)
    if np.any(steps > 1):
        latched.steps = steps
    return latched


def run_method(inputs: Inputs, profile: Profile, name: str,
               overrides: dict[str, float] | None = None, dt: float = TICK_DT) -> Estimate:
    """Run method ``name`` over latched inputs; returns its supervised outputs."""
    pipeline = Pipeline(name, profile, overrides, dt)
    return Estimate(name, inputs.t, pipeline.run(inputs.U, inputs.steps))


def run_log(log_path: str | Path, profile: Profile | str, method_names: list[str],
            skip_bad: bool = False, bus_map: dict[str, str] | None = None
            ) -> dict[str, Estimate]:
    """Read, decode and estimate a whole log with each method in ``method_names``."""
    profile = load_profile(profile) if isinstance(profile, str) else profile
    frames = checked_log(read_frames(log_path, skip_bad=skip_bad), skip_bad, profile)
    inputs = latch_log_or_recording(frames, profile, bus_map)
    return {name: run_method(inputs, profile, name) for name in method_names}


__all__ = ["Inputs", "Estimate", "latch_log", "run_method", "run_log", "tick_grid",
           "ERROR_NAMES"]
