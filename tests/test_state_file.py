"""The state file's robustness: whatever is at its path, start-up goes on and says why the
saved state was ignored; a write that fails leaves nothing behind; killed writers' leftovers
are cleaned."""

from __future__ import annotations

import errno
import json
import math
import os
import threading

import can
import pytest

from slipd.daemon.loop import Daemon, DaemonConfig
from slipd.daemon.service import (
    ACCEL_OFFSET_LIMIT,
    StateStore,
    plausible_bound,
    plausible_state,
)
from slipd.estimators import consistency, registry
from slipd.pipeline import Pipeline
from slipd.profile import load_profile

PROFILE = load_profile("default")

LAYOUT = "abc"  # a state layout hash


def _load(store: StateStore, layout: str = LAYOUT):
    """load() in a thread, so a blocking read fails the test instead of hanging it."""
    result = []
    worker = threading.Thread(target=lambda: result.append(store.load("kinematic_heuristic",
                                                                       layout)), daemon=True)
    worker.start()
    worker.join(10)
    assert result, "StateStore.load blocked"
    return result[0]


HEAD = '{"method": "kinematic_heuristic", "layout": "abc", "state": '


def _write(path, text: str | bytes) -> None:
    path.write_bytes(text.encode() if isinstance(text, str) else text)


@pytest.mark.parametrize(("content", "reason"), [
    ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
    ((HEAD + '{"OFFSETS.AX": 1.0}}').encode() + b"\xff\xfe", "not UTF-8"),
    (HEAD + '{"OFFSETS.AX": [1, 2]}}', "corrupt"),
    (HEAD + '["OFFSETS.AX"]}', "corrupt"),
    ('["a list"]', "expected a JSON object"),
    ("{not json", "not JSON"),
])
def test_corrupt_contents_are_ignored_with_the_reason(tmp_path, content, reason):
    """A 400-digit integer (OverflowError) and deep nesting (RecursionError) stopped start-up."""
    path = tmp_path / "state.json"
    _write(path, content)
    values, message = _load(StateStore(path))
    assert values == {}
    assert "corrupt" in message and reason in message and str(path) in message


def test_a_directory_at_the_path_is_ignored(tmp_path):
    (tmp_path / "state.json").mkdir()
    values, message = _load(StateStore(tmp_path / "state.json"))
    assert values == {} and "a directory" in message


def test_a_fifo_at_the_path_does_not_block_start_up(tmp_path):
    """Reading a FIFO blocked start-up until something wrote into it."""
    os.mkfifo(tmp_path / "state.json")
    values, message = _load(StateStore(tmp_path / "state.json"))
    assert values == {} and "a FIFO" in message


def test_a_huge_file_is_not_read_whole(tmp_path):
    path = tmp_path / "state.json"
    with open(path, "wb") as handle:
        handle.truncate(64 << 20)  # sparse: 64 MB of zeros
    values, message = _load(StateStore(path))
    assert values == {} and "larger than" in message


def test_a_failed_write_leaves_no_temporary_and_raises(tmp_path, monkeypatch):
    store = StateStore(tmp_path / "state.json")
    store.save("kinematic_heuristic", LAYOUT, {"OFFSETS.AX": 2.0, "OFFSETS.AY": 3.0})

    def full_disk(_fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full_disk)
    with pytest.raises(OSError, match="No space left"):
        store.save("kinematic_heuristic", LAYOUT, {"OFFSETS.AX": 4.0, "OFFSETS.AY": 6.0})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.json"]
    assert json.loads((tmp_path / "state.json").read_text())["state"] == {"OFFSETS.AX": 2.0,
                                                                  "OFFSETS.AY": 3.0}


def test_temporaries_left_by_killed_writers_are_cleaned(tmp_path):
    """SIGKILL (or ENOSPC) between mkstemp and rename left .slipd-state-* files forever."""
    path = tmp_path / "state.json"
    ours = tmp_path / ".state.json.tmp-abc123"
    ours.write_text("{")
    legacy = tmp_path / ".slipd-state-xyz"
    legacy.write_text("{")
    old = os.stat(legacy).st_mtime - 3600
    os.utime(legacy, (old, old))
    someone_elses = tmp_path / ".other.json.tmp-def"
    someone_elses.write_text("{")
    StateStore(path).save("kinematic_heuristic", LAYOUT, {"OFFSETS.AX": 2.0})
    values, message = _load(StateStore(path))
    assert values == {"OFFSETS.AX": 2.0} and "2 temporary file(s)" in message
    assert not ours.exists() and not legacy.exists() and someone_elses.exists()


def _daemon_restoring(tmp_path, estimator: str, state_text: str) -> Daemon:
    """A daemon (not started) whose state file holds ``state_text`` under its layout."""
    layout = Pipeline(estimator, PROFILE).persistence_hash
    path = tmp_path / "state.json"
    path.write_text(f'{{"method": "{estimator}", "layout": "{layout}", "state": {state_text}}}')
    bus = can.Bus(interface="virtual", channel=f"state-{estimator}-{tmp_path.name}")
    config = DaemonConfig(profile=PROFILE, estimator=estimator, interface="virtual",
                          channel="unused", state_file=path)
    daemon = Daemon(config, bus=bus)
    daemon.bus_to_close = bus
    return daemon


def test_implausible_or_non_finite_restored_values_start_fresh_and_are_reported(tmp_path):
    """A restored offset was not bounds-checked: 57 m/s^2 of accelerometer offset went into
    the estimator; and one non-finite value (a 400-digit integer, 1e400, NaN) threw away the
    whole file, the plausible values with it."""
    daemon = _daemon_restoring(tmp_path, "kinematic_heuristic", (
        '{"OFFSETS.YAW_RATE": 0.004, "OFFSETS.AX": 57.0, "OFFSETS.AY": 1e400, '
        '"OFFSETS.ROLL_RATE": NaN, "OFFSETS.PITCH_RATE": ' + "9" * 400 + "}"))
    fresh = daemon.pipeline.new_state()
    slots = daemon.pipeline.persistent_slots
    message = daemon.restore_state()
    daemon.bus_to_close.shutdown()
    assert daemon.state[slots["OFFSETS.YAW_RATE"]] == 0.004
    for name in ("OFFSETS.AX", "OFFSETS.AY", "OFFSETS.ROLL_RATE", "OFFSETS.PITCH_RATE"):
        assert daemon.state[slots[name]] == fresh[slots[name]], name
    assert "4 of them rejected" in message
    assert "OFFSETS.AX = 57 m/s^2 is beyond +-2 m/s^2" in message
    assert "OFFSETS.AY = inf is not a finite number" in message
    assert "OFFSETS.ROLL_RATE = nan" in message and "OFFSETS.PITCH_RATE = inf" in message
    assert any("4 saved value(s) rejected" in event and str(tmp_path) in event
               for event in daemon.tool_events)


def test_a_restored_covariance_must_be_positive_semidefinite(tmp_path):
    """Yoon's calibration covariance is one 3 x 3 block: an indefinite one (each entry within
    bounds) is rejected whole; the calibration itself is still restored."""
    fresh = Pipeline("gnss_magnetometer", PROFILE).new_state()
    slots = Pipeline("gnss_magnetometer", PROFILE).persistent_slots
    saved = {name: float(fresh[index]) for name, index in slots.items()}
    saved["CAL_C[0]"] += 1.5
    saved["CAL_P[0]"] = -saved["CAL_P[4]"]  # a negative variance
    daemon = _daemon_restoring(tmp_path, "gnss_magnetometer", json.dumps(saved))
    message = daemon.restore_state()
    daemon.bus_to_close.shutdown()
    assert daemon.state[slots["CAL_C[0]"]] == fresh[slots["CAL_C[0]"]] + 1.5
    assert daemon.state[slots["CAL_P[0]"]] == fresh[slots["CAL_P[0]"]]
    assert "CAL_P is not positive semidefinite" in message
    accepted, rejected = plausible_state({**saved, "CAL_P[1]": saved["CAL_P[1]"] + 1.0,
                                          "CAL_P[0]": fresh[slots["CAL_P[0]"]]})
    assert rejected == ["CAL_P is not symmetric"] and "CAL_P[0]" not in accepted
    assert "CAL_C[0]" in accepted


@pytest.mark.parametrize("name", registry.available())
def test_every_persistent_element_has_a_plausible_bound_its_start_value_meets(name):
    """A method that persists a value names its bound in PLAUSIBLE_STATE; a fresh state
    (what a first save writes) passes the check unchanged."""
    pipeline = Pipeline(name, PROFILE)
    fresh = pipeline.new_state()
    values = {n: float(fresh[i]) for n, i in pipeline.persistent_slots.items()}
    for element in values:
        assert plausible_bound(element) is not None, element
    assert plausible_state(values) == (values, [])
    assert plausible_bound("KINEMATIC_HEURISTIC.OFFSETS.AX")[0] == ACCEL_OFFSET_LIMIT


def test_the_monitor_s_innovation_levels_on_this_car_survive_a_restart(tmp_path):
    """A fresh innovation level starts at the prior and learns a car whose level is far above
    it (the real run's ~24) in ~40 s, during which the dynamic witness vouches for less: the
    daemon keeps the levels it learnt (also for d_ekf, whose method persists nothing), and a
    restored level beyond what a tracking filter keeps starts fresh, reported."""
    path = tmp_path / "state.json"
    bus = can.Bus(interface="virtual", channel=f"levels-{tmp_path.name}")
    config = DaemonConfig(profile=PROFILE, estimator="d_ekf", interface="virtual",
                          channel="unused", state_file=path)
    daemon = Daemon(config, bus=bus)
    slots = daemon.pipeline.persistent_slots
    assert set(slots) == {f"CONSISTENCY.{name}" for name in consistency.PERSISTENT}
    learnt = {"CONSISTENCY.LOG_NIS_SUM": 0.9 * math.log(24.0),
              "CONSISTENCY.LOG_NIS_WEIGHT": 0.9,
              "CONSISTENCY.WITNESS_LOG_NIS_SUM": 0.5 * math.log(2700.0),
              "CONSISTENCY.WITNESS_LOG_NIS_WEIGHT": 0.5}
    for name, value in learnt.items():
        daemon.state[slots[name]] = value
    monitor = daemon.pipeline.parts(daemon.state)[2]
    assert monitor[consistency.S.LOG_NIS_SUM] == learnt["CONSISTENCY.LOG_NIS_SUM"]
    daemon.save_state()
    bus.shutdown()
    saved = json.loads(path.read_text())
    assert saved["layout"] == Pipeline("d_ekf", PROFILE).persistence_hash
    assert saved["state"] == learnt
    restarted = _daemon_restoring(tmp_path, "d_ekf", json.dumps(learnt))
    assert "restored 4 state values" in restarted.restore_state()
    restarted.bus_to_close.shutdown()
    assert {name: restarted.state[i] for name, i in slots.items()} == learnt
    # a level of 1e9 per measurement: no tracking filter keeps it; it starts fresh
    implausible = {**learnt, "CONSISTENCY.LOG_NIS_SUM": 0.9 * math.log(1e9)}
    restarted = _daemon_restoring(tmp_path, "d_ekf", json.dumps(implausible))
    message = restarted.restore_state()
    restarted.bus_to_close.shutdown()
    assert "1 of them rejected" in message and "CONSISTENCY.LOG_NIS_SUM" in message
    assert restarted.state[slots["CONSISTENCY.LOG_NIS_SUM"]] == 0.0
    # the monitor's layout is part of the file's identity
    assert Pipeline("d_ekf", PROFILE, monitor=False).persistence_hash != saved["layout"]
