"""The registry (slipd.estimators.registry): permanent wire IDs, variants, the entry-point group
for third-party methods, and the state-layout builder every method's state is made with."""

from __future__ import annotations

import enum
import textwrap
import warnings

import cantools
import numpy as np
import pytest

from slipd.channels import N_OUT, U_LEN
from slipd.codec.plan import SLIPD_DBC
from slipd.errors import ConfigError
from slipd.estimators import registry
from slipd.estimators.common.layout import build_layout
from slipd.pipeline import Pipeline

#: SLIPD_AUX.ESTIMATOR_ID of every method, as cars on the road decode them. Never change a
#: value here: a new method gets a new ID, a removed one's ID stays retired.
WIRE_IDS = {
    "zero": 0,
    "kinematic_heuristic": 1,
    "dk_ekf": 2,
    "d_ekf": 3,
    "k_kf": 4,
    "gnss_magnetometer": 5,
    "pseudo_fusion": 6,
    "pseudo_fusion_kbe": 7,
    "pseudo_fusion_dbe": 8,
    "pseudo_fusion_wbe": 9,
    "hybrid_friction": 10,
    "hybrid_friction_nocls": 11,
    "ensemble": 12,
    "linear_kf": 13,
}


def test_wire_ids_are_pinned():
    assert {s.name: s.wire_id for s in registry.BUILTIN} == WIRE_IDS


def test_the_dbc_names_every_wire_id():
    db = cantools.database.load_file(str(SLIPD_DBC))
    choices = db.get_message_by_name("SLIPD_AUX").get_signal_by_name("ESTIMATOR_ID").choices
    assert {str(name): int(value) for value, name in choices.items()} == WIRE_IDS


def test_the_pipeline_sends_the_wire_id_not_a_position(profile):
    for name, wire_id in WIRE_IDS.items():
        assert Pipeline(name, profile).wire_id == wire_id


def test_a_variant_is_its_module_with_overrides():
    kbe = registry.load("pseudo_fusion_kbe")
    fused = registry.load("pseudo_fusion")
    assert kbe.module is fused.module and kbe.spec.family == fused.spec.family == "chen2018"
    part = kbe.module.PARAMS.PART
    assert kbe.params[part] == 1.0 and fused.params[part] == 0.0
    # a caller's override comes on top of the variant's
    assert registry.load("pseudo_fusion_kbe", {"min_speed": 5.0}).params[part] == 1.0


def test_names_from_a_command_line():
    assert registry.parse_names("all") == registry.available()
    assert registry.parse_names("zero, dk_ekf") == ["zero", "dk_ekf"]
    with pytest.raises(ConfigError, match="available: zero"):
        registry.parse_names("zero,nonsense")
    with pytest.raises(ConfigError, match="unknown parameter 'bogus'"):
        registry.load("zero", {"bogus": 1.0})


def test_a_name_with_parameter_values_is_the_method_with_them_set(profile):
    name = "pseudo_fusion_kbe:min_speed=4:kbe_vy_leak_time_constant=0"
    tuned = registry.load(name)
    base = registry.load("pseudo_fusion_kbe")
    assert tuned.name == name and tuned.module is base.module
    params = tuned.module.PARAMS
    assert tuned.params[params.MIN_SPEED] == 4.0
    assert tuned.params[params.KBE_VY_LEAK_TIME_CONSTANT] == 0.0
    assert tuned.params[params.PART] == base.params[params.PART]  # the variant's own stay
    assert not tuned.spec.ensemble
    assert Pipeline(name, profile).wire_id == WIRE_IDS["pseudo_fusion_kbe"]
    assert registry.parse_names(f"pseudo_fusion_kbe,{name}") == ["pseudo_fusion_kbe", name]
    # the paper's observer beside slipd's default in one run, through the whole data path
    from slipd.api import estimate, simulate

    log = simulate("step_steer", duration=8.0)
    both = estimate(log, estimator=["kinematic_heuristic", "kinematic_heuristic:steady_gain=0"])
    by_override = estimate(log, estimator="kinematic_heuristic",
                           overrides={"steady_gain": 0.0})
    default = estimate(log, estimator="kinematic_heuristic")
    tuned_beta = both[both.estimator == "kinematic_heuristic:steady_gain=0"].beta.to_numpy()
    assert np.array_equal(tuned_beta, by_override.beta.to_numpy())
    assert np.array_equal(both[both.estimator == "kinematic_heuristic"].beta.to_numpy(),
                          default.beta.to_numpy())
    assert not np.array_equal(tuned_beta, default.beta.to_numpy())


@pytest.mark.parametrize(("name", "message"), [
    ("d_ekf:min_speed", "'min_speed' is not KEY=VALUE"),
    ("d_ekf:=3", "'=3' is not KEY=VALUE"),
    ("d_ekf:min_speed=fast", "min_speed = 'fast' is not a number"),
    ("d_ekf:min_sped=3", "estimator 'd_ekf:min_sped=3': unknown parameter 'min_sped'"),
    ("d_ekff:min_speed=3", "unknown estimator 'd_ekff'"),
])
def test_a_bad_parameter_value_in_a_name_says_which_and_why(name, message):
    with pytest.raises(ConfigError, match=message):
        registry.parse_names(f"zero,{name}")


def test_ensemble_members_come_from_the_registry():
    from slipd.estimators import ensemble

    assert ensemble.MEMBERS == tuple(s.name for s in registry.ensemble_members())
    families = [registry.spec(name).family for name in ensemble.MEMBERS]
    for i, a in enumerate(families):
        for j, b in enumerate(families):
            assert (ensemble.FAMILY[i] == ensemble.FAMILY[j]) == (a == b)


# ---------------------------------------------------------------------------------------------
# third-party methods through the slipd.estimators entry-point group
# ---------------------------------------------------------------------------------------------


def install_plugin(root, dist: str, entry_points: dict[str, str], module: str, source: str):
    """A distribution on sys.path as pip would install it: the module and its dist-info."""
    (root / f"{module}.py").write_text(textwrap.dedent(source))
    info = root / f"{dist}-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 1.0\n")
    lines = "".join(f"{name} = {value}\n" for name, value in entry_points.items())
    (info / "entry_points.txt").write_text(f"[slipd.estimators]\n{lines}")


@pytest.fixture
def plugins(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(tmp_path))
    registry.reset_plugins()
    yield tmp_path
    registry.reset_plugins()


def test_a_third_party_method_registers_through_the_entry_point_group(plugins, profile):
    install_plugin(plugins, "slipd-plugin-floor", {"plugin_floor": "plugin_floor:SPEC"},
                   "plugin_floor", '''
        from slipd.estimators.registry import Spec
        from slipd.estimators.zero import DEFAULTS, LAYOUT, PARAMS, init, run_ticks, step

        SPEC = Spec("plugin_floor", "plugin_floor", wire_id=200, family="plugin")
        ''')  # fmt: skip
    assert "plugin_floor" in registry.available()
    method = registry.load("plugin_floor")
    assert method.spec.wire_id == 200 and method.module.__name__ == "plugin_floor"
    pipeline = Pipeline("plugin_floor", profile)
    assert pipeline.wire_id == 200.0
    out = pipeline.run(np.zeros((5, U_LEN)))
    assert out.shape == (5, N_OUT)


def test_a_broken_or_conflicting_plugin_is_reported_and_left_out(plugins):
    install_plugin(plugins, "slipd-plugin-bad", {
        "takes_a_builtin_id": "plugin_bad:TAKEN",
        "not_a_spec": "plugin_bad:NOT_A_SPEC",
        "cannot_import": "plugin_missing:SPEC",
    }, "plugin_bad", '''
        from slipd.estimators.registry import Spec

        TAKEN = Spec("takes_a_builtin_id", "plugin_bad", wire_id=5, family="plugin")
        NOT_A_SPEC = {"name": "not_a_spec"}
        ''')  # fmt: skip
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        names = registry.available()
    reported = " ".join(str(w.message) for w in caught)
    for name in ("takes_a_builtin_id", "not_a_spec", "cannot_import"):
        assert name not in names and name in reported
    assert "wire_id 5" in reported and "expected 128..254" in reported
    with pytest.raises(ConfigError, match="cannot be loaded.*plugin_missing"):
        registry.spec("cannot_import")
    assert "zero" in names  # the builtin methods are unaffected


# ---------------------------------------------------------------------------------------------
# state layouts
# ---------------------------------------------------------------------------------------------


class Block(enum.IntEnum):
    A = 0
    B = 1


def test_a_layout_places_fields_and_names_every_element():
    inner = build_layout("inner", "X", ("Y", 2))
    layout = build_layout("outer", "VX", ("P", 3), ("OFF", Block), ("SUB", inner), "LAST")
    assert [int(layout.S[f]) for f in ("VX", "P", "OFF", "SUB", "LAST")] == [0, 1, 4, 6, 9]
    assert layout.size == 10
    assert layout.element_names == ("VX", "P[0]", "P[1]", "P[2]", "OFF.A", "OFF.B", "SUB.X",
                                    "SUB.Y[0]", "SUB.Y[1]", "LAST")
    assert layout.indices(["OFF", "SUB.Y[1]", "VX"]) == (4, 5, 8, 0)
    with pytest.raises(KeyError, match="NOPE"):
        layout.indices(["NOPE"])
    with pytest.raises(ValueError, match="twice"):
        build_layout("bad", "A", "A")


def test_the_layout_hash_changes_with_any_name_or_position():
    base = build_layout("m", "A", ("B", 2)).hash
    assert build_layout("m", "A", ("B", 2)).hash == base
    assert build_layout("m", ("B", 2), "A").hash != base
    assert build_layout("m", "A", ("B", 3)).hash != base
    assert build_layout("m", "A", ("C", 2)).hash != base
    assert build_layout("n", "A", ("B", 2)).hash != base


def test_every_method_persists_names_its_layout_has():
    for spec in registry.BUILTIN:
        method = registry.load(spec.name)
        assert method.layout is not None, spec.name
        method.layout.indices(method.persistent)  # raises on a name the layout lacks
