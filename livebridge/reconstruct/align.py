"""Coordinate alignment: the capture-to-model similarity and the virtual markers on the face surface.

As in the design: a similarity transform (scale, rotation, translation) from capture space to model
space is solved on the neutral frame against the markers' virtual positions; then each captured
marker, carried into the model frame, is projected onto the face surface along the normal (the
closest surface point), the similarity is solved again against those surface points, and this
repeats until the error stops falling. The virtual markers are then placed at those surface points
(triangle + barycentric coordinates), so the solver's displacement matrix describes the markers
where they really are on the face.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from livebridge.face.basis import Basis
from livebridge.face.markers import MarkerSet
from livebridge.geometry.transforms import apply, umeyama


@dataclass(frozen=True, eq=False)
class Alignment:
    """Result of the coordinate alignment.

    Attributes
    ----------
    capture2model : ndarray, shape (4, 4)
        Similarity transform from the capture (world) frame to the model frame.
    markers : MarkerSet
        The virtual markers, face markers moved to the surface points found.
    rms_mm : float
        RMS distance (model mm) of the aligned captured face markers from the surface.
    iterations : int
    """

    capture2model: np.ndarray
    markers: MarkerSet
    rms_mm: float
    iterations: int


class MeshSurface:
    """Closest-point queries on a triangle mesh.

    Parameters
    ----------
    vertices : ndarray, shape (n_vertices, 3)
    triangles : ndarray of int, shape (n_triangles, 3)
    candidates : int
        Triangles (nearest by centroid) tested per query point.
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, candidates: int = 24):
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.triangles = np.asarray(triangles, dtype=np.int64)
        self.corners = self.vertices[self.triangles]  # (T, 3, 3)
        self.tree = cKDTree(self.corners.mean(axis=1))
        self.candidates = min(int(candidates), len(self.triangles))

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest surface point to each query.

        Parameters
        ----------
        points : ndarray, shape (n, 3)

        Returns
        -------
        triangle : ndarray of int, shape (n,)
        barycentric : ndarray, shape (n, 3)
        surface_points : ndarray, shape (n, 3)
        """
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        _, near = self.tree.query(points, k=self.candidates)
        near = near.reshape(len(points), -1)
        corners = self.corners[near]  # (n, k, 3, 3)
        bary = closest_barycentric(np.broadcast_to(points[:, None], near.shape + (3,)), corners)
        surface = np.einsum("nkc,nkcd->nkd", bary, corners)
        best = np.argmin(((surface - points[:, None]) ** 2).sum(axis=-1), axis=1)
        pick = np.arange(len(points))
        return near[pick, best], bary[pick, best], surface[pick, best]


def closest_barycentric(points: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Barycentric coordinates of the closest point on each triangle (Ericson, *Real-Time Collision Detection*).

    Parameters
    ----------
    points : ndarray, shape (..., 3)
    corners : ndarray, shape (..., 3, 3)
        Triangle corners ``a, b, c``.

    Returns
    -------
    ndarray, shape (..., 3)
    """
    a, b, c = corners[..., 0, :], corners[..., 1, :], corners[..., 2, :]
    ab, ac, ap = b - a, c - a, points - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = points - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = points - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(all="ignore"):
        denom = va + vb + vc
        v = vb / denom
        w = vc / denom
        out = np.stack([1 - v - w, v, w], axis=-1)  # interior
        # edges
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    zeros = np.zeros_like(d1)
    region_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    region_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    region_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    out = np.where(region_bc[..., None], np.stack([zeros, 1 - t_bc, t_bc], -1), out)
    out = np.where(region_ac[..., None], np.stack([1 - t_ac, zeros, t_ac], -1), out)
    ones = np.ones_like(d1)
    out = np.where(((d6 >= 0) & (d5 <= d6))[..., None], np.stack([zeros, zeros, ones], -1), out)
    out = np.where(region_ab[..., None], np.stack([1 - t_ab, t_ab, zeros], -1), out)
    out = np.where(((d3 >= 0) & (d4 <= d3))[..., None], np.stack([zeros, ones, zeros], -1), out)
    out = np.where(((d1 <= 0) & (d2 <= 0))[..., None], np.stack([ones, zeros, zeros], -1), out)
    out = np.where(np.isfinite(out).all(-1, keepdims=True), out, np.array([1.0, 0.0, 0.0]))
    return np.clip(out, 0.0, 1.0) / np.clip(out, 0.0, 1.0).sum(-1, keepdims=True)


def align_to_model(points_capture: np.ndarray, markers: MarkerSet, basis: Basis, max_iterations: int = 20,
                   tolerance_mm: float = 1e-6) -> Alignment:
    """Solve ``capture2model`` on the neutral frame and place the virtual markers on the surface.

    Parameters
    ----------
    points_capture : ndarray, shape (n_markers, 3)
        Labelled neutral-frame positions in the capture frame; NaN for markers not seen.
    markers : MarkerSet
    basis : Basis
        Its neutral mesh is the surface.
    max_iterations : int
    tolerance_mm : float
        Stop when the RMS error falls by less than this.

    Returns
    -------
    Alignment
    """
    points_capture = np.asarray(points_capture, dtype=np.float64)
    virtual = markers.neutral_positions(basis)
    face = markers.face_mask & np.isfinite(points_capture).all(axis=1)
    transform = umeyama(points_capture, virtual, with_scale=True)
    if face.sum() < 3 or not np.isfinite(transform).all():
        return Alignment(transform, markers, np.inf, 0)
    surface = MeshSurface(basis.neutral, basis.triangles)
    triangles, barycentric = markers.triangles.copy(), markers.barycentric.copy()
    face_index = np.flatnonzero(face)
    tri, bary, target = surface.closest(apply(transform, points_capture[face]))
    best = (np.sqrt(np.mean(((apply(transform, points_capture[face]) - target) ** 2).sum(-1))), transform, tri, bary)
    iterations = 0
    while iterations < max_iterations:
        candidate = umeyama(points_capture[face], target, with_scale=True)
        moved = apply(candidate, points_capture[face])
        tri, bary, target = surface.closest(moved)
        error = float(np.sqrt(np.mean(((moved - target) ** 2).sum(-1))))
        if error >= best[0] - tolerance_mm:
            break  # the error stopped falling
        best = (error, candidate, tri, bary)
        iterations += 1
    error, transform, tri, bary = best
    triangles[face_index] = tri
    barycentric[face_index] = bary
    placed = MarkerSet(markers.names, triangles, barycentric, markers.regions, markers.roles)
    return Alignment(transform, placed, float(error), iterations)
