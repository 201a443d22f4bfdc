"""Attaching commands that live in other modules to a click group."""

from __future__ import annotations

import importlib

import click


def attach(group: click.Group, commands: tuple[tuple[str, str], ...]) -> None:
    """Add each ``(module, attribute)`` command to ``group``.

    A module that fails to import is an error, not a command quietly missing from ``--help``.
    """
    for module_name, attribute in commands:
        group.add_command(getattr(importlib.import_module(module_name), attribute))
