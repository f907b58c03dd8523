"""``slipd eval --plot``: the single-log figure (with inputs), the suite and mismatch summaries
(heatmaps and pooled CDFs) in PNG, PDF and SVG, and a method's style in every figure."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from slipd.cli import main  # noqa: E402
from slipd.eval import plots  # noqa: E402


@pytest.fixture(scope="module")
def suite(tmp_path_factory):
    pytest.importorskip("vehiclemodels")
    from slipd.commands.sim import simulate_to_files

    folder = tmp_path_factory.mktemp("plots")
    for scenario in ("step_steer", "sine_steer"):
        simulate_to_files(scenario, folder, duration=4.0)
    return folder


def test_single_log_figure_with_inputs_as_pdf(suite, tmp_path, capsys):
    out = tmp_path / "one.pdf"
    assert main(["eval", str(suite / "step_steer.log"), "--estimator", "zero,d_ekf",
                 "--plot", str(out), "--plot-inputs"]) == 0
    assert out.read_bytes()[:5] == b"%PDF-"
    assert f"figure -> {out}" in capsys.readouterr().err


def test_suite_and_mismatch_write_heatmaps_and_pooled_cdfs(suite, tmp_path, capsys):
    summary = tmp_path / "suite.png"
    assert main(["eval", "--suite", str(suite), "--estimator", "zero,kinematic_heuristic",
                 "--plot", str(summary)]) == 0
    assert summary.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / "suite.cdf.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    mismatch = tmp_path / "mismatch.svg"
    assert main(["eval", "--suite", str(suite), "--estimator", "zero", "--mismatch",
                 "mass+15%", "--plot", str(mismatch)]) == 0
    assert b"<svg" in mismatch.read_bytes()[:2000]
    assert b"<svg" in (tmp_path / "mismatch.cdf.svg").read_bytes()[:2000]
    assert "mismatch.cdf.svg" in capsys.readouterr().err
    assert main(["eval", "--suite", str(suite), "--estimator", "zero", "--plot",
                 str(tmp_path / "x.gif")]) == 2


def test_a_method_keeps_its_style_and_the_registered_methods_are_distinct():
    from slipd.estimators.registry import available

    names = available()
    looks = {(plots.style(n)["color"], plots.style(n)["linestyle"]) for n in names}
    assert len(looks) == len(names)
    assert plots.style("d_ekf") == plots.style(names.index("d_ekf"))
    assert all(s["color"] != plots.TRUTH_COLOUR for s in map(plots.style, names))


def test_pooled_cdf_matches_the_sorted_errors():
    from slipd.eval.metrics import Accumulator

    rng = np.random.default_rng(3)
    err = np.radians(rng.normal(0.0, 1.0, 20_000))
    x, f = Accumulator().add_arrays(err, np.zeros(err.size)).cdf()
    exact = np.sort(np.degrees(np.abs(err)))
    for q in (0.1, 0.5, 0.9, 0.99):
        assert np.interp(q, f, x) == pytest.approx(np.quantile(exact, q), rel=3e-3)
    assert f[-1] == 1.0
