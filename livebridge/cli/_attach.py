"""Attaching commands that live in other modules to a click group."""

from __future__ import annotations

import importlib

import click


def attach(group: click.Group, commands: tuple[tuple[str, str], ...]) -> None:
    """Add each ``(module, attribute)`` command to ``group``; modules not written yet are skipped."""
    for module_name, attribute in commands:
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as error:
            if error.name != module_name:
                raise
            continue
        group.add_command(getattr(module, attribute))
