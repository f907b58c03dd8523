"""Evaluation metrics on synthetic signals, and ``slipd eval`` end to end on a short log."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from slipd.channels import N_OUT, Out, Status
from slipd.eval.metrics import KPH, errors, pooled, score, wrap_angle

DEG = math.pi / 180.0


def _estimate(t: np.ndarray, beta: np.ndarray, vx: np.ndarray) -> np.ndarray:
    out = np.zeros((t.size, N_OUT))
    out[:, Out.BETA] = beta
    out[:, Out.VX] = vx
    return out


def test_constant_error_gives_equal_rms_max_p99():
    t = np.arange(0.0, 10.0, 0.01)
    truth_beta = 2.0 * DEG * np.sin(t)
    est = _estimate(t, truth_beta + 1.0 * DEG, np.full(t.size, 20.5))
    e = errors(t, est, t, truth_beta, np.full(t.size, 20.0))
    s = e.scores()
    assert s.beta_rms_deg == pytest.approx(1.0)
    assert s.beta_max_deg == pytest.approx(1.0)
    assert s.beta_p99_deg == pytest.approx(1.0, rel=1e-3)  # histogram resolution
    assert s.vx_rms_mps == pytest.approx(0.5)
    assert s.samples == t.size


def test_sine_error_rms_is_amplitude_over_sqrt2():
    t = np.arange(0.0, 20.0, 0.01)
    est = _estimate(t, 0.5 * DEG * np.sin(2 * np.pi * t), np.full(t.size, 15.0))
    s = errors(t, est, t, np.zeros(t.size), np.full(t.size, 15.0)).scores()
    assert s.beta_rms_deg == pytest.approx(0.5 / math.sqrt(2.0), rel=1e-3)
    assert s.beta_max_deg == pytest.approx(0.5, rel=1e-3)
    assert 0.49 < s.beta_p99_deg <= 0.5


def test_speed_threshold_and_time_range_select_samples():
    t_truth = np.arange(0.0, 10.0, 0.01)
    vx = np.where(t_truth < 5.0, 3.0, 10.0)  # 10.8 km/h, then 36 km/h
    t_est = np.arange(-1.0, 12.0, 0.01)  # ticks before and after the truth are not scored
    est = _estimate(t_est, np.full(t_est.size, 1.0 * DEG), np.full(t_est.size, 10.0))
    e = errors(t_est, est, t_truth, np.zeros(t_truth.size), vx, min_speed=20.0 * KPH)
    assert e.t.min() > 5.0 - 0.02 and e.t.max() <= t_truth[-1]
    assert e.scores().samples == pytest.approx(500, abs=2)
    none = errors(t_est, est, t_truth, np.zeros(t_truth.size), vx, min_speed=50.0 * KPH)
    assert none.scores().samples == 0 and math.isnan(none.scores().beta_rms_deg)


def test_truth_is_interpolated_onto_the_ticks():
    """Truth at 100 Hz, ticks offset by 5 ms: a ramp interpolates exactly."""
    t_truth = np.arange(0.0, 5.0, 0.01)
    beta = 0.01 * t_truth
    t_est = t_truth[:-1] + 0.005
    est = _estimate(t_est, 0.01 * t_est, np.full(t_est.size, 20.0))
    s = errors(t_est, est, t_truth, beta, np.full(t_truth.size, 20.0)).scores()
    assert s.beta_max_deg < 1e-9


def test_nonfinite_estimates_are_counted_not_scored():
    t = np.arange(0.0, 1.0, 0.01)
    beta = np.zeros(t.size)
    beta[:10] = np.nan
    e = errors(t, _estimate(t, beta, np.full(t.size, 20.0)), t, np.zeros(t.size),
               np.full(t.size, 20.0))
    assert e.rejected_nonfinite == 10 and e.scores().samples == t.size - 10


def test_errors_wrap_across_pi():
    assert wrap_angle(np.array([math.pi + 0.1]))[0] == pytest.approx(-math.pi + 0.1)
    t = np.arange(0.0, 1.0, 0.01)
    est = _estimate(t, np.full(t.size, math.pi - 0.01), np.full(t.size, 20.0))
    s = errors(t, est, t, np.full(t.size, -math.pi + 0.01), np.full(t.size, 20.0)).scores()
    assert s.beta_max_deg == pytest.approx(math.degrees(0.02), rel=1e-6)


def test_pooled_equals_scoring_the_concatenation():
    rng = np.random.default_rng(0)
    t = np.arange(0.0, 3.0, 0.01)
    parts = []
    for k in range(3):
        est = _estimate(t, rng.normal(0, (k + 1) * DEG, t.size), np.full(t.size, 20.0))
        parts.append(errors(t, est, t, np.zeros(t.size), np.full(t.size, 20.0)))
    direct = score(np.concatenate([p.beta_err for p in parts]),
                   np.concatenate([p.vx_err for p in parts]),
                   np.concatenate([p.valid for p in parts]),
                   np.concatenate([p.sigma_beta for p in parts]))
    pool = pooled(parts)
    for name, value in pool.as_dict().items():
        assert value == pytest.approx(getattr(direct, name), rel=1e-12, nan_ok=True), name


def _with_status(out: np.ndarray, valid: np.ndarray, sigma: float) -> np.ndarray:
    out[:, Out.STATUS] = np.where(valid, float(Status.VALID), float(Status.NOT_CONVERGED))
    out[:, Out.SIGMA_BETA] = sigma
    return out


def test_validity_metrics_count_only_valid_ticks():
    """10 % of the ticks are VALID and 3 deg off, the rest invalid and 10 deg off: the VALID
    figures see only the first, the all-tick figures both."""
    t = np.arange(0.0, 10.0, 0.01)
    valid = np.zeros(t.size, dtype=bool)
    valid[::10] = True
    beta = np.where(valid, 3.0, 10.0) * DEG
    out = _with_status(_estimate(t, beta, np.full(t.size, 20.0)), valid, 1.0 * DEG)
    s = errors(t, out, t, np.zeros(t.size), np.full(t.size, 20.0)).scores()
    assert s.valid_fraction == pytest.approx(0.1)
    assert s.valid_samples == valid.sum()
    assert s.valid_rms_deg == pytest.approx(3.0)
    assert s.valid_max_err_deg == pytest.approx(3.0)
    assert s.valid_err_over_2deg == 1.0 and s.valid_err_over_5deg == 0.0
    assert s.sigma2_coverage == 0.0  # 3 deg > 2 x 1 deg
    assert s.beta_max_deg == pytest.approx(10.0)
    wide = errors(t, _with_status(out.copy(), valid, 2.0 * DEG), t, np.zeros(t.size),
                  np.full(t.size, 20.0)).scores()
    assert wide.sigma2_coverage == 1.0


def test_a_method_never_valid_has_no_valid_figures_and_nonfinite_ticks_count_as_invalid():
    t = np.arange(0.0, 1.0, 0.01)
    beta = np.zeros(t.size)
    beta[:50] = np.nan  # never VALID (supervise requires finite values)
    valid = np.zeros(t.size, dtype=bool)
    valid[50:75] = True
    out = _with_status(_estimate(t, beta, np.full(t.size, 20.0)), valid, math.nan)
    s = errors(t, out, t, np.zeros(t.size), np.full(t.size, 20.0)).scores()
    assert s.valid_fraction == pytest.approx(25 / 100)  # the window counts the NaN ticks
    assert s.sigma2_coverage == 0.0  # a NaN sigma covers nothing
    never = errors(t, _with_status(out.copy(), np.zeros(t.size, bool), 0.0), t,
                   np.zeros(t.size), np.full(t.size, 20.0)).scores()
    assert never.valid_fraction == 0.0 and never.valid_samples == 0
    assert math.isnan(never.valid_rms_deg) and math.isnan(never.sigma2_coverage)


def test_p99_of_the_histogram_is_within_its_resolution():
    rng = np.random.default_rng(1)
    b = rng.normal(0.0, 1.0, 200_000) * DEG
    s = score(b, np.zeros(b.size))
    assert s.beta_p99_deg == pytest.approx(np.percentile(np.degrees(np.abs(b)), 99.0),
                                           rel=1e-3)


# --- end to end -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def short_log(tmp_path_factory):
    pytest.importorskip("vehiclemodels")
    from slipd.commands.sim import simulate_to_files

    out = tmp_path_factory.mktemp("sim")
    simulate_to_files("step_steer", out, duration=5.0)
    return out / "step_steer.log", out / "step_steer.truth.csv"


def test_eval_json_of_the_zero_estimator_is_the_truth_rms(short_log, capsys):
    """The zero estimator's beta error is the truth itself: the CLI's RMS must equal the RMS
    of the truth over the samples above 20 km/h (checks time alignment end to end)."""
    from slipd.cli import main
    from slipd.sim.writer import read_truth_csv

    log, truth_path = short_log
    assert main(["eval", str(log), "--truth", str(truth_path), "--estimator", "zero",
                 "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    zero = doc["estimators"]["zero"]
    assert {"beta_rms_deg", "beta_max_deg", "beta_p99_deg", "vx_rms_mps", "samples",
            "valid_fraction", "valid_err_over_2deg", "valid_err_over_5deg", "valid_max_err_deg",
            "sigma2_coverage", "valid_rms_deg", "valid_p99_deg"} <= set(zero)
    truth, _ = read_truth_csv(truth_path)
    fast = truth["speed"] > 20.0 * KPH
    expected = math.degrees(math.sqrt(np.mean(truth["beta"][fast] ** 2)))
    assert zero["beta_rms_deg"] == pytest.approx(expected, rel=0.03)
    assert zero["samples"] == pytest.approx(fast.sum(), abs=3)


def test_eval_plot_and_suite(short_log, capsys, tmp_path):
    pytest.importorskip("matplotlib")
    from slipd.cli import main

    log, truth_path = short_log
    png = tmp_path / "eval.png"
    assert main(["eval", str(log), "--truth", str(truth_path), "--estimator", "zero",
                 "--plot", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "zero" in capsys.readouterr().out  # the table
    assert main(["eval", "--suite", str(log.parent), "--estimator", "zero", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert "step_steer" in doc["scenarios"] and "zero" in doc["overall"]["estimators"]
    summary = tmp_path / "suite.svg"
    assert main(["eval", "--suite", str(log.parent), "--estimator", "zero", "--plot",
                 str(summary)]) == 0
    assert b"<svg" in summary.read_bytes()[:2000]


def test_eval_mismatch_changes_the_model_based_estimate_not_the_zero_one(short_log, capsys,
                                                                           tmp_path):
    """--mismatch runs each case on the same log with the estimator's profile perturbed:
    `zero` does not use the profile (same figures in every case), d_ekf does (its
    cornering-stiffness cases differ from nominal), and --out holds every case."""
    from slipd.cli import main

    log, truth_path = short_log
    out = tmp_path / "mismatch.json"
    assert main(["eval", str(log), "--truth", str(truth_path), "--estimator", "zero,d_ekf",
                 "--mismatch", "c-30%,steering_ratio+5%", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "== mismatch c-30%" in text and "cases pooled" in text
    doc = json.loads(out.read_text())
    cases = doc["mismatch"]["cases"]
    assert set(cases) == {"c-30%", "steering_ratio+5%"}
    nominal = doc["estimators"]
    for case in cases.values():
        assert case["estimators"]["zero"]["beta_rms_deg"] == nominal["zero"]["beta_rms_deg"]
        assert case["estimators"]["d_ekf"]["beta_rms_deg"] != nominal["d_ekf"]["beta_rms_deg"]
    assert "d_ekf" in doc["mismatch"]["pooled"]["estimators"]
    assert main(["eval", str(log), "--mismatch", "nosuch"]) == 2
    assert "unknown case" in capsys.readouterr().err


def test_mismatch_cases_perturb_the_profile_and_what_derives_from_it():
    from slipd.channels import In, Veh
    from slipd.eval.mismatch import CASES
    from slipd.profile import load_profile

    base = load_profile("default")
    steer = load_profile("default", edit=CASES["steering_ratio+5%"].edit())
    assert steer.vehicle[Veh.STEER_RATIO] == pytest.approx(1.05 * base.vehicle[Veh.STEER_RATIO])
    factor = steer.channels[In.STEER].signals[0].factor  # decode follows the wrong ratio
    assert factor == pytest.approx(base.channels[In.STEER].signals[0].factor / 1.05)
    imu = load_profile("default", edit=CASES["imu_x+10cm"].edit())
    assert imu.vehicle[Veh.IMU_X] == pytest.approx(base.vehicle[Veh.IMU_X] + 0.10)
    both = load_profile("default", edit=CASES["c+30%"].edit())
    for key in (Veh.CORNERING_STIFFNESS_F, Veh.CORNERING_STIFFNESS_R):
        assert both.vehicle[key] == pytest.approx(1.3 * base.vehicle[key])
    assert np.array_equal(load_profile("default").vehicle, base.vehicle)  # nothing leaks


def test_eval_reports_user_errors(tmp_path, capsys):
    from slipd.cli import main

    assert main(["eval", str(tmp_path / "missing.log"), "--truth", str(tmp_path / "x.csv"),
                 "--estimator", "zero"]) == 2
    assert "no such log" in capsys.readouterr().err
    assert main(["eval", "--suite", str(tmp_path), "--estimator", "nope"]) == 2
