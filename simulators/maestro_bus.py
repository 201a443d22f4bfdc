"""A simulated Pololu Maestro on a pseudo-terminal (compact and Pololu protocols).

Byte-exact command parsing (set target, set multiple targets, set speed, set
acceleration, get position, get moving state, get errors, go home); channel
outputs move toward their targets limited by speed (0.25 µs / 10 ms) and
acceleration (0.25 µs / 10 ms / 80 ms) as the Maestro does; targets are
clamped to each channel's [min, max] (default 500..2500 µs here; a new
Maestro ships with 992..2000 µs). A malformed command sets the serial
protocol error bit (bit 4), cleared by get errors. Commands in the Pololu
protocol for another device number are ignored. Fault injection as the
Dynamixel simulator: corrupted or dropped replies. Commands are decoded by
:mod:`livebridge.drivers.maestro_protocol`; :func:`open_url` serves the
``simmaestro://`` scheme with the real driver on the pseudo-terminal.
"""

from __future__ import annotations

import random
import threading
import time

from livebridge.devices.url import DeviceURL
from livebridge.drivers import maestro_protocol as mp
from livebridge.drivers.maestro import MaestroBus
from livebridge.simulators.pty_bus import PtyDevice, Reply, open_on_pty, simulated_device

URL_PARAMETERS = ("channels", "device", "baud", "corrupt", "drop", "seed", "process")


class MaestroSim(PtyDevice):
    """A Maestro with ``channels`` servo channels, device number ``device``."""

    tick_period = 0.01

    def __init__(self, channels: int = 24, device: int = 12, range_us=(500.0, 2500.0), home_us: float = 0.0,
                 corrupt_rate: float = 0.0, drop_rate: float = 0.0, seed: int = 0, clock=time.monotonic):
        self.channels = channels
        self.device = device
        self.low, self.high = (int(range_us[0] * 4), int(range_us[1] * 4))
        self.home = int(home_us * 4)
        self.target = [0] * channels
        self.position = [0.0] * channels
        self.velocity = [0.0] * channels
        self.speed = [0] * channels
        self.acceleration = [0] * channels
        self.errors = 0
        self.corrupt_rate, self.drop_rate = corrupt_rate, drop_rate
        self.random = random.Random(seed)
        self.clock = clock
        self.lock = threading.RLock()
        self.buffer = bytearray()
        self.target_log: list[tuple[int, int]] = []  # (channel, quarter-µs) of every target received
        self.commands = 0
        self._last = clock()

    def tick(self) -> None:
        with self.lock:
            now = self.clock()
            dt, self._last = now - self._last, now
            for c in range(self.channels):
                self._move(c, dt)

    def _move(self, c: int, dt: float) -> None:
        goal = self.target[c]
        if goal == 0 or self.position[c] == 0:
            self.position[c] = float(goal)
            return
        d = goal - self.position[c]
        speed = self.speed[c] * 100.0 if self.speed[c] else float("inf")  # quarter-µs per second
        step = min(abs(d), speed * dt)
        if self.acceleration[c]:
            a = self.acceleration[c] * 100.0 / 0.08  # quarter-µs per s^2
            v = min(abs(self.velocity[c]) + a * dt, speed, (2 * a * abs(d)) ** 0.5)
            step = min(abs(d), v * dt)
            self.velocity[c] = v if d else 0.0
        self.position[c] += step if d > 0 else -step

    def handle(self, data: bytes) -> list[Reply]:
        with self.lock:
            self.tick()
            self.buffer += data
            replies = []
            while self.buffer:
                used, reply = self._parse()
                if used == 0:
                    break
                del self.buffer[:used]
                if reply:
                    replies.append(reply)
        return [(0.0, reply) for reply in map(self.inject_fault, replies) if reply is not None]

    def _parse(self) -> tuple[int, bytes | None]:
        """Consume one command from the buffer: (bytes used, reply); (0, None) when incomplete."""
        decoded = mp.decode_command(self.buffer)
        if decoded.protocol_error:
            self.errors |= mp.PROTOCOL_ERROR
        command = decoded.command
        if command is None or (command.device is not None and command.device != self.device):
            return decoded.used, None
        self.commands += 1
        return decoded.used, self._execute(command.command, command.data)

    def _channel(self, c: int) -> bool:
        if c >= self.channels:
            self.errors |= mp.PROTOCOL_ERROR
            return False
        return True

    def _set_target(self, c: int, value: int) -> None:
        self.target_log.append((c, value))
        if value and self.position[c] == 0:
            self.position[c] = float(min(self.high, max(self.low, value)))
        self.target[c] = 0 if value == 0 else min(self.high, max(self.low, value))

    def _execute(self, command: int, data: bytes) -> bytes | None:
        if command == mp.SET_TARGET:
            if self._channel(data[0]):
                self._set_target(data[0], mp.join14(data[1], data[2]))
        elif command == mp.SET_MULTIPLE_TARGETS:
            n, first = data[0], data[1]
            for k in range(n):
                if self._channel(first + k):
                    self._set_target(first + k, mp.join14(data[2 + 2 * k], data[3 + 2 * k]))
        elif command == mp.SET_SPEED:
            if self._channel(data[0]):
                self.speed[data[0]] = mp.join14(data[1], data[2])
        elif command == mp.SET_ACCELERATION:
            if self._channel(data[0]):
                self.acceleration[data[0]] = mp.join14(data[1], data[2])
        elif command == mp.GET_POSITION:
            if self._channel(data[0]):
                return mp.encode_u16(int(round(self.position[data[0]])))
        elif command == mp.GET_MOVING_STATE:
            return bytes([int(any(abs(p - t) > 0.5 for p, t in zip(self.position, self.target) if t))])
        elif command == mp.GET_ERRORS:
            errors, self.errors = self.errors, 0
            return mp.encode_u16(errors)
        elif command == mp.GO_HOME:
            for c in range(self.channels):
                self._set_target(c, self.home)
        return None


def open_url(url: DeviceURL, **options) -> MaestroBus:
    """``simmaestro://?channels=24&device=12&baud=115200&corrupt=0&drop=0&seed=0&process=0``: a simulated
    Maestro on a pseudo-terminal (``process=1``: served from its own process) and the real driver on it;
    closing the bus closes the simulator. ``device`` also makes the driver use the Pololu protocol.
    ``options``: :class:`~livebridge.drivers.maestro.MaestroBus` keyword arguments."""
    url.check_known(URL_PARAMETERS)
    device, baud = url.take("device", int, within=(0, 127)), url.take("baud", int, 115200)
    sim = simulated_device(MaestroSim, {"channels": url.take("channels", int, 24, within=(1, 24)),
                                        "device": mp.DEFAULT_DEVICE if device is None else device,
                                        "corrupt_rate": url.take("corrupt", float, 0.0, within=(0, 1)),
                                        "drop_rate": url.take("drop", float, 0.0, within=(0, 1)),
                                        "seed": url.take("seed", int, 0, within=(0, 2**32 - 1))},
                           url.take("process", bool, False))
    return open_on_pty(sim, lambda path: MaestroBus(path, baud=baud, device=device, url=url.url, companion=sim,
                                                    **options))
