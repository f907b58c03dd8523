"""``slipd identify``: the car's parameters and sensor errors from an ordinary drive, with no
ground truth.

The logs are read through the codec like a replay (slipd.identify.data), with the profile's
``[calibration]`` left out, and each quantity is found from the segments that make it
identifiable, in an order where each step uses what the earlier ones found:

1. the IMU's offsets and mounting (slipd.identify.imu: standstills, straights, the
   cross-coupling a tilt causes while driving);
2. each wheel's relative rolling radius (slipd.identify.wheels: steady straights; absolute
   against GNSS speed);
3. steering-wheel offset, steering ratio and understeer gradient (slipd.identify.steering:
   the steady-state handling diagram);
4. roll stiffness from the roll gradient, where a roll rate exists (slipd.identify.roll);
5. axle cornering stiffnesses (slipd.identify.single_track: output-error fit of the linear
   single-track model); the yaw inertia is fitted with them and reported, not written (the
   fit is biased, see slipd.identify.single_track.YAW_INERTIA_NOT_WRITTEN).

Every value comes with its method, the data it used and a 95 % interval
(slipd.identify.results); a quantity the data cannot support is left as it was, with the
reason. :func:`slipd.identify.profile_text.write_profile` writes the profile copy.

    from slipd.identify import identify
    result = identify(["drive.log"], "default")
    result.outcome.findings["vehicle.steering_ratio"].value
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slipd.channels import Veh
from slipd.errors import ConfigError
from slipd.identify.data import Drive, Signals, raw_profile, read_drives, signals
from slipd.identify.results import Finding, Missing, Outcome
from slipd.profile import Calibration, Profile, load_profile

#: --only names -> the profile keys they write.
QUANTITIES: dict[str, tuple[str, ...]] = {
    "gyro_offset": ("calibration.gyro_offset",),
    "accel_offset": ("calibration.accel_offset",),
    "imu_mounting": ("calibration.imu_mounting_deg",),
    "wheel_radius": ("calibration.wheel_radius_scale",),
    "steer_offset": ("calibration.steer_offset_deg",),
    "steering_ratio": ("vehicle.steering_ratio",),
    "roll_stiffness": ("vehicle.roll_stiffness",),
    "cornering_stiffness": ("vehicle.tyre.cornering_stiffness_front",
                            "vehicle.tyre.cornering_stiffness_rear"),
    "yaw_inertia": ("vehicle.yaw_inertia",),
}


def parse_only(spec: str | None) -> set[str]:
    """The quantities of ``--only a,b`` (all without it)."""
    if not spec:
        return set(QUANTITIES)
    chosen = {part.strip() for part in spec.split(",") if part.strip()}
    unknown = sorted(chosen - set(QUANTITIES))
    if unknown or not chosen:
        raise ConfigError(f"--only {spec}: unknown quantity {unknown or spec!r}; expected "
                          f"names from {', '.join(QUANTITIES)}")
    return chosen


@dataclass
class Identification:
    """The result of one run: the profile it started from, what was asked for, what was
    found (``outcome``) and the drives' signals after every correction."""

    profile: Profile
    wanted: set[str]
    outcome: Outcome
    drives: list[Drive]
    corrected: list[Signals]
    calibration: Calibration
    vehicle: np.ndarray  # the profile's [vehicle] vector with the identified values

    def written(self) -> dict[str, Finding]:
        """The findings that go into the new profile (asked for and found)."""
        keys = {key for name in self.wanted for key in QUANTITIES[name]}
        return {k: f for k, f in self.outcome.findings.items() if k in keys}

    def left(self) -> dict[str, Missing | str]:
        """Asked-for keys that stay as they were, with the reason."""
        keys = [key for name in QUANTITIES if name in self.wanted for key in QUANTITIES[name]]
        return {k: self.outcome.missing.get(k, Missing(k, "not identified"))
                for k in keys if k not in self.outcome.findings}


def identify(logs: Iterable[str | Path], profile: str | Path | Profile = "default",
             only: set[str] | None = None, progress: bool = True,
             bus_map: dict[str, str] | None = None) -> Identification:
    """Identify the car in ``profile`` from ``logs`` (any format replay reads)."""
    base = profile if isinstance(profile, Profile) else load_profile(profile)
    raw = raw_profile(base)
    drives = read_drives([Path(p) for p in logs], raw, progress, bus_map)
    if not drives:
        raise ConfigError("slipd identify needs at least one log")
    return identify_drives(drives, base, only)


def _keep(wanted: set[str], name: str, found: dict, key: str, old):
    """The identified value when it was asked for and found, else the profile's."""
    return found[key] if name in wanted and key in found else old


def identify_drives(drives: list[Drive], base: Profile, only: set[str] | None = None
                    ) -> Identification:
    """:func:`identify` on drives already latched with the raw profile."""
    from slipd.identify.imu import identify_imu
    from slipd.identify.roll import identify_roll
    from slipd.identify.single_track import identify_cornering
    from slipd.identify.steering import identify_steering
    from slipd.identify.wheels import identify_wheels

    wanted = set(QUANTITIES) if only is None else set(only)
    raw = raw_profile(base)
    outcome = Outcome()
    old = base.calibration
    for drive in drives:
        if len(drive.t) == 0:
            outcome.messages.append(f"{drive.name}: no ticks (no input frame of the profile)")

    # 1. the IMU, on the raw signals
    first = [signals(d, raw, Calibration()) for d in drives]
    outcome.diagnostics["raw_signals"] = first
    imu = identify_imu(first, outcome, lambda c: [signals(d, raw, c) for d in drives])
    cal = Calibration(
        imu_mounting_deg=_keep(wanted, "imu_mounting", imu, "imu_mounting_deg",
                               old.imu_mounting_deg),
        accel_offset=_keep(wanted, "accel_offset", imu, "accel_offset", old.accel_offset),
        gyro_offset=_keep(wanted, "gyro_offset", imu, "gyro_offset", old.gyro_offset),
        steer_divisor=raw.calibration.steer_divisor)
    yaw_offset = np.radians(cal.gyro_offset[2])

    # 2. wheels
    wheels = identify_wheels(first, yaw_offset, outcome)
    cal = dataclasses.replace(cal, wheel_radius_scale=_keep(
        wanted, "wheel_radius", wheels, "wheel_radius_scale", old.wheel_radius_scale))

    # 3. steering, on IMU- and wheel-corrected signals
    sigs = [signals(d, raw, cal) for d in drives]
    steering = identify_steering(sigs, raw, outcome)
    vehicle = raw.vehicle.copy()
    ratio_old = float(raw.vehicle[Veh.STEER_RATIO])
    ratio = _keep(wanted, "steering_ratio", steering, "steering_ratio", ratio_old)
    vehicle[Veh.STEER_RATIO] = ratio
    divisor = ratio if raw.calibration.steer_divisor != 1.0 else 1.0
    cal = dataclasses.replace(cal, steer_divisor=divisor, steer_offset_deg=_keep(
        wanted, "steer_offset", steering, "steer_offset_deg", old.steer_offset_deg))
    working = dataclasses.replace(raw, vehicle=vehicle, calibration=cal)
    sigs = [signals(d, working, cal, steer_scale=ratio_old / ratio if divisor != 1.0 else 1.0)
            for d in drives]

    # 4. roll
    roll = identify_roll(sigs, working, 0.0, outcome)
    vehicle[Veh.ROLL_STIFFNESS] = _keep(wanted, "roll_stiffness", roll, "roll_stiffness",
                                        vehicle[Veh.ROLL_STIFFNESS])
    gradient = float(vehicle[Veh.MASS] * vehicle[Veh.H_ROLL_AXIS] / vehicle[Veh.ROLL_STIFFNESS])

    # 5. cornering stiffness and yaw inertia
    cornering = identify_cornering(sigs, working, gradient, 0.0, outcome,
                                   fit_inertia="yaw_inertia" in wanted)
    if "cornering_stiffness" in wanted:
        for key, index in (("cornering_stiffness_front", Veh.CORNERING_STIFFNESS_F),
                           ("cornering_stiffness_rear", Veh.CORNERING_STIFFNESS_R)):
            if key in cornering:
                vehicle[index] = cornering[key]
    return Identification(base, wanted, outcome, drives, sigs, cal, vehicle)


__all__ = ["QUANTITIES", "Identification", "identify", "identify_drives", "parse_only"]
