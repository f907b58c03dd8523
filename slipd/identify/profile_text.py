"""The identified profile: a copy of the user's TOML with the identified values written in,
each commented with its source, the data used and its 95 % interval. The text is edited with
tomlkit, so the user's comments, order and layout stay as they were; values the data could
not support keep their old value and are listed with the reason in a comment above the
``[calibration]`` table."""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

from slipd.errors import ConfigError, DependencyError
from slipd.identify import Identification
from slipd.identify.results import Finding
from slipd.profile import PROFILE_DIR, load_profile

#: Significant digits a value is written with, by profile key (the rest: 5).
DIGITS = {
    "calibration.wheel_radius_scale": 5,
    "vehicle.steering_ratio": 4,
    "vehicle.roll_stiffness": 4,
    "vehicle.yaw_inertia": 4,
    "vehicle.tyre.cornering_stiffness_front": 4,
    "vehicle.tyre.cornering_stiffness_rear": 4,
}
DECIMALS = {  # fixed decimals instead, for offsets near zero
    "calibration.gyro_offset": 4,
    "calibration.accel_offset": 4,
    "calibration.imu_mounting_deg": 3,
    "calibration.steer_offset_deg": 3,
}
UNITS = {
    "calibration.gyro_offset": "deg/s",
    "calibration.accel_offset": "m/s^2",
    "calibration.imu_mounting_deg": "deg",
    "calibration.steer_offset_deg": "deg",
    "calibration.wheel_radius_scale": "",
    "vehicle.steering_ratio": "",
    "vehicle.roll_stiffness": "Nm/rad",
    "vehicle.yaw_inertia": "kg m^2",
    "vehicle.tyre.cornering_stiffness_front": "N/rad",
    "vehicle.tyre.cornering_stiffness_rear": "N/rad",
}


def rounded(key: str, value: float) -> float:
    """``value`` as written into the profile."""
    if not math.isfinite(value):
        return value
    if key in DECIMALS:
        return round(value, DECIMALS[key]) + 0.0
    digits = DIGITS.get(key, 5)
    return float(f"{value:.{digits}g}")


def _number(key: str, value: float) -> str:
    return f"{rounded(key, value):g}"


def interval_text(key: str, finding: Finding) -> str:
    parts = []
    for lo, hi in finding.intervals():
        if math.isfinite(lo) and math.isfinite(hi):
            parts.append(f"[{_number(key, lo)}, {_number(key, hi)}]")
        else:
            parts.append("[n/a]")
    return parts[0] if len(parts) == 1 else ", ".join(parts)


def comment_of(key: str, finding: Finding, old) -> str:
    old_text = ("[" + ", ".join(_number(key, v) for v in old) + "]" if isinstance(old, list | tuple)
                else _number(key, float(old)) if old is not None else "unset")
    return (f"slipd identify: {finding.method}; {finding.data_text()}; 95 % CI "
            f"{interval_text(key, finding)}; was {old_text}"
            + (f"; {finding.note}" if finding.note else ""))


def _table(doc, path: list[str], create: bool):
    import tomlkit

    table = doc
    for name in path:
        if name not in table:
            if not create:
                raise ConfigError(f"the profile has no [{'.'.join(path)}] table")
            table.add(name, tomlkit.table())
        table = table[name]
    return table


def _value(key: str, finding: Finding):
    import tomlkit

    if isinstance(finding.value, tuple):
        array = tomlkit.array()
        for v in finding.value:
            array.append(rounded(key, float(v)))
        return array
    return tomlkit.item(rounded(key, float(finding.value)))


def profile_text(result: Identification, out: Path | None = None) -> str:
    """The new profile's text (``out``: where it will be written, to keep its DBC found).

    Each identified value replaces the old one in place (its inline comment kept) and gets a
    comment line above it: slipd identify, the method, the data, the 95 % interval and the old
    value. A missing ``[calibration]`` table is added at the end."""
    try:
        import tomlkit
    except ImportError as exc:
        raise DependencyError("slipd identify needs tomlkit: pip install 'slipd[identify]'"
                              ) from exc
    source = result.profile.path
    doc = tomlkit.parse(source.read_text(encoding="utf-8"))
    written = result.written()
    if any(k.startswith("calibration.") for k in written) and "calibration" not in doc:
        table = tomlkit.table()
        table.add(tomlkit.comment("The car's sensor errors, corrected where the codec samples"))
        table.add(tomlkit.comment("the inputs (slipd/codec/calibration.py)."))
        doc.add(tomlkit.nl())
        doc.add("calibration", table)
    notes: dict[tuple[str, str], str] = {}
    for key, finding in written.items():
        *path, name = key.split(".")
        table = _table(doc, path, create=True)
        old = table.get(name)
        item = _value(key, finding)
        trivia = getattr(old, "trivia", None)
        if trivia is not None:  # keep the user's spacing and inline comment
            item.trivia.comment_ws = trivia.comment_ws
            item.trivia.comment = trivia.comment
        table[name] = item
        old_value = old.unwrap() if hasattr(old, "unwrap") else old
        notes[(".".join(path), name)] = comment_of(key, finding, old_value)
    lines = _annotate(tomlkit.dumps(doc).splitlines(), notes)
    header = [f"# slipd identify {time.strftime('%Y-%m-%d')} on "
              f"{', '.join(d.name for d in result.drives)}, from profile {source.name}"]
    for key, missing in result.left().items():
        reason = missing.reason if hasattr(missing, "reason") else str(missing)
        header.extend(_wrap(f"not identified, left as it was: {key}: {reason}"))
    return _keep_dbc("\n".join(header + lines) + "\n", source, out)


def _wrap(text: str, indent: str = "") -> list[str]:
    import textwrap

    return [indent + line for line in textwrap.wrap(
        text, width=99 - len(indent), initial_indent="# ", subsequent_indent="#   ")]


def _annotate(lines: list[str], notes: dict[tuple[str, str], str]) -> list[str]:
    """Insert each note as comment lines above its key (found by table header and name)."""
    import re

    header = re.compile(r"^\s*\[([^\[\]]+)\]\s*(#.*)?$")
    key_line = re.compile(r"^(\s*)([A-Za-z0-9_\-]+)\s*=")
    table = ""
    out = []
    for line in lines:
        match = header.match(line)
        if match:
            table = match.group(1).strip()
        else:
            found = key_line.match(line)
            if found and (table, found.group(2)) in notes:
                out.extend(_wrap(notes[(table, found.group(2))], found.group(1)))
        out.append(line)
    return out


def _keep_dbc(text: str, source: Path, out: Path | None) -> str:
    """Point the copy's ``dbc`` at the same file when it is written elsewhere."""
    import tomlkit

    if out is None:
        return text
    doc = tomlkit.parse(text)
    name = str(doc["profile"]["dbc"])
    original = (source.parent / name).resolve()
    target_dir = out.resolve().parent
    if (target_dir / name).resolve() == original or not original.exists():
        return text  # the same place, or a shipped DBC found by name
    if (PROFILE_DIR / name).is_file() and original == (PROFILE_DIR / name).resolve():
        return text
    doc["profile"]["dbc"] = os.path.relpath(original, target_dir)
    return tomlkit.dumps(doc)


def write_profile(result: Identification, out: Path) -> str:
    """Write the identified profile to ``out`` and check that it loads; returns its text."""
    text = profile_text(result, out)
    try:
        out.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"--out {out}: cannot write: {exc.strerror}") from exc
    load_profile(out)  # the copy must be a profile slipd loads
    return text
