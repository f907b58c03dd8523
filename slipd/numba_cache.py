"""Where numba caches slipd's compiled kernels: ``<base>/<hash of slipd's sources>``.

Numba keys a cached kernel on its own file's timestamp only, so a kernel that inlines a
function of another module (every estimator calls slipd.estimators.common; the ensemble
links all its members) kept its stale machine code when only that other module changed
(measured: an edit to carnier.py did not reach hybrid_friction.step until the cache was
deleted). On a car that is an upgrade away from running old code silently. A directory per
source hash makes any change a fresh cache; identical sources (a CI clone, the VM guest)
share one. Base: $NUMBA_CACHE_DIR, else $XDG_CACHE_HOME/slipd/numba.

Every way in: slipd's kernel modules import numba as ``from slipd.numba_cache import nb``,
which installs a cache locator for slipd's own files first in numba's list (``SourceKeyedLocator``
in :func:`_install_locator`): their cache directory is the keyed one under numba's configured
directory, else under the XDG cache, even for a script that imports a kernel module directly
(numba's default would put it in the module's ``__pycache__``, keyed to that file alone); a
user's own ``cache=True`` functions keep numba's locators, and no environment variable
changes (the Python API relies on this alone; importing slipd sets nothing, :mod:`slipd` must
stay a library). On top of that the ``slipd`` command (daemon included) and the test suite
call :func:`use_keyed_cache`, which sets ``NUMBA_CACHE_DIR`` for the process and the
processes it starts and prunes the caches of old source versions.

Hashing the ~1 MB of sources takes a few ms, once per process.

Without numba's runtime: the kernels of the per-frame and per-tick path (codec, estimators,
the log parser) are decorated ``@nb.njit(cache=True, _nrt=False)``. With the runtime (NRT)
numba counts references to every array a kernel hands an inlined helper or a call (an atomic
increment and a decrement through a function pointer each), and its pruning pass does not
remove them across branches (numba issue #2350, where its authors measure the same flag):
decoding a frame took 18 such calls, 78 % of the decode's time (173 -> 38 ns a frame, outputs
identical). slipd's kernels allocate nothing (arrays come from the caller), so they need no
runtime; one that allocates does not compile without it. ``inline="always"`` helpers are
compiled into their callers with the callers' options and keep the default (Python may call
them on arrays). tests/test_api.py lists the few kernels there that keep the runtime.
``_nrt`` is numba's private name for the option (it came with the runtime, numba PR #1077):
a numba that dropped it would refuse to compile these kernels, not run them differently.
"""

from __future__ import annotations

import functools
import hashlib
import os
import shutil
import sys
import time
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


# ---------------------------------------------------------------------------------------------
# numba's cache locator for slipd's kernel files
# ---------------------------------------------------------------------------------------------


_RESOLVED_ROOT = _ROOT.resolve()


def _is_slipd_source(py_file: str) -> bool:
    try:
        return Path(py_file).resolve().is_relative_to(_RESOLVED_ROOT)
    except (OSError, ValueError):
        return False


def _install_locator(caching) -> None:
    """Put a locator for slipd's own kernel files first in numba's cache locators: their cache
    directory is :func:`keyed_dir` of numba's configured one, whoever imported them (the
    command, the API, the tests or a user's script that imports a kernel module directly,
    which numba's default would cache in the module's ``__pycache__``, keyed to that file
    alone). Every other function keeps numba's locators."""
    from numba.core import config

    # numba 0.68 names the class CacheImpl, earlier releases _CacheImpl
    impl = getattr(caching, "CacheImpl", None) or caching._CacheImpl
    classes = impl._locator_classes
    if any(getattr(cls, "slipd_source_keyed", False) for cls in classes):
        return

    class SourceKeyedLocator(caching.UserProvidedCacheLocator):
        """numba's locator for a configured cache directory, the directory keyed to slipd's
        sources (numba's own stamp stays: the kernel file's hash)."""

        slipd_source_keyed = True

        def __init__(self, py_func, py_file):
            self._py_file = py_file
            self._lineno = py_func.__code__.co_firstlineno
            self._cache_path = os.path.join(keyed_dir(config.CACHE_DIR or None),
                                            self.get_suitable_cache_subpath(py_file))

        @classmethod
        def from_function(cls, py_func, py_file):
            if not _is_slipd_source(py_file):
                return None
            # numba's source-file check and writable-directory test, without the
            # UserProvidedCacheLocator's "only when CACHE_DIR is set"
            return super(caching.UserProvidedCacheLocator, cls).from_function(py_func, py_file)

    classes.insert(0, SourceKeyedLocator)


def __getattr__(name: str):
    """``nb``: numba itself, with slipd's cache locator installed first. slipd's kernel modules
    import numba as ``from slipd.numba_cache import nb`` (tests/test_api.py checks that each
    does), so no way of importing them caches a kernel where a change of another slipd module
    leaves it stale; importing this module alone still imports no numba (the command calls
    :func:`use_keyed_cache` before anything else)."""
    if name == "nb":
        import numba
        from numba.core import caching

        _install_locator(caching)
        return numba
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
