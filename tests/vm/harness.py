"""Boot a stock Debian kernel in qemu (virtme-ng, TCG) over the host filesystem and run a shell
script in it; the real-SocketCAN tests use this because the host kernel has no CAN support.

One boot runs one whole script. The guest sees the host's filesystem read-only (so the
project's checkout and ``.venv`` are there at the same paths), except the run directory, which
is shared read-write: the guest writes its results there and the host asserts on them after the
VM has powered off.

Layout of a run directory (``VmResult.run_dir``)::

    out/            $VM_OUT in the guest: the files the script writes (VmResult.files)
    out/steps/      one NAME.out / NAME.rc / NAME.time per ``step NAME cmd...`` (VmResult.steps)
    .harness/       wrapper.sh, script.sh, the script's stdout / stderr / exit code, timings

Every script gets PRELUDE first: bash functions for the guest side (``step`` runs a command and
records its output, exit status and guest-time duration; ``wait_can_receivers`` waits until the
kernel lists a program's CAN sockets, so a sender does not race a receiver that is still
starting under TCG).

The script's exit code, stdout and stderr are taken from files the guest wrapper writes, not
from virtme-ng: without udev in the guest (the host needs none, and udev costs ~15 s of boot
under TCG), virtme-ng finds no virtio-serial script ports and reports 255 for every script.

KVM is never used (nested KVM hangs the guest on these machines): qemu runs under TCG, where
the guest's Python is 25-100x slower than the host's (the more, the busier the host). Compile
numba code on the host for a portable target (``NUMBA_CPU_NAME=generic``) and let the guest
load it from the cache.

Prerequisites are installed by ``.ci/vm-setup``; ``find_prerequisites`` names what is missing.
"""

from __future__ import annotations

import os
import shlex
import shutil
import signal
import struct
import subprocess
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

#: The project checkout (tests/vm/harness.py -> ../..).
ROOT = Path(__file__).resolve().parents[2]
#: Where .ci/vm-setup puts the kernel (``kernel/current``) and where runs are made (``runs/``).
CACHE_DIR = Path(os.environ.get("SLIPD_VM_CACHE", ROOT / ".vm-cache"))
VENV = Path(os.environ.get("SLIPD_VENV", ROOT / ".venv"))
#: Host commands the guest uses from the shared root filesystem.
GUEST_TOOLS = ("modprobe", "ip", "cansend", "candump", "cangen", "canplayer")
DEFAULT_TIMEOUT = float(os.environ.get("SLIPD_VM_TIMEOUT", "600"))
SETUP_HINT = "run .ci/vm-setup (as root) to install it"


#: Bash functions put in front of every guest script (see the module docstring).
PRELUDE = r"""
mkdir -p "$VM_OUT/steps"
_uptime() { cut -d' ' -f1 /proc/uptime; }
step() {  # step NAME CMD...: run CMD (a program or a function); record output, status, time
    local name=$1 t0 rc
    shift
    t0=$(_uptime)
    echo "$t0" >"$VM_OUT/steps/$name.time"
    "$@" >"$VM_OUT/steps/$name.out" 2>&1
    rc=$?
    echo "$rc" >"$VM_OUT/steps/$name.rc"
    echo "$t0 $(_uptime)" >"$VM_OUT/steps/$name.time"
    return $rc
}
can_receivers() {  # can_receivers DEV: how many CAN receivers the kernel lists on DEV
    cat /proc/net/can/rcvlist_* 2>/dev/null | grep -c -E "^ +$1 " || true
}
wait_can_receivers() {  # wait_can_receivers DEV N [SECONDS]: until DEV has >= N receivers
    local deadline=$(( $(date +%s) + ${3:-30} ))
    while [ "$(can_receivers "$1")" -lt "$2" ]; do
        if [ "$(date +%s)" -ge "$deadline" ]; then
            echo "timed out waiting for $2 CAN receiver(s) on $1:" >&2
            cat /proc/net/can/rcvlist_* >&2 2>/dev/null
            return 1
        fi
        sleep 0.05
    done
}
"""


@dataclass(frozen=True)
class Step:
    """One ``step NAME cmd...`` of a guest script."""

    name: str
    returncode: int | None  # None: the step never finished
    output: str  # stdout and stderr, interleaved
    seconds: float | None  # guest time


@dataclass(frozen=True)
class VmConfig:
    """Everything needed to boot: the kernel image and the programs that boot it."""

    kernel: Path
    vng: Path
    qemu: Path
    memory: str = "2G"
    #: One vCPU by default: under TCG a second vCPU made the guest 2-3x slower here (measured
    #: on a loaded 2-core host: boot 16-22 s vs 10 s, a Python loop 27-40 s vs 7-14 s).
    cpus: int = int(os.environ.get("SLIPD_VM_CPUS", "1"))

    @property
    def kernel_version(self) -> str:
        """The kernel's release (``uname -r`` in the guest)."""
        return self.kernel.name.removeprefix("vmlinuz-")


@dataclass(frozen=True)
class VmResult:
    """What one boot produced.

    ``exit_code`` is the script's exit status, or None when the script never finished (the
    boot failed, the kernel panicked or the timeout struck); ``stdout``/``stderr`` are the
    script's. ``vng_*`` are virtme-ng's own streams (kernel console when ``verbose``), for
    diagnosing a boot that went wrong. ``files`` maps each file the guest wrote under ``out/``
    (relative POSIX path) to its host path.
    """

    exit_code: int | None
    stdout: str
    stderr: str
    files: dict[str, Path]
    run_dir: Path
    wall_seconds: float
    #: guest uptime when the script started (kernel boot + virtme-ng init), None if it never did
    boot_seconds: float | None
    #: guest uptime when the script ended
    guest_end_seconds: float | None
    timed_out: bool
    vng_returncode: int | None
    vng_stdout: str
    vng_stderr: str
    steps: dict[str, Step] = field(default_factory=dict)
    command: list[str] = field(default_factory=list)

    @property
    def out_dir(self) -> Path:
        return self.run_dir / "out"

    def step(self, name: str) -> Step:
        """The record of step ``name`` (a never-started step has returncode None)."""
        return self.steps.get(name, Step(name, None, f"<step {name} never ran>", None))

    def read(self, name: str) -> str:
        """Text of the guest-written file ``out/<name>`` ('' with a note when it is missing)."""
        path = self.out_dir / name
        if not path.is_file():
            return f"<{name} not written by the guest>"
        return path.read_text(errors="replace")

    def describe(self, tail: int = 4000) -> str:
        """A diagnosis for assertion messages: how the run ended and the ends of its streams."""
        head = (
            f"exit_code={self.exit_code} timed_out={self.timed_out} "
            f"vng_returncode={self.vng_returncode} wall={self.wall_seconds:.1f}s "
            f"boot={self.boot_seconds} run_dir={self.run_dir}"
        )
        parts = [head]
        for name, text in (
            ("script stdout", self.stdout),
            ("script stderr", self.stderr),
            ("vng stdout", self.vng_stdout),
            ("vng stderr", self.vng_stderr),
        ):
            if text.strip():
                parts.append(f"--- {name} (last {tail} chars) ---\n{text[-tail:]}")
        return "\n".join(parts)


def find_kernel(cache_dir: Path = CACHE_DIR) -> Path | None:
    """The kernel image ``.ci/vm-setup`` extracted (``kernel/current/boot/vmlinuz-<ver>``)."""
    current = cache_dir / "kernel" / "current"
    if not current.is_dir():
        return None
    version = current.resolve().name
    image = current / "boot" / f"vmlinuz-{version}"
    modules = current / "lib" / "modules" / version / "modules.dep"
    if image.is_file() and modules.is_file():
        return image
    return None


def is_static_elf(path: Path) -> bool:
    """True when ``path`` is an ELF executable without a program interpreter (PT_INTERP)."""
    with open(path, "rb") as f:
        ident = f.read(64)
        if len(ident) < 64 or ident[:4] != b"\x7fELF":
            return False
        is64 = ident[4] == 2
        endian = "<" if ident[5] == 1 else ">"
        if is64:
            (phoff,) = struct.unpack_from(endian + "Q", ident, 32)
            phentsize, phnum = struct.unpack_from(endian + "HH", ident, 54)
        else:
            (phoff,) = struct.unpack_from(endian + "I", ident, 28)
            phentsize, phnum = struct.unpack_from(endian + "HH", ident, 42)
        f.seek(phoff)
        table = f.read(phentsize * phnum)
    pt_interp = 3
    for i in range(phnum):
        (p_type,) = struct.unpack_from(endian + "I", table, i * phentsize)
        if p_type == pt_interp:
            return False
    return True


def _which(name: str) -> Path | None:
    # The guest runs the host's binaries, so look on the host PATH plus the sbin directories
    # that a non-login shell may lack.
    path = os.environ.get("PATH", "") + os.pathsep + "/usr/local/sbin:/usr/sbin:/sbin"
    found = shutil.which(name, path=path)
    return Path(found) if found else None


def find_prerequisites(
    cache_dir: Path = CACHE_DIR, venv: Path = VENV
) -> tuple[VmConfig | None, list[str]]:
    """Look for everything a boot needs.

    Returns ``(config, [])`` when all is there, else ``(None, reasons)`` with one line per
    missing piece, each saying how to get it.
    """
    missing: list[str] = []
    qemu = _which("qemu-system-x86_64")
    if qemu is None:
        missing.append(
            f"qemu-system-x86_64 not found (Debian package qemu-system-x86); {SETUP_HINT}"
        )
    vng = venv / "bin" / "vng"
    if not (vng.is_file() and os.access(vng, os.X_OK)):
        found = _which("vng")
        if found is None:
            missing.append(f"virtme-ng (vng) not in {venv}/bin nor on PATH; {SETUP_HINT}")
        else:
            vng = found
    busybox = next(
        (b for b in map(_which, ("busybox-static", "busybox.static", "busybox")) if b is not None),
        None,
    )
    if busybox is None or not is_static_elf(busybox):
        missing.append(
            f"no statically linked busybox (Debian package busybox-static), "
            f"virtme-ng needs one for its initramfs; {SETUP_HINT}"
        )
    kernel = find_kernel(cache_dir)
    if kernel is None:
        missing.append(
            f"no guest kernel in {cache_dir}/kernel/current (extracted Debian "
            f"linux-image-*-amd64 with its module index); {SETUP_HINT}"
        )
    for tool in GUEST_TOOLS:
        if _which(tool) is None:
            pkg = "iproute2" if tool == "ip" else "kmod" if tool == "modprobe" else "can-utils"
            missing.append(f"{tool} not found (Debian package {pkg}); {SETUP_HINT}")
    if missing:
        return None, missing
    assert qemu is not None and kernel is not None
    return VmConfig(kernel=kernel, vng=vng, qemu=qemu), []


def new_run_dir(name: str, cache_dir: Path = CACHE_DIR) -> Path:
    """A fresh directory under ``<cache>/runs`` for one boot (unique per call).

    Not under /tmp: virtme-ng overlays the guest's /tmp with a tmpfs, so the host would not
    see what the guest writes there.
    """
    import tempfile

    runs = cache_dir / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=f"{name}-", dir=runs))


def _read(path: Path) -> str:
    return path.read_text(errors="replace") if path.is_file() else ""


def _read_float(path: Path) -> float | None:
    try:
        return float(path.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def _read_steps(directory: Path) -> dict[str, Step]:
    """The steps' records, in the order they started."""
    steps: dict[str, Step] = {}
    starts: dict[str, float] = {}
    for rc_or_out in sorted(directory.glob("*.out")) + sorted(directory.glob("*.rc")):
        name = rc_or_out.stem
        if name in steps:
            continue
        rc_text = _read(directory / f"{name}.rc").strip()
        times = _read(directory / f"{name}.time").split()
        seconds = float(times[1]) - float(times[0]) if len(times) == 2 else None
        starts[name] = float(times[0]) if times else float("inf")
        steps[name] = Step(
            name=name,
            returncode=int(rc_text) if rc_text.lstrip("-").isdigit() else None,
            output=_read(directory / f"{name}.out"),
            seconds=seconds,
        )
    return dict(sorted(steps.items(), key=lambda item: starts[item[0]]))


def run_in_vm(
    script: str,
    run_dir: Path,
    config: VmConfig,
    *,
    env: Mapping[str, str] | None = None,
    timeout: float = DEFAULT_TIMEOUT,
    verbose: bool = False,
    vng_args: Sequence[str] = (),
) -> VmResult:
    """Boot once, run ``script`` (bash) in the guest as root and power off.

    The script runs in the checkout (cwd = ``ROOT``) with stdin from /dev/null, ``$VM_OUT``
    set to ``run_dir/out`` (write results there), ``$VM_RUN_DIR`` to ``run_dir``, the project
    venv's bin first on PATH and ``env`` exported on top. ``run_dir`` must be on a host path
    the guest sees (see ``new_run_dir``); it is the only writable host directory in the guest.

    ``timeout`` bounds the whole boot; on expiry qemu is killed (its process group) and
    ``exit_code`` is None. ``verbose`` passes ``--verbose`` to vng (kernel console on its
    stderr; slower, for debugging a boot). ``vng_args`` go to vng before ``--exec`` (e.g.
    ``["--cpus", "1"]`` or ``["--qemu-opts", "..."]``).
    """
    run_dir = run_dir.resolve()
    harness_dir = run_dir / ".harness"
    out_dir = run_dir / "out"
    harness_dir.mkdir(parents=True, exist_ok=True)
    out_dir.mkdir(parents=True, exist_ok=True)
    for stale in ("stdout", "stderr", "exit_code", "uptime_start", "uptime_end"):
        (harness_dir / stale).unlink(missing_ok=True)

    script_path = harness_dir / "script.sh"
    script_path.write_text(PRELUDE + "\n" + script)
    exports = {
        "PATH": f"{VENV / 'bin'}:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin",
        "HOME": "/root",
        "LANG": "C.UTF-8",
        "PYTHONDONTWRITEBYTECODE": "1",
        "VM_OUT": str(out_dir),
        "VM_RUN_DIR": str(run_dir),
        **(env or {}),
    }
    h = shlex.quote(str(harness_dir))
    lines = [
        "#!/bin/bash",
        f"cat /proc/uptime > {h}/uptime_start",
        *(f"export {k}={shlex.quote(v)}" for k, v in exports.items()),
        f"cd {shlex.quote(str(ROOT))}",
        f"bash {shlex.quote(str(script_path))} </dev/null >{h}/stdout 2>{h}/stderr",
        "rc=$?",
        f"cat /proc/uptime > {h}/uptime_end",
        # write-then-rename: the host never reads a half-written exit code
        f"echo $rc > {h}/exit_code.tmp && mv {h}/exit_code.tmp {h}/exit_code",
        "sync",
        "exit $rc",
    ]
    wrapper = harness_dir / "wrapper.sh"
    wrapper.write_text("\n".join(lines) + "\n")

    command = [
        str(config.vng),
        "--run",
        str(config.kernel),
        "--disable-kvm",
        "--force-9p",
        "--memory",
        config.memory,
        "--cpus",
        str(config.cpus),
        "--rwdir",
        str(run_dir),
        *(["--verbose"] if verbose else []),
        *vng_args,
        "--exec",
        f"bash {shlex.quote(str(wrapper))}",
    ]
    vng_env = dict(os.environ)
    # vng runs virtme-run and qemu by name: the venv's bin must be on its PATH.
    vng_env["PATH"] = f"{config.vng.parent}{os.pathsep}{vng_env.get('PATH', '')}"

    start = time.monotonic()
    timed_out = False
    # Own session: on timeout kill the whole group, since vng forks qemu as a child and a
    # killed vng alone would leave qemu running.
    proc = subprocess.Popen(
        command,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=vng_env,
        cwd=ROOT,
        start_new_session=True,
    )
    try:
        vng_out, vng_err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        timed_out = True
        os.killpg(proc.pid, signal.SIGKILL)
        vng_out, vng_err = proc.communicate()
    wall = time.monotonic() - start

    exit_text = _read(harness_dir / "exit_code").strip()
    exit_code = int(exit_text) if exit_text.lstrip("-").isdigit() else None
    files = {
        p.relative_to(out_dir).as_posix(): p for p in sorted(out_dir.rglob("*")) if p.is_file()
    }
    return VmResult(
        steps=_read_steps(out_dir / "steps"),
        exit_code=exit_code,
        stdout=_read(harness_dir / "stdout"),
        stderr=_read(harness_dir / "stderr"),
        files=files,
        run_dir=run_dir,
        wall_seconds=wall,
        boot_seconds=_read_float(harness_dir / "uptime_start"),
        guest_end_seconds=_read_float(harness_dir / "uptime_end"),
        timed_out=timed_out,
        vng_returncode=None if timed_out else proc.returncode,
        vng_stdout=vng_out.decode(errors="replace"),
        vng_stderr=vng_err.decode(errors="replace"),
        command=command,
    )
