"""The servo-bus interface and the URL registry that picks an implementation.

A servo bus moves raw targets to servos and reads their state back. Real
drivers (``livebridge.drivers.dynamixel``, ``.maestro``, ``.ssc32``) and the
simulated buses implement the same :class:`ServoBus` protocol; which one is
used is chosen by a URL in the rig file, never by code::

    dynamixel:///dev/ttyUSB0?baud=1000000
    maestro:///dev/ttyACM0?device=12          (device => Pololu protocol)
    ssc32:///dev/ttyUSB1?baud=115200
    simdynamixel://?ids=1-16&model=XL330-M288  (simulated bus on a pty, real driver)
    simmaestro://?channels=12
    simssc32://?channels=32

Raw units: Dynamixel position ticks (0..4095 in position mode), Maestro and
SSC-32 pulse widths in microseconds.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable
from urllib.parse import parse_qs, urlsplit

from livebridge.errors import InputError

# Raw range each bus kind accepts at all (rig limits must lie inside).
RAW_RANGES: dict[str, tuple[float, float]] = {
    "dynamixel": (0, 4095),
    "maestro": (64, 4080),  # µs: 0.25 µs units, 14-bit target
    "ssc32": (500, 2500),  # µs, SSC-32U manual
}
_KIND = {"dynamixel": "dynamixel", "simdynamixel": "dynamixel", "maestro": "maestro", "simmaestro": "maestro",
         "ssc32": "ssc32", "simssc32": "ssc32"}
_OPENERS = {
    "dynamixel": "livebridge.drivers.dynamixel:open_url",
    "simdynamixel": "livebridge.drivers.dynamixel:open_url",
    "maestro": "livebridge.drivers.maestro:open_url",
    "simmaestro": "livebridge.drivers.maestro:open_url",
    "ssc32": "livebridge.drivers.ssc32:open_url",
    "simssc32": "livebridge.drivers.ssc32:open_url",
}


@dataclass(frozen=True)
class ServoInfo:
    """A servo found by a scan: its address (ID or channel) and what it said about itself."""

    address: int
    model: str | None = None
    model_number: int | None = None
    firmware: int | None = None


@dataclass(frozen=True)
class ServoSetup:
    """What a bus needs to know about one servo: address, raw limits (low <= high), neutral, model."""

    address: int
    low: float
    high: float
    neutral: float
    model: str | None = None
    name: str = ""


@dataclass(frozen=True)
class ServoStatus:
    """Last known state of one servo (``None`` where the bus cannot tell).

    ``position`` raw units; ``temperature`` °C; ``error`` device error bits
    (Dynamixel hardware error status, Maestro error flags); ``fault`` a short
    text while the servo is stopped by a fault; ``t`` seconds, monotonic.
    """

    address: int
    position: float | None
    temperature: float | None
    error: int
    fault: str | None
    t: float


@runtime_checkable
class ServoBus(Protocol):
    """One bus of servos. Lifecycle: ``configure`` -> ``activate`` -> ``write``/``poll`` ... -> ``deactivate``."""

    url: str
    kind: str

    def scan(self, addresses: Sequence[int] | None = None) -> list[ServoInfo]:
        """Servos that answer (for buses that cannot answer, the configured channels)."""

    def configure(self, servos: Sequence[ServoSetup], frame_period: float) -> None:
        """Check the servos are there and set them up for one target every ``frame_period`` seconds."""

    def activate(self) -> dict[int, float]:
        """Power the servos on holding their present position; returns address -> raw position."""

    def write(self, targets: Mapping[int, float]) -> None:
        """Send one frame of raw targets (one bus transaction where the protocol allows)."""

    def poll(self) -> dict[int, ServoStatus]:
        """Read back state at the bus's own (lower) rate; returns the latest known status."""

    def estop(self) -> None:
        """Stop now: torque off (Dynamixel), stop pulses or go home (Maestro, SSC-32)."""

    def deactivate(self) -> None:
        """Torque off / pulses off, keep the port open."""

    def close(self) -> None:
        """Release the port (and a simulator the bus started)."""


def bus_kind(url: str) -> str:
    """``dynamixel``, ``maestro`` or ``ssc32`` for a bus URL; :class:`InputError` otherwise."""
    scheme = urlsplit(url).scheme
    if scheme not in _KIND:
        raise InputError(f"unknown bus URL scheme {scheme!r}; known: {', '.join(sorted(_KIND))}", url)
    return _KIND[scheme]


def url_options(url: str) -> dict[str, str]:
    """Query options of a URL as a flat dict (last value wins)."""
    return {k: v[-1] for k, v in parse_qs(urlsplit(url).query).items()}


def register(scheme: str, opener: str | Callable[[str], ServoBus], kind: str) -> None:
    """Add a URL scheme: ``opener`` is ``"module:function"`` or a callable ``url -> ServoBus``."""
    _OPENERS[scheme] = opener
    _KIND[scheme] = kind


def open_bus(url: str, **options) -> ServoBus:
    """Open the bus a URL names (the port opens now; servos are touched in ``configure``)."""
    scheme = urlsplit(url).scheme
    bus_kind(url)
    opener = _OPENERS[scheme]
    if isinstance(opener, str):
        module_name, function = opener.split(":")
        opener = getattr(importlib.import_module(module_name), function)
    return opener(url, **options)
