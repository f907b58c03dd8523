"""slipd's Python API: logs in, pandas DataFrames out, on the same kernels as the daemon.

    import slipd
    inputs = slipd.decode("drive.log", profile="default")          # SI channels per tick
    est = slipd.estimate("drive.log", estimator=["d_ekf", "zero"])  # one row per tick/method
    scores = slipd.evaluate(est, "drive.truth.csv")                 # one row per method
    sim = slipd.simulate("slalom", duration=20.0)                   # truth + a bus to replay
    e = slipd.Estimator("d_ekf", profile="default")                 # embed in your own loop
    out = e.step({"ax": 0.1, "ay": 2.0, ...}, t=0.01)

Every path goes through the codec like the car's bus (decode, E2E checks, latch, 100 Hz
sample-and-hold), then the estimator and the input supervision that decides VALID: a log
replayed here gives the daemon's outputs. Units are SI (rad, m/s, rad/s) with ISO 8855 signs
(``slipd.channels``); each DataFrame's ``attrs["units"]`` names them.

Importing slipd compiles nothing, imports neither numba nor pandas and changes no environment
variable: kernels load on first use (in numba's cache under a key of slipd's sources, see
:mod:`slipd.numba_cache`), pandas when a function returns a DataFrame.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

from slipd.errors import ConfigError, DependencyError

if TYPE_CHECKING:
    import numpy as np
    import pandas as pd

    from slipd.profile import Profile
    from slipd.replay.candump import Frames
    from slipd.replay.engine import Inputs

#: The tick interval of every estimator, s (100 Hz, as the daemon; slipd.pipeline.TICK_DT).
TICK_DT = 0.01
#: The estimate DataFrame's value columns, in slipd.channels.Out order.
OUTPUT_COLUMNS = ("beta", "beta_rate", "vx", "vy", "mu", "sigma_beta", "roll",
                  "friction_class", "status", "nis")
#: The estimate table columns (``slipd replay --out``) that hold an output in degrees.
_DEGREE_COLUMNS = {"beta_deg": "beta", "beta_rate_deg_s": "beta_rate",
                   "sigma_beta_deg": "sigma_beta", "roll_deg": "roll"}
_SI_ALIASES = {"vx_mps": "vx", "vy_mps": "vy"}


def _pandas():
    try:
        import pandas
    except ImportError as exc:
        raise DependencyError("slipd's Python API returns pandas DataFrames: "
                              "pip install 'slipd[pandas]'") from exc
    return pandas


def _profile(profile: str | os.PathLike | Profile) -> Profile:
    from slipd.profile import Profile, load_profile

    return profile if isinstance(profile, Profile) else load_profile(profile)


def _methods(estimator: str | Sequence[str] | None) -> list[str]:
    """The names ``estimator`` says; None: the default (``registry.DEFAULT_ESTIMATOR``; the
    registry is imported here, so that importing slipd loads no estimator code)."""
    from slipd.estimators import registry

    if estimator is None:
        return [registry.DEFAULT_ESTIMATOR]
    if isinstance(estimator, str):
        return registry.parse_names(estimator)
    chosen = list(estimator)
    if not chosen:
        raise ConfigError(f"no estimator named; available: {', '.join(registry.available())} "
                          f"(or 'all')")
    for name in chosen:
        registry.spec(name)  # an unknown one fails naming the available ones
    return chosen


# ---- sources: a log, python-can messages, a simulation, a DataFrame of SI channels ------


def _frames(source: Any, skip_bad: bool = False) -> Frames:
    """Frames of a log path, a :class:`Simulation` or an iterable of python-can Messages."""
    from slipd.replay.messages import frames_from_messages
    from slipd.replay.readers import read_frames

    if isinstance(source, str | os.PathLike):
        if not Path(source).exists():
            raise ConfigError(f"{source}: no such log")
        return read_frames(source, skip_bad=skip_bad)
    if isinstance(source, Simulation):
        return source.frames()
    if isinstance(source, Iterable) and not isinstance(source, bytes | Mapping):
        return frames_from_messages(source, source=f"<{type(source).__name__} of messages>")
    raise ConfigError(f"expected a log path, a slipd.Simulation, python-can Messages or a "
                      f"DataFrame of SI channels, got {type(source).__name__}")


def _inputs(source: Any, profile: Profile, skip_bad: bool = False,
            buses: Mapping[str, str] | None = None) -> Inputs:
    """The latched inputs at every tick of ``source`` (a DataFrame is taken as ticks);
    ``buses``: the profile's bus names -> the log's channel names (``--bus chassis=can0``)."""
    from slipd.replay.engine import latch_log_or_recording

    pd = _pandas()
    if isinstance(source, pd.DataFrame):
        return _inputs_of_frame(source)
    return latch_log_or_recording(_frames(source, skip_bad), profile,
                                  dict(buses) if buses else None)


def _channel_names() -> dict[str, int]:
    from slipd.channels import In

    return {c.name.lower(): int(c) for c in In}


def _inputs_of_frame(frame: pd.DataFrame) -> Inputs:
    """A DataFrame of ticks (``t`` plus SI channel columns, optional ``<channel>_valid``)
    -> the engine's inputs. A value is valid where it is finite (and its _valid column, if
    any, is true); a channel without a column is invalid throughout."""
    import numpy as np

    from slipd.channels import U_LEN, U_TIME, VALID
    from slipd.pipeline import steps_per_tick
    from slipd.replay.engine import Inputs

    names = _channel_names()
    if "t" in frame.columns:
        t = frame["t"].to_numpy(dtype=np.float64)
    elif frame.index.name == "t":
        t = frame.index.to_numpy(dtype=np.float64)
    else:
        raise ConfigError("the DataFrame needs a column (or index) 't': tick times in s")
    known = {"t", *names, *(f"{n}_valid" for n in names)}
    unknown = [str(c) for c in frame.columns if c not in known]
    if unknown:
        raise ConfigError(f"DataFrame column(s) {unknown} are not slipd input channels; "
                          f"expected 't' and some of {list(names)} (SI units, ISO 8855), each "
                          f"optionally with a '<channel>_valid' column; drop the others")
    if len(t) and not np.all(np.isfinite(t)):
        raise ConfigError(f"DataFrame row {int(np.flatnonzero(~np.isfinite(t))[0])}: t is not "
                          f"finite")
    step = np.diff(t)
    if np.any(step < 0.5 * TICK_DT):
        bad = int(np.flatnonzero(step < 0.5 * TICK_DT)[0]) + 1
        raise ConfigError(f"DataFrame row {bad}: t = {t[bad]:.6f} s is {step[bad - 1] * 1e3:.3g}"
                          f" ms after the row before; slipd's estimators run on 10 ms ticks "
                          f"(resample the data to 100 Hz, e.g. with DataFrame.resample)")
    U = np.zeros((len(t), U_LEN), dtype=np.float64)
    U[:, U_TIME] = t
    for name, ch in names.items():
        if name not in frame.columns:
            continue
        values = frame[name].to_numpy(dtype=np.float64, na_value=np.nan)
        ok = np.isfinite(values)
        if f"{name}_valid" in frame.columns:
            ok &= frame[f"{name}_valid"].to_numpy(dtype=bool)
        U[:, ch] = np.where(np.isfinite(values), values, 0.0)
        U[:, VALID + ch] = ok
    steps = steps_per_tick(t, TICK_DT)
    return Inputs(t, U, {}, 0, steps if np.any(steps > 1) else None)


# ---- decode -----------------------------------------------------------------------------


def decode(log: Any, profile: str | os.PathLike | Profile = "default", *,
           buses: Mapping[str, str] | None = None, skip_bad: bool = False) -> pd.DataFrame:
    """Decode a log through the codec and latch it onto the 100 Hz ticks (``slipd decode``).

    ``log``: a log path (candump ``.log``/``.log.gz``, ``.asc``, ``.blf``, ``.trc``, ``.mf4``),
    an iterable of python-can Messages or a :class:`Simulation`; ``buses``: a several-bus
    profile's bus names -> the log's channel names (as ``--bus chassis=can0``). Returns one
    row per tick: ``t`` (s, the log's time axis), then per channel the profile maps its SI
    value and ``<channel>_valid`` (fresh, E2E-checked and not marked unavailable at that
    tick; an invalid channel holds its last value, 0 before the first). ``attrs``: ``units``,
    ``profile``, ``frames`` and the decoder's per-message ``errors``. The frame is what
    :func:`estimate` takes back.
    """
    from slipd.profile_tools.decode import channel_columns, unit_of

    pd = _pandas()
    prof = _profile(profile)
    inputs = _inputs(log, prof, skip_bad, buses)
    columns = channel_columns(inputs, prof)
    frame = pd.DataFrame({name: values.astype(bool) if name.endswith("_valid") else values
                          for name, values in columns.items()})
    frame.attrs.update(units={c: unit_of(c) for c in columns if not c.endswith("_valid")},
                       profile=prof.name, frames=inputs.n_frames, errors=inputs.errors)
    return frame


# ---- estimate ---------------------------------------------------------------------------


def estimate(source: Any, profile: str | os.PathLike | Profile = "default",
             estimator: str | Sequence[str] | None = None, *,
             overrides: Mapping[str, float] | None = None,
             buses: Mapping[str, str] | None = None, skip_bad: bool = False) -> pd.DataFrame:
    """Run estimators over a log, python-can Messages, a :class:`Simulation` or a DataFrame
    of SI channels per 10 ms tick (``t`` plus channel columns, as :func:`decode` returns).

    ``estimator``: a name, a list of names, comma-separated names or ``"all"`` (None: the
    default, ``d_ekf``);
    ``overrides``: parameter values by name (one method only); ``buses``: as :func:`decode`.
    Returns one row per tick and
    method: ``t`` (s), ``estimator``, ``beta``, ``beta_rate``, ``vx``, ``vy``, ``mu`` (NaN where
    the method does not estimate it), ``sigma_beta``, ``roll`` (rad, rad/s, m/s),
    ``friction_class``, ``status`` (slipd.channels.Status bits) and ``valid`` (the VALID bit:
    what a controller may trust). ``attrs["units"]`` names the units.
    """
    pd = _pandas()
    prof = _profile(profile)
    methods = _methods(estimator)
    if overrides and len(methods) != 1:
        raise ConfigError("overrides apply to one estimator; name one")
    inputs = _inputs(source, prof, skip_bad, buses)
    from slipd.replay.engine import run_method

    results = [run_method(inputs, prof, name, dict(overrides or {})) for name in methods]
    frame = pd.concat([_estimate_frame(r.method, r.t, r.out) for r in results],
                      ignore_index=True)
    frame["estimator"] = pd.Categorical(frame["estimator"], categories=methods)
    frame.attrs.update(units=estimate_units(), profile=prof.name)
    return frame


def estimate_units() -> dict[str, str]:
    """Units of the :func:`estimate` columns."""
    from slipd.channels import OUT_UNITS, Out

    return {"t": "s", **{c: OUT_UNITS[Out(i)] for i, c in enumerate(OUTPUT_COLUMNS)},
            "valid": "bool"}


def _estimate_frame(method: str, t: np.ndarray, out: np.ndarray) -> pd.DataFrame:
    import numpy as np

    from slipd.channels import Out, Status

    pd = _pandas()
    columns: dict[str, Any] = {"t": t, "estimator": method}
    for i, name in enumerate(OUTPUT_COLUMNS):
        columns[name] = out[:, i]
    status = np.nan_to_num(out[:, Out.STATUS]).astype(np.int64)
    columns["friction_class"] = np.nan_to_num(out[:, Out.FRICTION_CLASS]).astype(np.int8)
    columns["status"] = status.astype(np.int16)
    columns["valid"] = (status & int(Status.VALID)) != 0
    return pd.DataFrame(columns)


def _outputs_by_method(estimates: pd.DataFrame) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{method: (t, out [n, N_OUT])} of an :func:`estimate` frame, or of a replay table read
    back (``slipd replay --out``: degrees, ``*_deg`` columns)."""
    import numpy as np

    from slipd.channels import N_OUT, Out

    pd = _pandas()
    if not isinstance(estimates, pd.DataFrame):
        raise ConfigError(f"expected the DataFrame of slipd.estimate (or a replay table), got "
                          f"{type(estimates).__name__}")
    frame = estimates
    renames = {c: s for c, s in _SI_ALIASES.items() if c in frame.columns}
    if renames:
        frame = frame.rename(columns=renames)
    need = ["t", "estimator", "beta", "vx", "status"]
    degrees = [c for c in _DEGREE_COLUMNS if c in frame.columns]
    have = set(frame.columns) | {_DEGREE_COLUMNS[c] for c in degrees}
    missing = [c for c in need if c not in have]
    if missing:
        raise ConfigError(f"estimates lack column(s) {missing}; expected the DataFrame "
                          f"slipd.estimate returns (or a slipd replay table)")
    result = {}
    for method, rows in frame.groupby("estimator", sort=False, observed=True):
        out = np.full((len(rows), N_OUT), np.nan)
        for i, name in enumerate(OUTPUT_COLUMNS):
            if name in rows.columns:
                out[:, i] = rows[name].to_numpy(dtype=np.float64, na_value=np.nan)
        for column, name in _DEGREE_COLUMNS.items():
            if column in rows.columns:
                out[:, OUTPUT_COLUMNS.index(name)] = np.radians(
                    rows[column].to_numpy(dtype=np.float64, na_value=np.nan))
        out[:, Out.STATUS] = np.nan_to_num(out[:, Out.STATUS])
        result[str(method)] = (rows["t"].to_numpy(dtype=np.float64), out)
    return result


# ---- truth and evaluate -----------------------------------------------------------------


def read_truth(path: str | os.PathLike) -> pd.DataFrame:
    """A truth CSV (``slipd sim``, ``slipd import --truth``) with ``t`` on the log's time
    axis (the file's t plus its log_epoch), SI units, ISO 8855; ``attrs["epoch"]``."""
    from slipd.sim.writer import read_truth_csv

    pd = _pandas()
    if not Path(path).exists():
        raise ConfigError(f"{path}: no such truth file")
    columns, epoch = read_truth_csv(path)
    frame = pd.DataFrame(columns)
    frame["t"] = frame["t"] + epoch
    frame.attrs.update(epoch=epoch, source=str(path))
    return frame


def _truth_frame(truth: Any) -> pd.DataFrame:
    pd = _pandas()
    if isinstance(truth, Simulation):
        return truth.truth
    if isinstance(truth, str | os.PathLike):
        return read_truth(truth)
    if isinstance(truth, pd.DataFrame):
        missing = [c for c in ("t", "beta", "vx") if c not in truth.columns]
        if missing:
            raise ConfigError(f"truth lacks column(s) {missing}; expected t (s, the estimates' "
                              f"time axis), beta (rad), vx (m/s), optionally speed (m/s)")
        return truth
    raise ConfigError(f"expected a truth CSV path, a DataFrame or a slipd.Simulation, got "
                      f"{type(truth).__name__}")


def evaluate(estimates: pd.DataFrame, truth: Any, *, min_speed_kph: float = 20.0
             ) -> pd.DataFrame:
    """Score every method of ``estimates`` against ``truth`` (slipd.eval.metrics).

    ``estimates``: what :func:`estimate` returns (or a replay table read back with pandas);
    ``truth``: a truth CSV path, a :class:`Simulation`, or a DataFrame with ``t`` on the
    estimates' time axis, ``beta`` (rad), ``vx`` (m/s) and optionally ``speed`` (m/s). Ticks
    with truth speed above ``min_speed_kph`` are scored. Returns one row per method (index
    ``estimator``): beta RMS/p99/max (deg) and vx RMS (m/s) over the scored ticks, and the
    validity figures: ``valid_fraction``, the same errors over the VALID ticks,
    ``valid_err_over_2deg``/``_5deg`` and ``sigma2_coverage`` (shares, 0..1).
    """
    import numpy as np

    from slipd.eval.metrics import KPH, errors

    pd = _pandas()
    if not math.isfinite(min_speed_kph) or min_speed_kph < 0:
        raise ConfigError(f"min_speed_kph {min_speed_kph}: expected a speed >= 0 km/h")
    truth = _truth_frame(truth)
    truth_t = truth["t"].to_numpy(dtype=np.float64)
    speed = truth["speed"].to_numpy(dtype=np.float64) if "speed" in truth.columns else None
    rows = {}
    for method, (t, out) in _outputs_by_method(estimates).items():
        try:
            errs = errors(t, out, truth_t, truth["beta"].to_numpy(dtype=np.float64),
                          truth["vx"].to_numpy(dtype=np.float64), speed,
                          min_speed=min_speed_kph * KPH)
        except ValueError as exc:
            raise ConfigError(f"evaluate {method}: {exc}") from exc
        rows[method] = errs.scores().as_dict()
    frame = pd.DataFrame.from_dict(rows, orient="index")
    frame.index.name = "estimator"
    frame.attrs.update(min_speed_kph=min_speed_kph)
    return frame


# ---- plot -------------------------------------------------------------------------------


def plot(estimates: pd.DataFrame, truth: Any, path: str | os.PathLike | None = None, *,
         inputs: pd.DataFrame | None = None, estimators: Sequence[str] | None = None,
         min_speed_kph: float = 20.0, title: str = "", overlay_max: int = 4):
    """Draw estimates against the truth (slipd.eval.plots.plot_evaluation): beta over time
    where VALID, each method's VALID spans, the error over time on VALID ticks, the CDF of
    |beta error| over the ticks :func:`evaluate` scores and, with ``inputs`` (a
    :func:`decode` frame), panels of ay, yaw rate, steer and the wheel-speed mean. More than
    ``overlay_max`` methods become small multiples. Returns the matplotlib Figure (shown by a
    notebook), written to ``path`` (.png, .pdf, .svg) when given."""
    import numpy as np

    from slipd.eval import plots
    from slipd.eval.metrics import KPH, errors

    truth = _truth_frame(truth)
    series = _outputs_by_method(estimates)
    if estimators is not None:
        unknown = [m for m in estimators if m not in series]
        if unknown:
            raise ConfigError(f"plot: estimator(s) {unknown} are not in the estimates "
                              f"({list(series)})")
        series = {m: series[m] for m in estimators}
    truth_t = truth["t"].to_numpy(dtype=np.float64)
    beta = truth["beta"].to_numpy(dtype=np.float64)
    speed = truth["speed"].to_numpy(dtype=np.float64) if "speed" in truth.columns else None
    errs = {m: errors(t, out, truth_t, beta, truth["vx"].to_numpy(dtype=np.float64), speed,
                      min_speed=min_speed_kph * KPH) for m, (t, out) in series.items()}
    return plots.plot_evaluation(path, truth_t, beta, series, errs, title=title,
                                 inputs=_input_series(inputs), overlay_max=overlay_max)


def _input_series(inputs: pd.DataFrame | None) -> dict[str, tuple]:
    """The input panels' series of a :func:`decode` frame (those it has)."""
    import numpy as np

    from slipd.eval.plots import input_series

    if inputs is None:
        return {}

    def channel(name: str):
        if name not in inputs.columns:
            return None
        valid = inputs.get(f"{name}_valid")
        return (inputs[name].to_numpy(dtype=np.float64),
                None if valid is None else valid.to_numpy(dtype=bool))

    return input_series(inputs["t"].to_numpy(dtype=np.float64), channel)


# ---- simulate ---------------------------------------------------------------------------


@dataclass
class Simulation:
    """A simulated drive: its ground truth and the bus its car would carry.

    ``truth``: DataFrame at 100 Hz, ``t`` on the log's time axis (SI, ISO 8855; columns of
    slipd.sim.writer.TRUTH_COLUMNS); ``log``/``truth_path``: the files when written (``out``);
    ``result``: the simulator's SimResult. Pass it to :func:`decode`/:func:`estimate` as a log
    and to :func:`evaluate` as the truth.
    """

    scenario: str
    truth: pd.DataFrame
    result: Any
    profile: Any
    epoch: float
    log: Path | None = None
    truth_path: Path | None = None

    def frames(self) -> Frames:
        """Every frame of the drive through the codec, time-sorted (what the log holds)."""
        import numpy as np

        from slipd.replay.candump import FLAG_FD, Frames
        from slipd.sim.writer import bus_channels, encode_frames

        t, frame_id, data, dlc = encode_frames(self.result, self.profile, self.epoch)
        channel, channels = bus_channels(frame_id, self.profile)
        flags = np.where(dlc > 8, FLAG_FD, 0).astype(np.uint8)  # as write_candump writes it
        return Frames(t, frame_id, flags, dlc, data, channel, channels,
                      f"<simulation {self.scenario}>")

    def messages(self) -> Iterable:
        """The frames as python-can Messages (e.g. to send onto a bus)."""
        import can

        from slipd.replay.candump import FLAG_EXTENDED, FLAG_FD

        frames = self.frames()
        for k in range(len(frames)):
            flags = int(frames.flags[k])
            yield can.Message(timestamp=float(frames.t[k]),
                              arbitration_id=int(frames.frame_id[k]),
                              is_extended_id=bool(flags & FLAG_EXTENDED),
                              is_fd=bool(flags & FLAG_FD),
                              data=bytes(frames.data[k, : frames.dlc[k]]),
                              channel=frames.channels[frames.channel[k]])


def simulate(scenario: str, *, seed: int = 0, vehicle: int = 2, duration: float | None = None,
             variant: str | None = None, sensor: Mapping[str, Any] | None = None,
             profile: str | os.PathLike | Profile = "default",
             out: str | os.PathLike | None = None) -> Simulation:
    """Simulate ``scenario`` (``slipd sim --list``) on the independent plant: sensor seed
    ``seed``, CommonRoad parameter set ``vehicle``, an optional sensor ``variant``
    (slipd.sim.variants) and ``sensor`` overrides; ``duration`` cuts it (s). With ``out``
    (a directory) the log and truth CSV are written there as ``slipd sim`` writes them.
    """
    from slipd.sim.core import simulate as run_simulation
    from slipd.sim.writer import START_EPOCH, write_log, write_truth_csv

    pd = _pandas()
    prof = _profile(profile)
    try:
        result = run_simulation(scenario, vehicle=vehicle, seed=seed, duration=duration,
                                profile=prof, sensor=dict(sensor or {}), variant=variant)
    except ImportError as exc:
        raise DependencyError(f"slipd.simulate needs {exc.name}: pip install 'slipd[sim]'"
                              ) from exc
    from slipd.sim.writer import TRUTH_COLUMNS

    truth = pd.DataFrame({c: result.truth[c] for c in TRUTH_COLUMNS if c in result.truth})
    truth["t"] = truth["t"] + START_EPOCH
    truth.attrs.update(epoch=START_EPOCH, scenario=scenario, seed=seed)
    sim = Simulation(scenario, truth, result, prof, START_EPOCH)
    if out is not None:
        folder = Path(out)
        folder.mkdir(parents=True, exist_ok=True)
        sim.log, sim.truth_path = folder / f"{scenario}.log", folder / f"{scenario}.truth.csv"
        write_log(sim.log, result, prof, START_EPOCH)
        write_truth_csv(sim.truth_path, result, START_EPOCH)
    return sim


# ---- Estimator: one method, one tick at a time -------------------------------------------


class Output(NamedTuple):
    """One tick's estimate (SI, ISO 8855): what SLIPD_STATE/SLIPD_AUX would carry."""

    t: float
    beta: float
    beta_rate: float
    vx: float
    vy: float
    mu: float
    sigma_beta: float
    roll: float
    friction_class: int
    status: int
    valid: bool


class Estimator:
    """One method on one car, stepped tick by tick from your own loop.

    Two ways in, the same kernels and supervision as the daemon:

    * ``step(values, t=...)``: one 10 ms tick of SI channel values you have already decoded
      (a mapping of channel names, e.g. a row of :func:`decode`; a channel that is absent,
      NaN or has a false ``<channel>_valid`` is invalid at this tick);
    * ``receive(message)`` for each CAN frame (python-can Message) and ``tick(t)`` every
      10 ms: the profile's codec decodes, E2E-checks and latches the frames as on the car.
      A several-bus profile reads each message's ``channel`` as the bus of that name, or as
      ``buses`` maps them (profile bus name -> channel name, as ``slipd run --bus``).

    A tick ``t`` more than 10 ms after the last steps the method once per elapsed tick (at
    most 101 times), as the daemon does after an overrun.
    """

    def __init__(self, name: str | None = None,
                 profile: str | os.PathLike | Profile = "default",
                 overrides: Mapping[str, float] | None = None,
                 buses: Mapping[str, str] | None = None):
        import numpy as np

        from slipd.channels import N_OUT, U_LEN
        from slipd.pipeline import Pipeline

        if name is not None and (not isinstance(name, str) or name == "all" or "," in name):
            raise ConfigError(f"Estimator takes one estimator name, got {name!r}")
        self.name = _methods(name)[0]
        self.profile = _profile(profile)
        from slipd.codec import Codec

        self._pipeline = Pipeline(self.name, self.profile, dict(overrides or {}), TICK_DT)
        self._codec = Codec(self.profile)
        names = self._codec.inputs.buses
        #: message channel name -> bus index; None: a one-bus profile reads every channel
        self._bus_of = None if len(names) == 1 and not buses else (
            {str(ch): self._codec.bus_index(bus) for bus, ch in buses.items()} if buses
            else {bus: i for i, bus in enumerate(names)})
        self._names = _channel_names()
        self._u = np.zeros(U_LEN)
        self._out = np.zeros(N_OUT)
        self.reset()

    @property
    def channels(self) -> tuple[str, ...]:
        """The input channel names ``step`` accepts (slipd.channels.In, lower case)."""
        return tuple(self._names)

    def reset(self) -> None:
        """Start again: the method's initial state, an empty latch, no previous tick."""
        from slipd.codec import DecodeState

        self._state = self._pipeline.new_state()
        self._codec.state = DecodeState.new(self._codec.inputs.n_messages)
        self._last_t: float | None = None

    def step(self, values: Mapping[str, Any] | None = None, t: float | None = None,
             **channels: float) -> Output:
        """One tick of SI channel values (``values`` and/or keyword arguments); ``t``: the tick
        time in s (default: 10 ms after the last tick; a ``t`` key in ``values`` counts too)."""
        from slipd.channels import VALID

        merged = {**(values or {}), **channels}
        if "t" in merged:
            t = float(merged.pop("t")) if t is None else t
        u = self._u
        u[:] = 0.0
        flags = {}
        for key, value in merged.items():
            ch = self._names.get(key)
            if ch is not None:
                v = float(value)
                if math.isfinite(v):
                    u[ch] = v
                    u[VALID + ch] = 1.0
            elif key.endswith("_valid") and key[: -len("_valid")] in self._names:
                flags[self._names[key[: -len("_valid")]]] = bool(value)
            else:
                raise ConfigError(f"Estimator.step: {key!r} is not an input channel; expected "
                                  f"'t' and some of {list(self._names)} (SI units), optionally "
                                  f"'<channel>_valid'")
        for ch, ok in flags.items():
            if not ok:
                u[VALID + ch] = 0.0
        return self._advance(self._tick_time(t), sample=False)

    def receive(self, message) -> bool:
        """Decode one CAN frame (python-can Message, its timestamp in s) into the latch;
        returns whether the profile's codec accepted it (a known ID with a good CRC/counter).
        Error and remote frames are ignored, as on the car."""
        if message.is_error_frame or message.is_remote_frame:
            return False
        bus = 0
        if self._bus_of is not None:
            bus = self._bus_of.get(str(message.channel), -1)
            if bus < 0:  # a channel the profile does not read
                return False
        row = self._codec.decode(int(message.arbitration_id), bytes(message.data or b""),
                                 float(message.timestamp), bool(message.is_extended_id),
                                 bus=bus)
        return row >= 0

    def tick(self, t: float) -> Output:
        """One tick at time ``t`` (s, the frames' time axis) on what :meth:`receive` latched:
        each channel valid when its newest value is fresh and checked."""
        return self._advance(self._tick_time(t), sample=True)

    def _tick_time(self, t: float | None) -> float:
        if t is None:
            return (self._last_t + TICK_DT) if self._last_t is not None else 0.0
        t = float(t)
        if not math.isfinite(t) or (self._last_t is not None and t <= self._last_t):
            raise ConfigError(f"Estimator: tick time {t} must be finite and after the last "
                              f"tick ({self._last_t})")
        return t

    def _advance(self, t: float, sample: bool) -> Output:
        from slipd.channels import U_TIME, Out, Status
        from slipd.pipeline import catch_up_steps

        u, out = self._u, self._out
        if sample:
            self._codec.sample(t, u)
        u[U_TIME] = t
        steps = 1
        if self._last_t is not None:
            steps = int(catch_up_steps(int(round((t - self._last_t) / TICK_DT)) - 1))
        self._last_t = t
        self._pipeline.tick(self._state, u, out, steps)
        status = int(out[Out.STATUS])
        return Output(t, float(out[Out.BETA]), float(out[Out.BETA_RATE]), float(out[Out.VX]),
                      float(out[Out.VY]), float(out[Out.MU]), float(out[Out.SIGMA_BETA]),
                      float(out[Out.ROLL]), int(out[Out.FRICTION_CLASS]), status,
                      bool(status & int(Status.VALID)))


__all__ = ["decode", "estimate", "evaluate", "read_truth", "plot", "simulate", "Simulation",
           "Estimator", "Output", "estimate_units", "TICK_DT"]
