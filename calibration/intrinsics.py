"""Per-camera intrinsics (full pinhole or fisheye) and per-view board poses."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from livebridge.calibration.boards import Board
from livebridge.calibration.cameras import undistort_normalised
from livebridge.errors import InputError

MIN_VIEWS = 3


@dataclass(frozen=True, eq=False)
class Intrinsics:
    """Initial lens model of one camera.

    Attributes
    ----------
    matrix : ndarray, shape (3, 3)
    distortions : ndarray, shape (5,) pinhole ``(k1, k2, p1, p2, k3)`` or (4,) fisheye ``(k1..k4)``
    fisheye : bool
    rms_px : float
        OpenCV's RMS reprojection error over the views used.
    views : ndarray of int
        Indices of the views used.
    """

    matrix: np.ndarray
    distortions: np.ndarray
    fisheye: bool
    rms_px: float
    views: np.ndarray


def usable_views(board: Board, corners: np.ndarray) -> np.ndarray:
    """Indices of views with enough corners, shape (n_usable,); ``corners`` (n_views, n_corners, 2)."""
    counts = np.isfinite(corners[..., 0]).sum(axis=1)
    return np.flatnonzero(counts >= board.min_corners)


def calibrate_intrinsics(board: Board, corners: np.ndarray, size: tuple[int, int], fisheye: bool = False,
                         name: str = "", max_views: int = 40) -> Intrinsics:
    """Calibrate one camera's lens from its board views.

    Parameters
    ----------
    board : Board
    corners : ndarray, shape (n_views, n_corners, 2)
        NaN where unseen.
    size : (int, int)
        Image ``(width, height)``.
    fisheye : bool
        Fisheye model (``cv2.fisheye``) instead of the 5-term pinhole model.
    name : str
        Camera name, for error messages.
    max_views : int
        At most this many views, evenly spread over the usable ones (deterministic), for speed;
        bundle adjustment later uses every view.
    """
    views = usable_views(board, corners)
    if len(views) < MIN_VIEWS:
        raise InputError(f"the board was found in only {len(views)} views; at least {MIN_VIEWS} are needed "
                         "(more, at varied angles, give a better lens model)", field=f"camera {name}")
    if len(views) > max_views:
        views = views[np.unique(np.round(np.linspace(0, len(views) - 1, max_views)).astype(int))]
    objects, images = [], []
    for v in views:
        seen = np.isfinite(corners[v, :, 0])
        objects.append(board.object_points[seen].astype(np.float32).reshape(-1, 1, 3))
        images.append(corners[v, seen].astype(np.float32).reshape(-1, 1, 2))
    width, height = size
    guess = cv2.initCameraMatrix2D(objects, images, (width, height))
    try:
        if fisheye:
            flags = _fisheye_flag("CALIB_RECOMPUTE_EXTRINSIC") | _fisheye_flag("CALIB_FIX_SKEW") \
                | _fisheye_flag("CALIB_USE_INTRINSIC_GUESS")
            criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-10)
            rms, matrix, distortions, _, _ = cv2.fisheye.calibrate(
                [o.reshape(1, -1, 3).astype(np.float64) for o in objects],  # fisheye wants 1xN, float64
                [i.reshape(1, -1, 2).astype(np.float64) for i in images], (width, height),
                guess.astype(np.float64), np.zeros((4, 1)), flags=flags, criteria=criteria)
        else:
            criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
            rms, matrix, distortions, _, _ = cv2.calibrateCamera(objects, images, (width, height), guess.copy(),
                                                                 np.zeros(5), flags=cv2.CALIB_USE_INTRINSIC_GUESS,
                                                                 criteria=criteria)
    except cv2.error as error:
        raise InputError(f"OpenCV could not calibrate this camera's lens ({str(error).strip().splitlines()[-1]}); "
                         "check the board spec and that the views are not all nearly parallel to the image",
                         field=f"camera {name}") from None
    return Intrinsics(np.asarray(matrix, np.float64), np.asarray(distortions, np.float64).ravel(), fisheye,
                      float(rms), views)


def _fisheye_flag(name: str) -> int:
    """``cv2.fisheye.NAME`` (OpenCV 4) or ``cv2.NAME`` (OpenCV 5 moved the fisheye flags)."""
    return int(getattr(cv2.fisheye, name, None) or getattr(cv2, name))


def board_poses(board: Board, corners: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """Pose of the board in the camera for every usable view.

    Parameters
    ----------
    corners : ndarray, shape (n_views, n_corners, 2)

    Returns
    -------
    board2cam : ndarray, shape (n_views, 4, 4); NaN for views without enough corners.
    """
    board2cam = np.full((len(corners), 4, 4), np.nan)
    for v in usable_views(board, corners):
        seen = np.isfinite(corners[v, :, 0])
        normalised = undistort_normalised(corners[v, seen], intrinsics.matrix, intrinsics.distortions,
                                          intrinsics.fisheye)
        transform = solve_planar_pose(board.object_points[seen], normalised)
        if transform is not None:
            board2cam[v] = transform
    return board2cam


def solve_planar_pose(object_points: np.ndarray, normalised: np.ndarray) -> np.ndarray | None:
    """``board2cam`` (4, 4) from board points (n, 3) with z = 0 and undistorted normalised image points (n, 2)."""
    objects = object_points.reshape(-1, 1, 3).astype(np.float64)
    images = normalised.reshape(-1, 1, 2).astype(np.float64)
    eye = np.eye(3)
    ok, rvec, tvec = cv2.solvePnP(objects, images, eye, None, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(objects, images, eye, None, rvec, tvec)
    transform = np.eye(4)
    transform[:3, :3] = cv2.Rodrigues(rvec)[0]
    transform[:3, 3] = tvec.ravel()
    return transform if np.isfinite(transform).all() and transform[2, 3] > 0 else None
