"""ROBOTIS DYNAMIXEL Protocol 2.0: pure encoding and decoding over bytes.

Everything here is a function of bytes to bytes (or to small frozen
dataclasses); nothing does I/O. The simulator (``livebridge.simulators.
dynamixel_bus``) and the tests use it directly; the driver
(``livebridge.drivers.dynamixel``) talks through the vendor's
``dynamixel_sdk``, whose packets these functions reproduce byte for byte.

Packet layout (ROBOTIS e-Manual, "DYNAMIXEL Protocol 2.0")::

    FF FF FD 00 | ID | LEN_L LEN_H | INST | PARAM ... | CRC_L CRC_H

``LEN`` counts INST + PARAM + CRC after byte stuffing. A status packet has
INST = 0x55 followed by the ERROR byte. Byte stuffing inserts an extra 0xFD
after every ``FF FF FD`` that appears from INST onwards, so a header can
never appear inside a packet. CRC-16 (polynomial 0x8005, initial 0) covers
every byte before the CRC, after stuffing.

The X-series control table (XL330, XM430) is described here too, as data:
the simulator serves it and the driver reads its addresses from it.
"""

from __future__ import annotations

from dataclasses import dataclass

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
MAX_ID = 0xFC

# Instructions.
PING = 0x01
READ = 0x02
WRITE = 0x03
REG_WRITE = 0x04
ACTION = 0x05
FACTORY_RESET = 0x06
REBOOT = 0x08
CLEAR = 0x10
STATUS = 0x55
SYNC_READ = 0x82
SYNC_WRITE = 0x83
FAST_SYNC_READ = 0x8A
BULK_READ = 0x92
BULK_WRITE = 0x93
FAST_BULK_READ = 0x9A

# Error byte of a status packet: bit 7 is the alert, the low bits a number.
ERROR_ALERT = 0x80
ERROR_RESULT_FAIL = 1
ERROR_INSTRUCTION = 2
ERROR_CRC = 3
ERROR_DATA_RANGE = 4
ERROR_DATA_LENGTH = 5
ERROR_DATA_LIMIT = 6
ERROR_ACCESS = 7
ERROR_NAMES = {
    0: "ok", ERROR_RESULT_FAIL: "result fail", ERROR_INSTRUCTION: "instruction error", ERROR_CRC: "CRC error",
    ERROR_DATA_RANGE: "data range error", ERROR_DATA_LENGTH: "data length error",
    ERROR_DATA_LIMIT: "data limit error", ERROR_ACCESS: "access error",
}

# Hardware Error Status (address 70) bits.
HW_INPUT_VOLTAGE = 0x01
HW_OVERHEATING = 0x04
HW_ENCODER = 0x08
HW_ELECTRICAL_SHOCK = 0x10
HW_OVERLOAD = 0x20
HW_ERROR_NAMES = {
    HW_INPUT_VOLTAGE: "input voltage", HW_OVERHEATING: "overheating", HW_ENCODER: "motor encoder",
    HW_ELECTRICAL_SHOCK: "electrical shock", HW_OVERLOAD: "overload",
}

# Baud Rate (address 8) codes of the X series.
BAUD_CODES = {0: 9600, 1: 57600, 2: 115200, 3: 1_000_000, 4: 2_000_000, 5: 3_000_000, 6: 4_000_000, 7: 4_500_000}

_CRC_TABLE: list[int] = []


def _build_crc_table() -> None:
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        _CRC_TABLE.append(crc & 0xFFFF)


_build_crc_table()


def crc16(data: bytes | bytearray, crc: int = 0) -> int:
    """CRC-16 of Protocol 2.0 (polynomial 0x8005, MSB first, initial ``crc``)."""
    table = _CRC_TABLE
    for byte in data:
        crc = ((crc << 8) ^ table[((crc >> 8) ^ byte) & 0xFF]) & 0xFFFF
    return crc


def stuff(head: bytes, body: bytes) -> bytes:
    """Byte-stuff ``body`` (INST + PARAM) that follows ``head`` (header, ID, LEN).

    An extra 0xFD is inserted after every ``FF FF FD`` whose last byte lies in
    ``body``; the two bytes before it may lie in ``head`` (as in the SDK).
    """
    out = bytearray()
    prev2, prev1 = head[-2], head[-1]
    for byte in body:
        out.append(byte)
        if byte == 0xFD and prev1 == 0xFF and prev2 == 0xFF:
            out.append(0xFD)
            prev2, prev1 = 0xFD, 0xFD
        else:
            prev2, prev1 = prev1, byte
    return bytes(out)


def unstuff(head: bytes, body: bytes) -> bytes:
    """Undo :func:`stuff`: drop the 0xFD after each ``FF FF FD``."""
    out = bytearray()
    prev2, prev1 = head[-2], head[-1]
    skip = False
    for byte in body:
        if skip:
            skip = False
            prev2, prev1 = 0xFD, 0xFD
            if byte == 0xFD:
                continue
        out.append(byte)
        if byte == 0xFD and prev1 == 0xFF and prev2 == 0xFF:
            skip = True
        prev2, prev1 = prev1, byte
    return bytes(out)


def _packet(servo_id: int, body: bytes) -> bytes:
    # LEN depends on the stuffed body, and stuffing may look back at LEN_L/LEN_H (as the SDK does),
    # so settle LEN by iterating (at most twice in practice).
    length = len(body) + 2
    for _ in range(4):
        head = HEADER + bytes([servo_id, length & 0xFF, length >> 8])
        stuffed = stuff(head, body)
        if len(stuffed) + 2 == length:
            break
        length = len(stuffed) + 2
    packet = head + stuffed
    crc = crc16(packet)
    return packet + bytes([crc & 0xFF, crc >> 8])


def encode_instruction(servo_id: int, instruction: int, params: bytes = b"") -> bytes:
    """One instruction packet, stuffed and with its CRC."""
    if not 0 <= servo_id <= BROADCAST_ID:
        raise ValueError(f"servo id {servo_id} outside 0..254")
    return _packet(servo_id, bytes([instruction]) + bytes(params))


def encode_status(servo_id: int, error: int, params: bytes = b"") -> bytes:
    """One status packet (INST 0x55), stuffed and with its CRC."""
    return _packet(servo_id, bytes([STATUS, error]) + bytes(params))


def u16(value: int) -> bytes:
    return int(value & 0xFFFF).to_bytes(2, "little")


def u32(value: int) -> bytes:
    return int(value & 0xFFFFFFFF).to_bytes(4, "little")


def to_int(data: bytes, signed: bool = False) -> int:
    return int.from_bytes(bytes(data), "little", signed=signed)


# Instruction builders (all return complete packets).

def ping(servo_id: int) -> bytes:
    return encode_instruction(servo_id, PING)


def read(servo_id: int, address: int, length: int) -> bytes:
    return encode_instruction(servo_id, READ, u16(address) + u16(length))


def write(servo_id: int, address: int, data: bytes) -> bytes:
    return encode_instruction(servo_id, WRITE, u16(address) + bytes(data))


def reg_write(servo_id: int, address: int, data: bytes) -> bytes:
    return encode_instruction(servo_id, REG_WRITE, u16(address) + bytes(data))


def action(servo_id: int = BROADCAST_ID) -> bytes:
    return encode_instruction(servo_id, ACTION)


def reboot(servo_id: int) -> bytes:
    return encode_instruction(servo_id, REBOOT)


def factory_reset(servo_id: int, option: int = 0xFF) -> bytes:
    """``option``: 0xFF everything, 0x01 all but the ID, 0x02 all but ID and baud rate."""
    return encode_instruction(servo_id, FACTORY_RESET, bytes([option]))


def sync_read(address: int, length: int, ids: list[int], fast: bool = False) -> bytes:
    return encode_instruction(BROADCAST_ID, FAST_SYNC_READ if fast else SYNC_READ,
                              u16(address) + u16(length) + bytes(ids))


def sync_write(address: int, length: int, data: dict[int, bytes]) -> bytes:
    """``data``: servo id -> exactly ``length`` bytes."""
    params = bytearray(u16(address) + u16(length))
    for servo_id, chunk in data.items():
        if len(chunk) != length:
            raise ValueError(f"sync write to id {servo_id}: {len(chunk)} bytes, expected {length}")
        params += bytes([servo_id]) + bytes(chunk)
    return encode_instruction(BROADCAST_ID, SYNC_WRITE, bytes(params))


def bulk_read(items: list[tuple[int, int, int]]) -> bytes:
    """``items``: (id, address, length) per servo."""
    params = b"".join(bytes([i]) + u16(a) + u16(n) for i, a, n in items)
    return encode_instruction(BROADCAST_ID, BULK_READ, params)


def bulk_write(items: list[tuple[int, int, bytes]]) -> bytes:
    """``items``: (id, address, data) per servo."""
    params = b"".join(bytes([i]) + u16(a) + u16(len(d)) + bytes(d) for i, a, d in items)
    return encode_instruction(BROADCAST_ID, BULK_WRITE, params)


def encode_fast_sync_status(replies: list[tuple[int, int, bytes]]) -> bytes:
    """The single status packet that answers FAST SYNC READ (and FAST BULK READ).

    ``replies``: (error, id, data) per servo, in request order. The packet has
    ID 0xFE; each servo's block is ``ERR ID DATA CRC`` where the CRC covers
    the packet so far (so the last block's CRC is the packet's CRC). No byte
    stuffing, as the SDK reads it raw.
    """
    body = bytearray()
    for error, servo_id, data in replies:
        body += bytes([error, servo_id]) + bytes(data) + b"\x00\x00"
    length = len(body) + 1
    packet = bytearray(HEADER + bytes([BROADCAST_ID, length & 0xFF, length >> 8, STATUS]))
    for error, servo_id, data in replies:
        packet += bytes([error, servo_id]) + bytes(data)
        crc = crc16(packet)
        packet += bytes([crc & 0xFF, crc >> 8])
    return bytes(packet)


@dataclass(frozen=True)
class Packet:
    """A decoded packet. ``params`` are unstuffed; ``error`` is set for status packets."""

    id: int
    instruction: int
    params: bytes
    error: int | None = None

    @property
    def is_status(self) -> bool:
        return self.instruction == STATUS


@dataclass(frozen=True)
class CorruptPacket:
    """A framed packet whose CRC did not match (``id`` as received, maybe wrong)."""

    id: int
    raw: bytes


class PacketReader:
    """Incremental framer: feed bytes, get whole packets out.

    Bytes before a header are skipped; a packet with a bad CRC comes out as
    :class:`CorruptPacket`; an absurd length drops the header byte and resyncs.
    """

    def __init__(self, max_length: int = 1024):
        self.buffer = bytearray()
        self.max_length = max_length

    def feed(self, data: bytes) -> list[Packet | CorruptPacket]:
        self.buffer += data
        out: list[Packet | CorruptPacket] = []
        buf = self.buffer
        while True:
            start = buf.find(HEADER)
            if start < 0:
                # keep a possible partial header at the end
                keep = 0
                for k in (3, 2, 1):
                    if buf.endswith(HEADER[:k]):
                        keep = k
                        break
                del buf[: len(buf) - keep]
                return out
            if start:
                del buf[:start]
            if len(buf) < 7:
                return out
            length = buf[5] | (buf[6] << 8)
            if length < 3 or length > self.max_length:
                del buf[:1]
                continue
            total = 7 + length
            if len(buf) < total:
                return out
            raw = bytes(buf[:total])
            del buf[:total]
            crc = raw[-2] | (raw[-1] << 8)
            if crc16(raw[:-2]) != crc:
                out.append(CorruptPacket(raw[4], raw))
                continue
            body = unstuff(raw[:7], raw[7:-2])
            if body[0] == STATUS and len(body) >= 2:
                out.append(Packet(raw[4], STATUS, body[2:], body[1]))
            else:
                out.append(Packet(raw[4], body[0], body[1:]))


def decode(packet: bytes) -> Packet:
    """Decode exactly one packet; raises ``ValueError`` if it is not one."""
    found = PacketReader().feed(packet)
    if len(found) != 1 or not isinstance(found[0], Packet):
        raise ValueError(f"not one valid packet: {packet.hex(' ')}")
    return found[0]


# --- X-series control table ---------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Field:
    """One control-table item: address, size in bytes, writable, in EEPROM, default, valid range."""

    name: str
    address: int
    size: int
    writable: bool
    eeprom: bool
    default: int
    low: int = 0
    high: int = 0xFFFFFFFF
    signed: bool = False


def _x_series_table(temperature_limit: int, current_limit: int, velocity_limit: int, pwm_limit: int = 885,
                    max_voltage: int = 70, min_voltage: int = 35) -> tuple[Field, ...]:
    return (
        Field("model_number", 0, 2, False, True, 0),
        Field("model_information", 2, 4, False, True, 0),
        Field("firmware_version", 6, 1, False, True, 0),
        Field("id", 7, 1, True, True, 1, 0, 252),
        Field("baud_rate", 8, 1, True, True, 1, 0, 7),
        Field("return_delay_time", 9, 1, True, True, 250, 0, 254),
        Field("drive_mode", 10, 1, True, True, 0, 0, 13),
        Field("operating_mode", 11, 1, True, True, 3, 0, 16),
        Field("secondary_id", 12, 1, True, True, 255, 0, 255),
        Field("protocol_type", 13, 1, True, True, 2, 1, 2),
        Field("homing_offset", 20, 4, True, True, 0, -1044479, 1044479, True),
        Field("moving_threshold", 24, 4, True, True, 10, 0, 1023),
        Field("temperature_limit", 31, 1, True, True, temperature_limit, 0, 100),
        Field("max_voltage_limit", 32, 2, True, True, max_voltage, 31, 140),
        Field("min_voltage_limit", 34, 2, True, True, min_voltage, 31, 140),
        Field("pwm_limit", 36, 2, True, True, pwm_limit, 0, 885),
        Field("current_limit", 38, 2, True, True, current_limit, 0, current_limit),
        Field("velocity_limit", 44, 4, True, True, velocity_limit, 0, 2047),
        Field("max_position_limit", 48, 4, True, True, 4095, 0, 4095),
        Field("min_position_limit", 52, 4, True, True, 0, 0, 4095),
        Field("shutdown", 63, 1, True, True, 52, 0, 255),
        Field("torque_enable", 64, 1, True, False, 0, 0, 1),
        Field("led", 65, 1, True, False, 0, 0, 1),
        Field("status_return_level", 68, 1, True, False, 2, 0, 2),
        Field("registered_instruction", 69, 1, False, False, 0),
        Field("hardware_error_status", 70, 1, False, False, 0),
        Field("velocity_i_gain", 76, 2, True, False, 1920, 0, 16383),
        Field("velocity_p_gain", 78, 2, True, False, 100, 0, 16383),
        Field("position_d_gain", 80, 2, True, False, 0, 0, 16383),
        Field("position_i_gain", 82, 2, True, False, 0, 0, 16383),
        Field("position_p_gain", 84, 2, True, False, 800, 0, 16383),
        Field("feedforward_2nd_gain", 88, 2, True, False, 0, 0, 16383),
        Field("feedforward_1st_gain", 90, 2, True, False, 0, 0, 16383),
        Field("bus_watchdog", 98, 1, True, False, 0, 0, 127),
        Field("goal_pwm", 100, 2, True, False, pwm_limit, -pwm_limit, pwm_limit, True),
        Field("goal_current", 102, 2, True, False, current_limit, -current_limit, current_limit, True),
        Field("goal_velocity", 104, 4, True, False, 0, -velocity_limit, velocity_limit, True),
        Field("profile_acceleration", 108, 4, True, False, 0, 0, 32767),
        Field("profile_velocity", 112, 4, True, False, 0, 0, 32767),
        Field("goal_position", 116, 4, True, False, 0, -1048575, 1048575, True),
        Field("realtime_tick", 120, 2, False, False, 0),
        Field("moving", 122, 1, False, False, 0),
        Field("moving_status", 123, 1, False, False, 0),
        Field("present_pwm", 124, 2, False, False, 0, signed=True),
        Field("present_current", 126, 2, False, False, 0, signed=True),
        Field("present_velocity", 128, 4, False, False, 0, signed=True),
        Field("present_position", 132, 4, False, False, 0, signed=True),
        Field("velocity_trajectory", 136, 4, False, False, 0, signed=True),
        Field("position_trajectory", 140, 4, False, False, 0, signed=True),
        Field("present_input_voltage", 144, 2, False, False, 0),
        Field("present_temperature", 146, 1, False, False, 0),
        Field("backup_ready", 147, 1, False, False, 0),
    )


@dataclass(frozen=True)
class Model:
    """An X-series model: number, the control table, and physical figures the simulator uses."""

    name: str
    number: int
    table: tuple[Field, ...]
    max_speed: float  # position units per second at no load
    nominal_voltage: float  # volts
    firmware: int = 46

    def field(self, name: str) -> Field:
        for item in self.table:
            if item.name == name:
                return item
        raise KeyError(name)


MODELS: dict[str, Model] = {
    "XL330-M288": Model("XL330-M288", 1200, _x_series_table(70, 1750, 445, max_voltage=70, min_voltage=31),
                        max_speed=103 / 60 * 4096, nominal_voltage=5.0),
    "XL330-M077": Model("XL330-M077", 1190, _x_series_table(70, 1750, 445, max_voltage=70, min_voltage=31),
                        max_speed=383 / 60 * 4096, nominal_voltage=5.0),
    "XM430-W350": Model("XM430-W350", 1020, _x_series_table(80, 1193, 128, max_voltage=160, min_voltage=95),
                        max_speed=46 / 60 * 4096, nominal_voltage=12.0),
    "XM430-W210": Model("XM430-W210", 1030, _x_series_table(80, 1193, 230, max_voltage=160, min_voltage=95),
                        max_speed=77 / 60 * 4096, nominal_voltage=12.0),
}
MODEL_BY_NUMBER = {model.number: model for model in MODELS.values()}
X_TABLE = {f.name: f for f in MODELS["XL330-M288"].table}
POSITION_RANGE = (0, 4095)
DRIVE_MODE_TIME_BASED = 0x04
FAST_SYNC_READ_MIN_FIRMWARE = 45  # assumption: X series firmware v45+ answers FAST SYNC READ
