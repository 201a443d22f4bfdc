"""Checks of the numeric options of the servo and simulated-bus commands, made before anything is sent.

Each check raises :class:`click.BadParameter` naming the option, so a refusal is one ``Error:`` line and
a non-zero exit, and no bus has been opened yet.
"""

from __future__ import annotations

import math

import click


def finite(value: float | None, option: str) -> float | None:
    """``value`` unchanged when it is finite (or None, an option not given)."""
    if value is not None and not math.isfinite(value):
        raise click.BadParameter(f"must be a finite number, got {value}", param_hint=option)
    return value


def inside(value: float | None, low: float, high: float, option: str, what: str) -> float | None:
    """``value`` unchanged when it is finite and in ``[low, high]`` (``what`` names that range in the error)."""
    finite(value, option)
    if value is not None and not low <= value <= high:
        raise click.BadParameter(f"{value:g} is outside {what} ({low:g}..{high:g})", param_hint=option)
    return value


def positive(value: float, option: str, unit: str) -> float:
    """``value`` unchanged when it is finite and > 0."""
    finite(value, option)
    if not value > 0:
        raise click.BadParameter(f"must be > 0 {unit}, got {value:g}", param_hint=option)
    return value


def probability(value: float, option: str) -> float:
    """``value`` unchanged when it is a finite number in [0, 1]."""
    return inside(value, 0.0, 1.0, option, "the probability range")


def parse_addresses(text: str, first: int, last: int, option: str) -> list[int]:
    """``"1-4,7"`` -> ``[1, 2, 3, 4, 7]``, every address in ``first..last`` and none twice.

    Bounds are checked before a range is expanded, so ``1-999999999`` is refused at once.
    """
    addresses: list[int] = []
    for part in str(text).split(","):
        part = part.strip()
        if not part:
            continue
        low_text, dash, high_text = part.partition("-")
        try:
            low = int(low_text)
            high = int(high_text) if dash else low
        except ValueError:
            raise click.BadParameter(f"{part!r} is not an address or a range like 1-20", param_hint=option) from None
        if not first <= low <= high <= last:
            raise click.BadParameter(f"{part!r}: addresses run {first}..{last}, ranges upwards", param_hint=option)
        addresses.extend(range(low, high + 1))
    if not addresses:
        raise click.BadParameter(f"no address in {text!r}", param_hint=option)
    if len(set(addresses)) != len(addresses):
        raise click.BadParameter(f"an address is given twice in {text!r}", param_hint=option)
    return addresses
