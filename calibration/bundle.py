"""Bundle adjustment of all cameras (intrinsics and extrinsics) and all board poses.

``scipy.optimize.least_squares`` (trust-region reflective, LSMR) with a sparse
Jacobian pattern (``jac_sparsity``), a robust loss, and iterative pruning of
outlier corners between rounds. Camera 0 is held at the world origin (the
gauge); the board's known size fixes the scale. Everything is deterministic:
no random sampling, fixed iteration order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import csr_matrix

from livebridge.calibration.boards import Board
from livebridge.geometry.transforms import apply, rotation_matrices, rotation_vector


@dataclass(frozen=True, eq=False)
class BundleResult:
    """Refined cameras and board poses.

    Attributes
    ----------
    matrices : ndarray, shape (n_cams, 3, 3)
    distortions : ndarray, shape (n_cams, 5) or (n_cams, 4) for fisheye
    world2cam : ndarray, shape (n_cams, 4, 4)
    board2world : ndarray, shape (n_views, 4, 4); NaN for views not used
    errors : ndarray, shape (n_cams, n_views, n_corners)
        Reprojection error in pixels of every detected corner (NaN where not detected).
    inliers : ndarray, bool, shape (n_cams, n_views, n_corners)
        Corners kept after outlier pruning.
    rounds : int
        Optimisation rounds run.
    """

    matrices: np.ndarray
    distortions: np.ndarray
    world2cam: np.ndarray
    board2world: np.ndarray
    errors: np.ndarray
    inliers: np.ndarray
    rounds: int

    def rms_px(self, inliers_only: bool = True) -> np.ndarray:
        """RMS reprojection error per camera, shape (n_cams,)."""
        errors = np.where(self.inliers, self.errors, np.nan) if inliers_only else self.errors
        flat = errors.reshape(len(errors), -1)
        count = np.isfinite(flat).sum(axis=1)
        return np.sqrt(np.nansum(flat ** 2, axis=1) / np.maximum(count, 1)) + np.where(count, 0.0, np.nan)


def distort(normalised: np.ndarray, matrix_params: np.ndarray, distortions: np.ndarray,
            fisheye: bool) -> np.ndarray:
    """Apply the lens model to normalised points.

    Parameters
    ----------
    normalised : ndarray, shape (n, 2)
        ``(X/Z, Y/Z)``.
    matrix_params : ndarray, shape (n, 4)
        ``(fx, fy, cx, cy)`` per point.
    distortions : ndarray, shape (n, 5) pinhole or (n, 4) fisheye
        Per point.

    Returns
    -------
    ndarray, shape (n, 2): pixels, identical to ``cv2.projectPoints`` / ``cv2.fisheye.projectPoints``.
    """
    x, y = normalised[:, 0], normalised[:, 1]
    if fisheye:
        r = np.hypot(x, y)
        theta = np.arctan(r)
        t2 = theta * theta
        k = distortions
        theta_d = theta * (1 + t2 * (k[:, 0] + t2 * (k[:, 1] + t2 * (k[:, 2] + t2 * k[:, 3]))))
        scale = np.where(r > 1e-12, theta_d / np.where(r > 1e-12, r, 1.0), 1.0)
        xd, yd = x * scale, y * scale
    else:
        k1, k2, p1, p2, k3 = distortions.T
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([matrix_params[:, 0] * xd + matrix_params[:, 2], matrix_params[:, 1] * yd + matrix_params[:, 3]],
                    axis=1)


class _Problem:
    """Parameter layout, residuals and Jacobian pattern for one set of observations."""

    def __init__(self, board: Board, corners: np.ndarray, mask: np.ndarray, views: np.ndarray, n_dist: int,
                 fisheye: bool):
        self.middle = board.object_points.mean(axis=0)
        self.object_points = board.object_points - self.middle  # board poses rotate about the board's middle
        self.n_cams = corners.shape[0]
        self.views = views  # view indices with a board pose parameter
        self.n_dist = n_dist
        self.fisheye = fisheye
        view_slot = np.full(corners.shape[1], -1)
        view_slot[views] = np.arange(len(views))
        cam, view, corner = np.nonzero(mask & (view_slot[None, :, None] >= 0))
        self.cam, self.view, self.corner = cam, view_slot[view], corner
        self.observed = corners[cam, view, corner]
        self.n_intr = 4 + n_dist
        self.extr_offset = 0
        self.intr_offset = 6 * (self.n_cams - 1)
        self.board_offset = self.intr_offset + self.n_intr * self.n_cams
        self.n_params = self.board_offset + 6 * len(views)

    def pack(self, matrices, distortions, world2cam, board2world) -> np.ndarray:
        params = np.zeros(self.n_params)
        for c in range(1, self.n_cams):
            centre = -world2cam[c, :3, :3].T @ world2cam[c, :3, 3]
            params[6 * (c - 1):6 * c] = np.r_[rotation_vector(world2cam[c, :3, :3]), centre]
        for c in range(self.n_cams):
            k = matrices[c]
            start = self.intr_offset + self.n_intr * c
            params[start:start + self.n_intr] = np.r_[k[0, 0], k[1, 1], k[0, 2], k[1, 2], distortions[c]]
        for i, v in enumerate(self.views):
            start = self.board_offset + 6 * i
            rotation = board2world[v, :3, :3]
            params[start:start + 6] = np.r_[rotation_vector(rotation), rotation @ self.middle + board2world[v, :3, 3]]
        return params

    def unpack(self, params):
        extr = np.zeros((self.n_cams, 6))
        extr[1:] = params[:self.intr_offset].reshape(-1, 6)
        intr = params[self.intr_offset:self.board_offset].reshape(self.n_cams, self.n_intr)
        boards = params[self.board_offset:].reshape(-1, 6)
        return extr, intr, boards

    def project(self, params: np.ndarray) -> np.ndarray:
        """Pixels of every observation, shape (n_obs, 2)."""
        extr, intr, boards = self.unpack(params)
        board_rot = rotation_matrices(boards[:, :3])
        world = np.einsum("vij,nj->vni", board_rot, self.object_points) + boards[:, None, 3:]
        points = world[self.view, self.corner]
        cam_rot = rotation_matrices(extr[:, :3])
        in_cam = np.einsum("nij,nj->ni", cam_rot[self.cam], points - extr[self.cam, 3:])
        z = in_cam[:, 2:3]
        normalised = in_cam[:, :2] / np.where(np.abs(z) > 1e-9, z, 1e-9)
        per_obs = intr[self.cam]
        return distort(normalised, per_obs[:, :4], per_obs[:, 4:], self.fisheye)

    def scale(self) -> np.ndarray:
        """Typical parameter change for one pixel of effect (``x_scale``), shape (n_params,)."""
        extr = np.tile([1e-3, 1e-3, 1e-3, 1.0, 1.0, 1.0], self.n_cams - 1)
        dist = [1e-3] * self.n_dist if self.fisheye else [1e-3, 1e-3, 1e-4, 1e-4, 1e-3]
        intr = np.tile(np.r_[[1.0, 1.0, 1.0, 1.0], dist], self.n_cams)
        boards = np.tile([1e-3, 1e-3, 1e-3, 1.0, 1.0, 1.0], len(self.views))
        return np.r_[extr, intr, boards]

    def residuals(self, params: np.ndarray) -> np.ndarray:
        return (self.project(params) - self.observed).ravel()

    def blocks(self) -> list[np.ndarray]:
        """Parameter indices of each camera (extrinsics + intrinsics) and each board pose."""
        out = []
        for c in range(self.n_cams):
            extr = np.arange(6 * (c - 1), 6 * c) if c > 0 else np.arange(0)
            out.append(np.r_[extr, self.intr_offset + self.n_intr * c + np.arange(self.n_intr)].astype(int))
        out += [self.board_offset + 6 * i + np.arange(6) for i in range(len(self.views))]
        return out

    def preconditioner(self, params: np.ndarray) -> csr_matrix:
        """Block-diagonal P with ``(J_b P_b)^T (J_b P_b) = I`` per block, from forward differences.

        Columns of different cameras never share a row, nor do columns of different board poses, so
        one evaluation per column position covers all blocks of a kind (about 21 evaluations).
        """
        blocks = self.blocks()
        grams = []
        base = self.residuals(params).reshape(-1, 2)
        for group, owner in ((blocks[:self.n_cams], self.cam), (blocks[self.n_cams:], self.view)):
            width = max((len(b) for b in group), default=0)
            derivative = np.zeros((len(base), 2, width))
            for j in range(width):
                step = np.zeros_like(params)
                for b in group:
                    if j < len(b):
                        step[b[j]] = 1e-6 * max(1.0, abs(params[b[j]]))
                per_block = np.array([step[b[j]] if j < len(b) else 1.0 for b in group])
                derivative[:, :, j] = (self.residuals(params + step).reshape(-1, 2) - base) / per_block[owner][:, None]
            for k, b in enumerate(group):
                rows = derivative[owner == k][:, :, :len(b)].reshape(-1, len(b))
                grams.append(rows.T @ rows)
        rows, cols, values = [], [], []
        for b, gram in zip(blocks, grams):
            eigenvalues, vectors = np.linalg.eigh(gram)
            floor = max(eigenvalues.max(), 1e-300) * 1e-14
            block = vectors / np.sqrt(np.maximum(eigenvalues, floor))
            r, c = np.meshgrid(b, b, indexing="ij")
            rows.append(r.ravel())
            cols.append(c.ravel())
            values.append(block.ravel())
        return csr_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(len(params), len(params)))

    def sparsity(self) -> csr_matrix:
        n_obs = len(self.cam)
        extr_cols = np.where(self.cam[:, None] > 0, 6 * (self.cam[:, None] - 1) + np.arange(6), -1)
        intr_cols = self.intr_offset + self.n_intr * self.cam[:, None] + np.arange(self.n_intr)
        board_cols = self.board_offset + 6 * self.view[:, None] + np.arange(6)
        columns = np.concatenate([extr_cols, intr_cols, board_cols], axis=1)
        rows = np.repeat(np.arange(n_obs), columns.shape[1]).reshape(n_obs, -1)
        keep = columns >= 0
        r, col = rows[keep], columns[keep]
        r = np.concatenate([2 * r, 2 * r + 1])
        col = np.concatenate([col, col])
        return csr_matrix((np.ones(len(r), np.int8), (r, col)), shape=(2 * n_obs, self.n_params))


def bundle_adjust(board: Board, corners: np.ndarray, matrices: np.ndarray, distortions: np.ndarray,
                  world2cam: np.ndarray, board2world: np.ndarray, fisheye: bool = False, f_scale_px: float = 1.0,
                  prune_rounds: int = 3, min_threshold_px: float = 1.0, max_nfev: int = 200) -> BundleResult:
    """Refine every camera's lens and pose and every board pose together.

    Parameters
    ----------
    board : Board
    corners : ndarray, shape (n_cams, n_views, n_corners, 2)
        Detections, NaN where unseen.
    matrices : ndarray, shape (n_cams, 3, 3)
    distortions : ndarray, shape (n_cams, 5) or (n_cams, 4) when ``fisheye``
    world2cam : ndarray, shape (n_cams, 4, 4)
        Initial poses; camera 0 must be the identity (it stays fixed).
    board2world : ndarray, shape (n_views, 4, 4)
        Initial board poses, NaN for views to leave out.
    fisheye : bool
    f_scale_px : float
        Scale of the soft-L1 robust loss in pixels.
    prune_rounds : int
        After each round, corners with error above ``max(min_threshold_px, 5 sigma)`` are dropped
        (sigma from the median error) and the problem is solved again, at most this many times.
    min_threshold_px : float
        Corners below this error are never pruned.
    """
    distortions = np.asarray(distortions, dtype=np.float64)
    n_dist = distortions.shape[1]
    views = np.flatnonzero(np.isfinite(board2world[:, 0, 0]))
    seen = np.isfinite(corners[..., 0])
    inliers = seen.copy()
    params = None
    rounds = 0
    for rounds in range(1, prune_rounds + 2):
        problem = _Problem(board, corners, inliers, views, n_dist, fisheye)
        if params is None:
            params = problem.pack(matrices, distortions, world2cam, board2world)
        # Solve in preconditioned coordinates x = x0 + P y, P block-diagonal (one block per camera and per
        # board pose, whitening that block's Jacobian columns): P keeps the sparsity pattern and makes LSMR's
        # inner solves converge in far fewer iterations than a diagonal x_scale.
        origin, precondition = params, problem.preconditioner(params)

        def residuals(y, origin=origin, precondition=precondition, problem=problem):
            return problem.residuals(origin + precondition @ y)

        solution = least_squares(residuals, np.zeros_like(params), jac_sparsity=problem.sparsity(), method="trf",
                                 tr_solver="lsmr", x_scale=1.0, loss="soft_l1", f_scale=f_scale_px,
                                 ftol=1e-10, xtol=1e-10, gtol=1e-10, max_nfev=max_nfev,
                                 tr_options={"atol": 1e-10, "btol": 1e-10})
        params = origin + precondition @ solution.x
        matrices, distortions, world2cam, board2world = _unpack_all(problem, params, corners.shape[1])
        errors = _errors(board, corners, matrices, distortions, world2cam, board2world, fisheye)
        current = errors[inliers & np.isfinite(errors)]
        sigma = np.median(current) / 1.1774 if current.size else 0.0  # Rayleigh median -> per-axis sigma
        threshold = max(min_threshold_px, 5 * sigma)
        # a detection whose corners are mostly wrong (a grid matched one square off, a misread marker set)
        # is dropped as a whole: pruning its corners one by one would leave its worst-fitting remains
        bad_detection = (inliers & (errors > threshold)).sum(axis=2) > 0.5 * inliers.sum(axis=2)
        new_inliers = inliers & (errors <= threshold) & ~bad_detection[..., None]
        if rounds > prune_rounds or (new_inliers == inliers).all():
            break
        inliers = new_inliers
    return BundleResult(matrices, distortions, world2cam, board2world, errors, inliers & np.isfinite(errors), rounds)


def _unpack_all(problem: _Problem, params: np.ndarray, n_views: int):
    extr, intr, boards = problem.unpack(params)
    n_cams = problem.n_cams
    matrices = np.tile(np.eye(3), (n_cams, 1, 1))
    matrices[:, 0, 0], matrices[:, 1, 1], matrices[:, 0, 2], matrices[:, 1, 2] = intr[:, :4].T
    world2cam = np.tile(np.eye(4), (n_cams, 1, 1))
    world2cam[:, :3, :3] = rotation_matrices(extr[:, :3])
    world2cam[:, :3, 3] = -np.einsum("cij,cj->ci", world2cam[:, :3, :3], extr[:, 3:])
    board2world = np.full((n_views, 4, 4), np.nan)
    board2world[problem.views] = np.eye(4)
    board2world[problem.views, :3, :3] = rotation_matrices(boards[:, :3])
    board2world[problem.views, :3, 3] = boards[:, 3:] - board2world[problem.views, :3, :3] @ problem.middle
    return matrices, intr[:, 4:].copy(), world2cam, board2world


def _errors(board, corners, matrices, distortions, world2cam, board2world, fisheye) -> np.ndarray:
    """Reprojection error of every detection, (n_cams, n_views, n_corners); NaN where undetected or no pose."""
    n_cams, n_views, n_corners, _ = corners.shape
    world = np.einsum("vij,nj->vni", board2world[:, :3, :3], board.object_points) + board2world[:, None, :3, 3]
    errors = np.full((n_cams, n_views, n_corners), np.nan)
    for c in range(n_cams):
        in_cam = apply(world2cam[c], world)
        normalised = in_cam[..., :2] / in_cam[..., 2:3]
        flat = normalised.reshape(-1, 2)
        k = matrices[c]
        intr = np.tile([k[0, 0], k[1, 1], k[0, 2], k[1, 2]], (len(flat), 1))
        pixels = distort(flat, intr, np.tile(distortions[c], (len(flat), 1)), fisheye).reshape(n_views, n_corners, 2)
        errors[c] = np.linalg.norm(pixels - corners[c], axis=-1)
    return errors
