"""Evaluation metrics on synthetic signals, and ``slipd eval`` end to end on a short log."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from slipd.channels import N_OUT, Out
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
    assert s.beta_p99_deg == pytest.approx(1.0)
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
                   np.concatenate([p.vx_err for p in parts]))
    assert pooled(parts) == direct


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
    assert set(zero) == {"beta_rms_deg", "beta_max_deg", "beta_p99_deg", "vx_rms_mps",
                         "samples"}
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


def test_eval_reports_user_errors(tmp_path, capsys):
    from slipd.cli import main

    assert main(["eval", str(tmp_path / "missing.log"), "--truth", str(tmp_path / "x.csv"),
                 "--estimator", "zero"]) == 2
    assert "no such log" in capsys.readouterr().err
    assert main(["eval", "--suite", str(tmp_path), "--estimator", "nope"]) == 2
