"""``simulate``: scenario -> plant -> truth and sensor messages."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from slipd.channels import In, Veh
from slipd.errors import ConfigError
from slipd.sim.plant import (
    N_MB,
    OMEGA_FL,
    OMEGA_RR,
    PITCH_RATE,
    POS_X,
    POS_Y,
    ROLL_RATE,
    STEER,
    VX,
    VY,
    VZ_S,
    YAW,
    YAW_RATE,
    Plant,
    PlantOutput,
    vehicle_parameters,
)
from slipd.sim.result import DEFAULT_MESSAGES, MessageSpec, SimResult, sample_messages
from slipd.sim.scenarios import (
    CRAWL,
    LIMIT_SCENARIOS,
    SCENARIOS,
    STOP_DECEL,
    Plan,
    find_scenario,
)
from slipd.sim.sensors import SensorConfig, sensor_channels, truth
from slipd.sim.vehicle_data import DEFAULT_IMU_POSITION, DEFAULT_STEER_RATIO

DT = 0.01  # s, the plant output grid (truth and sensor sampling)


def _profile_or_none(profile):
    """The vehicle profile to take the message layout, IMU position and steering ratio from.

    ``profile`` may be a Profile, a name/path, or None for the shipped default; when the profile
    machinery is not importable the simulator falls back to slipd.dbc's layout (DEFAULT_MESSAGES)
    and its own vehicle data.
    """
    if profile is not None and not isinstance(profile, str):
        return profile
    try:
        from slipd.profile import load_profile
    except ImportError:
        return None
    return load_profile(profile or "default")


def message_specs(profile) -> tuple[MessageSpec, ...]:
    if profile is None:
        return DEFAULT_MESSAGES
    return tuple(
        MessageSpec(m.name, int(m.frame_id), float(m.rate_hz), tuple(m.channels))
        for m in profile.input_messages
    )


def _leg_output(args) -> PlantOutput:
    """Integrate one leg from its own settled start (module-level: picklable for a pool)."""
    plan_name, vehicle, leg_index, leg_time, extra_mass = args
    plan = find_scenario(plan_name).build(vehicle)
    leg = plan.legs[leg_index]
    p = vehicle_parameters(vehicle, extra_mass=extra_mass)
    return Plant(p, leg.road, leg.driver).run(leg_time, leg.start_speed, dt=DT)


def _stitch(out: PlantOutput, t0: float, s0: float, pose: tuple[float, float, float]):
    """Shift a leg computed from the origin to start at time t0, distance s0 and ``pose``
    (x, y, yaw): the dynamics do not depend on position or heading, so this equals
    integrating from there."""
    x0, y0, yaw0 = pose
    x = out.x.copy()
    c, s = math.cos(yaw0), math.sin(yaw0)
    px, py = x[:, POS_X], x[:, POS_Y]
    x[:, POS_X], x[:, POS_Y] = x0 + c * px - s * py, y0 + s * px + c * py
    x[:, YAW] = x[:, YAW] + yaw0
    dx = out.dx.copy()
    vxw, vyw = dx[:, POS_X].copy(), dx[:, POS_Y].copy()
    dx[:, POS_X], dx[:, POS_Y] = c * vxw - s * vyw, s * vxw + c * vyw
    return dataclasses.replace(out, t=out.t + t0, x=x, dx=dx, s=out.s + s0)


def _ramp(t0: float, x_from: np.ndarray, x_to: np.ndarray, v_from: float, v_to: float,
          s0: float, p, road_end: PlantOutput) -> PlantOutput:
    """Straight-line constant-acceleration motion from ``v_from`` to ``v_to`` (stop or
    pull-away below the model's domain). Body states move linearly from ``x_from`` to ``x_to``;
    lateral motion is zero, the wheels roll without slip."""
    accel = STOP_DECEL if v_to > v_from else -STOP_DECEL
    duration = abs(v_to - v_from) / STOP_DECEL
    n = max(1, int(round(duration / DT)))
    tau = np.arange(1, n + 1) * DT
    frac = tau / (n * DT)
    v = v_from + accel * tau
    dist = v_from * tau + 0.5 * accel * tau**2
    x = x_from[None, :] + frac[:, None] * (x_to - x_from)[None, :]
    yaw = x_from[YAW]
    x[:, POS_X] = x_from[POS_X] + dist * math.cos(yaw)
    x[:, POS_Y] = x_from[POS_Y] + dist * math.sin(yaw)
    x[:, YAW] = yaw
    x[:, VX] = v
    for i in (VY, YAW_RATE, ROLL_RATE, PITCH_RATE, VZ_S, STEER):
        x[:, i] = 0.0
    x[:, OMEGA_FL : OMEGA_RR + 1] = (v / p.R_w)[:, None]
    dx = np.zeros_like(x)
    dx[:, VX] = accel
    dx[:, POS_X] = v * math.cos(yaw)
    dx[:, POS_Y] = v * math.sin(yaw)
    return PlantOutput(
        t=t0 + tau, x=x, dx=dx, s=s0 + dist, accel_demand=np.full(n, accel),
        mu=np.full(n, road_end.mu[-1]), bank=np.full(n, road_end.bank[-1]),
        grade=np.full(n, road_end.grade[-1]),
    )


def _standstill(t0: float, n: int, x_end: np.ndarray, s_end: float, last: PlantOutput):
    """``n`` samples of a parked car: ``x_end`` with every velocity zero."""
    x = np.array(x_end, dtype=np.float64)
    for i in (VX, VY, YAW_RATE, ROLL_RATE, PITCH_RATE, VZ_S, 14, 15, 17, 19, 20, 22):
        x[i] = 0.0
    x[OMEGA_FL : OMEGA_RR + 1] = 0.0
    return PlantOutput(
        t=t0 + np.arange(1, n + 1) * DT,
        x=np.repeat(x[None, :], n, axis=0),
        dx=np.zeros((n, N_MB)),
        s=np.full(n, s_end),
        accel_demand=np.zeros(n),
        mu=np.full(n, last.mu[-1]),
        bank=np.full(n, last.bank[-1]),
        grade=np.full(n, last.grade[-1]),
    )


def run_plan(
    scenario: str,
    vehicle: int,
    duration: float | None = None,
    progress: Callable[[float], None] | None = None,
    workers: int = 1,
) -> tuple[PlantOutput, object, Plan]:
    """Integrate every leg of the scenario's plan (cut at ``duration`` s) and join them.

    Legs are independent integrations (each starts settled at its own start speed; a leg after
    a standstill starts from the crawl speed the pull-away ramp reaches), so ``workers`` > 1
    integrates them in parallel processes. Stops between legs are ramps and a parked car.
    """
    plan = find_scenario(scenario).build(vehicle)
    p = vehicle_parameters(vehicle, extra_mass=plan.extra_mass)
    legs = list(plan.legs)
    if duration is not None and len(legs) == 1:
        legs[0] = dataclasses.replace(legs[0], duration=duration)
    # how long each leg runs when the whole is cut at ``duration`` (the stop ramps included)
    jobs, budget = [], duration if duration is not None else math.inf
    for i, leg in enumerate(legs):
        if budget < DT:
            break
        leg_time = min(leg.duration, budget)
        jobs.append((scenario, vehicle, i, leg_time, plan.extra_mass))
        budget -= leg_time + leg.dwell + 2 * CRAWL / STOP_DECEL
    if len(jobs) == 1:
        leg = legs[0]
        outs = [Plant(p, leg.road, leg.driver).run(jobs[0][3], leg.start_speed, dt=DT,
                                                    progress=progress)]
    elif workers > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(max_workers=workers) as pool:
            outs = []
            for out in pool.map(_leg_output, jobs):
                outs.append(out)
                if progress is not None:
                    progress(sum(float(o.t[-1]) for o in outs))
    else:
        outs = []
        for job in jobs:
            outs.append(_leg_output(job))
            if progress is not None:
                progress(sum(float(o.t[-1]) for o in outs))
    parts: list[PlantOutput] = []
    t0, s0, pose = 0.0, 0.0, (0.0, 0.0, 0.0)
    for i, out in enumerate(outs):
        if i > 0:  # pull away from the standstill up to this leg's start speed
            ramp = _ramp(t0, parts[-1].x[-1], out.x[0], 0.0, legs[i].start_speed, s0, p,
                         parts[-1])
            ramp.x[:, POS_X] = pose[0] + (ramp.s - s0) * math.cos(pose[2])
            ramp.x[:, POS_Y] = pose[1] + (ramp.s - s0) * math.sin(pose[2])
            parts.append(ramp)
            t0, s0 = float(ramp.t[-1]), float(ramp.s[-1])
            pose = (float(ramp.x[-1, POS_X]), float(ramp.x[-1, POS_Y]), pose[2])
            out = _slice(out, 1)
            out = dataclasses.replace(out, t=out.t - DT)
        part = _stitch(out, t0 + (DT if i > 0 else 0.0), s0, pose)
        parts.append(part)
        t0, s0 = float(part.t[-1]), float(part.s[-1])
        pose = (float(part.x[-1, POS_X]), float(part.x[-1, POS_Y]), float(part.x[-1, YAW]))
        if legs[i].dwell > 0 and len(outs) > 1:
            still_x = part.x[-1].copy()
            ramp = _ramp(t0, part.x[-1], still_x, float(part.x[-1, VX]), 0.0, s0, p, part)
            parts.append(ramp)
            t0, s0 = float(ramp.t[-1]), float(ramp.s[-1])
            pose = (float(ramp.x[-1, POS_X]), float(ramp.x[-1, POS_Y]), pose[2])
            still = _standstill(t0, int(round(legs[i].dwell / DT)), ramp.x[-1], s0, part)
            parts.append(still)
            t0 = float(still.t[-1])
    joined = PlantOutput(*(np.concatenate([getattr(o, f.name) for o in parts])
                           for f in dataclasses.fields(PlantOutput)))
    if duration is not None:
        joined = _head(joined, int(round(duration / DT)) + 1)
    return joined, p, plan


def _slice(out: PlantOutput, start: int) -> PlantOutput:
    return PlantOutput(*(getattr(out, f.name)[start:] for f in dataclasses.fields(PlantOutput)))


def _head(out: PlantOutput, n: int) -> PlantOutput:
    return PlantOutput(*(getattr(out, f.name)[:n] for f in dataclasses.fields(PlantOutput)))


#: Channels whose messages take SensorConfig.imu_delay, wheel_delay and steer_delay.
_DELAY_GROUPS = (
    ("imu_delay", frozenset((In.AX, In.AY, In.AZ, In.YAW_RATE, In.ROLL_RATE, In.PITCH_RATE))),
    ("wheel_delay", frozenset((In.WHEEL_SPEED_FL, In.WHEEL_SPEED_FR, In.WHEEL_SPEED_RL,
                               In.WHEEL_SPEED_RR, In.SPEED_REF))),
    ("steer_delay", frozenset((In.STEER, In.STEER_RATE))),
)


def message_delays(specs, cfg: SensorConfig) -> tuple[float, ...] | None:
    """Per message, the extra age of its values (the largest of its channels' groups); None when
    every delay is 0 (the baseline's sampling, untouched)."""
    if not any(getattr(cfg, name) for name, _ in _DELAY_GROUPS):
        return None
    return tuple(
        max([getattr(cfg, name) for name, group in _DELAY_GROUPS
             if group.intersection(spec.channels)], default=0.0)
        for spec in specs
    )


def _sensor_config(plan: Plan, prof, overrides: dict) -> SensorConfig:
    cfg_kw = {**plan.sensor, **overrides}
    unknown = set(cfg_kw) - {f.name for f in dataclasses.fields(SensorConfig)}
    if unknown:
        raise ConfigError(f"unknown sensor setting(s) {sorted(unknown)}")
    if prof is not None:
        veh = prof.vehicle
        cfg_kw.setdefault("imu_position", (float(veh[Veh.IMU_X]), float(veh[Veh.IMU_Y]),
                                           float(veh[Veh.IMU_Z])))
        cfg_kw.setdefault("steer_ratio", float(veh[Veh.STEER_RATIO]))
    else:
        cfg_kw.setdefault("imu_position", DEFAULT_IMU_POSITION)
        cfg_kw.setdefault("steer_ratio", DEFAULT_STEER_RATIO)
    return SensorConfig(**cfg_kw)


def sense(
    scenario: str,
    plant: tuple[PlantOutput, object, Plan],
    vehicle: int = 2,
    seed: int = 0,
    profile=None,
    sensor: dict | None = None,
    variant: str | None = None,
) -> SimResult:
    """The sensors' view of an integrated scenario (``plant`` as :func:`run_plan` returns it):
    truth and messages for sensor seed ``seed``, sensor variant ``variant`` (a name of
    :data:`slipd.sim.variants.VARIANTS` or names joined by commas) and the explicit ``sensor``
    overrides on top. ``profile`` must be a loaded Profile or None (slipd.dbc's layout)."""
    from slipd.sim.variants import resolve

    out, p, plan = plant
    variant_name, variant_overrides = resolve(variant)
    overrides = {**variant_overrides, **(sensor or {})}
    cfg = _sensor_config(plan, profile, overrides)
    rng = np.random.default_rng(seed)
    drawn: dict = {}
    channels = sensor_channels(out, p, cfg, rng, heading0=plan.heading0, record=drawn)
    specs = message_specs(profile)
    sensors = sample_messages(
        out.t, channels, specs, rng,
        cfg.latency_base, cfg.latency_spacing, cfg.latency_jitter,
        delays=message_delays(specs, cfg),
    )
    return SimResult(
        scenario=scenario, vehicle=vehicle, seed=seed, truth=truth(out, p), sensors=sensors,
        meta={"sensor_config": cfg, "extra_mass": plan.extra_mass, "variant": variant_name,
              "sensor_overrides": overrides, "sensor_errors": drawn},
    )


def simulate(
    scenario: str,
    vehicle: int = 2,
    seed: int = 0,
    duration: float | None = None,
    profile=None,
    progress: Callable[[float], None] | None = None,
    workers: int = 1,
    sensor: dict | None = None,
    variant: str | None = None,
) -> SimResult:
    """Run ``scenario`` on vehicle parameter set ``vehicle`` with sensor seed ``seed``.

    ``duration`` (s) cuts the scenario (or stretches a one-leg manoeuvre). ``profile`` (a
    Profile or a name) supplies the input messages, the IMU position and the steering ratio;
    default: the shipped default profile. ``progress(t_sim)`` is called after each segment.
    ``workers`` > 1 integrates the legs of a multi-leg drive (endurance) in parallel processes.
    ``variant`` names a sensor variant (slipd.sim.variants.VARIANTS; several joined by commas
    apply together); ``sensor`` overrides fields of :class:`~slipd.sim.sensors.SensorConfig`
    (e.g. ``{"gnss_delay": 0.1}``) on top of the scenario's own and the variant's.
    """
    return simulate_variants(scenario, [variant], vehicle, seed, duration, profile, progress,
                             workers, sensor)[0]


def simulate_variants(
    scenario: str,
    variants,
    vehicle: int = 2,
    seed: int = 0,
    duration: float | None = None,
    profile=None,
    progress: Callable[[float], None] | None = None,
    workers: int = 1,
    sensor: dict | None = None,
) -> list[SimResult]:
    """:func:`simulate` for each entry of ``variants`` (a variant spec or None for the baseline)
    on one integration of the plant: the results share the truth and differ only in the
    sensors."""
    from slipd.sim.variants import resolve

    if find_scenario(scenario) is None:
        raise ConfigError(f"unknown scenario {scenario!r}; available: {', '.join(SCENARIOS)} "
                          f"and, beyond the suite, {', '.join(LIMIT_SCENARIOS)}")
    if duration is not None and duration <= 0:
        raise ConfigError(f"duration must be positive, got {duration}")
    prof = _profile_or_none(profile)
    plan = find_scenario(scenario).build(vehicle)
    for spec in variants:  # refuse a bad name or setting before the integration
        _sensor_config(plan, prof, {**resolve(spec)[1], **(sensor or {})})
    plant = run_plan(scenario, vehicle, duration, progress, workers)
    return [sense(scenario, plant, vehicle, seed, prof, sensor, spec) for spec in variants]
