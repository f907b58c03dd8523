"""Fast reading and writing of ``candump -L`` logs (numba over the file's bytes).

Line format: ``(SECONDS.FRACTION) CHANNEL ID#DATA [R|T]`` where ID has 3 hex digits
(standard) or 8 (extended), DATA is hex pairs, ``##F`` starts a CAN FD payload with flags
nibble F (bit 0 BRS, bit 1 ESI, bit 2 FDF: Linux sets CANFD_FDF on every FD frame since
6.x, so its candump writes ``##5`` for a BRS frame), ``#R[DLC]`` is a remote frame, and the
optional trailing ``R``/``T`` is python-can's receive/transmit marker. Frames equal python-can's
``CanutilsLogReader`` on the same file (tests compare them), with two departures: an ID
with the error flag (0x20000000) is an error frame whatever its error classes (python-can
also asks for the bus-error class 0x80 and otherwise reads the class bits as an ID), and
lines a bus cannot carry are malformed, not accepted (python-can reads them): classic frames
over 8 bytes, CAN FD lengths between the DLC steps, remote DLCs over 8, a 3-digit ID above
7FF, flag bits other than the error flag above a 29-bit ID.

A malformed line raises :class:`LogFormatError` naming file and line; with ``skip_bad=True``
bad lines are counted and their first line numbers kept instead.
"""

from __future__ import annotations

import gzip
import mmap
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slipd.errors import LogFormatError
from slipd.numba_cache import nb

FLAG_EXTENDED = 1
FLAG_REMOTE = 2
FLAG_ERROR = 4
FLAG_FD = 8
FLAG_BRS = 16
FLAG_ESI = 32
FLAG_TX = 64  # trailing " T" (python-can: is_rx False)
FLAG_DIRECTION = 128  # the line carried a trailing R/T marker

CAN_ERR_FLAG = 0x20000000
MAX_CHANNELS = 64
MAX_SECONDS_DIGITS = 12  # epoch seconds have 10; more is no clock a CAN logger has

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
    11: "bad CAN FD flags nibble (expected 0-7: BRS, ESI, FDF)",
    12: "bad remote frame (a DLC of 0-8, and CAN FD has none)",
    13: f"timestamp has more than {MAX_SECONDS_DIGITS} digits of seconds",
    14: "a 3-digit (standard) CAN ID above 7FF",
    15: "CAN ID above 1FFFFFFF (only the error flag 20000000 may be set above it)",
    16: "CAN FD data length is not one a bus carries (0-8, 12, 16, 20, 24, 32, 48, 64)",
    17: "classic CAN frame with more than 8 data bytes (CAN FD is written ID##F...)",
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
    #: int64 line number (candump) or record number (other formats, from 1) of each frame
    line: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.t)

    def where(self, index: int) -> str:
        """``FILE:LINE`` of frame ``index`` (``FILE frame N`` when lines are not known)."""
        if self.line is not None:
            return f"{self.source}:{int(self.line[index])}"
        return f"{self.source} frame {index + 1}"

    def select(self, mask: np.ndarray) -> Frames:
        return Frames(self.t[mask], self.frame_id[mask], self.flags[mask], self.dlc[mask],
                      self.data[mask], self.channel[mask], self.channels, self.source,
                      self.bad_lines, self.bad_line_numbers,
                      None if self.line is None else self.line[mask])


@nb.njit(cache=True, _nrt=False)
def _hex(c):
    if 48 <= c <= 57:
        return c - 48
    if 65 <= c <= 70:
        return c - 55
    if 97 <= c <= 102:
        return c - 87
    return -1


# Stage results: (error code or 0, position after the field, values...). Every stage reads
# the line's bytes ``buf[p:stop]`` (trailing blanks and CR trimmed) and never looks beyond.


@nb.njit(cache=True, _nrt=False)
def _scan_timestamp(buf, p, stop):
    """``(SECONDS.FRACTION) ``: (code, p, int_part, frac, int_digits, frac_digits, approx).

    ``approx`` is the value as a double (exact when the caller's exactness test passes; a
    long fraction is summed from its first 17 digits); seconds have at most
    MAX_SECONDS_DIGITS digits (epoch seconds have 10), which keeps ``int_part`` exact."""
    int_part = 0
    frac = 0
    digits = 0
    frac_digits = 0
    approx_frac = 0.0
    weight = 0.1
    if buf[p] != 40:
        return 1, p, 0, 0, 0, 0, 0.0
    p += 1
    while p < stop and 48 <= buf[p] <= 57:
        if digits < MAX_SECONDS_DIGITS:
            int_part = int_part * 10 + (buf[p] - 48)
        digits += 1
        p += 1
    if digits > MAX_SECONDS_DIGITS:
        return 13, p, 0, 0, 0, 0, 0.0
    if digits == 0 or p >= stop or buf[p] != 46:
        return 2, p, 0, 0, 0, 0, 0.0
    p += 1
    while p < stop and 48 <= buf[p] <= 57:
        if frac_digits < 18:
            frac = frac * 10 + (buf[p] - 48)
        if frac_digits < 17:
            approx_frac += (buf[p] - 48) * weight
            weight *= 0.1
        frac_digits += 1
        p += 1
    if frac_digits == 0:
        return 2, p, 0, 0, 0, 0, 0.0
    if p + 1 >= stop or buf[p] != 41 or buf[p + 1] != 32:
        return 3, p, 0, 0, 0, 0, 0.0
    return 0, p + 2, int_part, frac, digits, frac_digits, int_part + approx_frac


@nb.njit(cache=True, _nrt=False)
def _scan_channel(buf, p, stop):
    """The interface name: (code, p, start, length)."""
    while p < stop and buf[p] == 32:
        p += 1
    start = p
    while p < stop and buf[p] != 32 and buf[p] != 9:
        p += 1
    if p == start or p >= stop:
        return 4, p, start, 0
    return 0, p, start, p - start


@nb.njit(cache=True, _nrt=False)
def _scan_id(buf, p, stop):
    """``ID#``: (code, p after '#', can_id, digits). Three digits are a standard ID (at most
    7FF), more an extended one; 8 digits may carry the error flag (an error frame); the RTR
    and EFF flag bits are not part of an ID and are refused, not masked away."""
    while p < stop and buf[p] == 32:
        p += 1
    can_id = 0
    digits = 0
    while p < stop and buf[p] != 35:
        h = _hex(buf[p])
        if h < 0:
            return 5, p, 0, 0
        can_id = can_id * 16 + h
        digits += 1
        p += 1
    if digits == 0 or p >= stop:
        return 5, p, 0, 0
    if digits > 8:
        return 6, p, 0, 0
    if digits <= 3 and can_id > 0x7FF:
        return 14, p, 0, 0
    if can_id > 0x1FFFFFFF and (can_id & ~0x3FFFFFFF) != 0:
        return 15, p, 0, 0
    return 0, p + 1, can_id, digits


@nb.njit(cache=True, _nrt=False)
def _valid_fd_length(length):
    return length <= 8 or length == 12 or length == 16 or length == 20 or length == 24 or \
        length == 32 or length == 48 or length == 64


@nb.njit(cache=True, _nrt=False)
def _scan_payload(buf, p, stop, width, row, data_out):
    """After ``#``: an FD flags nibble (``#F``), a remote frame (``R[DLC]``) or hex data
    bytes written into ``data_out[row]`` (when ``row`` is in range and the byte fits
    ``width``). Returns (code, p, flags, length); lengths a bus cannot carry are refused:
    classic data over 8 bytes, FD lengths between the DLC steps, a remote DLC over 8."""
    flags = 0
    length = 0
    if p < stop and buf[p] == 35:
        flags |= FLAG_FD
        p += 1
        fd = _hex(buf[p]) if p < stop else -1
        if fd < 0 or fd > 7:  # bit 3 is no flag of struct canfd_frame
            return 11, p, 0, 0
        if fd & 1:
            flags |= FLAG_BRS
        if fd & 2:
            flags |= FLAG_ESI
        p += 1
    if p < stop and (buf[p] == 82 or buf[p] == 114):
        if flags & FLAG_FD:
            return 12, p, 0, 0  # CAN FD has no remote frames
        flags |= FLAG_REMOTE
        p += 1
        while p < stop and 48 <= buf[p] <= 57:
            length = length * 10 + (buf[p] - 48)
            if length > 8:
                return 12, p, 0, 0
            p += 1
        return 0, p, flags, length
    while p < stop and buf[p] != 32 and buf[p] != 9:
        if p + 1 >= stop:
            return 7, p, 0, 0
        hi = _hex(buf[p])
        lo = _hex(buf[p + 1])
        if hi < 0 or lo < 0:
            return 7, p, 0, 0
        if length >= 64:
            return 8, p, 0, 0
        if length < width and row < data_out.shape[0]:
            data_out[row, length] = hi * 16 + lo
        length += 1
        p += 2
    if flags & FLAG_FD:
        if not _valid_fd_length(length):
            return 16, p, 0, 0
    elif length > 8:
        return 17, p, 0, 0
    return 0, p, flags, length


@nb.njit(cache=True, _nrt=False)
def _scan_marker(buf, p, stop):
    """Optional trailing ``R``/``T`` (python-can's direction): (code, flags)."""
    while p < stop and (buf[p] == 32 or buf[p] == 9):
        p += 1
    if p >= stop:
        return 0, 0
    if p + 1 == stop and (buf[p] == 82 or buf[p] == 114):
        return 0, FLAG_DIRECTION
    if p + 1 == stop and (buf[p] == 84 or buf[p] == 116):
        return 0, FLAG_DIRECTION | FLAG_TX
    return 9, 0


@nb.njit(cache=True, _nrt=False)
def _same_bytes(buf, a, b, length):
    """``buf[a:a+length] == buf[b:b+length]``."""
    for j in range(length):
        if buf[a + j] != buf[b + j]:
            return False
    return True


@nb.njit(cache=True, _nrt=False)
def _channel_index(buf, start, length, chan_table, n_chan):
    """Index of the channel name ``buf[start:start+length]`` in ``chan_table``, added when
    new: (code, index, n_chan)."""
    for c in range(n_chan):
        off = chan_table[c, 0]
        if chan_table[c, 1] != length:
            continue
        same = True
        for j in range(length):
            if buf[off + j] != buf[start + j]:
                same = False
                break
        if same:
            return 0, c, n_chan
    if n_chan >= chan_table.shape[0]:
        return 10, -1, n_chan
    chan_table[n_chan, 0] = start
    chan_table[n_chan, 1] = length
    return 0, n_chan, n_chan + 1


@nb.njit(cache=True, _nrt=False)
def _line_bounds(buf, pos):
    """(first non-blank byte, end after trimming blanks/CR, start of the next line)."""
    n = buf.shape[0]
    end = pos
    while end < n and buf[end] != 10:
        end += 1
    stop = end
    while stop > pos and (buf[stop - 1] == 32 or buf[stop - 1] == 13 or buf[stop - 1] == 9):
        stop -= 1
    p = pos
    while p < stop and (buf[p] == 32 or buf[p] == 9):
        p += 1
    return p, stop, end + 1


#: hex digit value of each byte, -1 for a byte that is none
_HEX_VALUE = np.full(256, -1, dtype=np.int64)
for _k, _c in enumerate(b"0123456789ABCDEF"):
    _HEX_VALUE[_c] = _k
for _k, _c in enumerate(b"abcdef"):
    _HEX_VALUE[_c] = 10 + _k
#: exact powers of ten (the timestamp's fraction scale)
_POW10_INT = np.array([10**k for k in range(19)], dtype=np.int64)
_POW10_FLOAT = np.array([10.0**k for k in range(19)])


@nb.njit(cache=True, _nrt=False)
def _decimal(buf, p, most):
    """The decimal digits from ``p``: (value, count, position after them), reading at most
    ``most`` + 1 digits (a count over ``most`` means too many)."""
    value = 0
    count = 0
    while p < buf.shape[0] and 48 <= buf[p] <= 57 and count <= most:
        value = value * 10 + (buf[p] - 48)
        count += 1
        p += 1
    return value, count, p


@nb.njit(cache=True, _nrt=False)
def _scan_plain_line(buf, pos, width, row, data_out):
    """The common line in one pass: ``(SECONDS.FRACTION) CHANNEL ID#HEXDATA`` then a newline
    (or the buffer's end), one blank between the fields, a classic data frame of at most 8
    bytes whose timestamp the exact formula covers. Returns (ok, next line's start,
    int_part, frac, int_digits, frac_digits, channel start, channel length, can_id,
    id_digits, length), data bytes written into ``data_out[row]``. Any other line (``ok`` 0)
    goes through the general stages of :func:`_parse`, which accept a superset of these
    lines and read them to the same values (tests/test_candump.py holds the two equal)."""
    n = buf.shape[0]
    p = pos
    if p >= n or buf[p] != 40 or row >= data_out.shape[0] or width < 8:
        return 0, pos, 0, 0, 0, 0, 0, 0, 0, 0, 0
    int_part, digits, p = _decimal(buf, p + 1, MAX_SECONDS_DIGITS)
    if digits == 0 or digits > MAX_SECONDS_DIGITS or p >= n or buf[p] != 46:
        return 0, pos, 0, 0, 0, 0, 0, 0, 0, 0, 0
    frac, frac_digits, p = _decimal(buf, p + 1, 18 - digits)  # exact below 19 digits
    if frac_digits == 0 or frac_digits > 18 - digits or p + 1 >= n or buf[p] != 41 or \
            buf[p + 1] != 32:
        return 0, pos, 0, 0, 0, 0, 0, 0, 0, 0, 0
    if int_part * _POW10_INT[frac_digits] + frac >= 2**53:
        return 0, pos, 0, 0, 0, 0, 0, 0, 0, 0, 0
    p += 2
    chan_start = p
    while p < n and buf[p] > 32:
        p += 1
    chan_len = p - chan_start
    if chan_len == 0 or p >= n or buf[p] != 32:
        return 0, pos, 0, 0, 0, 0, 0, 0, 0, 0, 0
    p += 1
    can_id = 0
    id_digits = 0
    while p < n and buf[p] != 35:
        h = _HEX_VALUE[buf[p]]
        if h < 0 or id_digits == 8:
            return 0, pos, 0, 0, 0, 0, 0, 0, 0, 0, 0
        can_id = can_id * 16 + h
        id_digits += 1
        p += 1
    if id_digits == 0 or p >= n or can_id > 0x1FFFFFFF or (id_digits <= 3 and can_id > 0x7FF):
        return 0, pos, 0, 0, 0, 0, 0, 0, 0, 0, 0
    p += 1
    length = 0
    while p < n and buf[p] != 10:
        if p + 1 >= n or length == 8:
            return 0, pos, 0, 0, 0, 0, 0, 0, 0, 0, 0
        hi = _HEX_VALUE[buf[p]]
        lo = _HEX_VALUE[buf[p + 1]]
        if hi < 0 or lo < 0:
            return 0, pos, 0, 0, 0, 0, 0, 0, 0, 0, 0
        data_out[row, length] = hi * 16 + lo
        length += 1
        p += 2
    return (1, p + 1, int_part, frac, digits, frac_digits, chan_start, chan_len, can_id,
            id_digits, length)


#: decimal digit value of each byte, -1 for a byte that is none
_DEC_VALUE = np.full(256, -1, dtype=np.int64)
for _k, _c in enumerate(b"0123456789"):
    _DEC_VALUE[_c] = _k


@nb.njit(cache=True, inline="always")
def _scan_known_shape(buf, pos, digits, frac_digits, chan_start, chan_len, row, data_out):
    """The common line when it has the shape of the line before: ``digits`` and
    ``frac_digits`` digits of timestamp and the channel name ``buf[chan_start:][:chan_len]``
    at fixed places, then a 3- or 8-digit ID and at most 8 data bytes to the newline (or the
    buffer's end). No branch per digit: the bytes' values are or-ed, a non-digit makes the
    result negative. Returns (ok, next line's start, int_part, frac, this line's channel
    start, can_id, id_digits, length), data bytes written into ``data_out[row]`` (wiped again
    when ``ok`` is 0; the caller's scans take such a line). The caller's shape comes from a
    line :func:`_scan_plain_line` read, so the exact-timestamp bound holds but for the size
    of the seconds, checked here; any line this reads, that one reads to the same values
    (tests/test_candump.py)."""
    n = buf.shape[0]
    dot = pos + 1 + digits
    close = dot + 1 + frac_digits
    here = close + 2  # this line's channel
    q = here + chan_len + 1  # the ID's first digit
    if q + 4 > n or row >= data_out.shape[0] or buf[pos] != 40 or buf[dot] != 46 or \
            buf[close] != 41 or buf[close + 1] != 32 or buf[q - 1] != 32:
        return 0, pos, 0, 0, 0, 0, 0, 0
    for j in range(chan_len):
        if buf[here + j] != buf[chan_start + j]:
            return 0, pos, 0, 0, 0, 0, 0, 0
    bad = 0
    int_part = 0
    for j in range(pos + 1, dot):
        d = _DEC_VALUE[buf[j]]
        bad |= d
        int_part = int_part * 10 + d
    frac = 0
    for j in range(dot + 1, close):
        d = _DEC_VALUE[buf[j]]
        bad |= d
        frac = frac * 10 + d
    if buf[q + 3] == 35:
        id_digits = 3
    elif q + 8 < n and buf[q + 8] == 35:
        id_digits = 8
    else:
        return 0, pos, 0, 0, 0, 0, 0, 0
    can_id = 0
    for j in range(q, q + id_digits):
        h = _HEX_VALUE[buf[j]]
        bad |= h
        can_id = can_id * 16 + h
    if bad < 0 or can_id > (0x7FF if id_digits == 3 else 0x1FFFFFFF) or \
            int_part * _POW10_INT[frac_digits] + frac >= 2**53:
        return 0, pos, 0, 0, 0, 0, 0, 0
    p = q + id_digits + 1
    length = 0
    while p < n and buf[p] != 10 and length < 8 and p + 1 < n:
        hi = _HEX_VALUE[buf[p]]
        lo = _HEX_VALUE[buf[p + 1]]
        bad |= hi | lo
        data_out[row, length] = hi * 16 + lo
        length += 1
        p += 2
    if bad < 0 or (p < n and buf[p] != 10):
        for j in range(length):
            data_out[row, j] = 0
        return 0, pos, 0, 0, 0, 0, 0, 0
    return 1, p + 1, int_part, frac, here, can_id, id_digits, length


@nb.njit(cache=True, nogil=True, _nrt=False)
def _parse(buf, width, skip_bad, t_out, id_out, flags_out, dlc_out, data_out, chan_out,
           line_out, chan_table, bad_out, fallback_out, line_shift=0, one_pass=True,
           known_shape=True):
    """Parse every line; returns (n_frames, n_bad, first_error_line, error_code, n_channels,
    needed_width, n_fallback). ``chan_table`` [MAX_CHANNELS, 2] holds (offset, length) of
    each distinct channel name. ``line_out`` gets each frame's line number plus
    ``line_shift`` (the line before ``buf`` in its log). ``fallback_out`` gets the first
    frames (indices) whose timestamp has too many digits to parse exactly here (Python
    re-parses those lines; ``n_fallback`` counts them all, a caller with a short array parses
    again with a longer one). Error frames get python-can's dlc 0 and no data bytes here.
    ``one_pass``/``known_shape`` False skip the one-pass scans (tests: the same frames)."""
    n = buf.shape[0]
    pos = 0
    line_no = 0
    count = 0
    n_bad = 0
    n_chan = 0
    needed = 0
    last_chan = -1
    last_start = 0
    last_len = 0
    n_fallback = 0
    shape_digits = -1  # the timestamp's digits of the last line a one-pass scan read
    shape_frac = 0
    while pos < n:
        line_no += 1
        flags = 0
        approx = 0.0
        known = 0
        if known_shape and shape_digits >= 0 and last_chan >= 0 and width >= 8:
            (known, next_pos, int_part, frac, chan_start, can_id, id_digits,
             length) = _scan_known_shape(buf, pos, shape_digits, shape_frac, last_start,
                                         last_len, count, data_out)
        if known:
            digits = shape_digits
            frac_digits = shape_frac
            chan_len = last_len
            plain = 1
        else:
            (plain, next_pos, int_part, frac, digits, frac_digits, chan_start, chan_len,
             can_id, id_digits, length) = (_scan_plain_line(buf, pos, width, count, data_out)
                                           if one_pass else (0, pos, 0, 0, 0, 0, 0, 0, 0, 0, 0))
            if plain:
                shape_digits = digits
                shape_frac = frac_digits
        if plain:
            pos = next_pos
            code = 0
        else:
            if count < data_out.shape[0]:  # wipe what the one-pass scan wrote
                for j in range(width):
                    data_out[count, j] = 0
            p, stop, next_pos = _line_bounds(buf, pos)
            pos = next_pos
            if p >= stop:
                continue
            code, p, int_part, frac, digits, frac_digits, approx = _scan_timestamp(buf, p,
                                                                                 stop)
            chan_start = 0
            chan_len = 0
            can_id = 0
            id_digits = 0
            length = 0
            if code == 0:
                code, p, chan_start, chan_len = _scan_channel(buf, p, stop)
            if code == 0:
                code, p, can_id, id_digits = _scan_id(buf, p, stop)
            if code == 0:
                code, p, flags, length = _scan_payload(buf, p, stop, width, count, data_out)
            if code == 0:
                code, marker = _scan_marker(buf, p, stop)
                flags |= marker
        chan_index = -1
        if known:  # the last line's channel
            chan_index = last_chan
            last_start = chan_start
        elif code == 0 and last_chan >= 0 and chan_len == last_len and _same_bytes(
                buf, chan_start, last_start, chan_len):
            chan_index = last_chan
        elif code == 0:
            code, chan_index, n_chan = _channel_index(buf, chan_start, chan_len, chan_table,
                                                      n_chan)
            last_chan, last_start, last_len = chan_index, chan_start, chan_len
        if code != 0:
            if not skip_bad:
                return count, n_bad, line_no, code, n_chan, needed, n_fallback
            if n_bad < bad_out.shape[0]:
                bad_out[n_bad] = line_no
            n_bad += 1
            if count < t_out.shape[0]:  # wipe any data bytes written for this line
                for j in range(width):
                    data_out[count, j] = 0
            continue
        if id_digits > 3:
            flags |= FLAG_EXTENDED
        if (can_id & CAN_ERR_FLAG) != 0:
            # An error frame: SocketCAN's CAN_ERR_FLAG marks one, whatever its classes
            # (python-can's reader asks for the bus-error class too: see the module doc).
            flags = (flags & (FLAG_DIRECTION | FLAG_TX)) | FLAG_ERROR
            can_id = 0
            length = 8 if length == 0 else length
        if length > needed:
            needed = length
        # (int_part * 10^n + frac) is exact below 2^53, and one division by an exact power
        # of ten is then correctly rounded: the same double as Python's float() of the text.
        scale = _POW10_FLOAT[frac_digits] if frac_digits <= 18 else 10.0**frac_digits
        exact = digits + frac_digits <= 18 and (int_part * _POW10_INT[frac_digits] + frac
                                                ) < 2**53
        t_out[count] = (int_part * scale + frac) / scale if exact else approx
        if not exact:
            if n_fallback < fallback_out.shape[0]:
                fallback_out[n_fallback] = count
            n_fallback += 1
        if flags & FLAG_ERROR:  # python-can keeps no length or data of an error frame
            length = 0
            for j in range(width):
                data_out[count, j] = 0
        id_out[count] = can_id
        flags_out[count] = flags
        dlc_out[count] = length
        chan_out[count] = chan_index
        line_out[count] = line_no + line_shift
        count += 1
    return count, n_bad, 0, 0, n_chan, needed, n_fallback


def count_newlines(buf: np.ndarray) -> int:
    """Newline bytes in ``buf`` (uint8, contiguous): ``np.count_nonzero(buf == 10)`` without
    its temporary, 8 bytes at a time (the read of a block counts them before it is parsed)."""
    if buf.shape[0] < 16:
        return int(np.count_nonzero(buf == 10))
    return int(_count_newlines(buf, -buf.ctypes.data % 8))


_ONES = np.uint64(0x0101010101010101)
_LOW7 = np.uint64(0x7F7F7F7F7F7F7F7F)
_NEWLINES = np.uint64(0x0A0A0A0A0A0A0A0A)


@nb.njit(cache=True, nogil=True, _nrt=False)
def _count_newlines(buf, head):
    """Newline bytes in ``buf``: the ``head`` bytes before its first 8-byte aligned address
    one by one, then words (a byte x of w ^ 0x0A.. is 0 exactly when ((x & 0x7F) + 0x7F) | x
    has its high bit clear; the high bits summed by a multiply), then the tail."""
    n = buf.shape[0]
    count = 0
    for i in range(head):
        count += buf[i] == 10
    words = (n - head) // 8
    w = buf[head:head + 8 * words].view(np.uint64)
    for i in range(words):
        x = w[i] ^ _NEWLINES
        t = ((x & _LOW7) + _LOW7) | x
        count += ((~t >> np.uint64(7)) & _ONES) * _ONES >> np.uint64(56)
    for i in range(head + 8 * words, n):
        count += buf[i] == 10
    return count


def _load_bytes(path: Path) -> tuple[np.ndarray, object]:
    if path.suffix == ".gz":
        try:
            with gzip.open(path, "rb") as handle:
                return np.frombuffer(handle.read(), dtype=np.uint8), None
        except (OSError, EOFError, zlib.error) as exc:  # BadGzipFile is an OSError
            raise LogFormatError(f"{path}: not a readable gzip file ({exc or 'truncated'})"
                                 ) from exc
    size = path.stat().st_size
    if size == 0:
        return np.zeros(0, dtype=np.uint8), None
    with open(path, "rb") as handle:
        mapped = mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)
    return np.frombuffer(mapped, dtype=np.uint8), mapped


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
                  first_line: int = 1, one_pass: bool = True,
                  newlines: int | None = None, known_shape: bool = True) -> Frames:
    """The frames of the whole ``candump -L`` lines in ``buf`` (uint8). ``first_line`` is the
    line number of ``buf``'s first line in ``source`` (a piece of a longer log, read in
    chunks by slipd.replay.stream), so errors and skipped lines name the log's own lines.
    Channel indices are this piece's own, in order of first appearance. ``one_pass`` False
    skips the one-pass scans of the common line, ``known_shape`` False the one of a line
    shaped as the one before (tests: each reads the same frames).
    ``newlines``: ``count_newlines(buf)`` when the caller has counted them already."""
    n_lines = (count_newlines(buf) if newlines is None else newlines) + 1
    width = 8
    shift = first_line - 1
    fallback = np.zeros(64, dtype=np.int64)
    while True:
        t = np.empty(n_lines)
        ids = np.empty(n_lines, dtype=np.int64)
        flags = np.empty(n_lines, dtype=np.uint8)
        dlc = np.empty(n_lines, dtype=np.uint8)
        data = np.zeros((n_lines, width), dtype=np.uint8)
        chan = np.empty(n_lines, dtype=np.uint8)
        line = np.empty(n_lines, dtype=np.int64)
        chan_table = np.zeros((MAX_CHANNELS, 2), dtype=np.int64)
        bad = np.zeros(100, dtype=np.int64)
        count, n_bad, err_line, err_code, n_chan, needed, n_fallback = _parse(
            buf, width, skip_bad, t, ids, flags, dlc, data, chan, line, chan_table, bad,
            fallback, shift, one_pass, known_shape and one_pass)
        if err_code:
            text = bytes(_line_text(buf, err_line)).decode("utf-8", "replace")
            raise LogFormatError(
                f"{source}:{err_line + shift}: {ERROR_REASONS.get(err_code, 'malformed line')}: "
                f"{text!r} (use --skip-bad to count and skip such lines)"
            )
        if needed <= width and n_fallback <= len(fallback):
            break
        width = 64 if needed > width else width
        fallback = np.zeros(max(n_fallback, len(fallback)), dtype=np.int64)
    names = [bytes(buf[o:o + n]).decode("ascii", "replace") for o, n in chan_table[:n_chan]]
    if n_fallback:
        line_starts = np.concatenate(([0], np.flatnonzero(buf == 10) + 1))
        for index in fallback[:n_fallback]:
            t[index] = _python_timestamp(buf, line_starts, int(line[index]) - shift)
    return Frames(t[:count], ids[:count], flags[:count], dlc[:count], data[:count],
                  chan[:count], names, source, int(n_bad),
                  [int(x) + shift for x in bad[:min(n_bad, 100)]], line[:count])


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
