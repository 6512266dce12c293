"""What a modeling path tells the command line about itself.

A path is a folder under ``modeling/`` whose ``__init__`` defines ``SPEC``, a
:class:`PathSpec`, and imports nothing heavy; ``modeling/__init__`` lists it in
``PATHS``. The command line builds ``workbench model NAME`` from the spec: the inputs, a
flag per field of the options dataclass, and a call of ``run`` whose :class:`ModelRun`
the one writer turns into the run folder.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class Input:
    """A file or folder a path reads.

    name : keyword of the run function; help; metavar; flag : None for a positional
    argument, else the flag (optional input)."""

    name: str
    help: str
    metavar: str
    flag: str | None = None


@dataclass(frozen=True)
class PathSpec:
    """A modeling path as the command line sees it.

    Attributes
    ----------
    name : str
        ``workbench model NAME``; also model.json's ``method``.
    help, description : str
        One line for the list of paths, a paragraph for the path's own help.
    options : type
        Its options dataclass (fields declared with :func:`workbench.options.option`).
    inputs : tuple of Input
    run : str
        ``"module:function"`` of ``function(*positional, options, **optional) -> ModelRun``.
    summary : str, optional
        ``"module:function"`` of ``function(record, buildings) -> list of str``: what the
        command prints beside the counts, from model.json's record (but its buildings) and
        its buildings' records, an iterable read one at a time
        (:func:`workbench.model_run.model_buildings`).
    tasks : bool
        The run function takes ``engine=`` (:mod:`workbench.engine`) and runs its
        buildings as its tasks: the command gives it ``--workers``, ``--scheduler`` and
        ``--resume``.
    check : str, optional
        ``"module:function"`` called with the run function's arguments (no engine) before
        the command starts its workers: bad input stops there, in one line.
    """

    name: str
    help: str
    description: str
    options: type
    inputs: tuple[Input, ...]
    run: str
    summary: str | None = None
    tasks: bool = False
    check: str | None = None

    def load(self) -> Callable:
        """The run function (imported now: it pulls in the path's dependencies)."""
        return _load(self.run)

    def arguments(self, given: dict) -> list:
        """The command-line arguments of the inputs in ``given`` ({input name: value}):
        every positional input (required), and the flags of the optional ones given."""
        args = []
        for item in self.inputs:
            if item.flag is None:
                args.append(given[item.name])
            elif item.name in given:
                args += [item.flag, given[item.name]]
        return args

    def check_inputs(self, *positional, **kwargs) -> None:
        """Run the path's input check, if it has one (before any worker starts)."""
        if self.check:
            _load(self.check)(*positional, **kwargs)

    def summary_lines(self, record: dict, buildings=()) -> list[str]:
        return _load(self.summary)(record, buildings) if self.summary else []


def _load(target: str) -> Callable:
    module, function = target.split(":")
    return getattr(importlib.import_module(module), function)
