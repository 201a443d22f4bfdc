"""Synthetic calibration scenes shared by the calibration tests."""

from __future__ import annotations

import numpy as np

from livebridge.calibration.boards import parse_board
from livebridge.calibration.detect import Detections
from livebridge.simulators.board_render import example_board_poses, example_rig, project_board

BOARD = "charuco:8x6:60:45:DICT_4X4_50"


def synthetic_detections(n_cams=4, n_views=40, noise_px=0.1, seed=0, fisheye=False, board=BOARD):
    """(board, true CameraGroup, true board2world (n_views, 4, 4), Detections) from projected corners."""
    board = parse_board(board)
    group = example_rig(n_cams, fisheye=fisheye, seed=seed)
    poses = example_board_poses(board, n_views, seed=seed + 1)
    corners = project_board(board, group, poses, noise_px, np.random.default_rng(seed + 2))
    detections = Detections(group.names, tuple(c.size for c in group.cameras), corners,
                            tuple(f"{v:03d}" for v in range(n_views)))
    return board, group, poses, detections


def centres_in_cam0(group) -> np.ndarray:
    """Camera centres in camera 0's frame (frame-independent comparison), shape (n_cams, 3)."""
    world2cam0 = group.cameras[0].world2cam
    return np.array([(world2cam0 @ np.r_[camera.center, 1.0])[:3] for camera in group.cameras])
