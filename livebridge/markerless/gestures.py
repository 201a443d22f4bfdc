"""Bounded gestures of a training take, found automatically from an activity curve.

A training take holds isolated gestures separated by rests at neutral. The *activity* of a frame is how
far its (normalised) face image is from neutral, one number per frame. A gesture is a run of frames whose
activity rises clearly above the neutral floor; its *bounded* part (the paper's) runs from the first
non-neutral frame to the first frame of maximum actuation, where the activity first comes within a small
tolerance of the run's peak. An activity that finds weak gestures (the few most changed pixels) saturates
before a large one is full (an opening jaw's strongest changes stop growing at 0.8 of its opening), so the
peak may be read from a second, broader activity too: the first frame where both have come within the
tolerance of their maxima.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import median_filter


@dataclass(frozen=True)
class Gesture:
    """One gesture of a take (frame numbers).

    Attributes
    ----------
    start : int
        First non-neutral frame.
    peak : int
        First frame of maximum actuation; ``start..peak`` inclusive is the bounded gesture.
    end : int
        Last frame before the activity falls back to neutral.
    """

    start: int
    peak: int
    end: int

    @property
    def frames(self) -> np.ndarray:
        """Frame numbers of the bounded gesture, shape (peak - start + 1,)."""
        return np.arange(self.start, self.peak + 1)


@dataclass(frozen=True)
class GestureConfig:
    """Segmentation thresholds.

    Attributes
    ----------
    detect_k : float
        A run counts as a gesture where its activity exceeds the neutral floor by this many noise deviations
        (weak muscles change little of the image: the noise, not the strongest gesture, sets the bar).
    noise_k : float
        A frame is non-neutral once its activity exceeds the floor by this many noise deviations.
    peak_tolerance : float
        The peak frame is the first within this fraction (of the run's rise) of the run's maximum.
    min_frames : int
        Shorter runs are noise, not gestures.
    smooth : int
        Median-filter width applied to the activity (frames, odd).
    """

    detect_k: float = 6.0
    noise_k: float = 3.0
    peak_tolerance: float = 0.03
    min_frames: int = 4
    smooth: int = 3


def neutral_floor(activity: np.ndarray) -> tuple[float, float]:
    """The activity of neutral frames and the frame noise: (median of the lowest quarter, noise deviation).

    The noise comes from second differences, which a smooth gesture barely moves.
    """
    floor = float(np.median(np.sort(activity)[: max(2, len(activity) // 4)]))
    second = np.diff(activity, 2)
    spread = float(1.4826 * np.median(np.abs(second)) / np.sqrt(6.0)) if len(second) else 0.0
    return floor, max(spread, 1e-9 * max(1.0, abs(floor)))


def find_gestures(activity: np.ndarray, config: GestureConfig = GestureConfig(),
                  breadth: np.ndarray | None = None) -> list[Gesture]:
    """Bounded gestures in an activity curve.

    Parameters
    ----------
    activity : ndarray, shape (n_frames,)
        Distance of each frame from neutral (any non-negative measure); NaN for frames not seen (never
        part of a gesture).
    config : GestureConfig
    breadth : ndarray, shape (n_frames,), optional
        A broader activity that keeps growing where ``activity`` saturates: a gesture's peak is not before
        its first frame within the tolerance of its maximum over the gesture.

    Returns
    -------
    list of Gesture, in time order.
    """
    activity = np.asarray(activity, dtype=np.float64)
    seen = np.isfinite(activity)
    if seen.sum() < 4:
        return []
    filled = _filled(activity, seen)
    _, spread = neutral_floor(filled[seen])
    filled = _smoothed(filled, config.smooth)
    floor, _ = neutral_floor(filled[seen])
    broad = broad_floor = None
    if breadth is not None:
        broad = _smoothed(_filled(breadth, seen), config.smooth)
        broad_floor, _ = neutral_floor(broad[seen])
    active = (filled > floor + config.detect_k * spread) & seen
    moving = (filled > floor + config.noise_k * spread) & seen
    gestures = []
    for first, last in _runs(active):
        start, end = first, last
        while start > 0 and moving[start - 1]:
            start -= 1
        while end + 1 < len(filled) and moving[end + 1]:
            end += 1
        if gestures and start <= gestures[-1].end:  # one movement seen as two runs
            continue
        if end - start + 1 < config.min_frames:
            continue
        peak = _first_near_top(filled[start:end + 1], floor, config.peak_tolerance)
        if broad is not None:
            peak = max(peak, _first_near_top(broad[start:end + 1], broad_floor, config.peak_tolerance))
        gestures.append(Gesture(int(start), int(start + peak), int(end)))
    return gestures


def _filled(curve: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """``curve`` (n,) as float64 with its frames not ``seen`` (n,) bool, or not finite, at its lowest seen value."""
    curve = np.asarray(curve, dtype=np.float64)
    known = seen & np.isfinite(curve)
    return np.where(known, curve, np.min(curve[known]) if known.any() else np.nan)


def _smoothed(curve: np.ndarray, width: int) -> np.ndarray:
    """``curve`` (n,) median-filtered over ``width`` frames (as it is when ``width`` <= 1)."""
    return median_filter(curve, size=width, mode="nearest") if width > 1 else curve


def _first_near_top(values: np.ndarray, floor: float, tolerance: float) -> int:
    """Index of the first of ``values`` (n,) within ``tolerance`` of their rise above ``floor`` of their maximum."""
    top = values.max()
    return int(np.argmax(values >= top - tolerance * (top - floor)))


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) index of each run of True in ``mask (n,)``."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1))
