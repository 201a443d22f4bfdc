"""Batched multi-view triangulation (DLT) with outlier-view rejection and optional refinement.

Points are *undistorted* pixel coordinates (``Camera.undistort_points``), camera-first,
NaN where a camera does not see the point: ``points_2d (n_cams, n_points, 2)``.

The DLT is the same algebraic problem aniposelib solves (rows ``x P_3 - P_1``, ``y P_3 - P_2``
in normalised camera coordinates with ``P = [R | t]``), so results agree with
``aniposelib.cameras.CameraGroup.triangulate`` to numerical precision. Instead of one SVD per
point, the ``(4, 4)`` normal matrix ``AᵀA`` of every point is built with a single matrix product
over per-camera quadratic forms, and its null vector found by inverse iteration: one compiled loop
(numba) factorises every point's matrix and iterates, where a batched ``np.linalg.inv`` cost half the
frame in call overhead. This is what makes a frame of ~70 markers cost tens of microseconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from livebridge.calibration.cameras import CameraGroup

INVERSE_ITERATIONS = 2


@njit(cache=True, nogil=True)
def null_vectors(normal: np.ndarray, iterations: int) -> np.ndarray:
    """Null vector of each ``(4, 4)`` normal matrix by inverse iteration, shape (n, 4).

    Starts from the last column of the inverse (``N^-1 e_4``) and applies ``N^-1`` ``iterations``
    more times, each a solve with the same LU factors (partial pivoting). A row whose matrix is
    exactly singular comes back as NaN: the caller solves those with an eigendecomposition.
    """
    n = normal.shape[0]
    out = np.empty((n, 4))
    lu = np.empty((4, 4))
    pivot = np.empty(4, dtype=np.int64)
    vector = np.empty(4)
    for i in range(n):
        lu[:, :] = normal[i]
        singular = False
        for k in range(4):
            best = k
            for r in range(k + 1, 4):
                if abs(lu[r, k]) > abs(lu[best, k]):
                    best = r
            pivot[k] = best
            if lu[best, k] == 0.0:
                singular = True
                break
            if best != k:
                for c in range(4):
                    lu[k, c], lu[best, c] = lu[best, c], lu[k, c]
            for r in range(k + 1, 4):
                lu[r, k] /= lu[k, k]
                for c in range(k + 1, 4):
                    lu[r, c] -= lu[r, k] * lu[k, c]
        if singular:
            out[i, :] = np.nan
            continue
        vector[:] = 0.0
        vector[3] = 1.0
        for _ in range(iterations + 1):
            for k in range(4):  # apply the row swaps, then forward and back substitution
                p = pivot[k]
                vector[k], vector[p] = vector[p], vector[k]
            for r in range(1, 4):
                for c in range(r):
                    vector[r] -= lu[r, c] * vector[c]
            for r in range(3, -1, -1):
                for c in range(r + 1, 4):
                    vector[r] -= lu[r, c] * vector[c]
                vector[r] /= lu[r, r]
        out[i, :] = vector
    return out


@dataclass(frozen=True, eq=False)
class Triangulation:
    """Triangulated points and how well they fit.

    Attributes
    ----------
    points_3d : ndarray, shape (n_points, 3)
        World positions (mm); NaN where fewer than 2 views remain.
    used : ndarray of bool, shape (n_cams, n_points)
        The views each point was triangulated from (outlier views removed).
    residual_px : ndarray, shape (n_cams, n_points)
        Reprojection error of every observed view in undistorted pixels (NaN where unobserved).
    """

    points_3d: np.ndarray
    used: np.ndarray
    residual_px: np.ndarray

    @property
    def n_views(self) -> np.ndarray:
        """Views used per point, shape (n_points,)."""
        return self.used.sum(axis=0)

    @property
    def max_residual_px(self) -> np.ndarray:
        """Largest residual over the used views, shape (n_points,); NaN where not triangulated."""
        residual = np.where(self.used, self.residual_px, -np.inf).max(axis=0)
        return np.where(np.isfinite(residual), residual, np.nan)


class Triangulator:
    """Triangulation for one calibrated rig (precomputes the per-camera matrices).

    Parameters
    ----------
    cameras : CameraGroup
    """

    def __init__(self, cameras: CameraGroup):
        self.cameras = cameras
        self.inverse_matrices = np.linalg.inv(np.stack([camera.matrix for camera in cameras.cameras]))
        self.extrinsics = np.stack([camera.world2cam[:3] for camera in cameras.cameras])  # (c, 3, 4)
        self.projections = np.stack([camera.projection for camera in cameras.cameras])  # (c, 3, 4)
        # AᵀA = Σ_cams (x²+y²) P3P3ᵀ - x (P3P1ᵀ+P1P3ᵀ) - y (P3P2ᵀ+P2P3ᵀ) + P1P1ᵀ + P2P2ᵀ
        rt = self.extrinsics
        outer = np.einsum("cai,cbj->cabij", rt, rt)
        q33, q_x, q_y = outer[:, 2, 2], -(outer[:, 2, 0] + outer[:, 0, 2]), -(outer[:, 2, 1] + outer[:, 1, 2])
        q_1 = outer[:, 0, 0] + outer[:, 1, 1]
        # in pixels, x = a u + b and y = g v + d (no skew): the forms of (u², v², u, v, 1) per camera
        k = self.inverse_matrices
        self._skewed = bool(np.abs(k[:, 0, 1]).max() > 0)
        if self._skewed:  # normalise first (x = u, y = v below)
            k = np.tile(np.eye(3), (len(k), 1, 1))
        a, b, g, d = (k[:, 0, 0, None, None], k[:, 0, 2, None, None], k[:, 1, 1, None, None], k[:, 1, 2, None, None])
        forms = np.stack([a * a * q33, g * g * q33, 2 * a * b * q33 + a * q_x, 2 * g * d * q33 + g * q_y,
                          (b * b + d * d) * q33 + b * q_x + d * q_y + q_1], axis=1)  # (c, 5, 4, 4)
        self._forms = forms.reshape(-1, 16)  # (c * 5, 16)

    def __len__(self) -> int:
        return len(self.cameras)

    def normalize(self, points_2d: np.ndarray) -> np.ndarray:
        """Undistorted pixels to normalised camera coordinates, ``(n_cams, n, 2)`` in and out."""
        k = self.inverse_matrices
        x, y = points_2d[..., 0], points_2d[..., 1]
        return np.stack([k[:, 0, 0, None] * x + k[:, 0, 1, None] * y + k[:, 0, 2, None],
                         k[:, 1, 1, None] * y + k[:, 1, 2, None]], axis=-1)

    def dlt(self, points_2d: np.ndarray) -> np.ndarray:
        """Linear triangulation of every point from all the views that see it.

        Parameters
        ----------
        points_2d : ndarray, shape (n_cams, n_points, 2)
            Undistorted pixels, NaN where unseen.

        Returns
        -------
        ndarray, shape (n_points, 3); NaN where fewer than 2 views.
        """
        points_2d = np.asarray(points_2d, dtype=np.float64)
        n_cams, n_points = points_2d.shape[:2]
        if n_points == 0:
            return np.zeros((0, 3))
        if self._skewed:  # rare: a skewed intrinsic matrix, so work in normalised coordinates
            points_2d = self.normalize(points_2d)
        seen = ~np.isnan(points_2d[..., 0])  # (c, n)
        pixels = np.where(seen[..., None], points_2d, 0.0).transpose(1, 0, 2)  # (n, c, 2), unseen -> 0
        features = np.empty((n_points, n_cams, 5))
        np.square(pixels, out=features[..., :2])
        features[..., 2:4] = pixels
        features[..., 4] = seen.T
        normal = (features.reshape(n_points, -1) @ self._forms).reshape(n_points, 4, 4)
        enough = seen.sum(axis=0) >= 2
        all_enough = bool(enough.all())
        if not all_enough:
            normal[~enough] = np.eye(4)
        vector = null_vectors(normal, INVERSE_ITERATIONS)
        singular = np.isnan(vector[:, 0])
        if singular.any():  # an exactly singular system (noise-free data): eigen-solve those
            vector[singular] = np.linalg.eigh(normal[singular])[1][:, :, 0]
        with np.errstate(all="ignore"):
            points_3d = vector[:, :3] / vector[:, 3:]
        if not all_enough:
            points_3d[~enough] = np.nan
        return points_3d

    def residuals(self, points_3d: np.ndarray, points_2d: np.ndarray) -> np.ndarray:
        """Reprojection error in undistorted pixels, shape (n_cams, n_points); NaN where unseen.

        Parameters
        ----------
        points_3d : ndarray, shape (n_points, 3)
        points_2d : ndarray, shape (n_cams, n_points, 2)
        """
        return np.linalg.norm(self.reproject(points_3d) - points_2d, axis=-1)

    def reproject(self, points_3d: np.ndarray) -> np.ndarray:
        """Undistorted pixels of world points in every camera, shape (n_cams, n_points, 2)."""
        homogeneous = np.einsum("cij,nj->cni", self.projections[:, :, :3], points_3d) + self.projections[:, None, :, 3]
        with np.errstate(all="ignore"):
            return homogeneous[..., :2] / homogeneous[..., 2:]

    def triangulate(self, points_2d: np.ndarray, max_residual_px: float = 2.0, refine_iterations: int = 0,
                    min_views: int = 2) -> Triangulation:
        """DLT over all views, then drop outlier views until every residual is below ``max_residual_px``.

        A point whose worst used view is off by more than ``max_residual_px`` loses that view and is
        triangulated again, while it keeps at least ``min_views`` views; a point that cannot be
        brought under the threshold with ``min_views`` views is dropped (NaN). Optionally a few
        Gauss-Newton steps then minimise the pixel reprojection error.

        Parameters
        ----------
        points_2d : ndarray, shape (n_cams, n_points, 2)
            Undistorted pixels, NaN where unseen.
        max_residual_px : float
        refine_iterations : int
            Gauss-Newton steps on the reprojection error after the DLT (0: DLT only).
        min_views : int

        Returns
        -------
        Triangulation
        """
        points_2d = np.asarray(points_2d, dtype=np.float64)
        used = np.isfinite(points_2d).all(axis=-1)
        points_3d = self.dlt(points_2d)
        for _ in range(len(self)):
            residual = self.residuals(points_3d, points_2d)
            masked = np.where(used, residual, -np.inf)
            worst = masked.argmax(axis=0)
            bad = np.take_along_axis(masked, worst[None], axis=0)[0] > max_residual_px
            fixable = bad & (used.sum(axis=0) > min_views)
            if not fixable.any():
                break
            used[worst[fixable], np.flatnonzero(fixable)] = False
            subset = np.where(used[:, fixable, None], points_2d[:, fixable], np.nan)
            points_3d[fixable] = self.dlt(subset)
        if refine_iterations:
            points_3d = self.refine(points_3d, np.where(used[..., None], points_2d, np.nan), refine_iterations)
        residual = self.residuals(points_3d, points_2d)
        worst = np.where(used, residual, -np.inf).max(axis=0)
        failed = (used.sum(axis=0) < min_views) | ~(worst <= max_residual_px)
        points_3d[failed] = np.nan
        used[:, failed] = False
        return Triangulation(points_3d, used, residual)

    def refine(self, points_3d: np.ndarray, points_2d: np.ndarray, iterations: int = 2) -> np.ndarray:
        """Gauss-Newton steps minimising the pixel reprojection error of every point (batched).

        Parameters
        ----------
        points_3d : ndarray, shape (n_points, 3)
        points_2d : ndarray, shape (n_cams, n_points, 2)
            Undistorted pixels, NaN where not used.

        Returns
        -------
        ndarray, shape (n_points, 3)
        """
        points_3d = np.array(points_3d, dtype=np.float64)
        seen = np.isfinite(points_2d).all(axis=-1)  # (c, n)
        ok = np.isfinite(points_3d).all(axis=1) & (seen.sum(axis=0) >= 2)
        if not ok.any():
            return points_3d
        p = self.projections
        observed = np.where(seen[..., None], points_2d, 0.0)[:, ok]
        weight = seen[:, ok].astype(np.float64)
        estimate = points_3d[ok]
        for _ in range(iterations):
            h = np.einsum("cij,nj->cni", p[:, :, :3], estimate) + p[:, None, :, 3]  # (c, n, 3)
            u = h[..., :2] / h[..., 2:]
            # d(u)/dX = (P_a - u_a P_3)[:3] / h_3
            jac = (p[:, None, :2, :3] - u[..., None] * p[:, None, 2:3, :3]) / h[..., 2:, None]  # (c, n, 2, 3)
            r = (observed - u) * weight[..., None]
            jac = jac * weight[..., None, None]
            jtj = np.einsum("cnai,cnaj->nij", jac, jac)
            jtr = np.einsum("cnai,cna->ni", jac, r)
            estimate = estimate + np.linalg.solve(jtj, jtr[..., None])[..., 0]
        points_3d[ok] = estimate
        return points_3d
