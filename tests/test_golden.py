"""Golden outputs: every registered method on the codec drives (conftest.CODEC_DRIVES), hashed.

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
inputs of each drive are hashed too, so a failure says whether the simulator or codec moved
(``inputs``) or an estimator did. The values hold for this project's toolchain (numba with
NUMBA_CPU_NAME=generic, the pinned simulator); another CPU or libm may round a
transcendental function differently, and the simulator's drives then move by ~1e-4 deg
(regenerated on 2026-12-02 for the 2-vCPU Xeon with AVX-512 machines: every fingerprint
within 1e-4 deg of the earlier machines' but snow_drift's, within 0.05 deg of its mean).
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


def method_outputs(drive, profile) -> dict[str, np.ndarray]:
    from slipd.estimators.registry import available
    from slipd.pipeline import Pipeline

    return {name: Pipeline(name, profile).run(drive.inputs.U, drive.inputs.steps)
            for name in available()}


def current_values(codec_drives, profile) -> tuple[dict, dict]:
    values, outputs = {}, {}
    for scenario, drive in codec_drives.items():
        outs = method_outputs(drive, profile)
        outputs[scenario] = outs
        values[scenario] = {
            "inputs": canonical_hash(drive.inputs.U),
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


def test_outputs_match_the_golden_values(codec_drives, profile):
    values, outputs = current_values(codec_drives, profile)
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
            problems.append(f"{scenario}: the latched inputs changed (simulator or codec), so "
                            "every method's outputs may; this test cannot judge the estimators")
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
