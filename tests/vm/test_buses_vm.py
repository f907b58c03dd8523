"""Production buses on real SocketCAN (vcan in a qemu VM): the Hyundai CAN FD profile on an FD
vcan (canfd_frame in and out), and a two-bus profile on two vcans with its outputs on their
configured IDs and bus. One boot, both daemons at once (each Python start costs minutes under
TCG); can-utils play the drives and log the buses; the host checks the logs and the stats.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from slipd.codec import Codec
from slipd.profile import PROFILE_DIR, load_profile
from slipd.replay.candump import FLAG_FD, read_candump, write_candump

from . import harness
from .test_daemon_vm import GUEST_RATE_HZ, GUEST_TIMEOUT, STATS_PY

pytestmark = pytest.mark.vm

ESTIMATOR = "zero"
OUTPUT_IDS = (0x700, 0x701, 0x702)

GUEST_SCRIPT = r"""
O="$VM_OUT"; R="$VM_RUN_DIR"
mkdir -p /tmp/numba-cache && cp -r "$NUMBA_CACHE_DIR" /tmp/numba-cache/ &&
    export NUMBA_CACHE_DIR="/tmp/numba-cache/$(basename "$NUMBA_CACHE_DIR")"
wait_line() {  # wait_line FILE PATTERN SECONDS PID
    local deadline=$(( $(date +%s) + $3 ))
    until grep -q "$2" "$1" 2>/dev/null; do
        kill -0 "$4" 2>/dev/null || { echo "process $4 exited"; return 1; }
        [ "$(date +%s)" -ge "$deadline" ] && { echo "timed out"; return 1; }
        sleep 0.2
    done
}
step modprobe modprobe vcan
step links bash -c 'ip link add dev vcan0 type vcan && ip link set vcan0 mtu 72 &&
    ip link set up vcan0 && for d in vcan1 vcan2; do ip link add dev $d type vcan &&
    ip link set up $d; done'
slipd run -i socketcan -c vcan0 --profile "$R/fd.toml" --estimator __ESTIMATOR__ \
    --recorder "$O/fd_recorder.log" --stats-socket /tmp/fd.sock >"$O/fd.out" 2>&1 &
FD=$!
slipd run -i socketcan --bus chassis=vcan1 --bus pt=vcan2 --profile "$R/two.toml" \
    --estimator __ESTIMATOR__ --stats-socket /tmp/two.sock >"$O/two.out" 2>&1 &
TWO=$!
step fd_ready wait_line "$O/fd.out" "warm-up" 900 $FD
step two_ready wait_line "$O/two.out" "warm-up" 900 $TWO
sleep 1
cat /proc/net/can/rcvlist_fil >"$O/rcvlist_fil.txt"
for d in vcan0 vcan1 vcan2; do candump -L $d >"$O/$d.log" 2>>"$O/candump.err" & done
sleep 1
step play_fd canplayer -I "$R/fd_drive.log" vcan0=can0
step play_two canplayer -I "$R/two_drive.log" vcan1=chassis vcan2=pt
step stats_fd python "$R/stats.py" /tmp/fd.sock "$O/stats_fd.json" __N_FD__ 2
step stats_two python "$R/stats.py" /tmp/two.sock "$O/stats_two.json" __N_TWO__ 2
kill -TERM $FD $TWO
wait $FD; echo $? >"$O/fd.rc"
wait $TWO; echo $? >"$O/two.rc"
sleep 0.5
pkill candump
"""


def _guest(text: str, dbc: Path, name: str) -> str:
    text = re.sub(r"(?m)^timeout = [0-9.]+\n", "", text)
    text = re.sub(r"(?m)^rate_hz = [0-9.]+", f"rate_hz = {GUEST_RATE_HZ}\ntimeout = "
                  f"{GUEST_TIMEOUT}", text)
    text = re.sub(r'(?m)^dbc = "[^"]+"', f'dbc = "{dbc}"', text)
    return re.sub(r'(?m)^name = "[^"]+"', f'name = "{name}"', text, count=1)


def prepare(run_dir: Path) -> dict:
    from test_buses import two_bus_profile  # tests/ is on sys.path (pytest's rootdir rule)

    from slipd.sim import simulate
    from slipd.sim.writer import encode_frames, write_log

    hyundai = load_profile("hyundai_ioniq_5")
    (run_dir / "fd.toml").write_text(_guest(hyundai.path.read_text(), hyundai.dbc_path, "fd"))
    fd = load_profile(run_dir / "fd.toml")
    n_fd = write_log(run_dir / "fd_drive.log", simulate("step_steer", duration=6.0,
                                                        profile=fd), fd)
    (run_dir / "src").mkdir(exist_ok=True)
    two_src = two_bus_profile(run_dir / "src", outputs='bus = "pt"\nstate_id = 0x700\n'
                              "aux_id = 0x701\ndiag_id = 0x702\n")
    (run_dir / "two.toml").write_text(_guest(two_src.read_text(), PROFILE_DIR / "slipd.dbc",
                                             "two"))
    two = load_profile(run_dir / "two.toml")
    t, ids, data, dlc = encode_frames(simulate("step_steer", duration=6.0, profile=two), two)
    plan = Codec(two).inputs
    bus_of = {plan.frame_id(n): plan.buses.index(plan.bus(n)) for n in plan.message_names}
    channel = np.array([bus_of[int(i)] for i in ids], dtype=np.uint8)
    write_candump(run_dir / "two_drive.log", t, ids, data, dlc, channel=channel,
                  channels=list(plan.buses))
    (run_dir / "stats.py").write_text(STATS_PY)
    return {"fd": fd, "two": two, "n_fd": n_fd, "n_two": len(t)}


@pytest.fixture(scope="module")
def story(vm_config, vm_boot, vm_run_dir):
    run_dir = vm_run_dir("buses")
    prepared = prepare(run_dir)
    env = {"NUMBA_CPU_NAME": "generic", "PYTHONUNBUFFERED": "1",
           "NUMBA_CACHE_DIR": os.environ.get("NUMBA_CACHE_DIR",
                                             str(harness.ROOT / ".numba_cache"))}
    buses = {"fd.toml": ["-c", "vm-warm"],
             "two.toml": ["--bus", "chassis=vm-warm-a", "--bus", "pt=vm-warm-b"]}
    for name, where in buses.items():  # every kernel the guest's daemons run, in the cache
        warm = subprocess.run(
            [sys.executable, "-m", "slipd.cli", "run", "-i", "virtual", *where, "--profile",
             str(run_dir / name), "--estimator", ESTIMATOR, "--duration", "0.2"],
            env={**os.environ, **env}, cwd=harness.ROOT, capture_output=True, text=True,
            timeout=600)
        assert warm.returncode == 0, warm.stdout + warm.stderr
    script = GUEST_SCRIPT
    for key, value in (("__ESTIMATOR__", ESTIMATOR), ("__N_FD__", str(prepared["n_fd"])),
                       ("__N_TWO__", str(prepared["n_two"]))):
        script = script.replace(key, value)
    vm = vm_boot("buses", script, run_dir, env=env, timeout=1500)
    assert vm.exit_code is not None, f"the guest script did not finish:\n{vm.describe()}"
    return vm, prepared


def _ok(vm, name: str) -> str:
    step = vm.step(name)
    assert step.returncode == 0, (f"guest step {name!r} exited {step.returncode}:\n"
                                  f"{step.output}\n--- fd.out ---\n{vm.read('fd.out')[-2000:]}"
                                  f"\n--- two.out ---\n{vm.read('two.out')[-2000:]}\n"
                                  f"{vm.describe()}")
    return step.output


def test_hyundai_canfd_profile_decodes_fd_frames_on_an_fd_vcan(story):
    vm, prepared = story
    _ok(vm, "fd_ready")
    stats = json.loads(vm.read("stats_fd.json"))
    errors = stats["decode_errors"]
    for name in ("WHEEL_SPEEDS", "STEERING_SENSORS", "ESC_02_10ms"):
        assert errors[name]["accepted"] > 0.9 * prepared["n_fd"] / 3, (name, errors)
        assert errors[name]["e2e"] == 0 and errors[name]["wrong_length"] == 0
    bus = read_candump(vm.out_dir / "vcan0.log")
    state = bus.frame_id == Codec(prepared["fd"]).outputs.frame_id("SLIPD_STATE")
    assert state.sum() > 10
    assert np.all(bus.flags[state] & FLAG_FD)  # slipd's outputs as CAN FD frames
    assert np.all(bus.flags[bus.dlc > 8] & FLAG_FD)
    recording = read_candump(vm.out_dir / "fd_recorder.log")
    assert np.count_nonzero(recording.dlc == 24) == errors["WHEEL_SPEEDS"]["accepted"] + \
        errors["WHEEL_SPEEDS"]["counter_repeat"] + errors["WHEEL_SPEEDS"]["counter_jump"]
    assert vm.read("fd.rc").strip() == "0"


def test_two_buses_on_two_vcans_outputs_on_their_ids(story):
    vm, prepared = story
    _ok(vm, "two_ready")
    listed = vm.read("rcvlist_fil.txt")
    plan = Codec(prepared["two"]).inputs
    for name in plan.message_names:  # each message's kernel filter on its own interface
        device = "vcan1" if plan.bus(name) == "chassis" else "vcan2"
        assert re.search(rf"^\s+{device}\s+0*{plan.frame_id(name):x}\s", listed, re.M | re.I), (
            name, listed)
    stats = json.loads(vm.read("stats_two.json"))
    for name in ("IMU_ACCEL", "IMU_RATE", "WHEEL_SPEEDS", "STEERING"):
        assert stats["decode_errors"][name]["accepted"] > 0, stats["decode_errors"]
        assert stats["decode_errors"][name]["counter_repeat"] == 0
    chassis, pt = read_candump(vm.out_dir / "vcan1.log"), read_candump(vm.out_dir / "vcan2.log")
    assert not np.isin(chassis.frame_id, [*OUTPUT_IDS, 0x300, 0x301, 0x302]).any()
    assert np.isin(pt.frame_id, OUTPUT_IDS[:2]).sum() > 10
    assert not np.isin(pt.frame_id, [0x300, 0x301, 0x302]).any()
    assert vm.read("two.rc").strip() == "0"
