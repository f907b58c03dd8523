"""``zero``: beta = 0, vx from the mean of the rear wheel speeds.

Not a paper; the floor every method must beat (a straight-driving assumption costs exactly
|beta| of error). Its error is unknown, so its sigma_beta is NaN (sent as the signal's
maximum) and its frames are never VALID (supervision requires a known sigma). With a rear
wheel invalid, vx is the other one's (0 without either), flagged INPUT_TIMEOUT.
"""

from __future__ import annotations

import math

import numpy as np

from slipd.channels import ST_INPUT_TIMEOUT, In
from slipd.estimators.common.inputs import channel
from slipd.estimators.common.layout import build_layout
from slipd.estimators.common.outputs import write_outputs
from slipd.estimators.common.params import build_params
from slipd.numba_cache import nb

PARAMS, DEFAULTS = build_params("zero", ("UNUSED", 0.0))
LAYOUT = build_layout("zero", "UNUSED")


def init(params: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    return np.zeros(LAYOUT.size, dtype=np.float64)


@nb.njit(cache=True, _nrt=False)
def step(state, u, params, vehicle, dt, out):
    rear_left, rear_left_ok = channel(u, In.WHEEL_SPEED_RL)
    rear_right, rear_right_ok = channel(u, In.WHEEL_SPEED_RR)
    status = ST_INPUT_TIMEOUT
    if rear_left_ok and rear_right_ok:
        vx = 0.5 * (rear_left + rear_right)
        status = 0
    elif rear_left_ok:
        vx = rear_left
    elif rear_right_ok:
        vx = rear_right
    else:
        vx = 0.0
    write_outputs(out, 0.0, 0.0, vx, 0.0, math.nan, math.nan, 0.0, 0.0, status)


@nb.njit(cache=True, nogil=True, _nrt=False)
def run_ticks(state, U, params, vehicle, dt, OUT):
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])
