"""Lynxmotion SSC-32U servo controller: a driver on pyserial (the bytes: :mod:`livebridge.drivers.ssc32_protocol`).

One group move per frame, timed to the frame period. Raw units in livebridge are microseconds.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence

from livebridge.devices.url import DeviceURL
from livebridge.drivers.serial_bus import PySerialServoBus, clamp_whole, url_device
from livebridge.drivers.ssc32_protocol import PULSE_RANGE, decode_pulses, move, pulses_off, query_pulses, version
from livebridge.errors import InputError
from livebridge.servo.bus import BusFacts, ServoInfo, ServoSetup, ServoStatus

FACTS = BusFacts(kind="ssc32", raw_range=PULSE_RANGE, address_range=(0, 31), address_key="channel", first_address=0,
                 centre=1500.0, typical_span=400.0, estop_modes=("stop", "home"))
URL_PARAMETERS = ("baud",)


class SSC32Bus(PySerialServoBus):
    """An SSC-32U on a serial port; one group move per frame, timed to the frame period.

    ``companion`` (anything with ``close()``) is closed after the port when the bus closes (the simulated
    SSC-32U serving a ``simssc32://`` port).
    """

    kind = FACTS.kind

    def __init__(self, port: str, baud: int = 115200, url: str | None = None, companion=None,
                 status_every: int = 10, estop: str = "stop", timeout: float = 0.05, clock=time.monotonic,
                 log=None):
        super().__init__(port, baud, url or f"ssc32://{port}?baud={baud}", companion, status_every, estop, timeout,
                         clock, log)
        self.frame_ms = 20.0

    def firmware(self) -> str | None:
        self.serial.reset_input_buffer()
        self._send(version())
        line = self.serial.read_until(b"\r", 64)
        return line.strip().decode("ascii", "replace") if line.endswith(b"\r") else None

    def pulses(self, channels: Sequence[int]) -> dict[int, float] | None:
        channels = list(channels)
        self.serial.reset_input_buffer()
        self._send(query_pulses(channels))
        reply = self.serial.read(len(channels))
        if len(reply) != len(channels):
            return None
        return {c: float(pw) for c, pw in zip(channels, decode_pulses(reply))}

    def scan(self, addresses: Sequence[int] | None = None) -> list[ServoInfo]:
        name = self.firmware()
        if name is None:
            return []
        channels = range(32) if addresses is None else addresses
        return [ServoInfo(c, name) for c in channels]

    def configure(self, servos: Sequence[ServoSetup], frame_period: float) -> None:
        if self.firmware() is None:
            raise InputError("the SSC-32U does not answer VER (port, baud rate?)", self.url)
        self.servos = {s.address: s for s in servos}
        self.frame_ms = frame_period * 1000.0

    def activate(self) -> dict[int, float]:
        positions = self.pulses(sorted(self.servos)) or {}
        return {c: (positions.get(c) or float("nan")) for c in self.servos}

    def write(self, targets: Mapping[int, float]) -> None:
        pulses = {}
        for channel, value in targets.items():
            if channel in self.servos and math.isfinite(value):
                pulses[channel] = clamp_whole(self.servos[channel], value)
        if pulses:
            self._send(move(pulses, self.frame_ms))
        self.stats["frames"] += 1

    def poll(self) -> dict[int, ServoStatus]:
        now = self.clock()
        if self._status_due() and self.servos:
            positions = self.pulses(sorted(self.servos)) or {}
            for channel in self.servos:
                self.status[channel] = ServoStatus(channel, positions.get(channel), None, 0, None, now)
        return dict(self.status)

    def estop(self) -> None:
        if not self.servos:
            return
        if self.estop_mode == "home":
            self._send(move({c: s.neutral for c, s in self.servos.items()}))
        else:
            self.deactivate()

    def recover(self, address: int) -> bool:
        """An SSC-32U cannot restart one channel's servo: nothing to recover."""
        return False

    def deactivate(self) -> None:
        if self.servos:
            self._send(pulses_off(self.servos))


def open_url(url: DeviceURL, **options) -> SSC32Bus:
    """``ssc32:///dev/ttyUSB1?baud=115200``."""
    url.check_known(URL_PARAMETERS)
    port = url_device(url, "ssc32:///dev/ttyUSB1")
    return SSC32Bus(port, baud=url.take("baud", int, 115200), url=url.url, **options)
