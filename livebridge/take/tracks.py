"""The data every marker-file reader returns: :class:`Trajectories` (named markers over time, mm), the units a
file may be in, and the frame grid of formats with one frame per sample period. Readers and writers import
it from here; :mod:`livebridge.take.trajectories` dispatches to them by suffix."""

from __future__ import annotations

import math
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
    unit : {"mm", "cm", "m"} or None
        The unit the file stored (its own header's, or the one the user gave); None when neither said and
        millimetres were assumed.
    """

    names: tuple[str, ...]
    t: np.ndarray
    points: np.ndarray
    source: Path | None = None
    unit: str | None = None

    def __post_init__(self):
        n_frames, n_markers = len(self.t), len(self.names)
        if self.points.shape != (n_frames, n_markers, 3):
            raise ValueError(f"points has shape {self.points.shape}, expected {(n_frames, n_markers, 3)}")
        if len(set(self.names)) != n_markers:
            raise ValueError("marker names repeat")

    @property
    def rate(self) -> float | None:
        """Frames per second: sample periods over the span of the times (None for fewer than two frames).

        The period count takes each step as a whole number of median steps, so gaps do not lower the rate and
        times rounded to the millisecond (OpenFace writes ``0.033``, ``0.067``...) do not bias it.
        """
        if len(self.t) < 2:
            return None
        steps = np.diff(self.t)
        median = float(np.median(steps))
        span = float(self.t[-1] - self.t[0])
        if not (median > 0 and math.isfinite(span) and span > 0):
            return None
        periods = float(np.sum(np.maximum(1.0, np.rint(steps / median))))
        return periods / span

    @property
    def seen(self) -> np.ndarray:
        """Per marker, the fraction of frames it was seen in, shape (n_markers,)."""
        if not len(self.t):
            return np.zeros(len(self.names))
        return np.mean(np.all(np.isfinite(self.points), axis=-1), axis=0)


def unit_name(units_mm: float | None) -> str | None:
    """``"mm"``, ``"cm"`` or ``"m"`` for a factor of :data:`UNITS_MM` (None stays None)."""
    return None if units_mm is None else next(k for k, v in UNITS_MM.items() if v == units_mm)


def file_units(stated: str, given_mm: float | None, path: Path, field: str) -> tuple[float, str | None]:
    """Millimetres per unit and the unit's name for a file whose header states the unit ``stated``.

    An empty ``stated`` leaves the unit to the user (``given_mm``; millimetres when not given). A stated
    unit the user contradicts is refused: a silent factor of 1000 is worse than asking.
    """
    stated = stated.strip().lower()
    if not stated:
        return (given_mm or 1.0), unit_name(given_mm)
    if stated not in UNITS_MM:
        if given_mm is None:
            raise InputError(f"unknown unit {stated!r} (known: {', '.join(UNITS_MM)}); give the file's unit "
                             "(--units)", path, field)
        return given_mm, unit_name(given_mm)
    if given_mm is not None and given_mm != UNITS_MM[stated]:
        raise InputError(f"the file says its unit is {stated}, --units says {unit_name(given_mm)}; "
                         "leave --units out", path, field)
    return UNITS_MM[stated], stated


def on_frame_grid(t: np.ndarray, points: np.ndarray, rate: float) -> np.ndarray:
    """The frames ``points`` placed one sample period apart at ``rate``, NaN frames where none was recorded.

    For formats with one frame per sample period (C3D): a frame set dropped on the way leaves a gap instead
    of shifting every later frame one period early. Each step counts the periods since the previous frame
    (at least one), so a camera clock a little off the nominal rate never makes two frames collide or a
    spurious gap build up over a long take.

    Parameters
    ----------
    t : ndarray, shape (n_frames,)
        Seconds, increasing.
    points : ndarray, shape (n_frames, n_markers, 3)
    rate : float
        Frames per second of the grid.

    Returns
    -------
    ndarray, shape (n_slots, n_markers, 3)
        ``n_slots >= n_frames``; the recorded frames in order, NaN frames in the gaps.
    """
    if len(t) < 2:
        return np.asarray(points, float)
    steps = np.maximum(1, np.rint(np.diff(np.asarray(t, float)) * rate)).astype(np.int64)
    slots = np.concatenate([[0], np.cumsum(steps)])
    grid = np.full((int(slots[-1]) + 1,) + points.shape[1:], np.nan)
    grid[slots] = points
    return grid
