"""The registry: one :class:`Spec` per method, and loading a method by name.

A Spec says which module implements the method, with which parameter overrides (a variant is
a registry line, not a module), which family of kernels it belongs to, whether ``ensemble``
fuses it, and its **wire ID**: the value of SLIPD_AUX.ESTIMATOR_ID on the bus. Wire IDs are
permanent (a controller on a car decodes them through slipd.dbc's VAL_ table): a new method
takes a new ID, a removed method's ID is never reused. slipd's own methods use 0-127;
third-party methods 128-254.

Third-party methods register through the ``slipd.estimators`` entry-point group, as
python-can's interfaces do through ``can.interface``: in the package's pyproject.toml::

    [project.entry-points."slipd.estimators"]
    my_method = "my_package.my_method:SPEC"

where ``SPEC = Spec("my_method", "my_package.my_method", wire_id=130, family="my_paper")``.
Entry points are read the first time a name is looked up; a broken or conflicting one is
reported (a warning naming it) and left out, never loaded half-way.

A method with some of its parameters set, for one run, is named ``METHOD:KEY=VALUE[:KEY=VALUE
...]`` wherever a method name is taken (``slipd replay --estimator``, ``slipd eval``, ``slipd
run``, the Python API): ``kinematic_heuristic:steady_gain=0`` is the paper's observer without
slipd's steady-state hold, beside the default in the same replay
(``--estimator kinematic_heuristic,kinematic_heuristic:steady_gain=0``); every departure from a
paper is such a parameter, with the paper's value in the method's docstring. It is the method's
Spec with the values added to its overrides (same module and wire ID, never fused by
``ensemble``), made where it is looked up, so worker processes resolve it the same way.

Importing this module compiles nothing: a method's module is imported by :func:`load`.
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import cache
from types import MappingProxyType, ModuleType

import numpy as np

from slipd.channels import CORE_CHANNELS
from slipd.errors import ConfigError

ENTRY_POINT_GROUP = "slipd.estimators"
#: The method ``slipd run``, replay, the demo and the API use unless told otherwise: chosen by
#: the accuracy figures (benchmarks/accuracy.py, README "Estimators"): the only method within
#: the real run's targets (0.52 deg RMS, p99 1.9) that stays within 0.4 deg on every model
#: mismatch and sensor variant, with no VALID tick 5 deg off anywhere.
DEFAULT_ESTIMATOR = "d_ekf"
#: Wire IDs of slipd's own methods and of third-party ones (SLIPD_AUX.ESTIMATOR_ID, 8 bits).
BUILTIN_WIRE_IDS = range(0, 128)
PLUGIN_WIRE_IDS = range(128, 255)

_PACKAGE = "slipd.estimators"


@dataclass(frozen=True)
class Spec:
    """One registered method.

    ``module``: import path of the module with ``PARAMS``, ``DEFAULTS``, ``init``, ``step``,
    ``run_ticks`` (the contract in ``slipd.estimators``); ``overrides``: param values that
    make this entry a variant of the module's method; ``family``: the paper (or kernel set)
    the method is built from, so that ``ensemble`` knows whose errors are correlated;
    ``ensemble``: fused by ``ensemble``; ``wire_id``: permanent, see the module docstring.
    """

    name: str
    module: str
    wire_id: int
    family: str
    overrides: Mapping[str, float] = field(default_factory=dict)
    ensemble: bool = False
    summary: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "overrides", MappingProxyType(dict(self.overrides)))


def _builtin(name: str, module: str, wire_id: int, family: str, summary: str,
             overrides: Mapping[str, float] | None = None, ensemble: bool = False) -> Spec:
    return Spec(name, f"{_PACKAGE}.{module}", wire_id, family, overrides or {}, ensemble,
                summary)


#: slipd's methods, in the order tables list them (and ``ensemble`` fuses its members in).
#: Never renumber a wire_id.
BUILTIN: tuple[Spec, ...] = (
    _builtin("zero", "zero", 0, "floor", "beta = 0: the floor every method must beat"),
    _builtin("linear_kf", "linear_kf", 13, "floor",
             "linear single-track Kalman filter [vy, r]: the classic baseline"),
    _builtin("kinematic_heuristic", "selmanaj2017.kinematic_heuristic", 1, "selmanaj2017",
             "Selmanaj 2017: kinematic observer, straight-running heuristic", ensemble=True),
    _builtin("dk_ekf", "righetti_lenzo2025.dk_ekf", 2, "righetti_lenzo2025",
             "Righetti & Lenzo 2025: dynamic EKF feeding a kinematic KF", ensemble=True),
    _builtin("d_ekf", "righetti_lenzo2025.d_ekf", 3, "righetti_lenzo2025",
             "Righetti & Lenzo 2025: the dynamic EKF alone, its tyre friction read from "
             "wheel slip (Carnier 2023's classifier)", ensemble=True),
    _builtin("k_kf", "righetti_lenzo2025.k_kf", 4, "righetti_lenzo2025",
             "Righetti & Lenzo 2025: the kinematic KF alone", ensemble=True),
    _builtin("hybrid_friction", "carnier2023.hybrid_friction", 10, "carnier2023",
             "Carnier 2023: hybrid observer, adaptive friction, classifier", ensemble=True),
    _builtin("hybrid_friction_nocls", "carnier2023.hybrid_friction", 11, "carnier2023",
             "Carnier 2023: the adaptive observer without the classifier",
             {"classifier_enabled": 0.0}),
    _builtin("pseudo_fusion", "chen2018.pseudo_fusion", 6, "chen2018",
             "Chen 2018: kinematic, dynamic, wheel-speed estimators fused", ensemble=True),
    _builtin("pseudo_fusion_kbe", "chen2018.pseudo_fusion", 7, "chen2018",
             "Chen 2018: the kinematics-based estimator alone",
             {"part": 1.0, "kbe_vy_leak_time_constant": 2.0}),
    _builtin("pseudo_fusion_dbe", "chen2018.pseudo_fusion", 8, "chen2018",
             "Chen 2018: the dynamics-based estimator alone", {"part": 2.0}),
    _builtin("pseudo_fusion_wbe", "chen2018.pseudo_fusion", 9, "chen2018",
             "Chen 2018: the wheel-speed estimator alone", {"part": 3.0}),
    _builtin("gnss_magnetometer", "yoon2016.gnss_magnetometer", 5, "yoon2016",
             "Yoon 2016: heading EKF, GNSS sideslip KF, friction EKF", ensemble=True),
    _builtin("ensemble", "ensemble", 12, "ensemble",
             "every ensemble member, fused by N-method minimum variance"),
)


def _check(specs: list[Spec], spec: Spec, wire_ids: range, source: str) -> None:
    if not isinstance(spec, Spec):
        raise ConfigError(f"{source}: expected a slipd.estimators.registry.Spec, got "
                          f"{type(spec).__name__}")
    if not spec.name.isidentifier():
        raise ConfigError(f"{source}: method name {spec.name!r} is not an identifier")
    if spec.wire_id not in wire_ids:
        raise ConfigError(f"{source}: {spec.name} has wire_id {spec.wire_id}; expected "
                          f"{wire_ids.start}..{wire_ids.stop - 1}")
    for other in specs:
        if other.name == spec.name:
            raise ConfigError(f"{source}: method name {spec.name!r} is already registered")
        if other.wire_id == spec.wire_id:
            raise ConfigError(f"{source}: {spec.name} has wire_id {spec.wire_id}, which "
                              f"{other.name} already has")


def _entry_points():
    from importlib.metadata import entry_points

    return entry_points(group=ENTRY_POINT_GROUP)


@cache
def _registry() -> tuple[dict[str, Spec], dict[str, str]]:
    """(name -> Spec of every usable method, name -> why a plugin was left out)."""
    specs: list[Spec] = []
    for spec in BUILTIN:
        _check(specs, spec, BUILTIN_WIRE_IDS, "slipd.estimators.registry")
        specs.append(spec)
    broken: dict[str, str] = {}
    for point in sorted(_entry_points(), key=lambda p: p.name):
        dist = getattr(point, "dist", None)
        source = (f"entry point {point.name} = {point.value} of "
                  f"{dist.name if dist else 'an unknown distribution'}")
        try:
            spec = point.load()
            _check(specs, spec, PLUGIN_WIRE_IDS, source)
            if spec.name != point.name:
                raise ConfigError(f"{source}: names method {spec.name!r}; the entry point "
                                  "must carry the method's name")
        except Exception as exc:  # noqa: BLE001 - any plugin failure is reported, not fatal
            problem = str(exc) if isinstance(exc, ConfigError) else f"{source}: {exc!r}"
            broken[point.name] = problem
            warnings.warn(f"slipd: estimator plugin left out: {problem}", RuntimeWarning,
                          stacklevel=2)
            continue
        specs.append(spec)
    return {spec.name: spec for spec in specs}, broken


def reset_plugins() -> None:
    """Forget the entry points read so far (they are read again at the next lookup)."""
    _registry.cache_clear()


def specs() -> dict[str, Spec]:
    """Every usable method's Spec by name, builtin ones first in table order."""
    return dict(_registry()[0])


#: Separates a method's name from the parameter values set for a run (module docstring).
PARAM_SEPARATOR = ":"


def _with_values(name: str) -> Spec:
    """The Spec of ``METHOD:KEY=VALUE[:...]``: METHOD's with the values added to its overrides;
    a malformed item, an unknown key or a value that is not a number fails naming it."""
    base_name, *items = name.split(PARAM_SEPARATOR)
    base = spec(base_name.strip())
    values: dict[str, float] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip() or not value.strip():
            raise ConfigError(f"estimator {name!r}: {item!r} is not KEY=VALUE; expected "
                              f"{base.name}:KEY=VALUE[:KEY=VALUE...], e.g. "
                              f"{base.name}:min_speed=2")
        try:
            values[key.strip()] = float(value)
        except ValueError:
            raise ConfigError(f"estimator {name!r}: {key.strip()} = {value.strip()!r} is not a "
                              "number") from None
    derived = Spec(name, base.module, base.wire_id, base.family,
                   {**base.overrides, **values}, False, base.summary)
    try:
        make_params(_module(derived), derived.overrides)  # an unknown key names the known ones
    except ConfigError as exc:
        raise ConfigError(f"estimator {name!r}: {exc}") from None
    return derived


def spec(name: str) -> Spec:
    """The Spec of method ``name`` (or ``METHOD:KEY=VALUE...``, module docstring); an unknown
    name names the available ones."""
    if PARAM_SEPARATOR in name:
        return _with_values(name)
    known, broken = _registry()
    if name in known:
        return known[name]
    if name in broken:
        raise ConfigError(f"estimator {name!r} cannot be loaded: {broken[name]}")
    raise ConfigError(f"unknown estimator {name!r}; available: {', '.join(known)}")


def available() -> list[str]:
    """Names of the usable methods, in registry order."""
    return list(_registry()[0])


def ensemble_members() -> tuple[Spec, ...]:
    """The Specs ``ensemble`` fuses, in registry order."""
    return tuple(s for s in _registry()[0].values() if s.ensemble)


def parse_names(text: str) -> list[str]:
    """Method names from a command line: ``all``, a name, or comma-separated names; an unknown
    one fails naming the available ones."""
    if text.strip() == "all":
        return available()
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise ConfigError(f"no estimator named in {text!r}; available: {', '.join(available())}")
    for name in names:
        spec(name)
    return names


# ---------------------------------------------------------------------------------------------
# loading
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Method:
    """A loaded method: its Spec, module and params vector."""

    spec: Spec
    module: ModuleType
    params: np.ndarray

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def step(self) -> Callable:
        return self.module.step

    @property
    def run_ticks(self) -> Callable:
        return self.module.run_ticks

    @property
    def required(self) -> tuple:
        """The channels whose loss makes the output invalid (the module's REQUIRED, default
        the core IMU, steer and wheel set)."""
        return tuple(getattr(self.module, "REQUIRED", CORE_CHANNELS))

    @property
    def layout(self):
        """The module's state layout (``common.layout.Layout``), None where it has none."""
        return getattr(self.module, "LAYOUT", None)

    @property
    def persistent(self) -> tuple[str, ...]:
        """Names of the state elements kept across restarts (learnt offsets, calibrations)."""
        return tuple(getattr(self.module, "PERSISTENT", ()))

    def init(self, vehicle: np.ndarray) -> np.ndarray:
        return self.module.init(self.params, vehicle)


def make_params(module: ModuleType, overrides: Mapping[str, float] | None = None) -> np.ndarray:
    """The params vector of ``module`` from its DEFAULTS with ``overrides`` applied by name."""
    fields = module.PARAMS
    values = dict(module.DEFAULTS)
    for key, value in (overrides or {}).items():
        if key not in values:
            raise ConfigError(
                f"unknown parameter {key!r} for {module.__name__.rsplit('.', 1)[-1]}; "
                f"expected one of: {', '.join(sorted(values))}"
            )
        try:
            values[key] = float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"parameter {key!r}: {value!r} is not a number") from None
    missing = [f.name for f in fields if f.name.lower() not in values]
    if missing:
        raise ConfigError(f"{module.__name__}: DEFAULTS lacks {missing}")
    params = np.empty(len(fields), dtype=np.float64)
    for f in fields:
        params[f] = values[f.name.lower()]
    return params


def _module(entry: Spec) -> ModuleType:
    """The module implementing ``entry``; one that cannot be imported is a ConfigError."""
    try:
        return importlib.import_module(entry.module)
    except ImportError as exc:
        raise ConfigError(f"estimator {entry.name!r}: cannot import {entry.module}: "
                          f"{exc}") from exc


def load(name: str, overrides: Mapping[str, float] | None = None) -> Method:
    """Method ``name`` with its defaults, the Spec's overrides, then ``overrides`` by name."""
    entry = spec(name)
    module = _module(entry)
    params = make_params(module, {**entry.overrides, **(overrides or {})})
    return Method(entry, module, params)
