"""The calibration pipeline: detections -> intrinsics -> pose graph -> bundle adjustment -> world frame.

World frame
-----------
Origin at corner 0 of the board (the first inner corner of a chessboard, the
corner with id 0 of a ChArUco board) in the origin view. With the board held
``upright`` (the default; printed top edge up, printed side facing the
cameras): +x along the board's rows (left to right as printed), ``--up y``
makes +y up and +z out of the board towards the cameras (the face model's
convention); ``--up z`` makes +z up and +y into the board. With the board
lying ``flat`` (printed side up): up is the board's front normal, +x along
its rows. The frame is always right-handed.

On a chessboard that looks the same turned (square, or COLS + ROWS even), corner 0
is the one :mod:`livebridge.calibration.orientation` chooses: the same physical
corner for every camera in a view, and in each view the one that puts the board's
+y most nearly down in the images (its printed order when held within 45 deg of upright).
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from livebridge.calibration.boards import Board
from livebridge.calibration.bundle import BundleResult, bundle_adjust
from livebridge.calibration.cameras import Camera, CameraGroup
from livebridge.calibration.detect import Detections
from livebridge.calibration.extrinsics import initial_board_poses, initial_extrinsics
from livebridge.calibration.intrinsics import board_poses, calibrate_intrinsics
from livebridge.calibration.orientation import resolve_orientation
from livebridge.calibration.threads import single_threaded
from livebridge.errors import InputError
from livebridge.geometry.transforms import rotation_vector


@dataclass(frozen=True, eq=False)
class Calibration:
    """Result of a calibration run.

    Attributes
    ----------
    group : CameraGroup
        Cameras in the final world frame (mm).
    board : Board
    detections : Detections
        As given, with the corners of a symmetric chessboard in the order calibration chose
        (:mod:`livebridge.calibration.orientation`).
    board2world : ndarray, shape (n_views, 4, 4); NaN for views not used
    errors : ndarray, shape (n_cams, n_views, n_corners)
        Final reprojection error (px) of every detected corner.
    inliers : ndarray, bool, shape (n_cams, n_views, n_corners)
    origin_view : int
    up : str
    board_pose : str
    initial_rms_px : ndarray, shape (n_cams,)
        OpenCV's per-camera intrinsic calibration RMS, before bundle adjustment.
    """

    group: CameraGroup
    board: Board
    detections: Detections
    board2world: np.ndarray
    errors: np.ndarray
    inliers: np.ndarray
    origin_view: int
    up: str
    board_pose: str
    initial_rms_px: np.ndarray

    def rms_px(self, inliers_only: bool = True) -> np.ndarray:
        """RMS reprojection error per camera, shape (n_cams,)."""
        errors = np.where(self.inliers, self.errors, np.nan) if inliers_only else self.errors
        flat = errors.reshape(len(errors), -1)
        count = np.isfinite(flat).sum(axis=1)
        return np.sqrt(np.nansum(flat ** 2, axis=1) / np.maximum(count, 1)) + np.where(count, 0.0, np.nan)

    def views_used(self) -> np.ndarray:
        """Views with inlier corners per camera, int (n_cams,)."""
        return self.inliers.any(axis=2).sum(axis=1)

    def metadata(self, date: str | None = None) -> dict:
        """The metadata table of ``calibration.toml``."""
        from livebridge import __version__

        names = self.group.names
        rms, rms_all = self.rms_px(), self.rms_px(inliers_only=False)
        return {
            "board": self.board.spec,
            "date": date or calibration_date(),
            "livebridge_version": __version__,
            "fisheye": bool(self.group.cameras[0].fisheye),
            "world_frame": world_frame_description(self.up, self.board_pose),
            "up": self.up,
            "board_pose": self.board_pose,
            "origin_view": self.detections.view_names[self.origin_view],
            "units": "mm",
            "rms_px": {n: float(v) for n, v in zip(names, rms)},
            "rms_all_px": {n: float(v) for n, v in zip(names, rms_all)},
            "views_used": {n: int(v) for n, v in zip(names, self.views_used())},
            "outliers": {n: int(v) for n, v in zip(names, (np.isfinite(self.errors) & ~self.inliers)
                                                    .reshape(len(names), -1).sum(axis=1))},
        }


def calibration_date() -> str:
    """Today's date (UTC), or the date of ``SOURCE_DATE_EPOCH`` when set (reproducible files)."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    seconds = int(epoch) if epoch and epoch.isdigit() else time.time()
    return time.strftime("%Y-%m-%d", time.gmtime(seconds))


def world_frame_description(up: str, board_pose: str) -> str:
    origin = "origin at board corner 0 in the origin view; "
    if board_pose == "upright":
        axes = ("+x along the board rows, +y up, +z out of the board towards the cameras" if up == "y" else
                "+x along the board rows, +z up, +y into the board (away from the cameras)")
    else:
        axes = ("+x along the board rows, +y up (board front normal), +z = x cross y" if up == "y" else
                "+x along the board rows, +z up (board front normal), +y = z cross x")
    return origin + axes + "; right-handed, mm"


def calibrate(detections: Detections, board: Board, fisheye: bool = False, up: str = "y",
              origin_view: int | None = None, board_pose: str = "upright",
              log: Callable[[str], None] = lambda _: None) -> Calibration:
    """Calibrate all cameras from their board detections.

    Parameters
    ----------
    detections : Detections
    board : Board
    fisheye : bool
        Fisheye lens model instead of the 5-term pinhole model.
    up : {'y', 'z'}
        World axis that points up.
    origin_view : int, optional
        View that defines the world frame; default: the view seen by the most cameras (then most corners,
        then earliest).
    board_pose : {'upright', 'flat'}
        How the board stands in the origin view (see the module docstring).
    log : callable
        Progress messages.

    Raises
    ------
    InputError
        Too few views, cameras that share no view, a camera that sees the board from behind
        (mirrored images), a bad origin view.
    """
    with single_threaded():  # bit-for-bit repeatable, and no thread thrash (see calibration.threads)
        return _calibrate(detections, board, fisheye, up, origin_view, board_pose, log)


def _calibrate(detections, board, fisheye, up, origin_view, board_pose, log) -> Calibration:
    if up not in ("y", "z"):
        raise InputError(f"--up must be 'y' or 'z', got {up!r}", field="--up")
    if board_pose not in ("upright", "flat"):
        raise InputError(f"board pose must be 'upright' or 'flat', got {board_pose!r}", field="--board-pose")
    names = detections.camera_names
    corners = detections.corners.copy()
    intrinsics = []
    for c, name in enumerate(names):
        intrinsics.append(calibrate_intrinsics(board, corners[c], detections.sizes[c], fisheye, name))
        log(f"{name}: lens from {len(intrinsics[-1].views)} views, RMS {intrinsics[-1].rms_px:.3f} px")
    board2cam = np.stack([board_poses(board, corners[c], intrinsics[c]) for c in range(len(names))])
    _check_front_side(board2cam, names, corners, log)
    counts = np.isfinite(corners[..., 0]).sum(axis=2)
    orientation = resolve_orientation(board, board2cam)
    if orientation.turns.any():
        log(f"board corner order: turned {int((orientation.turns != 0).sum())} detections of the symmetric "
            "board to agree across cameras and views")
    corners, board2cam = orientation.relabel(board, corners), orientation.turn_poses(board, board2cam)
    detections = dataclasses.replace(detections, corners=orientation.relabel(board, detections.corners))
    world2cam = initial_extrinsics(board2cam, names)
    board2world = initial_board_poses(board2cam, world2cam, counts)
    result = bundle_adjust(board, corners, np.stack([i.matrix for i in intrinsics]),
                           np.stack([i.distortions for i in intrinsics]), world2cam, board2world, fisheye)
    log("bundle adjustment: RMS " + ", ".join(f"{n} {r:.3f} px" for n, r in zip(names, result.rms_px())))
    final_board2cam = np.einsum("cij,vjk->cvik", result.world2cam, result.board2world)
    final_board2cam[~result.inliers.any(axis=2)] = np.nan
    _check_front_side(final_board2cam, names, None, log)
    origin = _origin_view(result, origin_view, detections)
    old2new = world_transform(result.board2world[origin], up, board_pose)
    cameras = []
    for c, name in enumerate(names):
        world2cam_new = result.world2cam[c] @ np.linalg.inv(old2new)
        cameras.append(Camera(name, detections.sizes[c], result.matrices[c], result.distortions[c],
                              rotation_vector(world2cam_new[:3, :3]), world2cam_new[:3, 3], fisheye))
    board2world_new = np.einsum("ij,vjk->vik", old2new, result.board2world)
    check_right_handed(cameras, board2world_new[origin], up, board_pose)
    return Calibration(CameraGroup(cameras), board, detections, board2world_new, result.errors, result.inliers,
                       origin, up, board_pose, np.array([i.rms_px for i in intrinsics]))


def world_axes(up: str, board_pose: str) -> np.ndarray:
    """World axes as columns in board coordinates, (3, 3), a proper rotation."""
    bx, by, bz = np.eye(3)
    if board_pose == "upright":
        up_axis, x = -by, bx
    else:
        up_axis, x = -bz, bx
    if up == "y":
        y, z = up_axis, np.cross(x, up_axis)
    else:
        z, y = up_axis, np.cross(up_axis, x)
    return np.stack([x, y, z], axis=1)


def world_transform(board2old: np.ndarray, up: str, board_pose: str) -> np.ndarray:
    """``old2new`` (4, 4): the new world frame sits at the board with the stated axes."""
    axes = world_axes(up, board_pose)
    board2new = np.eye(4)
    board2new[:3, :3] = axes.T
    return board2new @ np.linalg.inv(board2old)


def check_right_handed(cameras: list[Camera], board2world: np.ndarray, up: str, board_pose: str) -> None:
    """Raise if the world frame or any camera rotation is mirrored, or the board is not where the frame says."""
    axes = world_axes(up, board_pose)
    if not np.isclose(np.linalg.det(axes), 1.0):
        raise RuntimeError("internal error: world axes are not right-handed")
    for camera in cameras:
        rotation = camera.world2cam[:3, :3]
        if not np.isclose(np.linalg.det(rotation), 1.0, atol=1e-6):
            raise InputError("rotation is not a proper rotation (mirrored frame)", field=f"camera {camera.name}")
    if not np.allclose(board2world[:3, :3], axes.T, atol=1e-6):
        raise RuntimeError("internal error: the origin board does not match the stated world axes")


def _check_front_side(board2cam: np.ndarray, names, corners: np.ndarray | None, log) -> None:
    """Every camera must see the printed side of the board; views seen from behind are dropped or reported."""
    posed = np.isfinite(board2cam[:, :, 0, 0])
    # camera on the printed side <=> the board's +z (into the paper) points away from the camera
    facing = np.einsum("cvi,cvi->cv", board2cam[:, :, :3, 2], board2cam[:, :, :3, 3]) > 0
    for c, name in enumerate(names):
        n_posed, n_back = int(posed[c].sum()), int((posed[c] & ~facing[c]).sum())
        if n_posed and n_back > n_posed / 2:
            raise InputError(f"sees the board from behind in {n_back} of {n_posed} views: its images are probably "
                             "mirrored (a webcam 'mirror' setting, or a flipped video); turn mirroring off and "
                             "calibrate again", field=f"camera {name}")
        if n_back and corners is not None:
            log(f"{name}: dropped {n_back} views whose detection is mirrored")
            back = posed[c] & ~facing[c]
            corners[c, back] = np.nan
            board2cam[c, back] = np.nan


def _origin_view(result: BundleResult, origin_view: int | None, detections: Detections) -> int:
    used = result.inliers.sum(axis=2)
    if origin_view is not None:
        if not 0 <= origin_view < detections.n_views:
            raise InputError(f"view {origin_view} does not exist (0..{detections.n_views - 1})",
                             field="--origin-view")
        if not np.isfinite(result.board2world[origin_view, 0, 0]):
            raise InputError(f"the board was not found in view {origin_view} "
                             f"({detections.view_names[origin_view]})", field="--origin-view")
        return int(origin_view)
    n_cams_seen = (used > 0).sum(axis=0)
    order = np.lexsort((np.arange(detections.n_views), -used.sum(axis=0), -n_cams_seen))
    return int(order[0])
