"""slipd identify on simulated drives with known truth (slipd.identify.truth): the endurance
route of CommonRoad vehicle 1 (900 s: town, country road, two stops) sensed with two seeds,
the IMU misaligned by 1.5 deg per axis (plus the random 0.3 deg), the steering sensor 3 deg
off, the wheels' radii off, identified from a wrong profile (steering ratio +15 %, cornering
stiffness -30 % / +30 %, roll stiffness +50 %, yaw inertia +30 %). Each quantity's truth
must lie in its 95 % interval and within the issue's tolerance; the written profile loads
with the values; bad input is a clear error. benchmarks/identify.py runs vehicles 1-3."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slipd.channels import Veh
from slipd.cli import main
from slipd.errors import ConfigError
from slipd.identify import identify, parse_only
from slipd.identify.profile_text import write_profile
from slipd.identify.truth import TOLERANCE, compare, truth_of, write_car_profile
from slipd.profile import load_profile

WRONG = {"vehicle.steering_ratio": 1.15, "vehicle.tyre.cornering_stiffness_front": 0.7,
         "vehicle.tyre.cornering_stiffness_rear": 1.3, "vehicle.roll_stiffness": 1.5,
         "vehicle.yaw_inertia": 1.3}
VARIANT = "misalignment,steer_offset"
SENSOR = {"wheel_radius_bias": (0.01, -0.005, 0.0, 0.008)}
SEEDS = (1, 2)


@pytest.fixture(scope="module")
def drives(tmp_path_factory):
    from slipd.sim.core import run_plan, sense
    from slipd.sim.writer import write_log

    folder = tmp_path_factory.mktemp("identify")
    right = write_car_profile(folder / "right.toml", 1)
    wrong = write_car_profile(folder / "wrong.toml", 1, scale=WRONG)
    plant = run_plan("endurance", 1, 900.0)
    out = {}
    for seed in SEEDS:
        result = sense("endurance", plant, 1, seed, load_profile(right), SENSOR, VARIANT)
        log = folder / f"seed{seed}.log"
        write_log(log, result, load_profile(right))
        found = identify([log], load_profile(wrong), progress=False)
        out[seed] = (log, result, found)
    return folder, right, wrong, out


@pytest.mark.parametrize("seed", SEEDS)
def test_every_quantity_is_recovered_within_its_interval_and_tolerance(drives, seed):
    _, _, _, out = drives
    _, result, found = out[seed]
    checks = compare(found, truth_of(result, 1))
    # the yaw inertia is fitted and reported, never written (its fit is biased, see
    # single_track.YAW_INERTIA_NOT_WRITTEN); its reason names the fitted value
    left = found.left()
    assert {c.key for c in checks} | set(left) == set(TOLERANCE), left
    assert set(left) == {"vehicle.yaw_inertia"}, left
    assert "kg m^2" in left["vehicle.yaw_inertia"].reason
    assert found.vehicle[Veh.YAW_INERTIA] == found.profile.vehicle[Veh.YAW_INERTIA]
    for c in checks:
        assert c.inside, (c, found.outcome.findings[c.key].method)
        assert c.within_tolerance, (c, TOLERANCE[c.key])


def test_the_wrong_profile_is_corrected_in_the_written_copy(drives, tmp_path):
    _, _, wrong, out = drives
    _, result, found = out[SEEDS[0]]
    path = tmp_path / "identified.toml"
    text = write_profile(found, path)
    new, old = load_profile(path), load_profile(wrong)
    assert "slipd identify:" in text and "95 % CI" in text and "was 18.4" in text
    assert new.vehicle[Veh.STEER_RATIO] == pytest.approx(16.0, rel=0.02)
    assert old.vehicle[Veh.STEER_RATIO] == pytest.approx(18.4)
    truth = truth_of(result, 1)
    np.testing.assert_allclose(new.calibration.imu_mounting_deg,
                               truth["calibration.imu_mounting_deg"], atol=0.3)
    assert new.calibration.steer_offset_deg == pytest.approx(
        truth["calibration.steer_offset_deg"][0], abs=0.1)
    # the dbc is found from the new place, the rest of the profile is the old one's
    assert new.dbc_path == old.dbc_path and new.messages.keys() == old.messages.keys()


def test_only_writes_the_chosen_quantities_and_lists_the_others(drives, tmp_path):
    _, _, wrong, out = drives
    log, _, _ = out[SEEDS[0]]
    path = tmp_path / "only.toml"
    assert main(["identify", str(log), "--profile", str(wrong), "--out", str(path),
                 "--only", "gyro_offset,steer_offset", "--quiet"]) == 0
    new, old = load_profile(path), load_profile(wrong)
    assert new.calibration.gyro_offset != (0.0, 0.0, 0.0)
    assert new.calibration.steer_offset_deg != 0.0
    assert new.calibration.imu_mounting_deg == (0.0, 0.0, 0.0)
    np.testing.assert_array_equal(new.vehicle, old.vehicle)


def test_a_drive_without_usable_segments_says_why_and_changes_nothing(tmp_path, capsys):
    from slipd.commands.sim import simulate_to_files

    simulate_to_files("sine_steer", tmp_path, seed=0, duration=4.0)
    out = tmp_path / "new.toml"
    assert main(["identify", str(tmp_path / "sine_steer.log"), "--out", str(out),
                 "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "no standstill" in printed and "left as they were" in printed
    assert "cornering stiffness not identified" in printed
    new, old = load_profile(out), load_profile("default")
    np.testing.assert_array_equal(new.vehicle, old.vehicle)
    assert "not identified, left as it was: vehicle.tyre.cornering_stiffness_front" in \
        out.read_text().replace("\n#   ", " ")


def test_bad_input_is_a_clear_error(tmp_path, capsys):
    profile = tmp_path / "p.toml"
    write_car_profile(profile, 1)
    missing = tmp_path / "nothing.log"
    assert main(["identify", str(missing), "--profile", str(profile), "--out",
                 str(tmp_path / "x.toml"), "--quiet"]) == 2
    assert f"{missing}: no such log" in capsys.readouterr().err
    log = tmp_path / "bad.log"
    log.write_text("this is not a bus log\n")
    assert main(["identify", str(log), "--profile", str(profile), "--out",
                 str(tmp_path / "x.toml"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "bad.log" in err and "Traceback" not in err
    assert main(["identify", str(log), "--profile", str(profile), "--out", str(profile),
                 "--quiet"]) == 2
    assert "is the profile itself" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="unknown quantity .*'yaw'.* expected names from"):
        parse_only("gyro_offset,yaw")


def test_the_single_track_kernel_and_its_plain_twin_agree():
    from slipd.identify.single_track import simulate_segments, simulate_segments_plain

    rng = np.random.default_rng(3)
    n = 600
    delta = 0.02 * np.sin(np.arange(n) * 0.01 * 2 * math.pi * 0.5) + rng.normal(0, 1e-3, n)
    lateral = rng.normal(0.0, 0.1, n)
    vx = 15.0 + 5.0 * np.sin(np.arange(n) * 0.003)
    starts, stops = np.array([0, 250], np.int64), np.array([240, 600], np.int64)
    params = np.array([120e3, 110e3, 1800.0, 1300.0, 1.1, 1.5])
    outs = [np.zeros(n) for _ in range(4)]
    simulate_segments(params, delta, lateral, vx, starts, stops, outs[0], outs[1])
    simulate_segments_plain(params, delta, lateral, vx, starts, stops, outs[2], outs[3])
    np.testing.assert_allclose(outs[0], outs[2], rtol=0, atol=1e-12)
    np.testing.assert_allclose(outs[1], outs[3], rtol=0, atol=1e-12)


def test_the_report_writes_the_summary_and_every_figure(drives, tmp_path):
    from slipd.identify.report import write_report

    _, _, _, out = drives
    files = write_report(out[SEEDS[0]][2], tmp_path / "report", ["extra line"])
    names = {f.name for f in files}
    assert names == {"summary.txt", "handling_diagram.png", "fit_residuals.png", "offsets.png",
                     "roll_gradient.png"}
    for f in files:
        assert f.stat().st_size > 1000, f
    summary = (tmp_path / "report" / "summary.txt").read_text()
    assert "understeer gradient (handling diagram)" in summary and "extra line" in summary
