"""2D marker detection: bright blobs, sub-pixel intensity-weighted centroids, then undistortion.

The image is thresholded above its background, connected components are found
(``cv2.connectedComponentsWithStats``), components are filtered by area, and each survivor's
centroid is the intensity-weighted mean over its bounding box grown by a margin, with the local
background (median of the patch border) subtracted and pixels of other components excluded, so
the faint rim of the blob below the threshold still counts and the centroid is not rounded to the
threshold mask. A circularity filter (minor/major axis ratio of the weighted second moments)
rejects streaks and elongated highlights. Centroids are then undistorted with the calibration.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from livebridge.calibration.cameras import CameraGroup


@dataclass(frozen=True)
class DetectConfig:
    """Blob detection parameters.

    Attributes
    ----------
    threshold : float or None
        Intensity above which a pixel belongs to a blob; None: background median plus
        ``contrast`` times the spread between the median and the brightest pixels.
    contrast : float
        For the automatic threshold, in (0, 1).
    min_area, max_area : int
        Accepted blob area (thresholded pixels).
    min_circularity : float
        Smallest accepted minor/major axis ratio of the blob (1 for a disc).
    margin : int
        Pixels added around each blob's bounding box for the weighted centroid.
    """

    threshold: float | None = None
    contrast: float = 0.3
    min_area: int = 3
    max_area: int = 5000
    min_circularity: float = 0.5
    margin: int = 2


def _threshold(image: np.ndarray, config: DetectConfig) -> float:
    if config.threshold is not None:
        return float(config.threshold)
    sample = image[::4, ::4]
    background = float(np.median(sample))
    peak = float(image.max())
    noise = 1.4826 * float(np.median(np.abs(sample - background)))
    return max(background + config.contrast * (peak - background), background + 6 * noise)


def detect_blobs(image: np.ndarray, config: DetectConfig = DetectConfig()) -> np.ndarray:
    """Sub-pixel centroids of bright blobs in one image.

    Parameters
    ----------
    image : ndarray, shape (height, width) or (height, width, 3)
        8- or 16-bit or float intensities (colour is averaged).
    config : DetectConfig

    Returns
    -------
    ndarray, shape (n_blobs, 2)
        Distorted pixel coordinates ``(x, y)``; pixel centres are at integer coordinates.
    """
    image = np.asarray(image)
    if image.ndim == 3:
        image = image.mean(axis=2)
    gray = image.astype(np.float32, copy=False)
    level = _threshold(gray, config)
    mask = (gray > level).astype(np.uint8)
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if len(rows) == 0:
        return np.zeros((0, 2))
    # label only the region that holds bright pixels (plus the centroid margin)
    m = config.margin
    top, left = max(rows[0] - m, 0), max(cols[0] - m, 0)
    gray = gray[top:rows[-1] + m + 1, left:cols[-1] + m + 1]
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask[top:rows[-1] + m + 1, left:cols[-1] + m + 1],
                                                                connectivity=8)
    area = stats[1:, cv2.CC_STAT_AREA]
    keep = np.flatnonzero((area >= config.min_area) & (area <= config.max_area)) + 1
    height, width = gray.shape
    out = []
    for label in keep:
        x0, y0, w, h = stats[label, :4]
        xa, ya = max(x0 - m, 0), max(y0 - m, 0)
        xb, yb = min(x0 + w + m, width), min(y0 + h + m, height)
        patch = gray[ya:yb, xa:xb]
        own = labels[ya:yb, xa:xb]
        border = np.concatenate([patch[0], patch[-1], patch[1:-1, 0], patch[1:-1, -1]])
        background = float(np.median(border))
        weight = np.clip(patch - background, 0.0, None) * ((own == 0) | (own == label))
        total = weight.sum()
        if total <= 0:
            continue
        ys, xs = np.mgrid[ya:yb, xa:xb]
        cx = float((weight * xs).sum() / total)
        cy = float((weight * ys).sum() / total)
        dx, dy = xs - cx, ys - cy
        cxx = (weight * dx * dx).sum() / total
        cyy = (weight * dy * dy).sum() / total
        cxy = (weight * dx * dy).sum() / total
        spread = np.sqrt(((cxx - cyy) / 2) ** 2 + cxy**2)
        major, minor = (cxx + cyy) / 2 + spread, (cxx + cyy) / 2 - spread
        if major <= 0 or np.sqrt(max(minor, 0.0) / major) < config.min_circularity:
            continue
        out.append((cx + left, cy + top))
    return np.array(out, dtype=np.float64).reshape(-1, 2)


def detect_markers(images: Sequence[np.ndarray], cameras: CameraGroup,
                   config: DetectConfig = DetectConfig()) -> list[np.ndarray]:
    """Undistorted marker centroids in each camera's image.

    Parameters
    ----------
    images : sequence of ndarray, one per camera, each shape (height, width[, 3])
    cameras : CameraGroup
    config : DetectConfig

    Returns
    -------
    list of ndarray, one per camera, each shape (n_blobs_i, 2): undistorted pixels.
    """
    if len(images) != len(cameras):
        raise ValueError(f"got {len(images)} images for {len(cameras)} cameras")
    return [camera.undistort_points(detect_blobs(image, config)) for camera, image in zip(cameras.cameras, images)]
