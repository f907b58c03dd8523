"""Where numba caches slipd's compiled kernels: ``<base>/<hash of slipd's sources>``.

Numba keys a cached kernel on its own file's timestamp only, so a kernel that inlines a
function of another module (every estimator calls slipd.estimators.common; the ensemble
links all its members) kept its stale machine code when only that other module changed
(measured: an edit to carnier.py did not reach hybrid_friction.step until the cache was
deleted). On a car that is an upgrade away from running old code silently. A directory per
source hash makes any change a fresh cache; identical sources (a CI clone, the VM guest)
share one. Base: $NUMBA_CACHE_DIR, else $XDG_CACHE_HOME/slipd/numba.

Who sets it (importing slipd sets nothing, :mod:`slipd` must stay a library):

* the ``slipd`` command (daemon included) and the test suite call :func:`use_keyed_cache`,
  which sets ``NUMBA_CACHE_DIR`` for the process and the processes it starts;
* the Python API (:mod:`slipd.api`) loads its kernels inside :func:`keyed_cache`, which points
  numba's ``config.CACHE_DIR`` at the keyed directory only while slipd's kernel modules are
  imported (numba binds a kernel's cache directory when the function is decorated) and then
  restores it, so a user's own ``cache=True`` functions cache where they always did and no
  environment variable changes.

Hashing the ~1 MB of sources takes a few ms, once per process.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import shutil
import sys
import time
from collections.abc import Iterator
from pathlib import Path

_ROOT = Path(__file__).parent


@functools.lru_cache(maxsize=1)
def source_key() -> str:
    """16 hex digits of the SHA-256 over slipd's ``*.py`` files (paths and contents)."""
    digest = hashlib.sha256()
    for path in sorted(_ROOT.rglob("*.py")):
        digest.update(path.relative_to(_ROOT).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def _base(configured: str | None) -> str:
    return configured or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "slipd", "numba")


def keyed_dir(configured: str | None = None) -> str:
    """The keyed cache directory under ``configured`` (default: $NUMBA_CACHE_DIR, else the
    XDG cache); a directory that is keyed already (inherited by a child process) stays."""
    base = _base(configured if configured is not None else os.environ.get("NUMBA_CACHE_DIR"))
    key = source_key()
    return base if Path(base).name == key else os.path.join(base, key)


def use_keyed_cache() -> str:
    """Set ``NUMBA_CACHE_DIR`` to the keyed directory for this process and its children (the
    CLI, the daemon, the tests); returns it. Call before any slipd kernel module is imported
    (numba reads the variable when a kernel is decorated)."""
    keyed = keyed_dir()
    os.environ["NUMBA_CACHE_DIR"] = keyed
    config = sys.modules.get("numba.core.config")
    if config is not None:  # numba imported first: its config has read the variable already
        config.CACHE_DIR = keyed
    _prune_old_keys(Path(keyed).parent, source_key())
    return keyed


@contextlib.contextmanager
def keyed_cache() -> Iterator[str]:
    """Kernels decorated inside the block cache in the keyed directory; numba's
    ``config.CACHE_DIR`` is restored afterwards and the environment is not touched."""
    from numba.core import config

    before = config.CACHE_DIR
    keyed = keyed_dir(before or None)
    config.CACHE_DIR = keyed
    try:
        yield keyed
    finally:
        config.CACHE_DIR = before


def _prune_old_keys(base: Path, key: str, keep_days: float = 7.0) -> None:
    """Remove caches of other source versions untouched for ``keep_days`` (best effort)."""
    try:
        entries = list(base.iterdir())
    except OSError:
        return
    cutoff = time.time() - keep_days * 86400
    for entry in entries:
        name = entry.name
        if name == key or len(name) != len(key) or not all(c in "0123456789abcdef" for c in name):
            continue
        try:
            if entry.is_dir() and entry.stat().st_mtime < cutoff:
                shutil.rmtree(entry, ignore_errors=True)
        except OSError:
            continue
