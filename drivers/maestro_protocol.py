"""Pololu Maestro serial protocol: pure encoding and decoding over bytes, no I/O.

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
stops the pulses. The driver (:mod:`livebridge.drivers.maestro`) encodes
with these functions, the simulator (:mod:`livebridge.simulators.maestro_bus`)
decodes with :func:`decode_command`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

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

# data bytes after the command byte (set multiple targets: 2 + 2 per channel, see decode_command)
DATA_LENGTHS = {SET_TARGET: 3, SET_SPEED: 3, SET_ACCELERATION: 3, GET_POSITION: 1, GET_MOVING_STATE: 0,
                GET_ERRORS: 0, GO_HOME: 0}

ERROR_NAMES = {
    0: "serial signal error", 1: "serial overrun error", 2: "serial buffer full", 3: "serial CRC error",
    4: "serial protocol error", 5: "serial timeout", 6: "script stack error", 7: "script call stack error",
    8: "script program counter error",
}
PROTOCOL_ERROR = 1 << 4  # "serial protocol error" bit of get errors


def _split14(value: int) -> bytes:
    value = int(value)
    if not 0 <= value < 1 << 14:
        raise ValueError(f"value {value} outside 0..16383")
    return bytes([value & 0x7F, (value >> 7) & 0x7F])


def join14(low7: int, high7: int) -> int:
    """The 14-bit value of two data bytes (low 7 bits first)."""
    return low7 | (high7 << 7)


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


def encode_u16(value: int) -> bytes:
    """Little-endian 16-bit reply of get position / get errors."""
    return bytes([value & 0xFF, value >> 8])


def decode_u16(reply: bytes) -> int:
    """Little-endian 16-bit reply of get position / get errors."""
    if len(reply) != 2:
        raise ValueError(f"expected 2 bytes, got {len(reply)}")
    return reply[0] | (reply[1] << 8)


def error_text(bits: int) -> str:
    return ", ".join(name for bit, name in ERROR_NAMES.items() if bits & (1 << bit)) or "none"


@dataclass(frozen=True)
class Command:
    """One decoded command.

    Attributes
    ----------
    command : int
        The command byte with its high bit set (as in the compact protocol).
    data : bytes
        The data bytes (7 bits each).
    device : int or None
        The Pololu-protocol device number; None for the compact protocol.
    """

    command: int
    data: bytes
    device: int | None = None


@dataclass(frozen=True)
class Decoded:
    """What :func:`decode_command` took from the front of a buffer.

    ``used`` bytes are consumed (0: the command is incomplete, wait for more); ``command`` is None when
    they were malformed (then ``protocol_error``, the Maestro's serial protocol error) or incomplete.
    """

    used: int
    command: Command | None = None
    protocol_error: bool = False


def decode_command(buffer: bytes | bytearray) -> Decoded:
    """Decode one command from the front of ``buffer`` (compact or Pololu protocol), as the Maestro does.

    A byte with the high bit set always starts a new command: one that interrupts a command's data is a
    protocol error and the interrupted bytes are dropped; so are unknown commands and stray data bytes.
    """
    buf = buffer
    if not buf:
        return Decoded(0)
    offset, device = 0, None
    if buf[0] == POLOLU_START:
        if len(buf) < 3:
            return Decoded(0)
        device, command, offset = buf[1], buf[2] | 0x80, 3
        if buf[1] & 0x80 or buf[2] & 0x80:
            return Decoded(1, protocol_error=True)
    elif buf[0] & 0x80:
        command, offset = buf[0], 1
    else:
        return Decoded(1, protocol_error=True)
    for k in range(offset, len(buf)):  # a byte with the high bit set starts a new command
        if buf[k] & 0x80:
            if k < offset + (2 if command == SET_MULTIPLE_TARGETS else DATA_LENGTHS.get(command, 0)):
                return Decoded(k, protocol_error=True)
            break
    if command == SET_MULTIPLE_TARGETS:
        if len(buf) < offset + 2:
            return Decoded(0)
        length = 2 + 2 * buf[offset]
    elif command in DATA_LENGTHS:
        length = DATA_LENGTHS[command]
    else:
        return Decoded(offset, protocol_error=True)
    if len(buf) < offset + length:
        return Decoded(0)
    data = bytes(buf[offset:offset + length])
    if any(b & 0x80 for b in data):
        return Decoded(offset + next(i for i, b in enumerate(data) if b & 0x80), protocol_error=True)
    return Decoded(offset + length, Command(command, data, device))
