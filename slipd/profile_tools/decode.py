"""``slipd decode``: a log through a profile into slipd's SI input channels, one row per tick.

The same path the estimators see (codec decode -> latch -> sample at each 10 ms tick), so a
table from here is what a method was given: each channel in SI with ISO 8855 signs, and its
validity (fresh, E2E-checked, not marked unavailable) beside it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slipd.channels import VALID, In
from slipd.errors import ConfigError, DependencyError
from slipd.profile import CHANNEL_DIMENSION, Profile
from slipd.replay.engine import Inputs, latch_log_or_recording
from slipd.replay.readers import read_frames

SI_UNITS = {"acceleration": "m/s^2", "angular rate": "rad/s", "angle": "rad", "speed": "m/s",
            "1": "1", "magnetic field": "uT", "torque": "Nm"}


def decode_log(log: str | Path, profile: Profile, skip_bad: bool = False,
               bus_map: dict[str, str] | None = None) -> Inputs:
    """The log latched onto the 100 Hz tick grid (or its recorded ticks) through ``profile``."""
    return latch_log_or_recording(read_frames(log, skip_bad=skip_bad), profile, bus_map)


def channel_columns(inputs: Inputs, profile: Profile) -> dict[str, np.ndarray]:
    """t, then per mapped channel its SI value and ``<name>_valid`` (0/1)."""
    columns: dict[str, np.ndarray] = {"t": inputs.t}
    for channel in sorted(profile.channels):
        name = channel.name.lower()
        columns[name] = inputs.U[:, channel]
        columns[f"{name}_valid"] = inputs.U[:, VALID + channel].astype(np.int8)
    return columns


def unit_of(column: str) -> str:
    if column == "t":
        return "s"
    if column.endswith("_valid"):
        return "1 = valid"
    return SI_UNITS[CHANNEL_DIMENSION[In[column.upper()]]]


def write_inputs(path: Path, inputs: Inputs, profile: Profile) -> int:
    """Write the table as CSV or Parquet by suffix; returns the rows written."""
    columns = channel_columns(inputs, profile)
    suffix = path.suffix.lower()
    if suffix == ".csv":  # plain (pandas.read_csv reads it); units in FILE.csv.meta.json
        import json

        from slipd.replay.writers import sidecar_of

        matrix = np.column_stack(list(columns.values()))
        formats = ["%.6f"] + ["%d" if c.endswith("_valid") else "%.9g"
                              for c in list(columns)[1:]]
        with open(path, "w", encoding="utf-8") as handle:
            handle.write(",".join(columns) + "\n")
            np.savetxt(handle, matrix, fmt=formats, delimiter=",")
        sidecar_of(path).write_text(json.dumps({
            "format": f"slipd decode: profile {profile.name}; SI units, ISO 8855 signs, one "
                      "row per 10 ms tick",
            "profile": profile.name,
            "columns": {c: {"unit": unit_of(c)} for c in columns}}, indent=2) + "\n")
    elif suffix == ".parquet":
        try:
            import pyarrow as pa
            import pyarrow.parquet as pq
        except ImportError as exc:
            raise DependencyError("--out FILE.parquet needs pyarrow: pip install "
                                  "'slipd[parquet]'") from exc
        table = pa.table({name: pa.array(values) for name, values in columns.items()})
        table = table.replace_schema_metadata(
            {"slipd": f"slipd decode, profile {profile.name}",
             **{f"unit:{c}": unit_of(c) for c in columns}})
        pq.write_table(table, str(path), compression="zstd")
    else:
        raise ConfigError(f"--out {path}: expected a .csv or .parquet file")
    return len(inputs.t)
