"""Supervision (slipd.estimators.supervision): the VALID decision against a plain twin, and its
ranges read from slipd.dbc (never typed by hand)."""

from __future__ import annotations

import math

import cantools
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipd.channels import (
    CORE_CHANNELS,
    N_IN,
    N_OUT,
    ST_DEGRADED,
    ST_INPUT_TIMEOUT,
    ST_NOT_CONVERGED,
    ST_RESET,
    ST_UNAVAILABLE,
    ST_VALID,
    U_LEN,
    VALID,
    In,
    Out,
)
from slipd.codec.plan import SLIPD_DBC
from slipd.estimators.supervision import (
    PLAN_LEN,
    Limit,
    supervise,
    supervise_ticks,
    supervision_plan,
)

DEG = math.pi / 180.0
#: SLIPD_STATE's signals and their SI factor (the output plan's)
SIGNALS = {Out.BETA: ("BETA", DEG), Out.BETA_RATE: ("BETA_RATE", DEG), Out.VX: ("VX", 1.0),
           Out.VY: ("VY", 1.0)}


def dbc_ranges() -> dict[Out, tuple[float, float]]:
    message = cantools.database.load_file(str(SLIPD_DBC)).get_message_by_name("SLIPD_STATE")
    ranges = {}
    for out, (name, factor) in SIGNALS.items():
        signal = message.get_signal_by_name(name)
        ranges[out] = (signal.minimum * factor, signal.maximum * factor)
    return ranges


def plain_supervise(u: np.ndarray, required: set[int], out: np.ndarray) -> int:
    """The VALID rule written out: no blocking bit of the method, every required channel fresh,
    every checked output finite and inside the frame's range."""
    status = int(out[Out.STATUS]) & ~ST_VALID
    if any(u[VALID + ch] < 0.5 for ch in required):
        status |= ST_INPUT_TIMEOUT
    blocked = status & (ST_INPUT_TIMEOUT | ST_NOT_CONVERGED | ST_UNAVAILABLE | ST_RESET)
    in_range = all(math.isfinite(out[o]) and low <= out[o] <= high
                   for o, (low, high) in dbc_ranges().items())
    return status | (ST_VALID if not blocked and in_range else 0)


def test_the_plan_carries_the_dbc_ranges_in_si():
    plan = supervision_plan(CORE_CHANNELS)
    assert plan.shape == (PLAN_LEN,)
    assert set(np.flatnonzero(plan[:N_IN])) == {int(c) for c in CORE_CHANNELS}
    ranges = dbc_ranges()
    assert plan[N_IN + Limit.BETA_MIN] == pytest.approx(ranges[Out.BETA][0], rel=1e-15)
    assert plan[N_IN + Limit.BETA_MAX] == pytest.approx(math.radians(40.955), rel=1e-12)
    assert plan[N_IN + Limit.VX_MIN] == 0.0 and plan[N_IN + Limit.VX_MAX] == 81.9
    assert plan[N_IN + Limit.VY_MIN] == pytest.approx(-10.24) and plan[N_IN + Limit.VY_MAX] == 10.2
    assert plan[N_IN + Limit.BETA_RATE_MAX] == pytest.approx(math.radians(102.3), rel=1e-12)


@given(st.integers(0, 2**31 - 1))
@settings(max_examples=300, deadline=None)
def test_supervise_agrees_with_its_plain_twin(seed):
    rng = np.random.default_rng(seed)
    required = {int(c) for c in rng.choice(N_IN, size=rng.integers(0, 6), replace=False)}
    plan = supervision_plan(required)
    u = np.zeros(U_LEN)
    u[VALID : VALID + N_IN] = (rng.random(N_IN) < 0.9).astype(float)
    out = np.zeros(N_OUT)
    ranges = dbc_ranges()
    for o, (low, high) in ranges.items():
        # mostly inside, sometimes just outside a limit, now and then non-finite
        choice = rng.random()
        if choice < 0.8:
            out[o] = rng.uniform(low, high)
        elif choice < 0.95:
            out[o] = (low if rng.random() < 0.5 else high) * (1 + rng.choice([-1e-9, 1e-9]))
        else:
            out[o] = rng.choice([np.nan, np.inf, -np.inf])
    own = 0
    for bit in (ST_DEGRADED, ST_INPUT_TIMEOUT, ST_NOT_CONVERGED, ST_UNAVAILABLE, ST_RESET,
                ST_VALID):
        if rng.random() < 0.15:
            own |= bit
    out[Out.STATUS] = float(own)
    expected = plain_supervise(u, required, out)
    supervise(u, plan, out)
    assert int(out[Out.STATUS]) == expected


def test_a_value_at_the_limit_is_valid_and_beyond_it_is_not():
    plan = supervision_plan(())
    u = np.zeros(U_LEN)
    OUT = np.zeros((4, N_OUT))
    beta_max = plan[N_IN + Limit.BETA_MAX]
    OUT[:, Out.VX] = 20.0
    OUT[:, Out.BETA] = [beta_max, np.nextafter(beta_max, 1.0), -beta_max, 0.0]
    OUT[3, Out.STATUS] = float(ST_DEGRADED)  # degraded alone does not block VALID
    supervise_ticks(np.zeros((4, U_LEN)), plan, OUT)
    status = OUT[:, Out.STATUS].astype(int)
    assert status[0] & ST_VALID and not status[1] & ST_VALID and status[2] & ST_VALID
    assert status[3] == ST_DEGRADED | ST_VALID
    u[VALID + In.AY] = 0.0
    out = OUT[0].copy()
    supervise(u, supervision_plan((In.AY,)), out)
    assert int(out[Out.STATUS]) == ST_INPUT_TIMEOUT
