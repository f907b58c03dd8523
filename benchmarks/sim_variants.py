"""Sensor variants of the simulator: how large each one's effect is, and what it costs.

Every scenario (default: the suite without the 4000 s endurance drive) is integrated once and
sensed with the baseline and with every variant of slipd.sim.variants.VARIANTS on that same
plant output and seed (slipd.sim.core.sense). Per variant and channel it prints:

* ``effect``: RMS of (variant - baseline) over all messages: the variant's own effect (the
  same seed gives the same noise, so the difference is the effect alone);
* ``err base`` / ``err var``: RMS of the message against the truth at its sample time (ax, ay:
  the kinematic acceleration at the CoG; yaw rate; wheel speed RL; road-wheel steer), for the
  baseline and the variant, pooled over the scenarios;
* ``sense``: the sensor model's time with the variant over the baseline's, measured in this run
  (the plant's integration, shared, is printed once).

    .venv/bin/python -m benchmarks.sim_variants [--scenarios a,b] [--seed 0]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from slipd.channels import In
from slipd.profile import load_profile
from slipd.sim import SCENARIOS
from slipd.sim.core import run_plan, sense
from slipd.sim.variants import VARIANTS

#: (message, channel, truth column, unit scale, unit) compared against the truth.
CHANNELS = (
    ("IMU_ACCEL", In.AX, "ax", 1.0, "m/s^2"),
    ("IMU_ACCEL", In.AY, "ay", 1.0, "m/s^2"),
    ("IMU_ACCEL", In.AZ, None, 1.0, "m/s^2"),
    ("IMU_RATE", In.YAW_RATE, "yaw_rate", 180.0 / math.pi, "deg/s"),
    ("IMU_RATE", In.ROLL_RATE, "roll_rate", 180.0 / math.pi, "deg/s"),
    ("WHEEL_SPEEDS", In.WHEEL_SPEED_RL, "wheel_speed_rl", 1.0, "m/s"),
    ("STEERING", In.STEER, "steer", 180.0 / math.pi, "deg"),
)


def _at_samples(result, message: str, column: str) -> np.ndarray:
    """The truth column at the message's sample instants (its grid points)."""
    n_msg = len(result.sensors[message].t)
    stride = max(1, len(result.truth["t"]) // max(1, n_msg))
    return result.truth[column][::stride][:n_msg]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenarios", default=None,
                        help="comma-separated scenarios (default: all but endurance)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    names = (args.scenarios.split(",") if args.scenarios
             else [n for n in SCENARIOS if SCENARIOS[n].duration < 1000])
    profile = load_profile("default")
    specs = [None, *VARIANTS]
    sq = {(v, c[1]): [0.0, 0.0, 0.0, 0] for v in specs for c in CHANNELS}  # effect, base, var
    sense_time = dict.fromkeys(specs, 0.0)
    plant_time = simulated = 0.0
    for scenario in names:
        started = time.perf_counter()
        plant = run_plan(scenario, 2)
        plant_time += time.perf_counter() - started
        results = {}
        for spec in specs:
            started = time.perf_counter()
            results[spec] = sense(scenario, plant, 2, args.seed, profile, None, spec)
            sense_time[spec] += time.perf_counter() - started
        base = results[None]
        simulated += base.duration
        for spec in specs:
            res = results[spec]
            for message, channel, column, scale, _ in CHANNELS:
                var = res.sensors[message].values[channel] * scale
                ref = base.sensors[message].values[channel] * scale
                acc = sq[spec, channel]
                acc[0] += float(np.sum((var - ref) ** 2))
                if column is not None:
                    truth = _at_samples(res, message, column) * scale
                    acc[1] += float(np.sum((ref - truth) ** 2))
                    acc[2] += float(np.sum((var - truth) ** 2))
                acc[3] += len(var)
    print(f"scenarios: {', '.join(names)} ({simulated:.0f} s simulated, seed {args.seed})")
    print(f"plant integration (shared by all sensor sets): {plant_time:.1f} s; "
          f"baseline sensor model: {sense_time[None]:.2f} s")
    print(f"{'variant':15s} {'channel':11s} {'unit':6s} {'effect':>8s} {'err base':>9s} "
          f"{'err var':>8s}  sense")
    for spec in VARIANTS:
        ratio = sense_time[spec] / sense_time[None]
        for _, channel, column, _, unit in CHANNELS:
            effect, err_base, err_var, n = sq[spec, channel]
            if effect == 0.0:
                continue
            errors = (f"{math.sqrt(err_base / n):9.4f} {math.sqrt(err_var / n):8.4f}"
                      if column is not None else f"{'-':>9s} {'-':>8s}")
            print(f"{spec:15s} {channel.name:11s} {unit:6s} {math.sqrt(effect / n):8.4f} "
                  f"{errors}  {ratio:4.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
