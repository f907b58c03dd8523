"""Log readers by file suffix: candump (fast path) or python-can's LogReader for the rest,
and the checks a log's time axis must pass before frames are latched or played."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from slipd.errors import LogFormatError
from slipd.replay.candump import Frames, read_candump

CANDUMP_SUFFIXES = (".log", ".candump")
LIBRARY_SUFFIXES = (".asc", ".blf", ".trc", ".mf4", ".csv")
#: Longest gap between two frames of one log: a 100 Hz tick grid over a bigger one would be
#: millions of ticks of nothing (one frame 1e6 s after the rest once asked for 42 GiB).
MAX_GAP_S = 24 * 3600.0


def read_frames(path: str | Path, skip_bad: bool = False) -> Frames:
    """Read any supported log into :class:`Frames` (candump natively, others via python-can)."""
    path = Path(path)
    suffixes = "".join(path.suffixes[-2:]) if path.suffix == ".gz" else path.suffix
    base_suffix = suffixes.removesuffix(".gz")
    if base_suffix in CANDUMP_SUFFIXES or base_suffix == "":
        return read_candump(path, skip_bad=skip_bad)
    if suffixes == ".mf4":  # bus-logging MF4 as whole arrays (slipd.replay.mf4)
        from slipd.replay.mf4 import read_mf4

        return read_mf4(path)
    if base_suffix in LIBRARY_SUFFIXES:
        return _read_with_python_can(path)
    raise LogFormatError(f"{path}: unknown log format {suffixes!r}; expected "
                         f"{CANDUMP_SUFFIXES + LIBRARY_SUFFIXES} (optionally .gz)")


def python_can_errors() -> tuple[type[BaseException], ...]:
    """What python-can's readers raise on a bad file (python-can imported when needed)."""
    import can
    from can.io.blf import BLFParseError

    return (ValueError, OSError, EOFError, IndexError, KeyError, struct.error, zlib.error,
            BLFParseError, can.CanError)


def _read_with_python_can(path: Path) -> Frames:
    import can

    from slipd.replay.messages import frames_from_messages

    try:
        frames = frames_from_messages(can.LogReader(str(path)), source=str(path))
    except python_can_errors() as exc:
        raise LogFormatError(f"{path}: python-can cannot read it: "
                             f"{type(exc).__name__}: {exc}") from exc
    frames.line = np.arange(1, len(frames) + 1, dtype=np.int64)  # record numbers
    return frames


def check_time_axis(frames: Frames, skip_bad: bool = False,
                    checked: np.ndarray | None = None) -> Frames:
    """Frames whose times a tick grid or a player can follow: each at or after the one
    before, no gap over MAX_GAP_S. A frame that breaks this is a LogFormatError naming its
    line and the line it is compared with; with ``skip_bad`` it is dropped and counted with
    the malformed lines (and the next frame is compared with the last one kept).
    ``checked``: a mask of the frames to check (the others are kept as they are)."""
    subset = np.flatnonzero(checked) if checked is not None else np.arange(len(frames))
    t = frames.t[subset]
    if len(t) == 0:
        return frames
    step = np.diff(t)
    if np.isfinite(t).all() and np.all((step >= 0) & (step <= MAX_GAP_S)):
        return frames
    keep = np.ones(len(frames), dtype=bool)
    last = -1  # the last frame kept (an index into frames)
    for index in subset:
        value = frames.t[index]
        fits = np.isfinite(value) and (last < 0 or
                                       frames.t[last] <= value <= frames.t[last] + MAX_GAP_S)
        if fits:
            last = index
            continue
        if not skip_bad:
            raise LogFormatError(_time_axis_reason(frames, index, last))
        keep[index] = False
    dropped = frames.line[~keep] if frames.line is not None else np.flatnonzero(~keep) + 1
    kept = frames.select(keep)
    kept.bad_lines = frames.bad_lines + int(np.count_nonzero(~keep))
    kept.bad_line_numbers = sorted(frames.bad_line_numbers + [int(x) for x in dropped])[:100]
    return kept


def _time_axis_reason(frames: Frames, index: int, last: int) -> str:
    value = frames.t[index]
    if not np.isfinite(value):
        return f"{frames.where(index)}: timestamp {value} is not a finite number"
    before = frames.where(last).removeprefix(f"{frames.source}:").removeprefix(
        f"{frames.source} ")
    if value < frames.t[last]:
        return (f"{frames.where(index)}: timestamp {value:.6f} goes back in time (line "
                f"{before} has {frames.t[last]:.6f}); sort the log, or --skip-bad drops such "
                "frames")
    return (f"{frames.where(index)}: timestamp {value:.6f} is {value - frames.t[last]:.0f} s "
            f"after line {before}, more than {MAX_GAP_S:.0f} s: the 100 Hz tick grid would "
            f"need {(value - frames.t[last]) * 100:.3g} ticks; split the log there, or "
            "--skip-bad drops such frames")
