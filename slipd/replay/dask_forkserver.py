"""What the forkserver of a ``--dask local[:N]`` cluster imports before it forks the workers
(multiprocessing's forkserver preload): numba's keyed cache, the replay's allocator setting
(slipd.replay.stream.keep_freed_memory), slipd's kernel modules and the run's kernels loaded
from the cache, once, so each worker starts with them instead of
importing and loading them again (on 2 cores: ~2.5 s of CPU per worker).

The run's methods and profile come in ``SLIPD_DASK_KERNELS`` (``METHOD,METHOD...@PROFILE``),
set by :func:`slipd.replay.fleet.dask_client` before the forkserver starts. Nothing here may
stop the forkserver: a failure leaves the loading to each worker's own warm-up
(:class:`slipd.replay.dask_worker.KernelWarmup`), which reports it.
"""

from __future__ import annotations

import os

#: the environment variable naming the kernels to load
KERNELS_VARIABLE = "SLIPD_DASK_KERNELS"


def _preload() -> None:
    from slipd.numba_cache import use_keyed_cache
    from slipd.replay.stream import keep_freed_memory

    use_keyed_cache()
    keep_freed_memory()  # slipd's own worker processes: they inherit it by fork
    methods, _, profile = os.environ.get(KERNELS_VARIABLE, "").partition("@")
    if methods:
        from slipd.replay.stream import warm_kernels

        warm_kernels(methods.split(","), profile or "default")


try:
    _preload()
except Exception:  # noqa: BLE001 - see the module docstring: the workers' warm-up reports it
    pass
