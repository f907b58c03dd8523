"""Pipelining a chunked replay over cores: a stage's items produced by a thread, ahead of
their consumer, or a stage's function mapped over its items by a pool of threads.

The streaming replay (:mod:`slipd.replay.stream`) is a chain of stages over chunks of a log:
read and parse, decode and latch, estimate, write. Their kernels release the GIL (numba
``nogil``, pyarrow's writers), so a stage running in its own thread overlaps with the stages
after it on another core, while the order of the chunks, and so every output byte, stays the
sequential run's. Measured in ``benchmarks/replay.py``.

The threads a replay may use are :func:`replay_threads` (``$SLIPD_REPLAY_THREADS``, else the
cores this process may run on). With one, every stage runs in the caller's thread, in the
same order: a Dask worker of a cluster that has a worker process per core (``--dask
local:2`` here) has one core of its own, and threads of its stages would only take turns on
it with the other workers' (benchmarks/fleet.py measures both).
"""

from __future__ import annotations

import os
import queue
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")

_DONE = object()

#: environment variable: the threads a replay may run its stages on (1: none but the caller)
THREADS_VARIABLE = "SLIPD_REPLAY_THREADS"


def replay_threads() -> int:
    """Threads a replay in this process may run its stages on: ``$SLIPD_REPLAY_THREADS``
    (an integer >= 1), else the CPUs this process may run on."""
    value = os.environ.get(THREADS_VARIABLE, "").strip()
    if not value:
        try:
            return max(1, len(os.sched_getaffinity(0)))
        except (AttributeError, OSError):  # not Linux
            return max(1, os.cpu_count() or 1)
    if not value.isdigit() or int(value) < 1:
        from slipd.errors import ConfigError

        raise ConfigError(f"{THREADS_VARIABLE}={value!r}: expected an integer >= 1 (the "
                          "threads a replay may use; 1: every stage in one thread)")
    return int(value)


def _threaded(threaded: bool | None) -> bool:
    return replay_threads() > 1 if threaded is None else threaded


def ahead(items: Iterable[T], depth: int = 1, name: str = "slipd ahead",
          threaded: bool | None = None) -> Iterator[T]:
    """The items of ``items``, in order, produced by a thread at most ``depth`` items ahead
    of the caller (memory: ``depth`` + 2 items at a time). An exception ``items`` raises is
    raised here, after the items before it. Closing this generator early (a consumer's error,
    ``break``) stops the thread and closes ``items``. ``threaded`` False (default: whether
    :func:`replay_threads` > 1): the items are made in the caller's thread."""
    if not _threaded(threaded):
        yield from items
        return
    results: queue.Queue = queue.Queue(maxsize=max(1, depth))
    stop = threading.Event()

    def put(item) -> bool:  # False: the consumer has gone
        results.put(item)  # blocks (no polling) while the consumer is behind
        return not stop.is_set()

    def produce() -> None:
        iterator = iter(items)
        try:
            for item in iterator:
                if not put((item, None)):
                    return
            put((_DONE, None))
        except BaseException as exc:  # handed to the consumer, raised there
            put((None, exc))
        finally:
            close = getattr(iterator, "close", None)
            if close is not None:
                close()

    worker = threading.Thread(target=produce, name=name, daemon=True)
    worker.start()
    try:
        while True:
            item, error = results.get()
            if error is not None:
                raise error
            if item is _DONE:
                return
            yield item
    finally:
        stop.set()
        while worker.is_alive():  # unblock its put; it sees the stop and closes ``items``
            try:
                results.get_nowait()
            except queue.Empty:
                worker.join(0.01)


def ahead_map(function: Callable[[T], R], items: Iterable[T], workers: int = 2,
              depth: int | None = None, name: str = "slipd map",
              threaded: bool | None = None) -> Iterator[R]:
    """``function(item)`` of each of ``items``, in order, computed by ``workers`` threads
    (``function`` should release the GIL: a numba ``nogil`` kernel), at most ``depth``
    (default ``workers + 1``) items submitted and not yet handed out. ``items`` is advanced in
    the caller's thread, and only while fewer than ``depth`` are in flight, so an item may
    reuse a buffer of the ``depth + 1``-th item before it. An exception of ``function`` is
    raised here, after the results before it; closing this generator early cancels what has
    not started and waits for what has (it may still be using its item's buffer).
    ``threaded`` False (default: whether :func:`replay_threads` > 1): ``function`` is called
    in the caller's thread, item by item."""
    if not _threaded(threaded):
        iterator = iter(items)
        try:
            yield from map(function, iterator)
        finally:
            close = getattr(iterator, "close", None)
            if close is not None:
                close()
        return
    depth = max(1, depth if depth is not None else workers + 1)
    pool = ThreadPoolExecutor(max(1, workers), thread_name_prefix=name)
    pending: deque[Future] = deque()
    iterator = iter(items)
    error: Exception | None = None
    try:
        while True:
            try:
                item = next(iterator)
            except StopIteration:
                break
            except Exception as exc:  # raised after the results of the items before it
                error = exc
                break
            pending.append(pool.submit(function, item))
            if len(pending) >= depth:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
        if error is not None:
            raise error
    finally:
        for future in pending:
            future.cancel()
        pool.shutdown(wait=True)
        close = getattr(iterator, "close", None)
        if close is not None:
            close()
