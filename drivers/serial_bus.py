"""What the serial servo-controller drivers share (Maestro, SSC-32U, DYNAMIXEL).

- :class:`SerialServoBus`: the state every driver keeps (URL, servos,
  status, faults, clock, log), closing the port and then its companion (an
  object the bus was given to close with it, e.g. the simulator serving a
  ``sim...://`` port), and the cadence of the slow status reads;
- :class:`PySerialServoBus`: the same on a pyserial port (open with an
  :class:`~livebridge.errors.InputError` that names the URL, counted writes);
- :func:`url_device`: the serial device a URL names;
- :func:`clamp_whole`: a raw target clamped to a servo's limits in whole units.

pyserial is imported inside :meth:`PySerialServoBus.__init__` only.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from livebridge.devices.url import DeviceURL
from livebridge.errors import InputError
from livebridge.servo.bus import ServoSetup, ServoStatus


def clamp_whole(setup: ServoSetup, value: float) -> int:
    """``value`` rounded and clamped to ``[ceil(setup.low), floor(setup.high)]``."""
    return int(min(math.floor(setup.high), max(math.ceil(setup.low), round(value))))


def url_device(url: DeviceURL, example: str) -> str:
    """The serial device of ``url`` (``scheme:///dev/ttyUSB0``); ``example`` is quoted when there is none."""
    port = url.path or url.netloc
    if not port:
        raise InputError(f"no serial device in the URL ({example})", url.url)
    return port


class SerialServoBus:
    """Base of a servo bus on a serial port.

    A subclass opens its port after :meth:`__init__` and defines :meth:`_close_port`. ``companion``
    (anything with ``close()``, or None) is closed after the port when the bus closes: whoever opened the
    bus on a port it serves (a simulator on a pseudo-terminal) hands it over this way.
    """

    def __init__(self, url: str, companion, status_every: int, clock: Callable[[], float], log):
        self.url = url
        self.companion = companion
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
            if self.companion is not None:
                self.companion.close()
                self.companion = None


class PySerialServoBus(SerialServoBus):
    """A :class:`SerialServoBus` on a pyserial port ``self.serial``; ``stats["tx_bytes"]`` counts what is sent.

    ``estop`` is kept as ``estop_mode`` (``"stop"`` or ``"home"``).
    """

    def __init__(self, port: str, baud: int, url: str, companion, status_every: int, estop: str, timeout: float,
                 clock: Callable[[], float], log):
        import serial

        super().__init__(url, companion, status_every, clock, log)
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
