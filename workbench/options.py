"""One source of defaults: options dataclasses whose fields carry their own help.

A path's (or the fusion's) options are a dataclass whose fields are declared with
:func:`option`. From that one declaration come:

- the default, used by Python callers (``VoxelOptions()``);
- the command-line flag, its parsing, its help text with units and default
  (:func:`add_option_arguments`), and the instance built from parsed arguments
  (:func:`options_from_args`);
- the class's ``Attributes`` docstring section (:func:`documented`);
- the ``parameters`` of the run's record (:func:`options_record`).

Example
-------
>>> @documented
... @dataclass
... class Options:
...     voxel_m: float = option(1.0, "voxel size r", unit="m", flag="--voxel")
"""

from __future__ import annotations

import argparse
import dataclasses
import os
from collections.abc import Callable
from typing import Any

_KINDS = ("positive", "non_negative", "any")


def option(
    default: Any,
    help: str,
    *,
    unit: str | None = None,
    flag: str | None = None,
    kind: str = "positive",
    choices: tuple | None = None,
    auto: str | None = None,
    cli: bool = True,
    parse: Callable[[str], Any] | None = None,
    nargs: int | None = None,
    metavar: str | None = None,
) -> Any:
    """A dataclass field with what the command line and the docs need to know of it.

    Parameters
    ----------
    default
        The default value (None for "decided at run time"; say how in ``auto``).
    help : str
        What the option does, one or two sentences, without its default.
    unit : str, optional
        Unit of a number ("m", "m2", "deg", "px", ...), shown after the default.
    flag : str, optional
        The command-line flag (default ``--`` and the field name with dashes). For a
        boolean that defaults to True, the flag that turns it off (``--no-...``).
    kind : {"positive", "non_negative", "any"}
        What numbers are accepted.
    choices : tuple, optional
        The accepted values of a string option.
    auto : str, optional
        What None means (the help says "default: <auto>"); also the word that asks for
        it on the command line when ``parse`` does not handle it.
    cli : bool
        False for options only Python callers set.
    parse : callable, optional
        Converts the command-line text (the default follows the default's type).
    nargs : int, optional
        Numbers the flag takes (a tuple option).
    metavar : str, optional
        The value's name in the help (default: the unit, else the type).
    """
    if kind not in _KINDS:
        raise ValueError(f"kind: one of {_KINDS}, got {kind!r}")
    meta = {
        "help": help, "unit": unit, "flag": flag, "kind": kind, "choices": choices,
        "auto": auto, "cli": cli, "parse": parse, "nargs": nargs,
        "metavar": metavar,
    }  # fmt: skip
    if isinstance(default, list | dict | set):
        raise TypeError("option: mutable defaults are not supported")
    return dataclasses.field(default=default, metadata={"option": meta})


# about the largest building's width, metres: the margin of a block of the grid (the
# fusion's and the modeling paths' --block), so that a building its edge cuts is whole in
# it; also the fusion's ground filter's largest opening
LARGEST_BUILDING_M = 80.0


def block_side_option() -> Any:
    """A modeling path's ``--block``: the side of the blocks it models the grid in."""
    return option(
        None, "model the grid in blocks of this side, each segmented with a margin around "
        "it and each building modelled in one block: the command's memory follows the "
        "block, not the area", unit="m", flag="--block", kind="positive",
        auto="the whole grid up to 4096 cells a side",
    )  # fmt: skip


def block_margin_option() -> Any:
    """A modeling path's ``--block-margin``."""
    return option(
        LARGEST_BUILDING_M, "a block's margin: about the largest building's width (a wider "
        "building is modelled from the part of it a block holds)", unit="m",
        flag="--block-margin",
    )  # fmt: skip


def workers_option(also: str = "") -> Any:
    """A modeling path's ``--workers``: its buildings are tasks of :mod:`workbench.engine`
    (``also``: what else the workers run, a clause)."""
    return option(
        None, "buildings modelled at once: worker processes of a local Dask cluster (1: in "
        f"this process){also}; the models do not depend on it", auto="every core",
    )  # fmt: skip


def _meta(f: dataclasses.Field) -> dict:
    return f.metadata.get("option", {})


def describe_default(f: dataclasses.Field) -> str:
    """The default as the help and the docs show it: ``1 m``, ``auto: ...``, ``on``."""
    m = _meta(f)
    d = f.default
    if d is None:
        return m.get("auto") or "none"
    if isinstance(d, bool):
        return "on" if d else "off"
    text = f"{d:g}" if isinstance(d, float) else str(d)
    return f"{text} {m['unit']}" if m.get("unit") else text


def documented(cls):
    """Append an ``Attributes`` section, generated from the fields, to the docstring."""
    lines = ["", "    Attributes", "    ----------"]
    for f in dataclasses.fields(cls):
        m = _meta(f)
        if not m:
            continue
        lines.append(f"    {f.name} : {_type_name(f)}, default {describe_default(f)}")
        lines.append(f"        {m['help']}")
    cls.__doc__ = (cls.__doc__ or cls.__name__).rstrip() + "\n" + "\n".join(lines) + "\n"
    return cls


def _type_name(f: dataclasses.Field) -> str:
    t = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
    return t.replace(" | None", " or None")


def number(kind: str, cast: type = float) -> Callable[[str], Any]:
    """An argparse type: text to ``cast`` (int or float), checked to be ``kind``."""
    word = "integer" if cast is int else "number"

    def parse(text: str):
        try:
            v = cast(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a {word}, got {text!r}") from None
        if kind == "positive" and not v > 0:
            raise argparse.ArgumentTypeError(f"expected a positive {word}, got {text}")
        if kind == "non_negative" and not v >= 0:
            raise argparse.ArgumentTypeError(f"expected a non-negative {word}, got {text}")
        return v

    return parse


def comma_choices(choices: tuple[str, ...]) -> Callable[[str], tuple[str, ...]]:
    """An argparse type: a comma-separated list of some of ``choices``, as a tuple."""

    def parse(text: str) -> tuple[str, ...]:
        names = tuple(t.strip() for t in text.split(",") if t.strip())
        if not names or any(n not in choices for n in names):
            raise argparse.ArgumentTypeError(
                f"a comma-separated list of {', '.join(choices)}, got {text!r}"
            )
        return names

    return parse


def _with_auto(word: str, inner: Callable[[str], Any]) -> Callable[[str], Any]:
    def parse(text: str):
        return None if text == word else inner(text)

    return parse


def _cast_for(f: dataclasses.Field) -> type:
    t = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", "")
    for name, cast in (("bool", bool), ("int", int), ("float", float), ("tuple", float)):
        if t.startswith(name):
            return cast
    return str


def add_option_arguments(parser: argparse.ArgumentParser, cls) -> None:
    """Add one flag per :func:`option` field of ``cls`` to ``parser``; the help says the
    unit and the default. Fields declared with ``cli=False`` are left out."""
    for f in dataclasses.fields(cls):
        m = _meta(f)
        if not m or not m["cli"]:
            continue
        cast = _cast_for(f)
        flag = m["flag"]
        if cast is bool:
            flag = flag or ("--no-" if f.default else "--") + f.name.replace("_", "-")
            state = "on by default; this flag turns it off" if f.default else "off by default"
            parser.add_argument(
                flag, dest=f.name, action="store_false" if f.default else "store_true",
                default=f.default, help=f"{m['help']} ({state})",
            )  # fmt: skip
            continue
        flag = flag or "--" + f.name.replace("_", "-")
        if m["parse"] is not None:
            parse = m["parse"]
        elif m["choices"]:
            parse = str
        elif cast in (int, float):
            parse = number(m["kind"], cast)
        else:
            parse = str
        if m["auto"] and m["parse"] is None and not m["choices"]:
            parse = _with_auto("auto", parse)  # "auto" asks for what None means
        kwargs = {"choices": m["choices"]} if m["choices"] else {}
        metavar = None if m["choices"] else m["metavar"] or (m["unit"] or cast.__name__).upper()
        if m["nargs"]:
            parse, kwargs["nargs"] = number(m["kind"], float), m["nargs"]
        parser.add_argument(
            flag, dest=f.name, type=parse, default=f.default, metavar=metavar,
            help=f"{m['help']} (default {describe_default(f)})", **kwargs,
        )  # fmt: skip


def options_from_args(cls, args: argparse.Namespace):
    """An instance of ``cls`` from parsed arguments (fields absent from them keep their
    defaults)."""
    given = vars(args)
    values = {f.name: given[f.name] for f in dataclasses.fields(cls) if f.name in given}
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})


def options_record(options) -> dict:
    """The options as JSON-ready ``parameters`` of a run record (paths as strings)."""
    out = {}
    for f in dataclasses.fields(options):
        v = getattr(options, f.name)
        if isinstance(v, os.PathLike):
            v = str(v)
        elif isinstance(v, tuple):
            v = list(v)
        out[f.name] = v
    return out
