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

    .venv/bin/python -m benchmarks.identify [--vehicles 1,3] [--seeds 1,2] [--duration 900]
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
from slipd.sim.writer import write_log, write_truth_csv

WRONG = {"vehicle.steering_ratio": 1.15, "vehicle.tyre.cornering_stiffness_front": 0.7,
         "vehicle.tyre.cornering_stiffness_rear": 1.3, "vehicle.roll_stiffness": 1.5,
         "vehicle.yaw_inertia": 1.3}
VARIANT = "misalignment,steer_offset"
SENSOR = {"wheel_radius_bias": (0.01, -0.005, 0.0, 0.008)}
RATIO = 16.0
EVAL_SCENARIO = "handling_high_mu"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", default="1,3")
    parser.add_argument("--seeds", default="1,2")
    parser.add_argument("--duration", type=float, default=900.0)
    parser.add_argument("--no-eval", action="store_true")
    args = parser.parse_args()
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


if __name__ == "__main__":
    main()
