"""Labelled marker trajectories: named markers over time, whatever system recorded them.

:class:`Trajectories` is what every marker-file reader returns and what the offline tools (solve, marker
placement) take: positions in millimetres in the recording system's frame, NaN where a marker was not
seen. :func:`read_trajectories` picks the reader by the file's suffix.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.errors import InputError

UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
"""Millimetres per unit, for files whose unit is given by the user (``--units``) or their header."""


@dataclass(frozen=True, eq=False)
class Trajectories:
    """Named marker positions over time.

    Attributes
    ----------
    names : tuple of str, length n_markers
    t : ndarray, shape (n_frames,)
        Seconds from the first frame, increasing.
    points : ndarray, shape (n_frames, n_markers, 3)
        Millimetres, NaN where the marker was not seen.
    source : Path or None
        The file they were read from (named in errors).
    """

    names: tuple[str, ...]
    t: np.ndarray
    points: np.ndarray
    source: Path | None = None

    def __post_init__(self):
        n_frames, n_markers = len(self.t), len(self.names)
        if self.points.shape != (n_frames, n_markers, 3):
            raise ValueError(f"points has shape {self.points.shape}, expected {(n_frames, n_markers, 3)}")
        if len(set(self.names)) != n_markers:
            raise ValueError("marker names repeat")

    @property
    def rate(self) -> float | None:
        """Frames per second from the median frame interval (None for fewer than two frames)."""
        if len(self.t) < 2:
            return None
        step = float(np.median(np.diff(self.t)))
        return 1.0 / step if step > 0 and math.isfinite(step) else None


def _read_npz_take(path: Path, units_mm: float | None) -> Trajectories:
    """The capture-frame marker positions of a livebridge ``.npz`` take (mm by definition)."""
    from livebridge.take.npz import Take

    take = Take.load(path)
    if take.positions is None:
        raise InputError("the take has no marker positions (only model-frame displacements)", path, "positions")
    return Trajectories(tuple(take.marker_names), np.asarray(take.t, float) - float(take.t[0]),
                        np.asarray(take.positions, float), path)


READERS: dict[str, Callable[[Path, float | None], Trajectories]] = {".npz": _read_npz_take}
"""Suffix -> ``reader(path, units_mm)``; ``units_mm`` is the user's unit (None: the file's own or mm)."""


def read_trajectories(path: str | Path, units: str | None = None) -> Trajectories:
    """The labelled marker trajectories in ``path``, in millimetres.

    Parameters
    ----------
    path : str or Path
        A marker file; its suffix picks the reader (:data:`READERS`).
    units : {"mm", "cm", "m"}, optional
        The unit of a file that does not say.
    """
    path = Path(path)
    if units is not None and units not in UNITS_MM:
        raise InputError(f"unknown unit {units!r}; known: {', '.join(UNITS_MM)}", path, "units")
    reader = READERS.get(path.suffix.lower())
    if reader is None:
        raise InputError(f"unknown marker-file type {path.suffix!r}; known: {', '.join(sorted(READERS))}", path)
    if not path.is_file():
        raise InputError("file not found" if not path.exists() else "not a file", path)
    return reader(path, UNITS_MM[units] if units is not None else None)
