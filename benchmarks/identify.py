"""slipd identify on simulated drives with known truth: identified value, 95 % interval, the
truth and the issue's tolerance per quantity, for several vehicles and sensor seeds, starting
from a wrong profile.

Per vehicle the endurance route (cut at ``--duration`` s: town, country road, stops) is
integrated once and sensed with each seed, with the IMU misaligned (variant
``misalignment``: 1.5 deg per axis + random), the steering sensor off (``steer_offset``) and
fixed rolling-radius errors on top of the random offsets. The log is identified with the
car's profile made wrong (steering ratio +15 %, cornering stiffness front -30 % and rear
+30 %, roll stiffness +50 %, yaw inertia +30 %). The truth: slipd.identify.truth. Then
d_ekf and linear_kf are evaluated on another scenario of the same car and seed
(handling_high_mu) with the wrong and with the identified profile.

``--start default`` (issue 18's first "done when"): the same drive is identified starting
from the shipped default profile as it is (the simulator's vehicle 2, whatever car drove),
and d_ekf and kinematic_heuristic are evaluated on the suite's short manoeuvres of the same
car (EVAL_SUITE: every scenario but the identification drive itself and straight_offsets,
which has sensor offsets of its own) with the same sensors as the drive (``--sensors
faulty``: VARIANT and SENSOR; ``nominal``: each scenario's own, so only the parameters
differ), pooled: beta RMS with the default profile, the default profile with only the
identified ``[calibration]``, the identified profile, the identified one with the plant's
I_z / m (what an identifiable yaw inertia would add), the car's own parameters (mass,
geometry, inertias: what identify does not estimate) with the identified ``[calibration]``,
and the identified profile and the car's own with each scenario's true ``[calibration]``
(its own turn-on offsets undone exactly: the car's own values with it are the bound any
profile can reach with d_ekf); each as a ratio to the default profile, over all scenarios
and apart over the linear-range ones and the three at the friction limit (FRICTION_LIMIT).
Before: each car's default, identified and plant values of what d_ekf reads.

    .venv/bin/python -m benchmarks.identify [--vehicles 1,2,3] [--seeds 1,2] [--duration 900]
        [--start wrong|default] [--sensors faulty|nominal] [--jobs 2]
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

from slipd.channels import G, Veh
from slipd.eval.metrics import Accumulator
from slipd.identify import identify
from slipd.identify.profile_text import write_profile
from slipd.identify.truth import (
    car_values,
    check_table,
    compare,
    truth_of,
    write_car_profile,
)
from slipd.profile import load_profile
from slipd.sim.core import run_plan, sense
from slipd.sim.plant import SimulationError
from slipd.sim.scenarios import SCENARIOS
from slipd.sim.writer import sensor_errors_as_calibration, write_log, write_truth_csv

WRONG = {"vehicle.steering_ratio": 1.15, "vehicle.tyre.cornering_stiffness_front": 0.7,
         "vehicle.tyre.cornering_stiffness_rear": 1.3, "vehicle.roll_stiffness": 1.5,
         "vehicle.yaw_inertia": 1.3}
VARIANT = "misalignment,steer_offset"
SENSOR = {"wheel_radius_bias": (0.01, -0.005, 0.0, 0.008)}
RATIO = 16.0
EVAL_SCENARIO = "handling_high_mu"
#: --start default: the scenarios evaluated on (the suite's short manoeuvres; not endurance,
#: the drive identified on, nor straight_offsets, whose own sensor offsets are another IMU's)
EVAL_SUITE = ("step_steer", "double_lane_change", "slalom", "j_turn", "sine_steer",
              "handling_high_mu", "handling_low_mu", "mu_jump", "banked_road", "loaded_vehicle",
              "snow_drift")
DEFAULT_START_METHODS = ("d_ekf", "kinematic_heuristic")
#: EVAL_SUITE's manoeuvres at the friction limit, where d_ekf's error is its tyre model's at
#: the nominal friction whatever the profile (pooled apart: "limit", the rest "linear")
FRICTION_LIMIT = ("j_turn", "mu_jump", "snow_drift")
TRUE = object()  # a profile's [calibration]: each scenario's own sensor errors
GROUPS = {"all": None, "linear": tuple(n for n in EVAL_SUITE if n not in FRICTION_LIMIT),
          "limit": FRICTION_LIMIT}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", default="1,2,3")
    parser.add_argument("--seeds", default="1,2")
    parser.add_argument("--duration", type=float, default=900.0)
    parser.add_argument("--no-eval", action="store_true")
    parser.add_argument("--start", choices=("wrong", "default"), default="wrong",
                        help="wrong: the car's profile made wrong (WRONG); default: the shipped "
                             "default profile as it is, evaluated on EVAL_SUITE")
    parser.add_argument("--sensors", choices=("faulty", "nominal"), default="faulty",
                        help="--start default: faulty (VARIANT and SENSOR, as --start wrong) or "
                             "nominal (each scenario's own sensors: only the parameters differ)")
    parser.add_argument("--jobs", type=int, default=2,
                        help="processes integrating the plant (default 2)")
    args = parser.parse_args()
    if args.start == "default":
        return main_default_start(args)
    vehicles = [int(v) for v in args.vehicles.split(",")]
    seeds = [int(s) for s in args.seeds.split(",")]
    folder = Path(tempfile.mkdtemp(prefix="slipd-identify-bench-"))
    total, inside = 0, 0
    for vehicle in vehicles:
        right = write_car_profile(folder / f"v{vehicle}_right.toml", vehicle, RATIO)
        wrong = write_car_profile(folder / f"v{vehicle}_wrong.toml", vehicle, RATIO, WRONG)
        started = time.perf_counter()
        plant = run_plan("endurance", vehicle, args.duration, workers=2)
        eval_plant = None if args.no_eval else run_plan(EVAL_SCENARIO, vehicle)
        print(f"vehicle {vehicle}: endurance {args.duration:.0f} s integrated in "
              f"{time.perf_counter() - started:.0f} s")
        for seed in seeds:
            result = sense("endurance", plant, vehicle, seed, load_profile(right), SENSOR, VARIANT)
            log = folder / f"v{vehicle}_s{seed}.log"
            write_log(log, result, load_profile(right))
            started = time.perf_counter()
            found = identify([log], load_profile(wrong), progress=False)
            elapsed = time.perf_counter() - started
            new = write_profile(found, folder / f"v{vehicle}_s{seed}_identified.toml")
            del new
            checks = compare(found, truth_of(result, vehicle, RATIO))
            total += len(checks)
            inside += sum(c.inside for c in checks)
            print(f"\nvehicle {vehicle}, seed {seed}: identified in {elapsed:.1f} s "
                  f"({sum(c.inside for c in checks)}/{len(checks)} truths inside the 95 % CI)")
            print("\n".join(check_table(checks)))
            for key, missing in found.left().items():
                print(f"  left: {key}: {missing.reason}")
            if eval_plant is not None:
                _evaluate(folder, vehicle, seed, eval_plant, right, wrong,
                          folder / f"v{vehicle}_s{seed}_identified.toml")
    print(f"\noverall: {inside}/{total} truths inside their 95 % CI "
          f"({100 * inside / max(total, 1):.0f} %)")
    print(f"files: {folder}")


def _evaluate(folder: Path, vehicle: int, seed: int, plant, right: Path, wrong: Path,
              identified: Path) -> None:
    """beta RMS of d_ekf and linear_kf on another scenario with the wrong, identified and
    right profiles (the drive has the same sensor errors: the same seed and settings)."""
    from slipd.eval.runs import LogCase, evaluate_logs

    result = sense(EVAL_SCENARIO, plant, vehicle, seed, load_profile(right), SENSOR, VARIANT)
    log = folder / f"v{vehicle}_s{seed}_{EVAL_SCENARIO}.log"
    truth = folder / f"v{vehicle}_s{seed}_{EVAL_SCENARIO}.truth.csv"
    write_log(log, result, load_profile(right))
    write_truth_csv(truth, result)
    methods = ["d_ekf", "linear_kf"]
    rms = {}
    for name, path in (("wrong", wrong), ("identified", identified),
                       ("right parameters, no [calibration]", right)):
        report, _, _ = evaluate_logs([LogCase(log.name, log, truth)], methods,
                                     load_profile(path), name=name)
        rms[name] = {m: s.beta_rms_deg for m, s in report.overall().items()}
    print(f"  beta RMS [deg] on {EVAL_SCENARIO} (seed {seed}), baseline the wrong profile:")
    for name, row in rms.items():
        print(f"    {name:36s} " + "  ".join(
            f"{m} {row[m]:.3f} ({row[m] / rms['wrong'][m]:.2f}x)" for m in methods))


def _integrate(job: tuple[str, int]):
    """run_plan in a worker process: the plant output and parameters (a plan holds local
    functions, which do not pickle: the caller builds it again), or the error's text where
    the plant fails on this car (reported and left out of the pool, not hidden)."""
    try:
        out, parameters, _ = run_plan(*job)
    except (SimulationError, ArithmeticError, ValueError) as exc:
        return f"{type(exc).__name__}: {exc}"
    return out, parameters


def main_default_start(args) -> None:
    """Identify from the shipped default profile; evaluate on EVAL_SUITE of the same car."""
    from concurrent.futures import ProcessPoolExecutor

    from slipd.eval.runs import LogCase, evaluate_logs

    vehicles = [int(v) for v in args.vehicles.split(",")]
    seeds = [int(s) for s in args.seeds.split(",")]
    methods = list(DEFAULT_START_METHODS)
    sensor, variant = (SENSOR, VARIANT) if args.sensors == "faulty" else (None, None)
    print(f"sensors: {args.sensors} (variant {variant}, overrides {sensor})")
    folder = Path(tempfile.mkdtemp(prefix="slipd-identify-default-"))
    default = load_profile("default")
    rows = []  # (vehicle, seed, profile name, {method: rms})
    for vehicle in vehicles:
        right = write_car_profile(folder / f"v{vehicle}_right.toml", vehicle, RATIO)
        started = time.perf_counter()
        plant = run_plan("endurance", vehicle, args.duration, workers=args.jobs)
        with ProcessPoolExecutor(max_workers=args.jobs) as pool:
            integrated = dict(zip(EVAL_SUITE, pool.map(
                _integrate, [(name, vehicle) for name in EVAL_SUITE]), strict=True))
        eval_plants = {}
        for name, plant_of in integrated.items():
            if isinstance(plant_of, str):
                print(f"  {name}: left out, the plant does not integrate on vehicle {vehicle} "
                      f"({plant_of})")
            else:
                eval_plants[name] = (*plant_of, SCENARIOS[name].build(vehicle))
        print(f"vehicle {vehicle}: endurance {args.duration:.0f} s and {len(eval_plants)} "
              f"evaluation scenarios integrated in {time.perf_counter() - started:.0f} s")
        _print_mismatch(vehicle)
        for seed in seeds:
            result = sense("endurance", plant, vehicle, seed, default, sensor, variant)
            log = folder / f"v{vehicle}_s{seed}.log"
            write_log(log, result, default)
            started = time.perf_counter()
            found = identify([log], default, progress=False)
            identified = folder / f"v{vehicle}_s{seed}_identified.toml"
            write_profile(found, identified)
            checks = compare(found, truth_of(result, vehicle, RATIO))
            print(f"\nvehicle {vehicle}, seed {seed}: identified from the default profile in "
                  f"{time.perf_counter() - started:.1f} s "
                  f"({sum(c.inside for c in checks)}/{len(checks)} truths inside the 95 % CI)")
            print("\n".join(check_table(checks)))
            for key, missing in found.left().items():
                print(f"  left: {key}: {missing.reason}")
            _print_parameters(vehicle, default, load_profile(identified))
            cases, true_calibrations = [], {}
            for name in eval_plants:
                sensed = sense(name, eval_plants[name], vehicle, seed, default, sensor, variant)
                case_log = folder / f"v{vehicle}_s{seed}_{name}.log"
                case_truth = folder / f"v{vehicle}_s{seed}_{name}.truth.csv"
                write_log(case_log, sensed, default)
                write_truth_csv(case_truth, sensed)
                cases.append(LogCase(name, case_log, case_truth))
                true_calibrations[name] = _calibration_table(
                    sensor_errors_as_calibration(sensed.meta["sensor_errors"]))
            calibration = load_toml(identified).get("calibration", {})
            car = car_values(vehicle)
            # I_z at the profile's mass with the plant's I_z / m (the dynamics see I_z / m):
            # what an identifiable yaw inertia would add (identify reports, never writes it)
            inertia = car["vehicle.yaw_inertia"] / car["vehicle.mass"] * float(
                load_profile(identified).vehicle[Veh.MASS])
            # name -> (profile, its [calibration] or TRUE: each scenario's own sensor errors
            # undone exactly, which no identification from another drive can give (the turn-on
            # offsets are drawn per drive): with the car's own values, the bound; [vehicle]
            # keys set)
            profiles = {
                "default": ("default", None, {}),
                "default + identified [calibration]": ("default", calibration, {}),
                "identified": (identified, None, {}),
                "identified + the plant's I_z / m": (identified, None, {"yaw_inertia": inertia}),
                "car's own values + identified [calibration]": (right, calibration, {}),
                "identified + true [calibration]": (identified, TRUE, {}),
                "car's own values + true [calibration]": (right, TRUE, {}),
            }
            per_case = {}
            for name, (base, cal, keys) in profiles.items():
                groups = {g: {m: Accumulator() for m in methods} for g in GROUPS}
                per_case[name] = {}
                for case in cases:
                    table = true_calibrations[case.name] if cal is TRUE else cal
                    profile = load_profile(base, edit=_edit(table, keys))
                    report, _, _ = evaluate_logs([case], methods, profile, name=name)
                    per_case[name][case.name] = report.logs[case.name]
                    for group, members in GROUPS.items():
                        if members is None or case.name in members:
                            for m in methods:
                                groups[group][m].merge(report.pooled[m])
                rows.append((vehicle, seed, name, {
                    (g, m): acc.scores().beta_rms_deg for g, by in groups.items()
                    for m, acc in by.items()}))
            _print_per_scenario(vehicle, seed, per_case, methods[0])
    print("\nbeta RMS [deg], pooled over the scenarios of EVAL_SUITE each car integrates "
          "(above), same car and sensors; ratio to the default profile (target for "
          f"identified: <= 0.70); linear: all but {', '.join(FRICTION_LIMIT)}")
    columns = [("all", m) for m in methods] + [(g, methods[0]) for g in GROUPS if g != "all"]
    print(f"{'vehicle':>7s} {'seed':>4s} {'profile':44s} " + " ".join(
        f"{m + ' ' + g:>26s} {'ratio':>5s}" for g, m in columns))
    for vehicle, seed, name, rms in rows:
        base = next(r for v, s, n, r in rows if (v, s, n) == (vehicle, seed, "default"))
        print(f"{vehicle:7d} {seed:4d} {name:44s} " + " ".join(
            f"{rms[c]:26.3f} {rms[c] / base[c]:5.2f}" for c in columns))
    print(f"files: {folder}")


def _edit(calibration: dict | None, vehicle: dict):
    """A load_profile edit: the [calibration] table replaced (unless None), [vehicle] keys set."""

    def edit(doc):
        if calibration is not None:
            doc["calibration"] = calibration
        for key, value in vehicle.items():
            doc["vehicle"][key] = value

    return edit


def _calibration_table(truth: dict[str, tuple[float, ...]]) -> dict:
    """sensor_errors_as_calibration's values as a profile's [calibration] table (scalars for
    the one-number keys)."""
    return {k: (v[0] if len(v) == 1 else list(v)) for k, v in truth.items()}


#: what the single-track model of d_ekf consumes (slipd.estimators.righetti_lenzo2025.filters
#: .single_track): the dynamics depend on C/m, I_z/m and the CoG position, not on m itself
PARAMETER_ROWS = (
    ("mass [kg]", lambda v: v[Veh.MASS]),
    ("a = cog_to_front_axle [m]", lambda v: v[Veh.LF]),
    ("b = cog_to_rear_axle [m]", lambda v: v[Veh.LR]),
    ("a / (a + b)", lambda v: v[Veh.LF] / (v[Veh.LF] + v[Veh.LR])),
    ("yaw_inertia [kg m^2]", lambda v: v[Veh.YAW_INERTIA]),
    ("I_z / (m a b) [-]", lambda v: v[Veh.YAW_INERTIA] / (v[Veh.MASS] * v[Veh.LF] * v[Veh.LR])),
    ("C_f [N/rad]", lambda v: v[Veh.CORNERING_STIFFNESS_F]),
    ("C_r [N/rad]", lambda v: v[Veh.CORNERING_STIFFNESS_R]),
    ("C_f / m [m/s^2/rad]", lambda v: v[Veh.CORNERING_STIFFNESS_F] / v[Veh.MASS]),
    ("C_r / m [m/s^2/rad]", lambda v: v[Veh.CORNERING_STIFFNESS_R] / v[Veh.MASS]),
    ("understeer K_us [deg/g]", lambda v: _understeer_deg_per_g(v)),
    ("steering_ratio", lambda v: v[Veh.STEER_RATIO]),
    ("steering_ratio / wheelbase [1/m]", lambda v: v[Veh.STEER_RATIO] / (v[Veh.LF] + v[Veh.LR])),
    ("mu_nominal", lambda v: v[Veh.MU_NOMINAL]),
)


def _understeer_deg_per_g(v) -> float:
    """K_us = m / L (b / C_f - a / C_r) (Gillespie 1992, eq. 6-15) in deg per g."""
    m, a, b = v[Veh.MASS], v[Veh.LF], v[Veh.LR]
    cf, cr = v[Veh.CORNERING_STIFFNESS_F], v[Veh.CORNERING_STIFFNESS_R]
    return math.degrees(G * m / (a + b) * (b / cf - a / cr))


def _print_parameters(vehicle: int, default, identified) -> None:
    """The default, the identified and the plant's values of what d_ekf reads."""
    car = load_profile(write_car_profile(Path(tempfile.mkdtemp()) / "car.toml", vehicle, RATIO))
    print(f"  parameters (vehicle {vehicle}): {'default':>10s} {'identified':>10s} "
          f"{'plant':>10s}  ident/plant")
    for label, value in PARAMETER_ROWS:
        d, i, c = (float(value(p.vehicle)) for p in (default, identified, car))
        print(f"    {label:32s} {d:10.4g} {i:10.4g} {c:10.4g}  {i / c:+.3f}")


def load_toml(path: Path) -> dict:
    import tomllib

    return tomllib.loads(path.read_text(encoding="utf-8"))


def _print_mismatch(vehicle: int) -> None:
    """The default profile's values against the car's (the ones identify leaves alone too)."""
    from slipd.identify.truth import car_values

    doc = load_toml(Path(load_profile("default").path))
    line = []
    for key, true in car_values(vehicle).items():
        *tables, name = key.split(".")
        table = doc
        for t in tables:
            table = table[t]
        line.append(f"{name} {table[name]:.5g} vs {true:.5g} ({table[name] / true - 1:+.0%})")
    print(f"  default profile vs vehicle {vehicle}: " + "; ".join(line))


def _print_per_scenario(vehicle: int, seed: int, per_case: dict, method: str) -> None:
    names = list(per_case)
    print(f"  {method} beta RMS [deg] per scenario (vehicle {vehicle}, seed {seed}), profiles: "
          + "; ".join(f"[{k}] {n}" for k, n in enumerate(names)))
    print(f"    {'scenario':20s} " + " ".join(f"{f'[{k}]':>6s}" for k in range(len(names))))
    for case in per_case["default"]:
        print(f"    {case:20s} " + " ".join(
            f"{per_case[n][case][method].beta_rms_deg:6.3f}" for n in names))


if __name__ == "__main__":
    main()
