"""Writing a method's outputs: every element of ``out`` (``slipd.channels.Out``), every tick."""

from __future__ import annotations

import math

from slipd.channels import ST_NOT_CONVERGED, Out
from slipd.numba_cache import nb


@nb.njit(cache=True, inline="always")
def write_outputs(out, beta, beta_rate, vx, vy, mu, sigma, roll, friction_class, status):
    """Fill ``out``. ``mu`` NaN: the method does not estimate friction; a non-finite roll is
    written as 0 (a method without a roll estimate passes 0). NIS is written NaN: a method
    with a Kalman filter writes its innovation test after this (``common.kalman.nis_test``)."""
    out[Out.BETA] = beta
    out[Out.BETA_RATE] = beta_rate
    out[Out.VX] = vx
    out[Out.VY] = vy
    out[Out.MU] = mu
    out[Out.SIGMA_BETA] = sigma
    out[Out.ROLL] = roll if math.isfinite(roll) else 0.0
    out[Out.FRICTION_CLASS] = friction_class
    out[Out.STATUS] = float(status)
    out[Out.NIS] = math.nan


@nb.njit(cache=True, inline="always")
def write_held(out, vx, sigma, roll, status):
    """Outputs while a method cannot run (start-up, standstill, no speed, missing sensor):
    beta 0 (the straight-running assumption), vx as given, no friction, NOT_CONVERGED added.
    ``sigma`` is a finite "unknown" (``held_sigma``), not NaN, so that every consumer can
    encode it."""
    write_outputs(out, 0.0, 0.0, vx, 0.0, math.nan, sigma, roll, 0.0,
                  status | ST_NOT_CONVERGED)  # fmt: skip


@nb.njit(cache=True, inline="always")
def held_sigma(p0_vy, vx, speed_floor):
    """sigma_beta of an initial lateral-velocity variance ``p0_vy`` at the speed ``vx`` (not
    below ``speed_floor``): atan(sqrt(p0_vy) / max(vx, speed_floor))."""
    return math.atan(math.sqrt(p0_vy) / max(vx, speed_floor))
