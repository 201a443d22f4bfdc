"""A cleaner image of the neutral skin from all of a person's scans (a groupwise template).

Every expression is tracked against the neutral's skin image, so the neutral scan's own noise (its finest
pores resolved one way by its sampling, its colour noise) is in every element's flow alike. But each
expression scan is another picture of the same skin: warped back to the neutral by the motion already
found, the expression images and the neutral's average into a template whose noise is lower than any one
scan's, and tracking each expression against that template instead of the single neutral scan leaves only
the expression's own noise. (The iterative template of groupwise registration, one round.)
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from livebridge.retarget.grid import FaceGrid
from livebridge.retarget.skin_flow import _remap, skin_image, vertex_field

TEMPLATE_TRUST = 0.5
"""Only skin whose tracking was trusted at least this much is averaged into the template. Measured in
`livebridge bench scans`-like runs (60k points, seed 7), jaw / risorius_R / depressor_anguli_oris: 0.995 gave
0.122 / 0.129 / 0.147, 0.97 0.118 / 0.124 / 0.146, 0.9 0.124 / 0.114 / 0.148, 0.5 0.113 / 0.112 / 0.149
(without the template 0.110 / 0.122 / 0.164); a further check that the warped skin matches the neutral's
(local residual at most 0.8) was worse (frontalis_L 0.101 against 0.090)."""


def skin_templates(neutral_skin: FaceGrid, at: np.ndarray,
                   expressions: list[tuple[FaceGrid, np.ndarray, np.ndarray]]) -> list[FaceGrid]:
    """For each expression, the neutral skin image with its colours replaced by the average of its own and
    the OTHER expressions' skin images warped back onto it (grey, contrast-normalised: each scan's exposure
    does not count). Leaving the expression's own image out keeps its noise out of what it is tracked
    against (with it in, the flow is pulled towards the motion that warped it).

    Parameters
    ----------
    neutral_skin : FaceGrid
        The neutral's coloured fine grid (the skin image).
    at : ndarray, shape (n_vertices, 2)
        The mesh vertices the motions are given at, as (row, column) pixels of ``neutral_skin`` (see
        :func:`~livebridge.retarget.skin_flow.pixels_of`).
    expressions : list of (FaceGrid, ndarray (n_vertices, 3), ndarray (n_vertices,))
        Each expression's skin image on the same grid lines as ``neutral_skin``, the motion of the vertices
        into it in the skin images' chart (u, v, height), and how much that motion is trusted.

    Returns
    -------
    list of FaceGrid
        One per expression: ``neutral_skin`` with a template as its (grey) colours, its heights unchanged.
    """
    image, valid = skin_image(neutral_skin)
    warped = [_warped_back(neutral_skin, at, valid, *expression) for expression in expressions]
    total = np.where(valid, image, 0.0) + sum(w * values for values, w in warped)
    weight = valid + sum(w for _, w in warped)

    def template(values, w):
        mean = np.where(valid, (total - w * values) / np.maximum(weight - w, 1.0), np.nan)
        return replace(neutral_skin, colours=np.repeat(mean[..., None], 3, axis=2))

    return [template(values, w) for values, w in warped]


def _warped_back(neutral_skin: FaceGrid, at: np.ndarray, valid: np.ndarray, skin: FaceGrid, motion: np.ndarray,
                 trust: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An expression's skin image at where each neutral skin pixel went, and its weight (1 where that is
    trusted, on both skins), both (n_rows, n_cols)."""
    target, target_valid = skin_image(skin)
    field = vertex_field(at, np.column_stack([motion[:, :2], trust]), neutral_skin.shape)
    flow = (field[..., :2] / neutral_skin.spacing).astype(np.float32)
    landed = _remap(target_valid.astype(np.float32), flow) > 0.999
    weight = np.where(valid & landed & (field[..., 2] >= TEMPLATE_TRUST), 1.0, 0.0)
    return _remap(target, flow).astype(np.float64), weight
