"""Fixtures for the real-SocketCAN tests that run inside a qemu VM (see harness.py).

Locally the tests skip, naming what is missing, when qemu, virtme-ng or the guest kernel are not
installed (``.ci/vm-setup`` installs them). With ``SLIPD_REQUIRE_VM=1`` (CI sets it) a missing
prerequisite is an error instead, so the VM tests can never silently not run there.

Other environment variables: ``SLIPD_VM_KEEP=1`` keeps each run directory
(``.vm-cache/runs/<name>-*``) for inspection; ``SLIPD_VM_TIMEOUT`` bounds one boot (seconds).
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from . import harness

_TRUE = {"1", "true", "yes", "on"}
_BOOTS: list[tuple[str, harness.VmResult]] = []


def require_vm() -> bool:
    """True when a missing VM prerequisite must fail the run (CI), not skip it."""
    return os.environ.get("SLIPD_REQUIRE_VM", "").strip().lower() in _TRUE


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    here = Path(__file__).parent
    for item in items:
        if here in Path(str(item.fspath)).parents:
            item.add_marker(pytest.mark.vm)


@pytest.fixture(scope="session")
def vm_config() -> harness.VmConfig:
    """The boot configuration; skips (or, with SLIPD_REQUIRE_VM=1, fails) when incomplete."""
    config, missing = harness.find_prerequisites()
    if config is None:
        reason = "VM prerequisites missing: " + "; ".join(missing)
        if require_vm():
            pytest.fail(f"{reason} (SLIPD_REQUIRE_VM=1: the VM tests must run here)", pytrace=False)
        pytest.skip(reason)
    return config


@pytest.fixture(scope="session")
def vm_run_dir() -> Iterator[Callable[[str], Path]]:
    """A factory of fresh run directories under .vm-cache/runs, removed at the session's end
    unless SLIPD_VM_KEEP=1."""
    made: list[Path] = []

    def make(name: str) -> Path:
        path = harness.new_run_dir(name)
        made.append(path)
        return path

    yield make
    if os.environ.get("SLIPD_VM_KEEP", "").strip().lower() not in _TRUE:
        for path in made:
            shutil.rmtree(path, ignore_errors=True)


@pytest.fixture(scope="session")
def vm_boot(vm_config: harness.VmConfig) -> Callable[..., harness.VmResult]:
    """``vm_boot(name, script, run_dir, env=..., timeout=...)``: one boot with ``run_in_vm``,
    recorded for the timing summary at the end of the session."""

    def boot(name: str, script: str, run_dir: Path, **kwargs: object) -> harness.VmResult:
        result = harness.run_in_vm(script, run_dir, vm_config, **kwargs)  # type: ignore[arg-type]
        _BOOTS.append((name, result))
        return result

    return boot


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    if not _BOOTS:
        return
    terminalreporter.section("qemu VM boots")
    for name, r in _BOOTS:
        boot = f"{r.boot_seconds:.1f}s" if r.boot_seconds is not None else "n/a"
        script = (
            f"{r.guest_end_seconds - r.boot_seconds:.1f}s"
            if r.boot_seconds is not None and r.guest_end_seconds is not None
            else "n/a"
        )
        terminalreporter.write_line(
            f"{name}: boot to script {boot}, script {script}, host wall {r.wall_seconds:.1f}s, "
            f"exit {r.exit_code}{' (TIMED OUT)' if r.timed_out else ''}"
        )
        for step in r.steps.values():
            took = f"{step.seconds:.1f}s" if step.seconds is not None else "n/a"
            terminalreporter.write_line(f"    step {step.name}: {took}, exit {step.returncode}")
