"""A simulated Lynxmotion SSC-32U on a pseudo-terminal (ASCII protocol).

Parses ``#<ch>P<pw>[S<spd>]...[T<ms>]\\r`` group moves (all channels of a
group finish together after ``T`` ms, linear in time; ``S`` limits a
channel's speed in µs/s), ``Q`` (``+`` moving / ``.`` done), ``QP<ch>`` (one
byte per channel, µs / 10), ``VER`` and ``STOP<ch>``. Pulse widths are
clamped to 500..2500 µs; ``P0`` turns a channel off. Unknown text is
ignored, as the controller does. Fault injection: corrupted or dropped replies.
Lines are decoded by :mod:`livebridge.drivers.ssc32_protocol`; :func:`open_url`
serves the ``simssc32://`` scheme with the real driver on the pseudo-terminal.
"""

from __future__ import annotations

import random
import threading
import time

from livebridge.devices.url import DeviceURL
from livebridge.drivers import ssc32_protocol as sp
from livebridge.drivers.ssc32 import SSC32Bus
from livebridge.simulators.pty_bus import PtyDevice, Reply, open_on_pty, simulated_device

VERSION = b"SSC32-V2.50USB"
URL_PARAMETERS = ("channels", "baud", "corrupt", "drop", "seed", "process")


class SSC32Sim(PtyDevice):
    """32 channels, pulse widths in µs (0 = off)."""

    def __init__(self, channels: int = 32, corrupt_rate: float = 0.0, drop_rate: float = 0.0, seed: int = 0,
                 clock=time.monotonic):
        self.channels = channels
        self.clock = clock
        self.start_pw = [0.0] * channels
        self.goal = [0.0] * channels
        self.t0 = [0.0] * channels
        self.duration = [0.0] * channels
        self.corrupt_rate, self.drop_rate = corrupt_rate, drop_rate
        self.random = random.Random(seed)
        self.lock = threading.RLock()
        self.buffer = bytearray()
        self.move_log: list[tuple[int, int]] = []  # (channel, µs) of every pulse width commanded
        self.commands = 0

    def pulse(self, channel: int, now: float | None = None) -> float:
        """Pulse width being output on ``channel`` now, µs."""
        now = self.clock() if now is None else now
        if self.goal[channel] == 0 or self.start_pw[channel] == 0 or self.duration[channel] <= 0:
            return self.goal[channel]
        s = min(1.0, max(0.0, (now - self.t0[channel]) / self.duration[channel]))
        return self.start_pw[channel] + s * (self.goal[channel] - self.start_pw[channel])

    def moving(self, now: float) -> bool:
        return any(self.goal[c] and abs(self.pulse(c, now) - self.goal[c]) > 0.5 for c in range(self.channels))

    def handle(self, data: bytes) -> list[Reply]:
        replies = []
        with self.lock:
            self.buffer += data
            while b"\r" in self.buffer:
                line, _, rest = bytes(self.buffer).partition(b"\r")
                self.buffer = bytearray(rest)
                reply = self._line(line)
                if reply:
                    replies.append(reply)
        return [(0.0, reply) for reply in map(self.inject_fault, replies) if reply is not None]

    def _line(self, line: bytes) -> bytes | None:
        now = self.clock()
        self.commands += 1
        decoded = sp.decode_line(line)
        reply = bytearray()
        for name, c in decoded.queries:  # answered (and stops done) at the time the line arrives
            if name == "QP":
                reply.append(sp.encode_pulse(self.pulse(c, now)) if c < self.channels else 0)
            elif name == "STOP":
                if c < self.channels:
                    self.goal[c] = self.start_pw[c] = self.pulse(c, now)
            elif name == "VER":
                reply += VERSION + b"\r"
            elif name == "Q":
                reply += b"+" if self.moving(now) else b"."
        for move in decoded.moves:
            c, pw = move.channel, move.pulse
            if c >= self.channels or pw is None:
                continue
            self.move_log.append((c, pw))
            if pw == 0:
                self.goal[c] = self.start_pw[c] = 0.0
                continue
            pw = float(min(sp.PULSE_RANGE[1], max(sp.PULSE_RANGE[0], pw)))
            start = self.pulse(c, now)
            duration = (decoded.time_ms or 0) / 1000.0
            if move.speed is not None and move.speed > 0 and start:
                duration = max(duration, abs(pw - start) / move.speed)
            self.start_pw[c], self.goal[c], self.t0[c], self.duration[c] = (start or pw), pw, now, duration
        return bytes(reply) if reply else None


def open_url(url: DeviceURL, **options) -> SSC32Bus:
    """``simssc32://?channels=32&baud=115200&corrupt=0&drop=0&seed=0&process=0``: a simulated SSC-32U on a
    pseudo-terminal (``process=1``: served from its own process) and the real driver on it; closing the bus
    closes the simulator. ``options``: :class:`~livebridge.drivers.ssc32.SSC32Bus` keyword arguments."""
    url.check_known(URL_PARAMETERS)
    baud = url.take("baud", int, 115200)
    sim = simulated_device(SSC32Sim, {"channels": url.take("channels", int, 32, within=(1, 32)),
                                      "corrupt_rate": url.take("corrupt", float, 0.0, within=(0, 1)),
                                      "drop_rate": url.take("drop", float, 0.0, within=(0, 1)),
                                      "seed": url.take("seed", int, 0, within=(0, 2**32 - 1))},
                           url.take("process", bool, False))
    return open_on_pty(sim, lambda path: SSC32Bus(path, baud=baud, url=url.url, companion=sim, **options))
