"""Feathered alpha masks: 1.0 inside a shape, falling linearly to 0 over ``feather_px`` at its boundary.

The paper's reconstruction elements carry an alpha mask of their own size, "1.0 everywhere with a 10 pixel
gradient to 0 approaching the boundary". The boundary is the edge of the sample's rectangle and of the
shape inside it (its drawn opacity, the region's mask): every pixel's alpha is its Euclidean distance to the
nearest pixel outside the shape, divided by ``feather_px`` and clipped to 1, so the pixel next to the
boundary has ``1 / feather_px`` and the one ``feather_px`` pixels in has 1.
"""

from __future__ import annotations

import cv2
import numpy as np

FEATHER_PX = 10.0
"""The paper's gradient width, pixels."""


def feathered_alpha(shape: np.ndarray, feather_px: float = FEATHER_PX,
                    open_edges: tuple[bool, bool, bool, bool] = (False, False, False, False)) -> np.ndarray:
    """Alpha of a shape with a linear ramp of ``feather_px`` pixels inside its boundary.

    Parameters
    ----------
    shape : ndarray of bool, shape (h, w)
        The pixels the element covers; beyond the array's edge counts as outside, except past an open edge.
    feather_px : float
        Width of the ramp, pixels; 0 gives a hard edge (the shape itself).
    open_edges : (bool, bool, bool, bool)
        Top, bottom, left, right: the shape goes on past that edge of the array (a sample that reaches the
        canvas's edge is not faded there; the picture ends, the element does not).

    Returns
    -------
    ndarray of float32, shape (h, w)
        In [0, 1]: 0 outside, ``min(1, d / feather_px)`` inside, ``d`` the distance to the nearest outside
        pixel (1 for a pixel next to the boundary).
    """
    shape = np.asarray(shape, dtype=bool)
    if feather_px <= 0:
        return shape.astype(np.float32)
    margin = int(np.ceil(feather_px)) + 1
    top, bottom, left, right = (margin if is_open else 1 for is_open in open_edges)
    padded = np.pad(shape, ((top, bottom), (left, right)), mode="edge")  # an open edge continues the shape
    closed = [(slice(0, top), slice(None)), (slice(padded.shape[0] - bottom, None), slice(None)),
              (slice(None), slice(0, left)), (slice(None), slice(padded.shape[1] - right, None))]
    for window, is_open in zip(closed, open_edges):
        if not is_open:
            padded[window] = False
    distance = cv2.distanceTransform(padded.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    distance = distance[top:top + shape.shape[0], left:left + shape.shape[1]]
    return np.minimum(distance / np.float32(feather_px), 1.0).astype(np.float32)


def crossfade_weight(own: np.ndarray, earlier: np.ndarray) -> np.ndarray:
    """How much of a later region shows where it overlaps an earlier one, shape (h, w), float32 in [0, 1].

    In the overlap of the two masks the later region's share rises from 0 at the earlier region's interior
    side to 1 at its own: ``d_own / (d_own + d_earlier)``, ``d`` the distance to the outside of each mask, so
    at the middle of the overlap the two regions show half and half instead of the later one hiding the
    earlier one (composited in order, the earlier region keeps its full alpha). 1 wherever they do not overlap.

    Parameters
    ----------
    own, earlier : ndarray of bool, shape (h, w)
        The later and the earlier region's masks on the same pixels.
    """
    d_own = cv2.distanceTransform(np.pad(own, 1).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]
    d_earlier = cv2.distanceTransform(np.pad(earlier, 1).astype(np.uint8), cv2.DIST_L2,
                                      cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]
    overlap = own & earlier
    weight = np.ones(own.shape, np.float32)
    weight[overlap] = d_own[overlap] / (d_own[overlap] + d_earlier[overlap])
    return weight
