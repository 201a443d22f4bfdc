"""Multi-view correspondence: group 2D detections across all cameras into 3D points.

Every pair of cameras proposes candidate matches by epipolar gating (symmetric point-to-line
distance within ``tolerance_px``). Each candidate pair is triangulated, projected into every other
camera, and picks up the nearest detection there within the same tolerance, so a candidate grows
into a group over *all* cameras. Groups are triangulated together (batched DLT), outlier views are
dropped by reprojection residual, and groups are accepted greedily - most views first, then the
smallest residual - with each detection used at most once (:func:`greedy_disjoint`). Detections
left over go through a second round on their own. Points seen by fewer than 2 cameras are never
invented.

The gating, the growth and the nearest-prediction test are compiled brute-force loops: with at
most a few hundred detections per frame set they cost a few microseconds, where building k-d
trees and a dozen small numpy operations per camera pair cost ~1 ms more per round (measured on the
demo take: a round over 5 leftover detections, 2.2 -> 1.2 ms). That time lands on the frames where
a marker returns from a gap, which set the live pipeline's p99 latency.

Two views alone are ambiguous when several markers lie near one epipolar plane. When the tracker
passes its predicted marker positions, groups whose point lies within ``prior_mm`` of a prediction
are accepted first (most views, then nearest to the prediction), so a marker seen by only two
cameras is not lost to a ghost pairing of its detections.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit

from livebridge.reconstruct.triangulate import Triangulator


@dataclass(frozen=True, eq=False)
class Correspondence:
    """Unlabelled 3D points of one frame set.

    Attributes
    ----------
    points_3d : ndarray, shape (n_points, 3)
        World positions, mm.
    detections : ndarray of int, shape (n_cams, n_points)
        Index of the detection each point uses in each camera; -1 where the camera is not used.
    residual_px : ndarray, shape (n_points,)
        Worst reprojection residual over the used views (undistorted px).
    n_unused : int
        Detections (over all cameras) not in any point.
    """

    points_3d: np.ndarray
    detections: np.ndarray
    residual_px: np.ndarray
    n_unused: int

    @property
    def n_views(self) -> np.ndarray:
        """Views per point, shape (n_points,)."""
        return (self.detections >= 0).sum(axis=0)


def fundamental(projection_a: np.ndarray, projection_b: np.ndarray) -> np.ndarray:
    """Fundamental matrix ``F`` with ``x_bᵀ F x_a = 0`` from two projection matrices ``(3, 4)``."""
    _, _, vt = np.linalg.svd(projection_a)
    center_a = vt[-1]
    epipole = projection_b @ center_a
    cross = np.array([[0, -epipole[2], epipole[1]], [epipole[2], 0, -epipole[0]], [-epipole[1], epipole[0], 0]])
    return cross @ projection_b @ np.linalg.pinv(projection_a)


class Correspondence3D:
    """Multi-view correspondence for one calibrated rig.

    Parameters
    ----------
    triangulator : Triangulator
    tolerance_px : float
        Epipolar and reprojection tolerance in undistorted pixels.
    """

    def __init__(self, triangulator: Triangulator, tolerance_px: float = 2.0):
        self.triangulator = triangulator
        self.tolerance_px = float(tolerance_px)
        n = len(triangulator)
        self.pairs = [(a, b) for a in range(n) for b in range(a + 1, n)]
        p = triangulator.projections
        self.fundamentals = {(a, b): fundamental(p[a], p[b]) for a, b in self.pairs}

    def __call__(self, points_2d: Sequence[np.ndarray], predicted: np.ndarray | None = None,
                 prior_mm: float = 3.0) -> Correspondence:
        """Group detections of one frame set.

        Parameters
        ----------
        points_2d : sequence of ndarray, one per camera, each shape (n_detections_i, 2)
            Undistorted pixel centroids.
        predicted : ndarray, shape (n_markers, 3), optional
            Predicted world positions of tracked markers (NaN rows ignored): groups near them go first.
        prior_mm : float
            How near a group must be to a prediction to go first.

        Returns
        -------
        Correspondence
        """
        points_2d = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in points_2d]
        n_cams = len(self.triangulator)
        if len(points_2d) != n_cams:
            raise ValueError(f"expected detections for {n_cams} cameras, got {len(points_2d)}")
        available = [np.isfinite(p).all(axis=1) for p in points_2d]
        groups, points_3d, residual = [], [], []
        for _ in range(2):
            found = self._round(points_2d, available, predicted, prior_mm)
            if found is None:
                break
            g, x, r = found
            groups.append(g)
            points_3d.append(x)
            residual.append(r)
            for cam in range(n_cams):
                used = g[cam][g[cam] >= 0]
                available[cam][used] = False
        if not groups:
            return Correspondence(np.zeros((0, 3)), np.zeros((n_cams, 0), dtype=np.int64), np.zeros(0),
                                  int(sum(a.sum() for a in available)))
        return Correspondence(np.concatenate(points_3d), np.concatenate(groups, axis=1), np.concatenate(residual),
                              int(sum(a.sum() for a in available)))

    def _candidates(self, points_2d, available) -> np.ndarray:
        """Candidate groups from epipolar pairs, shape (n_cams, n_candidates) of detection indices."""
        n_cams = len(points_2d)
        tol = self.tolerance_px
        index = [np.flatnonzero(a) for a in available]
        candidates = []
        for a, b in self.pairs:
            if len(index[a]) == 0 or len(index[b]) == 0:
                continue
            ia, ib = epipolar_pairs(points_2d[a][index[a]], points_2d[b][index[b]], self.fundamentals[(a, b)], tol)
            group = np.full((n_cams, len(ia)), -1, dtype=np.int64)
            group[a] = index[a][ia]
            group[b] = index[b][ib]
            candidates.append(group)
        if not candidates:
            return np.zeros((n_cams, 0), dtype=np.int64)
        return np.concatenate(candidates, axis=1)

    def _gather(self, points_2d, group) -> np.ndarray:
        """2D observations of groups, shape (n_cams, n_groups, 2), NaN where the group has no view."""
        n_cams, n_groups = group.shape
        out = np.full((n_cams, n_groups, 2), np.nan)
        for cam in range(n_cams):
            has = group[cam] >= 0
            out[cam, has] = points_2d[cam][group[cam, has]]
        return out

    def _round(self, points_2d, available, predicted, prior_mm):
        triangulator, tol = self.triangulator, self.tolerance_px
        group = self._candidates(points_2d, available)
        if group.shape[1] == 0:
            return None
        # grow every pair into the other cameras
        seeds = triangulator.dlt(self._gather(points_2d, group))
        projected = triangulator.reproject(seeds)  # (c, n, 2)
        for cam in range(len(points_2d)):
            free = np.flatnonzero(available[cam])
            empty = group[cam] < 0
            if len(free) == 0 or not empty.any():
                continue
            nearest = nearest_within(projected[cam, empty], points_2d[cam][free], tol)
            hit = nearest >= 0
            group[cam, np.flatnonzero(empty)[hit]] = free[nearest[hit]]
        group = np.unique(group, axis=1)
        fit = triangulator.triangulate(self._gather(points_2d, group), max_residual_px=tol)
        group = np.where(fit.used, group, -1)
        keep = np.isfinite(fit.points_3d).all(axis=1)
        group, points_3d, worst = group[:, keep], fit.points_3d[keep], fit.max_residual_px[keep]
        n_views = (group >= 0).sum(axis=0)
        if predicted is not None and np.isfinite(predicted).any() and len(points_3d):
            known = predicted[np.isfinite(predicted).all(axis=1)]
            distance = nearest_distance(points_3d, known)
            near = distance <= prior_mm
            order = np.lexsort((np.where(near, distance, worst), -n_views, ~near))
        else:
            order = np.lexsort((worst, -n_views))
        accepted = greedy_disjoint(group, order)
        return group[:, accepted], points_3d[accepted], worst[accepted]


def warm_up() -> None:
    """Compile (or load) this module's kernels for the argument types the live pipeline passes."""
    points, index = np.zeros((2, 2)), np.zeros(1, dtype=np.int64)
    epipolar_pairs(points, points, np.eye(3), 1.0)
    nearest_within(points, points, 1.0)
    nearest_distance(np.zeros((1, 3)), np.zeros((1, 3)))
    greedy_disjoint(np.zeros((2, 1), dtype=np.int64), index)


def greedy_disjoint(group: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Groups accepted greedily in ``order``, each detection used by at most one accepted group.

    Walks ``order`` and accepts every group that shares no detection with one accepted before it.

    Parameters
    ----------
    group : ndarray of int, shape (n_cams, n_groups)
        Detection index per camera, -1 where the group has no view.
    order : ndarray of int, shape (n_groups,)
        Priority order (a permutation of the groups).

    Returns
    -------
    ndarray of int
        Accepted groups, in priority order.
    """
    if group.shape[1] == 0:
        return np.zeros(0, dtype=np.int64)
    return _greedy_disjoint(np.ascontiguousarray(group, dtype=np.int64), np.asarray(order, dtype=np.int64))


@njit(cache=True, nogil=True)
def _greedy_disjoint(group, order):
    n_cams = group.shape[0]
    used = np.zeros((n_cams, max(group.max() + 1, 1)), dtype=np.bool_)
    accepted = np.empty(len(order), dtype=np.int64)
    n = 0
    for g in order:
        free = True
        for cam in range(n_cams):
            if group[cam, g] >= 0 and used[cam, group[cam, g]]:
                free = False
                break
        if free:
            for cam in range(n_cams):
                if group[cam, g] >= 0:
                    used[cam, group[cam, g]] = True
            accepted[n] = g
            n += 1
    return accepted[:n]


@njit(cache=True, nogil=True, error_model="numpy")
def epipolar_pairs(points_a, points_b, fundamental_ab, tolerance_px):
    """Detection pairs of cameras a and b that lie within ``tolerance_px`` of each other's epipolar line.

    Parameters
    ----------
    points_a : ndarray, shape (n_a, 2)
    points_b : ndarray, shape (n_b, 2)
        Undistorted pixel centroids.
    fundamental_ab : ndarray, shape (3, 3)
        ``x_bᵀ F x_a = 0``.
    tolerance_px : float

    Returns
    -------
    index_a, index_b : ndarray of int, shape (n_pairs,)
        In row-major order of (a, b).
    """
    f = fundamental_ab
    index_a = np.empty(len(points_a) * len(points_b), dtype=np.int64)
    index_b = np.empty_like(index_a)
    n = 0
    for i in range(len(points_a)):
        xa, ya = points_a[i, 0], points_a[i, 1]
        line_b = f[:, 0] * xa + f[:, 1] * ya + f[:, 2]  # epipolar line of a's point in b
        norm_b = np.hypot(line_b[0], line_b[1])
        for j in range(len(points_b)):
            xb, yb = points_b[j, 0], points_b[j, 1]
            algebraic = line_b[0] * xb + line_b[1] * yb + line_b[2]
            norm_a = np.hypot(f[0, 0] * xb + f[1, 0] * yb + f[2, 0], f[0, 1] * xb + f[1, 1] * yb + f[2, 1])
            if abs(algebraic) / norm_a < tolerance_px and abs(algebraic) / norm_b < tolerance_px:
                index_a[n], index_b[n] = i, j
                n += 1
    return index_a[:n], index_b[:n]


@njit(cache=True, nogil=True)
def nearest_within(queries, points, radius):
    """Index of the nearest of ``points (n, d)`` to each of ``queries (m, d)`` closer than ``radius``, else -1;
    non-finite queries get -1. Shape (m,)."""
    nearest = np.full(len(queries), -1, dtype=np.int64)
    for q in range(len(queries)):
        best = radius * radius
        for p in range(len(points)):
            distance = 0.0
            for k in range(queries.shape[1]):
                distance += (queries[q, k] - points[p, k]) ** 2
            if distance < best:
                best, nearest[q] = distance, p
    return nearest


@njit(cache=True, nogil=True)
def nearest_distance(queries, points):
    """Distance from each of ``queries (m, d)`` to the nearest of ``points (n, d)`` (inf when ``n == 0``)."""
    out = np.full(len(queries), np.inf)
    for q in range(len(queries)):
        for p in range(len(points)):
            distance = 0.0
            for k in range(queries.shape[1]):
                distance += (queries[q, k] - points[p, k]) ** 2
            out[q] = min(out[q], distance)
    return np.sqrt(out)
