"""Input supervision and the VALID decision, shared by the daemon and the batch engine.

A frame marked valid must carry a value slipd can vouch for: every required input fresh
and E2E-checked, the method converged and available, the values finite and inside the range
the output frame can carry. This kernel is the only place that sets ``Status.VALID``.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from slipd.channels import (
    ST_INPUT_TIMEOUT,
    ST_NOT_CONVERGED,
    ST_RESET,
    ST_UNAVAILABLE,
    ST_VALID,
    VALID,
    Out,
)

#: |beta| and |vy| limits of SLIPD_STATE (slipd.dbc): beyond them a frame is clamped, so
#: it cannot be valid.
BETA_LIMIT = math.radians(40.95)
BETA_RATE_LIMIT = math.radians(102.3)
VX_MAX = 81.9
VY_LIMIT = 10.2
BLOCKING = ST_INPUT_TIMEOUT | ST_NOT_CONVERGED | ST_UNAVAILABLE | ST_RESET


def required_mask(channels) -> np.ndarray:
    """float64 [N_IN] with 1.0 for each required channel."""
    from slipd.channels import N_IN

    mask = np.zeros(N_IN, dtype=np.float64)
    for channel in channels:
        mask[int(channel)] = 1.0
    return mask


@nb.njit(cache=True)
def supervise(u, required, out):
    """Add the input-supervision bits to ``out[STATUS]`` and decide VALID (in place)."""
    status = int(out[Out.STATUS]) & ~ST_VALID
    for ch in range(required.shape[0]):
        if required[ch] > 0.5 and u[VALID + ch] < 0.5:
            status |= ST_INPUT_TIMEOUT
            break
    beta = out[Out.BETA]
    ok = (status & BLOCKING) == 0
    ok = ok and math.isfinite(beta) and abs(beta) <= BETA_LIMIT
    ok = ok and math.isfinite(out[Out.BETA_RATE]) and abs(out[Out.BETA_RATE]) <= BETA_RATE_LIMIT
    ok = ok and math.isfinite(out[Out.VX]) and 0.0 <= out[Out.VX] <= VX_MAX
    ok = ok and math.isfinite(out[Out.VY]) and abs(out[Out.VY]) <= VY_LIMIT
    if ok:
        status |= ST_VALID
    out[Out.STATUS] = float(status)


@nb.njit(cache=True)
def supervise_ticks(U, required, OUT):
    for k in range(U.shape[0]):
        supervise(U[k], required, OUT[k])
