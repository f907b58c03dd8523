"""``slipd profile scaffold DBC``: a first profile proposed from a DBC's signal names, units
and comments, with every guess marked ``# REVIEW`` for the engineer to confirm.

Signals are scored per channel by name patterns (English, German as VW writes it, the common
abbreviations), by their DBC unit's dimension and by their comments; a channel takes the best
signal whose unit fits. For each chosen signal the scaffold also proposes what production
buses carry beside it: a sign bit (``VZ``, ``sign``) of a magnitude signal, a qualifier
(``QBit``, ``Qf``, ``SigSta``, ``_STAT``, ``valid``) and the message's checksum and counter
with the E2E scheme the DBC's platform uses. Vehicle data are placeholders to measure. The
file loads as it is written when the DBC carries every core channel, so `slipd profile check`
can run on a first log at once.
"""

from __future__ import annotations

import difflib
import re
from dataclasses import dataclass
from pathlib import Path

from slipd.channels import CORE_CHANNELS, In
from slipd.codec.plan import load_dbc
from slipd.profile import CHANNEL_DIMENSION, UNIT_TABLE, dbc_unit

_W = r"(?:^|[_\s.]|(?<=[a-z])(?=[A-Z]))"  # a word boundary in snake, camel or dotted names
#: channel -> name patterns (case-insensitive), the best first
PATTERNS: dict[In, tuple[str, ...]] = {
    In.YAW_RATE: (r"yaw.?r(a)?te?", r"gierrate", r"yaw"),
    In.AY: (r"lat(eral)?.?acc", r"querbeschl", r"acc(el)?.?y\b", r"\bay\b"),
    In.AX: (r"long(itudinal)?.?acc", r"laengsbeschl", r"längsbeschl", r"acc(el)?.?x\b",
            r"\bax\b"),
    In.AZ: (r"vert(ical)?.?acc", r"acc(el)?.?z\b"),
    In.ROLL_RATE: (r"roll.?r(a)?te?", r"wankrate"),
    In.PITCH_RATE: (r"pitch.?r(a)?te?", r"nickrate"),
    In.STEER: (r"steer(ing)?.?(wheel)?.?ang(le)?", r"lenkradwinkel", r"sas.?angle",
               r"str.?ang"),
    In.STEER_RATE: (r"steer(ing)?.?(wheel)?.?(angle)?.?(rate|speed)", r"lenkradw.*geschw",
                    r"sas.?speed"),
    In.WHEEL_SPEED_FL: (r"(wheel|whl|rad).*(fl|lf|vl)\b", r"\b(fl|vl)\b.*(wheel|speed|rad)",
                        r"spd.?fl", r"wheelspeedfrl", r"vl.?radgeschw"),
    In.WHEEL_SPEED_FR: (r"(wheel|whl|rad).*(fr|rf|vr)\b", r"\b(fr|vr)\b.*(wheel|speed|rad)",
                        r"spd.?fr", r"wheelspeedfrr", r"vr.?radgeschw"),
    In.WHEEL_SPEED_RL: (r"(wheel|whl|rad).*(rl|lr|hl)\b", r"\b(rl|hl)\b.*(wheel|speed|rad)",
                        r"spd.?rl", r"wheelspeedrel", r"hl.?radgeschw"),
    In.WHEEL_SPEED_RR: (r"(wheel|whl|rad).*(rr|hr)\b", r"\b(rr|hr)\b.*(wheel|speed|rad)",
                        r"spd.?rr", r"wheelspeedrer", r"hr.?radgeschw"),
    In.SPEED_REF: (r"veh(icle)?.?speed", r"v.?signal", r"^speed$", r"car.?speed"),
}
SIGN_WORDS = re.compile(r"(^|_)(vz|sign|sgn)(_|$)|vorzeichen", re.IGNORECASE)
QUALIFIER_WORDS = re.compile(r"qbit|(^|_)qf$|qf(_|$)|sigsta|_stat$|valid|gueltig|quality",
                             re.IGNORECASE)
CHECKSUM_WORDS = re.compile(r"checksum|chksum|crc|chks", re.IGNORECASE)
COUNTER_WORDS = re.compile(r"counter|alive|(^|_)cnt|alvcnt|msgcount", re.IGNORECASE)
#: DBC file name prefix -> the platform's E2E scheme (opendbc's naming)
PLATFORM_E2E = (("vw_", "autosar_crc8"), ("hyundai_canfd", "hkg_canfd_crc16"),
                ("honda", "honda_checksum"), ("acura", "honda_checksum"),
                ("toyota", "toyota_checksum"), ("lexus", "toyota_checksum"),
                ("subaru_global", "subaru_checksum"), ("tesla_model3_party", "tesla_checksum"))
DEFAULT_UNIT = {"acceleration": "m/s^2", "angular rate": "deg/s", "angle": "deg",
                "speed": "km/h"}


@dataclass
class Guess:
    channel: In
    message: str
    signal: str
    unit: str | None
    why: str
    sign_signal: str | None = None
    valid_signal: str | None = None


def _closest(stem: str, names: list[str], words: re.Pattern) -> str | None:
    """The helper signal whose name, without its sign/qualifier word, is most like ``stem``
    (at least 40 % alike), e.g. LWI_VZ_Lenkradwinkel for LWI_Lenkradwinkel."""
    scored = []
    for name in names:
        rest = _stem(words.sub("_", name)).strip("_").lower()
        ratio = difflib.SequenceMatcher(None, stem, rest).ratio()
        scored.append((ratio, name))
    ratio, name = max(scored, default=(0.0, None))
    return name if ratio >= 0.4 else None


def _stem(name: str) -> str:
    return re.sub(r"(?i)(^[a-z]+_)|(val(ue)?$)|(_\d+$)", "", name)


def _score(channel: In, signal, message) -> tuple[int, str] | None:
    name = signal.name
    text = f"{name} {signal.comment or ''}"
    rank = next((k for k, pattern in enumerate(PATTERNS[channel])
                 if re.search(pattern, text, re.IGNORECASE)), None)
    if rank is None:
        return None
    if signal.length < 6 or SIGN_WORDS.search(name) or QUALIFIER_WORDS.search(name) or \
            CHECKSUM_WORDS.search(name) or COUNTER_WORDS.search(name):
        return None
    unit = dbc_unit(signal.unit)
    dimension = CHANNEL_DIMENSION[channel]
    score = 100 - 10 * rank
    if unit is not None:
        if UNIT_TABLE[unit][1] != dimension:
            return None
        score += 50  # a DBC unit of the channel's dimension outweighs a looser name
    score -= 5 * bool(re.search(r"raw|soll|target|req|request|cmd|des", name, re.IGNORECASE))
    return score, f"name matches {PATTERNS[channel][rank]!r}" + (
        f", DBC unit {signal.unit!r}" if unit else ", no DBC unit")


def propose(dbc_path: Path) -> tuple[list[Guess], dict[str, dict]]:
    """Channel guesses and, per message used, its E2E proposal."""
    db = load_dbc(dbc_path)
    best: dict[In, tuple[int, Guess]] = {}
    for message in db.messages:
        if message.is_multiplexed() or message.length > 64:
            continue
        for signal in message.signals:
            for channel in PATTERNS:
                scored = _score(channel, signal, message)
                if scored is None:
                    continue
                score, why = scored
                if channel in best and best[channel][0] >= score:
                    continue
                unit = dbc_unit(signal.unit)
                best[channel] = (score, Guess(channel, message.name, signal.name, unit, why))
    used = {g.message for _, g in best.values()}
    for _, guess in best.values():
        message = db.get_message_by_name(guess.message)
        stem = _stem(guess.signal).lower()
        signs = [s.name for s in message.signals if s.length == 1 and s.name != guess.signal
                 and SIGN_WORDS.search(s.name)]
        qualifiers = [s.name for s in message.signals if s.length <= 6
                      and s.name != guess.signal and QUALIFIER_WORDS.search(s.name)]
        guess.sign_signal = _closest(stem, signs, SIGN_WORDS)
        guess.valid_signal = _closest(stem, qualifiers, QUALIFIER_WORDS)
    e2e = {}
    scheme = next((s for prefix, s in PLATFORM_E2E if dbc_path.name.startswith(prefix)), None)
    for name in sorted(used):
        message = db.get_message_by_name(name)
        crc = next((s.name for s in message.signals if CHECKSUM_WORDS.search(s.name)), None)
        counter = next((s.name for s in message.signals if COUNTER_WORDS.search(s.name)), None)
        cycle = getattr(message, "cycle_time", None)
        e2e[name] = {"crc": crc, "counter": counter, "scheme": scheme if crc else None,
                     "rate_hz": 1000.0 / cycle if cycle else None}
    return [g for _, g in sorted(best.values(), key=lambda x: int(x[1].channel))], e2e


def scaffold_text(dbc_path: Path, profile_path: Path, name: str) -> str:
    guesses, e2e = propose(dbc_path)
    try:
        dbc_ref = Path(dbc_path).resolve().relative_to(profile_path.resolve().parent)
    except ValueError:
        dbc_ref = Path(dbc_path).resolve()
    found = {g.channel for g in guesses}
    missing = [c.name.lower() for c in CORE_CHANNELS if c not in found]
    out = [
        f"# slipd vehicle profile proposed by `slipd profile scaffold {Path(dbc_path).name}`.",
        "# Every line marked REVIEW is a guess from signal names, units and comments:",
        "# confirm it against the car's documentation, then drive and run",
        f"#   slipd profile check LOG --profile {profile_path.name}",
        "# which checks signs, units, rates and E2E on the log.",
    ]
    if missing:
        out.append(f"# NOT FOUND in the DBC (the profile does not load until they are mapped): "
                   f"{missing}")
    out += ["", "[profile]", f'name = "{name}"',
            f'description = "REVIEW: proposed from {Path(dbc_path).name}"',
            f'dbc = "{dbc_ref.as_posix()}"', "",
            "[vehicle]  # REVIEW: every value is a placeholder for a C-segment car; measure",
            "mass = 1500.0", "yaw_inertia = 2500.0", "roll_inertia = 500.0",
            "cog_to_front_axle = 1.2", "cog_to_rear_axle = 1.5", "track_front = 1.55",
            "track_rear = 1.55", "cog_height = 0.55", "roll_axis_height = 0.45",
            "wheel_radius = 0.32", "steering_ratio = 15.5", "imu_position = [0.0, 0.0, 0.0]",
            "roll_stiffness = 60000.0", "roll_damping = 4000.0", "wheel_inertia = 1.2", "",
            "[vehicle.tyre]  # REVIEW: placeholders",
            "cornering_stiffness_front = 120000.0", "cornering_stiffness_rear = 120000.0",
            "longitudinal_stiffness = 60000.0", "peak_friction = 1.0", "pacejka_b = 13.0",
            "pacejka_c = 1.35", "pacejka_e = 0.0", ""]
    for message, info in e2e.items():
        out.append(f"[messages.{message}]")
        if info["scheme"]:
            out.append(f'e2e = "{info["scheme"]}"  # REVIEW: the scheme of the DBC\'s platform')
            out.append(f'crc_signal = "{info["crc"]}"')
            if info["counter"]:
                out.append(f'counter_signal = "{info["counter"]}"')
            if info["scheme"] == "autosar_crc8":
                out.append("data_ids = [" + ", ".join(["0x00"] * 16) + "]  # REVIEW: the "
                           "message's 16 data IDs (VW: opendbc VOLKSWAGEN_MQB_MEB_CONSTANTS)")
        else:
            note = (f"  # REVIEW: {info['crc']} looks like a checksum of an unknown scheme"
                    if info["crc"] else "  # no checksum signal in the DBC")
            out.append(f'e2e = "none"{note}')
            if info["counter"]:
                out.append(f'counter_signal = "{info["counter"]}"  # REVIEW')
        rate = info["rate_hz"]
        out.append(f"rate_hz = {rate:.1f}  # from the DBC's cycle time" if rate else
                   "rate_hz = 50.0  # REVIEW: the message's rate on the bus")
        out.append("")
    out.append("[channels]")
    for guess in guesses:
        dimension = CHANNEL_DIMENSION[guess.channel]
        unit = guess.unit or DEFAULT_UNIT.get(dimension)
        fields = [f'message = "{guess.message}"', f'signal = "{guess.signal}"']
        if unit:
            fields.append(f'unit = "{unit}"')
        if guess.sign_signal:
            fields.append(f'sign_signal = "{guess.sign_signal}"')
        if guess.valid_signal:
            fields.append(f'valid_signal = "{guess.valid_signal}", valid_values = [0]')
        if guess.channel == In.STEER or guess.channel == In.STEER_RATE:
            fields.append('divide_by = "steering_ratio"')
        notes = [guess.why]
        if not guess.unit:
            notes.append(f"unit {unit!r} assumed")
        if guess.sign_signal:
            notes.append("sign bit assumed 1 = negative")
        if guess.valid_signal:
            notes.append("qualifier assumed 0 = valid")
        notes.append("sign against ISO 8855 (left positive) unverified")
        out.append(f"{guess.channel.name.lower()} = {{ {', '.join(fields)} }}")
        out.insert(len(out) - 1, f"# REVIEW {guess.channel.name.lower()}: {'; '.join(notes)}")
    return "\n".join(out) + "\n"
