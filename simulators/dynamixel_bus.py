"""A simulated DYNAMIXEL Protocol 2.0 bus of X-series servos on a pseudo-terminal.

Byte-exact: framing, CRC-16, byte stuffing, status packets with the error
byte and the alert bit, PING (also broadcast), READ, WRITE, REG_WRITE/ACTION,
REBOOT, FACTORY_RESET, SYNC_READ, SYNC_WRITE, FAST_SYNC_READ, BULK_READ,
BULK_WRITE, status return level and return delay time, and the XL330/XM430
control table with the EEPROM area locked while torque is on. The vendor's
``dynamixel_sdk`` and our driver run against it unchanged.

Physics is deliberately simple and documented:

- motion follows the profile (``drive_mode`` bit 2 selects time-based, where
  profile velocity/acceleration are milliseconds; otherwise velocity-based in
  0.229 rpm and 214.577 rev/min^2 units), trapezoidal, never faster than the
  model's no-load speed;
- temperature relaxes toward ``ambient + 45 * load^2`` °C with a 20 s time
  constant; above the temperature limit the overheating bit is set, load
  above 1.0 for 1 s sets the overload bit; a set bit that is also in the
  ``shutdown`` mask turns torque off, and every status packet then carries
  the alert bit until a REBOOT clears the error (it trips again if the cause
  persists);
- the bus watchdog (address 98, 20 ms units) stops a servo that heard
  nothing for that long while torque is on, sets the item to 255 and refuses
  goal writes (data range error) until it is written 0.

Fault injection: ``corrupt_rate`` (a byte flipped in a reply),
``drop_rate`` (a reply not sent), :meth:`DynamixelSim.disconnect` (a servo
that disappears), :meth:`DynamixelSim.overheat` and :meth:`DynamixelSim.set_load`.
"""

from __future__ import annotations

import math
import random
import threading
import time
from dataclasses import dataclass, field

from livebridge.devices.url import DeviceURL, parse_ranges
from livebridge.drivers import dynamixel_protocol as dxl
from livebridge.drivers.dynamixel import DynamixelBus
from livebridge.errors import InputError
from livebridge.simulators.pty_bus import PtyDevice, Reply, open_on_pty, simulated_device

_TABLE_SIZE = 256
URL_PARAMETERS = ("ids", "model", "baud", "corrupt", "drop", "seed", "delay", "process")
SHUTDOWN_DELAY_S = 1.0  # overload must persist this long
THERMAL_TAU_S = 20.0


@dataclass
class _Motion:
    start: float
    goal: float
    t0: float
    duration: float
    t_acc: float

    def at(self, t: float) -> tuple[float, float]:
        """Position and velocity (units/s) at time ``t`` (trapezoidal profile)."""
        d = self.goal - self.start
        if self.duration <= 0 or t >= self.t0 + self.duration:
            return self.goal, 0.0
        s = max(0.0, t - self.t0)
        T, ta = self.duration, min(self.t_acc, self.duration / 2)
        v = d / (T - ta)
        if ta <= 0:
            return self.start + v * s, v
        a = v / ta
        if s < ta:
            return self.start + 0.5 * a * s * s, a * s
        if s <= T - ta:
            return self.start + 0.5 * a * ta * ta + v * (s - ta), v
        r = T - s
        return self.goal - 0.5 * a * r * r, a * r


@dataclass
class SimServo:
    """One simulated servo: its control table memory and physical state."""

    model: dxl.Model
    memory: bytearray = field(default_factory=lambda: bytearray(_TABLE_SIZE))
    position: float = 2048.0
    temperature: float = 30.0
    load: float = 0.0
    overload_since: float | None = None
    motion: _Motion | None = None
    registered: tuple[int, bytes] | None = None
    last_heard: float = 0.0
    connected: bool = True
    goals_received: int = 0

    def __post_init__(self):
        self.fields = {f.name: f for f in self.model.table}
        self.by_address = {}
        for f in self.model.table:
            for a in range(f.address, f.address + f.size):
                self.by_address[a] = f

    def reset(self, keep: tuple[str, ...] = ()) -> None:
        saved = {name: self.get(name) for name in keep}
        for f in self.model.table:
            self.set(f.name, f.default)
        self.set("model_number", self.model.number)
        self.set("firmware_version", self.model.firmware)
        for name, value in saved.items():
            self.set(name, value)
        self.reset_ram()

    def reset_ram(self) -> None:
        for f in self.model.table:
            if not f.eeprom and f.writable:
                self.set(f.name, f.default)
        self.set("hardware_error_status", 0)
        self.set("registered_instruction", 0)
        self.set("goal_position", int(round(self.position)))
        self.motion = None
        self.registered = None
        self.overload_since = None

    def get(self, name: str) -> int:
        f = self.fields[name]
        return int.from_bytes(self.memory[f.address:f.address + f.size], "little", signed=f.signed)

    def set(self, name: str, value: int) -> None:
        f = self.fields[name]
        self.memory[f.address:f.address + f.size] = (int(value) & ((1 << (8 * f.size)) - 1)).to_bytes(f.size,
                                                                                                      "little")

    @property
    def id(self) -> int:
        return self.get("id")

    @property
    def alert(self) -> bool:
        return self.get("hardware_error_status") != 0

    # -- physics ---------------------------------------------------------------------------------------------------

    def update(self, now: float, dt: float, ambient: float) -> None:
        if self.motion is not None:
            self.position, velocity = self.motion.at(now)
            if now >= self.motion.t0 + self.motion.duration:
                self.motion = None
        else:
            velocity = 0.0
        self.set("present_position", int(round(self.position)))
        self.set("present_velocity", int(round(velocity / (0.229 / 60 * 4096))))
        self.set("moving", int(self.motion is not None))
        self.set("present_current", int(round(self.load * self.get("current_limit"))) if self.torque_on else 0)
        self.set("present_input_voltage", int(self.model.nominal_voltage * 10))
        self.set("realtime_tick", int(now * 1000) % 32768)
        target = ambient + 45.0 * self.load ** 2 * (1.0 if self.torque_on else 0.0)
        if dt > 0:
            self.temperature += (target - self.temperature) * (1 - math.exp(-dt / THERMAL_TAU_S))
        self.set("present_temperature", int(round(self.temperature)))
        error = self.get("hardware_error_status")
        if self.temperature > self.get("temperature_limit"):
            error |= dxl.HW_OVERHEATING
        if self.torque_on and self.load > 1.0:
            if self.overload_since is None:
                self.overload_since = now
            elif now - self.overload_since >= SHUTDOWN_DELAY_S:
                error |= dxl.HW_OVERLOAD
        else:
            self.overload_since = None
        if error != self.get("hardware_error_status"):
            self.set("hardware_error_status", error)
        if error & self.get("shutdown") and self.torque_on:
            self.set("torque_enable", 0)
            self.stop(now)
        watchdog = self.get("bus_watchdog")
        if 0 < watchdog < 255 and self.torque_on and now - self.last_heard > watchdog * 0.020:
            self.set("bus_watchdog", 255)
            self.stop(now)

    @property
    def torque_on(self) -> bool:
        return self.memory[64] == 1

    def stop(self, now: float) -> None:
        """Halt where it is (torque off, shutdown, watchdog); the goal position item keeps its value."""
        if self.motion is not None:
            self.position, _ = self.motion.at(now)
        self.motion = None

    def start_motion(self, goal: int, now: float) -> None:
        if self.motion is not None:
            self.position, _ = self.motion.at(now)
        distance = abs(goal - self.position)
        pv, pa = self.get("profile_velocity"), self.get("profile_acceleration")
        fastest = distance / self.model.max_speed
        if self.get("drive_mode") & dxl.DRIVE_MODE_TIME_BASED:
            duration, t_acc = pv / 1000.0, pa / 1000.0
        else:
            v = pv * 0.229 / 60 * 4096 if pv else self.model.max_speed
            a = pa * 214.577 / 3600 * 4096 if pa else math.inf
            t_acc = v / a
            duration = distance / v + t_acc if distance else 0.0
        duration = max(duration, fastest)
        self.motion = _Motion(self.position, float(goal), now, duration, min(t_acc, duration / 2))


class DynamixelSim(PtyDevice):
    """Several X-series servos on one simulated Protocol 2.0 bus.

    Parameters
    ----------
    ids : iterable of int
        Servo IDs on the bus.
    model : str
        A key of :data:`livebridge.drivers.dynamixel_protocol.MODELS`, or a
        dict id -> model name for a mixed bus.
    baud : int
        The baud rate the servos are set to (recorded in address 8; a pty
        moves bytes at any rate).
    corrupt_rate, drop_rate : float
        Probability that a status packet gets one byte flipped / is not sent.
    seed : int
        Seed of the fault-injection random generator.
    return_delay_time : int, optional
        Override address 9 (2 µs units) of every servo; default the model's 250.
    """

    tick_period = 0.01

    def __init__(self, ids=(1,), model: str | dict[int, str] = "XL330-M288", baud: int = 1_000_000,
                 corrupt_rate: float = 0.0, drop_rate: float = 0.0, seed: int = 0,
                 return_delay_time: int | None = None, ambient: float = 30.0, clock=time.monotonic,
                 start_position: float = 2048.0):
        self.clock = clock
        self.ambient = ambient
        self.corrupt_rate = corrupt_rate
        self.drop_rate = drop_rate
        self.random = random.Random(seed)
        self.lock = threading.RLock()
        self.reader = dxl.PacketReader()
        self.servos: dict[int, SimServo] = {}
        self.stats = {"packets": 0, "corrupt_in": 0, "replies": 0, "corrupted_out": 0, "dropped_out": 0}
        self.goal_log: list[tuple[float, int, int]] = []  # (t, id, goal) of every goal position received
        self.log_goals = False
        baud_code = {v: k for k, v in dxl.BAUD_CODES.items()}.get(baud, 3)
        now = clock()
        for servo_id in ids:
            name = model[servo_id] if isinstance(model, dict) else model
            if name not in dxl.MODELS:
                raise ValueError(f"unknown model {name!r}; known: {', '.join(dxl.MODELS)}")
            servo = SimServo(dxl.MODELS[name], position=start_position, temperature=ambient)
            servo.reset()
            servo.set("id", servo_id)
            servo.set("baud_rate", baud_code)
            if return_delay_time is not None:
                servo.set("return_delay_time", return_delay_time)
            servo.last_heard = now
            servo.update(now, 0.0, ambient)
            self.servos[servo_id] = servo
        self._last_tick = now

    # -- serving -----------------------------------------------------------------------------------------------

    @property
    def path(self) -> str:
        if self.pty is None:
            raise RuntimeError("simulator not started")
        return self.pty.path

    def tick(self) -> None:
        with self.lock:
            now = self.clock()
            dt, self._last_tick = now - self._last_tick, now
            for servo in self.servos.values():
                servo.update(now, dt, self.ambient)

    # -- fault injection ---------------------------------------------------------------------------------------

    def disconnect(self, servo_id: int) -> None:
        """The servo disappears from the bus: it hears and answers nothing."""
        with self.lock:
            self.servos[servo_id].connected = False

    def reconnect(self, servo_id: int) -> None:
        with self.lock:
            self.servos[servo_id].connected = True

    def overheat(self, servo_id: int, excess: float = 8.0) -> None:
        """Heat the servo ``excess`` °C above its temperature limit (it then cools with the thermal model)."""
        with self.lock:
            servo = self.servos[servo_id]
            servo.temperature = servo.get("temperature_limit") + excess
            servo.update(self.clock(), 0.0, self.ambient)

    def set_load(self, servo_id: int, load: float) -> None:
        """External load as a fraction of the current limit (>1 overloads after 1 s)."""
        with self.lock:
            self.servos[servo_id].load = float(load)

    def servo(self, servo_id: int) -> SimServo:
        return self.servos[servo_id]

    # -- protocol ----------------------------------------------------------------------------------------------

    def handle(self, data: bytes) -> list[Reply]:
        """Bytes from the client -> replies (delay, bytes), in order."""
        replies: list[Reply] = []
        with self.lock:
            now = self.clock()
            dt, self._last_tick = now - self._last_tick, now
            for servo in self.servos.values():
                servo.update(now, dt, self.ambient)
            for packet in self.reader.feed(data):
                if isinstance(packet, dxl.CorruptPacket):
                    self.stats["corrupt_in"] += 1
                    servo = self._find(packet.id)
                    if servo is not None and servo.get("status_return_level") >= 1:
                        replies.append(self._status(servo, dxl.ERROR_CRC))
                    continue
                if packet.is_status:
                    continue  # another device's status (e.g. our own echo); not for us
                self.stats["packets"] += 1
                replies.extend(self._dispatch(packet, now))
        return [r for r in (self._inject(r) for r in replies) if r is not None]

    def _inject(self, reply: Reply) -> Reply | None:
        delay, data = reply
        sent = self.inject_fault(data)
        if sent is None:
            self.stats["dropped_out"] += 1
            return None
        if sent != data:
            self.stats["corrupted_out"] += 1
        self.stats["replies"] += 1
        return delay, sent

    def _find(self, servo_id: int) -> SimServo | None:
        for servo in self.servos.values():
            if servo.connected and servo.id == servo_id:
                return servo
        return None

    def _present(self) -> list[SimServo]:
        return sorted((s for s in self.servos.values() if s.connected), key=lambda s: s.id)

    def _status(self, servo: SimServo, error: int = 0, params: bytes = b"") -> Reply:
        if servo.alert:
            error |= dxl.ERROR_ALERT
        delay = servo.get("return_delay_time") * 2e-6
        return delay, dxl.encode_status(servo.id, error, params)

    def _dispatch(self, packet: dxl.Packet, now: float) -> list[Reply]:
        inst, p = packet.instruction, packet.params
        broadcast = packet.id == dxl.BROADCAST_ID
        targets = self._present() if broadcast else [s for s in [self._find(packet.id)] if s is not None]
        for servo in targets:
            servo.last_heard = now
        if inst == dxl.PING:
            return [self._status(s, 0, dxl.u16(s.model.number) + bytes([s.model.firmware])) for s in targets]
        if inst in (dxl.SYNC_READ, dxl.FAST_SYNC_READ):
            return self._sync_read(p, inst == dxl.FAST_SYNC_READ, now)
        if inst == dxl.SYNC_WRITE:
            self._sync_write(p, now)
            return []
        if inst in (dxl.BULK_READ, dxl.FAST_BULK_READ):
            return self._bulk_read(p, inst == dxl.FAST_BULK_READ, now)
        if inst == dxl.BULK_WRITE:
            self._bulk_write(p, now)
            return []
        replies = []
        for servo in targets:
            level = servo.get("status_return_level")  # the level before this instruction decides its reply
            error, params = self._single(servo, inst, p, now)
            wants = level >= 2 or (level == 1 and inst == dxl.READ)
            if not broadcast and wants:
                replies.append(self._status(servo, error, params))
            if inst == dxl.REBOOT and error == 0:
                servo.stop(now)
                servo.reset_ram()
            elif inst == dxl.FACTORY_RESET and error == 0:
                option = p[0] if p else 0xFF
                servo.reset(keep={0xFF: (), 0x01: ("id",), 0x02: ("id", "baud_rate")}.get(option, ()))
        return replies

    def _single(self, servo: SimServo, inst: int, p: bytes, now: float) -> tuple[int, bytes]:
        if inst == dxl.READ:
            if len(p) != 4:
                return dxl.ERROR_DATA_LENGTH, b""
            address, length = dxl.to_int(p[:2]), dxl.to_int(p[2:4])
            if address + length > _TABLE_SIZE:
                return dxl.ERROR_ACCESS, b""
            return 0, bytes(servo.memory[address:address + length])
        if inst in (dxl.WRITE, dxl.REG_WRITE):
            if len(p) < 3:
                return dxl.ERROR_DATA_LENGTH, b""
            address, data = dxl.to_int(p[:2]), p[2:]
            error = self._check_write(servo, address, data)
            if error:
                return error, b""
            if inst == dxl.WRITE:
                self._apply_write(servo, address, data, now)
            else:
                servo.registered = (address, data)
                servo.set("registered_instruction", 1)
            return 0, b""
        if inst == dxl.ACTION:
            if servo.registered is None:
                return dxl.ERROR_RESULT_FAIL, b""
            address, data = servo.registered
            servo.registered = None
            servo.set("registered_instruction", 0)
            self._apply_write(servo, address, data, now)
            return 0, b""
        if inst == dxl.REBOOT:
            return 0, b""
        if inst == dxl.FACTORY_RESET:
            if servo.torque_on:
                return dxl.ERROR_RESULT_FAIL, b""
            return 0, b""
        return dxl.ERROR_INSTRUCTION, b""

    def _check_write(self, servo: SimServo, address: int, data: bytes) -> int:
        end = address + len(data)
        covered = set()
        for a in range(address, end):
            f = servo.by_address.get(a)
            if f is None or not f.writable:
                return dxl.ERROR_ACCESS
            if f.eeprom and servo.torque_on:
                return dxl.ERROR_ACCESS
            covered.add(f)
        for f in covered:
            if f.address < address or f.address + f.size > end:
                return dxl.ERROR_DATA_LENGTH  # partial item
            value = int.from_bytes(data[f.address - address:f.address - address + f.size], "little",
                                   signed=f.signed)
            if not f.low <= value <= f.high:
                return dxl.ERROR_DATA_RANGE
            if f.name == "torque_enable" and value == 1 and servo.alert:
                return dxl.ERROR_RESULT_FAIL
            if f.name == "goal_position":
                if self.log_goals:
                    self.goal_log.append((self.clock(), servo.id, value))
                servo.goals_received += 1
                if servo.get("bus_watchdog") == 255:
                    return dxl.ERROR_DATA_RANGE
                if servo.get("operating_mode") == 3 and not (
                        servo.get("min_position_limit") <= value <= servo.get("max_position_limit")):
                    return dxl.ERROR_DATA_LIMIT
        return 0

    def _apply_write(self, servo: SimServo, address: int, data: bytes, now: float) -> None:
        was_on = servo.torque_on
        servo.memory[address:address + len(data)] = data
        if address <= 64 < address + len(data) and was_on and not servo.torque_on:
            servo.stop(now)
        if address < 120 and address + len(data) > 116 and servo.torque_on:
            servo.start_motion(servo.get("goal_position"), now)
        elif address <= 64 < address + len(data) and servo.torque_on and not was_on:
            servo.start_motion(servo.get("goal_position"), now)

    def _sync_read(self, p: bytes, fast: bool, now: float) -> list[Reply]:
        if len(p) < 5:
            return []
        address, length, ids = dxl.to_int(p[:2]), dxl.to_int(p[2:4]), list(p[4:])
        replies = []
        blocks = []
        for servo_id in ids:
            servo = self._find(servo_id)
            if servo is None:
                if fast:
                    break  # the chain of replies stops at a missing servo
                continue
            servo.last_heard = now
            ok = address + length <= _TABLE_SIZE
            data = bytes(servo.memory[address:address + length]) if ok else b""
            error = (0 if ok else dxl.ERROR_ACCESS) | (dxl.ERROR_ALERT if servo.alert else 0)
            if fast:
                blocks.append((error, servo_id, data.ljust(length, b"\x00")))
            else:
                replies.append(self._status(servo, error & 0x7F, data))
        if fast and blocks:
            first = self._find(ids[0])
            packet = bytearray(dxl.encode_fast_sync_status(blocks))
            if len(blocks) < len(ids):  # the header claims every servo; the missing ones never come
                claimed = len(ids) * (length + 4) + 1
                packet[5:7] = dxl.u16(claimed)
            replies.append((first.get("return_delay_time") * 2e-6 if first else 0.0, bytes(packet)))
        return replies

    def _sync_write(self, p: bytes, now: float) -> None:
        if len(p) < 4:
            return
        address, length = dxl.to_int(p[:2]), dxl.to_int(p[2:4])
        i = 4
        while i + 1 + length <= len(p):
            servo = self._find(p[i])
            data = p[i + 1:i + 1 + length]
            i += 1 + length
            if servo is None:
                continue
            servo.last_heard = now
            if self._check_write(servo, address, data) == 0:
                self._apply_write(servo, address, data, now)

    def _bulk_read(self, p: bytes, fast: bool, now: float) -> list[Reply]:
        replies, blocks = [], []
        for i in range(0, len(p) - 4, 5):
            servo_id, address, length = p[i], dxl.to_int(p[i + 1:i + 3]), dxl.to_int(p[i + 3:i + 5])
            servo = self._find(servo_id)
            if servo is None:
                continue
            servo.last_heard = now
            data = bytes(servo.memory[address:address + length])
            if fast:
                blocks.append((dxl.ERROR_ALERT if servo.alert else 0, servo_id, data))
            else:
                replies.append(self._status(servo, 0, data))
        if fast and blocks:
            replies.append((0.0, dxl.encode_fast_sync_status(blocks)))
        return replies

    def _bulk_write(self, p: bytes, now: float) -> None:
        i = 0
        while i + 5 <= len(p):
            servo_id, address, length = p[i], dxl.to_int(p[i + 1:i + 3]), dxl.to_int(p[i + 3:i + 5])
            data = p[i + 5:i + 5 + length]
            i += 5 + length
            servo = self._find(servo_id)
            if servo is None:
                continue
            servo.last_heard = now
            if self._check_write(servo, address, data) == 0:
                self._apply_write(servo, address, data, now)


def parse_ids(text: str) -> list[int]:
    """``"1-4,7"`` -> ``[1, 2, 3, 4, 7]``: ids 0..252, none twice, bounds checked before a range is expanded
    (:func:`~livebridge.devices.url.parse_ranges`); raises :class:`~livebridge.errors.InputError`."""
    return parse_ranges(text, 0, dxl.MAX_ID)


def open_url(url: DeviceURL, **options) -> DynamixelBus:
    """``simdynamixel://?ids=1-16&model=XL330-M288&process=1``: a simulated bus on a pseudo-terminal and the
    real driver on it; closing the bus closes the simulator.

    Parameters in the URL: ``ids`` (default 1), ``model``, ``baud``, ``corrupt``, ``drop`` (fault rates),
    ``seed``, ``delay`` (return delay time, 2 µs units), ``process=1`` (serve it from its own process, as
    hardware would be). ``options``: :class:`~livebridge.drivers.dynamixel.DynamixelBus` keyword arguments;
    the reply timeout margin defaults to 150 ms (a simulator shares this machine's CPUs).
    """
    url.check_known(URL_PARAMETERS)
    baud = url.take("baud", int, 1_000_000)
    try:
        ids = parse_ids(url.query.get("ids", "1"))
    except InputError as error:
        raise InputError(error.message, url.url, "ids") from None
    settings = {"ids": ids, "model": url.query.get("model", "XL330-M288"), "baud": baud,
                "corrupt_rate": url.take("corrupt", float, 0.0, within=(0, 1)),
                "drop_rate": url.take("drop", float, 0.0, within=(0, 1)),
                "seed": url.take("seed", int, 0, within=(0, 2**32 - 1)),
                "return_delay_time": url.take("delay", int, within=(0, 254))}
    own_process = url.take("process", bool, False)
    try:
        sim = simulated_device(DynamixelSim, settings, own_process)
    except ValueError as error:  # an unknown model
        raise InputError(str(error), url.url) from None
    options.setdefault("timeout_margin_ms", 150.0)
    return open_on_pty(sim, lambda path: DynamixelBus(path, baud=baud, url=url.url, companion=sim, **options))
