"""Pololu Maestro servo controllers: a driver on pyserial (the bytes: :mod:`livebridge.drivers.maestro_protocol`).

Raw units in livebridge are microseconds; the wire carries quarter-microseconds.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence

from livebridge.devices.url import DeviceURL
from livebridge.drivers.maestro_protocol import (
    decode_u16,
    error_text,
    get_errors,
    get_position,
    go_home,
    set_acceleration,
    set_multiple_targets,
    set_speed,
    set_target,
    us_to_quarters,
)
from livebridge.drivers.serial_bus import PySerialServoBus, url_device
from livebridge.errors import InputError
from livebridge.servo.bus import BusFacts, ServoInfo, ServoSetup, ServoStatus

FACTS = BusFacts(kind="maestro", raw_range=(64, 4080),  # µs: 0.25 µs units, 14-bit target
                 address_range=(0, 23), address_key="channel", first_address=0, centre=1500.0, typical_span=400.0,
                 estop_modes=("stop", "home"))
URL_PARAMETERS = ("baud", "device")


class MaestroBus(PySerialServoBus):
    """A Maestro on a serial port (USB command port ``/dev/ttyACM0`` or TTL).

    Parameters
    ----------
    port : str
    device : int, optional
        Pololu-protocol device number; ``None`` uses the compact protocol.
    multiple : bool
        Use "set multiple targets" for runs of consecutive channels (Mini Maestro 12/18/24 only).
    status_every : int
        Read errors and positions every this many polls.
    companion : object with ``close()``, optional
        Closed after the port when the bus closes (the simulated Maestro serving a ``simmaestro://`` port).
    estop : str
        ``"stop"`` (target 0: no pulses) or ``"home"`` (the Maestro's home positions).
    """

    kind = FACTS.kind

    def __init__(self, port: str, baud: int = 115200, device: int | None = None, url: str | None = None,
                 companion=None, multiple: bool = True, status_every: int = 10, estop: str = "stop",
                 timeout: float = 0.05, clock=time.monotonic, log=None):
        self.device = device
        self.multiple = multiple
        super().__init__(port, baud, url or f"maestro://{port}", companion, status_every, estop, timeout, clock, log)
        self.events: list[tuple[float, int, str]] = []
        self.errors = 0

    def _query(self, data: bytes, n: int) -> bytes | None:
        self.serial.reset_input_buffer()
        self._send(data)
        reply = self.serial.read(n)
        return reply if len(reply) == n else None

    def position(self, channel: int) -> float | None:
        """The pulse width the Maestro outputs on ``channel`` now, µs (0: no pulses); None if no answer."""
        reply = self._query(get_position(channel, self.device), 2)
        return None if reply is None else decode_u16(reply) / 4.0

    def read_errors(self) -> int | None:
        reply = self._query(get_errors(self.device), 2)
        return None if reply is None else decode_u16(reply)

    def scan(self, addresses: Sequence[int] | None = None) -> list[ServoInfo]:
        channels = range(24) if addresses is None else addresses
        return [ServoInfo(c, "maestro-channel") for c in channels if self.position(c) is not None]

    def configure(self, servos: Sequence[ServoSetup], frame_period: float) -> None:
        if self.read_errors() is None:
            raise InputError("the Maestro does not answer (device number, port?)", self.url)
        for setup in servos:
            if self.position(setup.address) is None:
                raise InputError(f"channel {setup.address} does not answer", self.url, f"servo.{setup.name}")
            self._send(set_speed(setup.address, 0, self.device))  # our safety stage limits speed
            self._send(set_acceleration(setup.address, 0, self.device))
        self.servos = {s.address: s for s in servos}

    def activate(self) -> dict[int, float]:
        """Hobby servos report no position: a channel already pulsing reports its target, else NaN (neutral)."""
        out = {}
        for channel in self.servos:
            value = self.position(channel)
            out[channel] = value if value else float("nan")
        return out

    def _clamp(self, channel: int, value: float) -> int:
        """``value`` (µs) in quarter-µs, inside the servo's limits after rounding to the wire's resolution."""
        setup = self.servos[channel]
        return min(math.floor(setup.high * 4), max(math.ceil(setup.low * 4), us_to_quarters(value)))

    def write(self, targets: Mapping[int, float]) -> None:
        quarters = {c: self._clamp(c, v) for c, v in targets.items() if c in self.servos and math.isfinite(v)}
        channels = sorted(quarters)
        packet = bytearray()
        i = 0
        while i < len(channels):
            j = i
            while self.multiple and j + 1 < len(channels) and channels[j + 1] == channels[j] + 1:
                j += 1
            if j > i:
                packet += set_multiple_targets(channels[i], [quarters[c] for c in channels[i:j + 1]], self.device)
            else:
                packet += set_target(channels[i], quarters[channels[i]], self.device)
            i = j + 1
        if packet:
            self._send(bytes(packet))
        self.stats["frames"] += 1

    def poll(self) -> dict[int, ServoStatus]:
        now = self.clock()
        if not self._status_due():
            return dict(self.status)
        bits = self.read_errors()
        if bits:
            self.errors |= bits
            self.events.append((now, -1, error_text(bits)))
            self.log(f"{self.url}: Maestro error {error_text(bits)}")
        for channel in self.servos:
            position = self.position(channel)
            self.status[channel] = ServoStatus(channel, position, None, bits or 0, self.faults.get(channel), now)
        return dict(self.status)

    def estop(self) -> None:
        if self.estop_mode == "home":
            self._send(go_home(self.device))
        else:
            self.deactivate()

    def recover(self, address: int) -> bool:
        """A Maestro cannot restart one channel's servo: nothing to recover."""
        return False

    def deactivate(self) -> None:
        for channel in self.servos:
            self._send(set_target(channel, 0, self.device))


def open_url(url: DeviceURL, **options) -> MaestroBus:
    """``maestro:///dev/ttyACM0?device=12&baud=115200`` (``device``: Pololu protocol with that device number)."""
    url.check_known(URL_PARAMETERS)
    port = url_device(url, "maestro:///dev/ttyACM0")
    return MaestroBus(port, baud=url.take("baud", int, 115200), device=url.take("device", int), url=url.url,
                      **options)
