"""A phone take's input: the Live Link Face packets a take directory's contractions were solved from.

A take recorded from an iPhone (``[source] kind = "livelinkface"``) has, beside ``contractions.csv``,
``arkit.csv`` (the manifest's ``arkit``): one row per solved frame, the same ``frame``, ``seq`` and ``t`` as
``contractions.csv``, then the packet's frame time (``frame_number``, ``sub_frame``, ``rate_numerator``,
``rate_denominator``: the phone's timecode) and its 61 values in the order they travel
(:data:`livebridge.arkit.names.LIVELINK_NAMES`: the 52 ARKit weights, then the head's and eyes' yaw, pitch
and roll, normalised so that 1.0 is a quarter turn). Values are written with 9 significant digits, so the
float32 the phone sent reads back exactly. The manifest names the phone (``device_id``, ``subject``).

:func:`parse_arkit` checks it: every value finite and in the range a packet may carry, or an
:class:`~livebridge.errors.InputError` naming the file, the line and the column.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.arkit.names import LIVELINK_NAMES, N_BLENDSHAPES
from livebridge.errors import InputError

ARKIT = "arkit.csv"
TIME_COLUMNS = ("frame_number", "sub_frame", "rate_numerator", "rate_denominator")
INT32 = 2 ** 31
WEIGHT_SLACK = 1e-3  # as the packet decoder's: float rounding on the phone


def arkit_header() -> list[str]:
    """Columns of ``arkit.csv``."""
    return ["frame", "seq", "t", *TIME_COLUMNS, *LIVELINK_NAMES]


def arkit_row(packet) -> str:
    """The fields after ``frame,seq,t`` of one packet (a :class:`~livebridge.arkit.packet.LiveLinkPacket`)."""
    numerator, denominator = packet.rate
    values = ",".join(f"{v:.9g}" for v in np.asarray(packet.values, dtype=np.float64).tolist())
    return f"{int(packet.frame_number)},{float(packet.sub_frame):.9g},{int(numerator)},{int(denominator)},{values}"


@dataclass(frozen=True, eq=False)
class ArkitTrack:
    """``arkit.csv`` read back.

    Attributes
    ----------
    path : Path
    frame, seq : ndarray of int, shape (n_frames,)
        As ``contractions.csv``'s.
    t : ndarray, shape (n_frames,)
        Arrival of each packet at the recording host, monotonic seconds.
    frame_number : ndarray of int, shape (n_frames,)
    sub_frame : ndarray, shape (n_frames,)
    rate : ndarray of int, shape (n_frames, 2)
        Numerator, denominator.
    values : ndarray, shape (n_frames, 61)
        Weights (52, in [0, 1]) then rotations (9, in [-1, 1]).
    torn : bool
        The last line was cut short (a crash) and dropped.
    """

    path: Path
    frame: np.ndarray
    seq: np.ndarray
    t: np.ndarray
    frame_number: np.ndarray
    sub_frame: np.ndarray
    rate: np.ndarray
    values: np.ndarray
    torn: bool = False

    @property
    def weights(self) -> np.ndarray:
        """The 52 ARKit weights per frame, shape (n_frames, 52)."""
        return self.values[:, :N_BLENDSHAPES]

    @property
    def head_rotation(self) -> np.ndarray:
        """Head yaw, pitch, roll per frame, normalised, shape (n_frames, 3)."""
        return self.values[:, N_BLENDSHAPES:N_BLENDSHAPES + 3]

    def head(self, n: int) -> ArkitTrack:
        """The first ``n`` frames."""
        return ArkitTrack(self.path, self.frame[:n], self.seq[:n], self.t[:n], self.frame_number[:n],
                          self.sub_frame[:n], self.rate[:n], self.values[:n], self.torn)


def _field_check(name: str):
    """(check, what it wants) of one column of ``arkit.csv``."""
    if name in ("frame", "seq", "frame_number"):
        return (lambda v: v == int(v) and abs(v) < INT32), "an integer"
    if name == "t":
        return (lambda v: True), "a number of seconds"
    if name == "sub_frame":
        return (lambda v: 0.0 <= v < 1.0), "a fraction of a frame in [0, 1)"
    if name in ("rate_numerator", "rate_denominator"):
        return (lambda v: v == int(v) and 0 < v < INT32), "a positive integer"
    if name in LIVELINK_NAMES[:N_BLENDSHAPES]:
        return (lambda v: -WEIGHT_SLACK <= v <= 1.0 + WEIGHT_SLACK), "a weight in [0, 1]"
    return (lambda v: -1.0 <= v <= 1.0), "a normalised rotation in [-1, 1]"


_CHECKS = [_field_check(name) for name in arkit_header()]


def parse_arkit(path: str | Path, text: str) -> ArkitTrack:
    """Check and parse the text of ``arkit.csv`` (see the module docstring; ``path`` names it in errors;
    :func:`livebridge.take.directory.read_arkit` reads the file); a torn last line (a crash) is dropped."""
    path = Path(path)
    lines = text.split("\n")
    torn = not text.endswith("\n")
    lines = lines[:-1]
    header = arkit_header()
    if not lines:
        raise InputError("empty file (no header)", path)
    found = lines[0].split(",")
    if found != header:
        column = next((k for k, (a, b) in enumerate(zip(found, header)) if a != b), min(len(found), len(header)))
        wanted = header[column] if column < len(header) else "(end of line)"
        got = found[column] if column < len(found) else "(end of line)"
        raise InputError(f"header column {column + 1}: expected {wanted!r}, got {got!r}", path, "line 1")
    rows = np.array([_row(path, number, line, header) for number, line in enumerate(lines[1:], start=2)],
                    dtype=np.float64).reshape(-1, len(header))
    values = rows[:, 7:]
    values[:, :N_BLENDSHAPES] = np.clip(values[:, :N_BLENDSHAPES], 0.0, 1.0)
    return ArkitTrack(path, rows[:, 0].astype(np.int64), rows[:, 1].astype(np.int64), rows[:, 2],
                      rows[:, 3].astype(np.int64), rows[:, 4], rows[:, 5:7].astype(np.int64), values, torn)


def _row(path: Path, number: int, line: str, header: list[str]) -> list[float]:
    fields = line.split(",")
    if len(fields) != len(header):
        raise InputError(f"{len(fields)} fields, expected {len(header)}", path, f"line {number}")
    row = []
    for column, (name, field, (check, wanted)) in enumerate(zip(header, fields, _CHECKS), start=1):
        try:
            value = float(field)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and check(value)):
            raise InputError(f"expected {wanted}, got {field!r:.40}", path, f"line {number}, column {column} ({name})")
        row.append(value)
    return row
