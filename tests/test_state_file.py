"""The state file's robustness: whatever is at its path, start-up goes on and says why the
saved state was ignored; a write that fails leaves nothing behind; killed writers' leftovers
are cleaned."""

from __future__ import annotations

import errno
import json
import os
import threading

import pytest

from slipd.daemon.service import StateStore

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
    (HEAD + '{"OFFSETS.AX": ' + "9" * 400 + "}}", "non-finite"),
    ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
    ((HEAD + '{"OFFSETS.AX": 1.0}}').encode() + b"\xff\xfe", "not UTF-8"),
    (HEAD + '{"OFFSETS.AX": [1, 2]}}', "corrupt"),
    (HEAD + '["OFFSETS.AX"]}', "corrupt"),
    (HEAD + '{"OFFSETS.AX": NaN}}', "non-finite"),
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
