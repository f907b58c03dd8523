"""File formats in and out, each read back with its own library: the replay CSV (pandas
defaults), Parquet (pyarrow), MCAP (mcap), MF4 out and in (asammdf, python-can)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from slipd.cli import main
from slipd.profile import load_profile
from slipd.replay.engine import run_log

METHODS = ["zero", "d_ekf"]


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    pytest.importorskip("vehiclemodels")
    from slipd.commands.sim import simulate_to_files

    folder = tmp_path_factory.mktemp("formats")
    simulate_to_files("sine_steer", folder, duration=4.0)
    log = folder / "sine_steer.log"
    return log, run_log(log, "default", METHODS)


def test_replay_csv_is_plain_and_pandas_reads_it_with_defaults(drive, tmp_path):
    pd = pytest.importorskip("pandas")
    log, engine = drive
    out = tmp_path / "est.csv"
    assert main(["replay", str(log), "--estimator", ",".join(METHODS), "--out", str(out)]) == 0
    table = pd.read_csv(out)
    assert list(table.columns) == ["t", "estimator", "beta_deg", "beta_rate_deg_s", "vx_mps",
                                   "vy_mps", "mu", "sigma_beta_deg", "roll_deg",
                                   "friction_class", "status"]
    assert table["status"].dtype == np.int64 and table["t"].dtype == np.float64
    for m in METHODS:
        rows = table[table["estimator"] == m]
        assert np.allclose(rows["beta_deg"], np.degrees(engine[m].out[:, 0]), atol=6e-6)
        assert np.array_equal(rows["status"], engine[m].out[:, 8].astype(int))
        assert np.allclose(rows["t"], engine[m].t, atol=1e-6, rtol=0)
    # zero estimates no friction and d_ekf reports its only once its estimator has settled:
    # empty cells read as NaN
    for m in METHODS:
        mu = table[table["estimator"] == m]["mu"].to_numpy()
        assert np.allclose(mu, engine[m].out[:, 4], atol=1e-6, equal_nan=True)
    assert table[table["estimator"] == "zero"]["mu"].isna().all()
    assert table["mu"].isna().any()
    meta = json.loads((tmp_path / "est.csv.meta.json").read_text())
    assert meta["columns"]["beta_deg"]["unit"] == "deg" and meta["estimators"] == METHODS
    assert "VALID" in meta["columns"]["status"]["description"]
    # the table goes back into the API's evaluate as it is
    import slipd
    from slipd.sim.writer import truth_path_of

    scores = slipd.evaluate(table, truth_path_of(log))
    direct = slipd.evaluate(slipd.estimate(log, estimator=METHODS), truth_path_of(log))
    assert np.allclose(scores["beta_rms_deg"], direct["beta_rms_deg"], rtol=1e-4)


def test_parquet_carries_units_in_its_schema(drive, tmp_path):
    pq = pytest.importorskip("pyarrow.parquet")
    log, engine = drive
    out = tmp_path / "est.parquet"
    assert main(["replay", str(log), "--estimator", ",".join(METHODS), "--out", str(out)]) == 0
    table = pq.read_table(out)
    units = {f.name: f.metadata[b"unit"].decode() for f in table.schema}
    assert units["beta_deg"] == "deg" and units["vx_mps"] == "m/s" and units["t"] == "s"
    run = json.loads(table.schema.metadata[b"slipd"])
    assert run["estimators"] == METHODS and run["profile"] == "default"
    data = table.to_pydict()
    ours = [k for k, name in enumerate(data["estimator"]) if name == "d_ekf"]
    assert np.array_equal(np.array(data["beta_deg"])[ours],
                          np.degrees(engine["d_ekf"].out[:, 0]))
    assert data["mu"][ours[0]] is None


def test_mcap_holds_inputs_every_estimator_and_the_truth(drive, tmp_path):
    pytest.importorskip("mcap")
    from mcap.reader import make_reader

    from slipd.sim.writer import read_truth_csv, truth_path_of

    log, engine = drive
    out = tmp_path / "run.mcap"
    assert main(["replay", str(log), "--estimator", ",".join(METHODS), "--out", str(out)]) == 0
    with open(out, "rb") as handle:
        reader = make_reader(handle)
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == {"/slipd/inputs", "/slipd/estimate/zero", "/slipd/estimate/d_ekf",
                               "/slipd/truth"}
        for channel in topics.values():
            schema = summary.schemas[channel.schema_id]
            assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
            assert json.loads(schema.data)["type"] == "object"
        counts = summary.statistics.channel_message_counts
        ticks = len(engine["d_ekf"].t)
        assert counts[topics["/slipd/estimate/d_ekf"].id] == ticks
        assert counts[topics["/slipd/inputs"].id] == ticks
        truth, _ = read_truth_csv(truth_path_of(log))
        assert counts[topics["/slipd/truth"].id] == len(truth["t"])
        beta, stamps = [], []
        for _, _, message in reader.iter_messages(topics=["/slipd/estimate/d_ekf"]):
            row = json.loads(message.data)
            beta.append(row["beta"])
            stamps.append(message.log_time)
        inputs = next(json.loads(m.data) for _, _, m in
                      reader.iter_messages(topics=["/slipd/inputs"]))
    assert np.array_equal(beta, engine["d_ekf"].out[:, 0])
    assert np.all(np.abs(np.array(stamps) / 1e9 - engine["d_ekf"].t) < 1e-6)
    assert {"ay", "ay_valid", "yaw_rate", "wheel_speed_fl"} <= set(inputs)
    schema = json.loads(summary.schemas[topics["/slipd/estimate/d_ekf"].schema_id].data)
    assert schema["properties"]["beta"]["description"].startswith("[rad]")


def test_mf4_out_reads_back_with_asammdf(drive, tmp_path):
    asammdf = pytest.importorskip("asammdf")
    log, engine = drive
    out = tmp_path / "run.mf4"
    assert main(["replay", str(log), "--estimator", ",".join(METHODS), "--out", str(out)]) == 0
    mdf = asammdf.MDF(str(out))
    try:
        beta = mdf.get("d_ekf.beta")
        start = mdf.header.start_time.timestamp()
        assert beta.unit == "rad"
        assert np.array_equal(beta.samples, engine["d_ekf"].out[:, 0])
        assert np.allclose(beta.timestamps + start, engine["d_ekf"].t, atol=1e-6, rtol=0)
        status = mdf.get("zero.status").samples
        assert np.array_equal(status, engine["zero"].out[:, 8].astype(int))
        assert mdf.get("inputs.yaw_rate").unit == "rad/s"
        assert mdf.get("truth.beta").samples.size > 0
    finally:
        mdf.close()


def _messages_with_fd_and_a_second_bus(log):
    import can

    messages = list(can.LogReader(str(log)))
    t0 = messages[0].timestamp
    extra = [
        can.Message(timestamp=t0 + 0.0005, arbitration_id=0x1ABCDE0, is_extended_id=True,
                    data=bytes(range(8)), channel=1),
        can.Message(timestamp=t0 + 0.0015, arbitration_id=0x321, is_fd=True,
                    bitrate_switch=True, data=bytes(range(64)), channel=1),
        can.Message(timestamp=t0 + 0.0025, arbitration_id=0x322, is_fd=True,
                    error_state_indicator=True, data=bytes(range(12)), channel=1, is_rx=False),
    ]
    return sorted(messages + extra, key=lambda m: m.timestamp)


def test_mf4_bus_log_reads_as_python_can_reads_it_and_replays(drive, tmp_path):
    pytest.importorskip("asammdf")
    import can

    from slipd.replay.messages import frames_from_messages
    from slipd.replay.readers import read_frames

    log, engine = drive
    mf4 = tmp_path / "bus.mf4"
    with can.Logger(str(mf4)) as writer:  # python-can's MF4Writer (asammdf)
        for message in _messages_with_fd_and_a_second_bus(log):
            writer.on_message_received(message)
    ours = read_frames(mf4)
    reference = frames_from_messages(can.LogReader(str(mf4)))
    for name in ("t", "frame_id", "flags", "dlc", "data", "channel"):
        assert np.array_equal(getattr(ours, name), getattr(reference, name)), name
    assert ours.channels == reference.channels
    fd = ours.dlc == 64
    assert fd.sum() == 1 and np.array_equal(ours.data[fd][0], np.arange(64))
    out = tmp_path / "est.csv"
    assert main(["replay", str(mf4), "--estimator", "d_ekf", "--out", str(out)]) == 0
    pd = pytest.importorskip("pandas")
    beta = pd.read_csv(out)["beta_deg"].to_numpy()
    assert np.allclose(beta, np.degrees(engine["d_ekf"].out[:, 0]), atol=6e-6)


def test_mf4_that_is_not_a_bus_log_is_a_clear_error(tmp_path, capsys):
    asammdf = pytest.importorskip("asammdf")
    signals = tmp_path / "signals.mf4"
    mdf = asammdf.MDF(version="4.10")
    mdf.append([asammdf.Signal(np.zeros(5), np.arange(5.0), name="ay")])
    mdf.save(signals, overwrite=True)
    assert main(["replay", str(signals)]) == 2
    assert "no CAN bus-logging channel group" in capsys.readouterr().err
    (tmp_path / "junk.mf4").write_bytes(b"not an mdf file at all")
    assert main(["replay", str(tmp_path / "junk.mf4")]) == 2
    assert "not a readable MDF file" in capsys.readouterr().err


def test_signal_level_mf4_imports_as_its_csv_does(tmp_path):
    """The real run's columns written as an MF4 import to the same bus log as the CSV; with
    channels in two groups at other rates, --raster samples and holds them."""
    asammdf = pytest.importorskip("asammdf")
    from benchmarks.accuracy import REAL_CSV, REAL_IMPORT, REAL_PROFILE
    from slipd.replay.importer import import_table, parse_map, parse_truth, read_table

    if not REAL_CSV.exists():
        pytest.skip(f"{REAL_CSV} not found")
    table = read_table(REAL_CSV)
    n = 3000
    t = table["t_s"][:n]
    mdf = asammdf.MDF(version="4.10")
    mdf.append([asammdf.Signal(table[c][:n], t, name=c) for c in table if c != "t_s"])
    source = tmp_path / "revs.mf4"
    mdf.save(source, overwrite=True)
    csv = tmp_path / "revs.csv"
    columns = list(table)
    np.savetxt(csv, np.column_stack([table[c][:n] for c in columns]), delimiter=",",
               header=",".join(columns), comments="", fmt="%.17g")
    profile = load_profile(REAL_PROFILE)
    args = dict(derive=["wheel-speeds"], speed_spec=REAL_IMPORT["speed"],
                truth=parse_truth(REAL_IMPORT["truth"]))
    mapping = parse_map(REAL_IMPORT["map"])
    import_table(csv, profile, mapping, tmp_path / "csv.log", time_spec="t_s:s", **args)
    import_table(source, profile, mapping, tmp_path / "mf4.log", time_spec="t:s", **args)
    assert (tmp_path / "csv.log").read_bytes() == (tmp_path / "mf4.log").read_bytes()

    split = asammdf.MDF(version="4.10")  # the IMU at 100 Hz, steering at 50 Hz, offset
    imu = [c for c in table if c not in ("t_s", "steer_road_rad")]
    split.append([asammdf.Signal(table[c][:n], t, name=c) for c in imu])
    split.append([asammdf.Signal(table["steer_road_rad"][:n:2], t[::2] + 0.003,
                                 name="steer_road_rad")])
    split.save(tmp_path / "split.mf4", overwrite=True)
    report = import_table(tmp_path / "split.mf4", profile, mapping, tmp_path / "split.log",
                          time_spec="t:s", raster=0.01, **args)
    assert report.messages["STEERING"] == pytest.approx(n, abs=2)
    meta = json.loads((tmp_path / "split.log.meta.json").read_text())
    assert meta["raster"].startswith("0.01 s")
    assert not math.isnan(read_table(tmp_path / "split.mf4", {"steer_road_rad"}, 0.01)
                          ["steer_road_rad"][5])


def test_writers_fed_in_chunks_write_what_one_call_writes(drive, tmp_path):
    """A streaming replay hands the writers a run in pieces: the files hold the same rows."""
    pq = pytest.importorskip("pyarrow.parquet")
    asammdf = pytest.importorskip("asammdf")
    from slipd.replay.engine import latch_log_or_recording
    from slipd.replay.readers import read_frames
    from slipd.replay.writers import RunInfo, open_writer, write_estimates

    log, engine = drive
    profile = load_profile("default")
    inputs = latch_log_or_recording(read_frames(log), profile)
    info = RunInfo(METHODS, "default", str(log), sorted(profile.channels, key=int),
                   float(inputs.t[0]))
    for suffix in (".csv", ".parquet", ".mf4"):
        whole, pieces = tmp_path / f"whole{suffix}", tmp_path / f"pieces{suffix}"
        write_estimates(whole, [engine[m] for m in METHODS], info, inputs)
        with open_writer(pieces, info) as writer:
            bounds = np.linspace(0, len(inputs.t), 4).astype(int)
            writer.write_inputs(inputs.t[: bounds[1]], inputs.U[: bounds[1]])
            writer.write_inputs(inputs.t[bounds[1]:], inputs.U[bounds[1]:])
            for m in METHODS:
                est = engine[m]
                for a, b in zip(bounds[:-1], bounds[1:], strict=True):
                    writer.write(m, est.t[a:b], est.out[a:b])
        if suffix == ".csv":
            assert whole.read_bytes() == pieces.read_bytes()
        elif suffix == ".parquet":
            a, b = pq.read_table(whole), pq.read_table(pieces)
            assert a.schema == b.schema and a.to_pandas().equals(b.to_pandas())  # NaN == NaN
        else:
            a, b = asammdf.MDF(str(whole)), asammdf.MDF(str(pieces))
            for name in ("d_ekf.beta", "zero.status", "inputs.ay"):
                assert np.array_equal(a.get(name).samples, b.get(name).samples), name
                assert np.array_equal(a.get(name).timestamps, b.get(name).timestamps), name
            a.close()
            b.close()
