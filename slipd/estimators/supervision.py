"""Input supervision and the VALID decision, shared by the daemon and the batch engine.

A frame marked valid must carry a value slipd can vouch for: every required input fresh
and E2E-checked, the method converged and available, the values finite and inside the range
the output frame can carry, and a known sigma_beta (``zero``, which has none, is never VALID).
This kernel is the only place that sets ``Status.VALID``; the consistency monitor
(``slipd.estimators.consistency``), which runs after it, may only clear it.

The ranges are the output plan's (slipd.dbc's SLIPD_STATE signals, in SI): a value outside
them would be sent clamped, so it cannot be valid. They are read from the DBC, never typed
here, and travel with the required-channel mask in one float64 vector (``supervision_plan``),
so that a tick passes one array.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable

import numpy as np

from slipd.channels import (
    N_IN,
    ST_INPUT_TIMEOUT,
    ST_NOT_CONVERGED,
    ST_RESET,
    ST_UNAVAILABLE,
    ST_VALID,
    VALID,
    Out,
)
from slipd.codec.plan import Tx
from slipd.numba_cache import nb

#: A method's own status bits any of which keeps a frame from being VALID.
BLOCKING = ST_INPUT_TIMEOUT | ST_NOT_CONVERGED | ST_UNAVAILABLE | ST_RESET


@enum.unique
class Limit(enum.IntEnum):
    """The range slots of a supervision plan, after its N_IN required-channel flags (SI)."""

    BETA_MIN = 0
    BETA_MAX = 1
    BETA_RATE_MIN = 2
    BETA_RATE_MAX = 3
    VX_MIN = 4
    VX_MAX = 5
    VY_MIN = 6
    VY_MAX = 7


#: The checked outputs and their output-frame slots, in Limit order (min, max each).
CHECKED = ((Out.BETA, Tx.BETA), (Out.BETA_RATE, Tx.BETA_RATE), (Out.VX, Tx.VX),
           (Out.VY, Tx.VY))
PLAN_LEN = N_IN + len(Limit)
_LIMITS = N_IN


def output_ranges(plan=None) -> dict[Tx, tuple[float, float]]:
    """(min, max) in SI of every output slot the output plan range-checks when it encodes
    (``plan``: a codec Plan, default slipd.dbc's)."""
    from slipd.codec import Codec
    from slipd.codec import kernels as K

    plan = Codec.output_plan() if plan is None else plan
    ranges = {}
    for row in range(plan.n_messages, len(plan.plan_i)):
        slot = int(plan.plan_i[row, K.S_SLOT])
        low, high = plan.plan_f[row, K.F_MIN], plan.plan_f[row, K.F_MAX]
        if slot >= 0 and low < high:
            factor = plan.plan_f[row, K.F_FACTOR]
            ranges[Tx(slot)] = (float(low * factor), float(high * factor))
    return ranges


def supervision_plan(required: Iterable[int], plan=None) -> np.ndarray:
    """float64 [PLAN_LEN]: 1.0 for each required channel, then the output ranges (Limit)."""
    vector = np.zeros(PLAN_LEN, dtype=np.float64)
    for channel in required:
        vector[int(channel)] = 1.0
    ranges = output_ranges(plan)
    for k, (_, slot) in enumerate(CHECKED):
        if slot not in ranges:
            from slipd.errors import ConfigError

            raise ConfigError(f"the output plan has no range for {slot.name}; slipd.dbc must "
                              "give SLIPD_STATE's signals a [min|max]")
        vector[_LIMITS + 2 * k], vector[_LIMITS + 2 * k + 1] = ranges[slot]
    return vector


@nb.njit(cache=True, _nrt=False)
def _within(value, low, high):
    return math.isfinite(value) and low <= value <= high


@nb.njit(cache=True, _nrt=False)
def supervise(u, plan, out):
    """Add the input-supervision bits to ``out[STATUS]`` and decide VALID (in place)."""
    status = int(out[Out.STATUS]) & ~ST_VALID
    for ch in range(N_IN):
        if plan[ch] > 0.5 and u[VALID + ch] < 0.5:
            status |= ST_INPUT_TIMEOUT
            break
    ok = (status & BLOCKING) == 0
    ok = ok and _within(out[Out.BETA], plan[_LIMITS + Limit.BETA_MIN],
                        plan[_LIMITS + Limit.BETA_MAX])
    ok = ok and _within(out[Out.BETA_RATE], plan[_LIMITS + Limit.BETA_RATE_MIN],
                        plan[_LIMITS + Limit.BETA_RATE_MAX])
    ok = ok and _within(out[Out.VX], plan[_LIMITS + Limit.VX_MIN], plan[_LIMITS + Limit.VX_MAX])
    ok = ok and _within(out[Out.VY], plan[_LIMITS + Limit.VY_MIN], plan[_LIMITS + Limit.VY_MAX])
    ok = ok and math.isfinite(out[Out.SIGMA_BETA])  # an estimate whose error is unknown
    if ok:
        status |= ST_VALID
    out[Out.STATUS] = float(status)


@nb.njit(cache=True, nogil=True, _nrt=False)
def supervise_ticks(U, plan, OUT):
    for k in range(U.shape[0]):
        supervise(U[k], plan, OUT[k])
