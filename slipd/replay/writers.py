"""Per-tick estimate files by suffix: CSV (+ JSON sidecar), Parquet, MCAP and MF4.

Every writer is fed in chunks (:meth:`EstimateWriter.write` takes any run of one method's
ticks, :meth:`~EstimateWriter.write_inputs` any run of the latched inputs), so a streaming
replay hands them a chunk of ticks at a time; :func:`write_estimates` writes a whole run. A
writer writes FILE's hidden sibling ``.STEM.partial.SUFFIX`` and renames it to FILE when it
closes, so a replay that fails half-way leaves no file that looks complete (``abort``, or
leaving the ``with`` block on an exception, removes it).

The tables (CSV, Parquet) hold one method's rows after another's, in the order the methods
were first written, however the rows were handed in: the first method's rows go straight to
the file, the others' wait in hidden spill files beside it (CSV text, Arrow IPC with zstd;
Parquet keeps them in memory while they fit in HOLD_BYTES) that ``close`` appends. Parquet
row groups hold ROW_GROUP_TICKS rows of one method each (a method's last group fewer), each
written from contiguous arrays. So a streamed run and a whole-run
write give the same bytes (tests/test_stream.py).

* ``.csv``: plain (one header row, ``pandas.read_csv`` with defaults reads it), the table of
  :data:`TABLE_COLUMNS` in degrees as ``slipd replay`` always wrote; what it is (units, status
  bits, source, profile) goes to ``FILE.csv.meta.json``.
* ``.parquet``: the same table (snappy; the float columns byte-stream-split), each field's
  unit in its field metadata and the run's description in the schema metadata
  (``b"slipd"``, JSON).
* ``.mcap`` (Foxglove, ``mcap`` package): JSON messages with a JSON schema (units in each
  property's description): ``/slipd/inputs`` (the latched input channels and their validity
  per tick), ``/slipd/estimate/<method>`` (the Python API's SI columns) and ``/slipd/truth``
  when a truth is given; log time = the tick time in ns.
* ``.mf4`` (ASAM MDF 4.1, asammdf): a channel group per method (``<method>.beta``, ... SI, with
  units), ``inputs.<channel>`` and ``truth.<column>``; times from the header's start time.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slipd.channels import N_IN, OUT_UNITS, VALID, In, Out, Status
from slipd.errors import ConfigError, DependencyError
from slipd.profile_tools.decode import unit_of
from slipd.replay import textformat

DEG = 180.0 / math.pi
#: rows of a Parquet row group (22 minutes of one method's ticks, ~10 MB in memory)
ROW_GROUP_TICKS = 1 << 17
#: How the Parquet table is encoded. Measured on a 10-minute replay's 60,000 rows
#: (benchmarks/replay.py writes them at the end of the run, on its critical path):
#: zstd with PLAIN floats (until stop 35) 6.0-6.4 ms and 2.89 MB; byte-stream-split floats
#: (their bytes grouped by significance, which compresses: the exponent bytes repeat)
#: with zstd 4.5 ms / 2.34 MB, with lz4 2.4 ms / 2.38 MB, with snappy 2.0 ms / 2.52 MB; no
#: compression 1.4 ms / 3.85 MB. Snappy is the codec every Parquet reader has; the batch
#: size is pyarrow's values per encoding call (1024 by default: ~4x slower uncompressed).
#: Dictionary pages only for the estimator name: on the float columns (every value distinct)
#: pyarrow's default builds a dictionary per column and gives it up.
PARQUET_COMPRESSION = "snappy"
PARQUET_WRITE_BATCH = 1 << 16
#: Arrow bytes of the later methods' rows a Parquet writer holds in memory before it spills
#: them to files: a short log (a fleet's minutes-long drives) never touches a spill (writing
#: and reading back the spills was ~120 ms of a ~0.75 s log with every method), a long one
#: spills as before with at most this much more memory.
HOLD_BYTES = 32 << 20

#: The replay table (CSV, Parquet): name -> (Out column or None, scale from SI, unit).
TABLE_COLUMNS: dict[str, tuple[Out | None, float, str]] = {
    "t": (None, 1.0, "s"),
    "estimator": (None, 1.0, ""),
    "beta_deg": (Out.BETA, DEG, "deg"),
    "beta_rate_deg_s": (Out.BETA_RATE, DEG, "deg/s"),
    "vx_mps": (Out.VX, 1.0, "m/s"),
    "vy_mps": (Out.VY, 1.0, "m/s"),
    "mu": (Out.MU, 1.0, "1"),
    "sigma_beta_deg": (Out.SIGMA_BETA, DEG, "deg"),
    "roll_deg": (Out.ROLL, DEG, "deg"),
    "friction_class": (Out.FRICTION_CLASS, 1.0, "1"),
    "status": (Out.STATUS, 1.0, "bits"),
}
DESCRIPTIONS = {
    "t": "tick time on the log's time axis",
    "estimator": "method name (slipd --estimator)",
    "beta": "sideslip angle at the CoG, atan2(vy, vx), ISO 8855 (+ left)",
    "beta_rate": "rate of beta",
    "vx": "longitudinal velocity at the CoG",
    "vy": "lateral velocity at the CoG (+ left)",
    "mu": "estimated road friction; empty/NaN where the method does not estimate it",
    "sigma_beta": "the method's 1-sigma of beta",
    "roll": "body roll angle (+ right side down)",
    "friction_class": "0 unknown, 1 low (ice/snow), 2 medium (wet), 3 high (dry)",
    "status": "bit field: " + ", ".join(f"{s.value} {s.name}" for s in Status),
    "valid": "the VALID bit: what a controller may trust",
}
#: SI estimate columns (the Python API's, MCAP, MF4): name -> Out column.
SI_COLUMNS = {"beta": Out.BETA, "beta_rate": Out.BETA_RATE, "vx": Out.VX, "vy": Out.VY,
              "mu": Out.MU, "sigma_beta": Out.SIGMA_BETA, "roll": Out.ROLL,
              "friction_class": Out.FRICTION_CLASS, "status": Out.STATUS}


def _describe(name: str) -> str:
    base = name.removesuffix("_deg_s").removesuffix("_deg").removesuffix("_mps")
    return DESCRIPTIONS.get(base, "")


@dataclass
class RunInfo:
    """What a file records about its run (sidecar, schema metadata, MCAP metadata)."""

    methods: list[str]
    profile: str = ""
    source: str = ""
    #: input channels the inputs topic/group carries (default: none written)
    channels: list[In] = field(default_factory=list)
    #: the run's first instant on the log's time axis (MF4's header start time)
    start: float | None = None
    truth_source: str = ""

    def as_dict(self) -> dict:
        from slipd.cli import _version

        return {"created_by": _version(), "source": self.source, "profile": self.profile,
                "estimators": self.methods, "tick_s": 0.01, "truth": self.truth_source or None}


class EstimateWriter:
    """Base of the writers: ``write`` a method's chunk, ``write_inputs`` a chunk of latched
    inputs (t [n], U [n, U_LEN]), ``write_truth`` the truth columns (``t`` on the log's time
    axis plus SI columns), then ``close`` (or ``abort``). A context manager: an exception
    inside the block aborts. Subclasses write ``self.partial``; ``close`` renames it to
    ``self.path``."""

    def __init__(self, path: Path, info: RunInfo):
        self.path = Path(path)
        self.info = info
        self.partial = partial_path(self.path)
        self._finished = False

    def write(self, method: str, t: np.ndarray, out: np.ndarray) -> None:
        raise NotImplementedError

    def write_inputs(self, t: np.ndarray, U: np.ndarray) -> None:
        """Table formats hold estimates only."""

    def write_truth(self, columns: dict[str, np.ndarray]) -> None:
        """Table formats hold estimates only."""

    def close(self) -> None:
        """Finish the file (subclasses first complete ``self.partial``) and put it in place."""
        if self._finished:
            return
        self._finished = True
        try:
            os.replace(self.partial, self.path)
        except OSError as exc:
            raise ConfigError(f"--out {self.path}: cannot write: {exc.strerror or exc}"
                              ) from exc

    def abort(self) -> None:
        """Drop what was written (a replay that failed): no file appears at ``path``."""
        self._finished = True
        self._discard()
        self.partial.unlink(missing_ok=True)

    def _discard(self) -> None:
        """Close open handles without finishing the file (subclasses)."""

    def __enter__(self) -> EstimateWriter:
        return self

    def __exit__(self, kind, value, traceback) -> None:
        if kind is None:
            self.close()
        else:
            self.abort()


def partial_path(path: Path) -> Path:
    """Where a writer writes ``path`` until it closes: ``.STEM.partial.SUFFIX`` beside it
    (hidden; the suffix kept, as asammdf insists on it)."""
    path = Path(path)
    return path.with_name(f".{path.stem}.partial{path.suffix}")


class _MethodOrder:
    """The first method written goes to the file; every other one to a spill file beside it,
    appended at close in the order the methods first came (see the module docstring).
    ``handles``: each spill's open writer (the format's), by method, in that order."""

    def __init__(self, path: Path, suffix: str):
        self.path, self.suffix = path, suffix
        self.direct: str | None = None
        self.spills: dict[str, Path] = {}
        self.handles: dict[str, object] = {}

    def is_direct(self, method: str) -> bool:
        if self.direct is None:
            self.direct = method
        return method == self.direct

    def handle(self, method: str, open_spill: Callable[[Path], object]):
        """The spill writer of ``method``, opened on its path the first time."""
        if method not in self.handles:
            self.spills[method] = self.path.with_name(
                f".{self.path.stem}.spill{len(self.spills)}{self.suffix}")
            self.handles[method] = open_spill(self.spills[method])
        return self.handles[method]

    def remove(self) -> None:
        for spill in self.spills.values():
            spill.unlink(missing_ok=True)

    def discard(self) -> None:
        """Close every spill writer and remove the spill files (an aborted run)."""
        for handle in self.handles.values():
            handle.close()
        self.remove()


def _table_values(t: np.ndarray, out: np.ndarray) -> dict[str, np.ndarray]:
    columns = {"t": t}
    for name, (column, scale, _) in TABLE_COLUMNS.items():
        if column is not None:
            columns[name] = out[:, column] * scale
    columns["friction_class"] = np.nan_to_num(out[:, Out.FRICTION_CLASS]).astype(np.int8)
    columns["status"] = np.nan_to_num(out[:, Out.STATUS]).astype(np.int16)
    return columns


def parquet_options(schema) -> dict:
    """pyarrow.parquet.ParquetWriter's options for a table of ``schema`` (PARQUET_COMPRESSION:
    floats byte-stream-split, a dictionary only for the estimator name)."""
    import pyarrow as pa

    floats = [f.name for f in schema if pa.types.is_floating(f.type)]
    return {"compression": PARQUET_COMPRESSION, "use_dictionary": ["estimator"],
            "column_encoding": dict.fromkeys(floats, "BYTE_STREAM_SPLIT"),
            "write_batch_size": PARQUET_WRITE_BATCH}


def _open(path: Path, mode: str):
    try:
        return open(path, mode, **({} if "b" in mode else {"encoding": "utf-8"}))
    except OSError as exc:
        raise ConfigError(f"--out {path}: cannot write: {exc.strerror or exc}") from exc


class CsvWriter(EstimateWriter):
    """Plain CSV, one header row; FILE.csv.meta.json describes it. The text is written by
    ``textformat.format_rows`` (numba): the bytes Python's ``f"{x:.5f}"`` gives."""

    #: digits after the point per TABLE_COLUMNS column but ``estimator`` (INTEGER: whole)
    DECIMALS = np.array([6, 5, 4, 4, 4, 4 + textformat.EMPTY_IF_NAN, 5, 4, textformat.INTEGER,
                         textformat.INTEGER], dtype=np.int64)

    def __init__(self, path: Path, info: RunInfo):
        super().__init__(path, info)
        self._handle = _open(self.partial, "wb")
        self._handle.write((",".join(TABLE_COLUMNS) + "\n").encode())
        self._order = _MethodOrder(self.path, ".csv")

    def write(self, method: str, t: np.ndarray, out: np.ndarray) -> None:
        c = _table_values(t, out)
        values = np.column_stack([c[name] for name in TABLE_COLUMNS if name != "estimator"])
        text = textformat.format_csv(values, self.DECIMALS, method, text_at=1)
        if self._order.is_direct(method):
            self._handle.write(text)
            return
        self._order.handle(method, lambda path: _open(path, "w+b")).write(text)

    def close(self) -> None:
        if self._finished:
            return
        try:
            for spill in self._order.handles.values():
                spill.seek(0)
                shutil.copyfileobj(spill, self._handle, 1 << 22)
                spill.close()
            self._handle.close()
            meta = {**self.info.as_dict(),
                    "format": "slipd estimates, one row per 10 ms tick and method",
                    "columns": {n: {"unit": u, "description": _describe(n)}
                                for n, (_, _, u) in TABLE_COLUMNS.items()}}
            sidecar = sidecar_of(self.path)
            partial = partial_path(sidecar)
            partial.write_text(json.dumps(meta, indent=2) + "\n")
            os.replace(partial, sidecar)
        finally:
            self._order.remove()
        super().close()

    def _discard(self) -> None:
        self._order.discard()
        self._handle.close()


def sidecar_of(path: Path) -> Path:
    """The JSON description beside a CSV table: FILE.csv.meta.json."""
    return Path(path).with_name(Path(path).name + ".meta.json")


class ParquetWriter(EstimateWriter):
    """Parquet (:func:`parquet_options`) by row groups of ROW_GROUP_TICKS rows: units in the
    field metadata, the run in the schema's."""

    def __init__(self, path: Path, info: RunInfo):
        super().__init__(path, info)
        try:
            import pyarrow as pa
            import pyarrow.parquet as pq
        except ImportError as exc:
            raise DependencyError("--out FILE.parquet needs pyarrow: pip install "
                                  "'slipd[parquet]'") from exc
        self._pa = pa
        types = {"t": pa.float64(), "estimator": pa.dictionary(pa.int32(), pa.string()),
                 "friction_class": pa.int8(), "status": pa.int16()}
        fields = [pa.field(name, types.get(name, pa.float64()),
                           metadata={"unit": unit, "description": _describe(name)})
                  for name, (_, _, unit) in TABLE_COLUMNS.items()]
        self.schema = pa.schema(fields, metadata={"slipd": json.dumps(info.as_dict())})
        self._dictionary = pa.array(list(info.methods), type=pa.string())
        try:
            self._writer = pq.ParquetWriter(str(self.partial), self.schema,
                                            **parquet_options(self.schema))
        except OSError as exc:
            raise ConfigError(f"--out {path}: cannot write: {exc}") from exc
        self._order = _MethodOrder(self.path, ".arrows")
        #: the later methods' tables while they fit in HOLD_BYTES (first-written order)
        self._held: dict[str, list] | None = {}
        self._held_bytes = 0
        self._waiting: list = []  # tables of the current method not yet in a row group
        self._waiting_rows = 0

    def _table(self, method: str, t: np.ndarray, out: np.ndarray):
        pa = self._pa
        columns = _table_values(t, out)
        index = self.info.methods.index(method)
        arrays = []
        for f in self.schema:
            if f.name == "estimator":
                arrays.append(pa.DictionaryArray.from_arrays(
                    pa.array(np.full(len(t), index, dtype=np.int32)), self._dictionary))
            else:
                arrays.append(pa.array(columns[f.name], type=f.type, from_pandas=f.name == "mu"))
        return pa.Table.from_arrays(arrays, schema=self.schema)

    def write(self, method: str, t: np.ndarray, out: np.ndarray) -> None:
        if not len(t):
            return
        table = self._table(method, t, out)
        if self._order.is_direct(method):
            self._add(table)
            return
        if self._held is not None:
            self._held.setdefault(method, []).append(table)
            self._held_bytes += table.nbytes
            if self._held_bytes > HOLD_BYTES:
                held, self._held = self._held, None
                for name, tables in held.items():
                    for part in tables:
                        self._spill(name, part)
            return
        self._spill(method, table)

    def _spill(self, method: str, table) -> None:
        options = self._pa.ipc.IpcWriteOptions(compression="zstd")
        self._order.handle(method, lambda path: self._pa.ipc.new_stream(
            str(path), self.schema, options=options)).write_table(table)

    def _add(self, table) -> None:
        """Rows of the current method: full row groups are written as they fill."""
        self._waiting.append(table)
        self._waiting_rows += table.num_rows
        while self._waiting_rows >= ROW_GROUP_TICKS:
            self._write_group(ROW_GROUP_TICKS)

    def _write_group(self, rows: int) -> None:
        waiting = self._pa.concat_tables(self._waiting)
        self._writer.write_table(waiting.slice(0, rows).combine_chunks(),
                                 row_group_size=ROW_GROUP_TICKS)
        rest = waiting.slice(rows)
        self._waiting = [rest] if rest.num_rows else []
        self._waiting_rows = rest.num_rows

    def add_metadata(self, metadata: dict[str, str]) -> None:
        """More key-value metadata in the file's footer (known only at the end, e.g. the
        log's SHA-256); ``pq.read_schema(FILE).metadata`` has it with the schema's."""
        self._writer.add_key_value_metadata(metadata)

    def _end_method(self) -> None:
        if self._waiting_rows:
            self._write_group(self._waiting_rows)

    def close(self) -> None:
        if self._finished:
            return
        try:
            self._end_method()
            for tables in (self._held or {}).values():
                for table in tables:
                    self._add(table)
                self._end_method()
            self._held = None
            for method, spill in self._order.handles.items():
                spill.close()
                # a NativeFile, not the path: open_stream memory-maps a path, and the pages
                # of a spill read back count in the RSS (a 24 h log's spills are GBs)
                with self._pa.OSFile(str(self._order.spills[method]), "rb") as file, \
                        self._pa.ipc.open_stream(file) as reader:
                    for batch in reader:
                        self._add(self._pa.Table.from_batches([batch]))
                self._end_method()
            self._writer.close()
        finally:
            self._order.remove()
        super().close()

    def _discard(self) -> None:
        self._order.discard()
        self._writer.close()


def _json_schema(title: str, properties: dict[str, tuple[str, str, str]]) -> bytes:
    """JSON Schema of a flat object: name -> (JSON type, unit, description)."""
    props = {name: {"type": kind, "description": f"[{unit}] {text}".strip() if unit else text}
             for name, (kind, unit, text) in properties.items()}
    return json.dumps({"title": title, "type": "object", "properties": props}).encode()


class McapWriter(EstimateWriter):
    """MCAP with JSON messages and JSON schemas (Foxglove reads them as they are)."""

    INPUTS, TRUTH, ESTIMATE = "/slipd/inputs", "/slipd/truth", "/slipd/estimate/"

    def __init__(self, path: Path, info: RunInfo):
        super().__init__(path, info)
        try:
            from mcap.writer import Writer
        except ImportError as exc:
            raise DependencyError("--out FILE.mcap needs mcap: pip install 'slipd[mcap]'"
                                  ) from exc
        self._handle = _open(self.partial, "wb")
        self._writer = Writer(self._handle)
        self._writer.start(profile="", library="slipd")
        self._writer.add_metadata("slipd", {k: json.dumps(v) if not isinstance(v, str) else v
                                            for k, v in info.as_dict().items()})
        props = {"t": ("number", "s", DESCRIPTIONS["t"])}
        for name, column in SI_COLUMNS.items():
            kind = "integer" if name in ("friction_class", "status") else "number"
            props[name] = (kind, OUT_UNITS[column], DESCRIPTIONS[name])
        props["mu"] = (["number", "null"], "1", DESCRIPTIONS["mu"])
        props["valid"] = ("boolean", "", DESCRIPTIONS["valid"])
        schema = self._writer.register_schema("slipd.Estimate", "jsonschema",
                                              _json_schema("slipd.Estimate", props))
        self._channels = {m: self._writer.register_channel(self.ESTIMATE + m, "json", schema)
                          for m in info.methods}
        self._sequence: dict[int, int] = {}
        self._inputs = None
        if info.channels:
            names = [c.name.lower() for c in info.channels]
            props = {"t": ("number", "s", DESCRIPTIONS["t"])}
            props.update({n: ("number", unit_of(n), "latched input channel, ISO 8855")
                          for n in names})
            props.update({f"{n}_valid": ("boolean", "", f"{n} fresh and E2E-checked")
                          for n in names})
            schema = self._writer.register_schema("slipd.Inputs", "jsonschema",
                                                  _json_schema("slipd.Inputs", props))
            self._inputs = self._writer.register_channel(self.INPUTS, "json", schema)

    def _add_rows(self, channel: int, t: np.ndarray, names: list[str], values: np.ndarray,
                  flags: dict[str, np.ndarray] | None = None,
                  integers: tuple[str, ...] = ()) -> None:
        """One JSON object per row: ``names`` from float columns ``values`` [n, k] (NaN and
        inf as null) and bool columns ``flags``; formatted by one template per row (json.dumps
        of a dict per row is 4x slower, benchmarks/formats.py)."""
        flags = flags or {}
        keys = [*names, *flags]
        template = "{" + ",".join(f'"{k}":%s' for k in keys) + "}"
        rows = np.column_stack([values] + [np.where(f, 1.0, 0.0) for f in flags.values()]) \
            if flags else values
        n_float = len(names)
        whole = [i for i, name in enumerate(names) if name in integers]
        for k, row in enumerate(rows.tolist()):
            cells = [repr(v) if math.isfinite(v) else "null" for v in row[:n_float]]
            for i in whole:
                cells[i] = str(int(row[i]))
            cells += ["true" if v else "false" for v in row[n_float:]]
            self._add_encoded(channel, float(t[k]), (template % tuple(cells)).encode())

    def _add_encoded(self, channel: int, t: float, data: bytes) -> None:
        seq = self._sequence.get(channel, 0)
        self._sequence[channel] = seq + 1
        stamp = int(round(t * 1e9))
        self._writer.add_message(channel, stamp, data, stamp, seq)

    def write(self, method: str, t: np.ndarray, out: np.ndarray) -> None:
        names = ["t", *SI_COLUMNS]
        values = np.column_stack([t] + [out[:, c] for c in SI_COLUMNS.values()])
        values[:, names.index("friction_class")] = np.nan_to_num(out[:, Out.FRICTION_CLASS])
        status = np.nan_to_num(out[:, Out.STATUS])
        values[:, names.index("status")] = status
        valid = (status.astype(np.int64) & int(Status.VALID)) != 0
        self._add_rows(self._channels[method], t, names, values, {"valid": valid},
                       integers=("friction_class", "status"))

    def write_inputs(self, t: np.ndarray, U: np.ndarray) -> None:
        if self._inputs is None:
            return
        columns = [int(c) for c in self.info.channels]
        names = [c.name.lower() for c in self.info.channels]
        flags = {f"{n}_valid": U[:, VALID + c] > 0.5 for n, c in zip(names, columns,
                                                                       strict=True)}
        self._add_rows(self._inputs, t, ["t", *names],
                       np.column_stack([t, U[:, columns]]), flags)

    def write_truth(self, columns: dict[str, np.ndarray]) -> None:
        from slipd.sim.sensors import TRUTH_UNITS

        props = {n: ("number", TRUTH_UNITS.get(n, ""), "reference (truth), SI, ISO 8855")
                 for n in columns}
        schema = self._writer.register_schema("slipd.Truth", "jsonschema",
                                              _json_schema("slipd.Truth", props))
        channel = self._writer.register_channel(self.TRUTH, "json", schema)
        names = list(columns)
        self._add_rows(channel, columns["t"], names,
                       np.column_stack([np.asarray(columns[n], dtype=np.float64) for n in names]))

    def close(self) -> None:
        if self._finished:
            return
        self._writer.finish()
        self._handle.close()
        super().close()

    def _discard(self) -> None:
        self._handle.close()


class Mf4Writer(EstimateWriter):
    """ASAM MDF 4.10 through asammdf: one channel group per method, inputs and truth."""

    def __init__(self, path: Path, info: RunInfo):
        super().__init__(path, info)
        try:
            from asammdf import MDF, Signal
        except ImportError as exc:
            raise DependencyError("--out FILE.mf4 needs asammdf: pip install 'slipd[mf4]'"
                                  ) from exc
        self._signal = Signal
        self._mdf = MDF(version="4.10")
        self._groups: dict[str, int] = {}
        self._start = info.start

    def _origin(self, t: np.ndarray) -> float:
        if self._start is None:
            self._start = float(t[0]) if len(t) else 0.0
        if not self._groups:
            from datetime import UTC, datetime

            self._mdf.header.start_time = datetime.fromtimestamp(self._start, UTC)
        return self._start

    def _put(self, group: str, t: np.ndarray, signals: list[tuple[str, np.ndarray, str, str]],
             comment: str) -> None:
        if not len(t):
            return
        stamps = np.asarray(t, dtype=np.float64) - self._origin(t)
        if group not in self._groups:
            index = len(self._groups)
            self._mdf.append([self._signal(samples=values, timestamps=stamps, name=name,
                                           unit=unit, comment=text)
                              for name, values, unit, text in signals],
                             acq_name=group, comment=comment, common_timebase=True)
            self._groups[group] = index
        else:
            self._mdf.extend(self._groups[group],
                             [(stamps, None)] + [(values, None) for _, values, _, _ in signals])

    def write(self, method: str, t: np.ndarray, out: np.ndarray) -> None:
        signals = []
        for name, column in SI_COLUMNS.items():
            values = out[:, column].astype(np.float64)
            if name in ("friction_class", "status"):
                values = np.nan_to_num(values).astype(np.int16 if name == "status" else np.int8)
            signals.append((f"{method}.{name}", values, OUT_UNITS[column], DESCRIPTIONS[name]))
        valid = (np.nan_to_num(out[:, Out.STATUS]).astype(np.int64) & int(Status.VALID)) != 0
        signals.append((f"{method}.valid", valid.astype(np.uint8), "", DESCRIPTIONS["valid"]))
        self._put(method, t, signals, f"slipd estimates of {method}, SI, ISO 8855")

    def write_inputs(self, t: np.ndarray, U: np.ndarray) -> None:
        signals = []
        for c in self.info.channels:
            name = c.name.lower()
            signals.append((f"inputs.{name}", U[:, c].astype(np.float64), unit_of(name),
                            "latched input channel, ISO 8855"))
            signals.append((f"inputs.{name}_valid", (U[:, N_IN + c] > 0.5).astype(np.uint8), "",
                            f"{name} fresh and E2E-checked"))
        if signals:
            self._put("inputs", t, signals, "slipd latched inputs per tick")

    def write_truth(self, columns: dict[str, np.ndarray]) -> None:
        from slipd.sim.sensors import TRUTH_UNITS

        signals = [(f"truth.{n}", np.asarray(v, dtype=np.float64), TRUTH_UNITS.get(n, ""),
                    "reference (truth), SI, ISO 8855") for n, v in columns.items() if n != "t"]
        self._put("truth", columns["t"], signals, "reference sensor (truth)")

    def close(self) -> None:
        if self._finished:
            return
        try:
            self._mdf.save(self.partial, overwrite=True)
        except OSError as exc:
            raise ConfigError(f"--out {self.path}: cannot write: {exc}") from exc
        finally:
            self._mdf.close()
        super().close()

    def _discard(self) -> None:
        self._mdf.close()


#: suffix -> writer
WRITERS: dict[str, type[EstimateWriter]] = {
    ".csv": CsvWriter, ".parquet": ParquetWriter, ".mcap": McapWriter, ".mf4": Mf4Writer}


def open_writer(path: str | Path, info: RunInfo) -> EstimateWriter:
    """The writer of ``path``'s suffix."""
    suffix = Path(path).suffix.lower()
    if suffix not in WRITERS:
        raise ConfigError(f"--out {path}: unknown format {suffix!r}; expected one of "
                          f"{tuple(WRITERS)}")
    return WRITERS[suffix](Path(path), info)


def write_estimates(path: str | Path, estimates: list, info: RunInfo,
                    inputs=None, truth: dict[str, np.ndarray] | None = None) -> None:
    """A whole run: ``estimates`` (engine Estimates), optionally the engine's Inputs and the
    truth columns (for MCAP and MF4)."""
    with open_writer(path, info) as writer:
        if inputs is not None:
            writer.write_inputs(inputs.t, inputs.U)
        for estimate in estimates:
            writer.write(estimate.method, estimate.t, estimate.out)
        if truth is not None:
            writer.write_truth(truth)
