"""Benchmarks: each module of this package is one benchmark.

A benchmark module defines ``run(quick: bool, log: Callable[[str], None]) ->
dict`` and a one-line module docstring. It times livebridge against a named
peer on the same input in the same run and reports ratios and accuracy
against ground truth. Wall-clock figures are asserted here, never in tests.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable


def available_benchmarks() -> dict[str, str]:
    """Name -> one-line summary of every benchmark module."""
    found = {}
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        found[info.name] = _summary(info.name)
    return found


def _summary(name: str) -> str:
    module = importlib.import_module(f"{__name__}.{name}")
    return (module.__doc__ or "").strip().splitlines()[0] if module.__doc__ else ""


def run_benchmark(name: str, quick: bool = False, log: Callable[[str], None] = print) -> dict:
    """Run one benchmark and return its result dictionary."""
    module = importlib.import_module(f"{__name__}.{name}")
    return module.run(quick=quick, log=log)
