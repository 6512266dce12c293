"""Write an output folder atomically: into a temporary sibling, renamed on success.

A command that fails leaves no half-written output behind.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from .errors import OutputExistsError


@contextlib.contextmanager
def atomic_output_dir(out: str | os.PathLike, *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary folder that becomes ``out`` when the block succeeds.

    Parameters
    ----------
    out : path
        The final output folder.
    overwrite : bool
        Replace ``out`` if it exists; otherwise an existing non-empty ``out`` is an error,
        raised before any work is done.

    Yields
    ------
    Path
        A fresh folder on the same file system as ``out``; write everything there.
    """
    out = Path(out).absolute()
    check_output_dir(out, overwrite=overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = None
    if out.exists():
        old = out.with_name(f".{out.name}.old-{os.getpid()}")
        os.replace(out, old)
    os.replace(tmp, out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True) if old.is_dir() else old.unlink()


def check_output_dir(out: str | os.PathLike, *, overwrite: bool = False) -> None:
    """Raise :class:`OutputExistsError` if ``out`` exists, is not an empty folder and may
    not be replaced: callers check before long work, then write with
    :func:`atomic_output_dir`."""
    out = Path(out)
    if out.exists() and not overwrite and (not out.is_dir() or any(out.iterdir())):
        raise OutputExistsError(out.absolute())


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Write one file through a temporary sibling and a rename."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
