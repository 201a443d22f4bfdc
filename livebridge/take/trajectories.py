"""Labelled marker trajectories: named markers over time, whatever system recorded them.

:class:`Trajectories` is what every marker-file reader returns and what the offline tools (solve, marker
placement) take: positions in millimetres in the recording system's frame, NaN where a marker was not
seen. :func:`read_trajectories` picks the reader by the file's suffix (:data:`READERS`: C3D, TRC, marker
CSV, livebridge ``.npz`` takes) and :func:`write_trajectories` the writer (:data:`WRITERS`: C3D, TRC, CSV).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from livebridge.errors import InputError
from livebridge.take.tracks import UNITS_MM, Trajectories, on_frame_grid, unit_name

__all__ = ["READERS", "UNITS_MM", "WRITERS", "Trajectories", "read_trajectories", "write_trajectories"]

def _read_npz_take(path: Path, units_mm: float | None) -> Trajectories:
    """The capture-frame marker positions of a livebridge ``.npz`` take (mm by definition)."""
    from livebridge.take.npz import Take

    take = Take.load(path)
    if take.positions is None:
        raise InputError("the take has no marker positions (only model-frame displacements)", path, "positions")
    if units_mm not in (None, 1.0):
        raise InputError(f"a livebridge take is in mm; --units {unit_name(units_mm)} contradicts it", path, "units")
    return Trajectories(tuple(take.marker_names), np.asarray(take.t, float) - float(take.t[0]),
                        np.asarray(take.positions, float), path, "mm")


def _read_c3d(path: Path, units_mm: float | None, rate: float | None) -> Trajectories:
    from livebridge.take.c3d import read_c3d

    return read_c3d(path, units_mm)


def _read_trc(path: Path, units_mm: float | None, rate: float | None) -> Trajectories:
    from livebridge.take.trc import read_trc

    return read_trc(path, units_mm)


def _read_csv(path: Path, units_mm: float | None, rate: float | None) -> Trajectories:
    from livebridge.take.marker_csv import read_marker_csv

    return read_marker_csv(path, units_mm, rate)


READERS: dict[str, Callable[[Path, float | None, float | None], Trajectories]] = {
    ".npz": lambda path, units_mm, rate: _read_npz_take(path, units_mm),
    ".c3d": _read_c3d, ".trc": _read_trc, ".csv": _read_csv, ".tsv": _read_csv,
}
"""Suffix -> ``reader(path, units_mm, rate)``; ``units_mm`` is the user's unit (None: the file's own or mm),
``rate`` the user's frame rate for a file without times (None: the file's own)."""


def read_trajectories(path: str | Path, units: str | None = None, rate: float | None = None) -> Trajectories:
    """The labelled marker trajectories in ``path``, in millimetres.

    Parameters
    ----------
    path : str or Path
        A marker file; its suffix picks the reader (:data:`READERS`).
    units : {"mm", "cm", "m"}, optional
        The unit of a file that does not say.
    rate : float, optional
        Frames per second of a file that has frame numbers but no times; a file whose own rate differs is
        refused.
    """
    path = Path(path)
    if units is not None and units not in UNITS_MM:
        raise InputError(f"unknown unit {units!r}; known: {', '.join(UNITS_MM)}", path, "units")
    if rate is not None and not (math.isfinite(rate) and rate > 0):
        raise InputError(f"the frame rate must be a positive number of Hz, got {rate}", path, "rate")
    reader = READERS.get(path.suffix.lower())
    if reader is None:
        raise InputError(f"unknown marker-file type {path.suffix!r}; known: {', '.join(sorted(READERS))}", path)
    if not path.is_file():
        raise InputError("file not found" if not path.exists() else "not a file", path)
    trajectories = reader(path, UNITS_MM[units] if units is not None else None, rate)
    own = trajectories.rate
    if rate is not None and own is not None and abs(own - rate) > 1e-3 * rate:
        raise InputError(f"the file's frames are {own:.6g} Hz apart; --rate {rate:g} contradicts it", path, "rate")
    return trajectories


def _write_c3d(path: Path, trajectories: Trajectories) -> None:
    from livebridge.take.c3d import write_c3d

    rate = trajectories.rate
    if rate is None:
        raise InputError("one frame: C3D needs a frame rate; give it (--rate)", trajectories.source, "rate")
    write_c3d(path, trajectories.names, on_frame_grid(trajectories.t, trajectories.points, rate), rate)


def _write_trc(path: Path, trajectories: Trajectories) -> None:
    from livebridge.take.trc import write_trc

    write_trc(path, trajectories)


def _write_csv(path: Path, trajectories: Trajectories) -> None:
    from livebridge.take.marker_csv import write_marker_csv

    write_marker_csv(path, trajectories)


WRITERS: dict[str, Callable[[Path, Trajectories], None]] = {
    ".c3d": _write_c3d, ".trc": _write_trc, ".csv": _write_csv, ".tsv": _write_csv}
"""Suffix -> ``writer(path, trajectories)`` (millimetres; C3D on a regular frame grid, gaps as invalid points)."""


def write_trajectories(path: str | Path, trajectories: Trajectories) -> Path:
    """Write ``trajectories`` to ``path`` in the format its suffix names (:data:`WRITERS`), atomically."""
    path = Path(path)
    writer = WRITERS.get(path.suffix.lower())
    if writer is None:
        raise InputError(f"cannot write {path.suffix!r} files; known: {', '.join(sorted(WRITERS))}", path)
    writer(path, trajectories)
    return path
