"""Method + profile -> the per-tick path the daemon and the batch replay both run.

A :class:`Pipeline` loads the method (``slipd.estimators.registry``), knows the channels whose
loss makes its output invalid (the method's own and the profile's required ones), the output
ranges the frames can carry (``supervision.supervision_plan``), the method's permanent wire ID
for SLIPD_AUX.ESTIMATOR_ID, and the catch-up rule after skipped ticks. Per tick it runs

    latched inputs u -> method.step (once per elapsed tick) -> supervise -> out

then the consistency monitor (``slipd.estimators.consistency``: the estimate against a
kinematic witness and a dynamic witness, ``d_ekf``, run on the same inputs; it may clear
VALID and writes the calibrated sigma_beta), so replaying the daemon's recorded input gives its
outputs exactly: both sides call the same kernels in the same order. The pipeline's state is one
float64 vector, [method | witness | monitor], so the daemon's dry runs on a scratch copy leave
the real one untouched and the persisted slots are the method's.

Time advances by ``dt`` per step, always: a tick that comes after ticks the daemon skipped
(an overrun) runs ``step`` once per elapsed tick on its inputs (at most
``1 + MAX_CATCH_UP_TICKS`` times), so the integrators see the time that passed and every
discrete filter keeps the step it was designed for; the batch engine does the same on a
recording's ticks (``steps_per_tick``).
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping

import numpy as np

from slipd.channels import N_OUT
from slipd.estimators import consistency, registry
from slipd.estimators.consistency import WITNESS, WITNESS_OF_WITNESS
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
                 dt: float = TICK_DT, monitor: bool = True):
        """``monitor`` False: the method and input supervision only (its raw outputs, e.g.
        to measure what the monitor adds)."""
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
        self.monitor = monitor
        # the witness's own method (any of its parameter values) is checked by the witness's
        same_kernel = self.method.spec.module == registry.spec(WITNESS).module
        witness = WITNESS_OF_WITNESS if same_kernel else WITNESS
        self.witness = registry.load(witness) if monitor else None
        self.monitor_params = consistency.default_params(witness == WITNESS_OF_WITNESS)
        #: what identifies a raw run of the method and of the witness (same kernel, same
        #: params, same dt: the same outputs on the same ticks), for sharing (``run``'s raw)
        self.method_key = (method, self.method.params.tobytes(), dt)
        self.witness_key = (witness, self.witness.params.tobytes(), dt) if monitor else None
        self._method_size = self.method.init(self.vehicle).size
        self._witness_size = self.witness.init(self.vehicle).size if self.witness else 0
        self._witness_out = np.full(N_OUT, np.nan)

    @property
    def layout(self):
        return self.method.layout

    @property
    def persistent_slots(self) -> dict[str, int]:
        """{element name: state index} of what the daemon keeps across restarts: the method's
        learnt offsets and calibrations (its PERSISTENT) and the consistency monitor's
        innovation levels on this car (``CONSISTENCY.``, consistency.PERSISTENT: a fresh one
        starts at the prior and takes tens of seconds to learn a car whose level is far above
        it); empty when nothing persists."""
        slots: dict[str, int] = {}
        layout = self.method.layout
        if layout is not None and self.method.persistent:
            slots = {layout.element_names[i]: i for i in layout.indices(self.method.persistent)}
        if self.monitor:
            start = self._method_size + self._witness_size
            monitor = consistency.LAYOUT
            slots.update({f"CONSISTENCY.{monitor.element_names[i]}": start + i
                          for i in monitor.indices(consistency.PERSISTENT)})
        return slots

    @property
    def persistence_hash(self) -> str:
        """The identity of the persisted slots' layout: the method's state layout's hash, and
        the monitor's with it when the monitor runs (a value is never restored into a slot
        that means something else)."""
        method_hash = self.method.layout.hash if self.method.layout is not None else ""
        if not self.monitor:
            return method_hash
        digest = hashlib.sha256(f"{method_hash}\n{consistency.LAYOUT.hash}".encode())
        return digest.hexdigest()[:12]

    def new_state(self) -> np.ndarray:
        """[method | witness | monitor] (the method's part first: persisted slots index it)."""
        if not self.monitor:
            return self.method.init(self.vehicle)
        parts = [self.method.init(self.vehicle)]
        if self.witness is not None:
            parts.append(self.witness.init(self.vehicle))
        parts.append(consistency.new_state())
        return np.concatenate(parts)

    def parts(self, state: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Views of the method's, the witness's and the monitor's state in ``state``."""
        m, w = self._method_size, self._method_size + self._witness_size
        return state[:m], state[m:w], state[w:]

    def consistency_flags(self, state: np.ndarray) -> int:
        """The monitor's ``consistency.Flag`` bits of the last tick (0 without a monitor)."""
        if not self.monitor:
            return 0
        return int(self.parts(state)[2][consistency.S.LAST_FLAGS])

    def tick(self, state: np.ndarray, u: np.ndarray, out: np.ndarray, steps: int = 1) -> None:
        """One tick on latched inputs ``u``: ``steps`` method steps (more than one after
        skipped ticks, ``catch_up_steps``), supervision, the consistency monitor; writes
        ``out``."""
        step, params, vehicle, dt = self.step, self.params, self.vehicle, self.dt
        if not self.monitor:
            for _ in range(steps):
                step(state, u, params, vehicle, dt, out)
            supervise(u, self.supervision, out)
            return
        method_state, witness_state, monitor_state = self.parts(state)
        for _ in range(steps):
            step(method_state, u, params, vehicle, dt, out)
        supervise(u, self.supervision, out)
        witness_out = self._witness_out
        if self.witness is not None:
            witness_step, witness_params = self.witness.step, self.witness.params
            for _ in range(steps):
                witness_step(witness_state, u, witness_params, vehicle, dt, witness_out)
        consistency.monitor(monitor_state, u, out, witness_out, self.monitor_params, vehicle,
                            dt * steps)

    def run(self, U: np.ndarray, steps: np.ndarray | None = None,
            state: np.ndarray | None = None, raw: RawRuns | None = None) -> np.ndarray:
        """Every tick of a recording (``U``: [n, U_LEN] latched inputs) in one numba loop;
        ``steps``: estimator steps per tick (``steps_per_tick``, None = one each). Returns
        the supervised, monitored outputs [n, N_OUT]. ``raw``: the raw runs other pipelines
        made on these very ticks from the same state (:class:`RawRuns`): a method or witness
        found there is not run again."""
        state = self.new_state() if state is None else state
        method_state, witness_state, monitor_state = self.parts(state) if self.monitor else (
            state, None, None)
        stepped = U if steps is None else np.repeat(U, steps, axis=0)
        out = self._raw_run(self.method, self.method_key, method_state, stepped, steps, raw)
        if raw is not None and self.method_key in raw.keys:
            out = out.copy()  # supervision and the monitor write into it
        supervise_ticks(U, self.supervision, out)
        if not self.monitor:
            return out
        if self.witness is not None:
            witness_out = self._raw_run(self.witness, self.witness_key, witness_state, stepped,
                                        steps, raw)
        else:
            witness_out = np.full((len(U), N_OUT), np.nan)
        tick_dt = np.full(len(U), self.dt) if steps is None else self.dt * steps.astype(float)
        consistency.monitor_ticks(monitor_state, U, out, witness_out, self.monitor_params,
                                  self.vehicle, tick_dt)
        return out

    def _raw_run(self, method, key, state, stepped, steps, raw: RawRuns | None
                 ) -> np.ndarray:
        """The method's raw outputs on the ticks, from ``raw`` (its state set to the one
        after that run) or run here (and kept in ``raw`` when others want it). The outputs
        in ``raw`` are only read."""
        if raw is not None and key in raw.runs:
            out, after = raw.runs[key]
            state[:] = after
            return out
        out = self._run_method(method, state, stepped, steps)
        if raw is not None and key in raw.keys:
            raw.runs[key] = (out, state.copy())
        return out

    def raw_jobs(self, state: np.ndarray) -> list[tuple[tuple, object, np.ndarray]]:
        """The raw runs ``run`` makes on ``state`` ([method | witness | monitor]): (key,
        loaded method, view of its part of ``state``) of the method and of the witness, for
        running them elsewhere (``raw_run``) and handing ``run`` the results in a
        :class:`RawRuns`."""
        if not self.monitor:
            return [(self.method_key, self.method, state)]
        method_state, witness_state, _ = self.parts(state)
        jobs = [(self.method_key, self.method, method_state)]
        if self.witness is not None:
            jobs.append((self.witness_key, self.witness, witness_state))
        return jobs

    def raw_run(self, method, state: np.ndarray, stepped: np.ndarray,
                steps: np.ndarray | None = None) -> np.ndarray:
        """``method``'s raw outputs [n_ticks, N_OUT] (one of ``raw_jobs``) on ``stepped``,
        the ticks' inputs repeated per step (``U`` when ``steps`` is None), advancing
        ``state`` (a copy of the job's part, which ``run`` then takes from the
        :class:`RawRuns`)."""
        return self._run_method(method, state, stepped, steps)

    def _run_method(self, method, state, stepped, steps) -> np.ndarray:
        out = np.zeros((len(stepped), N_OUT))
        method.run_ticks(state, stepped, method.params, self.vehicle, self.dt, out)
        if steps is not None:  # a tick's output is that of its last step
            out = np.ascontiguousarray(out[np.cumsum(steps) - 1])
        return out


class RawRuns:
    """Raw method runs (outputs before supervision, and the state after) on one run of ticks
    that several pipelines of one replay need: d_ekf is the consistency witness of every other
    method and a method of its own, so ``--estimator all`` stepped it 14 times per tick for one
    result. ``keys``: the ``method_key``/``witness_key`` that more than one role uses (the
    rest are not kept, unless put in ``runs`` beforehand, as a replay running them on
    threads does: such an output is then handed to its one pipeline without a copy). Valid
    for one call of ``Pipeline.run`` per pipeline, all on the same ticks from states that
    agree on the shared parts (fresh states, or ones that only such
    runs have advanced)."""

    def __init__(self, keys: set):
        self.keys = keys
        self.runs: dict = {}

    @staticmethod
    def shared_keys(pipelines) -> set:
        """The method and witness keys of ``pipelines`` that more than one of them uses."""
        seen: dict = {}
        for pipeline in pipelines:
            for key in (pipeline.method_key, pipeline.witness_key):
                if key is not None:
                    seen[key] = seen.get(key, 0) + 1
        return {key for key, count in seen.items() if count > 1}
