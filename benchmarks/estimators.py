"""Per-tick cost of every registered estimator, on the latched inputs of a simulated drive.

Two figures per method:

* ``batch``: ``run_ticks`` over the whole drive divided by the number of ticks: the method's
  own work (replay and eval run this way);
* ``call``: ``step`` called once per tick from Python, as the daemon does: the work plus
  numba's dispatch of the call (type checks, array unboxing), measured per call; median and
  p99 over the drive.

The baseline, measured in the same run, is ``zero`` (beta = 0): its ``call`` figure is the
dispatch floor every method pays in the daemon. Target (issue): each method's median step
<= 2 us; an ensemble of all methods <= 10 us.

    .venv/bin/python -m benchmarks.estimators [--scenario handling_high_mu] [--methods a,b]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from slipd.channels import N_OUT
from slipd.estimators import registry
from slipd.pipeline import TICK_DT
from slipd.profile import load_profile

TARGET_US = 2.0
ENSEMBLE_TARGET_US = 10.0


def drive_inputs(scenario: str) -> np.ndarray:
    from slipd.sim import simulate

    return np.ascontiguousarray(simulate(scenario).ticks())


def measure(name: str, U: np.ndarray, vehicle: np.ndarray, repeats: int) -> dict:
    method = registry.load(name)
    n = len(U)
    out = np.zeros((n, N_OUT))
    state = method.init(vehicle)
    method.run_ticks(state, U[:10], method.params, vehicle, TICK_DT, out[:10])  # load/compile
    batch = []
    for _ in range(repeats):
        state = method.init(vehicle)
        started = time.perf_counter()
        method.run_ticks(state, U, method.params, vehicle, TICK_DT, out)
        batch.append((time.perf_counter() - started) / n)
    step, params = method.step, method.params
    state = method.init(vehicle)
    row = np.zeros(N_OUT)
    step(state, U[0], params, vehicle, TICK_DT, row)
    per_call = np.empty(n)
    clock = time.perf_counter_ns
    for k in range(n):
        u = U[k]
        started = clock()
        step(state, u, params, vehicle, TICK_DT, row)
        per_call[k] = clock() - started
    timer = np.empty(1000)
    for k in range(1000):  # the cost of reading the clock twice, subtracted from each call
        started = clock()
        timer[k] = clock() - started
    per_call = (per_call - np.median(timer)) / 1e3
    return {"method": name, "batch_us": min(batch) * 1e6, "call_p50_us": np.median(per_call),
            "call_p99_us": np.percentile(per_call, 99), "ticks": n}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="handling_high_mu")
    parser.add_argument("--methods", help="comma-separated (default: every registered method)")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    vehicle = load_profile("default").vehicle
    U = drive_inputs(args.scenario)
    names = args.methods.split(",") if args.methods else registry.available()
    if "zero" in names:
        names.remove("zero")
    names.insert(0, "zero")
    print(f"{len(U)} ticks of {args.scenario}; per-tick cost in us (batch = run_ticks / ticks;"
          " call = one step() from Python, as the daemon calls it)")
    print(f"{'method':<24}{'batch':>8}{'call p50':>10}{'call p99':>10}"
          f"{'p50 - zero':>12}  target <= {TARGET_US:g} us (median)")
    results = [measure(name, U, vehicle, args.repeats) for name in names]
    floor = results[0]["call_p50_us"]
    for r in results:
        target = ENSEMBLE_TARGET_US if r["method"] == "ensemble" else TARGET_US
        verdict = "ok" if r["call_p50_us"] <= target else "OVER"
        print(f"{r['method']:<24}{r['batch_us']:>8.2f}{r['call_p50_us']:>10.2f}"
              f"{r['call_p99_us']:>10.2f}{r['call_p50_us'] - floor:>12.2f}  {verdict}")
    if "ensemble" in names:
        ensemble = next(r for r in results if r["method"] == "ensemble")
        verdict = "ok" if ensemble["call_p50_us"] <= ENSEMBLE_TARGET_US else "OVER"
        print(f"ensemble median step {ensemble['call_p50_us']:.2f} us: {verdict} "
              f"(<= {ENSEMBLE_TARGET_US:g} us)")
    total = sum(r["call_p50_us"] for r in results)
    print(f"all methods called one after the other: {total:.1f} us per tick "
          f"({100 * total * 1e-6 / TICK_DT:.3f} % of the 10 ms tick)")


if __name__ == "__main__":
    main()
