"""Synthetic calibration scenes shared by the calibration tests."""

from __future__ import annotations

import re

import numpy as np

from livebridge.calibration.boards import parse_board
from livebridge.calibration.calibfile import load_calibration, load_metadata
from livebridge.calibration.detect import Detections
from livebridge.calibration.run import world_transform
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


def assert_calibration_matches(path, rig, poses) -> tuple:
    """The calibration file at ``path`` against the rendered rig's truth, in the file's world (its origin view's
    board, upright): focal 0.5%, principal point 2 px, centres 1 mm, RMS 0.3 px. Returns (group, metadata)."""
    group, metadata = load_calibration(path), load_metadata(path)
    origin = int(re.findall(r"\d+", metadata["origin_view"])[-1])
    old2new = world_transform(poses[origin], "y", "upright")
    for camera, truth in zip(group.cameras, rig.cameras):
        assert camera.size == truth.size
        focal, true_focal = camera.matrix[[0, 1], [0, 1]], truth.matrix[[0, 1], [0, 1]]
        assert np.all(np.abs(focal / true_focal - 1) < 0.005), (camera.name, focal, true_focal)
        assert np.all(np.abs(camera.matrix[:2, 2] - truth.matrix[:2, 2]) < 2.0)
        expected_centre = (old2new @ np.r_[truth.center, 1])[:3]
        assert np.linalg.norm(camera.center - expected_centre) < 1.0, (camera.name, camera.center, expected_centre)
        assert metadata["rms_px"][camera.name] <= 0.3
    return group, metadata
