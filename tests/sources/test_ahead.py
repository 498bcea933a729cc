"""sources.frames.Ahead: an iterator's items made on a thread of their own."""

from __future__ import annotations

import threading
import time

import pytest

from pancam_graph.errors import InputError
from pancam_graph.sources.frames import Ahead


def test_items_arrive_in_order_made_off_the_callers_thread_at_most_depth_ahead():
    made_on, made = [], []

    def items():
        for k in range(6):
            made_on.append(threading.current_thread().name)
            made.append(k)
            yield k

    seen = []
    with Ahead(items(), depth=1) as ahead:
        for item in ahead:
            time.sleep(0.02)  # the consumer is slower: the thread waits for it
            # made so far: what was used, one queued, and at most one being made
            assert len(made) <= item + 3
            seen.append(item)
    assert seen == list(range(6))
    assert set(made_on) == {"ahead"}


def test_an_error_while_making_reaches_the_caller_where_it_iterates():
    def items():
        yield 1
        raise InputError("site 3: frame 000042_left.png is truncated")

    got = []
    with Ahead(items()) as ahead, pytest.raises(InputError, match="000042_left.png"):
        for item in ahead:
            got.append(item)
    assert got == [1]


def test_leaving_early_stops_the_thread_and_closes_the_items():
    closed = threading.Event()

    def items():
        try:
            yield from range(1000)
        finally:
            closed.set()

    with Ahead(items()) as ahead:
        for item in ahead:
            if item == 2:
                break
    assert closed.wait(2.0)
    assert not [t for t in threading.enumerate() if t.name == "ahead"]
