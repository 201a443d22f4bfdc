"""Corner order of symmetric chessboards, made consistent across views and cameras.

A chessboard whose printed pattern looks the same after a turn about its centre
(a half turn when COLS + ROWS is even, quarter turns too on some square boards:
see :attr:`Board.grid_rotations`) gives each detection one of several corner
labellings. A camera's lens model does not depend on the labelling, but the
board pose does (it turns with it), so the labellings must agree before the
pose graph is built:

1. Between cameras: cameras are taken in turn, starting with the one that posed
   the board most often; each next camera is the one sharing most views with the
   cameras already placed. Every shared view and every labelling of it proposes
   a pose of the new camera; the proposal most views agree with (rotation and
   position) wins, and each view takes the labelling closest to it.
2. Per view (the same turn for every camera, which no image can tell apart):
   the turn whose board +y (down its columns as printed) points most nearly down
   the images of the cameras that see the view. A board held within 45 deg of
   upright (the usual way) so gets its printed order in every view, and the
   board axes do not jump between views.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from livebridge.calibration.boards import Board
from livebridge.calibration.extrinsics import average_transform

AGREE_DEG = 20.0
"""Proposals within this angle (and the position tolerance) agree; look-alike labellings differ by >= 90 deg."""
AGREE_DISTANCE = 0.1
"""Position tolerance as a fraction of the median camera-to-board distance."""
MAX_SEED_VIEWS = 60
"""Views whose proposals are tried as the consensus (see :func:`_consensus`)."""


@dataclass(frozen=True, eq=False)
class Orientation:
    """The labelling chosen for every detection.

    Attributes
    ----------
    turns : ndarray of int, shape (n_cams, n_views)
        Quarter turns (0..3) applied to each detection's corner order; 0 where nothing was posed.
    """

    turns: np.ndarray

    def relabel(self, board: Board, corners: np.ndarray) -> np.ndarray:
        """``corners`` (n_cams, n_views, n_corners, 2) in the chosen order (a copy)."""
        by_turn = {r.quarter_turns: r for r in board.grid_rotations}
        corners = corners.copy()
        for c, v in zip(*np.nonzero(self.turns)):
            corners[c, v] = corners[c, v, by_turn[int(self.turns[c, v])].order]
        return corners

    def turn_poses(self, board: Board, board2cam: np.ndarray) -> np.ndarray:
        """Board poses (n_cams, n_views, 4, 4) of the detections as relabelled (a copy)."""
        by_turn = {r.quarter_turns: r for r in board.grid_rotations}
        board2cam = board2cam.copy()
        for c, v in zip(*np.nonzero(self.turns)):
            board2cam[c, v] = board2cam[c, v] @ by_turn[int(self.turns[c, v])].board_transform
        return board2cam


def resolve_orientation(board: Board, board2cam: np.ndarray) -> Orientation:
    """Choose the corner labelling of every detection of a symmetric chessboard.

    Parameters
    ----------
    board : Board
    board2cam : ndarray, shape (n_cams, n_views, 4, 4)
        Board poses of the detections as labelled, NaN where not posed.

    Returns
    -------
    Orientation; all zero turns for a board without look-alike turns.
    """
    turns = np.zeros(board2cam.shape[:2], int)
    options = {r.quarter_turns: r.board_transform for r in board.grid_rotations if r.keeps_colours}
    if len(options) == 1:
        return Orientation(turns)
    posed = np.isfinite(board2cam[:, :, 0, 0])
    distances = np.linalg.norm(board2cam[..., :3, 3][posed], axis=1)
    tolerance = AGREE_DISTANCE * (float(np.median(distances)) if distances.size else 1.0)
    world2cam = _place_cameras(board2cam, posed, options, turns, tolerance)
    _choose_view_turns(board2cam, posed, options, turns, world2cam)
    return Orientation(turns)


def _place_cameras(board2cam, posed, options, turns, tolerance) -> np.ndarray:
    """Fill ``turns`` camera by camera (relative labellings); returns ``world2cam`` (n_cams, 4, 4), NaN if unplaced."""
    n_cams = len(posed)
    world2cam = np.full((n_cams, 4, 4), np.nan)
    first = int(np.argmax(posed.sum(axis=1)))
    world2cam[first] = np.eye(4)
    placed = {first}
    while len(placed) < n_cams:
        seen_by_placed = posed[sorted(placed)].any(axis=0)
        shared = {b: int((posed[b] & seen_by_placed).sum()) for b in range(n_cams) if b not in placed}
        camera = max(shared, key=lambda b: (shared[b], -b))
        if shared[camera] == 0:
            break  # the rest share no view: the pose graph reports it
        proposals = _proposals(camera, placed, board2cam, posed, options, turns, world2cam)
        world2cam[camera] = _consensus(proposals, tolerance)
        for v in np.flatnonzero(posed[camera] & seen_by_placed):
            mine = [(turn, pose) for view, turn, pose in proposals if view == v]
            turns[camera, v] = min(mine, key=lambda item: _distance(item[1], world2cam[camera], tolerance))[0]
        placed.add(camera)
    return world2cam


def _proposals(camera, placed, board2cam, posed, options, turns, world2cam) -> list[tuple[int, int, np.ndarray]]:
    """``(view, turn, world2cam of camera)`` from every view shared with a placed camera, every labelling."""
    out = []
    for other in sorted(placed):
        for v in np.flatnonzero(posed[camera] & posed[other]):
            other_board2cam = board2cam[other, v] @ options[int(turns[other, v])]
            board2world = np.linalg.inv(world2cam[other]) @ other_board2cam
            for turn, transform in options.items():
                out.append((int(v), turn, board2cam[camera, v] @ transform @ np.linalg.inv(board2world)))
    return out


def _consensus(proposals, tolerance) -> np.ndarray:
    """The pose most views agree with: the proposal supported by most distinct views, averaged with its supporters.

    Candidates come from at most :data:`MAX_SEED_VIEWS` views spread over the shared ones (memory stays
    bounded for long videos); support is counted over every proposal.
    """
    poses = np.stack([pose for _, _, pose in proposals])
    views = np.array([view for view, _, _ in proposals])
    distinct = np.unique(views)
    seed_views = distinct[np.unique(np.linspace(0, len(distinct) - 1, min(len(distinct), MAX_SEED_VIEWS))
                                    .round().astype(int))]
    seeds = np.flatnonzero(np.isin(views, seed_views))
    distance = _distances(poses[seeds], poses, tolerance)
    agree = distance <= 1.0
    support = np.array([len(np.unique(views[row])) for row in agree])
    spread = np.where(agree, distance, 0.0).sum(axis=1)
    best = int(np.lexsort((spread, -support))[0])
    return average_transform(poses[agree[best]])


def _distance(a: np.ndarray, b: np.ndarray, tolerance: float) -> float:
    """Pose difference of two (4, 4) transforms in units of the agreement tolerance (<= 1 agrees)."""
    return float(_distances(a[None], b[None], tolerance)[0, 0])


def _distances(a: np.ndarray, b: np.ndarray, tolerance: float) -> np.ndarray:
    """Pairwise pose differences (n_a, n_b) of transforms (n_a, 4, 4) and (n_b, 4, 4): the larger of the angle
    (in units of :data:`AGREE_DEG`) and the position difference (in units of ``tolerance``)."""
    cos = (np.einsum("aij,bij->ab", a[:, :3, :3], b[:, :3, :3]) - 1) / 2
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    position = np.linalg.norm(a[:, None, :3, 3] - b[None, :, :3, 3], axis=2)
    return np.maximum(angle / AGREE_DEG, position / tolerance)


def _choose_view_turns(board2cam, posed, options, turns, world2cam) -> None:
    """Add one turn per view (the same for every camera): the one whose board +y points most nearly down the
    images of the cameras that see the view (right for a board held within 45 deg of upright)."""
    for v in range(posed.shape[1]):
        cameras = [c for c in np.flatnonzero(posed[:, v]) if np.isfinite(world2cam[c, 0, 0])]
        if not cameras:
            continue
        c = cameras[0]
        rotation = (np.linalg.inv(world2cam[c]) @ board2cam[c, v] @ options[int(turns[c, v])])[:3, :3]
        down = sum(np.linalg.inv(world2cam[k])[:3, 1] for k in cameras)  # image down of each camera, in the world
        turn = max(options, key=lambda t: (rotation @ options[t][:3, :3])[:, 1] @ down)
        turns[:, v] = np.where(posed[:, v], (turns[:, v] + turn) % 4, 0)
