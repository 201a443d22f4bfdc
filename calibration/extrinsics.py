"""Initial camera poses from a pose graph over the board views cameras share.

Cameras are nodes; two cameras are joined by an edge weighted by the number of
views in which both saw the board. A maximum spanning tree (Kruskal, ties broken
by camera index, so the result is deterministic) picks the best-supported
relative poses; each edge's relative pose is a robust average over its shared
views. A graph that falls apart raises :class:`InputError` naming the groups.
"""

from __future__ import annotations

import numpy as np

from livebridge.errors import InputError


def shared_view_counts(board2cam: np.ndarray) -> np.ndarray:
    """Views with a board pose in both cameras, int (n_cams, n_cams); ``board2cam`` (n_cams, n_views, 4, 4)."""
    seen = np.isfinite(board2cam[:, :, 0, 0]).astype(int)
    return seen @ seen.T


def spanning_tree(weights: np.ndarray, names: tuple[str, ...]) -> list[tuple[int, int]]:
    """Maximum spanning tree edges ``(a, b)`` in the order they were added.

    Raises
    ------
    InputError
        When the cameras fall into groups that share no board view.
    """
    n = len(weights)
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    edges = sorted((-int(weights[a, b]), a, b) for a in range(n) for b in range(a + 1, n) if weights[a, b] > 0)
    tree = []
    for _, a, b in edges:
        ra, rb = root(a), root(b)
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
            tree.append((a, b))
    groups: dict[int, list[str]] = {}
    for i in range(n):
        groups.setdefault(root(i), []).append(names[i])
    if len(groups) > 1:
        listed = "; ".join("[" + ", ".join(g) + "]" for g in groups.values())
        raise InputError(f"the cameras fall into {len(groups)} groups that share no board view: {listed}. "
                         "Record views in which a camera of each group sees the board at the same time as a "
                         "camera of another group", field="cameras")
    return tree


def average_transform(transforms: np.ndarray) -> np.ndarray:
    """Robust mean of rigid transforms (n, 4, 4): chordal rotation mean and median translation, outliers dropped."""
    rotations, translations = transforms[:, :3, :3], transforms[:, :3, 3]
    keep = np.ones(len(transforms), bool)
    for _ in range(2):
        mean = _project_rotation(rotations[keep].mean(axis=0))
        angles = _angle(np.einsum("ij,nkj->nik", mean, rotations))
        centre = np.median(translations[keep], axis=0)
        distance = np.linalg.norm(translations - centre, axis=1)
        angle_limit = max(3 * np.median(angles[keep]), np.radians(2.0))
        distance_limit = max(3 * np.median(distance[keep]), 1e-9)
        new_keep = (angles <= angle_limit) & (distance <= distance_limit)
        if new_keep.sum() < max(1, keep.sum() // 2):
            break
        keep = new_keep
    out = np.eye(4)
    out[:3, :3] = _project_rotation(rotations[keep].mean(axis=0))
    out[:3, 3] = np.median(translations[keep], axis=0)
    return out


def initial_extrinsics(board2cam: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    """``world2cam`` of every camera, with the world at camera 0.

    Parameters
    ----------
    board2cam : ndarray, shape (n_cams, n_views, 4, 4)
        Per-camera board poses, NaN where the camera has none.
    names : tuple of str

    Returns
    -------
    world2cam : ndarray, shape (n_cams, 4, 4)
    """
    n_cams = len(names)
    tree = spanning_tree(shared_view_counts(board2cam), names)
    seen = np.isfinite(board2cam[:, :, 0, 0])
    world2cam = np.full((n_cams, 4, 4), np.nan)
    world2cam[0] = np.eye(4)
    adjacency: dict[int, list[int]] = {i: [] for i in range(n_cams)}
    for a, b in tree:
        adjacency[a].append(b)
        adjacency[b].append(a)
    queue = [0]
    while queue:
        a = queue.pop(0)
        for b in sorted(adjacency[a]):
            if np.isfinite(world2cam[b, 0, 0]):
                continue
            shared = np.flatnonzero(seen[a] & seen[b])
            a2b = np.stack([board2cam[b, v] @ np.linalg.inv(board2cam[a, v]) for v in shared])
            world2cam[b] = average_transform(a2b) @ world2cam[a]
            queue.append(b)
    return world2cam


def initial_board_poses(board2cam: np.ndarray, world2cam: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """``board2world`` per view from the camera that saw the most corners, NaN for views nobody posed.

    Parameters
    ----------
    board2cam : ndarray, shape (n_cams, n_views, 4, 4)
    world2cam : ndarray, shape (n_cams, 4, 4)
    counts : ndarray, shape (n_cams, n_views)
        Corners seen.
    """
    n_views = board2cam.shape[1]
    board2world = np.full((n_views, 4, 4), np.nan)
    posed = np.isfinite(board2cam[:, :, 0, 0])
    for v in range(n_views):
        candidates = np.flatnonzero(posed[:, v])
        if len(candidates) == 0:
            continue
        best = candidates[np.argmax(counts[candidates, v])]  # argmax: first of equals
        board2world[v] = np.linalg.inv(world2cam[best]) @ board2cam[best, v]
    return board2world


def _project_rotation(matrix: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(matrix)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def _angle(rotations: np.ndarray) -> np.ndarray:
    cos = (np.trace(rotations, axis1=-2, axis2=-1) - 1) / 2
    return np.arccos(np.clip(cos, -1.0, 1.0))
