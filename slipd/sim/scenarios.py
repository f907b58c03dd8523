"""The scenario suite: each one mirrors a test of a seed paper (the docstring says which).

A scenario builds a :class:`Plan`: one or more legs (road + driver + duration; a leg may end in
a standstill of ``dwell`` s), an optional payload and sensor-model overrides. Courses and
manoeuvres are fixed (the same for every seed); the seed only changes the sensors.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from slipd.sim import driver as drv
from slipd.sim.plant import Driver, Road, vehicle_parameters
from slipd.sim.track import Course, Segment, build_course
from slipd.sim.vehicle_data import derived, understeer_gradient

DEG = math.pi / 180.0
KPH = 1.0 / 3.6
MU_DRY = 1.0489  # the tyre data's own peak lateral friction (p_dy1): a dry road
#: Speed (m/s) at which a leg hands over to a stop: vehicle_dynamics_mb cannot integrate through
#: standstill (measured: its slip definitions divide by the wheel-centre speed, the integration
#: fails below ~0.1 m/s), so the last 2.5 m/s before a stop and the first after it are straight
#: constant-acceleration ramps (slipd.sim.core.run_plan).
CRAWL = 2.5
STOP_DECEL = 1.0  # m/s^2 of those ramps


@dataclass
class Leg:
    road: Road
    driver: Driver
    duration: float
    start_speed: float
    dwell: float = 0.0  # standstill after the leg, s (ramps to and from it at STOP_DECEL)


@dataclass
class Plan:
    legs: list[Leg]
    extra_mass: float = 0.0
    sensor: dict = field(default_factory=dict)
    heading0: float = 0.3  # rad, initial heading of the body x axis from east (counter-clockwise)


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    paper: str
    build: Callable[[int], Plan]
    duration: float  # nominal, s


def _course_driver(course: Course, vehicle: int, extra_mass: float = 0.0, **kw) -> Driver:
    d = derived(vehicle, extra_mass)
    follower = drv.CurvatureFollower(
        kappa_s=course.kappa_s, kappa=course.kappa, wheelbase=d["LF"] + d["LR"],
        understeer=understeer_gradient(vehicle, extra_mass),
    )
    return Driver(steer=follower, speed_target=lambda t, s: course.speed_at(s), **kw)


def _const_speed(v: float) -> Callable[[float, float], float]:
    return lambda t, s: v


def _course_duration(course: Course) -> float:
    v = np.maximum(course.speed, 1.0)
    return float(np.sum(np.diff(course.speed_s) / v[1:]))


# --- manoeuvres ----------------------------------------------------------------------------


def _step_steer(vehicle: int, extra_mass: float = 0.0) -> Plan:
    speed = 20.0
    law = drv.steer_pulses([(2.0, 8.0, 0.05, 0.15)])
    d = Driver(steer=law, speed_target=_const_speed(speed))
    return Plan([Leg(Road(), d, 12.0, speed)], extra_mass=extra_mass)


def step_steer(vehicle: int) -> Plan:
    """Selmanaj et al. 2017, section 5.3: a steer step at constant speed (72 km/h) to ~8 m/s^2
    of lateral acceleration, held 6 s, released."""
    return _step_steer(vehicle)


def loaded_vehicle(vehicle: int) -> Plan:
    """Selmanaj et al. 2017, section 6 (Fig. 25): the step steer with 300 kg of payload behind
    the CoG; the profile still describes the empty car."""
    return _step_steer(vehicle, extra_mass=300.0)


def _path_following(vehicle: int, x: np.ndarray, y: np.ndarray, speed: float, road: Road,
                    duration: float) -> Plan:
    """Pure-pursuit path following of the centre line (x, y) at constant ``speed``."""
    d = derived(vehicle)
    pp = drv.PurePursuit(x, y, d["LF"] + d["LR"], understeer_gradient(vehicle),
                         lookahead_time=0.5, min_lookahead=5.0)
    plant_driver = Driver(steer=pp, speed_target=_const_speed(speed))
    return Plan([Leg(road, plant_driver, duration, speed)], heading0=0.0)


def _lane_change(vehicle: int, speed: float, road: Road) -> Plan:
    x, y = drv.iso3888_2_centreline(vehicle_parameters(vehicle).w)
    return _path_following(vehicle, x, y, speed, road, 12.0)


def _slalom(vehicle: int, speed: float, road: Road) -> Plan:
    x, y = drv.slalom_centreline(spacing=20.0, cones=10, amplitude=1.0)
    return _path_following(vehicle, x, y, speed, road, 19.0)


def double_lane_change(vehicle: int) -> Plan:
    """Righetti & Lenzo 2025, section 4 (Fig. 5): ISO 3888-2 obstacle-avoidance lane change at
    50 km/h, pure-pursuit path following on the cone-lane centre line."""
    return _lane_change(vehicle, 50.0 * KPH, Road())


def slalom(vehicle: int) -> Plan:
    """Righetti & Lenzo 2025, section 4 (Fig. 6): ten cones 20 m apart at 60 km/h, gates 10 m
    before the first and after the last cone; pure-pursuit path following."""
    return _slalom(vehicle, 60.0 * KPH, Road())


def j_turn(vehicle: int) -> Plan:
    """Chen et al. 2018, section 4.1: J-turn on mu = 0.4 at 10 m/s (steer ramp to a held
    angle beyond the friction limit)."""
    law = drv.steer_pulses([(2.0, 1e9, 0.12, 0.5)])
    d = Driver(steer=law, speed_target=_const_speed(10.0))
    road = Road(mu=np.array([0.4]))
    return Plan([Leg(road, d, 10.0, 10.0)])


def sine_steer(vehicle: int) -> Plan:
    """Chen et al. 2018, section 4.2: sine steer on mu = 0.8 at 20 m/s."""
    law = drv.steer_sine(2.0, 0.045, 0.5, 3.0)
    d = Driver(steer=law, speed_target=_const_speed(20.0))
    road = Road(mu=np.array([0.8]))
    return Plan([Leg(road, d, 12.0, 20.0)])


def _handling_track(mu: float, speed_scale: float) -> list[Segment]:
    """A closed-circuit style handling track: straights, hairpins, an S-bend, fast sweepers.
    Corner speeds use 70-80 % of the grip times ``speed_scale``."""
    def corner(radius: float, angle_deg: float, left: bool, fraction: float = 0.7) -> Segment:
        v = math.sqrt(fraction * mu * 9.81 * radius) * speed_scale
        return Segment(radius * angle_deg * DEG, (1 if left else -1) / radius, v, mu)

    return [
        Segment(150, 0.0, 30.0, mu),
        corner(45, 90, True),
        Segment(80, 0.0, 25.0, mu),
        corner(25, 150, False),
        Segment(60, 0.0, 22.0, mu),
        corner(60, 60, True),
        corner(60, 60, False),
        Segment(120, 0.0, 30.0, mu),
        corner(120, 70, True, 0.8),
        Segment(50, 0.0, 25.0, mu),
        corner(35, 120, False, 0.8),
        Segment(100, 0.0, 28.0, mu),
        corner(30, 180, True, 0.8),
        Segment(150, 0.0, 30.0, mu),
    ]


def handling_high_mu(vehicle: int) -> Plan:
    """Selmanaj et al. 2017, section 5.4: a dry handling track driven briskly (up to ~8 m/s^2)."""
    course = build_course(_handling_track(MU_DRY, 1.0), start_speed=20.0, decel=2.0)
    d = _course_driver(course, vehicle)
    return Plan([Leg(course.road, d, min(90.0, _course_duration(course)), 20.0)])


def handling_low_mu(vehicle: int) -> Plan:
    """Selmanaj et al. 2017, section 5.5: a low-adherence track (mu ~ 0.3): a straight and soft
    curves driven near the limit, with large sideslip."""
    course = build_course(_handling_track(0.3, 0.95), start_speed=12.0, decel=1.0, accel=0.8)
    d = _course_driver(course, vehicle)
    return Plan([Leg(course.road, d, min(120.0, _course_duration(course)), 12.0)])


def mu_jump(vehicle: int) -> Plan:
    """Carnier, Corno, Savaresi 2023, section 4.2: abrupt friction changes (dry <-> 0.3) while
    cornering and changing lanes hard."""
    segs = []
    mus = [MU_DRY, 0.3, MU_DRY, 0.3, MU_DRY, 0.3, MU_DRY]
    for i, mu in enumerate(mus):
        sign = 1 if i % 2 == 0 else -1
        segs += [
            Segment(40, 0.0, 16.0, mu),
            Segment(35, sign / 40.0, 16.0, mu),  # the friction changes under a loaded car
            Segment(35, -sign / 40.0, 16.0, mu),
        ]
    course = build_course(segs, start_speed=16.0, transition=10.0)
    d = _course_driver(course, vehicle)
    return Plan([Leg(course.road, d, min(60.0, _course_duration(course)), 16.0)])


def straight_offsets(vehicle: int) -> Plan:
    """Selmanaj et al. 2017, sections 2 (remark 2) and 5.2: a long, nearly straight drive where
    the kinematic model is unobservable and sensor offsets make an integrator drift; the IMU
    carries deliberate offsets (0.15/0.25 m/s^2, 0.5 deg/s) on top of the random ones."""
    segs = []
    rng = np.random.default_rng(12345)  # fixed road, whatever the sensor seed
    for _ in range(30):
        segs.append(Segment(float(rng.uniform(150, 350)), float(rng.normal(0, 1 / 3000)),
                            float(rng.uniform(24, 32))))
    course = build_course(segs, start_speed=28.0, transition=60.0, accel=0.5, decel=0.5)
    d = _course_driver(course, vehicle)
    sensor = {"accel_offset": (0.15, 0.25, 0.0), "gyro_offset": (0.0, 0.0, 0.5 * DEG)}
    return Plan([Leg(course.road, d, 300.0, 28.0)], sensor=sensor)


def banked_road(vehicle: int) -> Plan:
    """Selmanaj et al. 2017, section 5.2 (the banked 'parabolic curve' that their offset
    estimator mistakes for an offset) and 3.1 (gravity through roll): banked straights and
    curves, uphill and downhill grades."""
    # cross slopes of 2.5 % on straights, curves superelevated up to 10 % (ramps and race
    # tracks go beyond), grades up to 8 % (mountain roads); banks ramp in over 30 m
    segs = [
        Segment(150, 0.0, 22.0, bank=1.5 * DEG),
        Segment(200, 1 / 120.0, 22.0, bank=-6.0 * DEG),  # left curve banked into the turn
        Segment(150, 0.0, 22.0, bank=-1.5 * DEG, grade=0.06),
        Segment(200, -1 / 90.0, 18.0, bank=5.0 * DEG, grade=-0.04),
        Segment(150, 0.0, 25.0, bank=-3.0 * DEG, grade=0.08),
        Segment(200, 1 / 150.0, 25.0, bank=3.0 * DEG),
        Segment(150, 0.0, 25.0, grade=-0.06),
    ]
    course = build_course(segs, start_speed=22.0)
    d = _course_driver(course, vehicle)
    return Plan([Leg(course.road, d, min(60.0, _course_duration(course)), 22.0)])


def snow_drift(vehicle: int) -> Plan:
    """Selmanaj et al. 2017, section 5.5 (large sideslip on low adherence) pushed further: a
    power-on drift on packed snow (mu = 0.3) held with counter-steer; beta exceeds 10 deg."""
    mu = 0.3
    radius = 30.0
    speed = math.sqrt(0.6 * mu * 9.81 * radius)
    t_recover, ramp = 14.0, 6.0

    def beta_target(t: float) -> float:  # -12 deg, eased back to 0 from t_recover on
        return -12.0 * DEG * (1.0 - drv.smoothstep((t - t_recover) / ramp))

    def slip_target(t: float) -> float:  # 0.35 for 0.6 s breaks the rear loose, 0.15 holds
        if t < 5.6:
            return 0.35
        return 0.02 + 0.13 * (1.0 - drv.smoothstep((t - t_recover) / ramp))

    entry = drv.steer_pulses([(1.0, 1e9, 0.10, 1.0)])
    hold = drv.DriftHold(before=entry, t_on=5.0, beta_target=beta_target, r_target=0.5)
    throttle = drv.SlipThrottle(5.0, t_recover + ramp, slip_target,
                                wheel_radius=vehicle_parameters(vehicle).R_w)
    d = Driver(steer=hold, speed_target=_const_speed(speed), accel_override=throttle)
    road = Road(mu=np.array([mu]))
    return Plan([Leg(road, d, 26.0, speed)])


def endurance(vehicle: int) -> Plan:
    """Selmanaj et al. 2017, section 5 (hours of mixed driving) and 5.2 (offsets over a long
    drive with stops): 4000 s of town, country road and motorway with standstills, wet and
    snowy patches, banks and grades. A fixed route; the seed changes only the sensors."""
    rng = np.random.default_rng(2017)
    legs: list[Leg] = []
    total = 0.0
    kinds = ["town", "country", "motorway", "country", "town", "country", "motorway"]
    i = 0
    while total < 4000.0:
        kind = kinds[i % len(kinds)]
        i += 1
        segs = []
        n_seg = {"town": 14, "country": 18, "motorway": 10}[kind]
        mu = MU_DRY if rng.uniform() < 0.6 else float(rng.choice([0.8, 0.6, 0.35]))
        for _ in range(n_seg):
            if rng.uniform() < 0.15:
                mu = MU_DRY if mu < MU_DRY else float(rng.choice([0.8, 0.6, 0.35]))
            if kind == "town":
                length, radius, vmax = rng.uniform(60, 200), rng.uniform(15, 60), 14.0
            elif kind == "country":
                length, radius, vmax = rng.uniform(100, 400), rng.uniform(60, 300), 25.0
            else:
                length, radius, vmax = rng.uniform(400, 1500), rng.uniform(600, 2000), 36.0
            straight = rng.uniform() < 0.5
            kappa = 0.0 if straight else float(rng.choice([-1, 1])) / radius
            v_corner = vmax if straight else min(vmax, math.sqrt(0.45 * mu * 9.81 * radius))
            segs.append(Segment(
                float(length), kappa, float(v_corner), mu,
                bank=float(rng.normal(0, 2.0 * DEG)), grade=float(rng.normal(0, 0.03)),
            ))
        # straight ends: the stop and the pull-away happen in a straight line
        segs = [Segment(40.0, 0.0, 10.0, mu), *segs, Segment(80.0, 0.0, CRAWL, mu)]
        course = build_course(segs, start_speed=CRAWL, end_speed=CRAWL, accel=1.0, decel=2.0)
        drive_time = _course_duration(course) + 5.0
        dwell = float(rng.uniform(5, 40))
        legs.append(Leg(course.road, _course_driver(course, vehicle), drive_time, CRAWL, dwell))
        total += drive_time + dwell + 2 * CRAWL / STOP_DECEL
    return Plan(legs)


# --- at the limit, beyond the suite (benchmarks.accuracy's ``limits`` block) ---------------


def wet_handling(vehicle: int) -> Plan:
    """slipd, beyond the papers' tests: the handling track on a wet road (mu = 0.6) with
    corners at 75-85 % of its grip (cars that spin there are reported, not simulated)."""
    course = build_course(_handling_track(0.6, 1.08), start_speed=18.0, decel=2.0)
    d = _course_driver(course, vehicle)
    return Plan([Leg(course.road, d, min(90.0, _course_duration(course)), 18.0)])


def _skidpad(mu: float, v_end: float) -> Plan:
    v_start, steer, ramp_start, ramp = 6.0, 0.08, 3.0, 40.0

    def speed(t: float, s: float) -> float:
        return v_start + (v_end - v_start) * min(max((t - ramp_start) / ramp, 0.0), 1.0)

    d = Driver(steer=drv.steer_pulses([(1.0, 1e9, steer, 1.0)]), speed_target=speed)
    return Plan([Leg(Road(mu=np.array([mu])), d, 45.0, v_start)])


def skidpad_wet(vehicle: int) -> Plan:
    """slipd, beyond the papers' tests: a steady-state circle at a held steering angle (R ~ 33
    m) with the speed ramped from 6 to 17 m/s over 40 s, through the limit of a wet road (mu =
    0.6, ISO 4138's constant-steer-angle method)."""
    return _skidpad(0.6, 17.0)


def skidpad_dry(vehicle: int) -> Plan:
    """slipd, beyond the papers' tests: the same constant-steer-angle circle on a dry road,
    the speed ramped from 6 to 22 m/s through its limit."""
    return _skidpad(MU_DRY, 22.0)


def wet_sine_steer(vehicle: int) -> Plan:
    """slipd, beyond the papers' tests: a sine steer (0.06 rad at the wheels, 0.4 Hz, four
    periods) at 22 m/s on mu = 0.5: the car slides to 10+ deg of sideslip while every
    model that assumes the profile's friction sees far less (consistency's docstring)."""
    d = Driver(steer=drv.steer_sine(2.0, 0.06, 0.4, 4.0), speed_target=_const_speed(22.0))
    return Plan([Leg(Road(mu=np.array([0.5])), d, 14.0, 22.0)])


def wet_lane_change(vehicle: int) -> Plan:
    """slipd, beyond the papers' tests: the ISO 3888-2 obstacle-avoidance lane change of
    ``double_lane_change`` at 60 km/h on a wet road (mu = 0.5)."""
    return _lane_change(vehicle, 60.0 * KPH, Road(mu=np.array([0.5])))


def snow_slalom(vehicle: int) -> Plan:
    """slipd, beyond the papers' tests: the slalom of ``slalom`` (ten cones 20 m apart) at 45
    km/h on packed snow (mu = 0.3)."""
    return _slalom(vehicle, 45.0 * KPH, Road(mu=np.array([0.3])))


def icy_sine_steer(vehicle: int) -> Plan:
    """slipd, beyond the papers' tests: a slow sine steer (0.04 rad, 0.3 Hz, three periods) at
    25 m/s on an icy road (mu = 0.35); the car keeps sliding after the wheel is straight."""
    d = Driver(steer=drv.steer_sine(3.0, 0.04, 0.3, 3.0), speed_target=_const_speed(25.0))
    return Plan([Leg(Road(mu=np.array([0.35])), d, 16.0, 25.0)])


def wet_step_steer(vehicle: int) -> Plan:
    """slipd, beyond the papers' tests: the step steer of ``step_steer`` (0.05 rad at 72 km/h,
    held 6 s) on a wet road (mu = 0.6), which it asks beyond its grip."""
    law = drv.steer_pulses([(2.0, 8.0, 0.05, 0.15)])
    d = Driver(steer=law, speed_target=_const_speed(20.0))
    return Plan([Leg(Road(mu=np.array([0.6])), d, 12.0, 20.0)])


SCENARIOS: dict[str, Scenario] = {}
#: manoeuvres at and beyond the limit of adhesion that are not in the suite (``slipd sim
#: --suite``) and were in no block when the estimators were tuned: benchmarks.accuracy's
#: ``limits`` block; ``slipd sim NAME`` runs each like any scenario
LIMIT_SCENARIOS: dict[str, Scenario] = {}


def _register(fn: Callable[[int], Plan], duration: float,
              into: dict[str, Scenario] = SCENARIOS) -> None:
    doc = (fn.__doc__ or "").strip()
    paper = " ".join(doc.split(":")[0].split())
    description = " ".join(doc.split(":", 1)[1].split()) if ":" in doc else doc
    into[fn.__name__] = Scenario(fn.__name__, description, paper, fn, duration)


def find_scenario(name: str) -> Scenario | None:
    """The suite's or the limits' scenario ``name`` (None: neither has it)."""
    return SCENARIOS.get(name) or LIMIT_SCENARIOS.get(name)


for _fn, _dur in (
    (step_steer, 12.0),
    (double_lane_change, 12.0),
    (slalom, 19.0),
    (j_turn, 10.0),
    (sine_steer, 12.0),
    (handling_high_mu, 68.0),
    (handling_low_mu, 120.0),
    (mu_jump, 48.0),
    (straight_offsets, 300.0),
    (banked_road, 55.0),
    (loaded_vehicle, 12.0),
    (snow_drift, 26.0),
    (endurance, 4000.0),
):
    _register(_fn, _dur)
for _fn, _dur in ((wet_handling, 90.0), (skidpad_wet, 45.0), (skidpad_dry, 45.0),
                  (wet_sine_steer, 14.0), (wet_lane_change, 12.0), (snow_slalom, 19.0),
                  (icy_sine_steer, 16.0), (wet_step_steer, 12.0)):
    _register(_fn, _dur, LIMIT_SCENARIOS)
