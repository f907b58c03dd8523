"""slipd.replay.ahead: a stage's items made by a thread keep their order, their errors and
stop with their consumer (the streaming replay's outputs depend on all three)."""

from __future__ import annotations

import threading
import time

import pytest

from slipd.replay.ahead import ahead


def test_items_arrive_in_order_from_another_thread():
    threads = []

    def items():
        for k in range(200):
            threads.append(threading.get_ident())
            yield k

    assert list(ahead(items(), 2)) == list(range(200))
    assert set(threads) == {threads[0]} and threads[0] != threading.get_ident()


def test_an_error_is_raised_after_the_items_before_it():
    def items():
        yield 1
        yield 2
        raise ValueError("line 3: bad")

    got = []
    with pytest.raises(ValueError, match="line 3: bad"):
        for item in ahead(items()):
            got.append(item)
    assert got == [1, 2]


def test_closing_early_stops_the_thread_and_closes_the_source():
    closed = threading.Event()

    def items():
        try:
            k = 0
            while True:
                yield k
                k += 1
        finally:
            closed.set()

    before = threading.active_count()
    stream = ahead(items(), 1)
    assert next(stream) == 0
    stream.close()
    assert closed.wait(5)
    deadline = time.monotonic() + 5
    while threading.active_count() > before and time.monotonic() < deadline:
        time.sleep(0.01)
    assert threading.active_count() == before


def test_the_consumer_is_never_more_than_depth_items_behind():
    made = []

    def items():
        for k in range(50):
            made.append(k)
            yield k

    for item in ahead(items(), 2):
        time.sleep(0.002)
        # queued (depth) + the one being handed over + the one being put
        assert len(made) - (item + 1) <= 2 + 2
