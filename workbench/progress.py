"""Progress bars on a terminal, silence in CI and pipes."""

from __future__ import annotations

import sys
from collections.abc import Iterable

from tqdm import tqdm


def progress(items: Iterable, desc: str, total: int | None = None) -> Iterable:
    """Wrap ``items`` in a progress bar shown only when stderr is a terminal."""
    return tqdm(
        items,
        desc=desc,
        total=total,
        disable=not sys.stderr.isatty(),
        leave=False,
        unit="it",
        dynamic_ncols=True,
    )
