"""Per-view work spread over the machine's cores, in order and with bounded memory."""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


def default_workers() -> int:
    """The cores this process may run on (its CPU affinity, not the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def ordered_map(
    fn: Callable[[T], R], items: Iterable[T], workers: int, in_flight: int | None = None
) -> Iterator[R]:
    """``fn(item)`` for each item, yielded in the items' order, ``workers`` at a time.

    Threads, not processes: the per-view work (NumPy, OpenCV) releases the GIL, and the
    views' arrays need not be pickled. At most ``in_flight`` items are running or wait
    unconsumed, so memory grows with the workers, not with the number of items: the
    caller reduces each result (to one tile's observations, say) before asking for the
    next.

    Parameters
    ----------
    fn : callable
    items : iterable
    workers : int
        Threads; 1 runs ``fn`` in the calling thread.
    in_flight : int, optional
        Items submitted and not yet yielded; by default ``workers``. A larger window keeps
        the threads busy when the items' costs differ (a slow first item otherwise holds
        the next ones back), at the memory of that many results.
    """
    if workers <= 1:
        for item in items:
            yield fn(item)
        return
    with ThreadPoolExecutor(max_workers=workers) as pool:
        pending: deque = deque()
        for item in items:
            if len(pending) >= max(workers, in_flight or 0):
                yield pending.popleft().result()
            pending.append(pool.submit(fn, item))
        while pending:
            yield pending.popleft().result()
