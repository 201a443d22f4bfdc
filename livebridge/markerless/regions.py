"""Regions of influence and co-articulation regions (CRs).

A muscle's region of influence (ROI) is where its full gesture visibly changes the canonical face: the
smoothed difference image between its frame of maximum actuation and neutral, above a threshold set from
the noise between neutral frames. CRs are the non-empty intersections of ROIs: every pixel is labelled with
the set of muscles whose ROI holds it, and each contiguous component of one label is a candidate region.
Components smaller than ``min_area`` are merged into the neighbour they share the longest border with (the
merged region keeps both muscle sets), smallest first, until every region is large enough (and, with
``max_regions``, until there are at most that many).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class RegionConfig:
    """ROI and CR parameters.

    Attributes
    ----------
    smooth_sigma : float
        Gaussian smoothing of the absolute difference images, pixels.
    noise_k : float
        ROI threshold in noise deviations (of the smoothed difference between neutral frames).
    relative : float
        ROI threshold as a fraction of the muscle's own strongest (99th-percentile) change; the larger of
        the two thresholds holds.
    min_area : float
        Smallest CR, as a fraction of the union of all ROIs.
    max_regions : int or None
    min_cover : float
        After merging, a muscle acts on a CR when its ROI covers at least this fraction of the CR (and every
        muscle keeps the CR it covers most): small merged fragments do not drag their muscles along.
    """

    smooth_sigma: float = 3.0
    noise_k: float = 6.0
    relative: float = 0.15
    min_area: float = 0.02
    max_regions: int | None = None
    min_cover: float = 0.25


@dataclass(frozen=True, eq=False)
class Region:
    """One CR: a mask and the indices of the muscles (gestures) acting on it."""

    mask: np.ndarray
    muscles: tuple[int, ...]


def smoothed_difference(image: np.ndarray, neutral: np.ndarray, sigma: float) -> np.ndarray:
    """``|image - neutral|`` blurred, shape (H, W) float32."""
    diff = np.abs(image.astype(np.float32) - neutral.astype(np.float32))
    return cv2.GaussianBlur(diff, (0, 0), sigma) if sigma > 0 else diff


def regions_of_influence(full: np.ndarray, neutral: np.ndarray, neutral_other: np.ndarray,
                         config: RegionConfig = RegionConfig()) -> np.ndarray:
    """Each muscle's region of influence.

    Parameters
    ----------
    full : ndarray, shape (n_muscles, H, W)
        Each muscle's canonical frame of maximum actuation.
    neutral, neutral_other : ndarray, shape (H, W)
        Two neutral frames (their difference is the noise).

    Returns
    -------
    ndarray, shape (n_muscles, H, W), bool
    """
    noise = smoothed_difference(neutral_other, neutral, config.smooth_sigma)
    noise_level = float(np.percentile(noise, 99))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    rois = []
    for frame in full:
        change = smoothed_difference(frame, neutral, config.smooth_sigma)
        level = max(config.noise_k * noise_level / 2.33, config.relative * float(np.percentile(change, 99)))
        roi = (change > level).astype(np.uint8)
        roi = cv2.morphologyEx(cv2.morphologyEx(roi, cv2.MORPH_CLOSE, kernel), cv2.MORPH_OPEN, kernel)
        rois.append(roi.astype(bool))
    return np.array(rois)


def co_articulation_regions(rois: np.ndarray, config: RegionConfig = RegionConfig()) -> list[Region]:
    """CRs from regions of influence.

    Parameters
    ----------
    rois : ndarray, shape (n_muscles, H, W), bool
    config : RegionConfig

    Returns
    -------
    list of Region, largest first; their masks do not overlap.
    """
    n_muscles = len(rois)
    if n_muscles == 0 or not rois.any():
        return []
    weights = (1 << np.arange(n_muscles, dtype=np.int64))[:, None, None]
    label = (rois.astype(np.int64) * weights).sum(axis=0)
    components = np.zeros(label.shape, dtype=np.int32)
    muscle_sets: list[set[int]] = []
    for value in np.unique(label[label > 0]):
        count, parts = cv2.connectedComponents((label == value).astype(np.uint8), connectivity=4)
        members = {i for i in range(n_muscles) if value >> i & 1}
        for part in range(1, count):
            muscle_sets.append(set(members))
            components[parts == part] = len(muscle_sets)
    min_pixels = config.min_area * float((label > 0).sum())
    _merge_small(components, muscle_sets, min_pixels, config.max_regions)
    masks = [components == k + 1 for k, muscles in enumerate(muscle_sets) if muscles]
    cover = np.array([[(roi & mask).sum() / max(1, mask.sum()) for roi in rois] for mask in masks])  # (n_cr, n_m)
    keep = cover >= config.min_cover
    for m in range(n_muscles):
        if cover[:, m].max(initial=0) > 0:
            keep[np.argmax(cover[:, m]), m] = True
    regions = [Region(mask, tuple(int(m) for m in np.flatnonzero(row))) for mask, row in zip(masks, keep) if row.any()]
    return sorted(regions, key=lambda r: -int(r.mask.sum()))


def _merge_small(components: np.ndarray, muscle_sets: list[set[int]], min_pixels: float,
                 max_regions: int | None) -> None:
    """Merge regions in place (``components`` ids from 1; an emptied set marks a merged-away region)."""
    kernel = np.ones((3, 3), np.uint8)
    while True:
        areas = np.bincount(components.ravel(), minlength=len(muscle_sets) + 1)[1:]
        alive = [k for k in range(len(muscle_sets)) if muscle_sets[k] and areas[k] > 0]
        small = [k for k in alive if areas[k] < min_pixels]
        if not small and (max_regions is None or len(alive) <= max_regions):
            return
        k = min(small or alive, key=lambda j: areas[j])
        ring = cv2.dilate((components == k + 1).astype(np.uint8), kernel).astype(bool) & (components != k + 1)
        neighbours = np.bincount(components[ring], minlength=len(muscle_sets) + 1)[1:]
        neighbours[k] = 0
        if neighbours.sum() == 0:  # an island: nothing to merge with
            components[components == k + 1] = 0
            muscle_sets[k] = set()
            continue
        target = int(np.argmax(neighbours))
        components[components == k + 1] = target + 1
        muscle_sets[target] |= muscle_sets[k]
        muscle_sets[k] = set()
