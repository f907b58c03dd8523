"""Model-mismatch cases: the estimator's profile perturbed against the car (or plant) it runs on.

Real profiles are wrong: the mass changes with load and fuel, the yaw inertia is a formula,
cornering stiffness is a guess from the tyre's data sheet, the road friction is unknown, the
roll stiffness and CoG height are rarely measured, the IMU sits a few centimetres from where
the drawing says and the steering ratio is nominal. Each case changes one of these in the
estimator's copy of the profile (the log, i.e. the plant, is unchanged) so ``slipd eval
--mismatch`` measures how gracefully a method degrades (DESIGN.md, "Profiles are wrong in real
life"). Sizes: the issue's list (issue 15, item 3), which spans what a careful user's
spec-sheet profile gets wrong.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from slipd.errors import ConfigError


@dataclass(frozen=True)
class Change:
    """One profile value changed: ``key`` in [vehicle] (``tyre.KEY`` in [vehicle.tyre]),
    multiplied by ``scale`` and then ``offset`` added (per element for ``imu_position``)."""

    key: str
    scale: float = 1.0
    offset: tuple[float, ...] | float = 0.0

    def apply(self, vehicle: dict) -> None:
        table, key = vehicle, self.key
        if key.startswith("tyre."):
            table, key = vehicle.get("tyre", {}), key[len("tyre."):]
        if key not in table:
            raise ConfigError(f"mismatch: the profile has no [vehicle] {self.key} to perturb")
        value = table[key]
        if isinstance(value, list):
            offsets = self.offset if isinstance(self.offset, tuple) else (self.offset,) * 3
            table[key] = [float(v) * self.scale + o for v, o in zip(value, offsets, strict=True)]
        else:
            table[key] = float(value) * self.scale + float(self.offset)


@dataclass(frozen=True)
class MismatchCase:
    name: str
    description: str
    changes: tuple[Change, ...]

    def edit(self) -> Callable[[dict], None]:
        """The ``slipd.profile.load_profile(edit=...)`` function of this case."""

        def apply(doc: dict) -> None:
            vehicle = doc.get("vehicle")
            if not isinstance(vehicle, dict):
                raise ConfigError("mismatch: the profile has no [vehicle] table")
            for change in self.changes:
                change.apply(vehicle)

        return apply


def _scale(name: str, description: str, *keys: str, by: float) -> MismatchCase:
    return MismatchCase(name, description, tuple(Change(k, scale=by) for k in keys))


CF, CR = "tyre.cornering_stiffness_front", "tyre.cornering_stiffness_rear"

#: name -> case, in the order the tables print them.
CASES: dict[str, MismatchCase] = {c.name: c for c in (
    _scale("mass+15%", "payload and passengers the profile does not know", "mass", by=1.15),
    _scale("mass-10%", "profile written for a loaded car, driven empty", "mass", by=0.90),
    _scale("yaw_inertia+20%", "yaw inertia from a formula, 20 % low", "yaw_inertia", by=1.20),
    _scale("yaw_inertia-20%", "yaw inertia from a formula, 20 % high", "yaw_inertia", by=0.80),
    _scale("cf-30%", "front cornering stiffness 30 % below the car's", CF, by=0.70),
    _scale("cf+30%", "front cornering stiffness 30 % above the car's", CF, by=1.30),
    _scale("cr-30%", "rear cornering stiffness 30 % below the car's", CR, by=0.70),
    _scale("cr+30%", "rear cornering stiffness 30 % above the car's", CR, by=1.30),
    _scale("c-30%", "both axles' cornering stiffness 30 % low (worn or cold tyres)", CF, CR,
           by=0.70),
    _scale("c+30%", "both axles' cornering stiffness 30 % high", CF, CR, by=1.30),
    _scale("mu-20%", "tyre data's peak friction 20 % low", "tyre.peak_friction", by=0.80),
    _scale("roll_stiffness*0.5", "roll stiffness half the car's", "roll_stiffness", by=0.5),
    _scale("roll_stiffness*2", "roll stiffness twice the car's", "roll_stiffness", by=2.0),
    _scale("cog_height+20%", "CoG 20 % higher than the car's", "cog_height", by=1.20),
    _scale("cog_height-20%", "CoG 20 % lower than the car's", "cog_height", by=0.80),
    MismatchCase("imu_x+10cm", "IMU 10 cm further forward than the profile says",
                 (Change("imu_position", offset=(0.10, 0.0, 0.0)),)),
    MismatchCase("imu_y+10cm", "IMU 10 cm further left than the profile says",
                 (Change("imu_position", offset=(0.0, 0.10, 0.0)),)),
    _scale("steering_ratio+5%", "steering ratio 5 % above the car's", "steering_ratio",
           by=1.05),
)}


def parse_cases(spec: str) -> list[MismatchCase]:
    """``all`` or comma-separated case names -> the cases."""
    if spec.strip() == "all":
        return list(CASES.values())
    names = [s.strip() for s in spec.split(",") if s.strip()]
    unknown = [n for n in names if n not in CASES]
    if unknown or not names:
        raise ConfigError(f"--mismatch {spec!r}: unknown case(s) {unknown}; expected 'all' or "
                          f"some of: {', '.join(CASES)}")
    return [CASES[n] for n in names]
