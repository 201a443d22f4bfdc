"""A simulated Lynxmotion SSC-32U on a pseudo-terminal (ASCII protocol).

Parses ``#<ch>P<pw>[S<spd>]...[T<ms>]\\r`` group moves (all channels of a
group finish together after ``T`` ms, linear in time; ``S`` limits a
channel's speed in µs/s), ``Q`` (``+`` moving / ``.`` done), ``QP<ch>`` (one
byte per channel, µs / 10), ``VER`` and ``STOP<ch>``. Pulse widths are
clamped to 500..2500 µs; ``P0`` turns a channel off. Unknown text is
ignored, as the controller does. Fault injection: corrupted or dropped replies.
"""

from __future__ import annotations

import random
import re
import threading
import time

from livebridge.simulators.pty_bus import PtyDevice, Reply

_TOKEN = re.compile(rb"#(\d+)|P(\d+)|S(\d+)|T(\d+)|QP\s*(\d+)|Q|VER|STOP\s*(\d+)", re.I)
VERSION = b"SSC32-V2.50USB"


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
        moves: dict[int, dict[str, int]] = {}
        current = None
        group_ms = None
        reply = bytearray()
        for match in _TOKEN.finditer(line):
            ch, pw, spd, tm, qp, stop = match.groups()
            text = match.group(0).upper()
            if ch is not None:
                current = int(ch)
                moves.setdefault(current, {})
            elif pw is not None and current is not None:
                moves[current]["P"] = int(pw)
            elif spd is not None and current is not None:
                moves[current]["S"] = int(spd)
            elif tm is not None:
                group_ms = int(tm)
            elif qp is not None:
                c = int(qp)
                reply.append(min(255, int(round(self.pulse(c, now) / 10))) if c < self.channels else 0)
            elif stop is not None:
                c = int(stop)
                if c < self.channels:
                    self.goal[c] = self.start_pw[c] = self.pulse(c, now)
            elif text == b"VER":
                reply += VERSION + b"\r"
            elif text == b"Q":
                reply += b"+" if self.moving(now) else b"."
        for c, spec in moves.items():
            if c >= self.channels or "P" not in spec:
                continue
            pw = spec["P"]
            self.move_log.append((c, pw))
            if pw == 0:
                self.goal[c] = self.start_pw[c] = 0.0
                continue
            pw = float(min(2500, max(500, pw)))
            start = self.pulse(c, now)
            duration = (group_ms or 0) / 1000.0
            if "S" in spec and spec["S"] > 0 and start:
                duration = max(duration, abs(pw - start) / spec["S"])
            self.start_pw[c], self.goal[c], self.t0[c], self.duration[c] = (start or pw), pw, now, duration
        return bytes(reply) if reply else None
