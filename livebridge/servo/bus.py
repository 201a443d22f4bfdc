"""The servo-bus interface: what every bus (real driver or simulator) implements, and the facts it declares.

A servo bus moves raw targets to servos and reads their state back. Real
drivers (``livebridge.drivers.dynamixel``, ``.maestro``, ``.ssc32``) and the
simulated buses implement the same :class:`ServoBus` protocol; which one is
used is chosen by a URL in the rig file, never by code (the schemes and
their openers: :mod:`livebridge.devices.registry`)::

    dynamixel:///dev/ttyUSB0?baud=1000000
    maestro:///dev/ttyACM0?device=12          (device => Pololu protocol)
    ssc32:///dev/ttyUSB1?baud=115200
    simdynamixel://?ids=1-16&model=XL330-M288  (simulated bus on a pty, real driver)
    simmaestro://?channels=12
    simssc32://?channels=32

Raw units (Dynamixel position ticks, Maestro and SSC-32 pulse widths in
microseconds) and every other vendor fact belong to the driver that speaks
to that vendor; it declares what rig validation needs as :class:`BusFacts`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable


@dataclass(frozen=True)
class BusFacts:
    """What a driver declares about its device family, for rig files and tools (raw units of that family).

    Attributes
    ----------
    kind : str
        Family name (``dynamixel``, ``maestro``, ``ssc32``); a simulated bus has its real driver's.
    raw_range : tuple of float
        ``(low, high)`` raw targets the device accepts at all (rig limits must lie inside).
    address_range : tuple of int
        ``(first, last)`` servo address (ID or channel) the family allows.
    address_key : str
        The rig file's key for a servo address: ``"id"`` or ``"channel"``.
    first_address : int
        The lowest address a factory-new device uses (Dynamixel IDs start at 1, channels at 0).
    centre : float
        Raw target of a servo at mid travel.
    typical_span : float
        A modest raw span of travel (a ready-made demo rig swings this far).
    estop_modes : tuple of str
        The ``estop`` choices the driver takes (``"stop"``, ``"home"``); empty: E-stop is always torque off.
    """

    kind: str
    raw_range: tuple[float, float]
    address_range: tuple[int, int]
    address_key: str
    first_address: int
    centre: float
    typical_span: float
    estop_modes: tuple[str, ...] = ()


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
    status: dict[int, ServoStatus]
    """Address -> last known status (what the last :meth:`poll` read)."""
    faults: dict[int, str]
    """Address -> fault text, for servos the bus stopped and leaves out of the writes."""

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

    def recover(self, address: int) -> bool:
        """Bring a faulted servo back (reboot, reconfigure, soft start); False when it or the bus cannot."""

    def estop(self) -> None:
        """Stop now: torque off (Dynamixel), stop pulses or go home (Maestro, SSC-32)."""

    def deactivate(self) -> None:
        """Torque off / pulses off, keep the port open."""

    def close(self) -> None:
        """Release the port (and whatever the bus was given to close with it, e.g. the simulator serving it)."""
