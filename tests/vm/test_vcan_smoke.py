"""Smoke tests of real SocketCAN in a qemu VM: vcan, can-utils, python-can with kernel RX
filters, and numba code compiled on the host loaded from its cache in the guest.

One boot serves the whole module: the host writes the probe programs into the run directory
and builds the numba cache there, the guest runs GUEST_SCRIPT (each ``step`` is recorded in
``$VM_OUT/steps``, the probes write JSON to ``$VM_OUT``), and the tests assert on those files
after the VM has powered off.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from . import harness

pytestmark = pytest.mark.vm

#: The numba target both sides compile for / look up in the cache: the host's CPU name would
#: not match the guest's emulated CPU, so the cache would miss and the guest would recompile.
NUMBA_ENV = {"NUMBA_CPU_NAME": "generic", "NUMBA_DEBUG_CACHE": "1"}

# The frames cansend puts on the buses and candump -L must log, in candump's notation.
CANSEND_FRAMES = (
    ("vcan0", "123#DEADBEEF"),
    ("vcan0", "1F334455#1122334455667788"),
    ("vcan1", "7FF#00"),
    ("vcan1", "321#R"),
)

# Runs in the guest after harness.PRELUDE (step, wait_can_receivers). No `set -e`: every step
# records its own status, so one failure does not hide the others.
GUEST_SCRIPT = r"""
O="$VM_OUT"
uname -r >"$O/uname.txt"
step modprobe modprobe vcan
step links bash -c '
    for dev in vcan0 vcan1; do
        ip link add dev $dev type vcan && ip link set up $dev || exit 1
    done
    ip -details link show type vcan'

# can-utils: candump both interfaces, wait until the kernel has its sockets, then cansend.
timeout 60 candump -L -n 4 vcan0 vcan1 >"$O/candump.log" 2>"$O/candump.err" &
dump=$!
step candump_ready eval 'wait_can_receivers vcan0 1 && wait_can_receivers vcan1 1'
step cansend bash -c '__CANSEND__'
wait $dump
echo $? >"$O/candump.rc"

# python-can (project venv) with kernel RX filters; then numba from the host-built cache.
step python_can python "$VM_RUN_DIR/probe_python_can.py" "$O/python_can.json"
step numba python "$VM_RUN_DIR/probe_numba.py" "$O/numba.json"
lsmod >"$O/lsmod.txt"
"""
GUEST_SCRIPT = GUEST_SCRIPT.replace(
    "__CANSEND__", " && ".join(f"cansend {dev} {frame}" for dev, frame in CANSEND_FRAMES)
)

# Runs in the guest with the project's python: python-can's socketcan interface, kernel filters.
PROBE_PYTHON_CAN = r'''
"""Send on vcan0 through python-can and receive through a kernel RX filter; JSON to argv[1]."""
import json
import socket
import struct
import sys
import time

t0 = time.perf_counter()
import can

t_import = time.perf_counter() - t0
FILTER = [{"can_id": 0x123, "can_mask": 0x7FF, "extended": False}]
# (id, extended, data): only the standard-ID 0x123 frames match FILTER
SENT = [
    (0x124, False, b"\x01"),  # another ID
    (0x123, True, b"\x02"),  # same low bits, but an extended ID
    (0x523, False, b"\x03"),  # another ID (0x523 & 0x7FF != 0x123)
    (0x123, False, b"\x04\x05"),
    (0x123, False, b"\x06"),
]


def drain_bus(bus):
    got = []
    while (msg := bus.recv(timeout=1.0)) is not None:
        got.append(msg)
    return got


def drain_socket(sock):
    # Straight from the kernel, bypassing python-can: proves the kernel did the filtering.
    sock.settimeout(1.0)
    got = []
    try:
        while True:
            frame = sock.recv(16)
            can_id, dlc = struct.unpack_from("=IB", frame)
            got.append([can_id, frame[8 : 8 + dlc].hex()])
    except TimeoutError:
        return got


out = {"python_can_version": can.__version__, "import_seconds": t_import}
filtered = can.Bus(interface="socketcan", channel="vcan0", can_filters=FILTER)
filtered_raw = can.Bus(interface="socketcan", channel="vcan0", can_filters=FILTER)
monitor = can.Bus(interface="socketcan", channel="vcan0")
sender = can.Bus(interface="socketcan", channel="vcan0")
try:
    raw = filtered.socket.getsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER, 64)
    out["kernel_filter"] = [list(struct.unpack_from("=II", raw, i)) for i in range(0, len(raw), 8)]
    out["rcvlists"] = {}
    for name in ("rcvlist_all", "rcvlist_fil", "rcvlist_sff", "rcvlist_eff"):
        with open(f"/proc/net/can/{name}") as f:
            out["rcvlists"][name] = f.read()
    for can_id, extended, data in SENT:
        sender.send(can.Message(arbitration_id=can_id, is_extended_id=extended, data=data))
    out["sent_at"] = time.time()
    msgs = drain_bus(filtered)
    out["filtered"] = [[m.arbitration_id, m.is_extended_id, m.data.hex()] for m in msgs]
    out["filtered_timestamps"] = [m.timestamp for m in msgs]
    out["filtered_raw_socket"] = drain_socket(filtered_raw.socket)
    out["monitor"] = [[m.arbitration_id, m.is_extended_id, m.data.hex()]
                      for m in drain_bus(monitor)]
    out["sender_own"] = len(drain_bus(sender))
finally:
    for bus in (filtered, filtered_raw, monitor, sender):
        bus.shutdown()
with open(sys.argv[1], "w") as f:
    json.dump(out, f, indent=1)
'''

# Runs on the host (builds the cache) and then in the guest (must load it): same code, same env.
PROBE_NUMBA = r'''
"""Run slipd.estimators.zero.run_ticks and report numba's cache statistics; JSON to argv[1]."""
import json
import sys
import time

t0 = time.perf_counter()
import numba
import numpy as np
from numba.core import config

from slipd.channels import N_OUT, N_VEH, U_LEN, VALID, In, Out
from slipd.estimators import registry, zero

t_import = time.perf_counter() - t0
n = 64
U = np.zeros((n, U_LEN))
U[:, In.WHEEL_SPEED_RL] = np.linspace(10.0, 20.0, n)
U[:, In.WHEEL_SPEED_RR] = U[:, In.WHEEL_SPEED_RL] + 1.0
U[:, VALID + In.WHEEL_SPEED_RL] = 1.0
U[:, VALID + In.WHEEL_SPEED_RR] = 1.0
U[n // 2 :, VALID + In.WHEEL_SPEED_RR] = 0.0  # second half: an input times out
OUT = np.full((n, N_OUT), np.nan)
params = registry.make_params(zero)
state = zero.init(params, np.zeros(N_VEH))
t1 = time.perf_counter()
zero.run_ticks(state, U, params, np.zeros(N_VEH), 0.01, OUT)
t_first_call = time.perf_counter() - t1
stats = zero.run_ticks.stats
both = U[:, VALID + In.WHEEL_SPEED_RR] > 0.5  # else the one valid rear wheel
expected_vx = np.where(both, 0.5 * (U[:, In.WHEEL_SPEED_RL] + U[:, In.WHEEL_SPEED_RR]),
                       U[:, In.WHEEL_SPEED_RL])
out = {
    "numba_version": numba.__version__,
    "cpu_name": config.CPU_NAME,
    "cpu_features": config.CPU_FEATURES,
    "cache_dir": config.CACHE_DIR,
    "cache_path": stats.cache_path,
    "cache_hits": {str(k): v for k, v in stats.cache_hits.items()},
    "cache_misses": {str(k): v for k, v in stats.cache_misses.items()},
    "signatures": [str(s) for s in zero.run_ticks.signatures],
    "vx_max_error": float(np.max(np.abs(OUT[:, Out.VX] - expected_vx))),
    "beta_max_abs": float(np.max(np.abs(OUT[:, Out.BETA]))),
    "status": sorted(set(OUT[:, Out.STATUS].tolist())),
    "status_first_half": sorted(set(OUT[: n // 2, Out.STATUS].tolist())),
    "import_seconds": t_import,
    "first_call_seconds": t_first_call,
}
with open(sys.argv[1], "w") as f:
    json.dump(out, f, indent=1)
'''


@dataclass(frozen=True)
class Smoke:
    vm: harness.VmResult
    kernel_version: str
    host_numba: dict
    host_numba_seconds: float
    cache_before: dict[str, tuple[int, int]]
    cache_after: dict[str, tuple[int, int]]


def snapshot(directory: Path) -> dict[str, tuple[int, int]]:
    """{relative path: (size, mtime_ns)} of every file under ``directory``."""
    return {
        p.relative_to(directory).as_posix(): (p.stat().st_size, p.stat().st_mtime_ns)
        for p in sorted(directory.rglob("*"))
        if p.is_file()
    }


def probe_env(run_dir: Path) -> dict[str, str]:
    """Environment of the probes, identical on host and guest."""
    return {
        **NUMBA_ENV,
        "NUMBA_CACHE_DIR": str(run_dir / "numba-cache"),
        "PYTHONPATH": str(harness.ROOT),
    }


@pytest.fixture(scope="module")
def smoke(vm_config, vm_boot, vm_run_dir) -> Smoke:
    run_dir = vm_run_dir("vcan-smoke")
    (run_dir / "probe_python_can.py").write_text(PROBE_PYTHON_CAN)
    (run_dir / "probe_numba.py").write_text(PROBE_NUMBA)
    env = probe_env(run_dir)

    # Host: compile into the shared cache (a fresh one, so this must be a miss and a save).
    host_json = run_dir / "host_numba.json"
    started = time.monotonic()
    host = subprocess.run(
        [sys.executable, str(run_dir / "probe_numba.py"), str(host_json)],
        env={**os.environ, **env},
        cwd=harness.ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    host_seconds = time.monotonic() - started
    assert host.returncode == 0, f"host numba probe failed:\n{host.stdout}\n{host.stderr}"
    host_numba = json.loads(host_json.read_text())
    cache_before = snapshot(run_dir / "numba-cache")

    vm = vm_boot("vcan-smoke", GUEST_SCRIPT, run_dir, env=env)
    assert vm.exit_code is not None, f"the guest script did not finish:\n{vm.describe()}"
    return Smoke(
        vm=vm,
        kernel_version=vm_config.kernel_version,
        host_numba=host_numba,
        host_numba_seconds=host_seconds,
        cache_before=cache_before,
        cache_after=snapshot(run_dir / "numba-cache"),
    )


def assert_step(smoke: Smoke, name: str) -> str:
    """Assert that guest step ``name`` exited 0; return its output."""
    step = smoke.vm.step(name)
    assert step.returncode == 0, (
        f"guest step {name!r} exited {step.returncode}:\n{step.output}\n{smoke.vm.describe()}"
    )
    return step.output


def test_guest_runs_the_debian_kernel_and_the_script_completes(smoke: Smoke) -> None:
    vm = smoke.vm
    assert vm.exit_code == 0, vm.describe()
    assert not vm.timed_out
    assert vm.read("uname.txt").strip() == smoke.kernel_version
    assert vm.boot_seconds is not None and vm.boot_seconds > 0


def test_vcan_module_loads_and_interfaces_come_up(smoke: Smoke) -> None:
    assert_step(smoke, "modprobe")
    links = assert_step(smoke, "links")
    for dev in ("vcan0", "vcan1"):
        block = re.search(rf"^\d+: {dev}: <([^>]*)>.*?(?=^\d+: |\Z)", links, re.M | re.S)
        assert block, f"{dev} missing from `ip link`:\n{links}"
        assert "UP" in block.group(1).split(","), block.group(0)
        assert "vcan" in block.group(0)
    lsmod = smoke.vm.read("lsmod.txt")
    for module in ("vcan", "can_raw", "can"):
        assert re.search(rf"^{module}\s", lsmod, re.M), f"{module} not loaded:\n{lsmod}"


def test_candump_logs_what_cansend_sent_on_each_interface(smoke: Smoke) -> None:
    assert_step(smoke, "candump_ready")
    assert_step(smoke, "cansend")
    log = smoke.vm.read("candump.log")
    rc = smoke.vm.read("candump.rc").strip()
    assert rc == "0", (
        f"candump exited {rc} (124: timed out waiting for frames)\n{log}\n"
        + smoke.vm.read("candump.err")
    )
    lines = [line.split() for line in log.splitlines() if line.strip()]
    # candump -L: "(seconds.micros) iface frame"
    assert all(len(parts) == 3 for parts in lines), log
    logged = [(iface, frame) for _, iface, frame in lines]
    assert sorted(logged) == sorted(CANSEND_FRAMES), log
    for dev in ("vcan0", "vcan1"):  # per interface the order is kept
        assert [f for i, f in logged if i == dev] == [f for i, f in CANSEND_FRAMES if i == dev]
    # kernel receive timestamps on CLOCK_REALTIME: close to the host's wall clock
    stamps = [float(ts.strip("()")) for ts, _, _ in lines]
    assert all(abs(ts - time.time()) < 3600 for ts in stamps), stamps


def test_python_can_kernel_filter_drops_non_matching_frames(smoke: Smoke) -> None:
    assert_step(smoke, "python_can")
    result = json.loads(smoke.vm.read("python_can.json"))
    can_eff_flag = 0x80000000
    # the kernel holds the filter: read back from the socket and listed in /proc/net/can
    assert result["kernel_filter"] == [[0x123, 0x7FF | can_eff_flag]]
    assert re.search(
        r"^\s+vcan0\s+0*123\s+0*800007ff\s", result["rcvlists"]["rcvlist_fil"], re.M | re.I
    ), result["rcvlists"]
    wanted = [[0x123, False, "0405"], [0x123, False, "06"]]
    assert result["filtered"] == wanted
    # what the kernel delivered to a filtered socket, read without python-can in between
    assert result["filtered_raw_socket"] == [[0x123, "0405"], [0x123, "06"]]
    # all five frames were on the bus: the filter, not a lost send, dropped three
    assert result["monitor"] == [
        [0x124, False, "01"],
        [0x123, True, "02"],
        [0x523, False, "03"],
        [0x123, False, "0405"],
        [0x123, False, "06"],
    ]
    assert result["sender_own"] == 0  # no own messages unless asked for (receive_own_messages)
    # python-can timestamps are the kernel's receive times (CLOCK_REALTIME)
    for ts in result["filtered_timestamps"]:
        assert -5.0 < result["sent_at"] - ts < 5.0, (result["sent_at"], ts)


def test_numba_cache_built_on_host_is_loaded_in_guest(smoke: Smoke) -> None:
    host = smoke.host_numba
    # host: the fresh cache missed once, compiled for the portable target and saved
    assert host["cpu_name"] == "generic" and host["cpu_features"] == ""
    assert sum(host["cache_misses"].values()) == 1 and not host["cache_hits"], host
    assert any(name.endswith(".nbi") for name in smoke.cache_before), smoke.cache_before
    assert any(name.endswith(".nbc") for name in smoke.cache_before), smoke.cache_before

    assert_step(smoke, "numba")
    guest = json.loads(smoke.vm.read("numba.json"))
    assert guest["cpu_name"] == "generic" and guest["numba_version"] == host["numba_version"]
    assert guest["cache_path"] == host["cache_path"]
    assert sum(guest["cache_hits"].values()) >= 1, guest
    assert not guest["cache_misses"], f"guest recompiled: {guest}"
    assert guest["signatures"] == host["signatures"]
    # nothing compiled means nothing saved: the cache files are untouched
    assert smoke.cache_after == smoke.cache_before
    debug = smoke.vm.step("numba").output
    assert "data loaded from" in debug and "data saved to" not in debug, debug
    # and the loaded code computes what it should
    for side in (host, guest):
        assert side["vx_max_error"] < 1e-12 and side["beta_max_abs"] == 0.0
        assert side["status_first_half"] == [0.0] and side["status"] == [0.0, 4.0]
