"""The house's rules, checked on the source: layers point down, no path imports another,
and the fusion does not build what it needs at run time from the sample generator."""

import ast
from pathlib import Path

import pytest

from modeling import PATHS

ROOT = Path(__file__).resolve().parents[1]


def _imports(path: Path) -> set[str]:
    """Every module a file imports, absolute (relative imports resolved)."""
    package = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                out.add(".".join([*base, node.module] if node.module else base))
            else:
                out.add(node.module)
    return out


def _top(names: set[str]) -> set[str]:
    return {n.split(".")[0] for n in names}


@pytest.mark.parametrize(
    "path", sorted(p for p in (ROOT / "workbench").glob("*.py") if p.name != "cli.py"),
    ids=lambda p: p.name,
)  # fmt: skip
def test_core_modules_import_no_part_above_them(path):
    assert not _top(_imports(path)) & {"fusion", "modeling", "data_samples"}


@pytest.mark.parametrize("path", sorted((ROOT / "fusion").glob("*.py")), ids=lambda p: p.name)
def test_the_fusion_imports_no_modeling_path_nor_the_sample_generator(path):
    assert not _top(_imports(path)) & {"modeling", "data_samples"}


def test_no_path_imports_another_path():
    names = set(PATHS)
    assert names == {p.name for p in (ROOT / "modeling").iterdir()
                     if (p / "__init__.py").exists()} - {"shared"}  # fmt: skip
    for name in names:
        for path in (ROOT / "modeling" / name).glob("*.py"):
            used = {m.split(".")[1] for m in _imports(path)
                    if m.startswith("modeling.") and m.count(".") >= 1}  # fmt: skip
            assert used <= {name, "shared", "registry"}, path
    for path in (ROOT / "modeling" / "shared").glob("*.py"):
        assert (
            not {m for m in _imports(path) if m.startswith("modeling.")}
            - {f"modeling.shared.{p.stem}" for p in (ROOT / "modeling" / "shared").glob("*.py")}
            - {"modeling.shared"}
        ), path


def test_a_path_package_imports_nothing_heavy():
    """The command line reads every path's spec and options to build its flags."""
    for name in PATHS:
        for module in ("__init__", "options"):
            allowed = {"modeling.registry", "workbench.options", f"modeling.{name}.options",
                       "__future__", "dataclasses"}  # fmt: skip
            assert _imports(ROOT / "modeling" / name / f"{module}.py") <= allowed
