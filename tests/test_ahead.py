"""slipd.replay.ahead: a stage's items made by a thread keep their order, their errors and
stop with their consumer (the streaming replay's outputs depend on all three)."""

from __future__ import annotations

import threading
import time

import pytest

from slipd.replay.ahead import THREADS_VARIABLE, ahead, ahead_map


@pytest.fixture(autouse=True)
def two_replay_threads(monkeypatch):
    """The threaded path, whatever the CPUs of the machine (one CPU: none by default)."""
    monkeypatch.setenv(THREADS_VARIABLE, "2")


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


# ---- ahead_map: a function over the items in a pool of threads (the parallel parse)


def test_mapped_results_arrive_in_order_from_the_pool():
    threads = set()

    def square(k):
        threads.add(threading.get_ident())
        time.sleep(0.001 * (k % 3))  # later items finish first now and then
        return k * k

    assert list(ahead_map(square, range(100), workers=2)) == [k * k for k in range(100)]
    assert threading.get_ident() not in threads


def test_a_mapped_error_is_raised_after_the_results_before_it():
    def check(k):
        if k == 5:
            raise ValueError("line 5: bad")
        return k

    got = []
    with pytest.raises(ValueError, match="line 5: bad"):
        for item in ahead_map(check, range(20), workers=2):
            got.append(item)
    assert got == [0, 1, 2, 3, 4]


def test_an_error_of_the_items_comes_after_the_results_submitted_before_it():
    def items():
        yield from range(3)
        raise OSError("truncated gzip")

    got = []
    with pytest.raises(OSError, match="truncated"):
        for item in ahead_map(lambda k: k + 10, items(), workers=2):
            got.append(item)
    assert got == [10, 11, 12]


def test_closing_a_map_early_closes_the_source_and_its_threads():
    closed = threading.Event()

    def items():
        try:
            yield from range(10**6)
        finally:
            closed.set()

    before = threading.active_count()
    results = ahead_map(lambda k: k, items(), workers=2)
    assert next(results) == 0
    results.close()
    assert closed.is_set()
    assert threading.active_count() == before


def test_no_more_than_depth_items_are_in_flight():
    """line_blocks reuses a ring of buffers: an item must not be taken while ``depth``
    earlier ones are still unhanded."""
    taken = []
    handed = []

    def items():
        for k in range(60):
            taken.append(k)
            assert len(taken) - len(handed) <= 3
            yield k

    for item in ahead_map(lambda k: k, items(), workers=2, depth=3):
        handed.append(item)
        time.sleep(0.001)


def test_without_threads_the_items_come_from_the_caller_s_thread():
    here = threading.get_ident()
    seen = []

    def items():
        for k in range(5):
            seen.append(threading.get_ident())
            yield k

    assert list(ahead(items(), 2, threaded=False)) == list(range(5))
    assert list(ahead_map(lambda k: (seen.append(threading.get_ident()), k * k)[1], range(5),
                          threaded=False)) == [k * k for k in range(5)]
    assert set(seen) == {here}


def test_without_threads_closing_early_closes_the_source():
    closed = []

    def items():
        try:
            yield from range(100)
        finally:
            closed.append(True)

    for stream in (ahead(items(), threaded=False),
                   ahead_map(lambda k: k, items(), threaded=False)):
        for item in stream:
            if item == 3:
                break
        stream.close()
    assert closed == [True, True]
