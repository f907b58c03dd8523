"""``slipd profile check``: what a real log can tell about a profile without ground truth.

Every check compares two things the car measures independently, so it needs no reference:

* signs: the lateral acceleration must follow yaw rate x speed (a_y = r v in any turn, Ay
  sign), and the yaw rate must follow the steering at low lateral acceleration
  (r = delta v / (l + K v^2), the single-track model's steady state: same sign, gain at most
  about one). Which of the two relations is broken tells which channel is flipped;
* units: the same two relations as gains (a km/h wheel speed read as m/s makes r v 3.6 x too
  large, a yaw rate in deg/s read as rad/s 57 x), the wheel speeds against each other and
  against the car's own speed signal;
* rates and timeouts: each message's rate against the profile's ``rate_hz`` and its longest
  silence against its ``timeout``; E2E pass rates; channels never valid, or stuck.

Each channel gets a verdict: ``ok``, ``FAIL`` with the fault, or ``not checked`` (the log has
no stretch of driving that tests it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from slipd.channels import VALID, WHEEL_SPEEDS, In, Veh
from slipd.codec import Codec
from slipd.profile import Profile
from slipd.replay.candump import Frames
from slipd.replay.engine import Inputs, frame_buses, latch_log_or_recording

#: A gain this far from its nominal value (factor) is a unit fault, not a car's spread.
UNIT_FACTOR = 1.6
MIN_SAMPLES = 100  # ticks of driving a relation needs (1 s)
MIN_SPEED = 3.0  # m/s
#: Nominal yaw-rate/steering gain against the kinematic one: the single-track steady state is
#: below 1 for an understeering car (K v^2 / l of 0.1-0.5 at city speeds); 0.8 is the middle.
STEER_GAIN_NOMINAL = 0.8
#: Channels that vary whenever the car drives (a torque or a fix flag may rightly stay put).
STUCK_CHECKED = (In.AX, In.AY, In.AZ, In.YAW_RATE, In.ROLL_RATE, In.PITCH_RATE, In.STEER,
                 *WHEEL_SPEEDS, In.SPEED_REF)


@dataclass
class Verdict:
    channel: str
    status: str = "not checked"  # ok | FAIL | not checked
    notes: list[str] = field(default_factory=list)

    def fail(self, why: str) -> None:
        self.status = "FAIL"
        self.notes.append(why)

    def ok(self, why: str) -> None:
        if self.status != "FAIL":
            self.status = "ok"
        self.notes.append(why)


@dataclass
class CheckReport:
    verdicts: dict[str, Verdict]
    messages: list[str]
    ticks: int

    @property
    def passed(self) -> bool:
        return all(v.status != "FAIL" for v in self.verdicts.values()) and not any(
            line.startswith("FAIL") for line in self.messages)

    def text(self) -> str:
        lines = [f"{self.ticks} ticks ({self.ticks / 100:.1f} s)", "messages:"]
        lines += [f"  {line}" for line in self.messages]
        lines.append("channels:")
        width = max(len(n) for n in self.verdicts)
        for name, verdict in self.verdicts.items():
            lines.append(f"  {name:{width}s}  {verdict.status:11s}  {'; '.join(verdict.notes)}")
        lines.append("verdict: " + ("pass" if self.passed else "FAIL"))
        return "\n".join(lines)


def _slope(x: np.ndarray, y: np.ndarray) -> float:
    """Least-squares gain of y = k x through the origin."""
    return float(np.dot(x, y) / np.dot(x, x))


def check_profile_on_log(frames: Frames, profile: Profile,
                         bus_map: dict[str, str] | None = None) -> CheckReport:
    inputs = latch_log_or_recording(frames, profile, bus_map)
    verdicts = {c.name.lower(): Verdict(c.name.lower()) for c in sorted(profile.channels)}
    messages = _message_checks(frames, profile, inputs, bus_map)
    U = inputs.U

    def valid(*channels: In) -> np.ndarray:
        mask = np.ones(len(U), dtype=bool)
        for channel in channels:
            mask &= U[:, VALID + channel] > 0.5 if channel in profile.channels else False
        return mask

    # presence and stuck signals
    for channel in profile.channels:
        verdict = verdicts[channel.name.lower()]
        share = float(valid(channel).mean()) if len(U) else 0.0
        if share == 0.0:
            verdict.fail("never valid in the log (missing, failed E2E or marked unavailable)")
        elif share < 0.9:
            verdict.notes.append(f"valid on {share:.0%} of ticks")
    wheels = [c for c in WHEEL_SPEEDS if c in profile.channels]
    speed = np.mean(U[:, wheels], axis=1) if wheels else np.zeros(len(U))
    moving = valid(*wheels) & (speed > MIN_SPEED)
    for channel in STUCK_CHECKED:
        if channel not in profile.channels:
            continue
        values = U[moving & valid(channel), channel]
        if len(values) >= MIN_SAMPLES and np.ptp(values) == 0.0:
            verdicts[channel.name.lower()].fail(
                f"stuck at {values[0]:.6g} (SI) over {len(values) / 100:.0f} s of driving")

    _wheel_checks(U, profile, verdicts, moving, speed, valid)
    _dynamics_checks(U, profile, verdicts, moving, speed, valid)
    return CheckReport(verdicts, messages, len(U))


def _wheel_checks(U, profile, verdicts, moving, speed, valid) -> None:
    wheels = [c for c in WHEEL_SPEEDS if c in profile.channels]
    if len(wheels) < 2 or moving.sum() < MIN_SAMPLES:
        return
    median = np.median(U[moving][:, wheels], axis=1)
    for channel in wheels:
        ratio = float(np.median(U[moving, channel] / np.maximum(median, 1e-3)))
        verdict = verdicts[channel.name.lower()]
        if not 1 / 1.15 < ratio < 1.15:
            verdict.fail(f"reads {ratio:.2f} x the other wheels (unit or scale)")
        else:
            verdict.ok(f"agrees with the other wheels ({ratio:.3f})")
    if In.SPEED_REF in profile.channels:
        both = moving & valid(In.SPEED_REF)
        if both.sum() >= MIN_SAMPLES:
            ratio = float(np.median(speed[both] / np.maximum(U[both, In.SPEED_REF], 1e-3)))
            if not 1 / 1.15 < ratio < 1.15:
                verdicts["speed_ref"].fail(f"the wheels read {ratio:.2f} x speed_ref "
                                           "(a unit error in one of them)")
            else:
                verdicts["speed_ref"].ok(f"agrees with the wheel speeds ({ratio:.3f})")


def _dynamics_checks(U, profile, verdicts, moving, speed, valid) -> None:
    """Signs and units from a_y = r v and r = delta v / l (low lateral acceleration)."""
    have = {c for c in (In.AY, In.YAW_RATE, In.STEER) if c in profile.channels}
    if have != {In.AY, In.YAW_RATE, In.STEER}:
        return
    wheelbase = profile.vehicle[Veh.LF] + profile.vehicle[Veh.LR]
    ay, r, delta = U[:, In.AY], U[:, In.YAW_RATE], U[:, In.STEER]
    # the masks use no speed threshold beyond "rolling": a speed in the wrong unit must not
    # hide the turns that reveal it
    base = valid(In.AY, In.YAW_RATE, In.STEER, *[c for c in WHEEL_SPEEDS
                                                 if c in profile.channels]) & (speed > 1.0)
    turning = base & (np.abs(ay) > 1.0) & (np.abs(r) > 0.05)
    gentle = base & (np.abs(ay) < 3.0) & (np.abs(r) > 0.02) & (np.abs(delta) > 0.005)
    names = {c: c.name.lower() for c in (In.AY, In.YAW_RATE, In.STEER)}
    if turning.sum() < MIN_SAMPLES or gentle.sum() < MIN_SAMPLES:
        for c in names.values():
            verdicts[c].notes.append("no turns long enough in the log to check sign and unit")
        return
    k1 = _slope(r[turning] * speed[turning], ay[turning])  # nominal 1
    k2 = _slope(delta[gentle] * speed[gentle] / wheelbase, r[gentle])  # nominal ~0.8
    details = f"a_y / (r v) = {k1:+.2f}, r / (delta v / l) = {k2:+.2f}"
    # signs: which relation breaks tells which channel is flipped
    if k1 < 0 and k2 < 0:
        verdicts["yaw_rate"].fail(f"sign flipped ({details})")
    elif k1 < 0:
        verdicts["ay"].fail(f"sign flipped: a_y opposes yaw rate x speed ({details})")
    elif k2 < 0:
        verdicts["steer"].fail(f"sign flipped: the car turns against the steering ({details})")
    # units: log-gains; a single channel's unit error moves them in its own pattern
    e1 = math.log(abs(k1)) if k1 else 0.0
    e2 = math.log(abs(k2) / STEER_GAIN_NOMINAL) if k2 else 0.0
    limit = math.log(UNIT_FACTOR)
    blamed = ""
    if abs(e1) > limit or abs(e2) > limit:
        factor1, factor2 = math.exp(e1), math.exp(e2)
        blamed = "steer"
        if abs(e1) > limit and abs(e2) > limit and e1 * e2 < 0:
            blamed = "yaw_rate"
            verdicts["yaw_rate"].fail(f"unit: reads {1 / factor1:.3g} x what a_y and the "
                                      f"steering imply ({details})")
        elif abs(e1) > limit and abs(e2) > limit:
            blamed = "the wheel speeds"
            for channel in WHEEL_SPEEDS:
                if channel in profile.channels:
                    verdicts[channel.name.lower()].fail(
                        f"unit: the speed reads {1 / factor1:.3g} x what a_y / r and the "
                        f"steering imply ({details})")
        elif abs(e1) > limit:
            blamed = "ay"
            verdicts["ay"].fail(f"unit: reads {factor1:.3g} x yaw rate x speed ({details})")
        else:
            verdicts["steer"].fail(f"unit or steering_ratio: the car yaws {factor2:.3g} x "
                                   f"what the steering implies ({details})")
    for channel in names.values():
        if verdicts[channel].status != "FAIL":
            verdicts[channel].ok(f"sign and unit consistent ({details})" if not blamed else
                                 f"sign consistent; the gains are explained by {blamed}")


def _message_checks(frames: Frames, profile: Profile, inputs: Inputs,
                    bus_map: dict[str, str] | None) -> list[str]:
    codec = Codec(profile)
    buses = frame_buses(frames, codec, bus_map)
    extended = (frames.flags & 1) != 0
    lines = []
    for name, mmap in profile.messages.items():
        plan = codec.inputs
        on = (buses == plan.buses.index(mmap.bus)) & (frames.frame_id == plan.frame_id(name)) \
            & (extended == plan.is_extended(name))
        t = frames.t[on]
        counts = inputs.errors[name]
        if len(t) < 2:
            lines.append(f"FAIL {name}: {len(t)} frame(s) in the log")
            continue
        rate = (len(t) - 1) / (t[-1] - t[0]) if t[-1] > t[0] else 0.0
        gap = float(np.max(np.diff(t)))
        total = sum(v for k, v in counts.items() if k != "not_available")
        rejected = {k: v for k, v in counts.items() if k not in ("accepted", "not_available")
                    and v}
        status = "ok"
        notes = [f"{rate:.1f} Hz (profile {mmap.rate_hz:g})"]
        if not 0.8 * mmap.rate_hz <= rate <= 1.25 * mmap.rate_hz:
            status = "FAIL"
            notes.append(f"rate differs from rate_hz = {mmap.rate_hz:g}")
        if gap > mmap.timeout:
            notes.append(f"longest silence {gap * 1e3:.0f} ms > timeout "
                         f"{mmap.timeout * 1e3:.0f} ms")
        if total:
            share = counts["accepted"] / total
            notes.append(f"{share:.1%} accepted")
            if share < 0.99:
                status = "FAIL"
                notes.append(f"rejected {rejected}")
        if counts.get("not_available"):
            notes.append(f"{counts['not_available']} frame(s) with a value marked unavailable")
        lines.append(f"{'FAIL ' if status == 'FAIL' else ''}{name}: {', '.join(notes)}")
    return lines
