"""Bases from scans: a neutral and 16 expression scans sampled from the ICT meshes as noisy point clouds, the
basis built from them against the ICT elements (relative RMS per element), and the time it takes."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

SCAN_POINTS = 60_000
SCAN_NOISE_MM = 0.2
LANDMARK_NOISE_MM = 0.5
HOLE_RADIUS_MM = 8.0
HOLE_MUSCLE = "zygomatic_major_L"
ERROR_LIMIT = 0.10
"""The bar of issue 16: each element within 10% of its RMS displacement over the vertices it moves."""


@dataclass(frozen=True)
class SyntheticScan:
    """A simulated frontal scan of a face mesh: points and landmarks in the scanner's frame.

    Attributes
    ----------
    points : ndarray, shape (n, 3)
    landmarks : dict of str to ndarray, shape (3,)
    face2scanner : ndarray, shape (4, 4)
        Where the head was: from the mesh's frame to the scanner's.
    """

    points: np.ndarray
    landmarks: dict
    face2scanner: np.ndarray


def scan_surface(vertices: np.ndarray, triangles: np.ndarray, n_points: int, noise: float,
                 rng: np.random.Generator, hole: tuple[np.ndarray, float] | None = None) -> np.ndarray:
    """Points (<= n_points, 3) a scanner looking along -z sees on a mesh, with Gaussian noise ``noise`` mm.

    Area-weighted random barycentric points on the triangles facing +z; hidden ones (more than 1.5 mm behind
    the front-most surface within 0.5 mm in x-y) dropped; ``hole`` = (centre (3,), radius): no points there.
    """
    from livebridge.face.meshio import triangle_normals
    from livebridge.retarget.grid import front_surface

    corners = vertices[triangles]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    facing = triangle_normals(vertices, triangles)[:, 2] > 0.05
    weight = np.where(facing, area, 0.0)
    chosen = rng.choice(len(triangles), n_points, p=weight / weight.sum())
    a, b = rng.random(n_points), rng.random(n_points)
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    bary = np.stack([1 - a - b, a, b], axis=1)
    points = np.einsum("nk,nkd->nd", bary, corners[chosen])
    points = points[front_surface(points, 0.5, 1.5)]
    if hole is not None:
        points = points[np.linalg.norm(points - hole[0], axis=1) > hole[1]]
    return points + rng.normal(0.0, noise, points.shape)


def random_pose(rng: np.random.Generator, degrees: float = 10.0, shift_mm: float = 30.0) -> np.ndarray:
    """A random rigid motion (4, 4): rotation up to ``degrees`` about a random axis, shift up to ``shift_mm``."""
    from livebridge.geometry.transforms import rotation_matrix

    axis = rng.normal(size=3)
    pose = np.eye(4)
    pose[:3, :3] = rotation_matrix(axis / np.linalg.norm(axis) * np.radians(degrees) * rng.random())
    pose[:3, 3] = rng.uniform(-shift_mm, shift_mm, 3)
    return pose


def synthetic_scans(basis, landmarks, rng: np.random.Generator, n_points: int = SCAN_POINTS,
                    noise: float = SCAN_NOISE_MM, landmark_noise: float = LANDMARK_NOISE_MM,
                    hole_muscle: str | None = HOLE_MUSCLE) -> tuple[SyntheticScan, dict[str, SyntheticScan]]:
    """(neutral, {muscle: expression}) scans of ``basis`` (each element fully contracted), each with its own
    random head pose, sampling and noise; landmarks from ``landmarks`` (a LandmarkSet on the basis) plus
    Gaussian noise. The ``hole_muscle`` scan has a hole of :data:`HOLE_RADIUS_MM` on that side's cheek."""
    from livebridge.geometry.transforms import apply

    def one(shape, hole=None):
        pose = random_pose(rng)
        points = scan_surface(shape, basis.triangles, n_points, noise, rng, hole)
        marks = landmarks.as_dict(shape, basis.triangles)
        marks = {name: apply(pose, p[None])[0] + rng.normal(0.0, landmark_noise, 3) for name, p in marks.items()}
        return SyntheticScan(apply(pose, points), marks, pose)

    neutral = one(basis.neutral)
    expressions = {}
    for muscle, element in zip(basis.muscles, basis.elements):
        hole = None
        if muscle.name == hole_muscle:
            at = landmarks.as_dict(basis.neutral + element, basis.triangles)
            side = muscle.side or "L"
            hole = (0.5 * (at[f"mouth_corner_{side}"] + at[f"eye_outer_{side}"]), HOLE_RADIUS_MM)
        expressions[muscle.name] = one(basis.neutral + element, hole)
    return neutral, expressions


def truth_on_grid(basis, neutral_scan: SyntheticScan, face, names) -> np.ndarray:
    """The basis's elements at the grid vertices' points on its neutral surface, in the face frame.

    ``face`` is the prepared neutral (:class:`~livebridge.retarget.scans.FaceScan`); returns (k, n_vertices, 3).
    """
    from livebridge.geometry.transforms import apply
    from livebridge.retarget.landmarks import closest_surface_points

    mesh2face = face.scan2face @ neutral_scan.face2scanner
    on_mesh = apply(np.linalg.inv(mesh2face), face.vertices)
    triangle, bary, _ = closest_surface_points(on_mesh, basis.neutral, basis.triangles)
    index = [basis.index(name) for name in names]
    corners = basis.elements[index][:, basis.triangles[triangle]]  # (k, n, 3 corners, 3)
    return np.einsum("nk,enkd->end", bary, corners) @ mesh2face[:3, :3].T


def build_and_measure(basis, landmarks, rng: np.random.Generator, **scan_options):
    """Scans of ``basis``, the basis built from them, and per element (name, relative RMS error, surface error).

    Returns (built Basis, truth (k, n, 3), errors (k,), seconds to build).
    """
    from livebridge.retarget.basis import relative_errors
    from livebridge.retarget.scan import Scan
    from livebridge.retarget.scans import basis_from_scans, prepare_expression, prepare_neutral

    neutral_scan, expression_scans = synthetic_scans(basis, landmarks, rng, **scan_options)
    reference = landmarks.as_dict(basis.neutral, basis.triangles)
    start = time.perf_counter()
    neutral = prepare_neutral(Scan(neutral_scan.points, np.zeros((0, 3))), neutral_scan.landmarks, reference)
    faces = {name: prepare_expression(Scan(s.points, np.zeros((0, 3))), s.landmarks, neutral, name)
             for name, s in expression_scans.items()}
    built = basis_from_scans(neutral, faces)
    seconds = time.perf_counter() - start
    truth = truth_on_grid(basis, neutral_scan, neutral, built.names)
    return built, truth, relative_errors(built.elements, truth), seconds


def run(quick: bool, log) -> dict:
    from livebridge.bench.data import ict_basis
    from livebridge.retarget.landmarks import load_landmark_set

    basis = ict_basis()
    if basis is None:
        log("scans: the ICT reference data (../shared/data) is not here; nothing to measure")
        return {"skipped": "no ICT reference data"}
    built, truth, errors, seconds = build_and_measure(basis, load_landmark_set("ict-22"), np.random.default_rng(7))
    log(f"scans: {built.n_vertices} grid vertices, {built.n_muscles} elements, built in {seconds:.1f} s")
    log(f"  {'element':24s} {'rel. RMS':>9s} {'RMS mm':>7s}")
    for name, error, element in zip(built.names, errors, truth):
        size = np.linalg.norm(element, axis=1)
        rms = float(np.sqrt(np.mean(size[size > 0.01 * size.max()] ** 2)))
        log(f"  {name:24s} {error:9.3f} {rms:7.2f}{'' if error <= ERROR_LIMIT else '  > ' + str(ERROR_LIMIT)}")
    return {"build_s": seconds, "n_vertices": built.n_vertices, "max_relative_error": float(np.nanmax(errors)),
            "relative_errors": dict(zip(built.names, map(float, errors))), "limit": ERROR_LIMIT}
