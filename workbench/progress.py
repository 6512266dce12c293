"""Progress: a bar on a terminal; elsewhere (a batch job's log, a pipe) a line now and
then, so that a city-long run is not silent for half an hour, and short runs and CI
print nothing."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator

from tqdm import tqdm

LINE_EVERY_S = 60.0  # off a terminal, at most a line a minute: none for a short run


def progress(items: Iterable, desc: str, total: int | None = None) -> Iterable:
    """Wrap ``items`` in a progress bar when stderr is a terminal; otherwise yield them
    and write a line to stderr when a minute has passed since the start or the last
    line (:func:`progress_lines`)."""
    if sys.stderr.isatty():
        return tqdm(items, desc=desc, total=total, leave=False, unit="it", dynamic_ncols=True)
    if total is None and hasattr(items, "__len__"):
        total = len(items)
    return progress_lines(items, desc, total)


def progress_lines(
    items: Iterable,
    desc: str,
    total: int | None,
    every_s: float = LINE_EVERY_S,
    clock=time.monotonic,
) -> Iterator:
    """Yield ``items``; after an item, when ``every_s`` seconds have passed since the
    start or the last line, write ``desc: n of total (p %) in T, about R left`` to
    stderr (without ``total``: ``desc: n in T``)."""
    start = last = clock()
    for n, item in enumerate(items, start=1):
        yield item
        now = clock()
        if now - last >= every_s:
            last = now
            print(progress_line(desc, n, total, now - start), file=sys.stderr, flush=True)


def progress_line(desc: str, n: int, total: int | None, elapsed_s: float) -> str:
    """One line of progress: done, share, time so far and, with ``total``, the time left
    at the rate so far."""
    if not total:
        return f"{desc}: {n} in {duration(elapsed_s)}"
    left = elapsed_s * (total - n) / n
    return (
        f"{desc}: {n} of {total} ({100 * n / total:.0f} %) in {duration(elapsed_s)}, "
        f"about {duration(left)} left"
    )


def duration(seconds: float) -> str:
    """``seconds`` as ``1 h 02 min``, ``4 min 05 s`` or ``12 s``."""
    s = int(round(seconds))
    if s >= 3600:
        return f"{s // 3600} h {s % 3600 // 60:02d} min"
    if s >= 60:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s} s"
