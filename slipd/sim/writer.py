"""Files of a simulation: the candump log a car's bus would carry and the truth CSV."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slipd.sim.result import SimResult
from slipd.sim.sensors import TRUTH_UNITS

#: Log time of t = 0: fixed, so the same seed writes byte-identical logs
#: (2023-11-14 22:13:20 UTC).
START_EPOCH = 1_700_000_000.0

#: Truth columns written to the CSV (a subset of SimResult.truth, in this order).
TRUTH_COLUMNS = (
    "t", "beta", "vx", "vy", "speed", "yaw_rate", "roll", "pitch", "ax", "ay", "mu", "steer",
    "wheel_speed_fl", "wheel_speed_fr", "wheel_speed_rl", "wheel_speed_rr", "bank", "grade",
    "yaw", "s", "pos_x", "pos_y",
)


def write_truth_csv(path: str | Path, result: SimResult, epoch: float = START_EPOCH) -> None:
    """100 Hz truth, SI, ISO 8855. Comment lines (``#``) document the columns; ``t`` counts
    from the log's first instant, ``log_epoch`` is that instant on the log's time axis."""
    cols = [c for c in TRUTH_COLUMNS if c in result.truth]
    header = [
        f"# slipd sim truth: scenario={result.scenario} vehicle={result.vehicle} "
        f"seed={result.seed}",
        *_sensor_lines(result),
        f"# log_epoch = {epoch:.6f}  (log time = log_epoch + t)",
        "# SI units, ISO 8855 axes (x forward, y left, z up), beta = atan2(vy, vx) at the CoG,",
        "# roll/pitch: body relative to the road (ISO signs), bank: road roll (+ right edge",
        "# lower), grade: + uphill, mu: peak lateral friction of the road under the car.",
        "# columns: " + ", ".join(f"{c} [{TRUTH_UNITS[c]}]" for c in cols),
        ",".join(cols),
    ]
    data = np.column_stack([result.truth[c] for c in cols])
    with open(path, "w", encoding="ascii") as fh:
        fh.write("\n".join(header) + "\n")
        np.savetxt(fh, data, fmt="%.9g", delimiter=",")


def _sensor_lines(result: SimResult) -> list[str]:
    """Header lines naming the sensor variant and every sensor override (none for the baseline,
    whose header stays as it always was)."""
    from slipd.sim.variants import VARIANTS, format_value

    lines = []
    name = result.meta.get("variant")
    if name:
        described = "; ".join(VARIANTS[n].description for n in name.split(",") if n in VARIANTS)
        lines.append(f"# sensor variant: {name}  ({described})")
    overrides = result.meta.get("sensor_overrides") or {}
    if overrides:
        lines.append("# sensor overrides: " + " ".join(
            f"{key}={format_value(value)}" for key, value in sorted(overrides.items())))
    # the drawn errors (the truth of slipd identify) too, but not for the baseline, whose
    # header stays byte for byte as it was
    errors = sensor_errors_as_calibration(result.meta.get("sensor_errors") or {})
    if errors and (name or overrides):
        lines.append("# sensor errors (profile [calibration] conventions): " + " ".join(
            f"{key}={','.join(f'{v:.6g}' for v in np.atleast_1d(value))}"
            for key, value in errors.items()))
    return lines


def sensor_errors_as_calibration(drawn: dict) -> dict[str, tuple[float, ...]]:
    """The sensor errors a simulation drew (SimResult.meta['sensor_errors']) as the values of a
    profile's ``[calibration]`` table that undo them (slipd.profile.Calibration): the truth
    of slipd identify. {} when nothing was recorded."""
    if not drawn:
        return {}
    deg = np.degrees
    return {
        "imu_mounting_deg": tuple(float(v) for v in deg(drawn["imu_mounting"])),
        "accel_offset": tuple(float(v) for v in drawn["accel_offset"]),
        "gyro_offset": tuple(float(v) for v in deg(drawn["gyro_offset"])),
        "steer_offset_deg": (float(deg(drawn["swa_offset"])),),
        # the signal reads (1 + e) x the true speed; the scale undoes it
        "wheel_radius_scale": tuple(1.0 / (1.0 + float(e)) for e in drawn["wheel_radius_error"]),
    }


def read_truth_meta(path: str | Path) -> dict[str, str]:
    """What made a truth CSV: scenario, vehicle, seed, and variant / sensor_overrides when the
    header names them (written by :func:`write_truth_csv`)."""
    meta: dict[str, str] = {}
    with open(path, encoding="ascii") as fh:
        for line in fh:
            if not line.startswith("#"):
                break
            text = line[1:].strip()
            if text.startswith("slipd sim truth:"):
                for item in text.split(":", 1)[1].split():
                    key, _, value = item.partition("=")
                    meta[key] = value
            elif text.startswith("sensor variant:"):
                meta["variant"] = text.split(":", 1)[1].split("(", 1)[0].strip()
            elif text.startswith("sensor overrides:"):
                meta["sensor_overrides"] = text.split(":", 1)[1].strip()
            elif text.startswith("sensor errors"):
                meta["sensor_errors"] = text.split(":", 1)[1].strip()
    return meta


def read_truth_csv(path: str | Path) -> tuple[dict[str, np.ndarray], float]:
    """The truth columns and the log epoch of a truth CSV written by :func:`write_truth_csv`."""
    from slipd.errors import LogFormatError

    epoch = 0.0
    names: list[str] | None = None
    skip = 0
    with open(path, encoding="ascii") as fh:
        for line in fh:
            skip += 1
            if line.startswith("#"):
                if "log_epoch" in line:
                    epoch = float(line.split("=", 1)[1].split()[0])
                continue
            names = line.strip().split(",")
            break
    if not names or "t" not in names or "beta" not in names:
        raise LogFormatError(f"{path}: not a slipd truth CSV (needs a header with t and beta)")
    try:
        data = np.loadtxt(path, delimiter=",", skiprows=skip, ndmin=2)
    except ValueError as exc:
        raise LogFormatError(f"{path}: {exc}") from exc
    if data.shape[1] != len(names):
        raise LogFormatError(f"{path}: {data.shape[1]} values per line, header has {len(names)}")
    return {name: data[:, i] for i, name in enumerate(names)}, epoch


def encode_frames(result: SimResult, profile, epoch: float = START_EPOCH):
    """Every transmission through the codec, time-sorted: (t, frame_id, data [n, width], dlc);
    width is 8, or the longest CAN FD frame of the profile."""
    from slipd.codec import Codec

    codec = Codec.from_profile(profile)
    stamps, ids, payloads, dlcs, order_key = [], [], [], [], []
    for rank, (name, msg) in enumerate(result.sensors.items()):
        frame_id, data = codec.encode_channels(name, msg.values)
        n = len(msg.t)
        padded = np.zeros((n, codec.inputs.max_dlc if codec.inputs.max_dlc > 8 else 8),
                          dtype=np.uint8)
        padded[:, : data.shape[1]] = data
        stamps.append(np.round((epoch + msg.t) * 1e6) / 1e6)
        ids.append(np.full(n, frame_id, dtype=np.int64))
        payloads.append(padded)
        dlcs.append(np.full(n, data.shape[1], dtype=np.uint8))
        order_key.append(np.full(n, rank))
    t = np.concatenate(stamps)
    rank = np.concatenate(order_key)
    order = np.lexsort((rank, t))  # by time, ties in bus order
    return (t[order], np.concatenate(ids)[order], np.concatenate(payloads)[order],
            np.concatenate(dlcs)[order])


def write_log(path: str | Path, result: SimResult, profile, epoch: float = START_EPOCH) -> int:
    """Write the candump -L log; returns the number of frames."""
    from slipd.replay.candump import write_candump

    t, frame_id, data, dlc = encode_frames(result, profile, epoch)
    channel, channels = bus_channels(frame_id, profile)
    if len(channels) == 1:
        return write_candump(path, t, frame_id, data, dlc, interface=channels[0])
    return write_candump(path, t, frame_id, data, dlc, channel=channel, channels=channels)


def bus_channels(frame_id: np.ndarray, profile) -> tuple[np.ndarray, list[str]]:
    """Each frame's channel index and the channel names of a simulated log: ``can0`` for a
    one-bus profile, else one channel per bus, named after it."""
    buses = profile.buses if not isinstance(profile, str) else ("main",)
    if len(buses) == 1:
        return np.zeros(len(frame_id), dtype=np.uint8), ["can0"]
    from slipd.codec import Codec

    plan = Codec.from_profile(profile).inputs
    bus_of = {plan.frame_id(n): plan.buses.index(plan.bus(n)) for n in plan.message_names}
    channel = np.array([bus_of[int(i)] for i in frame_id], dtype=np.uint8)
    return channel, list(plan.buses)


def truth_path_of(log: str | Path) -> Path:
    """The truth CSV that belongs to a log: LOG without .log + .truth.csv (slipd sim, slipd
    import --truth; slipd eval looks there)."""
    log = Path(log)
    stem = log.name[: -len(".log")] if log.name.endswith(".log") else log.name
    return log.with_name(stem + ".truth.csv")


def write_truth_columns(path: str | Path, columns: dict[str, np.ndarray], epoch: float,
                        comments: list[str]) -> None:
    """A truth CSV from columns other than a simulation's (``slipd import --truth``), in the
    format :func:`read_truth_csv` reads: ``t`` from the log epoch, SI units, ISO 8855."""
    names = list(columns)
    header = [f"# {line}" for line in comments] + [
        f"# log_epoch = {epoch:.6f}  (log time = log_epoch + t)",
        "# columns: " + ", ".join(f"{c} [{TRUTH_UNITS.get(c, '?')}]" for c in names),
        ",".join(names),
    ]
    data = np.column_stack([np.asarray(columns[c], dtype=np.float64) for c in names])
    with open(path, "w", encoding="ascii") as fh:
        fh.write("\n".join(header) + "\n")
        np.savetxt(fh, data, fmt="%.9g", delimiter=",")
