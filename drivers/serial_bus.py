"""What the serial servo-controller drivers share (Maestro, SSC-32U, DYNAMIXEL).

- :class:`SerialServoBus`: the state every driver keeps (URL, servos,
  status, faults, clock, log), closing the port and then the simulator the
  bus owns (``sim...://`` URLs), and the cadence of the slow status reads;
- :class:`PySerialServoBus`: the same on a pyserial port (open with an
  :class:`~livebridge.errors.InputError` that names the URL, counted writes);
- :func:`simulator`, :func:`open_simulated` and :func:`url_device`: the
  halves of an ``open_url`` (a simulator on a pseudo-terminal, in this
  process or its own, or a device path);
- :func:`clamp_whole`: a raw target clamped to a servo's limits in whole units.

pyserial is imported inside :meth:`PySerialServoBus.__init__` only.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TypeVar
from urllib.parse import urlsplit

from livebridge.errors import InputError
from livebridge.servo.bus import ServoSetup, ServoStatus

Bus = TypeVar("Bus")


def clamp_whole(setup: ServoSetup, value: float) -> int:
    """``value`` rounded and clamped to ``[ceil(setup.low), floor(setup.high)]``."""
    return int(min(math.floor(setup.high), max(math.ceil(setup.low), round(value))))


def simulator(query: dict[str, str], factory, **options):
    """The simulated device a ``sim...://`` URL asks for: ``factory(**options)``, or with ``process=1`` the same
    device served from its own process (:class:`~livebridge.simulators.pty_bus.DeviceProcess`), as hardware
    would be: no simulator thread then competes with the driving process for the CPU and the GIL."""
    device = factory(**options)  # built here either way: bad options are reported with the URL, at once
    if query.get("process", "0").lower() in ("0", "false", "no"):
        return device
    from livebridge.simulators.pty_bus import DeviceProcess

    return DeviceProcess(factory, options)


def open_simulated(sim, make: Callable[[str], Bus]) -> Bus:
    """Start ``sim`` on a pseudo-terminal and ``make(path)`` the bus on it; the simulator is closed if that fails."""
    path = sim.start()
    try:
        return make(path)
    except BaseException:
        sim.close()
        raise


def url_device(url: str, example: str) -> str:
    """The serial device of ``url`` (``scheme:///dev/ttyUSB0``); ``example`` is quoted when there is none."""
    parts = urlsplit(url)
    port = parts.path or parts.netloc
    if not port:
        raise InputError(f"no serial device in the URL ({example})", url)
    return port


class SerialServoBus:
    """Base of a servo bus on a serial port that may own the simulator serving that port.

    A subclass opens its port after :meth:`__init__` and defines :meth:`_close_port`.
    """

    def __init__(self, url: str, simulator, status_every: int, clock: Callable[[], float], log):
        self.url = url
        self.simulator = simulator
        self.status_every = max(1, int(status_every))
        self.clock = clock
        self.log = log or (lambda message: None)
        self.servos: dict[int, ServoSetup] = {}
        self.status: dict[int, ServoStatus] = {}
        self.faults: dict[int, str] = {}
        self._polls = 0

    def _close_port(self) -> None:
        raise NotImplementedError

    def _status_due(self) -> bool:
        """Count a poll; True on every ``status_every``-th one, the first included."""
        due = self._polls % self.status_every == 0
        self._polls += 1
        return due

    def close(self) -> None:
        try:
            self._close_port()
        finally:
            if self.simulator is not None:
                self.simulator.close()
                self.simulator = None


class PySerialServoBus(SerialServoBus):
    """A :class:`SerialServoBus` on a pyserial port ``self.serial``; ``stats["tx_bytes"]`` counts what is sent.

    ``estop`` is kept as ``estop_mode`` (``"stop"`` or ``"home"``).
    """

    def __init__(self, port: str, baud: int, url: str, simulator, status_every: int, estop: str, timeout: float,
                 clock: Callable[[], float], log):
        import serial

        super().__init__(url, simulator, status_every, clock, log)
        self.estop_mode = estop
        try:
            self.serial = serial.Serial(port, baudrate=baud, timeout=timeout, write_timeout=1.0)
        except (serial.SerialException, ValueError) as error:
            raise InputError(f"cannot open serial port ({error})", self.url) from None
        self.stats = {"frames": 0, "tx_bytes": 0}

    def _send(self, data: bytes) -> None:
        self.serial.write(data)
        self.stats["tx_bytes"] += len(data)

    def _close_port(self) -> None:
        self.serial.close()
