"""Typed errors whose messages name the file and the field at fault.

The CLI turns every :class:`WorkbenchError` into one line on stderr and exit code 2.
"""

from __future__ import annotations

import os


class WorkbenchError(Exception):
    """Base class of the errors the CLI reports as one line (exit code 2)."""


class InputError(WorkbenchError):
    """Bad input: a missing or malformed file, or a field with a wrong value.

    Parameters
    ----------
    path : str or os.PathLike
        The file at fault (or the folder, for a missing scene).
    field : str or None
        The field inside the file, in a JSON-path-like notation (``images[3].R``).
    message : str
        What is wrong, in a few words.
    """

    def __init__(self, path: str | os.PathLike, field: str | None, message: str):
        self.path = os.fspath(path)
        self.field = field
        self.message = message
        where = f"{self.path}: {field}" if field else self.path
        super().__init__(f"{where}: {message}")

    def __reduce__(self):  # raised in a Dask worker, re-raised in the client
        return type(self), (self.path, self.field, self.message)


class OutputExistsError(WorkbenchError):
    """The output folder exists and ``overwrite`` was not asked for."""

    def __init__(self, path: str | os.PathLike):
        self.path = os.fspath(path)
        super().__init__(f"{self.path}: output exists (pass --overwrite to replace it)")

    def __reduce__(self):
        return type(self), (self.path,)
