"""Test-session setup (the keyed numba cache) and the fixtures shared by the test modules: the
vehicle of the default profile and simulated drives decoded through the codec, as the product
sees them.

Simulating costs seconds per drive, so each drive is simulated once per test session into a
temporary directory (a candump log written through the codec, then read back, decoded and
latched by the batch engine) and shared by every test that asks for it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from slipd.numba_cache import use_keyed_cache

# The kernels cache under a key of slipd's sources, as for the slipd command (importing slipd
# no longer sets it); child processes the tests start inherit the variable.
use_keyed_cache()

#: The drives every estimator is checked on through the codec: (scenario, seconds or None for
#: the scenario's own length). A steady corner on a dry road, friction jumps under a loaded
#: car (the friction estimators and classifiers), and a drift beyond the single-track models'
#: domain (saturation, resets, clamps).
CODEC_DRIVES: tuple[tuple[str, float | None], ...] = (
    ("step_steer", None),
    ("mu_jump", 25.0),
    ("snow_drift", None),
)


@dataclass(frozen=True)
class CodecDrive:
    """A simulated drive as a log and as the latched inputs the estimators see."""

    scenario: str
    log: Path
    truth: dict[str, np.ndarray]
    inputs: object  # slipd.replay.engine.Inputs


@pytest.fixture(scope="session")
def profile():
    """The default vehicle profile (the simulator's BMW 320i)."""
    from slipd.profile import load_profile

    return load_profile("default")


@pytest.fixture(scope="session")
def vehicle(profile) -> np.ndarray:
    """The default profile's vehicle vector (a copy per session; tests must not mutate it: a
    read-only array would make numba compile every kernel a second time for that type)."""
    return np.array(profile.vehicle, dtype=np.float64)


@pytest.fixture(scope="session")
def codec_drives(tmp_path_factory, profile) -> dict[str, CodecDrive]:
    """``CODEC_DRIVES`` simulated (seed 0), written as candump logs and latched on 100 Hz ticks
    through the codec: {scenario: CodecDrive}."""
    from slipd.replay.engine import latch_log
    from slipd.replay.readers import read_frames
    from slipd.sim import simulate
    from slipd.sim.writer import write_log

    directory = tmp_path_factory.mktemp("codec_drives")
    drives = {}
    for scenario, duration in CODEC_DRIVES:
        result = simulate(scenario, vehicle=2, seed=0, duration=duration)
        log = directory / f"{scenario}.log"
        write_log(log, result, profile)
        inputs = latch_log(read_frames(log), profile)
        drives[scenario] = CodecDrive(scenario, log, result.truth, inputs)
    return drives
