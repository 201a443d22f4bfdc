"""Multi-view correspondence: group 2D detections across all cameras into 3D points.

Every pair of cameras proposes candidate matches by epipolar gating (symmetric point-to-line
distance within ``tolerance_px``). Each candidate pair is triangulated, projected into every other
camera, and picks up the nearest detection there within the same tolerance, so a candidate grows
into a group over *all* cameras. Groups are triangulated together (batched DLT), outlier views are
dropped by reprojection residual, and groups are accepted greedily - most views first, then the
smallest residual - with each detection used at most once. Detections left over go through a
second round on their own. Points seen by fewer than 2 cameras are never invented.

Two views alone are ambiguous when several markers lie near one epipolar plane. When the tracker
passes its predicted marker positions, groups whose point lies within ``prior_mm`` of a prediction
are accepted first (most views, then nearest to the prediction), so a marker seen by only two
cameras is not lost to a ghost pairing of its detections.

With predictions, tracked markers are found first the cheap way: each prediction is projected into
every camera and takes the nearest available detection (mutual nearest, within ``prior_mm`` at the
marker's depth); the groups are triangulated with outlier views dropped, grown into cameras with a
free detection within the tolerance of the point, and every view is cross-checked against the
point triangulated from the other views. Points with at least three views within ``prior_mm`` of
their prediction are accepted; everything else (markers seen by two cameras, returning markers,
strays) goes through one general round on the detections left. All rounds work on all cameras
at once (detections padded per camera), and the greedy acceptance is computed in a few vectorised
passes (:func:`greedy_disjoint`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

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
        self._pair_index = (np.array([a for a, _ in self.pairs], dtype=np.int64).reshape(-1),
                            np.array([b for _, b in self.pairs], dtype=np.int64).reshape(-1))
        self._fundamentals = np.array([self.fundamentals[pair] for pair in self.pairs]).reshape(-1, 3, 3)

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
        # detections padded to (n_cams, m + 1, 2), NaN rows where missing: index -1 reads a NaN row
        m = max(len(p) for p in points_2d)
        padded = np.full((n_cams, m + 1, 2), np.nan)
        for cam, p in enumerate(points_2d):
            padded[cam, :len(p)] = p
        available = np.isfinite(padded).all(axis=2)  # (n_cams, m + 1)
        groups, points_3d, residual = [], [], []
        if predicted is not None:
            predicted = np.asarray(predicted, dtype=np.float64).reshape(-1, 3)
            predicted = predicted[np.isfinite(predicted).all(axis=1)]
            if not len(predicted):
                predicted = None
        # tracked markers first (around their predictions), then one general round for the rest; without
        # predictions two general rounds (the second pairs what the first left over)
        rounds = [self._predicted, self._round] if predicted is not None else [self._round, self._round]
        for find in rounds:
            if (available.sum(axis=1) > 0).sum() < 2:
                break
            found = find(padded, available, predicted, prior_mm)
            if found is None:
                if find == self._round:
                    break  # nothing more to pair
                continue
            g, x, r = found
            groups.append(g)
            points_3d.append(x)
            residual.append(r)
            available[np.arange(n_cams)[:, None], g] = False
            available[:, -1] = False
        n_unused = int(available.sum())
        if not groups:
            return Correspondence(np.zeros((0, 3)), np.zeros((n_cams, 0), dtype=np.int64), np.zeros(0), n_unused)
        return Correspondence(np.concatenate(points_3d), np.concatenate(groups, axis=1), np.concatenate(residual),
                              n_unused)

    def _predicted(self, padded, available, predicted, prior_mm):
        """Groups of the tracked markers, found around their predicted projections (see the module docstring).

        ``padded (n_cams, m + 1, 2)`` detections, ``available (n_cams, m + 1)``, ``predicted (n, 3)`` finite.
        Returns ``(group (n_cams, k), points_3d (k, 3), worst residual (k,))`` or None.
        """
        triangulator, tol = self.triangulator, self.tolerance_px
        n_cams, m = padded.shape[0], padded.shape[1] - 1
        padded = np.where(available[..., None], padded, np.nan)
        cams = np.arange(n_cams)[:, None]
        target = predicted
        n = len(target)
        projected = triangulator.reproject(target)  # (c, n, 2)
        # a detection farther than prior_mm (at the marker's depth) from the projection cannot give a point
        # within prior_mm of the prediction
        depth = np.einsum("cj,nj->cn", triangulator.extrinsics[:, 2, :3], target) + triangulator.extrinsics[:, 2, 3,
                                                                                                            None]
        with np.errstate(divide="ignore", invalid="ignore"):
            gate = np.where(depth > 0, prior_mm * triangulator.focal_px[:, None] / depth, 0.0) + tol  # (c, n)
        offset = projected[:, :, None, :] - padded[:, None, :m, :]
        distance = offset[..., 0] ** 2 + offset[..., 1] ** 2  # (c, n, m), squared
        distance[np.isnan(distance)] = np.inf
        nearest = distance.argmin(axis=2)  # (c, n)
        closest = np.take_along_axis(distance, nearest[..., None], axis=2)[..., 0]
        mutual = np.take_along_axis(distance.argmin(axis=1), nearest, axis=1) == np.arange(n)
        group = np.where(mutual & (closest <= gate**2), nearest, -1)
        enough = (group >= 0).sum(axis=0) >= 2
        if not enough.any():
            return None
        group, target = group[:, enough], target[enough]
        fit = triangulator.triangulate(padded[cams, group], max_residual_px=tol)
        group = np.where(fit.used, group, -1)
        # grow into every camera where a free detection lies within the tolerance of the point's projection
        # (a view the prediction gate missed, or one whose nearest detection was wrong and failed the residual test)
        found = np.isfinite(fit.points_3d).all(axis=1)
        missing = found & (group < 0)  # (c, n)
        if missing.any():
            free = np.ones((n_cams, m + 1), dtype=bool)
            free[cams, group] = False
            reprojected = triangulator.reproject(fit.points_3d)
            offset = reprojected[:, :, None, :] - padded[:, None, :m, :]
            distance = offset[..., 0] ** 2 + offset[..., 1] ** 2
            distance[np.isnan(distance) | ~free[:, None, :m] | ~missing[..., None]] = np.inf
            nearest = distance.argmin(axis=2)
            hit = np.take_along_axis(distance, nearest[..., None], axis=2)[..., 0] <= tol**2
            if hit.any():
                group = np.where(hit, nearest, group)
                fit = triangulator.triangulate(padded[cams, group], max_residual_px=tol)
                group = np.where(fit.used, group, -1)
        # cross-check: every view must lie within the tolerance of the point triangulated from the other views
        # (a wrong detection close to a marker's projection can pass the residual test inside the fit that it
        # pulls); a view that fails is dropped. Two views alone can pair a marker's detection with a
        # neighbour's on its epipolar line: markers left with fewer than three views go to the general round,
        # which weighs every pairing against the prediction.
        observed = padded[cams, group]  # (c, n, 2)
        used = fit.used & np.isfinite(fit.points_3d).all(axis=1)
        if used.any():
            held_out = np.where((np.arange(n_cams)[:, None, None] == np.arange(n_cams)[None, :, None])[..., None],
                                np.nan, observed[None])  # (c_left_out, c, n, 2)
            others = triangulator.dlt(held_out.transpose(1, 0, 2, 3).reshape(n_cams, -1, 2)).reshape(n_cams, -1, 3)
            check = triangulator.reproject(others.reshape(-1, 3)).reshape(n_cams, n_cams, -1, 2)
            diagonal = np.arange(n_cams)
            loo = np.linalg.norm(check[diagonal, diagonal] - observed, axis=-1)  # (c, n): view c vs the others' point
            failed = used & ~(loo <= tol)
            if failed.any():
                group = np.where(failed, -1, group)
                fit = triangulator.triangulate(padded[cams, group], max_residual_px=tol)
                group = np.where(fit.used, group, -1)
        near = (np.linalg.norm(fit.points_3d - target, axis=1) <= prior_mm) & (fit.n_views >= 3)  # False for NaN
        group, points_3d, worst = group[:, near], fit.points_3d[near], fit.max_residual_px[near]
        accepted = greedy_disjoint(group, np.lexsort((worst, -(group >= 0).sum(axis=0))))
        return group[:, accepted], points_3d[accepted], worst[accepted]

    def _candidates(self, padded, available) -> np.ndarray:
        """Candidate groups from epipolar pairs, shape (n_cams, n_candidates) of detection indices."""
        n_cams, m = padded.shape[0], padded.shape[1] - 1
        first, second = self._pair_index
        points = np.concatenate([padded[:, :m], np.ones((n_cams, m, 1))], axis=2)  # (c, m, 3) homogeneous
        xa, xb = points[first], points[second]  # (p, m, 3)
        lines_b = xa @ self._fundamentals.transpose(0, 2, 1)  # (p, m, 3): epipolar lines in b of a's points
        lines_a = xb @ self._fundamentals  # (p, m, 3): epipolar lines in a of b's points
        algebraic = np.abs(lines_b @ xb.transpose(0, 2, 1))  # (p, ma, mb) = |x_bᵀ F x_a|
        with np.errstate(invalid="ignore", divide="ignore"):
            dist_b = algebraic / np.hypot(lines_b[..., 0], lines_b[..., 1])[:, :, None]
            dist_a = algebraic / np.hypot(lines_a[..., 0], lines_a[..., 1])[:, None, :]
            close = np.maximum(dist_a, dist_b) < self.tolerance_px  # False for NaN
        close &= available[first, :m, None] & available[second, None, :m]
        pair, ia, ib = np.nonzero(close)
        group = np.full((n_cams, len(pair)), -1, dtype=np.int64)
        columns = np.arange(len(pair))
        group[first[pair], columns] = ia
        group[second[pair], columns] = ib
        return group

    def _gather(self, points_2d, group) -> np.ndarray:
        """2D observations of groups, shape (n_cams, n_groups, 2), NaN where the group has no view."""
        n_cams, n_groups = group.shape
        out = np.full((n_cams, n_groups, 2), np.nan)
        for cam in range(n_cams):
            has = group[cam] >= 0
            out[cam, has] = points_2d[cam][group[cam, has]]
        return out

    def _round(self, padded, available, predicted, prior_mm):
        """One round of the general correspondence over the available detections (see the module docstring)."""
        triangulator, tol = self.triangulator, self.tolerance_px
        n_cams, m = padded.shape[0], padded.shape[1] - 1
        padded = np.where(available[..., None], padded, np.nan)
        cams = np.arange(n_cams)[:, None]
        group = self._candidates(padded, available)
        if group.shape[1] == 0:
            return None
        # grow every pair into the other cameras: the nearest available detection within the tolerance
        projected = triangulator.reproject(triangulator.dlt(padded[cams, group]))  # (c, n, 2)
        offset = projected[:, :, None, :] - padded[:, None, :m, :]
        distance = offset[..., 0] ** 2 + offset[..., 1] ** 2  # (c, n, m), NaN where unavailable
        distance[np.isnan(distance)] = np.inf
        nearest = distance.argmin(axis=2)
        hit = (group < 0) & (np.take_along_axis(distance, nearest[..., None], axis=2)[..., 0] < tol**2)
        group = np.unique(np.where(hit, nearest, group), axis=1)
        fit = triangulator.triangulate(padded[cams, group], max_residual_px=tol)
        group = np.where(fit.used, group, -1)
        keep = np.isfinite(fit.points_3d).all(axis=1)
        group, points_3d, worst = group[:, keep], fit.points_3d[keep], fit.max_residual_px[keep]
        n_views = (group >= 0).sum(axis=0)
        if predicted is not None and len(points_3d):
            distance = np.sqrt(((points_3d[:, None] - predicted[None]) ** 2).sum(axis=2)).min(axis=1)
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
