"""The package's import structure: which rooms may use which (read with ``ast``, imports inside functions too)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE_DIRS = {"livebridge": ROOT / "livebridge", "livebridge.drivers": ROOT / "drivers",
                "livebridge.calibration": ROOT / "calibration", "livebridge.simulators": ROOT / "simulators"}


def _modules() -> dict[str, Path]:
    modules = {}
    for package, folder in PACKAGE_DIRS.items():
        for path in folder.rglob("*.py"):
            parts = list(path.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            modules[".".join([package, *parts])] = path
    return modules


MODULES = _modules()


def _imported_names(name: str, source: str, is_package: bool = False) -> set[str]:
    """Every module name an ``import`` or ``from ... import`` statement anywhere in ``source`` refers to."""
    names = set()
    package = name.split(".") if is_package else name.split(".")[:-1]
    for node in ast.walk(ast.parse(source, name)):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package[:len(package) - node.level + 1] + ([node.module] if node.module else []))
            names.add(base)
            names.update(f"{base}.{alias.name}" for alias in node.names)
    return names


def _owning_module(name: str) -> str | None:
    """The project module a dotted name lives in (``a.b.func`` -> ``a.b``), None outside the project."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def _graph() -> dict[str, set[str]]:
    graph = {}
    for name, path in MODULES.items():
        imported = _imported_names(name, path.read_text(), path.name == "__init__.py")
        owners = {_owning_module(dotted) for dotted in imported}
        graph[name] = {owner for owner in owners if owner is not None and owner != name}
    return graph


GRAPH = _graph()


def _edges(source_prefix: str, target_prefix: str, exempt: tuple[str, ...] = ()) -> list[str]:
    return sorted(f"{a} -> {b}" for a, targets in GRAPH.items() for b in targets
                  if _within(a, source_prefix) and _within(b, target_prefix)
                  and not any(_within(a, e) for e in exempt))


def _within(module: str, prefix: str) -> bool:
    return module == prefix or module.startswith(prefix + ".")


def test_the_walker_sees_imports_inside_functions_and_relative_ones():
    source = "def f():\n    from livebridge.drivers import dynamixel\n    from .frame import Frame\n"
    names = _imported_names("livebridge.capture.sync", source)
    assert {"livebridge.drivers.dynamixel", "livebridge.capture.frame.Frame"} <= names
    assert _owning_module("livebridge.capture.frame.Frame") == "livebridge.capture.frame"
    assert len(MODULES) > 90


@pytest.mark.parametrize(("source", "target", "exempt"), [
    ("livebridge.drivers", "livebridge.simulators", ()),
    ("livebridge.reconstruct", "livebridge.solve", ()),
    ("livebridge", "livebridge.bench", ("livebridge.bench", "livebridge.cli")),
])
def test_forbidden_imports(source, target, exempt):
    assert _edges(source, target, exempt) == []


def test_no_two_modules_import_each_other():
    mutual = sorted(f"{a} <-> {b}" for a, targets in GRAPH.items() for b in targets if a < b and a in GRAPH[b])
    assert mutual == []
