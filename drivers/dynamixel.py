"""DYNAMIXEL X-series driver (Protocol 2.0) on the vendor's ``dynamixel_sdk``.

The only module of livebridge that imports ``dynamixel_sdk`` (inside
functions, so importing this module needs no SDK). Implements
:class:`livebridge.servo.bus.ServoBus`:

- ``scan``: broadcast ping (or ping a list), model number -> model name;
- ``configure``: ping + model check, torque off, position mode, time-based
  profile with profile velocity = the frame period (so each goal is reached
  just as the next arrives: smooth motion between frames), the rig's raw
  limits written to the servo's own min/max position limits;
- ``activate``: goal := present position, then torque on (the safety layer
  ramps from there: soft start);
- ``write``: one SYNC WRITE of all goal positions per frame;
- ``poll``: SYNC READ (FAST SYNC READ where the firmware has it) of present
  position each call, temperature and hardware error status every
  ``status_every`` calls; the alert bit of any status packet makes it read
  that servo's hardware error at once, mark it faulted and leave it out of
  the writes until :meth:`DynamixelBus.recover` (reboot, reconfigure, soft
  start) succeeds;
- ``estop``: broadcast torque off.

A hint is logged when a USB adapter's latency timer is above 1 ms. Replies are
waited for in ``select`` on the port, not in the SDK's spin of non-blocking
reads (:func:`sdk_port`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

from livebridge.devices.url import DeviceURL
from livebridge.drivers import dynamixel_protocol as dxl
from livebridge.drivers.serial_bus import SerialServoBus, clamp_whole, url_device
from livebridge.errors import InputError
from livebridge.servo.bus import BusFacts, ServoInfo, ServoSetup, ServoStatus

ADDR = {f.name: f.address for f in dxl.MODELS["XL330-M288"].table}
FACTS = BusFacts(kind="dynamixel", raw_range=dxl.POSITION_RANGE, address_range=(0, dxl.MAX_ID), address_key="id",
                 first_address=1, centre=2048.0, typical_span=400.0)
URL_PARAMETERS = ("baud",)


def latency_timer_hint(port: str) -> str | None:
    """A hint when the FTDI/USB-serial latency timer of ``port`` is above 1 ms (None if fine or unknown)."""
    name = Path(port).resolve().name
    timer = Path(f"/sys/bus/usb-serial/devices/{name}/latency_timer")
    try:
        value = int(timer.read_text().strip())
    except (OSError, ValueError):
        return None
    if value <= 1:
        return None
    return (f"{port}: USB latency timer is {value} ms; every read waits for it. "
            f"Set it to 1 ms: echo 1 | sudo tee {timer}")


def _fileno(ser) -> int | None:
    """The OS file descriptor of a pyserial port, or None where there is none (Windows, ``loop://``, closed)."""
    try:
        return ser.fileno()
    except (AttributeError, OSError, ValueError):  # pyserial's PortNotOpenError is an OSError
        return None


def sdk_port(port: str, timeout_margin_ms: float = 34.0):
    """A ``dynamixel_sdk.PortHandler`` for ``port`` (not opened) that waits for replies without spinning.

    The SDK waits the bytes' wire time + 2 x its 16 ms latency constant + 2 ms (34 ms) for a reply. A
    simulated bus is served by a thread of this machine: when the machine is loaded, that thread can be
    descheduled for longer than 34 ms, and a reply that comes after the client stopped waiting is then read
    as the reply to the *next* request. The margin (ms, beyond the wire time) is the instance's
    ``timeout_margin_ms`` attribute and may be changed at any time.

    The SDK's packet loops call ``readPort`` (a non-blocking read) over and over until the bytes or the
    timeout come: thousands of reads per status reply, CPU and GIL taken from the pipeline threads. This
    port's ``readPort`` sleeps in ``select`` on the serial fd until bytes arrive or the packet timeout
    passes, so each call returns with data or with the timeout due. The bytes on the wire and the SDK's
    results are unchanged; a port without a file descriptor reads as the SDK does.
    """
    import select

    from dynamixel_sdk import PortHandler

    class Port(PortHandler):
        def setPacketTimeout(self, packet_length):
            self.packet_start_time = self.getCurrentTime()
            self.packet_timeout = self.tx_time_per_byte * packet_length + self.timeout_margin_ms

        def readPort(self, length):
            data = self.ser.read(length)
            if data or length <= 0:
                return data
            wait_s = self._wait_left_ms() / 1000.0
            fd = _fileno(self.ser)
            if wait_s <= 0 or fd is None:
                return data  # timeout due (the SDK checks it next) or nothing to wait on: the SDK's own loop
            select.select([fd], [], [], wait_s)
            return self.ser.read(length)

        def _wait_left_ms(self) -> float:
            """Milliseconds until the packet timeout; at most one whole timeout (the SDK's clock is wall time)."""
            left = self.packet_start_time + self.packet_timeout - self.getCurrentTime()
            return min(left, self.packet_timeout)

    handler = Port(port)
    handler.timeout_margin_ms = float(timeout_margin_ms)
    return handler


class DynamixelBus(SerialServoBus):
    """A Protocol 2.0 bus of X-series servos (see the module docstring).

    Parameters
    ----------
    port : str
        Serial device (``/dev/ttyUSB0``) or a simulator's pty path.
    baud : int
        Bus baud rate (the servos must already use it).
    companion : object with ``close()``, optional
        Closed after the port when the bus closes (the simulated bus serving a ``simdynamixel://`` port).
    status_every : int
        Read temperature and hardware error status every this many polls.
    fast_read : bool or None
        Use FAST SYNC READ; ``None`` = when every servo's firmware has it.
    bus_watchdog_s : float, optional
        Arm each servo's bus watchdog (stops it if the host goes silent).
    return_delay_us : int, optional
        Set each servo's return delay time (EEPROM) during ``configure``.
    missing_after : int
        Consecutive polls without an answer before a servo is reported missing.
    timeout_margin_ms : float
        Reply timeout beyond the bytes' wire time (the SDK's default is 34 ms;
        simulated buses default to 150 ms so a busy machine does not lose replies).
    """

    kind = FACTS.kind

    def __init__(self, port: str, baud: int = 1_000_000, url: str | None = None, companion=None,
                 status_every: int = 10, fast_read: bool | None = None, bus_watchdog_s: float | None = None,
                 return_delay_us: int | None = None, missing_after: int = 5, clock=time.monotonic,
                 log=None, retries: int = 3, timeout_margin_ms: float = 34.0):
        from dynamixel_sdk import PacketHandler

        super().__init__(url or f"dynamixel://{port}?baud={baud}", companion, status_every, clock, log)
        self.fast_read = fast_read
        self.bus_watchdog_s = bus_watchdog_s
        self.return_delay_us = return_delay_us
        self.missing_after = missing_after
        self.retries = retries
        self.port = sdk_port(port, timeout_margin_ms)
        try:
            opened = self.port.openPort()
        except (OSError, ValueError) as error:  # pyserial: SerialException (an OSError) or ValueError
            raise InputError(f"cannot open serial port ({error})", self.url) from None
        if not opened or not self.port.setBaudRate(int(baud)):
            raise InputError(f"cannot open the port at {baud} baud", self.url)
        self.ph = PacketHandler(2.0)
        self.baud = int(baud)
        self.hint = latency_timer_hint(port)
        if self.hint:
            self.log(self.hint)
        self.infos: dict[int, ServoInfo] = {}
        self.events: list[tuple[float, int, str]] = []
        self._silent: dict[int, int] = {}
        self._temperature: dict[int, float] = {}
        self._hw_error: dict[int, int] = {}
        self._use_fast = False
        self._writer = None
        self.frame_period = 0.02
        self.stats = {"frames": 0, "tx_bytes": 0, "reads": 0, "read_failures": 0, "fast_failures": 0}

    # -- low level -------------------------------------------------------------------------------------------

    def _event(self, address: int, message: str) -> None:
        self.events.append((self.clock(), address, message))
        self.log(f"{self.url} id {address}: {message}")

    def _write_item(self, servo_id: int, name: str, value: int) -> int:
        """Write one control-table item with retries; returns the status error byte (raises if no answer)."""
        field = dxl.X_TABLE[name]
        writer = {1: self.ph.write1ByteTxRx, 2: self.ph.write2ByteTxRx, 4: self.ph.write4ByteTxRx}[field.size]
        result = None
        for _ in range(self.retries):
            result, error = writer(self.port, servo_id, field.address, int(value) & ((1 << (8 * field.size)) - 1))
            if result == 0:
                return error
        raise InputError(f"no answer writing {name} ({self.ph.getTxRxResult(result)})", self.url, f"id {servo_id}")

    def _read_item(self, servo_id: int, name: str) -> int | None:
        field = dxl.X_TABLE[name]
        reader = {1: self.ph.read1ByteTxRx, 2: self.ph.read2ByteTxRx, 4: self.ph.read4ByteTxRx}[field.size]
        for _ in range(self.retries):
            value, result, _ = reader(self.port, servo_id, field.address)
            if result == 0:
                if field.signed and value >= 1 << (8 * field.size - 1):
                    value -= 1 << (8 * field.size)
                return value
        return None

    def _sync_write(self, name: str, values: Mapping[int, int]) -> None:
        """One SYNC WRITE of field ``name``, encoded by :mod:`dynamixel_protocol` (spec byte stuffing, table
        CRC: a third of the SDK's per-frame cost) and written to the port. A broadcast write has no reply, so
        unlike the SDK's ``txPacket`` it leaves the input alone (every read clears it before it asks)."""
        if not values:
            return
        field = dxl.X_TABLE[name]
        mask = (1 << (8 * field.size)) - 1
        packet = dxl.sync_write(field.address, field.size,
                                {servo_id: (int(value) & mask).to_bytes(field.size, "little")
                                 for servo_id, value in values.items()})
        self.port.writePort(packet)
        self.stats["tx_bytes"] += len(packet)

    def sync_read(self, address: int, length: int, ids: Sequence[int]) -> dict[int, tuple[bytes, int]]:
        """SYNC READ (or FAST SYNC READ) ``length`` bytes at ``address``: id -> (data, status error byte)."""
        ids = list(ids)
        if not ids:
            return {}
        self.stats["reads"] += 1
        if self._use_fast:
            got = self._fast_sync_read(address, length, ids)
            if got is not None:
                return got
            self.stats["fast_failures"] += 1
        got: dict[int, tuple[bytes, int]] = {}
        if self.ph.syncReadTx(self.port, address, length, ids, len(ids), False) != 0:
            return got
        for _ in range(3 * len(ids)):
            rx, result = self.ph.rxPacket(self.port, False)
            if result == -3001:  # COMM_RX_TIMEOUT: nothing more is coming
                break
            if result != 0:
                continue  # corrupt reply: skip it, keep collecting the others
            servo_id = rx[4]
            # exactly this read's length: a late reply to an earlier read of another length is not data
            if servo_id in ids and len(rx) == 11 + length:
                got[servo_id] = (bytes(rx[9:9 + length]), rx[8])
            if len(got) == len(ids):
                break
        if len(got) < len(ids):
            self.stats["read_failures"] += 1
        return got

    def _fast_sync_read(self, address: int, length: int, ids: list[int]) -> dict[int, tuple[bytes, int]] | None:
        if self.ph.syncReadTx(self.port, address, length, ids, len(ids), True) != 0:
            return None
        rx, result = self.ph.rxPacket(self.port, True)
        if result != 0:
            return None
        got = {}
        index = 8
        for _ in ids:
            if index + 2 + length > len(rx):
                return None
            error, servo_id = rx[index], rx[index + 1]
            got[servo_id] = (bytes(rx[index + 2:index + 2 + length]), error)
            index += length + 4
        return got if set(got) == set(ids) else None

    # -- ServoBus ----------------------------------------------------------------------------------------------

    def scan(self, addresses: Sequence[int] | None = None) -> list[ServoInfo]:
        found: dict[int, tuple[int, int | None]] = {}
        if addresses is None:
            data, result = self.ph.broadcastPing(self.port)
            if result == 0:
                found = {i: (v[0], v[1]) for i, v in data.items()}
        else:
            for servo_id in addresses:
                for _ in range(self.retries):
                    model, result, _ = self.ph.ping(self.port, int(servo_id))
                    if result == 0:
                        firmware = self._read_item(servo_id, "firmware_version")
                        found[int(servo_id)] = (model, firmware)
                        break
        infos = []
        for servo_id in sorted(found):
            number, firmware = found[servo_id]
            model = dxl.MODEL_BY_NUMBER.get(number)
            infos.append(ServoInfo(servo_id, model.name if model else None, number, firmware))
        return infos

    def configure(self, servos: Sequence[ServoSetup], frame_period: float) -> None:
        self.frame_period = float(frame_period)
        wanted = {s.address: s for s in servos}
        infos = {i.address: i for i in self.scan(sorted(wanted))}
        missing = [wanted[a] for a in wanted if a not in infos]
        if missing:
            names = ", ".join(f"{s.name or 'servo'} (id {s.address})" for s in missing)
            raise InputError(f"no answer from {names}", self.url)
        for setup in servos:
            info = infos[setup.address]
            if setup.model and info.model != setup.model:
                raise InputError(f"id {setup.address} is a {info.model or info.model_number}, the rig says "
                                 f"{setup.model}", self.url, f"servo.{setup.name or setup.address}.model")
            lo, hi = dxl.POSITION_RANGE
            if not lo <= setup.low <= setup.high <= hi:
                raise InputError(f"limits {setup.low}..{setup.high} outside {lo}..{hi}", self.url,
                                 f"servo.{setup.name or setup.address}")
        self.servos = dict(wanted)
        self.infos = infos
        profile_ms = max(1, int(round(self.frame_period * 1000)))
        for servo_id, setup in self.servos.items():
            self._write_item(servo_id, "torque_enable", 0)
            if self.return_delay_us is not None:
                self._write_item(servo_id, "return_delay_time", int(self.return_delay_us) // 2)
            drive = self._read_item(servo_id, "drive_mode") or 0
            self._write_item(servo_id, "drive_mode", drive | dxl.DRIVE_MODE_TIME_BASED)
            self._write_item(servo_id, "operating_mode", 3)
            self._write_item(servo_id, "max_position_limit", int(math.floor(setup.high)))
            self._write_item(servo_id, "min_position_limit", int(math.ceil(setup.low)))
            self._write_item(servo_id, "profile_velocity", profile_ms)
            self._write_item(servo_id, "profile_acceleration", profile_ms // 4)
        firmware = [i.firmware for i in infos.values()]
        self._use_fast = self.fast_read if self.fast_read is not None else all(
            f is not None and f >= dxl.FAST_SYNC_READ_MIN_FIRMWARE for f in firmware)

    def present_positions(self, ids: Sequence[int] | None = None) -> dict[int, float]:
        ids = list(self.servos) if ids is None else list(ids)
        out: dict[int, float] = {}
        for _ in range(self.retries):
            rest = [i for i in ids if i not in out]
            if not rest:
                break
            for servo_id, (data, _) in self.sync_read(ADDR["present_position"], 4, rest).items():
                out[servo_id] = float(dxl.to_int(data, signed=True))
        return out

    def activate(self) -> dict[int, float]:
        positions = self.present_positions()
        for servo_id in self.servos:
            if servo_id not in positions:
                value = self._read_item(servo_id, "present_position")
                if value is None:
                    raise InputError("cannot read the present position", self.url, f"id {servo_id}")
                positions[servo_id] = float(value)
        goals = {i: self._clamp(i, p) for i, p in positions.items()}
        for servo_id, goal in goals.items():
            self._write_item(servo_id, "goal_position", goal)
            error = self._write_item(servo_id, "torque_enable", 1)
            if error & 0x7F:
                self._fault(servo_id, f"torque on refused ({dxl.ERROR_NAMES.get(error & 0x7F, error)})")
            if self.bus_watchdog_s:
                self._write_item(servo_id, "bus_watchdog", 0)
                self._write_item(servo_id, "bus_watchdog", max(1, min(127, round(self.bus_watchdog_s / 0.02))))
        self.faults = {i: f for i, f in self.faults.items() if i not in goals or f.startswith("torque")}
        return positions

    def _clamp(self, servo_id: int, value: float) -> int:
        return clamp_whole(self.servos[servo_id], value)

    def write(self, targets: Mapping[int, float]) -> None:
        values = {}
        for servo_id, target in targets.items():
            if servo_id in self.faults or servo_id not in self.servos or not math.isfinite(target):
                continue
            values[servo_id] = self._clamp(servo_id, target)
        self._sync_write("goal_position", values)
        self.stats["frames"] += 1

    def poll(self) -> dict[int, ServoStatus]:
        now = self.clock()
        ids = list(self.servos)
        got = self.sync_read(ADDR["present_position"], 4, ids)
        if self._status_due():
            for servo_id, (data, _) in self.sync_read(ADDR["present_temperature"], 1, ids).items():
                self._temperature[servo_id] = float(data[0])
            for servo_id, (data, _) in self.sync_read(ADDR["hardware_error_status"], 1, ids).items():
                self._hw_error[servo_id] = data[0]
                if data[0] and servo_id not in self.faults:
                    self._fault(servo_id, _hardware_error_text(data[0]))
        for servo_id in ids:
            if servo_id in got:
                data, error = got[servo_id]
                if self._silent.get(servo_id, 0) >= self.missing_after:
                    self._event(servo_id, "answering again")
                    if self.faults.get(servo_id) == "not answering":
                        self.faults[servo_id] = "reappeared (needs recover)"
                self._silent[servo_id] = 0
                if error & dxl.ERROR_ALERT and servo_id not in self.faults:
                    hw = self._read_item(servo_id, "hardware_error_status")
                    if hw:
                        self._hw_error[servo_id] = hw
                        self._fault(servo_id, _hardware_error_text(hw))
                position = float(dxl.to_int(data, signed=True))
            else:
                self._silent[servo_id] = self._silent.get(servo_id, 0) + 1
                if self._silent[servo_id] == self.missing_after:
                    self._fault(servo_id, "not answering")
                previous = self.status.get(servo_id)
                position = previous.position if previous else None
            self.status[servo_id] = ServoStatus(servo_id, position, self._temperature.get(servo_id),
                                                self._hw_error.get(servo_id, 0), self.faults.get(servo_id), now)
        return dict(self.status)

    def _fault(self, servo_id: int, text: str) -> None:
        self.faults[servo_id] = text
        self._event(servo_id, f"fault: {text}; servo left out of the writes")
        if text != "not answering":
            self.ph.write1ByteTxOnly(self.port, servo_id, ADDR["torque_enable"], 0)

    def recover(self, servo_id: int) -> bool:
        """Reboot a faulted servo, reconfigure it and torque it on at its present position; True on success."""
        setup = self.servos[servo_id]
        self.ph.reboot(self.port, servo_id)
        time.sleep(0.05)
        hw = self._read_item(servo_id, "hardware_error_status")
        if hw is None or hw:
            self._event(servo_id, f"recovery failed ({'no answer' if hw is None else _hardware_error_text(hw)})")
            return False
        profile_ms = max(1, int(round(self.frame_period * 1000)))
        self._write_item(servo_id, "profile_velocity", profile_ms)
        self._write_item(servo_id, "profile_acceleration", profile_ms // 4)
        position = self._read_item(servo_id, "present_position")
        if position is None:
            return False
        self._write_item(servo_id, "goal_position", self._clamp(servo_id, position))
        if self._write_item(servo_id, "torque_enable", 1) & 0x7F:
            return False
        del self.faults[servo_id]
        self._hw_error[servo_id] = 0
        self._event(servo_id, f"recovered at position {position} ({setup.name or 'servo'})")
        return True

    def estop(self) -> None:
        for _ in range(2):
            self.ph.write1ByteTxOnly(self.port, dxl.BROADCAST_ID, ADDR["torque_enable"], 0)

    def deactivate(self) -> None:
        self._sync_write("torque_enable", {i: 0 for i in self.servos})
        self.ph.write1ByteTxOnly(self.port, dxl.BROADCAST_ID, ADDR["torque_enable"], 0)

    def _close_port(self) -> None:
        if self.port.is_open:
            self.port.closePort()


def _hardware_error_text(bits: int) -> str:
    names = [name for bit, name in dxl.HW_ERROR_NAMES.items() if bits & bit]
    return "hardware error: " + (", ".join(names) if names else f"0x{bits:02x}")


def open_url(url: DeviceURL, **options) -> DynamixelBus:
    """``dynamixel:///dev/ttyUSB0?baud=1000000`` (the servos must already use that baud rate)."""
    url.check_known(URL_PARAMETERS)
    port = url_device(url, "dynamixel:///dev/ttyUSB0")
    return DynamixelBus(port, baud=url.take("baud", int, 1_000_000), url=url.url, **options)
