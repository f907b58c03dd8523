"""slipd profile scaffold|check and slipd decode, as a user runs them on a new car."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from slipd.channels import In
from slipd.cli import main
from slipd.profile import PROFILE_DIR, load_profile

SHIPPED = ["default", "toyota_prius", "vw_golf_mk7", "hyundai_ioniq_5", "ford_escape_mk4"]


def _simulate(profile, path, scenario="handling_high_mu", duration=30.0):
    from slipd.sim import simulate
    from slipd.sim.writer import write_log

    write_log(path, simulate(scenario, profile=profile, seed=1, duration=duration), profile)
    return path


def _scaled(profile, channels, factor):
    """The profile with the SI factor of ``channels`` multiplied by ``factor``: a log written
    through it carries that fault for a reader with the right profile."""
    mapped = dict(profile.channels)
    for channel in channels:
        cmap = mapped[channel]
        mapped[channel] = dataclasses.replace(cmap, signals=tuple(
            dataclasses.replace(s, factor=s.factor * factor) for s in cmap.signals))
    return dataclasses.replace(profile, channels=mapped)


def _simulable(name):
    """The shipped profile; Toyota's 80 Hz messages at 100 Hz (the simulator's grid)."""
    profile = load_profile(name)
    if any(m.rate_hz == 80.0 for m in profile.messages.values()):
        profile = dataclasses.replace(profile, messages={
            k: dataclasses.replace(m, rate_hz=100.0) for k, m in profile.messages.items()})
    return profile


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    root = tmp_path_factory.mktemp("check")
    return {name: _simulate(_simulable(name), root / f"{name}.log") for name in SHIPPED}


@pytest.mark.parametrize("name", SHIPPED)
def test_check_passes_on_a_drive_of_each_shipped_profile(logs, name):
    from slipd.profile_tools.check import check_profile_on_log
    from slipd.replay.readers import read_frames

    report = check_profile_on_log(read_frames(logs[name]), _simulable(name))
    assert report.passed, report.text()
    for channel in ("ay", "yaw_rate", "steer", "wheel_speed_fl"):
        assert report.verdicts[channel].status == "ok", report.text()


def test_check_command_prints_a_verdict_per_channel(logs, capsys):
    assert main(["profile", "check", str(logs["vw_golf_mk7"]), "--profile", "vw_golf_mk7"]) == 0
    out = capsys.readouterr().out
    assert "verdict: pass" in out and "sign and unit consistent" in out


def test_check_names_a_flipped_yaw_rate_sign(tmp_path, capsys):
    profile = load_profile("vw_golf_mk7")
    log = _simulate(_scaled(profile, [In.YAW_RATE], -1.0), tmp_path / "flipped.log")
    assert main(["profile", "check", str(log), "--profile", "vw_golf_mk7"]) == 1
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.strip().startswith("yaw_rate"))
    assert "FAIL" in line and "sign flipped" in line
    assert "verdict: FAIL" in out
    for other in ("ay ", "steer "):
        assert "FAIL" not in next(x for x in out.splitlines() if x.strip().startswith(other))


def test_check_names_a_flipped_lateral_acceleration(tmp_path, capsys):
    profile = load_profile("hyundai_ioniq_5")
    log = _simulate(_scaled(profile, [In.AY], -1.0), tmp_path / "ay.log")
    assert main(["profile", "check", str(log), "--profile", "hyundai_ioniq_5"]) == 1
    line = next(x for x in capsys.readouterr().out.splitlines() if x.strip().startswith("ay "))
    assert "FAIL" in line and "sign flipped" in line


def test_check_names_wheel_speeds_in_the_wrong_unit(tmp_path, capsys):
    """An ECU sending m/s in a signal the profile reads as km/h (or the other way round)."""
    from slipd.profile_tools.check import check_profile_on_log
    from slipd.replay.readers import read_frames

    profile = _simulable("toyota_prius")
    wheels = [In.WHEEL_SPEED_FL, In.WHEEL_SPEED_FR, In.WHEEL_SPEED_RL, In.WHEEL_SPEED_RR]
    log = _simulate(_scaled(profile, wheels, 3.6), tmp_path / "kmh.log")
    report = check_profile_on_log(read_frames(log), profile)
    assert not report.passed
    out = report.text()
    line = next(x for x in out.splitlines() if x.strip().startswith("wheel_speed_fl"))
    assert "FAIL" in line and "unit: the speed reads 0.2" in line  # 1/3.6 x a_y/(r v)
    assert "FAIL" in next(x for x in out.splitlines() if x.strip().startswith("speed_ref"))


def test_check_names_one_wheel_off_the_others(tmp_path, capsys):
    profile = load_profile("vw_golf_mk7")
    log = _simulate(_scaled(profile, [In.WHEEL_SPEED_RL], 1 / 3.6), tmp_path / "rl.log")
    assert main(["profile", "check", str(log), "--profile", "vw_golf_mk7"]) == 1
    line = next(x for x in capsys.readouterr().out.splitlines()
                if x.strip().startswith("wheel_speed_rl"))
    assert "FAIL" in line and "3.6" in line


def test_check_reports_rates_and_rejections(tmp_path, capsys):
    profile = load_profile("vw_golf_mk7")
    log = _simulate(profile, tmp_path / "bad.log", duration=12.0)
    lines = log.read_text().splitlines()
    for k in range(0, len(lines), 3):  # corrupt every third ESP_02's CRC byte
        if " 101#" in lines[k]:
            head, data = lines[k].split("#")
            lines[k] = f"{head}#{int(data[:2], 16) ^ 0xFF:02X}{data[2:]}"
    log.write_text("\n".join(lines) + "\n")
    assert main(["profile", "check", str(log), "--profile", "vw_golf_mk7"]) == 1
    out = capsys.readouterr().out
    assert "FAIL ESP_02:" in out and "'e2e'" in out


def test_scaffold_proposes_a_loadable_profile_for_vw_mqb(tmp_path, capsys):
    out = tmp_path / "golf.toml"
    assert main(["profile", "scaffold", str(PROFILE_DIR / "vw_mqb.dbc"), "--out", str(out)]) == 0
    text = out.read_text()
    assert "REVIEW" in capsys.readouterr().out
    profile = load_profile(out)
    yaw = profile.channels[In.YAW_RATE].signals[0]
    assert (yaw.name, yaw.sign_signal, yaw.valid_signal) == (
        "ESP_Gierrate", "ESP_VZ_Gierrate", "ESP_QBit_Gierrate")
    steer = profile.channels[In.STEER].signals[0]
    assert steer.sign_signal == "LWI_VZ_Lenkradwinkel"
    assert profile.messages["ESP_02"].e2e == "autosar_crc8"
    assert text.count("# REVIEW") >= len(profile.channels)
    assert main(["profile", "scaffold", str(PROFILE_DIR / "vw_mqb.dbc"), "--out",
                 str(out)]) == 2  # no silent overwrite


def test_scaffold_of_the_toyota_dbc_matches_the_shipped_map(tmp_path):
    out = tmp_path / "prius.toml"
    assert main(["profile", "scaffold", str(PROFILE_DIR / "toyota_2017.dbc"), "--out",
                 str(out)]) == 0
    proposed, shipped = load_profile(out), load_profile("toyota_prius")
    for channel in (In.AX, In.AY, In.YAW_RATE, In.WHEEL_SPEED_FL, In.WHEEL_SPEED_RR):
        assert proposed.channels[channel].signals[0].name == \
            shipped.channels[channel].signals[0].name


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_decode_writes_the_si_channels_per_tick(logs, tmp_path, suffix, capsys):
    out = tmp_path / f"inputs{suffix}"
    assert main(["decode", str(logs["vw_golf_mk7"]), "--profile", "vw_golf_mk7", "--out",
                 str(out)]) == 0
    assert "ticks of 10 channels" in capsys.readouterr().out
    if suffix == ".csv":
        import json

        units = json.loads((tmp_path / "inputs.csv.meta.json").read_text())["columns"]
        assert units["yaw_rate"]["unit"] == "rad/s" and units["wheel_speed_fl"]["unit"] == "m/s"
        table = np.genfromtxt(out, delimiter=",", names=True)  # one plain header row
        columns = table.dtype.names
    else:
        import pyarrow.parquet as pq

        table = pq.read_table(out).to_pydict()
        columns = tuple(table)
    assert columns[0] == "t" and "yaw_rate_valid" in columns
    speed = np.asarray(table["wheel_speed_fl"])
    assert 5.0 < np.median(speed) < 60.0  # m/s, not km/h
    assert np.mean(np.asarray(table["yaw_rate_valid"])) > 0.95
