"""How alike two bases on one mesh move: a retargeted basis against the target face's own elements."""

from __future__ import annotations

import numpy as np

from livebridge.face.basis import Basis
from livebridge.retarget.landmarks import LandmarkSet

MOVING = 0.2
"""A landmark counts for a muscle when both elements move it at least this fraction of their most there."""


def motion_agreement(retargeted: Basis, own: Basis, landmarks: LandmarkSet) -> dict[str, float]:
    """Per muscle both bases have: the cosine between their directions of motion at the landmarks.

    Averaged over the landmarks both elements move (see :data:`MOVING`), weighted by the product of the two
    motions there; NaN when no landmark qualifies. Both bases must share the mesh (``own``'s).

    Returns
    -------
    dict of str to float
        In [-1, 1]: 1 = same directions everywhere both move.
    """
    if retargeted.neutral.shape != own.neutral.shape:
        raise ValueError("the bases are on different meshes")
    out = {}
    for name in own.names:
        if name not in retargeted.names:
            continue
        a = _at(landmarks, retargeted.elements[retargeted.index(name)], own.triangles)
        b = _at(landmarks, own.elements[own.index(name)], own.triangles)
        size_a, size_b = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
        both = (size_a > MOVING * size_a.max()) & (size_b > MOVING * size_b.max()) if size_a.max() > 0 and \
            size_b.max() > 0 else np.zeros(len(a), dtype=bool)
        if not both.any():
            out[name] = float("nan")
            continue
        weight = size_a[both] * size_b[both]
        cosine = np.einsum("nd,nd->n", a[both], b[both]) / weight
        out[name] = float(weight @ cosine / weight.sum())
    return out


def _at(landmarks: LandmarkSet, field: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """A per-vertex field (n_vertices, 3) at the landmarks, shape (n_landmarks, 3)."""
    return np.einsum("nk,nkd->nd", landmarks.barycentric, field[triangles[landmarks.triangles]])


def roughness(elements: np.ndarray, vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Per element, how rough its displacement field is on its mesh, 1/mm^2, shape (k,).

    The RMS over the vertices of the umbrella Laplacian of the field (each vertex's displacement minus its mesh
    neighbours' mean) over the RMS displacement, divided by the squared mean edge length: a smooth field's
    umbrella Laplacian grows with the squared spacing, so the figure is its curvature, comparable between meshes of
    different resolution (a source basis and its retargeted copy). NaN for an element that moves nothing.

    ``elements`` (k, n_vertices, 3); ``vertices`` (n_vertices, 3); ``triangles`` (m, 3).
    """
    from livebridge.face.meshio import edge_counts
    from livebridge.retarget.basis import neighbour_mean

    edges, _ = edge_counts(np.asarray(triangles))
    spacing = float(np.mean(np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)))
    mean = neighbour_mean(edges, len(vertices))
    out = np.full(len(elements), np.nan)
    for k, field in enumerate(np.asarray(elements, dtype=np.float64)):
        size = float(np.sum(field ** 2))
        if size > 0:
            out[k] = np.sqrt(np.sum((field - mean @ field) ** 2) / size) / spacing ** 2
    return out


BESIDE_GAP = 0.15
"""Gap between two faces shown side by side, as a fraction of the first face's width."""


def side_by_side(first: Basis, second: Basis, gap: float = BESIDE_GAP) -> Basis:
    """One basis holding both faces as two meshes, ``second`` to the right of ``first`` (+x, the viewer's right
    when the face looks along +z), its bounding box centred on ``first``'s in y and z; both move with the same
    contractions.

    The two must have the same muscles in the same order (a retargeted face has). ``first`` keeps its place, so
    whatever is drawn in its frame (markers) stays on it.
    """
    if first.names != second.names:
        raise ValueError("side by side needs the same muscles in the same order")
    low, high = first.neutral.min(axis=0), first.neutral.max(axis=0)
    other_low, other_high = second.neutral.min(axis=0), second.neutral.max(axis=0)
    shift = 0.5 * (low + high) - 0.5 * (other_low + other_high)
    shift[0] = high[0] + gap * (high[0] - low[0]) - other_low[0]
    neutral = np.vstack([first.neutral, second.neutral + shift])
    triangles = np.vstack([first.triangles, second.triangles + first.n_vertices])
    elements = np.concatenate([first.elements, second.elements], axis=1)
    return Basis(neutral, triangles, elements, first.muscles)
