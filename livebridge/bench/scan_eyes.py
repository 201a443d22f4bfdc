"""The eyes a simulated face scanner sees: a head's eyeballs (sclera and iris, fixed in the skull) through the
eye openings of its face mesh, hidden wherever the face is in front of them (a closed lid, the lids' rims).

A real scanner sees the eyes between the lids, where the bench's other scans have holes; see
:mod:`~livebridge.retarget.eyeballs` for how the pipeline leaves them out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from livebridge.bench.surface_samples import area_samples, facing_weights, triangle_samples

SCLERA = np.array([0.86, 0.83, 0.80])
"""RGB of the eye's white (before the scan's exposure)."""
IRIS = np.array([0.30, 0.20, 0.12])
"""A brown iris, the commonest and the nearest to skin in hue."""
PUPIL = np.array([0.04, 0.04, 0.04])
PUPIL_SHARE = 0.4
"""The pupil's radius over the iris's."""
BRIGHTNESS_SPREAD = 0.1
"""Each eye point's brightness is off by up to this fraction (the sclera's veins and the iris's pattern)."""
PIXEL_MM = 0.1
"""Pixel of the depth buffer that decides what the scanner sees."""
TRIANGLE_SAMPLES = 8
"""Random points a triangle of a textured mesh is judged seen by (most of them)."""
PATCH_TEXELS = 4
"""Side of each flat patch of an eye mesh's texture."""
FAR_MM = 1e5
"""The depth buffer's camera is this far in front of the face (its view is all but orthographic)."""


@dataclass(frozen=True)
class Eyeballs:
    """A head's eyeballs in its face mesh's frame.

    Attributes
    ----------
    vertices : ndarray, shape (n, 3)
        mm.
    triangles : ndarray of int, shape (m, 3)
    iris : ndarray of bool, shape (m,)
        Which triangles are the iris's (the rest the sclera's).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    iris: np.ndarray


def eye_points(eyes: Eyeballs, face: np.ndarray, face_triangles: np.ndarray, per_mm2: float,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Points (k, 3) a scanner looking along -z sees on ``eyes`` past the face mesh (``face`` (n, 3) vertices,
    ``face_triangles`` (m, 3)), ``per_mm2`` of them per mm² of the eyeballs' surface facing it, and their
    colours (k, 3), before exposure and noise."""
    count = int(rng.poisson(per_mm2 * facing_weights(eyes.vertices, eyes.triangles).sum()))
    points, chosen, _ = area_samples(eyes.vertices, eyes.triangles, count, rng)
    seen = _seen(points, face, face_triangles, eyes.vertices, eyes.triangles)
    points, chosen = points[seen], chosen[seen]
    colours = np.where(eyes.iris[chosen, None], IRIS, SCLERA)
    colours = np.where(_in_pupil(eyes, points, chosen)[:, None], PUPIL, colours)
    return points, colours * rng.uniform(1 - BRIGHTNESS_SPREAD, 1 + BRIGHTNESS_SPREAD, (len(points), 1))


def eye_mesh(eyes: Eyeballs, pose: np.ndarray, face: np.ndarray, face_triangles: np.ndarray,
             rng: np.random.Generator, exposure: float = 1.0):
    """The eyeball triangles a textured-mesh scanner looking along -z keeps, with the head at ``pose`` (4, 4;
    ``face`` (n, 3) the face mesh's vertices already there, ``face_triangles`` (m, 3)): those with most of
    :data:`TRIANGLE_SAMPLES` random points on them seen past the face. Returns their vertices (k, 3; all of the
    eyes', posed), triangles (t, 3), texture coordinates (t, 3, 2; OBJ convention) and the image they index
    (rows, columns, 3): flat patches of sclera, iris and pupil times ``exposure``, each triangle wholly one
    (the pupil's: its centre within :data:`PUPIL_SHARE` of the iris's radius)."""
    from livebridge.geometry.transforms import apply

    vertices = apply(pose, eyes.vertices)
    samples = triangle_samples(vertices, eyes.triangles, TRIANGLE_SAMPLES, rng).reshape(-1, 3)
    seen = _seen(samples, face, face_triangles, vertices, eyes.triangles).reshape(-1, TRIANGLE_SAMPLES)
    kept = np.flatnonzero(seen.mean(axis=1) >= 0.5)
    centres = eyes.vertices[eyes.triangles[kept]].mean(axis=1)
    kind = np.where(_in_pupil(eyes, centres, kept), 2, np.where(eyes.iris[kept], 1, 0))
    patches = (SCLERA, IRIS, PUPIL)
    image = np.concatenate([np.broadcast_to(colour * exposure, (PATCH_TEXELS, PATCH_TEXELS, 3)) for colour in patches],
                           axis=1)
    u = (kind + 0.5) / len(patches)
    uv = np.broadcast_to(np.stack([u, np.full(len(u), 0.5)], axis=-1)[:, None, :], (len(kept), 3, 2))
    return vertices, eyes.triangles[kept], np.ascontiguousarray(uv), np.clip(image, 0.0, 1.0).astype(np.float32)


def _in_pupil(eyes: Eyeballs, points: np.ndarray, chosen: np.ndarray) -> np.ndarray:
    """Which ``points`` (k, 3; on triangles ``chosen`` (k,)) lie in a pupil: within :data:`PUPIL_SHARE` of their
    iris's radius from its centre (each eyeball's iris is the iris triangles on its side of x = 0)."""
    out = np.zeros(len(points), dtype=bool)
    corners = eyes.vertices[eyes.triangles[eyes.iris]].reshape(-1, 3)
    for side in (corners[:, 0] > 0, corners[:, 0] <= 0):
        if not side.any():
            continue
        iris = corners[side]
        centre = iris.mean(axis=0)
        radius = np.linalg.norm(iris[:, :2] - centre[:2], axis=1).max()
        mine = eyes.iris[chosen] & ((points[:, 0] > 0) == (centre[0] > 0))
        out |= mine & (np.linalg.norm(points[:, :2] - centre[:2], axis=1) < PUPIL_SHARE * radius)
    return out


def _seen(points: np.ndarray, face: np.ndarray, face_triangles: np.ndarray, eye_vertices: np.ndarray,
          eye_triangles: np.ndarray) -> np.ndarray:
    """Which ``points`` (k, 3) on the eyes (``eye_vertices`` (n, 3), ``eye_triangles`` (m, 3)) are seen from +z:
    the nearest surface of their pixel of a depth buffer (:data:`PIXEL_MM`) of the face (``face`` vertices,
    ``face_triangles``) and the eyes is one of the eyes'."""
    from livebridge.simulators.raster import project_vertices, rasterize

    vertices = np.vstack([face, eye_vertices])
    triangles = np.vstack([face_triangles, eye_triangles + len(face)])
    if not len(points):
        return np.zeros(0, dtype=bool)
    low, high = points[:, :2].min(axis=0) - 1.0, points[:, :2].max(axis=0) + 1.0
    width, height = (np.ceil((high - low) / PIXEL_MM).astype(int) + 1).tolist()
    top = float(vertices[:, 2].max())
    world2cam = np.array([[1.0, 0, 0, 0], [0, -1.0, 0, 0], [0, 0, -1.0, top + FAR_MM], [0, 0, 0, 1]])
    focal = FAR_MM / PIXEL_MM
    matrix = np.array([[focal, 0, -low[0] / PIXEL_MM], [0, focal, high[1] / PIXEL_MM], [0, 0, 1.0]])

    def projected(p):
        pixels, depth = np.zeros((len(p), 2)), np.zeros(len(p))
        project_vertices(np.ascontiguousarray(p, dtype=np.float64), world2cam, matrix, pixels, depth)
        return pixels

    ids = np.full((height, width), -1, np.int32)
    rasterize(projected(vertices), vertices[:, 2] * -1.0 + top + FAR_MM, np.ascontiguousarray(triangles, np.int64),
              ids, np.zeros((height, width, 2), np.float32), np.zeros((height, width), np.float32),
              np.zeros(len(triangles), bool))
    at = np.rint(projected(points)).astype(int)
    inside = (at[:, 0] >= 0) & (at[:, 0] < width) & (at[:, 1] >= 0) & (at[:, 1] < height)
    seen = np.zeros(len(points), dtype=bool)
    seen[inside] = ids[at[inside, 1], at[inside, 0]] >= len(face_triangles)
    return seen
