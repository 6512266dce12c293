"""Write an output folder atomically: into a temporary sibling, renamed on success.

A command that fails leaves no half-written output behind; the temporary folder of one
that was killed goes when the same output is written again.
"""

from __future__ import annotations

import contextlib
import glob
import logging
import os
import shutil
import socket
import tempfile
from collections.abc import Iterator
from pathlib import Path

from .errors import OutputExistsError

log = logging.getLogger(__name__)


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
    for stale in killed_runs_folders(out):
        log.info("removing %s, left by a run that was killed", stale)
        shutil.rmtree(stale, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix=f"{_tmp_prefix(out)}{os.getpid()}-", dir=out.parent))
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


def _tmp_prefix(out: Path) -> str:
    """The start of the name of ``out``'s temporary folders made on this machine (the
    writing process's id follows)."""
    return f".{out.name}.tmp-{socket.gethostname()}-"


def killed_runs_folders(out: str | os.PathLike) -> list[Path]:
    """The temporary folders of ``out`` whose command, on this machine, no longer runs:
    a process killed (SIGKILL, out of memory, a machine restarted) writes no more into
    its folder, nor removes it. Another machine's, or a live process's, are left."""
    out = Path(out).absolute()
    prefix = _tmp_prefix(out)
    found = []
    for folder in out.parent.glob(f"{glob.escape(prefix)}*"):
        pid = folder.name[len(prefix) :].split("-", 1)[0]
        if folder.is_dir() and pid.isdigit() and not _running(int(pid)):
            found.append(folder)
    return found


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)  # no signal: only whether the process is there
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


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
