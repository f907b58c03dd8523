"""slipd: real-time vehicle sideslip estimation, CAN in, sideslip frames out."""

from __future__ import annotations

import hashlib
import os
import shutil
import sys
import time
from pathlib import Path


def _key_numba_cache_to_sources() -> None:
    """Point numba's kernel cache at ``<cache dir>/<hash of slipd's sources>``.

    Numba keys a cached kernel on its own file's timestamp only, so a kernel that inlines a
    function of another module (every estimator calls slipd.estimators.preprocess; the
    ensemble links all its members) kept its stale machine code when only that other module
    changed (measured: an edit to carnier.py did not reach hybrid_friction.step until the
    cache was deleted). On a car that is an upgrade away from running old code silently.
    A directory per source hash makes any change a fresh cache; identical sources (a CI clone,
    the VM guest) share one. Base: $NUMBA_CACHE_DIR, else $XDG_CACHE_HOME/slipd/numba.
    Hashing the ~1 MB of sources takes a few ms at import.
    """
    digest = hashlib.sha256()
    root = Path(__file__).parent
    for path in sorted(root.rglob("*.py")):
        digest.update(path.relative_to(root).as_posix().encode())
        digest.update(path.read_bytes())
    key = digest.hexdigest()[:16]
    base = os.environ.get("NUMBA_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "slipd", "numba")
    if Path(base).name == key:  # already keyed (inherited by a child process)
        return
    keyed = os.path.join(base, key)
    os.environ["NUMBA_CACHE_DIR"] = keyed
    config = sys.modules.get("numba.core.config")
    if config is not None:  # numba imported first: its config has read the variable already
        config.CACHE_DIR = keyed
    _prune_old_keys(Path(base), key)


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


_key_numba_cache_to_sources()
