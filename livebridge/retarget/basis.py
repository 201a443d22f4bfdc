"""Basis retargeting: every element of an actuation basis carried onto another face (any topology) by a TPS.

A landmark thin-plate spline ``f`` maps the source neutral face onto the target neutral face. Each target
vertex ``v`` finds its source surface point ``p`` through the inverse spline ``g`` (fitted target -> source on
the same landmarks) followed by the closest point on the source surface; the source element's displacement
``d`` there (barycentric interpolation) becomes ``f(p + d) - f(p)`` on the target, so the motion follows the
local scale and proportions of ``f``. Upper- and lower-face elements use the same ``f`` (the thesis warps the
two regions separately when animating, §5.6; a basis element is already confined to its region).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.retarget.landmarks import LandmarkSet, closest_surface_points
from livebridge.retarget.tps import Kernel, ThinPlateSpline, fit_tps


@dataclass(frozen=True)
class Correspondence:
    """Where each target vertex lies on the source surface.

    Attributes
    ----------
    triangle : ndarray of int, shape (n_target_vertices,)
        Source triangle.
    barycentric : ndarray, shape (n_target_vertices, 3)
    distance : ndarray, shape (n_target_vertices,)
        From the target vertex carried into source space (by ``g``) to that surface point, mm: large values
        mark target regions the source face does not cover.
    """

    triangle: np.ndarray
    barycentric: np.ndarray
    distance: np.ndarray

    def interpolate(self, values: np.ndarray, triangles: np.ndarray) -> np.ndarray:
        """Per-vertex ``values (..., n_source_vertices, 3)`` at the surface points, shape (..., n_target, 3)."""
        corners = values[..., triangles[self.triangle], :]  # (..., n_target, 3 corners, 3)
        return np.einsum("nk,...nkd->...nd", self.barycentric, corners)


def landmark_pairs(source_landmarks: LandmarkSet, source_mesh, target_landmarks: LandmarkSet,
                   target_mesh) -> tuple[np.ndarray, np.ndarray]:
    """(source positions (n, 3), target positions (n, 3)) of the source set's landmarks, matched by name.

    ``*_mesh`` are (vertices, triangles). Every landmark of the source set must be in the target set.
    """
    index = target_landmarks.index_of(source_landmarks.names)
    source = source_landmarks.positions(*source_mesh)
    target = target_landmarks.positions(*target_mesh)[index]
    return source, target


def landmark_splines(source_points: np.ndarray, target_points: np.ndarray,
                     kernel: Kernel | str = Kernel.BIHARMONIC) -> tuple[ThinPlateSpline, ThinPlateSpline]:
    """(``f`` source -> target, ``g`` target -> source): the two landmark splines of a transfer."""
    return fit_tps(source_points, target_points, kernel), fit_tps(target_points, source_points, kernel)


def correspond(target_vertices: np.ndarray, to_source: ThinPlateSpline, source_vertices: np.ndarray,
               source_triangles: np.ndarray) -> Correspondence:
    """Each target vertex's point on the source surface: ``g(v)`` snapped to the closest surface point."""
    triangle, barycentric, distance = closest_surface_points(to_source(target_vertices), source_vertices,
                                                             source_triangles)
    return Correspondence(triangle, barycentric, distance)


def transfer_elements(elements: np.ndarray, source: Basis, correspondence: Correspondence,
                      to_target: ThinPlateSpline) -> np.ndarray:
    """Source elements ``(k, n_source, 3)`` as target elements ``(k, n_target, 3)``: ``f(p + d) - f(p)``.

    An element that is zero at a surface point stays exactly zero there.
    """
    points = correspondence.interpolate(source.neutral, source.triangles)  # p, (n_target, 3)
    moves = correspondence.interpolate(elements, source.triangles)  # d, (k, n_target, 3)
    moving = np.any(moves != 0, axis=(0, 2))  # f only where something moves: the rest stays exactly 0
    out = np.zeros(moves.shape)
    if not moving.any():
        return out
    base = to_target(points[moving])
    displaced = to_target((points[moving][None] + moves[:, moving]).reshape(-1, 3))
    out[:, moving] = displaced.reshape(len(elements), -1, 3) - base[None]
    return out


def retarget_basis(source: Basis, source_landmarks: LandmarkSet, target_neutral: np.ndarray,
                   target_triangles: np.ndarray, target_landmarks: LandmarkSet,
                   kernel: Kernel | str = Kernel.BIHARMONIC) -> Basis:
    """The source basis carried onto the target mesh: same muscles (names, regions, sides), target topology.

    Parameters
    ----------
    source : Basis
    source_landmarks : LandmarkSet
        On the source mesh; at least 4 landmarks, not all on one plane (the thesis's 22 are the intent).
    target_neutral : ndarray, shape (n_target_vertices, 3)
        The target's neutral face, mm, in any pose (the landmark spline absorbs pose and size).
    target_triangles : ndarray of int, shape (n_target_triangles, 3)
    target_landmarks : LandmarkSet
        On the target mesh; must name every landmark of ``source_landmarks``.
    kernel : Kernel or str

    Returns
    -------
    Basis
        Neutral ``target_neutral``; muscles with no effect in the source stay exactly zero.
    """
    target_neutral = np.asarray(target_neutral, dtype=np.float64)
    target_triangles = np.asarray(target_triangles, dtype=np.int64)
    if target_neutral.ndim != 2 or target_neutral.shape[1] != 3 or not len(target_triangles):
        raise InputError(f"the target needs vertices (n, 3) and triangles, got {target_neutral.shape} vertices "
                         f"and {len(target_triangles)} triangles", field="target")
    source_points, target_points = landmark_pairs(source_landmarks, (source.neutral, source.triangles),
                                                  target_landmarks, (target_neutral, target_triangles))
    to_target, to_source = landmark_splines(source_points, target_points, kernel)
    correspondence = correspond(target_neutral, to_source, source.neutral, source.triangles)
    elements = transfer_elements(source.elements, source, correspondence, to_target)
    return Basis(target_neutral, target_triangles, elements, source.muscles)


# ------------------------------------------------------------------------------------------------ measuring
MOVED_FRACTION = 0.01
"""A vertex is moved by an element when it moves more than this fraction of the element's largest motion."""


def relative_errors(elements: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per element, the RMS error over the vertices it moves over its RMS displacement there, shape (k,).

    ``elements`` and ``truth``: (k, n_vertices, 3). NaN for an element that moves nothing.
    """
    size = np.linalg.norm(truth, axis=2)
    error = np.linalg.norm(elements - truth, axis=2)
    out = np.full(len(truth), np.nan)
    for k in range(len(truth)):
        moved = size[k] > MOVED_FRACTION * size[k].max()
        if moved.any():
            out[k] = np.sqrt(np.mean(error[k, moved] ** 2) / np.mean(size[k, moved] ** 2))
    return out


def naive_transfer(source: Basis, source_landmarks: LandmarkSet, target_neutral: np.ndarray,
                   target_triangles: np.ndarray, target_landmarks: LandmarkSet) -> np.ndarray:
    """The baseline: each target vertex copies the displacement of its nearest source vertex.

    The target is first aligned onto the source by the similarity of the landmarks (Umeyama); the copied
    displacement is turned and scaled back by that similarity. Returns elements (k, n_target_vertices, 3).
    """
    from scipy.spatial import cKDTree

    from livebridge.geometry.transforms import apply, umeyama

    source_points, target_points = landmark_pairs(source_landmarks, (source.neutral, source.triangles),
                                                  target_landmarks, (target_neutral, target_triangles))
    target2source = umeyama(target_points, source_points)
    _, nearest = cKDTree(source.neutral).query(apply(target2source, target_neutral))
    back = np.linalg.inv(target2source[:3, :3])
    return source.elements[:, nearest] @ back.T
