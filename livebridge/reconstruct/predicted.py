"""Tracked markers found at their predicted projections: the per-frame fast path after the first labelling.

A marker the tracker followed into the previous frame has a good prediction (constant velocity in
the head frame). The prediction is projected into every camera, where the marker claims the nearest
detection within a gate (the 3D gate expressed in pixels at the marker's depth). A claim stands only
when the detection is clearly nearer to this marker's projection than to any other marker's
(``ratio``; every marker with a prediction counts, also those not looked for), so a marker hidden in
one camera does not take a neighbour's detection there. Each marker is triangulated from its claimed
views; while a used view is off by more than ``tolerance_px``, the view whose detection lies farthest
from the predicted projection is dropped (the prediction, not the residual, says which view is wrong:
with one wrong view out of three, the least-squares point spreads the error over all of them). The
marker keeps its label only when the point lies within the 3D gate of its prediction and clearly
nearer to it than to any other marker's prediction (the tracker's swap guard). The views of the
accepted points are spent; whatever is left (markers returning from a gap, strays, a marker whose
views disagree) goes through the general multi-view correspondence.

Why: the general correspondence tries every epipolar pair of every camera pair and grows each into
the other cameras, which costs milliseconds per frame set in numpy; here the search is local and
compiled, and the labels come with it, as in optical mocap systems that track in 2D between frames.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit

from livebridge.reconstruct.triangulate import INVERSE_ITERATIONS, Triangulator, null_vectors


@njit(cache=True, nogil=True)
def _project(predicted: np.ndarray, gate_mm: np.ndarray, projections: np.ndarray,
             focal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Predicted pixels ``(n_cams, n_markers, 2)`` and pixel gates ``(n_cams, n_markers)`` at the markers' depths.

    ``predicted (n_markers, 3)`` world mm, ``gate_mm (n_markers,)``, ``projections (n_cams, 3, 4)``,
    ``focal (n_cams,)`` pixels per unit of x/z. NaN where a marker is behind a camera or unknown.
    """
    n_cams, n_markers = projections.shape[0], predicted.shape[0]
    projected = np.full((n_cams, n_markers, 2), np.nan)
    gate_px = np.full((n_cams, n_markers), np.nan)
    for c in range(n_cams):
        q = projections[c]
        for m in range(n_markers):
            x, y, z = predicted[m, 0], predicted[m, 1], predicted[m, 2]
            depth = q[2, 0] * x + q[2, 1] * y + q[2, 2] * z + q[2, 3]
            if depth > 0:  # False for NaN
                projected[c, m, 0] = (q[0, 0] * x + q[0, 1] * y + q[0, 2] * z + q[0, 3]) / depth
                projected[c, m, 1] = (q[1, 0] * x + q[1, 1] * y + q[1, 2] * z + q[1, 3]) / depth
                gate_px[c, m] = gate_mm[m] * focal[c] / depth
    return projected, gate_px


@njit(cache=True, nogil=True)
def _claim(projected: np.ndarray, look: np.ndarray, gate_px: np.ndarray, detections: np.ndarray,
           offsets: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Each looked-for marker's nearest detection within its gate in every camera, if unambiguous.

    Parameters
    ----------
    projected : ndarray, shape (n_cams, n_markers, 2)
        Predicted undistorted pixels of every marker; NaN where unknown.
    look : ndarray of bool, shape (n_markers,)
    gate_px : ndarray, shape (n_cams, n_markers)
    detections : ndarray, shape (n_detections, 2)
        Every camera's detections, camera after camera.
    offsets : ndarray of int, shape (n_cams + 1,)
        Camera ``c``'s detections are rows ``offsets[c]:offsets[c + 1]``.
    ratio : float
        The claimed detection must be nearer than ``ratio`` times its distance to any other marker's
        projection.

    Returns
    -------
    claims : ndarray of int, shape (n_cams, n_markers)
        Row of the claimed detection, -1 for none.
    distance : ndarray, shape (n_cams, n_markers)
        Pixel distance of the claimed detection from the projection (inf for none).
    """
    n_cams, n_markers = projected.shape[0], projected.shape[1]
    claims = np.full((n_cams, n_markers), -1, dtype=np.int64)
    distance = np.full((n_cams, n_markers), np.inf)
    for c in range(n_cams):
        for m in range(n_markers):
            if not look[m]:
                continue
            x, y = projected[c, m, 0], projected[c, m, 1]
            best, best_d2 = -1, gate_px[c, m] * gate_px[c, m]
            for d in range(offsets[c], offsets[c + 1]):
                dx, dy = detections[d, 0] - x, detections[d, 1] - y
                d2 = dx * dx + dy * dy
                if d2 <= best_d2:  # False for NaN
                    best, best_d2 = d, d2
            if best < 0:
                continue
            limit = best_d2 / (ratio * ratio)
            clear = True
            for other in range(n_markers):
                if other == m:
                    continue
                dx, dy = detections[best, 0] - projected[c, other, 0], detections[best, 1] - projected[c, other, 1]
                if dx * dx + dy * dy <= limit:
                    clear = False
                    break
            if clear:
                claims[c, m] = best
                distance[c, m] = np.sqrt(best_d2)
    return claims, distance


@njit(cache=True, nogil=True)
def _fit_claims(claims: np.ndarray, detections: np.ndarray, distance: np.ndarray, inverse_matrices: np.ndarray,
                extrinsics: np.ndarray, projections: np.ndarray, tolerance_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate each marker from its claimed views, dropping the view farthest from the prediction
    while a used view's residual exceeds ``tolerance_px``.

    Parameters
    ----------
    claims : ndarray of int, shape (n_cams, n_points)
        Row of ``detections`` each marker claimed in each camera, -1 for none.
    detections : ndarray, shape (n_detections, 2)
        Undistorted pixels.
    distance : ndarray, shape (n_cams, n_points)
        Each claim's distance from the predicted projection.
    inverse_matrices : ndarray, shape (n_cams, 3, 3)
    extrinsics : ndarray, shape (n_cams, 3, 4)
        ``world2cam[:3]``.
    projections : ndarray, shape (n_cams, 3, 4)
    tolerance_px : float

    Returns
    -------
    points_3d : ndarray, shape (n_points, 3)
        NaN where fewer than 2 consistent views.
    used : ndarray of bool, shape (n_cams, n_points)
    """
    n_cams, n_points = claims.shape[0], claims.shape[1]
    points = np.full((n_points, 3), np.nan)
    used = np.zeros((n_cams, n_points), dtype=np.bool_)
    normal = np.zeros((1, 4, 4))
    row = np.empty(4)
    for p in range(n_points):
        for c in range(n_cams):
            used[c, p] = claims[c, p] >= 0
        while True:
            views = 0
            for c in range(n_cams):
                views += used[c, p]
            if views < 2:
                for c in range(n_cams):
                    used[c, p] = False
                break
            normal[0] = 0.0
            for c in range(n_cams):
                if not used[c, p]:
                    continue
                k = inverse_matrices[c]
                u, v = detections[claims[c, p], 0], detections[claims[c, p], 1]
                xy = (k[0, 0] * u + k[0, 1] * v + k[0, 2], k[1, 0] * u + k[1, 1] * v + k[1, 2])
                for axis in range(2):
                    for j in range(4):
                        row[j] = xy[axis] * extrinsics[c, 2, j] - extrinsics[c, axis, j]
                    for i in range(4):
                        for j in range(4):
                            normal[0, i, j] += row[i] * row[j]
            vector = null_vectors(normal, INVERSE_ITERATIONS)[0]
            if np.isnan(vector[0]) or vector[3] == 0.0:
                for c in range(n_cams):
                    used[c, p] = False
                break
            x, y, z = vector[0] / vector[3], vector[1] / vector[3], vector[2] / vector[3]
            worst, drop = 0.0, -1
            for c in range(n_cams):
                if not used[c, p]:
                    continue
                q = projections[c]
                h = q[2, 0] * x + q[2, 1] * y + q[2, 2] * z + q[2, 3]
                du = (q[0, 0] * x + q[0, 1] * y + q[0, 2] * z + q[0, 3]) / h - detections[claims[c, p], 0]
                dv = (q[1, 0] * x + q[1, 1] * y + q[1, 2] * z + q[1, 3]) / h - detections[claims[c, p], 1]
                worst = max(worst, np.sqrt(du * du + dv * dv)) if h > 0 else np.inf
                if drop < 0 or distance[c, p] > distance[drop, p]:
                    drop = c
            if worst <= tolerance_px:
                points[p, 0], points[p, 1], points[p, 2] = x, y, z
                break
            used[drop, p] = False
    return points, used


@njit(cache=True, nogil=True)
def _clear(points_3d: np.ndarray, predicted: np.ndarray, look: np.ndarray, gate_mm: np.ndarray,
           ratio: float) -> np.ndarray:
    """Looked-for points within their marker's 3D gate and clearly nearer it than any other prediction.

    ``points_3d`` and ``predicted`` are ``(n_markers, 3)`` (row ``m``: marker ``m``'s point, NaN for none),
    ``gate_mm (n_markers,)``; returns ``(n_markers,)`` bool. Another prediction must be farther than
    ``own / ratio``.
    """
    n = len(points_3d)
    accepted = np.zeros(n, dtype=np.bool_)
    for m in range(n):
        if not look[m]:
            continue
        own = 0.0
        for k in range(3):
            own += (points_3d[m, k] - predicted[m, k]) ** 2
        if not own <= gate_mm[m] * gate_mm[m]:  # also NaN
            continue
        clear = True
        for other in range(n):
            if other == m:
                continue
            d2 = 0.0
            for k in range(3):
                d2 += (points_3d[m, k] - predicted[other, k]) ** 2
            if ratio * ratio * d2 <= own:
                clear = False
                break
        accepted[m] = clear
    return accepted


@dataclass(frozen=True, eq=False)
class PredictedMatch:
    """Markers found at their predicted projections in one frame set.

    Attributes
    ----------
    positions_world : ndarray, shape (n_markers, 3)
        Triangulated world positions of the markers found, NaN for the others.
    remaining : list of ndarray, one per camera, each shape (n_detections_i, 2)
        The camera's detections with the ones the found markers used set to NaN (same indices).
    n_views : ndarray of int, shape (n_markers,)
        Views each found marker was triangulated from (0 where not found).
    """

    positions_world: np.ndarray
    remaining: list
    n_views: np.ndarray


class PredictedMatcher:
    """Finds tracked markers around their predicted projections (see the module docstring).

    Parameters
    ----------
    triangulator : Triangulator
    tolerance_px : float
        Largest reprojection residual of a used view (undistorted px).
    ratio : float
        Uniqueness, in 2D against the other markers' projections and in 3D against their predictions.
    """

    def __init__(self, triangulator: Triangulator, tolerance_px: float = 1.5, ratio: float = 0.6):
        self.triangulator = triangulator
        self.tolerance_px = float(tolerance_px)
        self.ratio = float(ratio)
        matrices = np.linalg.inv(triangulator.inverse_matrices)
        self._focal = np.sqrt(matrices[:, 0, 0] * matrices[:, 1, 1])  # (c,) px per unit x/z: the pixel gates

    def __call__(self, points_2d: Sequence[np.ndarray], predicted: np.ndarray, look: np.ndarray,
                 gate_mm: np.ndarray) -> PredictedMatch:
        """Find the markers in ``look`` near their predictions.

        Parameters
        ----------
        points_2d : sequence of ndarray, one per camera, each shape (n_detections_i, 2)
            Undistorted pixel centroids.
        predicted : ndarray, shape (n_markers, 3)
            Predicted world positions of every marker (also those not looked for: uniqueness).
        look : ndarray of bool, shape (n_markers,)
            Markers to look for (followed into the previous frame).
        gate_mm : ndarray, shape (n_markers,)
            Largest distance (world mm) from its prediction at which a marker is accepted.

        Returns
        -------
        PredictedMatch
        """
        points_2d = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in points_2d]
        n_markers = len(predicted)
        found = np.full((n_markers, 3), np.nan)
        n_views = np.zeros(n_markers, dtype=np.int64)
        look = np.asarray(look, dtype=bool) & np.isfinite(predicted).all(axis=1)
        detections = np.concatenate(points_2d)
        if not look.any() or not len(detections):
            return PredictedMatch(found, points_2d, n_views)
        offsets = np.cumsum([0] + [len(p) for p in points_2d]).astype(np.int64)
        t = self.triangulator
        projected, gate_px = _project(predicted, gate_mm, t.projections, self._focal)
        claims, distance = _claim(projected, look, gate_px, detections, offsets, self.ratio)
        points_3d, used = _fit_claims(claims, detections, distance, t.inverse_matrices, t.extrinsics, t.projections,
                                      self.tolerance_px)
        accepted = _clear(points_3d, predicted, look, gate_mm, self.ratio)
        found[accepted] = points_3d[accepted]
        used &= accepted[None]
        n_views[accepted] = used[:, accepted].sum(axis=0)
        remaining = detections.copy()
        remaining[claims[used]] = np.nan
        return PredictedMatch(found, [remaining[a:b] for a, b in zip(offsets[:-1], offsets[1:])], n_views)
