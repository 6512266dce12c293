"""ordered_map: results in the items' order, errors raised, bounded work in flight."""

import threading
import time

import pytest

from workbench.parallel import default_workers, ordered_map


def test_results_come_in_the_items_order():
    def slow_square(x):
        time.sleep(0.002 * (10 - x))  # the first items finish last
        return x * x

    assert list(ordered_map(slow_square, range(10), 4)) == [x * x for x in range(10)]
    assert list(ordered_map(slow_square, range(10), 1)) == [x * x for x in range(10)]


def test_one_worker_runs_in_the_calling_thread():
    names = list(ordered_map(lambda _: threading.current_thread().name, range(3), 1))
    assert names == [threading.current_thread().name] * 3


def test_several_workers_run_at_once():
    barrier = threading.Barrier(2, timeout=5)  # breaks unless two calls overlap

    def meet(x):
        barrier.wait()
        return x

    assert list(ordered_map(meet, range(4), 2)) == [0, 1, 2, 3]


def test_no_more_than_the_workers_run_ahead_of_the_consumer():
    started = []

    def record(x):
        started.append(x)
        return x

    for x in ordered_map(record, range(20), 3):
        time.sleep(0.005)  # a slow consumer: the pool must wait for it
        # items submitted: the one consumed, at most 3 waiting or running
        assert len(started) <= x + 1 + 3


def test_an_error_in_a_worker_reaches_the_caller():
    def fail_on_three(x):
        if x == 3:
            raise ValueError("three")
        return x

    with pytest.raises(ValueError, match="three"):
        list(ordered_map(fail_on_three, range(6), 2))


def test_default_workers_is_at_least_one():
    assert default_workers() >= 1
