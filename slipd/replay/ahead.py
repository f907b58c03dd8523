"""Pipelining a chunked replay over cores: a stage's items produced by a thread, ahead of
their consumer.

The streaming replay (:mod:`slipd.replay.stream`) is a chain of stages over chunks of a log:
read and parse, decode and latch, estimate, write. Their kernels release the GIL (numba
``nogil``, pyarrow's writers), so a stage running in its own thread overlaps with the stages
after it on another core, while the order of the chunks, and so every output byte, stays the
sequential run's. Measured in ``benchmarks/replay.py``.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")

_DONE = object()


def ahead(items: Iterable[T], depth: int = 1, name: str = "slipd ahead") -> Iterator[T]:
    """The items of ``items``, in order, produced by a thread at most ``depth`` items ahead
    of the caller (memory: ``depth`` + 2 items at a time). An exception ``items`` raises is
    raised here, after the items before it. Closing this generator early (a consumer's error,
    ``break``) stops the thread and closes ``items``."""
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
