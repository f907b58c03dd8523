"""Rows of numbers as CSV text in numba, equal byte for byte to Python's ``format``.

The replay CSV writes each float with a fixed number of decimals (``f"{x:.5f}"``). Python
formats one value in ~150 ns, so a row of ten took ~2 us and the CSV writer capped a replay at
~0.9 M frames/s (issue 21); pyarrow's CSV writer prints the shortest round-trip digits instead
(``0.1234567890123``), which would change the files. :func:`format_rows` writes the same text
as Python at ~50 ns a value.

Exactness: ``|x|`` is split into its integer part and its fraction (both exact doubles), and
the fraction times ``10**d`` is computed in float64 (``10**d`` is exact for ``d <= 22``) with
an error of at most half an ulp of a number below ``10**d`` (scaling the whole of a Unix time
such as 1.7e9 by 1e6 would leave ulps of 0.25, and every such cell to Python). Where the
decimal fraction of that product is farther than two ulps from one half, rounding it gives the
digits Python prints (Python rounds the exact binary value, half to even); the few values
closer to a tie, and any value of 2**52 or more after scaling, are left to Python: the row is
flagged and :func:`format_csv` formats it with :func:`python_row`, the plain twin the tests
compare the kernel with.
"""

from __future__ import annotations

import math

import numpy as np

from slipd.numba_cache import nb

#: a column's kind in ``decimals``: >= 0 digits after the point, or one of these
INTEGER = -1
#: ``decimals`` + EMPTY_IF_NAN: an empty cell for NaN (the CSV's "not estimated")
EMPTY_IF_NAN = 100
_TWO52 = 4503599627370496.0
_TIE_ULPS = 4.5e-16  # two ulps of the scaled value, relative


@nb.njit(cache=True, _nrt=False)
def _put_text(out, p, text):
    for j in range(text.shape[0]):
        out[p + j] = text[j]
    return p + text.shape[0]


@nb.njit(cache=True, _nrt=False)
def _put_uint(out, p, value, min_digits):
    """Decimal digits of ``value`` (>= 0), at least ``min_digits`` (zero-padded)."""
    n = 0
    probe = value
    while probe > 0:
        n += 1
        probe //= 10
    if n < min_digits:
        n = min_digits
    for j in range(n - 1, -1, -1):
        out[p + j] = 48 + value % 10
        value //= 10
    return p + n


@nb.njit(cache=True, _nrt=False)
def _put_fixed(out, p, x, decimals):
    """``format(x, f".{decimals}f")`` into ``out`` at ``p``; returns the end, or -1 where the
    value needs Python (a near tie, or too large to scale exactly)."""
    if math.isnan(x):
        out[p] = 110  # nan
        out[p + 1] = 97
        out[p + 2] = 110
        return p + 3
    if math.isinf(x):
        if x < 0:
            out[p] = 45
            p += 1
        out[p] = 105  # inf
        out[p + 1] = 110
        out[p + 2] = 102
        return p + 3
    negative = x < 0.0 or (x == 0.0 and math.copysign(1.0, x) < 0.0)
    scale = 10.0**decimals
    magnitude = abs(x)
    if magnitude * scale >= _TWO52:
        return -1
    # the integer part and the fraction of |x| are exact doubles; only the fraction is
    # scaled, so a large x (a Unix time) keeps the fraction's own precision
    integer = math.floor(magnitude)
    y = (magnitude - integer) * scale
    whole = math.floor(y)
    fraction = y - whole
    if abs(fraction - 0.5) <= y * _TIE_ULPS + 1e-300:
        return -1
    power = np.int64(1)
    for _ in range(decimals):
        power *= 10
    rounded = np.int64(integer) * power + np.int64(whole) + (1 if fraction > 0.5 else 0)
    if negative:
        out[p] = 45
        p += 1
    p = _put_uint(out, p, rounded // power, 1)
    if decimals > 0:
        out[p] = 46
        p = _put_uint(out, p + 1, rounded % power, decimals)
    return p


@nb.njit(cache=True, nogil=True, _nrt=False)  # the CSV writer overlaps the stages before it
def format_rows(values, decimals, text, text_at, out, python_rows, row_end):
    """CSV lines of ``values`` [n, k] into ``out`` (uint8, :func:`row_room` bytes a row):
    column j with ``decimals[j]`` digits after the point (INTEGER: a whole number; plus
    EMPTY_IF_NAN: empty for NaN), the bytes ``text`` as an extra column before column
    ``text_at`` (-1: none). A row the kernel leaves to Python is written as an empty line and
    marked in ``python_rows`` (:func:`format_csv` fills it in); ``row_end[i]`` is the offset
    after row i's newline. Returns (bytes used, rows marked)."""
    n, k = values.shape
    p = 0
    marked = 0
    for i in range(n):
        start = p
        ok = True
        for j in range(k):
            if j == text_at:
                p = _put_text(out, p, text)
                out[p] = 44
                p += 1
            kind = decimals[j]
            x = values[i, j]
            if kind >= EMPTY_IF_NAN:
                if not math.isnan(x):
                    p = _put_fixed(out, p, x, kind - EMPTY_IF_NAN)
            elif kind == INTEGER:
                whole = np.int64(x)
                if whole < 0:
                    out[p] = 45
                    p += 1
                    whole = -whole
                p = _put_uint(out, p, whole, 1)
            else:
                p = _put_fixed(out, p, x, kind)
            if p < 0:
                ok = False
                break
            if j < k - 1:
                out[p] = 44
                p += 1
        if not ok:
            p = start
            python_rows[i] = True
            marked += 1
        out[p] = 10
        p += 1
        row_end[i] = p
    return p, marked


def python_row(row: np.ndarray, decimals: np.ndarray, text: str, text_at: int) -> str:
    """One line as Python formats it (the kernel's plain twin)."""
    cells = []
    for j, (x, kind) in enumerate(zip(row.tolist(), decimals.tolist(), strict=True)):
        if j == text_at:
            cells.append(text)
        if kind >= EMPTY_IF_NAN:
            cells.append("" if math.isnan(x) else f"{x:.{kind - EMPTY_IF_NAN}f}")
        elif kind == INTEGER:
            cells.append(str(int(x)))
        else:
            cells.append(f"{x:.{kind}f}")
    return ",".join(cells) + "\n"


def row_room(decimals: np.ndarray, text: bytes) -> int:
    """Bytes a row can take at most in the kernel: a fixed cell is below 2**52 scaled (16
    digits in all), a sign and a point; an integer cell 20 digits."""
    cells = sum(20 + 2 if d == INTEGER else 16 + 3 for d in decimals.tolist())
    return cells + len(text) + len(decimals) + 2


def format_csv(values: np.ndarray, decimals: np.ndarray, text: str = "",
               text_at: int = -1) -> bytes:
    """The CSV lines of ``values`` (see :func:`format_rows`), Python's text for every cell."""
    values = np.ascontiguousarray(values, dtype=np.float64)
    decimals = np.asarray(decimals, dtype=np.int64)
    encoded = np.frombuffer(text.encode(), dtype=np.uint8)
    out = np.empty(len(values) * row_room(decimals, text.encode()), dtype=np.uint8)
    python_rows = np.zeros(len(values), dtype=np.bool_)
    row_end = np.zeros(len(values), dtype=np.int64)
    used, marked = format_rows(values, decimals, encoded, text_at, out, python_rows, row_end)
    if not marked:
        return out[:used].tobytes()
    pieces, done = [], 0
    for i in np.flatnonzero(python_rows):
        start = int(row_end[i]) - 1  # the marked row is its newline alone
        pieces += [out[done:start].tobytes(),
                   python_row(values[i], decimals, text, text_at).encode()]
        done = int(row_end[i])
    pieces.append(out[done:used].tobytes())
    return b"".join(pieces)
