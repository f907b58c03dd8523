"""Method + profile -> the per-tick path the daemon and the batch replay both run.

A :class:`Pipeline` loads the method (``slipd.estimators.registry``), knows the channels whose
loss makes its output invalid (the method's own and the profile's required ones), the output
ranges the frames can carry (``supervision.supervision_plan``), the method's permanent wire ID
for SLIPD_AUX.ESTIMATOR_ID, and the catch-up rule after skipped ticks. Per tick it runs

    latched inputs u -> method.step (once per elapsed tick) -> supervise -> out

so replaying the daemon's recorded input gives its outputs exactly: both sides call the same
kernels in the same order.

Time advances by ``dt`` per step, always: a tick that comes after ticks the daemon skipped
(an overrun) runs ``step`` once per elapsed tick on its inputs (at most
``1 + MAX_CATCH_UP_TICKS`` times), so the integrators see the time that passed and every
discrete filter keeps the step it was designed for; the batch engine does the same on a
recording's ticks (``steps_per_tick``).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from slipd.channels import N_OUT
from slipd.estimators import registry
from slipd.estimators.supervision import supervise, supervise_ticks, supervision_plan

#: The tick interval, s (100 Hz).
TICK_DT = 0.01
#: skipped ticks made up for at the next tick (1 s); after a longer stall the inputs have
#: timed out and the method is holding anyway.
MAX_CATCH_UP_TICKS = 100


def catch_up_steps(skipped_ticks):
    """Estimator steps at a tick that follows ``skipped_ticks`` skipped ones (an int, or an
    array of them)."""
    return 1 + np.clip(skipped_ticks, 0, MAX_CATCH_UP_TICKS)


def steps_per_tick(tick_time: np.ndarray, dt: float = TICK_DT) -> np.ndarray:
    """``catch_up_steps`` for each of a run's tick times (the first takes one step)."""
    steps = np.ones(len(tick_time), dtype=np.int64)
    if len(tick_time) > 1:
        steps[1:] = catch_up_steps(np.rint(np.diff(tick_time) / dt).astype(np.int64) - 1)
    return steps


class Pipeline:
    """One method on one car: load, required channels, wire ID, stepping, supervision."""

    def __init__(self, method: str, profile, overrides: Mapping[str, float] | None = None,
                 dt: float = TICK_DT):
        self.method = registry.load(method, overrides)
        self.name = method
        self.dt = dt
        self.vehicle = profile.vehicle
        #: channels whose loss makes the output invalid: the method's and the profile's
        self.required = tuple(sorted(set(self.method.required) | set(profile.required_channels)))
        self.supervision = supervision_plan(self.required)
        #: SLIPD_AUX.ESTIMATOR_ID (the registry's permanent wire ID)
        self.wire_id = float(self.method.spec.wire_id)
        self.step = self.method.step
        self.params = self.method.params

    @property
    def layout(self):
        return self.method.layout

    @property
    def persistent_slots(self) -> dict[str, int]:
        """{element name: state index} of what the daemon keeps across restarts (learnt
        offsets, calibrations; the method's PERSISTENT); empty when nothing persists."""
        layout = self.method.layout
        if layout is None or not self.method.persistent:
            return {}
        return {layout.element_names[i]: i for i in layout.indices(self.method.persistent)}

    def new_state(self) -> np.ndarray:
        return self.method.init(self.vehicle)

    def tick(self, state: np.ndarray, u: np.ndarray, out: np.ndarray, steps: int = 1) -> None:
        """One tick on latched inputs ``u``: ``steps`` method steps (more than one after
        skipped ticks, ``catch_up_steps``), then supervision; writes ``out``."""
        step, params, vehicle, dt = self.step, self.params, self.vehicle, self.dt
        for _ in range(steps):
            step(state, u, params, vehicle, dt, out)
        supervise(u, self.supervision, out)

    def run(self, U: np.ndarray, steps: np.ndarray | None = None,
            state: np.ndarray | None = None) -> np.ndarray:
        """Every tick of a recording (``U``: [n, U_LEN] latched inputs) in one numba loop;
        ``steps``: estimator steps per tick (``steps_per_tick``, None = one each). Returns
        the supervised outputs [n, N_OUT]."""
        state = self.new_state() if state is None else state
        stepped = U if steps is None else np.repeat(U, steps, axis=0)
        out = np.zeros((len(stepped), N_OUT))
        self.method.run_ticks(state, stepped, self.params, self.vehicle, self.dt, out)
        if steps is not None:  # a tick's output is that of its last step
            out = np.ascontiguousarray(out[np.cumsum(steps) - 1])
        supervise_ticks(U, self.supervision, out)
        return out
