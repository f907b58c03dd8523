"""Per-tick outputs: the estimate table (CSV) and slipd's output frames for a merged log."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from slipd.channels import Out
from slipd.codec import N_TX, Codec, kernels
from slipd.codec.tx import fill_tx_rows
from slipd.errors import ConfigError, DependencyError
from slipd.estimators import base
from slipd.replay.candump import FLAG_BRS, FLAG_EXTENDED, FLAG_FD, Frames

CSV_HEADER = (
    "# slipd estimates, one row per 10 ms tick. t: s on the log's time axis; beta, "
    "beta_rate, roll, sigma_beta in deg (deg/s); vx, vy in m/s; mu dimensionless (empty when "
    "the method does not estimate it); status: bit 0 valid, 1 degraded, 2 input timeout, "
    "3 not converged, 4 unavailable, 5 reset\n"
    "t,estimator,beta_deg,beta_rate_deg_s,vx_mps,vy_mps,mu,sigma_beta_deg,roll_deg,"
    "friction_class,status\n"
)


TABLE_FORMATS = (".csv", ".parquet")


def write_table(path: str | Path, estimates: list) -> None:
    """Write the estimates as CSV or Parquet, by the file's suffix."""
    suffix = Path(path).suffix.lower()
    if suffix == ".csv":
        write_csv(path, estimates)
    elif suffix == ".parquet":
        write_parquet(path, estimates)
    else:
        raise ConfigError(f"--out {path}: unknown table format {suffix!r}; expected one of "
                          f"{TABLE_FORMATS}")


def table_columns(estimate) -> dict[str, np.ndarray]:
    """The estimate table's columns (units as in CSV_HEADER)."""
    out = estimate.out
    deg = 180.0 / math.pi
    return {
        "t": estimate.t,
        "beta_deg": out[:, Out.BETA] * deg,
        "beta_rate_deg_s": out[:, Out.BETA_RATE] * deg,
        "vx_mps": out[:, Out.VX],
        "vy_mps": out[:, Out.VY],
        "mu": out[:, Out.MU],
        "sigma_beta_deg": out[:, Out.SIGMA_BETA] * deg,
        "roll_deg": out[:, Out.ROLL] * deg,
        "friction_class": out[:, Out.FRICTION_CLASS].astype(np.int8),
        "status": out[:, Out.STATUS].astype(np.int16),
    }


def write_parquet(path: str | Path, estimates: list) -> None:
    """The same table as write_csv in Parquet (zstd), with the column units as metadata; mu is
    null where the method does not estimate it."""
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError as exc:
        raise DependencyError("--out FILE.parquet needs pyarrow: pip install 'slipd[parquet]'"
                              ) from exc
    tables = []
    for estimate in estimates:
        columns = table_columns(estimate)
        arrays = {name: pa.array(values, from_pandas=(name == "mu"))
                  for name, values in columns.items()}
        arrays["estimator"] = pa.DictionaryArray.from_arrays(
            pa.array(np.zeros(len(estimate.t), dtype=np.int32)), pa.array([estimate.method]))
        order = ["t", "estimator", *[n for n in columns if n != "t"]]
        tables.append(pa.table({name: arrays[name] for name in order}))
    table = pa.concat_tables(tables) if tables else pa.table({})
    table = table.replace_schema_metadata({"slipd": CSV_HEADER.strip().splitlines()[0]})
    pq.write_table(table, str(path), compression="zstd")


def write_csv(path: str | Path, estimates: list) -> None:
    """Write the estimates of one or more methods as one CSV table."""
    with open(path, "w", encoding="utf-8") as handle:
        handle.write(CSV_HEADER)
        for estimate in estimates:
            out = estimate.out
            deg = 180.0 / math.pi
            columns = np.column_stack([
                estimate.t, out[:, Out.BETA] * deg, out[:, Out.BETA_RATE] * deg, out[:, Out.VX],
                out[:, Out.VY], out[:, Out.MU], out[:, Out.SIGMA_BETA] * deg,
                out[:, Out.ROLL] * deg, out[:, Out.FRICTION_CLASS], out[:, Out.STATUS],
            ])
            for row in columns:
                mu = "" if math.isnan(row[5]) else f"{row[5]:.4f}"
                handle.write(
                    f"{row[0]:.6f},{estimate.method},{row[1]:.5f},{row[2]:.4f},{row[3]:.4f},"
                    f"{row[4]:.4f},{mu},{row[6]:.5f},{row[7]:.4f},{int(row[8])},{int(row[9])}\n"
                )


def tx_values(out: np.ndarray, estimator_id: int) -> np.ndarray:
    """Output-frame slots [n, N_TX] from estimator outputs [n, N_OUT] (the daemon's mapping)."""
    values = np.zeros((out.shape[0], N_TX))
    fill_tx_rows(np.ascontiguousarray(out), float(estimator_id), values)
    return values


def output_frames(estimate, channel_index: int, first_counter: int = 0,
                  profile=None) -> Frames:
    """SLIPD_STATE and SLIPD_AUX frames of every tick (what the daemon sends), on the
    profile's output IDs and frame format (slipd.dbc's without a profile)."""
    codec_plan = Codec.output_plan(profile)
    values = tx_values(estimate.out, base.available().index(estimate.method))
    n = len(estimate.t)
    parts = []
    for name in ("SLIPD_STATE", "SLIPD_AUX"):
        row = codec_plan.message_rows[name]
        data = np.zeros((n, 8), dtype=np.uint8)
        kernels.encode_rows(codec_plan.plan_i, codec_plan.plan_f, row, values, first_counter,
                            data)
        parts.append((codec_plan.frame_id(name), data))
    t = np.repeat(estimate.t, 2)
    frame_id = np.empty(2 * n, dtype=np.int64)
    data = np.empty((2 * n, 8), dtype=np.uint8)
    for k, (fid, rows) in enumerate(parts):
        frame_id[k::2] = fid
        data[k::2] = rows
    flags = 128 | 64 | (FLAG_FD | FLAG_BRS if codec_plan.is_fd("SLIPD_STATE") else 0)
    flags |= FLAG_EXTENDED if codec_plan.is_extended("SLIPD_STATE") else 0
    return Frames(t, frame_id, np.full(2 * n, flags, np.uint8), np.full(2 * n, 8, np.uint8),
                  data, np.full(2 * n, channel_index, np.uint8), [])


def merge(inputs: Frames, outputs: Frames) -> Frames:
    """Input and output frames in time order (outputs after inputs of the same time)."""
    width = max(inputs.data.shape[1], outputs.data.shape[1])
    pad = lambda d: np.pad(d, ((0, 0), (0, width - d.shape[1])))  # noqa: E731
    t = np.concatenate([inputs.t, outputs.t])
    order = np.argsort(np.concatenate([inputs.t, outputs.t + 0.0]), kind="stable")
    return Frames(t[order], np.concatenate([inputs.frame_id, outputs.frame_id])[order],
                  np.concatenate([inputs.flags, outputs.flags])[order],
                  np.concatenate([inputs.dlc, outputs.dlc])[order],
                  np.concatenate([pad(inputs.data), pad(outputs.data)])[order],
                  np.concatenate([inputs.channel, outputs.channel])[order], inputs.channels)
