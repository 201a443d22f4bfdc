"""Lynxmotion SSC-32U servo controller: pure encoding and decoding of its ASCII protocol, no I/O.

Commands (SSC-32U User Guide), each ended by a carriage return:

- ``#<ch>P<pw>[S<spd>]...[T<ms>]``: move one or more channels (pulse width
  in µs, 500..2500; ``S`` a channel's speed limit in µs/s) as a group
  finishing together in ``<ms>`` milliseconds;
- ``Q``: is a move in progress? -> ``+`` (moving) or ``.`` (done);
- ``QP<ch>`` (the guide writes ``QP <ch>``): pulse width of a channel now ->
  one byte, µs / 10 (several ``QP`` in one line give one byte each);
- ``VER``: firmware version string;
- ``STOP<ch>``: stop a channel where it is.

``#<ch>P0`` turns the channel's pulses off (used for E-stop "stop"; an
assumption about the firmware, the guide documents 500..2500 for moves).
The driver (:mod:`livebridge.drivers.ssc32`) encodes with these functions,
the simulator (:mod:`livebridge.simulators.ssc32_bus`) decodes with
:func:`decode_line`.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

PULSE_RANGE = (500, 2500)  # µs a move may command (the guide's range)
_TOKEN = re.compile(rb"#(\d+)|P(\d+)|S(\d+)|T(\d+)|QP\s*(\d+)|Q|VER|STOP\s*(\d+)", re.I)


def move(pulses: Mapping[int, float], time_ms: float | None = None,
         speeds: Mapping[int, float] | None = None) -> bytes:
    """``#<ch>P<pw>[S<spd>]...[T<ms>]\\r`` for ``pulses`` channel -> µs and ``speeds`` channel -> µs/s (whole
    units)."""
    if not pulses:
        raise ValueError("no channels to move")
    speeds = speeds or {}
    parts = []
    for channel, pw in sorted(pulses.items()):
        if not 0 <= channel <= 31:
            raise ValueError(f"channel {channel} outside 0..31")
        parts.append(f"#{channel}P{int(round(pw))}")
        if channel in speeds:
            parts.append(f"S{int(round(speeds[channel]))}")
    if time_ms is not None:
        parts.append(f"T{max(0, int(round(time_ms)))}")
    return ("".join(parts) + "\r").encode("ascii")


def pulses_off(channels: Sequence[int]) -> bytes:
    """``#<ch>P0...\\r``: no more pulses on ``channels`` (the servos go limp)."""
    return ("".join(f"#{c}P0" for c in sorted(channels)) + "\r").encode("ascii")


def query_moving() -> bytes:
    return b"Q\r"


def query_pulses(channels: Sequence[int]) -> bytes:
    """``QP0 QP1 ...\\r``: the reply is one byte per channel, pulse width / 10."""
    return (" ".join(f"QP{c}" for c in channels) + "\r").encode("ascii")


def version() -> bytes:
    return b"VER\r"


def encode_pulse(us: float) -> int:
    """The reply byte of ``QP`` for a pulse width in µs (µs / 10, at most 255)."""
    return min(255, int(round(us / 10)))


def decode_pulses(reply: bytes) -> list[int]:
    """One byte per channel -> pulse widths in µs."""
    return [b * 10 for b in reply]


@dataclass(frozen=True)
class Move:
    """One channel of a group move: ``pulse`` µs (None: the line gave no ``P``; 0: pulses off), ``speed``
    µs/s (None: no ``S``)."""

    channel: int
    pulse: int | None = None
    speed: int | None = None


@dataclass(frozen=True)
class Line:
    """One command line, decoded.

    Attributes
    ----------
    moves : tuple of Move
        The group move, in the order its channels first appear (a later ``P`` or ``S`` of a channel wins).
    time_ms : int or None
        The group's ``T``.
    queries : tuple of (str, int or None)
        In order: ``("Q", None)``, ``("QP", channel)``, ``("VER", None)``, ``("STOP", channel)``; the
        controller answers them (and stops) before it starts the move.
    """

    moves: tuple[Move, ...] = ()
    time_ms: int | None = None
    queries: tuple[tuple[str, int | None], ...] = ()


def decode_line(line: bytes) -> Line:
    """Decode one line (without its ``\\r``); text that is no command is ignored, as the controller does."""
    moves: dict[int, dict[str, int]] = {}
    queries: list[tuple[str, int | None]] = []
    current = None
    time_ms = None
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
            time_ms = int(tm)
        elif qp is not None:
            queries.append(("QP", int(qp)))
        elif stop is not None:
            queries.append(("STOP", int(stop)))
        elif text in (b"VER", b"Q"):
            queries.append((text.decode("ascii"), None))
    return Line(tuple(Move(c, spec.get("P"), spec.get("S")) for c, spec in moves.items()), time_ms, tuple(queries))
