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
