"""Which points on a face a camera sees: one model for the marker-layout designer and the simulated rig.

A camera sees a surface point when the point faces it (its normal within a limit angle of the direction
to the camera), lies in front of it and inside its image (:func:`in_view`), and no surface lies in front
of it (:func:`behind_surface`). The layout designer (``livebridge.face.layout``) places markers where
enough cameras see them; the simulated rig (``livebridge.simulators.rig``) draws a marker only in the
cameras that see it; both ask these functions, so "seen by 3 cameras" means the same in both.

The depth test splats the surface's vertices on a grid on the (pinhole, undistorted) normalised image
plane and keeps the nearest depth per cell. A cell is :func:`depth_cell_mm` wide at the face (a long mesh
edge: a cell then holds a vertex of any surface in front, so the splat has few holes). A point is hidden
when that nearest depth is nearer than its own surface patch can be: the cell seen at the point's angle
(with half again for the patch's curvature), plus :data:`SURFACE_SLACK_MM`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

SURFACE_SLACK_MM = 3.0  # a point is hidden only behind surface this much nearer than its own patch
PATCH_SPREAD = 1.5  # the own patch: the cell seen at the point's angle, and half again for its curvature
MIN_FACING = 0.17  # cosine (80 deg) below which the patch's slope stops growing
CELL_EDGE_QUANTILE = 0.75  # the cell is this quantile of the mesh's edge lengths


def depth_cell_mm(vertices: np.ndarray, triangles: np.ndarray) -> float:
    """Width of a depth-test cell at the face, mm: a long edge of the mesh (few holes in the splat).

    Parameters
    ----------
    vertices : ndarray, shape (n_vertices, 3)
    triangles : ndarray of int, shape (n_triangles, 3)
    """
    edges = np.linalg.norm(vertices[triangles] - vertices[np.roll(triangles, 1, axis=1)], axis=2)
    return float(np.quantile(edges, CELL_EDGE_QUANTILE))


def in_view(cosine: np.ndarray, depth: np.ndarray, pixels: np.ndarray, size: tuple[int, int],
            cos_limit: float) -> np.ndarray:
    """Points that face a camera within the limit angle, lie in front of it and inside its image.

    Parameters
    ----------
    cosine : ndarray, shape (n,)
        Cosine of the angle between each point's normal and its direction to the camera.
    depth : ndarray, shape (n,)
        Camera-frame z, mm.
    pixels : ndarray, shape (n, 2)
        Where the camera images the points (NaN: nowhere).
    size : tuple of int
        Image ``(width, height)``.
    cos_limit : float
        Cosine of the largest angle between normal and camera at which the camera sees a point.

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    width, height = size
    return ((cosine >= cos_limit) & (depth > 0) & (pixels[:, 0] >= -0.5) & (pixels[:, 0] < width - 0.5)
            & (pixels[:, 1] >= -0.5) & (pixels[:, 1] < height - 0.5))


@njit(cache=True, nogil=True)
def behind_surface(surface: np.ndarray, points: np.ndarray, cosine: np.ndarray, cell_mm: float) -> np.ndarray:
    """Points with the surface in front of them, by a depth splat of the surface's vertices.

    Parameters
    ----------
    surface : ndarray, shape (n_vertices, 3)
        The surface's vertices in the camera frame, mm; those no more than 1 mm in front of the camera
        are left out.
    points : ndarray, shape (n, 3)
        The points asked about, camera frame, mm, in front of the camera. A point's answer does not
        depend on which other points are asked about.
    cosine : ndarray, shape (n,)
        Cosine of the angle between each point's normal and its direction to the camera.
    cell_mm : float
        Width of a grid cell at the face's median depth (:func:`depth_cell_mm`).

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    n = points.shape[0]
    hidden = np.zeros(n, dtype=np.bool_)
    near = surface[:, 2] > 1.0
    if n == 0 or not near.any():
        return hidden
    face_depth = np.median(surface[:, 2][near])
    cell = cell_mm / face_depth  # on the normalised image plane
    cells = np.empty((n, 2), dtype=np.int64)
    for m in range(n):
        cells[m, 0] = int(math.floor(points[m, 0] / points[m, 2] / cell))
        cells[m, 1] = int(math.floor(points[m, 1] / points[m, 2] / cell))
    low_x, low_y = cells[:, 0].min(), cells[:, 1].min()
    nearest = np.full((cells[:, 0].max() - low_x + 1, cells[:, 1].max() - low_y + 1), np.inf)
    for v in range(surface.shape[0]):
        z = surface[v, 2]
        if not near[v]:
            continue
        i = int(math.floor(surface[v, 0] / z / cell)) - low_x
        j = int(math.floor(surface[v, 1] / z / cell)) - low_y
        if 0 <= i < nearest.shape[0] and 0 <= j < nearest.shape[1]:  # vertices elsewhere hide no point
            nearest[i, j] = min(nearest[i, j], z)
    for m in range(n):
        facing = min(max(cosine[m], MIN_FACING), 1.0)
        slope = math.sqrt(1.0 - facing * facing) / facing
        own_patch = PATCH_SPREAD * cell_mm * points[m, 2] / face_depth * slope
        hidden[m] = points[m, 2] > nearest[cells[m, 0] - low_x, cells[m, 1] - low_y] + own_patch + SURFACE_SLACK_MM
    return hidden


def sees(points_cam: np.ndarray, cosine: np.ndarray, pixels: np.ndarray, size: tuple[int, int], cos_limit: float,
         surface_cam: np.ndarray, cell_mm: float) -> np.ndarray:
    """Points a camera sees: :func:`in_view` and not :func:`behind_surface`.

    Parameters
    ----------
    points_cam : ndarray, shape (n, 3)
        The points in the camera frame, mm.
    cosine, pixels, size, cos_limit
        As for :func:`in_view`.
    surface_cam : ndarray, shape (n_vertices, 3)
        The surface that can hide them, camera frame, mm.
    cell_mm : float
        :func:`depth_cell_mm` of that surface.

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    seen = in_view(cosine, points_cam[:, 2], pixels, size, cos_limit)
    if seen.any():
        seen[seen] = ~behind_surface(surface_cam, np.ascontiguousarray(points_cam[seen]), cosine[seen], cell_mm)
    return seen
