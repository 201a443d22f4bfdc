"""Numpy references for the compiled geometry kernels (tests/test_geometry.py, tests/test_rig.py)."""

from __future__ import annotations

import numpy as np


def behind_surface_numpy(surface, points, cosine, cell_mm):
    """The depth splat of :func:`livebridge.geometry.visibility.behind_surface` written with numpy (the marker-layout
    designer's former implementation), shape (n,) bool.

    Parameters
    ----------
    surface : ndarray, shape (n_vertices, 3)
    points : ndarray, shape (n, 3)
        Camera frame, in front of the camera.
    cosine : ndarray, shape (n,)
    cell_mm : float
    """
    surface = surface[surface[:, 2] > 1.0]
    face_depth = float(np.median(surface[:, 2]))
    cell = cell_mm / face_depth
    site_cells = np.floor(points[:, :2] / points[:, 2:] / cell).astype(np.int64)
    surface_cells = np.floor(surface[:, :2] / surface[:, 2:] / cell).astype(np.int64)
    low, high = site_cells.min(axis=0), site_cells.max(axis=0)
    inside = ((surface_cells >= low) & (surface_cells <= high)).all(axis=1)
    nearest = np.full(tuple(high - low + 1), np.inf)
    np.minimum.at(nearest, tuple((surface_cells[inside] - low).T), surface[inside, 2])
    facing = np.clip(cosine, 0.17, 1.0)
    own_patch = 1.5 * cell_mm * points[:, 2] / face_depth * (np.sqrt(1.0 - facing ** 2) / facing)
    return points[:, 2] > nearest[tuple((site_cells - low).T)] + own_patch + 3.0
