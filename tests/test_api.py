"""The Python API (slipd.decode/estimate/evaluate/simulate/plot, slipd.Estimator): every way in
gives the replay engine's outputs, and importing slipd has no side effects."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pd = pytest.importorskip("pandas", reason="slipd's Python API returns pandas DataFrames")
pytest.importorskip("vehiclemodels", reason="the drives are simulated")

import slipd  # noqa: E402
from slipd.errors import ConfigError  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
METHODS = ["zero", "kinematic_heuristic", "d_ekf"]


def _python(code: str, env: dict[str, str]) -> str:
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                          text=True, timeout=600, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    return done.stdout


def _clean_env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    return {**env, **extra}


def test_importing_slipd_compiles_nothing_and_changes_no_environment_variable(tmp_path):
    code = """
import json, os, sys
before = dict(os.environ)
import slipd
names = [slipd.decode, slipd.estimate, slipd.evaluate, slipd.simulate, slipd.plot,
         slipd.Estimator, slipd.read_truth]
print(json.dumps({"env_same": dict(os.environ) == before,
                  "numba": "numba" in sys.modules, "pandas": "pandas" in sys.modules}))
"""
    for env in (_clean_env(), _clean_env(NUMBA_CACHE_DIR=str(tmp_path))):
        result = json.loads(_python(code, env))
        assert result == {"env_same": True, "numba": False, "pandas": False}


def test_api_kernels_cache_under_the_source_key_and_leave_numba_config_as_found():
    """The API's kernels land in <NUMBA_CACHE_DIR>/<source key> (stale-cache protection),
    while the variable and numba's config.CACHE_DIR stay what the user set."""
    from slipd.numba_cache import source_key

    base = str(Path(os.environ["NUMBA_CACHE_DIR"]).parent)  # conftest keyed the suite's
    code = """
import json, os
import slipd
e = slipd.Estimator("zero")
out = e.step({"ax": 0.0, "wheel_speed_fl": 10.0}, t=0.01)
from numba.core import config
from slipd.estimators import zero
from slipd.estimators import supervision
print(json.dumps({"env": os.environ["NUMBA_CACHE_DIR"], "config": config.CACHE_DIR,
                  "zero": zero.step._cache._cache_path,
                  "supervise": supervision.supervise._cache._cache_path,
                  "status": out.status}))
"""
    result = json.loads(_python(code, _clean_env(NUMBA_CACHE_DIR=base)))
    assert result["env"] == base and result["config"] == base
    for kernel in ("zero", "supervise"):
        assert result[kernel].startswith(os.path.join(base, source_key()) + os.sep), result


def test_the_slipd_command_keys_the_cache_variable_for_itself_and_its_children(tmp_path):
    from slipd.numba_cache import source_key

    code = """
import os
from slipd.cli import main
try:
    main(["--version"])
except SystemExit:
    pass
print(os.environ["NUMBA_CACHE_DIR"])
"""
    out = _python(code, _clean_env(NUMBA_CACHE_DIR=str(tmp_path))).strip().splitlines()[-1]
    assert out == str(tmp_path / source_key())


def test_a_script_that_imports_a_kernel_module_directly_caches_it_under_the_source_key(tmp_path):
    """Neither the command nor the API: numba's default would cache in the module's
    __pycache__, keyed to that file alone, and a kernel inlining another slipd module would
    run stale code after an upgrade. A user's own cache=True function keeps numba's locator."""
    from slipd.numba_cache import source_key

    user = tmp_path / "user_kernels.py"
    user.write_text("import numba\n\n@numba.njit(cache=True)\ndef twice(x):\n    return 2 * x\n")
    code = f"""
import json, sys
sys.path.insert(0, {str(tmp_path)!r})
from slipd.estimators.righetti_lenzo2025 import d_ekf
from slipd.estimators import supervision
from slipd.sim import mb_fast
import user_kernels
print(json.dumps({{"d_ekf": d_ekf.run_ticks._cache._cache_path,
                  "supervise": supervision.supervise._cache._cache_path,
                  "plant": [getattr(mb_fast, n)._cache._cache_path for n in dir(mb_fast)
                            if hasattr(getattr(mb_fast, n), "_cache")][0],
                  "user": user_kernels.twice._cache._cache_path}}))
"""
    xdg = tmp_path / "xdg"
    paths = json.loads(_python(code, _clean_env(XDG_CACHE_HOME=str(xdg))).splitlines()[-1])
    keyed = os.path.join(str(xdg), "slipd", "numba", source_key()) + os.sep
    for kernel in ("d_ekf", "supervise", "plant"):
        assert paths[kernel].startswith(keyed), paths
    assert paths["user"] == str(tmp_path / "__pycache__")


def test_every_cached_kernel_module_imports_numba_through_the_keyed_locator():
    """The locator is installed when numba is imported as ``from slipd.numba_cache import nb``;
    a module importing numba itself could decorate its kernels before that."""
    import ast

    offenders = []
    for path in sorted((ROOT / "slipd").rglob("*.py")):
        if path.name == "numba_cache.py":
            continue
        tree = ast.parse(path.read_text())
        cached = any(isinstance(node, ast.keyword) and node.arg == "cache"
                     for node in ast.walk(tree))
        direct = any(isinstance(node, ast.Import) and any(a.name.split(".")[0] == "numba"
                                                           for a in node.names)
                     or isinstance(node, ast.ImportFrom) and (node.module or "").startswith("numba")
                     for node in ast.walk(tree))
        if cached and direct:
            offenders.append(str(path.relative_to(ROOT)))
    assert not offenders, f"import numba as `from slipd.numba_cache import nb` in {offenders}"


#: kernels of the hot-path packages that keep numba's runtime, and why
KEEPS_NUMBA_RUNTIME = {
    "slipd.replay.candump._format": "the candump writer allocates its digit buffer once a call",
}


def test_the_per_frame_and_per_tick_kernels_are_compiled_without_numba_runtime():
    """Codec, estimators and the log parser are compiled with ``_nrt=False``
    (slipd.numba_cache): with numba's runtime each array an inlined helper or a call is
    handed costs an atomic reference count and its release, 78 % of the decode's time
    (measured). A kernel that allocates does not compile so, which is the brief's "no
    allocation per tick" made a compile error. ``inline="always"`` helpers are compiled
    into their callers, with the callers' options."""
    import importlib
    import pkgutil

    from numba.core.registry import CPUDispatcher

    with_runtime = []
    for package in ("slipd.codec", "slipd.estimators", "slipd.replay"):
        for info in pkgutil.walk_packages(importlib.import_module(package).__path__,
                                          package + "."):
            module = importlib.import_module(info.name)
            for name, kernel in vars(module).items():
                if not (isinstance(kernel, CPUDispatcher)
                        and kernel.py_func.__module__ == module.__name__):
                    continue
                options = kernel.targetoptions
                qualified = f"{module.__name__}.{name}"
                if (options.get("inline") != "always" and options.get("_nrt", True)
                        and qualified not in KEEPS_NUMBA_RUNTIME):
                    with_runtime.append(qualified)
    assert not with_runtime, f"compile these with _nrt=False: {with_runtime}"


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    folder = tmp_path_factory.mktemp("api")
    sim = slipd.simulate("double_lane_change", duration=8.0, out=folder)
    return sim


def _same(a: pd.DataFrame, b: pd.DataFrame) -> None:
    columns = ["t", "beta", "beta_rate", "vx", "vy", "mu", "sigma_beta", "roll",
               "friction_class", "status", "valid"]
    assert list(a["estimator"]) == list(b["estimator"])
    for c in columns:
        assert np.array_equal(a[c].to_numpy(), b[c].to_numpy(), equal_nan=True), c


def test_estimate_of_a_log_a_simulation_messages_and_decoded_channels_agree(drive):
    """Every source reaches the same estimates as the replay engine (slipd replay)."""
    import can

    from slipd.replay.engine import run_log

    by_log = slipd.estimate(drive.log, estimator=METHODS)
    engine = run_log(drive.log, "default", METHODS)
    for m in METHODS:
        rows = by_log[by_log["estimator"] == m]
        assert np.array_equal(rows["beta"].to_numpy(), engine[m].out[:, 0], equal_nan=True)
        assert np.array_equal(rows["t"].to_numpy(), engine[m].t)
    _same(by_log, slipd.estimate(drive, estimator=METHODS))
    _same(by_log, slipd.estimate(drive.messages(), estimator=METHODS))  # a generator
    _same(by_log, slipd.estimate(list(can.LogReader(str(drive.log))), estimator=METHODS))
    _same(by_log, slipd.estimate(slipd.decode(drive.log), estimator=METHODS))
    assert by_log.attrs["units"]["beta"] == "rad" and by_log["valid"].dtype == bool
    assert str(by_log["estimator"].dtype) == "category"


def test_decode_gives_si_channels_with_validity_per_tick(drive):
    frame = slipd.decode(drive.log)
    assert list(frame.columns[:5]) == ["t", "ax", "ax_valid", "ay", "ay_valid"]
    assert frame["ay_valid"].dtype == bool
    assert np.allclose(np.diff(frame["t"]), 0.01, rtol=0, atol=1e-6)
    assert frame["ay_valid"].iloc[10:].all()
    truth = drive.truth
    ay_true = np.interp(frame["t"], truth["t"], truth["ay"])
    gain = np.dot(frame["ay"], ay_true) / np.dot(ay_true, ay_true)
    assert 0.9 < gain < 1.25  # m/s^2 (body frame: the roll adds g sin(roll), ~10 %)
    assert frame.attrs["units"]["yaw_rate"] == "rad/s"
    assert frame.attrs["errors"]["IMU_ACCEL"]["accepted"] > 700
    mapped = slipd.decode(drive)
    assert {"ax", "steer", "wheel_speed_rr"} <= set(mapped.columns)


def test_estimator_step_and_receive_tick_reproduce_estimate(drive):
    """slipd.Estimator in a loop: SI values per tick (rows of decode) and CAN frames with a
    tick every 10 ms both give the batch outputs exactly."""
    import can

    batch = slipd.estimate(drive.log, estimator="kinematic_heuristic")
    decoded = slipd.decode(drive.log)
    by_values = slipd.Estimator("kinematic_heuristic")
    stepped = [by_values.step(row) for row in decoded.to_dict("records")]
    assert np.array_equal([o.beta for o in stepped], batch["beta"].to_numpy(), equal_nan=True)
    assert [o.status for o in stepped] == list(batch["status"])

    by_frames = slipd.Estimator("kinematic_heuristic", profile="default")
    messages = list(can.LogReader(str(drive.log)))
    ticks, outputs, i = batch["t"].to_numpy(), [], 0
    for t in ticks:
        while i < len(messages) and messages[i].timestamp <= t:
            by_frames.receive(messages[i])
            i += 1
        outputs.append(by_frames.tick(t))
    assert np.array_equal([o.beta for o in outputs], batch["beta"].to_numpy(), equal_nan=True)
    assert [o.valid for o in outputs] == list(batch["valid"])
    by_frames.reset()
    assert not by_frames.tick(ticks[0]).valid  # empty latch: inputs missing


def test_estimator_step_marks_absent_and_nan_channels_invalid():
    e = slipd.Estimator("zero")
    full = {"ax": 0.0, "ay": 0.0, "yaw_rate": 0.0, "steer": 0.0,
            **{f"wheel_speed_{w}": 15.0 for w in ("fl", "fr", "rl", "rr")}}
    assert e.step(full, t=0.01).vx == pytest.approx(15.0)
    missing = e.step({**full, "ay": float("nan")}, t=0.02)
    assert not missing.valid and missing.status & 4  # INPUT_TIMEOUT
    flagged = e.step({**full, "steer_valid": False}, t=0.03)
    assert flagged.status & 4
    with pytest.raises(ConfigError, match="'yawrate' is not an input channel"):
        e.step({**full, "yawrate": 0.1})
    with pytest.raises(ConfigError, match="after the last tick"):
        e.step(full, t=0.02)
    with pytest.raises(ConfigError, match="one estimator name"):
        slipd.Estimator("zero,d_ekf")


def test_evaluate_scores_as_slipd_eval_does(drive, tmp_path):
    from slipd.eval.runs import evaluate_log

    est = slipd.estimate(drive.log, estimator=METHODS)
    scores = slipd.evaluate(est, drive.truth_path)
    reference, _ = evaluate_log(drive.log, drive.truth_path, METHODS, "default")
    assert list(scores.index) == METHODS
    for m in METHODS:
        expected = reference[m].scores().as_dict()
        for key, value in expected.items():
            assert scores.loc[m, key] == pytest.approx(value, nan_ok=True, rel=1e-12), key
    assert {"valid_fraction", "valid_err_over_5deg", "sigma2_coverage"} <= set(scores.columns)
    same = slipd.evaluate(est, drive)  # the Simulation as truth
    assert np.allclose(same.to_numpy(float), scores.to_numpy(float), equal_nan=True)


def test_errors_name_what_is_wrong(drive):
    decoded = slipd.decode(drive.log)[["t", "ax", "ay"]]
    with pytest.raises(ConfigError, match=r"\['speed'\] are not slipd input channels"):
        slipd.estimate(decoded.assign(speed=1.0))
    with pytest.raises(ConfigError, match="10 ms ticks"):
        slipd.estimate(decoded.iloc[::1].assign(t=decoded["t"] * 0.1))
    with pytest.raises(ConfigError, match="unknown estimator"):
        slipd.estimate(drive.log, estimator="nope")
    with pytest.raises(ConfigError, match="no such log"):
        slipd.decode("missing.log")
    with pytest.raises(ConfigError, match=r"truth lacks column\(s\) \['vx'\]"):
        slipd.evaluate(slipd.estimate(decoded), pd.DataFrame({"t": [0, 1], "beta": [0, 0]}))
    with pytest.raises(ConfigError, match="python-can Messages"):
        slipd.estimate(42)


def test_plot_draws_png_pdf_svg_and_small_multiples(drive, tmp_path):
    pytest.importorskip("matplotlib")
    est = slipd.estimate(drive, estimator=METHODS)
    fig = slipd.plot(est, drive, tmp_path / "three.png", inputs=slipd.decode(drive))
    assert (tmp_path / "three.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(fig.axes) == 4 + 4  # inputs, beta, VALID strip, error, CDF
    slipd.plot(est, drive, tmp_path / "three.pdf")
    assert (tmp_path / "three.pdf").read_bytes()[:5] == b"%PDF-"
    five = slipd.estimate(drive, estimator=METHODS + ["k_kf", "pseudo_fusion_dbe"])
    fig = slipd.plot(five, drive, tmp_path / "five.svg")
    assert b"<svg" in (tmp_path / "five.svg").read_bytes()[:2000]
    assert len(fig.axes) == 1 + 5 + 1  # truth, one panel per method, CDF
    with pytest.raises(ConfigError, match="expected a file ending in"):
        slipd.plot(est, drive, tmp_path / "x.jpg")


def test_a_two_bus_profile_through_the_api_and_the_estimator(tmp_path):
    """A simulated drive of a profile on two buses (IMU on chassis, the rest on pt): the
    Simulation, its log and its messages estimate alike, and Estimator.receive reads each
    message's channel as its bus (or as ``buses`` maps it)."""
    from tests.test_buses import two_bus_profile

    profile = two_bus_profile(tmp_path)
    sim = slipd.simulate("step_steer", duration=3.0, profile=profile, out=tmp_path)
    by_log = slipd.estimate(sim.log, profile=profile, estimator="d_ekf")
    _same(by_log, slipd.estimate(sim, profile=profile, estimator="d_ekf"))
    assert by_log["valid"].any()
    renamed = []
    for message in sim.messages():
        message.channel = {"chassis": "can1", "pt": "can0"}[message.channel]
        renamed.append(message)
    for buses, messages in ((None, list(sim.messages())),
                            ({"chassis": "can1", "pt": "can0"}, renamed)):
        e = slipd.Estimator("d_ekf", profile=profile, buses=buses)
        outputs, i = [], 0
        for t in by_log["t"].to_numpy():
            while i < len(messages) and messages[i].timestamp <= t:
                e.receive(messages[i])
                i += 1
            outputs.append(e.tick(t))
        assert np.array_equal([o.beta for o in outputs], by_log["beta"].to_numpy(),
                              equal_nan=True)
    blind = slipd.Estimator("d_ekf", profile=profile, buses={"chassis": "can9", "pt": "can0"})
    assert not any(blind.receive(m) for m in renamed[:50] if m.channel == "can1")
