"""slipd identify on simulated drives with known truth: identified value, 95 % interval and
the truth per quantity, for several vehicles and sensor seeds, starting from a wrong profile.

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
identified ``[calibration]``, the identified profile, and the car's own parameters (mass,
geometry, inertias: what identify does not estimate) with the identified ``[calibration]``;
each as a ratio to the default profile.

    .venv/bin/python -m benchmarks.identify [--vehicles 1,3] [--seeds 1,2] [--duration 900]
        [--start wrong|default] [--sensors faulty|nominal] [--jobs 2]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from slipd.identify import identify
from slipd.identify.profile_text import write_profile
from slipd.identify.truth import check_table, compare, truth_of, write_car_profile
from slipd.profile import load_profile
from slipd.sim.core import run_plan, sense
from slipd.sim.plant import SimulationError
from slipd.sim.scenarios import SCENARIOS
from slipd.sim.writer import write_log, write_truth_csv

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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", default="1,3")
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
            cases = []
            for name in eval_plants:
                sensed = sense(name, eval_plants[name], vehicle, seed, default, sensor, variant)
                case_log = folder / f"v{vehicle}_s{seed}_{name}.log"
                case_truth = folder / f"v{vehicle}_s{seed}_{name}.truth.csv"
                write_log(case_log, sensed, default)
                write_truth_csv(case_truth, sensed)
                cases.append(LogCase(name, case_log, case_truth))
            calibration = load_toml(identified).get("calibration", {})

            def with_calibration(doc, calibration=calibration):
                doc["calibration"] = calibration

            profiles = {
                "default": default,
                "default + identified [calibration]": load_profile("default",
                                                                   edit=with_calibration),
                "identified": load_profile(identified),
                "car's own values + identified [calibration]": load_profile(
                    right, edit=with_calibration),
            }
            per_case = {}
            for name, profile in profiles.items():
                report, _, _ = evaluate_logs(cases, methods, profile, name=name)
                rows.append((vehicle, seed, name,
                             {m: s.beta_rms_deg for m, s in report.overall().items()}))
                per_case[name] = report.logs
            _print_per_scenario(vehicle, seed, per_case, methods)
    print("\nbeta RMS [deg], pooled over the scenarios of EVAL_SUITE each car integrates "
          "(above), same car and sensors; ratio to the default profile (target for "
          "identified: <= 0.70)")
    print(f"{'vehicle':>7s} {'seed':>4s} {'profile':44s} " + " ".join(
        f"{m + ' RMS':>22s} {'ratio':>6s}" for m in methods))
    for vehicle, seed, name, rms in rows:
        base = next(r for v, s, n, r in rows if (v, s, n) == (vehicle, seed, "default"))
        print(f"{vehicle:7d} {seed:4d} {name:44s} " + " ".join(
            f"{rms[m]:22.3f} {rms[m] / base[m]:6.2f}" for m in methods))
    print(f"files: {folder}")


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


def _print_per_scenario(vehicle: int, seed: int, per_case: dict, methods: list[str]) -> None:
    print(f"  beta RMS [deg] per scenario (vehicle {vehicle}, seed {seed}): default -> "
          "identified (ratio)")
    for case, before in per_case["default"].items():
        after = per_case["identified"][case]
        print(f"    {case:20s} " + "  ".join(
            f"{m} {before[m].beta_rms_deg:.3f} -> {after[m].beta_rms_deg:.3f} "
            f"({after[m].beta_rms_deg / before[m].beta_rms_deg:.2f})" for m in methods))


if __name__ == "__main__":
    main()
