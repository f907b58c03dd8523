"""Fast reading and writing of ``candump -L`` logs (numba over the file's bytes).

Line format: ``(SECONDS.FRACTION) CHANNEL ID#DATA [R|T]`` where ID has 3 hex digits
(standard) or 8 (extended), DATA is hex pairs, ``##F`` starts a CAN FD payload with flags
nibble F (bit 0 BRS, bit 1 ESI), ``#R[DLC]`` is a remote frame, and the optional trailing
``R``/``T`` is python-can's receive/transmit marker. Frames equal python-can's
``CanutilsLogReader`` on the same file (tests compare them), including its rule that an ID
with the error flag (0x20000000) and the bus-error class (0x80) is an error frame.

A malformed line raises :class:`LogFormatError` naming file and line; with ``skip_bad=True``
bad lines are counted and their first line numbers kept instead.
"""

from __future__ import annotations

import gzip
import mmap
from dataclasses import dataclass, field
from pathlib import Path

import numba as nb
import numpy as np

from slipd.errors import LogFormatError

FLAG_EXTENDED = 1
FLAG_REMOTE = 2
FLAG_ERROR = 4
FLAG_FD = 8
FLAG_BRS = 16
FLAG_ESI = 32
FLAG_TX = 64  # trailing " T" (python-can: is_rx False)
FLAG_DIRECTION = 128  # the line carried a trailing R/T marker

CAN_ERR_FLAG = 0x20000000
CAN_ERR_BUSERROR = 0x00000080
MAX_CHANNELS = 64

ERROR_REASONS = {
    1: "expected '(' and a timestamp",
    2: "timestamp is not SECONDS.FRACTION",
    3: "expected ') ' after the timestamp",
    4: "expected a channel name",
    5: "expected a hex CAN ID followed by '#'",
    6: "CAN ID has too many digits",
    7: "expected hex data bytes (an even number of hex digits)",
    8: "data longer than 64 bytes",
    9: "unexpected text after the frame (expected R, T or end of line)",
    10: "more than 64 distinct channel names",
    11: "bad CAN FD flags nibble",
    12: "bad remote-frame length",
}


@dataclass
class Frames:
    """A decoded log as parallel arrays (one entry per frame, in file order)."""

    t: np.ndarray  # float64 s
    frame_id: np.ndarray  # int64
    flags: np.ndarray  # uint8, FLAG_*
    dlc: np.ndarray  # uint8: data length in bytes (python-can's dlc)
    data: np.ndarray  # uint8 [n, width]
    channel: np.ndarray  # uint8 index into channels
    channels: list[str]
    source: str = ""
    bad_lines: int = 0
    bad_line_numbers: list[int] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.t)

    def select(self, mask: np.ndarray) -> Frames:
        return Frames(self.t[mask], self.frame_id[mask], self.flags[mask], self.dlc[mask],
                      self.data[mask], self.channel[mask], self.channels, self.source,
                      self.bad_lines, self.bad_line_numbers)


@nb.njit(cache=True)
def _hex(c):
    if 48 <= c <= 57:
        return c - 48
    if 65 <= c <= 70:
        return c - 55
    if 97 <= c <= 102:
        return c - 87
    return -1


@nb.njit(cache=True)
def _parse(buf, width, skip_bad, t_out, id_out, flags_out, dlc_out, data_out, chan_out,
           chan_table, bad_out, fallback_out):
    """Parse every line; returns (n_frames, n_bad, first_error_line, error_code, n_channels,
    needed_width). ``chan_table`` [MAX_CHANNELS, 2] holds (offset, length) of each distinct
    channel name. ``fallback_out`` holds, per frame, the line number of a timestamp with too
    many digits to parse exactly here (Python re-parses those lines), else 0."""
    n = buf.shape[0]
    pos = 0
    line_no = 0
    count = 0
    n_bad = 0
    n_chan = 0
    needed = 0
    while pos < n:
        line_no += 1
        end = pos
        while end < n and buf[end] != 10:
            end += 1
        next_pos = end + 1
        # trim trailing whitespace / CR
        stop = end
        while stop > pos and (buf[stop - 1] == 32 or buf[stop - 1] == 13 or buf[stop - 1] == 9):
            stop -= 1
        p = pos
        while p < stop and (buf[p] == 32 or buf[p] == 9):
            p += 1
        if p >= stop:
            pos = next_pos
            continue
        code = 0
        # ---- timestamp
        int_part = 0
        frac = 0
        frac_digits = 0
        digits = 0
        if buf[p] != 40:
            code = 1
        else:
            p += 1
            while p < stop and 48 <= buf[p] <= 57:
                int_part = int_part * 10 + (buf[p] - 48)
                digits += 1
                p += 1
            if digits == 0 or p >= stop or buf[p] != 46:
                code = 2
            else:
                p += 1
                while p < stop and 48 <= buf[p] <= 57:
                    frac = frac * 10 + (buf[p] - 48)
                    frac_digits += 1
                    p += 1
                if frac_digits == 0:
                    code = 2
                elif p + 1 >= stop or buf[p] != 41 or buf[p + 1] != 32:
                    code = 3
                else:
                    p += 2
        # ---- channel
        chan_start = p
        if code == 0:
            while p < stop and buf[p] == 32:
                p += 1
            chan_start = p
            while p < stop and buf[p] != 32 and buf[p] != 9:
                p += 1
            if p == chan_start or p >= stop:
                code = 4
        chan_len = p - chan_start
        # ---- id
        can_id = 0
        id_digits = 0
        if code == 0:
            while p < stop and buf[p] == 32:
                p += 1
            while p < stop and buf[p] != 35:
                h = _hex(buf[p])
                if h < 0:
                    code = 5
                    break
                can_id = can_id * 16 + h
                id_digits += 1
                p += 1
            if code == 0 and (id_digits == 0 or p >= stop):
                code = 5
            elif code == 0 and id_digits > 8:
                code = 6
            p += 1  # '#'
        flags = 0
        length = 0
        if code == 0:
            if id_digits > 3:
                flags |= 1
            if p < stop and buf[p] == 35:
                flags |= 8
                p += 1
                fd = _hex(buf[p]) if p < stop else -1
                if fd < 0:
                    code = 11
                else:
                    if fd & 1:
                        flags |= 16
                    if fd & 2:
                        flags |= 32
                    p += 1
            if code == 0 and p < stop and (buf[p] == 82 or buf[p] == 114):
                flags |= 2
                p += 1
                while p < stop and 48 <= buf[p] <= 57:
                    length = length * 10 + (buf[p] - 48)
                    p += 1
                if length > 64:
                    code = 12
            elif code == 0:
                while p < stop and buf[p] != 32 and buf[p] != 9:
                    if p + 1 >= stop:
                        code = 7
                        break
                    hi = _hex(buf[p])
                    lo = _hex(buf[p + 1])
                    if hi < 0 or lo < 0:
                        code = 7
                        break
                    if length >= 64:
                        code = 8
                        break
                    if length < width and count < t_out.shape[0]:
                        data_out[count, length] = hi * 16 + lo
                    length += 1
                    p += 2
        if code == 0:
            while p < stop and (buf[p] == 32 or buf[p] == 9):
                p += 1
            if p < stop:
                if p + 1 == stop and (buf[p] == 82 or buf[p] == 114):
                    flags |= 128
                elif p + 1 == stop and (buf[p] == 84 or buf[p] == 116):
                    flags |= 128 | 64
                else:
                    code = 9
        chan_index = -1
        if code == 0:
            for c in range(n_chan):
                off = chan_table[c, 0]
                ln = chan_table[c, 1]
                if ln == chan_len:
                    same = True
                    for j in range(ln):
                        if buf[off + j] != buf[chan_start + j]:
                            same = False
                            break
                    if same:
                        chan_index = c
                        break
            if chan_index < 0:
                if n_chan >= chan_table.shape[0]:
                    code = 10
                else:
                    chan_table[n_chan, 0] = chan_start
                    chan_table[n_chan, 1] = chan_len
                    chan_index = n_chan
                    n_chan += 1
        if code != 0:
            if not skip_bad:
                return count, n_bad, line_no, code, n_chan, needed
            if n_bad < bad_out.shape[0]:
                bad_out[n_bad] = line_no
            n_bad += 1
            # wipe any data bytes written for this line
            if count < t_out.shape[0]:
                for j in range(width):
                    data_out[count, j] = 0
            pos = next_pos
            continue
        if (can_id & 0x20000000) != 0 and (can_id & 0x80) != 0:
            flags = (flags & (128 | 64)) | 4
            can_id = 0
            length = 8 if length == 0 else length
        else:
            can_id &= 0x1FFFFFFF
        if length > needed:
            needed = length
        # (int_part * 10^n + frac) is exact below 2^53, and one division by an exact power
        # of ten is then correctly rounded: the same double as Python's float() of the text.
        scale = 10.0**frac_digits
        exact = digits + frac_digits <= 18 and frac_digits <= 22 and (
            int_part * 10**frac_digits + frac) < 9007199254740992
        t_out[count] = (int_part * scale + frac) / scale
        fallback_out[count] = 0 if exact else line_no
        id_out[count] = can_id
        flags_out[count] = flags
        dlc_out[count] = length
        chan_out[count] = chan_index
        count += 1
        pos = next_pos
    return count, n_bad, 0, 0, n_chan, needed


def _load_bytes(path: Path) -> tuple[np.ndarray, object]:
    if path.suffix == ".gz":
        with gzip.open(path, "rb") as handle:
            return np.frombuffer(handle.read(), dtype=np.uint8), None
    size = path.stat().st_size
    if size == 0:
        return np.zeros(0, dtype=np.uint8), None
    with open(path, "rb") as handle:
        mapped = mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)
    return np.frombuffer(mapped, dtype=np.uint8), mapped


def _error_frame_fixups(frames: Frames) -> None:
    """python-can's reader gives error frames dlc 0 and no data bytes; mirror that."""
    error = (frames.flags & FLAG_ERROR) != 0
    if error.any():
        frames.dlc[error] = 0
        frames.data[error] = 0


def read_candump(path: str | Path, skip_bad: bool = False) -> Frames:
    """Read a ``candump -L`` log (optionally ``.gz``) into :class:`Frames`."""
    path = Path(path)
    if not path.exists():
        raise LogFormatError(f"{path}: no such file")
    buf, mapped = _load_bytes(path)
    error = None
    try:
        return parse_candump(buf, str(path), skip_bad)
    except LogFormatError as exc:  # a fresh one: the parser's frame holds the mapped buffer
        error = LogFormatError(str(exc))
    finally:
        del buf
        if mapped is not None:
            mapped.close()
    raise error


def parse_candump(buf: np.ndarray, source: str, skip_bad: bool = False,
                  first_line: int = 1) -> Frames:
    """The frames of the whole ``candump -L`` lines in ``buf`` (uint8). ``first_line`` is the
    line number of ``buf``'s first line in ``source`` (a piece of a longer log, read in
    chunks by slipd.replay.stream), so errors and skipped lines name the log's own lines.
    Channel indices are this piece's own, in order of first appearance."""
    n_lines = int(np.count_nonzero(buf == 10)) + 1
    width = 8
    shift = first_line - 1
    while True:
        t = np.zeros(n_lines)
        ids = np.zeros(n_lines, dtype=np.int64)
        flags = np.zeros(n_lines, dtype=np.uint8)
        dlc = np.zeros(n_lines, dtype=np.uint8)
        data = np.zeros((n_lines, width), dtype=np.uint8)
        chan = np.zeros(n_lines, dtype=np.uint8)
        chan_table = np.zeros((MAX_CHANNELS, 2), dtype=np.int64)
        bad = np.zeros(100, dtype=np.int64)
        fallback = np.zeros(n_lines, dtype=np.int64)
        count, n_bad, err_line, err_code, n_chan, needed = _parse(
            buf, width, skip_bad, t, ids, flags, dlc, data, chan, chan_table, bad, fallback)
        if err_code:
            line = bytes(_line_text(buf, err_line)).decode("utf-8", "replace")
            raise LogFormatError(
                f"{source}:{err_line + shift}: {ERROR_REASONS.get(err_code, 'malformed line')}: "
                f"{line!r} (use --skip-bad to count and skip such lines)"
            )
        if needed <= width:
            break
        width = 64
    names = [bytes(buf[o:o + n]).decode("ascii", "replace") for o, n in chan_table[:n_chan]]
    if fallback[:count].any():
        line_starts = np.concatenate(([0], np.flatnonzero(buf == 10) + 1))
        for index in np.flatnonzero(fallback[:count]):
            t[index] = _python_timestamp(buf, line_starts, int(fallback[index]))
    frames = Frames(t[:count], ids[:count], flags[:count], dlc[:count], data[:count],
                    chan[:count], names, source, int(n_bad),
                    [int(x) + shift for x in bad[:min(n_bad, 100)]])
    _error_frame_fixups(frames)
    return frames


def _line_text(buf: np.ndarray, line_no: int) -> np.ndarray:
    newlines = np.flatnonzero(buf == 10)
    start = 0 if line_no == 1 else int(newlines[line_no - 2]) + 1
    end = int(newlines[line_no - 1]) if line_no - 1 < len(newlines) else len(buf)
    return buf[start:end][:200]


def _python_timestamp(buf: np.ndarray, line_starts: np.ndarray, line_no: int) -> float:
    """Exact timestamp of line ``line_no`` for the rare line with > 15 digits."""
    start = int(line_starts[line_no - 1])
    end = int(line_starts[line_no]) - 1 if line_no < len(line_starts) else len(buf)
    line = bytes(buf[start:end]).decode("ascii", "replace").strip()
    return float(line[1:line.index(")")])


@nb.njit(cache=True)
def _format(micros, frame_id, flags, dlc, data, chan, chan_bytes, chan_offsets, out):
    """Write candump lines into ``out`` (uint8); returns bytes used."""
    hexd = b"0123456789ABCDEF"
    p = 0
    digits = np.zeros(24, dtype=np.uint8)
    for k in range(micros.shape[0]):
        value = micros[k]
        seconds = value // 1000000
        fraction = value % 1000000
        out[p] = 40
        p += 1
        n = 0
        if seconds == 0:
            digits[0] = 48
            n = 1
        while seconds > 0:
            digits[n] = 48 + seconds % 10
            seconds //= 10
            n += 1
        for j in range(n - 1, -1, -1):
            out[p] = digits[j]
            p += 1
        out[p] = 46
        p += 1
        for j in range(5, -1, -1):
            out[p + j] = 48 + fraction % 10
            fraction //= 10
        p += 6
        out[p] = 41
        out[p + 1] = 32
        p += 2
        c = chan[k]
        for j in range(chan_offsets[c], chan_offsets[c + 1]):
            out[p] = chan_bytes[j]
            p += 1
        out[p] = 32
        p += 1
        f = flags[k]
        ident = frame_id[k]
        id_digits = 8 if f & 1 else 3
        if f & 4:
            ident = 0x20000080
            id_digits = 8
        for j in range(id_digits - 1, -1, -1):
            out[p + j] = hexd[ident & 15]
            ident >>= 4
        p += id_digits
        out[p] = 35
        p += 1
        if f & 2:
            out[p] = 82
            p += 1
        elif not (f & 4):
            if f & 8:
                out[p] = 35
                out[p + 1] = hexd[((f >> 4) & 1) | (((f >> 5) & 1) << 1)]
                p += 2
            for j in range(dlc[k]):
                b = data[k, j]
                out[p] = hexd[b >> 4]
                out[p + 1] = hexd[b & 15]
                p += 2
        if f & 128 and not (f & 4):
            out[p] = 32
            out[p + 1] = 84 if f & 64 else 82
            p += 2
        out[p] = 10
        p += 1
    return p


def write_candump(path: str | Path, t: np.ndarray, frame_id: np.ndarray, data: np.ndarray,
                  dlc: np.ndarray | None = None, interface: str = "can0",
                  flags: np.ndarray | None = None, channel: np.ndarray | None = None,
                  channels: list[str] | None = None, append: bool = False) -> int:
    """Write frames as ``candump -L`` lines; timestamps are rounded to microseconds.

    ``channel``/``channels`` give a per-frame interface name (default: ``interface``).
    Without ``flags``, frames longer than 8 bytes are written as CAN FD frames. ``append``
    adds the lines to an existing file (a streaming replay writes chunk by chunk).
    Returns the number of lines written.
    """
    n = len(t)
    data = np.ascontiguousarray(data, dtype=np.uint8).reshape(n, -1)
    dlc = np.full(n, data.shape[1], np.uint8) if dlc is None else np.asarray(dlc, np.uint8)
    # a payload longer than 8 bytes exists only as a CAN FD frame ("##F" in candump)
    flags = (np.where(dlc > 8, FLAG_FD, 0).astype(np.uint8) if flags is None
             else np.asarray(flags, np.uint8))
    names = channels or [interface]
    chan = np.zeros(n, np.uint8) if channel is None else np.asarray(channel, np.uint8)
    encoded = [name.encode("ascii") for name in names]
    chan_bytes = np.frombuffer(b"".join(encoded), dtype=np.uint8) if encoded else np.zeros(0)
    chan_offsets = np.concatenate([[0], np.cumsum([len(e) for e in encoded])]).astype(np.int64)
    micros = np.round(np.asarray(t, dtype=np.float64) * 1e6).astype(np.int64)
    if (micros < 0).any():
        raise ValueError("candump timestamps must be >= 0")
    longest = max(len(e) for e in encoded)
    out = np.empty(n * (40 + longest + 2 * 64 + 4), dtype=np.uint8)
    used = _format(micros, np.asarray(frame_id, np.int64), flags, dlc, data, chan,
                   chan_bytes, chan_offsets, out)
    with open(path, "ab" if append else "wb") as handle:
        handle.write(out[:used].data)
    return n
