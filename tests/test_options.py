"""One source of defaults: the options dataclasses generate the command line's flags,
their help and the run records' parameters."""

import argparse
import dataclasses
from dataclasses import dataclass

import pytest

from fusion.options import FusionOptions
from modeling import PATHS
from workbench.cli import build_parser
from workbench.options import (
    add_option_arguments,
    documented,
    option,
    options_from_args,
    options_record,
)


@documented
@dataclass
class Example:
    """An example."""

    size_m: float = option(1.5, "a size", unit="m", flag="--size")
    count: int = option(3, "a count", kind="non_negative")
    weight: float | None = option(2.0, "a weight, or auto", auto="auto")
    mode: str | None = option(None, "a mode", choices=("a", "b"), auto="chosen by the data")
    keep: bool = option(True, "keep it")
    loud: bool = option(False, "be loud")
    hidden: float = option(0.5, "not on the command line", cli=False)


def _parse(cls, argv):
    parser = argparse.ArgumentParser(exit_on_error=False)
    add_option_arguments(parser, cls)
    return options_from_args(cls, parser.parse_args(argv)), parser


def test_no_flag_gives_the_dataclass_defaults_and_flags_set_fields():
    opts, parser = _parse(Example, [])
    assert opts == Example()
    opts, _ = _parse(
        Example, ["--size", "2", "--count", "0", "--weight", "auto", "--mode", "b", "--no-keep",
                  "--loud"],
    )  # fmt: skip
    assert opts == Example(size_m=2.0, count=0, weight=None, mode="b", keep=False, loud=True)
    assert "--hidden" not in parser.format_help()


def test_help_names_the_unit_and_the_default():
    _, parser = _parse(Example, [])
    text = " ".join(parser.format_help().split())
    assert "a size (default 1.5 m)" in text
    assert "a mode (default chosen by the data)" in text
    assert "keep it (on by default; this flag turns it off)" in text
    assert "size_m : float, default 1.5 m" in Example.__doc__


@pytest.mark.parametrize("argv", [["--size", "0"], ["--size", "x"], ["--count", "-1"],
                                  ["--mode", "c"]])  # fmt: skip
def test_bad_values_are_refused(argv):
    parser = argparse.ArgumentParser(exit_on_error=False)
    add_option_arguments(parser, Example)
    with pytest.raises((argparse.ArgumentError, SystemExit)):
        parser.parse_args(argv)


def test_the_record_holds_every_field():
    assert options_record(Example()) == {f.name: getattr(Example(), f.name)
                                         for f in dataclasses.fields(Example)}  # fmt: skip


def _defaults_of(argv, cls):
    return options_from_args(cls, build_parser().parse_args(argv))


def test_every_command_line_default_is_the_dataclass_default():
    assert _defaults_of(["fusion", "S", "-o", "O"], FusionOptions) == FusionOptions()
    for name, spec in PATHS.items():
        positional = ["X" for i in spec.inputs if i.flag is None]
        assert _defaults_of(["model", name, *positional, "-o", "O"], spec.options) == (
            spec.options()
        ), name


def test_every_option_is_documented():
    for cls in (FusionOptions, *(spec.options for spec in PATHS.values())):
        for f in dataclasses.fields(cls):
            assert f.metadata.get("option", {}).get("help"), f"{cls.__name__}.{f.name}"
            assert f"{f.name} :" in cls.__doc__
