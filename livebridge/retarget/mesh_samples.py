"""A scanned mesh as points: every triangle split into ``n^2`` equal sub-triangles, a point at each one's
centroid (``n = ceil(sqrt(area) / spacing)``: a point per ``spacing^2`` of surface).

The scans' resampling (:mod:`~livebridge.retarget.grid`) reads a scan as points, and calls a grid point a hole
when no point is within a few median point spacings of it. A mesh's vertices are no such sample: scanners and
decimation put them densely where the face curves (the eyes, the nostrils, the lips) and sparsely on the
cheeks and forehead, so the median spacing is the dense parts' and the sparse parts came out full of holes.
ICT-FaceKit's full head read as a scan by its vertices (its eyes, lashes and mouth dense) kept 6846 of the 9646
grid vertices its face region alone gives; sampled (and what the face's front hides cut:
:data:`~livebridge.retarget.face_scan.HIDDEN_DEPTH_MM`), 9734, its neutral within 0.05 mm of the true surface at
the 90th percentile (0.58 mm from the face region's vertices). Vertices no triangle uses (a mesh's leftovers)
are no surface, and are not sampled.
"""

from __future__ import annotations

import numpy as np

from livebridge.face.meshio import triangle_areas

SAMPLE_SPACING_MM = 0.5
"""Default distance between the points sampled on a mesh: the skin images' pixel
(:data:`~livebridge.retarget.skin_flow.FINE_MM`); a finer texture is blurred to it
(:mod:`~livebridge.retarget.texture`). Finer sampling bought nothing (`livebridge bench scans`' textured meshes,
seed 7, the brow, smile and jaw elements and the eyelids, relative RMS): on 0.5 mm texels 0.034 / 0.026 / 0.057
from points 0.3 mm apart (99 s for the neutral and three expressions), 0.034 / 0.024 / 0.055 from 0.5 mm (45 s);
on 0.25 mm texels 0.034 / 0.027 / 0.059 and eyelids 0.151 / 0.170 from 0.3 mm, 0.033 / 0.024 / 0.054 and 0.149 /
0.169 from 0.5 mm, 0.035 / 0.024 / 0.054 and 0.149 / 0.165 from 0.6 mm (blurred)."""
MAX_SPLITS = 256
"""A triangle is split into at most this many parts along an edge (a scan's few very large triangles, off the
face, do not cost millions of points)."""


def surface_samples(points: np.ndarray, triangles: np.ndarray, spacing: float | None = None,
                    keep: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points every ``spacing`` mm over a mesh.

    Parameters
    ----------
    points : ndarray, shape (n_points, 3)
        The mesh's vertices, mm.
    triangles : ndarray of int, shape (n_triangles, 3)
    spacing : float, optional
        mm (default :data:`SAMPLE_SPACING_MM`).
    keep : ndarray of bool, shape (n_triangles,), optional
        Only these triangles are sampled (a crop).

    Returns
    -------
    samples : ndarray, shape (n_samples, 3)
    owner : ndarray of int, shape (n_samples,)
        The triangle each sample lies on.
    barycentric : ndarray, shape (n_samples, 3)
        Its place on that triangle (to carry anything the corners hold: colours, texture coordinates).
    """
    chosen = np.flatnonzero(keep) if keep is not None else np.arange(len(triangles))
    spacing = SAMPLE_SPACING_MM if spacing is None else spacing
    area = triangle_areas(points, triangles[chosen])
    splits = np.clip(np.ceil(np.sqrt(area) / spacing), 1, MAX_SPLITS).astype(int)
    owners, barys = [np.zeros(0, np.int64)], [np.zeros((0, 3))]
    for n in np.unique(splits):
        rows = chosen[splits == n]
        bary = _centroids(int(n))  # (m, 3)
        owners.append(np.repeat(rows, len(bary)))
        barys.append(np.tile(bary, (len(rows), 1)))
    owner, barycentric = np.concatenate(owners), np.vstack(barys)
    samples = np.einsum("sk,skd->sd", barycentric, points[triangles[owner]])
    return samples, owner, barycentric


def _centroids(n: int) -> np.ndarray:
    """Barycentric coordinates (n^2, 3) of the centroids of the n^2 sub-triangles of a triangle split n times."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    up = (i + j <= n - 1)
    down = (i + j <= n - 2)
    a = np.concatenate([i[up] + 1 / 3, i[down] + 2 / 3]) / n
    b = np.concatenate([j[up] + 1 / 3, j[down] + 2 / 3]) / n
    return np.stack([1 - a - b, a, b], axis=1)
