"""An exact running sum of float64 values: the same total however the values are split.

A streamed evaluation adds a log's squared errors chunk by chunk, a cluster run adds logs in
whatever pieces its tasks return, and ``float(np.dot(...))`` per piece then depends on the
cut (last-bit differences in an RMS). :class:`ExactSum` keeps Shewchuk's non-overlapping
partials (the algorithm behind ``math.fsum``: J. R. Shewchuk, "Adaptive Precision
Floating-Point Arithmetic and Fast Robust Geometric Predicates", 1997), so its value is the
exact sum of everything added, rounded once, whatever the chunking; ``math.fsum`` over all the
values is its plain twin (tests/test_stream.py).
"""

from __future__ import annotations

import math

import numpy as np

from slipd.numba_cache import nb

#: partials a finite float64 sum can need (2098 bits of exponent range / 53, rounded up)
_PARTIALS = 48


@nb.njit(cache=True)
def _grow(partials, count, values):
    """Add every finite value of ``values`` to the ``count`` partials; returns (count, sum of
    the non-finite values)."""
    special = 0.0
    for k in range(values.shape[0]):
        x = values[k]
        if not math.isfinite(x):
            special += x
            continue
        i = 0
        for j in range(count):
            y = partials[j]
            if abs(x) < abs(y):
                x, y = y, x
            high = x + y
            low = y - (high - x)
            if low != 0.0:
                partials[i] = low
                i += 1
            x = high
        partials[i] = x
        count = i + 1
    return count, special


class ExactSum:
    """Running exact sum: ``add`` arrays (or ``merge`` another), ``value()`` the rounded total
    (NaN/inf added make it NaN/inf, as in a plain sum)."""

    __slots__ = ("partials", "count", "special")

    def __init__(self) -> None:
        self.partials = np.zeros(_PARTIALS)
        self.count = 0
        self.special = 0.0

    def add(self, values: np.ndarray) -> ExactSum:
        values = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
        if values.size:
            self.count, special = _grow(self.partials, self.count, values)
            self.special += special
        return self

    def merge(self, other: ExactSum) -> ExactSum:
        self.add(other.partials[:other.count].copy())
        self.special += other.special
        return self

    def value(self) -> float:
        total = math.fsum(self.partials[:self.count].tolist())
        return total + self.special if self.special else total
