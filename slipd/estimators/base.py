"""The estimator contract and the registry of methods by name.

Every method lives in its own module ``slipd/estimators/<name>.py`` and exposes:

``PARAMS``
    an ``enum.IntEnum`` naming the elements of its float64 params vector;
``DEFAULTS``
    ``{field_name: value}`` with the paper's published values (the docstring cites the table);
``init(params, vehicle) -> np.ndarray``
    the float64 state vector at start (or at reset);
``step(state, u, params, vehicle, dt, out)``
    ``@numba.njit(cache=True)``; reads the per-tick input ``u`` (see ``slipd.channels``: values,
    validity flags at ``VALID + ch``, tick time at ``U_TIME``), advances ``state`` in place and
    writes every element of ``out`` (``slipd.channels.Out``). It allocates nothing;
``run_ticks(state, U, params, vehicle, dt, OUT)``
    ``@numba.njit(cache=True)``; the batch loop ``for k: step(state, U[k], ..., OUT[k])``.
    It lives beside ``step`` because numba cannot cache a kernel that takes another jitted
    function as an argument or closes over one (measured: it recompiles in every process).

Time advances by ``dt`` per step, always: a tick that comes after ticks the daemon skipped
(an overrun) runs ``step`` once per elapsed tick on its inputs (at most
``1 + MAX_CATCH_UP_TICKS`` times), so the integrators see the time that passed and every
discrete filter keeps the step it was designed for; the batch engine does the same on a
recording's ticks (:func:`steps_per_tick`).

A method writes ``Status.NOT_CONVERGED`` until it has settled, ``Status.UNAVAILABLE`` when a
sensor it needs is absent (it never invents the data), ``Status.RESET`` on the tick it resets
itself. The daemon and the batch engine add the input-supervision bits and decide VALID.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType

import numpy as np

from slipd.errors import ConfigError

#: name -> module path. Plain dict, lazy imports: importing slipd must not compile anything.
REGISTRY: dict[str, str] = {
    "zero": "slipd.estimators.zero",
    "kinematic_heuristic": "slipd.estimators.kinematic_heuristic",
    "dk_ekf": "slipd.estimators.dk_ekf",
    "d_ekf": "slipd.estimators.d_ekf",
    "k_kf": "slipd.estimators.k_kf",
    "gnss_magnetometer": "slipd.estimators.gnss_magnetometer",
    "pseudo_fusion": "slipd.estimators.pseudo_fusion",
    "pseudo_fusion_kbe": "slipd.estimators.pseudo_fusion_kbe",
    "pseudo_fusion_dbe": "slipd.estimators.pseudo_fusion_dbe",
    "pseudo_fusion_wbe": "slipd.estimators.pseudo_fusion_wbe",
    "hybrid_friction": "slipd.estimators.hybrid_friction",
    "hybrid_friction_nocls": "slipd.estimators.hybrid_friction_nocls",
    "ensemble": "slipd.estimators.ensemble",
}


@dataclass(frozen=True)
class Method:
    """A loaded estimator: its module's functions and a params vector."""

    name: str
    module: ModuleType
    params: np.ndarray

    @property
    def step(self) -> Callable:
        return self.module.step

    @property
    def run_ticks(self) -> Callable:
        return self.module.run_ticks

    def init(self, vehicle: np.ndarray) -> np.ndarray:
        return self.module.init(self.params, vehicle)


#: skipped ticks made up for at the next tick (1 s); after a longer stall the inputs have
#: timed out and the method is holding anyway.
MAX_CATCH_UP_TICKS = 100


def catch_up_steps(skipped_ticks):
    """Estimator steps at a tick that follows ``skipped_ticks`` skipped ones (an int, or an
    array of them)."""
    return 1 + np.clip(skipped_ticks, 0, MAX_CATCH_UP_TICKS)


def steps_per_tick(tick_time: np.ndarray, dt: float) -> np.ndarray:
    """:func:`catch_up_steps` for each of a run's tick times (the first takes one step)."""
    steps = np.ones(len(tick_time), dtype=np.int64)
    if len(tick_time) > 1:
        steps[1:] = catch_up_steps(np.rint(np.diff(tick_time) / dt).astype(np.int64) - 1)
    return steps


def available() -> list[str]:
    """Names of the registered methods, in registry order."""
    return list(REGISTRY)


def make_params(module: ModuleType, overrides: dict[str, float] | None = None) -> np.ndarray:
    """The params vector of ``module`` from its DEFAULTS with ``overrides`` applied by name."""
    fields = module.PARAMS
    values = dict(module.DEFAULTS)
    for key, value in (overrides or {}).items():
        if key not in values:
            raise ConfigError(
                f"unknown parameter {key!r} for {module.__name__.rsplit('.', 1)[-1]}; "
                f"expected one of: {', '.join(sorted(values))}"
            )
        values[key] = float(value)
    missing = [f.name for f in fields if f.name.lower() not in values and f.name not in values]
    if missing:
        raise ConfigError(f"{module.__name__}: DEFAULTS lacks {missing}")
    params = np.empty(len(fields), dtype=np.float64)
    for f in fields:
        params[f] = values.get(f.name.lower(), values.get(f.name))
    return params


def required_channels(method: Method, profile) -> tuple:
    """Channels whose loss makes ``method``'s output invalid: the method's own REQUIRED
    (default: the core IMU/wheel/steer set) that the profile maps, plus the profile's
    channels marked required."""
    from slipd.channels import CORE_CHANNELS

    own = getattr(method.module, "REQUIRED", CORE_CHANNELS)
    return tuple(sorted(set(own) | set(profile.required_channels)))


def load(name: str, overrides: dict[str, float] | None = None) -> Method:
    """Load method ``name`` with its default params (and ``overrides`` by field name)."""
    if name not in REGISTRY:
        raise ConfigError(f"unknown estimator {name!r}; available: {', '.join(available())}")
    module = importlib.import_module(REGISTRY[name])
    return Method(name=name, module=module, params=make_params(module, overrides))
