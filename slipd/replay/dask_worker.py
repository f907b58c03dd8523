"""What a dask.distributed worker runs for slipd before its first task (imported only with
``--dask``: dask is an extra)."""

from __future__ import annotations

from distributed import WorkerPlugin


class KernelWarmup(WorkerPlugin):
    """Once per worker: numba's keyed cache (slipd.numba_cache: set before any kernel module
    is imported), then the run's kernels loaded from it, or compiled into it when it is cold,
    so the first log's time is the log's and a cold cache is compiled once per worker."""

    idempotent = False

    def __init__(self, methods: list[str], profile: str):
        self.methods, self.profile = list(methods), profile

    def setup(self, worker) -> None:
        from slipd.numba_cache import use_keyed_cache

        use_keyed_cache()
        from slipd.replay.stream import warm_kernels

        warm_kernels(self.methods, self.profile)
