"""Golden outputs: every registered method on stored bus logs of the codec drives
(conftest.CODEC_DRIVES), hashed.

This pins the estimators' behaviour bit for bit, so that moving code (a refactoring) can be
shown to change nothing. A change meant to alter outputs regenerates the values once::

    SLIPD_GOLDEN_UPDATE=1 .venv/bin/pytest tests/test_golden.py

and its commit message says which methods changed and why. To see *how much* something
changed, dump the outputs before and compare after::

    SLIPD_GOLDEN_DUMP=/tmp/before .venv/bin/pytest tests/test_golden.py      # on the old code
    SLIPD_GOLDEN_COMPARE=/tmp/before .venv/bin/pytest tests/test_golden.py   # on the new code

What is hashed: the float64 bits of each method's supervised outputs (``Pipeline.run``, as
the batch engine runs it: every Out column incl. status), with every NaN mapped to one NaN
and -0.0 to 0.0 (a NaN's payload and a zero's sign change no frame on the bus). The latched
inputs of each drive are hashed too, so a failure says whether the codec moved (``inputs``)
or an estimator did.

The drives are bus logs in tests/data/golden_drives (the codec drives simulated once, seed 0,
written by ``slipd.sim.writer.write_log``, gzipped), not simulated here: the simulator's
transcendental functions round differently on different CPUs (numpy's SIMD paths, libm), so a
drive simulated on another machine kind moved every fingerprint by ~1e-4 deg and the golden
values held on one kind of machine only (regenerated for each new kind twice). The codec and
the kernels (numba with NUMBA_CPU_NAME=generic) give the same bits from the same log. Remake
the logs only when the bus layout changes (``python tests/test_golden.py --write-drives``),
then regenerate the values.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest

from slipd.channels import ST_VALID, Out

GOLDEN = Path(__file__).resolve().parent / "data" / "golden_outputs.json"
#: the stored drives: DRIVES / f"{scenario}.log.gz" for each of conftest.CODEC_DRIVES
DRIVES = GOLDEN.parent / "golden_drives"


def write_drives() -> None:
    """Simulate conftest.CODEC_DRIVES (seed 0, the default profile) into DRIVES."""
    import gzip

    from conftest import CODEC_DRIVES

    from slipd.profile import load_profile
    from slipd.sim import simulate
    from slipd.sim.writer import write_log

    DRIVES.mkdir(parents=True, exist_ok=True)
    profile = load_profile("default")
    for scenario, duration in CODEC_DRIVES:
        log = DRIVES / f"{scenario}.log"
        write_log(log, simulate(scenario, vehicle=2, seed=0, duration=duration), profile)
        with gzip.GzipFile(DRIVES / f"{scenario}.log.gz", "wb", 9, mtime=0) as packed:
            packed.write(log.read_bytes())
        log.unlink()


@pytest.fixture(scope="module")
def golden_inputs(profile) -> dict:
    """{scenario: latched inputs} of the stored drives, through the codec."""
    from conftest import CODEC_DRIVES

    from slipd.replay.engine import latch_log
    from slipd.replay.readers import read_frames

    return {scenario: latch_log(read_frames(DRIVES / f"{scenario}.log.gz"), profile)
            for scenario, _ in CODEC_DRIVES}


def canonical_hash(array: np.ndarray) -> str:
    values = np.array(array, dtype=np.float64, copy=True)
    values[np.isnan(values)] = np.nan
    values[values == 0.0] = 0.0
    return hashlib.sha256(np.ascontiguousarray(values).tobytes()).hexdigest()[:20]


def fingerprint(out: np.ndarray) -> dict:
    """A few readable figures beside the hash, for the failure message."""
    beta = np.degrees(out[:, Out.BETA])
    finite = np.isfinite(beta)
    valid = (out[:, Out.STATUS].astype(np.int64) & ST_VALID) != 0
    return {
        "beta_mean_deg": round(float(beta[finite].mean()), 6) if finite.any() else None,
        "beta_absmax_deg": round(float(np.abs(beta[finite]).max()), 6) if finite.any() else None,
        "valid_ticks": int(valid.sum()),
    }


def method_outputs(inputs, profile) -> dict[str, np.ndarray]:
    from slipd.estimators.registry import available
    from slipd.pipeline import Pipeline

    return {name: Pipeline(name, profile).run(inputs.U, inputs.steps) for name in available()}


def current_values(golden_inputs, profile) -> tuple[dict, dict]:
    values, outputs = {}, {}
    for scenario, inputs in golden_inputs.items():
        outs = method_outputs(inputs, profile)
        outputs[scenario] = outs
        values[scenario] = {
            "inputs": canonical_hash(inputs.U),
            "methods": {name: {"hash": canonical_hash(out), **fingerprint(out)}
                        for name, out in outs.items()},
        }
    return values, outputs


def _dump(directory: Path, outputs: dict) -> None:
    directory.mkdir(parents=True, exist_ok=True)
    for scenario, outs in outputs.items():
        np.savez(directory / f"{scenario}.npz", **outs)


def _compare(directory: Path, outputs: dict) -> list[str]:
    lines = []
    for scenario, outs in outputs.items():
        path = directory / f"{scenario}.npz"
        if not path.exists():
            continue
        before = np.load(path)
        for name, out in outs.items():
            if name not in before:
                lines.append(f"{scenario} {name}: new")
                continue
            old = before[name]
            same = (old == out) | (np.isnan(old) & np.isnan(out))
            if same.all():
                continue
            diff = np.abs(np.where(same, 0.0, out - old))
            columns = [Out(c).name for c in range(out.shape[1]) if not same[:, c].all()]
            first = int(np.flatnonzero(~same.all(axis=1))[0])
            lines.append(f"{scenario} {name}: {int((~same).any(axis=1).sum())} ticks differ "
                         f"from tick {first} in {columns}; max |diff| "
                         f"{[f'{v:.2g}' for v in np.nanmax(diff, axis=0)]}")
    return lines


def test_outputs_match_the_golden_values(golden_inputs, profile):
    values, outputs = current_values(golden_inputs, profile)
    if os.environ.get("SLIPD_GOLDEN_DUMP"):
        _dump(Path(os.environ["SLIPD_GOLDEN_DUMP"]), outputs)
    if os.environ.get("SLIPD_GOLDEN_COMPARE"):
        print("\n".join(_compare(Path(os.environ["SLIPD_GOLDEN_COMPARE"]), outputs)
                        or ["no output differs from the dump"]))
    if os.environ.get("SLIPD_GOLDEN_UPDATE"):
        GOLDEN.parent.mkdir(parents=True, exist_ok=True)
        GOLDEN.write_text(json.dumps(values, indent=1, sort_keys=True) + "\n")
        pytest.skip(f"golden values written to {GOLDEN}")
    golden = json.loads(GOLDEN.read_text())
    assert sorted(values) == sorted(golden), "the codec drives changed; regenerate"
    problems = []
    for scenario, now in values.items():
        recorded = golden[scenario]
        if now["inputs"] != recorded["inputs"]:
            problems.append(f"{scenario}: the latched inputs of the stored drive changed (the "
                            "codec), so every method's outputs may; this test cannot judge the "
                            "estimators")
            continue
        for name in sorted(set(now["methods"]) | set(recorded["methods"])):
            if name not in recorded["methods"]:
                problems.append(f"{scenario} {name}: no golden value (a new method: regenerate)")
            elif name not in now["methods"]:
                problems.append(f"{scenario} {name}: golden value of a method no longer "
                                "registered")
            elif now["methods"][name]["hash"] != recorded["methods"][name]["hash"]:
                problems.append(f"{scenario} {name}: outputs changed, now "
                                f"{now['methods'][name]}, golden {recorded['methods'][name]}")
    assert not problems, "\n".join(problems)


if __name__ == "__main__":
    import sys

    if sys.argv[1:] != ["--write-drives"]:
        sys.exit("usage: python tests/test_golden.py --write-drives")
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    write_drives()
