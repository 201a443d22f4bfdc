"""Pololu Maestro servo controllers: protocol encoding (pure) and a driver on pyserial.

Targets on the wire are in quarter-microseconds, 7 bits per data byte
(Pololu Maestro User's Guide, "Serial Servo Commands"). Two framings:

- compact protocol: ``CMD DATA...`` (e.g. set target 1500 µs on channel 0
  is ``84 00 70 2E``);
- Pololu protocol: ``AA DEVICE (CMD & 7F) DATA...`` so several devices can
  share a line (default device number 12).

Commands: set target (0x84), set multiple targets (0x9F, Mini Maestro), set
speed (0x87, 0.25 µs / 10 ms), set acceleration (0x89, 0.25 µs / 10 ms /
80 ms), get position (0x90 -> 2 bytes), get moving state (0x93 -> 1 byte),
get errors (0xA1 -> 2 bytes, clears them), go home (0xA2). A target of 0
stops the pulses. Raw units in livebridge are microseconds.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from urllib.parse import urlsplit

from livebridge.drivers.serial_bus import PySerialServoBus, open_simulated, simulator, url_device
from livebridge.errors import InputError
from livebridge.servo.bus import ServoInfo, ServoSetup, ServoStatus, url_options

SET_TARGET = 0x84
SET_MULTIPLE_TARGETS = 0x9F
SET_SPEED = 0x87
SET_ACCELERATION = 0x89
GET_POSITION = 0x90
GET_MOVING_STATE = 0x93
GET_ERRORS = 0xA1
GO_HOME = 0xA2
POLOLU_START = 0xAA
DEFAULT_DEVICE = 12

ERROR_NAMES = {
    0: "serial signal error", 1: "serial overrun error", 2: "serial buffer full", 3: "serial CRC error",
    4: "serial protocol error", 5: "serial timeout", 6: "script stack error", 7: "script call stack error",
    8: "script program counter error",
}


def _split14(value: int) -> bytes:
    value = int(value)
    if not 0 <= value < 1 << 14:
        raise ValueError(f"value {value} outside 0..16383")
    return bytes([value & 0x7F, (value >> 7) & 0x7F])


def frame(command: int, data: bytes = b"", device: int | None = None) -> bytes:
    """Compact (``device=None``) or Pololu-protocol framing of one command."""
    if device is None:
        return bytes([command]) + bytes(data)
    if not 0 <= device <= 127:
        raise ValueError(f"device number {device} outside 0..127")
    return bytes([POLOLU_START, device, command & 0x7F]) + bytes(data)


def us_to_quarters(us: float) -> int:
    return int(round(us * 4))


def set_target(channel: int, quarter_us: int, device: int | None = None) -> bytes:
    return frame(SET_TARGET, bytes([channel]) + _split14(quarter_us), device)


def set_multiple_targets(first_channel: int, quarter_us: Sequence[int], device: int | None = None) -> bytes:
    data = bytes([len(quarter_us), first_channel]) + b"".join(_split14(q) for q in quarter_us)
    return frame(SET_MULTIPLE_TARGETS, data, device)


def set_speed(channel: int, speed: int, device: int | None = None) -> bytes:
    return frame(SET_SPEED, bytes([channel]) + _split14(speed), device)


def set_acceleration(channel: int, acceleration: int, device: int | None = None) -> bytes:
    return frame(SET_ACCELERATION, bytes([channel]) + _split14(acceleration), device)


def get_position(channel: int, device: int | None = None) -> bytes:
    return frame(GET_POSITION, bytes([channel]), device)


def get_moving_state(device: int | None = None) -> bytes:
    return frame(GET_MOVING_STATE, b"", device)


def get_errors(device: int | None = None) -> bytes:
    return frame(GET_ERRORS, b"", device)


def go_home(device: int | None = None) -> bytes:
    return frame(GO_HOME, b"", device)


def decode_u16(reply: bytes) -> int:
    """Little-endian 16-bit reply of get position / get errors."""
    if len(reply) != 2:
        raise ValueError(f"expected 2 bytes, got {len(reply)}")
    return reply[0] | (reply[1] << 8)


def error_text(bits: int) -> str:
    return ", ".join(name for bit, name in ERROR_NAMES.items() if bits & (1 << bit)) or "none"


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
    estop : str
        ``"stop"`` (target 0: no pulses) or ``"home"`` (the Maestro's home positions).
    """

    kind = "maestro"

    def __init__(self, port: str, baud: int = 115200, device: int | None = None, url: str | None = None,
                 simulator=None, multiple: bool = True, status_every: int = 10, estop: str = "stop",
                 timeout: float = 0.05, clock=time.monotonic, log=None):
        self.device = device
        self.multiple = multiple
        super().__init__(port, baud, url or f"maestro://{port}", simulator, status_every, estop, timeout, clock, log)
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
        setup = self.servos[channel]
        return us_to_quarters(min(setup.high, max(setup.low, value)))

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

    def deactivate(self) -> None:
        for channel in self.servos:
            self._send(set_target(channel, 0, self.device))


def open_url(url: str, **options) -> MaestroBus:
    """``maestro:///dev/ttyACM0?device=12`` or ``simmaestro://?channels=12&device=12`` (``&process=1``: the
    simulator in its own process)."""
    parts = urlsplit(url)
    query = url_options(url)
    try:
        device = int(query["device"]) if "device" in query else None
        baud = int(query.get("baud", 115200))
    except ValueError as error:
        raise InputError(f"bad URL option ({error})", url) from None
    if parts.scheme == "simmaestro":
        from livebridge.simulators.maestro_bus import MaestroSim

        sim = simulator(query, MaestroSim, channels=int(query.get("channels", 24)),
                        device=device if device is not None else 12, corrupt_rate=float(query.get("corrupt", 0)),
                        drop_rate=float(query.get("drop", 0)), seed=int(query.get("seed", 0)))
        return open_simulated(sim, lambda path: MaestroBus(path, baud=baud, device=device, url=url,
                                                           simulator=sim, **options))
    port = url_device(url, "maestro:///dev/ttyACM0")
    return MaestroBus(port, baud=baud, device=device, url=url, **options)
