"""Bounded gestures of a training take, found automatically from an activity curve.

A training take holds isolated gestures separated by rests at neutral. The *activity* of a frame is how
far its (normalised) face image is from neutral, one number per frame. A gesture is a run of frames whose
activity rises clearly above the neutral floor; its *bounded* part (the paper's) runs from the first
non-neutral frame to the first frame of maximum actuation, where the activity first comes within a small
tolerance of the run's peak. An activity that finds weak gestures (the few most changed pixels) saturates
before a large one is full (an opening jaw's strongest changes stop growing at 0.8 of its opening), so the
peak may be read from a second, broader activity too: the first frame where both have come within the
tolerance of their maxima. Even the broader one is within that tolerance two frames (15 fps) before an opening
jaw's maximum, at 0.92 of its opening; so where the frame-to-frame *motion* is known too, the peak is the first
frame of those near the top where the face has stopped moving: its motion within a few of the motion's noise
deviations of the take's still frames (a held expression: the hold's first frames; a sweep: its turning point).
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
        The peak frame is the first within this fraction (of the run's rise) of the run's maximum (and, with a
        motion curve, the first of those frames that is still).
    still_k : float
        With a motion curve, a frame near the top is still when its motion exceeds that of the take's still
        frames (the motion's floor, :func:`neutral_floor`; or the least near the top, if more) by at most this
        many of the motion's noise deviations.
    min_frames : int
        Shorter runs are noise, not gestures.
    smooth : int
        Median-filter width applied to the activity (frames, odd).
    """

    detect_k: float = 6.0
    noise_k: float = 3.0
    peak_tolerance: float = 0.03
    still_k: float = 3.0
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
                  breadth: np.ndarray | None = None, motion: np.ndarray | None = None) -> list[Gesture]:
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
    motion : ndarray, shape (n_frames,), optional
        How much each frame differs from its neighbours (NaN: not known), e.g.
        :func:`~livebridge.markerless.train.change_curves`: the peak is the first frame near the top that is
        still (see ``GestureConfig.still_k``).

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
    if motion is not None:
        motion = np.asarray(motion, dtype=np.float64)
        known = np.isfinite(motion)
        motion_floor, motion_spread = neutral_floor(motion[known]) if known.sum() >= 4 else (np.inf, 0.0)
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
        near = _near_top(filled[start:end + 1], floor, config.peak_tolerance)
        peak = int(np.argmax(near))
        if broad is not None:
            near_broad = _near_top(broad[start:end + 1], broad_floor, config.peak_tolerance)
            peak = max(peak, int(np.argmax(near_broad)))
            near &= near_broad
        if motion is not None:
            peak = _first_still(motion[start:end + 1], near, peak, motion_floor, config.still_k * motion_spread)
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


def _near_top(values: np.ndarray, floor: float, tolerance: float) -> np.ndarray:
    """Mask (n,) of ``values`` (n,) within ``tolerance`` of their rise above ``floor`` of their maximum."""
    top = values.max()
    return values >= top - tolerance * (top - floor)


def _first_still(motion: np.ndarray, near: np.ndarray, peak: int, floor: float, margin: float) -> int:
    """The first index from ``peak`` on, in the run of ``near`` (n,) bool that holds it, whose ``motion`` (n,) is
    within ``margin`` of ``floor`` (a still frame's motion) or of the least motion there, whichever is more;
    ``peak`` when no motion is known there."""
    last = peak
    while last + 1 < len(near) and near[last + 1]:
        last += 1
    window = motion[peak:last + 1]
    known = np.isfinite(window)
    if not known.any():
        return peak
    still = known & (window <= max(floor, window[known].min()) + margin)
    return peak + int(np.argmax(still))


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) index of each run of True in ``mask (n,)``."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1))
