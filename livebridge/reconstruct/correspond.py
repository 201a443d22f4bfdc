"""Multi-view correspondence: group 2D detections across all cameras into 3D points.

Every pair of cameras proposes candidate matches by epipolar gating (symmetric point-to-line
distance within ``tolerance_px``). Each candidate pair is triangulated, projected into every other
camera, and picks up the nearest detection there within the same tolerance, so a candidate grows
into a group over *all* cameras. Groups are triangulated together (batched DLT), outlier views are
dropped by reprojection residual, and groups are accepted greedily - most views first, then the
smallest residual - with each detection used at most once (:func:`greedy_disjoint`, a few
vectorised passes instead of a walk over the groups). Detections left over go through a
second round on their own. Points seen by fewer than 2 cameras are never invented.

Two views alone are ambiguous when several markers lie near one epipolar plane. When the tracker
passes its predicted marker positions, groups whose point lies within ``prior_mm`` of a prediction
are accepted first (most views, then nearest to the prediction), so a marker seen by only two
cameras is not lost to a ghost pairing of its detections.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

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
            xa = np.column_stack([points_2d[a][index[a]], np.ones(len(index[a]))])
            xb = np.column_stack([points_2d[b][index[b]], np.ones(len(index[b]))])
            f = self.fundamentals[(a, b)]
            lines_b = xa @ f.T  # (na, 3): epipolar lines in b
            lines_a = xb @ f  # (nb, 3): epipolar lines in a
            algebraic = xa @ f.T @ xb.T  # (na, nb) = x_bᵀ F x_a
            dist_b = np.abs(algebraic) / np.hypot(lines_b[:, 0], lines_b[:, 1])[:, None]
            dist_a = np.abs(algebraic) / np.hypot(lines_a[:, 0], lines_a[:, 1])[None, :]
            ia, ib = np.nonzero(np.maximum(dist_a, dist_b) < tol)
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
            query = projected[cam, empty]
            finite = np.isfinite(query).all(axis=1)
            distance, nearest = cKDTree(points_2d[cam][free]).query(np.where(finite[:, None], query, 1e12),
                                                                    distance_upper_bound=tol)
            hit = np.isfinite(distance)
            target = np.flatnonzero(empty)[hit]
            group[cam, target] = free[nearest[hit]]
        group = np.unique(group, axis=1)
        fit = triangulator.triangulate(self._gather(points_2d, group), max_residual_px=tol)
        group = np.where(fit.used, group, -1)
        keep = np.isfinite(fit.points_3d).all(axis=1)
        group, points_3d, worst = group[:, keep], fit.points_3d[keep], fit.max_residual_px[keep]
        n_views = (group >= 0).sum(axis=0)
        if predicted is not None and np.isfinite(predicted).any() and len(points_3d):
            known = predicted[np.isfinite(predicted).all(axis=1)]
            distance, _ = cKDTree(known).query(points_3d)
            near = distance <= prior_mm
            order = np.lexsort((np.where(near, distance, worst), -n_views, ~near))
        else:
            order = np.lexsort((worst, -n_views))
        accepted = greedy_disjoint(group, order)
        return group[:, accepted], points_3d[accepted], worst[accepted]


def greedy_disjoint(group: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Groups accepted greedily in ``order``, each detection used by at most one accepted group.

    The same result as walking ``order`` and accepting every group that shares no detection with
    one accepted before it, computed in rounds over all groups at once: a group is accepted when
    it comes first (in ``order``) for every detection it uses among the groups still open; groups
    that share a detection with an accepted one close. The first open group is always accepted,
    so the rounds end, and there are few of them in practice.

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
    n_cams, n_groups = group.shape
    if n_groups == 0:
        return np.zeros(0, dtype=np.int64)
    rank = np.empty(n_groups, dtype=np.int64)
    rank[order] = np.arange(n_groups)
    has = group >= 0
    offsets = np.concatenate([[0], np.cumsum(np.maximum(group.max(axis=1), -1) + 1)])
    ids = np.where(has, group + offsets[:-1, None], offsets[-1])  # one id per (camera, detection); spare id
    open_ = np.ones(n_groups, dtype=bool)
    accepted = np.zeros(n_groups, dtype=bool)
    while open_.any():
        first = np.full(offsets[-1] + 1, n_groups, dtype=np.int64)
        live = has & open_
        np.minimum.at(first, ids[live], np.broadcast_to(rank, ids.shape)[live])
        wins = open_ & ((first[ids] == rank) | ~has).all(axis=0)
        accepted |= wins
        used = np.zeros(offsets[-1] + 1, dtype=bool)
        used[ids[:, wins]] = True
        used[-1] = False
        open_ &= ~wins & ~used[ids].any(axis=0)
    chosen = np.flatnonzero(accepted)
    return chosen[np.argsort(rank[chosen])]
