"""Numba runtime (NRT) allocation counts of estimators over given inputs, for the tests that
check a step allocates nothing.

The counters exist only when NUMBA_NRT_STATS=1 is set before numba is imported, so the count
runs in a child process; the inputs go there as .npy files.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from slipd.channels import U_LEN, VALID, WHEEL_SPEEDS, In

REPO = Path(__file__).resolve().parents[1]

_CHILD = """
import json, sys
import numpy as np
from numba.core.registry import cpu_target
from numba.core.runtime import rtsys
from slipd.channels import N_OUT
from slipd.estimators import registry

U = np.load(sys.argv[1])
vehicle = np.load(sys.argv[2])
OUT = np.zeros((U.shape[0], N_OUT))
# kernels loaded from the cache do not start the NRT; start it so its counters run
rtsys.initialize(cpu_target.target_context)
counts = {}
for name in sys.argv[3:]:
    method = registry.load(name)
    state = method.init(vehicle)

    def allocations(a, b):
        before = rtsys.get_allocation_stats()
        method.run_ticks(state, U[a:b], method.params, vehicle, 0.01, OUT[a:b])
        return rtsys.get_allocation_stats().alloc - before.alloc

    allocations(0, 10)  # load / compile
    counts[name] = [allocations(10, 20), allocations(20, U.shape[0])]
print(json.dumps(counts))
"""


def allocations(names: list[str], U: np.ndarray, vehicle: np.ndarray) -> dict[str, list[int]]:
    """{name: [allocations over 10 ticks, allocations over the remaining len(U) - 20 ticks]}
    after 10 ticks of warm-up; a step that allocates nothing gives two equal numbers (whatever
    the call itself costs)."""
    env = dict(os.environ, NUMBA_NRT_STATS="1")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    with tempfile.TemporaryDirectory() as tmp:
        u_path, vehicle_path = Path(tmp) / "U.npy", Path(tmp) / "vehicle.npy"
        np.save(u_path, np.ascontiguousarray(U, dtype=np.float64))
        np.save(vehicle_path, np.asarray(vehicle, dtype=np.float64))
        result = subprocess.run(
            [sys.executable, "-c", _CHILD, str(u_path), str(vehicle_path), *names],
            env=env, capture_output=True, text=True, timeout=600, cwd=REPO,
        )  # fmt: skip
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


def sine_drive_inputs(n: int, steer: float, yaw_rate: float, ay: float) -> np.ndarray:
    """A sine drive at 20 m/s with every core channel valid, and two gaps that take the
    fallback paths (ay invalid; all IMU and wheel channels invalid)."""
    t = np.arange(n) * 0.01
    U = np.zeros((n, U_LEN))
    U[:, In.STEER] = steer * np.sin(t)
    U[:, In.YAW_RATE] = yaw_rate * np.sin(t)
    U[:, In.AY] = ay * np.sin(t)
    U[:, In.ROLL_RATE] = 0.01 * np.cos(t)
    for ch in WHEEL_SPEEDS:
        U[:, ch] = 20.0
    for ch in (In.AX, In.AY, In.YAW_RATE, In.ROLL_RATE, In.PITCH_RATE, In.STEER, *WHEEL_SPEEDS):
        U[:, VALID + ch] = 1.0
    U[2000:2100, VALID + In.AY] = 0.0
    U[3000:3050, VALID : VALID + 12] = 0.0
    return U
