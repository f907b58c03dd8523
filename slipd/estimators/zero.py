"""``zero``: beta = 0, vx from the mean of the rear wheel speeds.

Not a paper; the floor every method must beat (a straight-driving assumption costs exactly
|beta| of error).
"""

from __future__ import annotations

import enum

import numba as nb
import numpy as np

from slipd.channels import ST_INPUT_TIMEOUT, VALID, In, Out


@enum.unique
class PARAMS(enum.IntEnum):
    UNUSED = 0


DEFAULTS = {"unused": 0.0}


def init(params: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    return np.zeros(1, dtype=np.float64)


@nb.njit(cache=True)
def step(state, u, params, vehicle, dt, out):
    vx = 0.5 * (u[In.WHEEL_SPEED_RL] + u[In.WHEEL_SPEED_RR])
    out[Out.BETA] = 0.0
    out[Out.BETA_RATE] = 0.0
    out[Out.VX] = vx
    out[Out.VY] = 0.0
    out[Out.MU] = np.nan
    out[Out.SIGMA_BETA] = np.nan
    out[Out.ROLL] = 0.0
    out[Out.FRICTION_CLASS] = 0.0
    ok = u[VALID + In.WHEEL_SPEED_RL] > 0.5 and u[VALID + In.WHEEL_SPEED_RR] > 0.5
    out[Out.STATUS] = 0.0 if ok else float(ST_INPUT_TIMEOUT)


@nb.njit(cache=True)
def run_ticks(state, U, params, vehicle, dt, OUT):
    for k in range(U.shape[0]):
        step(state, U[k], params, vehicle, dt, OUT[k])
