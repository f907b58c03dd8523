"""``slipd import``: recorded signals become the same frames the car's bus would carry."""

from __future__ import annotations

import json
import math

import can
import numpy as np
import pytest

from slipd.channels import In, new_u
from slipd.cli import main
from slipd.codec import Codec
from slipd.errors import ConfigError, LogFormatError
from slipd.profile import load_profile
from slipd.replay.candump import read_candump
from slipd.replay.importer import import_table, parse_constants, parse_map, sidecar_path

PROFILE = load_profile("default")


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """A simulated drive: its bus log and its per-message sensor values as one wide table."""
    from slipd.sim import simulate
    from slipd.sim.writer import START_EPOCH, write_log

    result = simulate("double_lane_change", duration=3.0)
    folder = tmp_path_factory.mktemp("import")
    write_log(folder / "bus.log", result, PROFILE)
    times = np.unique(np.concatenate([m.t for m in result.sensors.values()]))
    columns = {"time": times}
    for message in result.sensors.values():
        rows = np.searchsorted(times, message.t)
        for channel, values in message.values.items():
            column = np.full(len(times), np.nan)
            column[rows] = values
            columns[channel.name.lower()] = column
    return folder, columns, START_EPOCH


def write_csv(path, columns: dict[str, np.ndarray], delimiter: str = ",") -> None:
    names = list(columns)
    with open(path, "w") as handle:
        handle.write(delimiter.join(names) + "\n")
        for row in zip(*(columns[n] for n in names), strict=True):
            handle.write(delimiter.join("" if math.isnan(v) else repr(float(v)) for v in row))
            handle.write("\n")


def identity_map(columns) -> list[str]:
    return [f"{name}={name}" for name in columns if name != "time"]


def test_imported_table_gives_the_simulators_frames_byte_for_byte(drive, tmp_path):
    folder, columns, epoch = drive
    write_csv(tmp_path / "drive.csv", columns)
    report = import_table(
        tmp_path / "drive.csv",
        PROFILE,
        parse_map(identity_map(columns)),
        tmp_path / "drive.log",
        epoch=epoch,
    )
    ours, reference = read_candump(tmp_path / "drive.log"), read_candump(folder / "bus.log")
    assert report.frames == len(reference) and not report.left_out and not report.clamped
    order = np.lexsort((ours.frame_id, ours.t))
    ref_order = np.lexsort((reference.frame_id, reference.t))
    assert np.array_equal(ours.t[order], reference.t[ref_order])
    assert np.array_equal(ours.frame_id[order], reference.frame_id[ref_order])
    assert np.array_equal(ours.data[order], reference.data[ref_order])
    # a plain candump file: python-can reads it (no comment lines), provenance is beside it
    assert len(list(can.LogReader(str(tmp_path / "drive.log")))) == report.frames
    meta = json.loads(sidecar_path(tmp_path / "drive.log").read_text())
    assert meta["profile"] == "default" and meta["frames"] == report.frames
    assert meta["derived_on_request"] == {}


def test_units_sign_and_delimiter(drive, tmp_path):
    _, columns, _ = drive
    table = {
        "ms": columns["time"] * 1000.0,
        "yaw_dps_sae": -np.degrees(columns["yaw_rate"]),  # SAE: z down, yaw + to the right
        "roll_rate": columns["roll_rate"],
        "pitch_rate": columns["pitch_rate"],
    }
    write_csv(tmp_path / "rate.csv", table, delimiter=";")
    import_table(
        tmp_path / "rate.csv",
        PROFILE,
        parse_map(["yaw_dps_sae=-yaw_rate:deg/s", "roll_rate=roll_rate,pitch_rate=pitch_rate"]),
        tmp_path / "rate.log",
        time_spec="ms:ms",
    )
    frames = read_candump(tmp_path / "rate.log")
    codec = Codec(PROFILE)
    decoded = []
    u = new_u()
    for k in range(len(frames)):
        codec.decode(int(frames.frame_id[k]), frames.data[k, : frames.dlc[k]], frames.t[k])
        decoded.append(codec.sample(frames.t[k] + 1e-4, u)[In.YAW_RATE])
    sent = columns["yaw_rate"][np.isfinite(columns["yaw_rate"])]
    lsb = math.radians(0.01)  # IMU_RATE resolution, slipd.dbc
    assert np.max(np.abs(np.array(decoded) - sent)) <= lsb / 2 + 1e-12


def test_missing_channels_are_left_out_not_made_up(drive, tmp_path):
    _, columns, _ = drive
    kept = {k: v for k, v in columns.items() if not k.startswith(("mag_", "az"))}
    write_csv(tmp_path / "partial.csv", kept)
    report = import_table(
        tmp_path / "partial.csv", PROFILE, parse_map(identity_map(kept)), tmp_path / "partial.log"
    )
    assert "MAGNETOMETER" not in report.messages and "MAGNETOMETER" not in report.left_out
    assert report.left_out["IMU_ACCEL"] == ["az"]
    assert "IMU_ACCEL" not in report.messages
    ids = set(read_candump(tmp_path / "partial.log").frame_id.tolist())
    assert Codec(PROFILE).inputs.frame_id("IMU_ACCEL") not in ids

    # the user may declare a constant for the absent sensor: written, and recorded as such
    report = import_table(
        tmp_path / "partial.csv",
        PROFILE,
        parse_map(identity_map(kept)),
        tmp_path / "declared.log",
        constants=parse_constants(["az=1:g"]),
    )
    assert "IMU_ACCEL" in report.messages
    meta = json.loads(sidecar_path(tmp_path / "declared.log").read_text())
    assert "az" in meta["derived_on_request"] and "9.80665" in meta["derived_on_request"]["az"]


def test_wheel_speeds_derived_only_on_request(drive, tmp_path):
    _, columns, _ = drive
    table = {k: v for k, v in columns.items() if not k.startswith("wheel_speed")}
    speed = columns["wheel_speed_rl"] * 0.5 + columns["wheel_speed_rr"] * 0.5
    table["v_kmh"] = speed * 3.6
    write_csv(tmp_path / "speed.csv", table)
    maps = parse_map(identity_map({k: 0 for k in table if k != "v_kmh"}))
    plain = import_table(tmp_path / "speed.csv", PROFILE, maps, tmp_path / "plain.log")
    assert "WHEEL_SPEEDS" not in plain.messages

    report = import_table(
        tmp_path / "speed.csv",
        PROFILE,
        maps,
        tmp_path / "derived.log",
        derive=["wheel-speeds"],
        speed_spec="v_kmh:km/h",
    )
    assert report.messages["WHEEL_SPEEDS"] > 0
    meta = json.loads(sidecar_path(tmp_path / "derived.log").read_text())
    assert "zero sideslip" in meta["derived_on_request"]["wheel_speed_fl"]
    assert "yaw_rate" in meta["derived_on_request"]["wheel_speed_fl"]
    # the rear axle carries the vehicle speed -/+ r * track/2: compare after decoding
    frames = read_candump(tmp_path / "derived.log")
    codec = Codec(PROFILE)
    wheel_id = codec.inputs.frame_id("WHEEL_SPEEDS")
    u = new_u()
    rear_mean, rows = [], []
    for k in np.flatnonzero(frames.frame_id == wheel_id):
        rows.append(int(np.searchsorted(table["time"], frames.t[k] - 2e-6)))  # t is rounded to us
        codec.decode(wheel_id, frames.data[k, : frames.dlc[k]], frames.t[k])
        sample = codec.sample(frames.t[k] + 1e-4, u)
        rear_mean.append(0.5 * (sample[In.WHEEL_SPEED_RL] + sample[In.WHEEL_SPEED_RR]))
    assert len(rows) >= np.isfinite(speed).sum() - 1  # only rows before the first yaw rate
    assert np.max(np.abs(np.array(rear_mean) - speed[rows])) < 0.01  # km/h-resolution signals

    with pytest.raises(ConfigError, match="needs the vehicle speed"):
        import_table(
            tmp_path / "speed.csv", PROFILE, maps, tmp_path / "x.log", derive=["wheel-speeds"]
        )


def test_mat_file_equals_csv(drive, tmp_path):
    scipy_io = pytest.importorskip("scipy.io", reason="reading .mat needs scipy")
    _, columns, _ = drive
    write_csv(tmp_path / "drive.csv", columns)
    signals = {k: v for k, v in columns.items() if k != "time"}
    scipy_io.savemat(tmp_path / "drive.mat", {"time": columns["time"], "imu": signals})
    import_table(
        tmp_path / "drive.csv", PROFILE, parse_map(identity_map(columns)), tmp_path / "csv.log"
    )
    import_table(
        tmp_path / "drive.mat",
        PROFILE,
        parse_map([f"imu.{name}={name}" for name in signals]),
        tmp_path / "mat.log",
    )
    assert (tmp_path / "csv.log").read_bytes() == (tmp_path / "mat.log").read_bytes()


def test_out_of_range_values_are_counted(tmp_path):
    table = {
        "t": np.arange(5) * 0.01,
        "ax": np.array([0.0, 1.0, 40.0, -50.0, 2.0]),
        "ay": np.zeros(5),
        "az": np.full(5, 9.81),
    }
    write_csv(tmp_path / "range.csv", table)
    report = import_table(
        tmp_path / "range.csv", PROFILE, parse_map(["ax=ax,ay=ay,az=az"]), tmp_path / "range.log"
    )
    assert report.clamped == {"ax": 2}
    assert "clamped" in report.summary()


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("t,ax\n0.0,1\n0.01,abc\n", r"bad\.csv:3: column 'ax': 'abc' is not a number"),
        ("t,ax\n0.0,1\n0.01\n", r"bad\.csv:3: 1 values, the header has 2"),
        ("t,ax\n0.02,1\n0.01,2\n", r"goes backwards at data row 2"),
        ("t,ax,ax\n0.0,1,2\n", r"bad\.csv:1: duplicate column"),
        ("", r"empty file"),
        ("t,ax\n0.0,1\n0.01,inf\n", r"bad\.csv:3: column 'ax': 'inf' is not a measurement"),
        ("t,ax\n0.0,-Infinity\n", r"bad\.csv:2: column 'ax': '-Infinity' is not a"),
    ],
)
def test_bad_tables_name_file_and_line(tmp_path, text, expected):
    (tmp_path / "bad.csv").write_text(text)
    with pytest.raises(LogFormatError, match=expected):
        import_table(tmp_path / "bad.csv", PROFILE, parse_map(["ax=ax"]), tmp_path / "o.log")


def test_a_non_utf8_table_and_a_nan_epoch_are_clear_errors(tmp_path, capsys):
    (tmp_path / "latin1.csv").write_bytes("t,ax\n0.0,1\n# Messfahrt M\xfcnchen\n".encode("latin-1"))
    with pytest.raises(LogFormatError, match=r"latin1\.csv: not UTF-8 text \(byte 0xfc"):
        import_table(tmp_path / "latin1.csv", PROFILE, parse_map(["ax=ax"]), tmp_path / "o.log")
    (tmp_path / "ok.csv").write_text("t,ax\n0.0,1\n")
    assert main(["import", str(tmp_path / "ok.csv"), "--map", "ax=ax", "--epoch", "nan",
                 "--out", str(tmp_path / "o.log")]) == 2
    err = capsys.readouterr().err
    assert "--epoch nan: expected a finite number" in err and "Traceback" not in err


def test_bad_maps_are_clear_errors(tmp_path):
    (tmp_path / "ok.csv").write_text("t,ax,v\n0.0,1,2\n")
    with pytest.raises(ConfigError, match="unknown channel 'accel_x'"):
        parse_map(["ax=accel_x"])
    with pytest.raises(ConfigError, match="unknown unit 'furlong'"):
        parse_map(["ax=ax:furlong"])
    with pytest.raises(ConfigError, match="mapped twice"):
        parse_map(["ax=ax", "v=ax"])
    with pytest.raises(ConfigError, match="has no column 'nope'"):
        import_table(tmp_path / "ok.csv", PROFILE, parse_map(["nope=ax"]), tmp_path / "o.log")
    with pytest.raises(ConfigError, match="carries no speed_ref"):
        import_table(tmp_path / "ok.csv", PROFILE, parse_map(["v=speed_ref"]), tmp_path / "o.log")
    with pytest.raises(ConfigError, match="no message of profile default has all its channels"):
        import_table(tmp_path / "ok.csv", PROFILE, parse_map(["ax=ax"]), tmp_path / "o.log")


def test_import_command_then_replay(drive, tmp_path, capsys):
    _, columns, _ = drive
    write_csv(tmp_path / "drive.csv", columns)
    code = main(
        [
            "import",
            str(tmp_path / "drive.csv"),
            "--map",
            ",".join(identity_map(columns)),
            "--out",
            str(tmp_path / "drive.log"),
        ]
    )
    assert code == 0
    assert "drive.log.meta.json" in capsys.readouterr().out
    assert (
        main(
            [
                "replay",
                str(tmp_path / "drive.log"),
                "--estimator",
                "zero",
                "--out",
                str(tmp_path / "out.csv"),
            ]
        )
        == 0
    )
    assert (tmp_path / "out.csv").read_text().count("\n") > 250


def test_truth_columns_become_the_logs_truth_csv_that_eval_reads(tmp_path, capsys):
    """--truth writes LOG.truth.csv on the log's time axis (epoch included), with units and
    signs applied; eval finds it beside the log, and zero's beta error is the truth itself."""
    from slipd.replay.importer import parse_truth
    from slipd.sim.writer import read_truth_csv, truth_path_of

    t = np.arange(0.0, 20.0, 0.01)
    beta_deg = 2.0 * np.sin(2.0 * np.pi * t / 10.0)  # two whole periods
    source = tmp_path / "ref.csv"
    columns = {
        "time": t, "ax": np.zeros_like(t), "ay": np.zeros_like(t), "yaw": np.zeros_like(t),
        "steer": np.zeros_like(t), "v_kmh": np.full_like(t, 72.0), "beta_deg": beta_deg,
    }
    header = ",".join(columns)
    rows = np.column_stack(list(columns.values()))
    source.write_text(header + "\n" + "\n".join(",".join(f"{v:.9g}" for v in r) for r in rows))
    log = tmp_path / "ref.log"
    report = import_table(
        source, PROFILE, parse_map(["ax=ax,ay=ay,yaw=yaw_rate,steer=steer"]), log, epoch=1000.0,
        derive=["wheel-speeds"], speed_spec="v_kmh:km/h",
        truth=parse_truth(["beta=-beta_deg:deg,vx=v_kmh:km/h"]))
    assert report.truth_rows == t.size
    truth, epoch = read_truth_csv(truth_path_of(log))
    assert epoch == 1000.0 and truth["t"][0] == 0.0
    assert np.allclose(truth["beta"], -np.radians(beta_deg), atol=1e-8)
    assert np.allclose(truth["vx"], 20.0)
    assert json.loads(sidecar_path(log).read_text())["truth"] == ["beta=-beta_deg:deg",
                                                                  "vx=v_kmh:km/h"]
    assert main(["eval", str(log), "--estimator", "zero", "--json"]) == 0
    zero = json.loads(capsys.readouterr().out)["estimators"]["zero"]
    assert zero["beta_rms_deg"] == pytest.approx(2.0 / math.sqrt(2.0), rel=0.02)


@pytest.mark.parametrize("spec, expected", [
    ("beta=b", "needs at least beta and vx"),
    ("beta=b,vx=v,beta=c", "given twice"),
    ("slip=b,vx=v", "NAME one of"),
    ("beta=b:furlong,vx=v", "unknown unit"),
])
def test_bad_truth_maps_are_clear_errors(spec, expected):
    from slipd.replay.importer import parse_truth

    with pytest.raises(ConfigError, match=expected):
        parse_truth([spec])
