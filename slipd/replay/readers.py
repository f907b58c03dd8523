"""Log readers by file suffix: candump (fast path) or python-can's LogReader for the rest."""

from __future__ import annotations

from pathlib import Path

from slipd.errors import LogFormatError
from slipd.replay.candump import Frames, read_candump

CANDUMP_SUFFIXES = (".log", ".candump")
LIBRARY_SUFFIXES = (".asc", ".blf", ".trc", ".mf4", ".csv")


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


def _read_with_python_can(path: Path) -> Frames:
    import can

    from slipd.replay.messages import frames_from_messages

    try:
        return frames_from_messages(can.LogReader(str(path)), source=str(path))
    except (ValueError, OSError) as exc:
        raise LogFormatError(f"{path}: python-can cannot read it: {exc}") from exc
