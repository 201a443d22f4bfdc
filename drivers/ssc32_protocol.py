"""Lynxmotion SSC-32U servo controller: ASCII protocol encoding (pure) and a driver on pyserial.

Commands (SSC-32U User Guide), each ended by a carriage return:

- ``#<ch>P<pw>...T<ms>``: move one or more channels (pulse width in µs,
  500..2500) as a group finishing together in ``<ms>`` milliseconds;
- ``Q``: is a move in progress? -> ``+`` (moving) or ``.`` (done);
- ``QP<ch>``: pulse width of a channel now -> one byte, µs / 10 (several
  ``QP`` in one line give one byte each);
- ``VER``: firmware version string.

``#<ch>P0`` turns the channel's pulses off (used for E-stop "stop"; an
assumption about the firmware, the guide documents 500..2500 for moves).
Raw units in livebridge are microseconds.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from urllib.parse import urlsplit

from livebridge.drivers.serial_bus import PySerialServoBus, clamp_whole, open_simulated, simulator, url_device
from livebridge.errors import InputError
from livebridge.servo.bus import ServoInfo, ServoSetup, ServoStatus, url_options


def move(pulses: Mapping[int, float], time_ms: float | None = None) -> bytes:
    """``#<ch>P<pw>...[T<ms>]\\r`` for ``pulses`` channel -> µs (rounded to whole µs)."""
    if not pulses:
        raise ValueError("no channels to move")
    parts = []
    for channel, pw in sorted(pulses.items()):
        if not 0 <= channel <= 31:
            raise ValueError(f"channel {channel} outside 0..31")
        parts.append(f"#{channel}P{int(round(pw))}")
    if time_ms is not None:
        parts.append(f"T{max(0, int(round(time_ms)))}")
    return ("".join(parts) + "\r").encode("ascii")


def query_moving() -> bytes:
    return b"Q\r"


def query_pulses(channels: Sequence[int]) -> bytes:
    """``QP0 QP1 ...\\r``: the reply is one byte per channel, pulse width / 10."""
    return (" ".join(f"QP{c}" for c in channels) + "\r").encode("ascii")


def version() -> bytes:
    return b"VER\r"


def decode_pulses(reply: bytes) -> list[int]:
    """One byte per channel -> pulse widths in µs."""
    return [b * 10 for b in reply]


class SSC32Bus(PySerialServoBus):
    """An SSC-32U on a serial port; one group move per frame, timed to the frame period."""

    kind = "ssc32"

    def __init__(self, port: str, baud: int = 115200, url: str | None = None, simulator=None,
                 status_every: int = 10, estop: str = "stop", timeout: float = 0.05, clock=time.monotonic,
                 log=None):
        super().__init__(port, baud, url or f"ssc32://{port}?baud={baud}", simulator, status_every, estop, timeout,
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

    def deactivate(self) -> None:
        if self.servos:
            self._send(("".join(f"#{c}P0" for c in sorted(self.servos)) + "\r").encode("ascii"))


def open_url(url: str, **options) -> SSC32Bus:
    """``ssc32:///dev/ttyUSB1?baud=115200`` or ``simssc32://`` (``?process=1``: the simulator in its own process)."""
    parts = urlsplit(url)
    query = url_options(url)
    try:
        baud = int(query.get("baud", 115200))
    except ValueError as error:
        raise InputError(f"bad URL option ({error})", url) from None
    if parts.scheme == "simssc32":
        from livebridge.simulators.ssc32_bus import SSC32Sim

        sim = simulator(query, SSC32Sim, corrupt_rate=float(query.get("corrupt", 0)),
                        drop_rate=float(query.get("drop", 0)), seed=int(query.get("seed", 0)))
        return open_simulated(sim, lambda path: SSC32Bus(path, baud=baud, url=url, simulator=sim, **options))
    port = url_device(url, "ssc32:///dev/ttyUSB1")
    return SSC32Bus(port, baud=baud, url=url, **options)
