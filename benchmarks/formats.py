"""File formats: reading a bus-logging MF4, and writing the estimates in each --out format.

MF4 in: a bus of the default profile (every input message at its rate, counters and CRCs)
written as python-can's MF4 layout (``CAN_DataFrame`` group, asammdf); slipd's reader
(slipd.replay.mf4: whole arrays) against the baseline, python-can's ``MF4Reader`` (one Message
per frame) turned into the same Frames, both in the same run.

Out: one estimator's ticks of that bus through each writer of slipd.replay.writers (CSV +
sidecar, Parquet, MCAP with the inputs topic, MF4 with the inputs group); ticks per second
and the file size, against the CSV writer as the baseline.

    .venv/bin/python -m benchmarks.formats [--seconds 600] [--estimator kinematic_heuristic]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.codec import bus_frames
from slipd.codec import Codec
from slipd.profile import load_profile
from slipd.replay.candump import Frames

START = 1_700_000_000.0
#: python-can's MF4Writer layout (can.io.mf4.STD_DTYPE)
CAN_DATAFRAME = np.dtype([
    ("CAN_DataFrame.BusChannel", "<u1"), ("CAN_DataFrame.ID", "<u4"),
    ("CAN_DataFrame.IDE", "<u1"), ("CAN_DataFrame.DLC", "<u1"),
    ("CAN_DataFrame.DataLength", "<u1"), ("CAN_DataFrame.DataBytes", "(64,)u1"),
    ("CAN_DataFrame.Dir", "<u1"), ("CAN_DataFrame.EDL", "<u1"), ("CAN_DataFrame.BRS", "<u1"),
    ("CAN_DataFrame.ESI", "<u1"),
])


def write_bus_mf4(path: Path, t: np.ndarray, ids: np.ndarray, data: np.ndarray) -> None:
    """A bus-logging MF4 as CAN loggers and python-can write it."""
    from datetime import UTC, datetime

    from asammdf import MDF, Signal, Source

    records = np.zeros(len(t), dtype=CAN_DATAFRAME)
    records["CAN_DataFrame.ID"] = ids
    records["CAN_DataFrame.DLC"] = data.shape[1]
    records["CAN_DataFrame.DataLength"] = data.shape[1]
    records["CAN_DataFrame.DataBytes"][:, : data.shape[1]] = data
    mdf = MDF(version="4.10")
    mdf.header.start_time = datetime.fromtimestamp(START, UTC)
    source = Source(name="CAN", path="CAN", comment="", source_type=Source.SOURCE_BUS,
                    bus_type=Source.BUS_TYPE_CAN)
    mdf.append(Signal(samples=records, timestamps=t, name="CAN_DataFrame", source=source),
               acq_name="CAN", acq_source=source)
    mdf.groups[-1].channel_group.flags |= 0x2  # FLAG_CG_BUS_EVENT, as python-can's writer
    mdf.save(path, overwrite=True)
    mdf.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=600.0, help="seconds of bus")
    parser.add_argument("--estimator", default="kinematic_heuristic")
    args = parser.parse_args()
    import can

    from slipd.replay.engine import latch_log, run_method
    from slipd.replay.messages import frames_from_messages
    from slipd.replay.mf4 import read_mf4
    from slipd.replay.writers import RunInfo, open_writer

    profile = load_profile("default")
    t, ids, data = bus_frames(Codec(profile), args.seconds, np.random.default_rng(0))
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        mf4 = folder / "bus.mf4"
        write_bus_mf4(mf4, t, ids, data)
        print(f"bus: {len(t)} frames, {args.seconds:g} s, MF4 {mf4.stat().st_size / 1e6:.1f} MB")
        started = time.perf_counter()
        ours = read_mf4(mf4)
        fast = time.perf_counter() - started
        started = time.perf_counter()
        reference = frames_from_messages(can.LogReader(str(mf4)))
        slow = time.perf_counter() - started
        same = all(np.array_equal(getattr(ours, k), getattr(reference, k))
                   for k in ("t", "frame_id", "flags", "dlc", "data"))
        print(f"MF4 in  slipd.replay.mf4   {fast:7.2f} s  {len(t) / fast / 1e6:6.2f} M frames/s")
        print(f"MF4 in  python-can reader  {slow:7.2f} s  {len(t) / slow / 1e6:6.2f} M frames/s"
              f"  (baseline; frames identical: {same})")
        print(f"MF4 in  ratio              {slow / fast:7.1f}x")

        frames = Frames(ours.t, ours.frame_id, ours.flags, ours.dlc, ours.data, ours.channel,
                        ours.channels)
        inputs = latch_log(frames, profile)
        estimate = run_method(inputs, profile, args.estimator)
        info = RunInfo([args.estimator], profile.name, "bench", sorted(profile.channels, key=int),
                       float(t[0]))
        ticks = len(inputs.t)
        print(f"out: {ticks} ticks of {args.estimator} (MCAP and MF4 with the inputs too)")
        baseline = None
        for suffix in (".csv", ".parquet", ".mcap", ".mf4"):  # warm-up: imports, first calls
            with open_writer(folder / f"warm{suffix}", info) as writer:
                writer.write_inputs(inputs.t[:10], inputs.U[:10])
                writer.write(args.estimator, estimate.t[:10], estimate.out[:10])
        for suffix in (".csv", ".parquet", ".mcap", ".mf4"):
            path = folder / f"est{suffix}"
            started = time.perf_counter()
            with open_writer(path, info) as writer:
                writer.write_inputs(inputs.t, inputs.U)
                writer.write(args.estimator, estimate.t, estimate.out)
            took = time.perf_counter() - started
            baseline = baseline or took
            print(f"out {suffix:9s} {took:7.2f} s  {ticks / took / 1e3:8.1f} k ticks/s  "
                  f"{path.stat().st_size / 1e6:7.1f} MB  {baseline / took:5.2f}x CSV")


if __name__ == "__main__":
    main()
