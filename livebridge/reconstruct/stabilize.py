"""Rigid and similarity transforms between point sets, and the head pose from rigid head markers.

:func:`umeyama` is the least-squares similarity (or rigid) transform of Umeyama (1991), the
Kabsch solution with optional scale. Transforms are homogeneous ``(4, 4)`` matrices named by their
frames (``src2dst``).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _umeyama(src: np.ndarray, dst: np.ndarray, weights: np.ndarray, with_scale: bool) -> np.ndarray:
    """:func:`umeyama` on float64 arrays ``(n, 3)``, ``(n, 3)``, ``(n,)`` (compiled: called every frame)."""
    valid = np.empty(len(src), np.bool_)
    total = 0.0
    for i in range(len(src)):
        valid[i] = weights[i] > 0 and np.isfinite(src[i]).all() and np.isfinite(dst[i]).all()
        total += weights[i] if valid[i] else 0.0
    if valid.sum() < 3:
        return np.full((4, 4), np.nan)
    src_mean, dst_mean = np.zeros(3), np.zeros(3)
    for i in range(len(src)):
        if valid[i]:
            src_mean += weights[i] / total * src[i]
            dst_mean += weights[i] / total * dst[i]
    covariance = np.zeros((3, 3))
    variance = 0.0
    for i in range(len(src)):
        if valid[i]:
            w = weights[i] / total
            a, b = src[i] - src_mean, dst[i] - dst_mean
            covariance += w * np.outer(b, a)
            variance += w * (a @ a)
    u, sigma, vt = np.linalg.svd(covariance)
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2] = -1.0
    rotation = (u * sign) @ vt
    scale = 1.0
    if with_scale and variance > 0:
        scale = (sigma * sign).sum() / variance
    transform = np.eye(4)
    transform[:3, :3] = scale * rotation
    transform[:3, 3] = dst_mean - scale * rotation @ src_mean
    return transform


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True, weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares transform ``src2dst`` with ``dst ≈ s R src + t``.

    Parameters
    ----------
    src, dst : ndarray, shape (n_points, 3)
        Corresponding points; rows with a NaN in either are ignored. Needs 3 non-collinear pairs.
    with_scale : bool
        Solve the scale ``s`` too (similarity); otherwise ``s = 1`` (rigid, Kabsch).
    weights : ndarray, shape (n_points,), optional
        Non-negative weight per pair.

    Returns
    -------
    ndarray, shape (4, 4)
        ``[[s R, t], [0, 1]]``; all NaN when fewer than 3 valid pairs.
    """
    src = np.ascontiguousarray(src, dtype=np.float64).reshape(-1, 3)
    dst = np.ascontiguousarray(dst, dtype=np.float64).reshape(-1, 3)
    w = np.ones(len(src)) if weights is None else np.ascontiguousarray(weights, dtype=np.float64)
    return _umeyama(src, dst, w, bool(with_scale))


def apply(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a homogeneous transform ``(4, 4)`` to points ``(..., 3)``; NaN stays NaN."""
    points = np.asarray(points, dtype=np.float64)
    return points @ transform[:3, :3].T + transform[:3, 3]


def transform_scale(transform: np.ndarray) -> float:
    """The uniform scale of a similarity transform ``(4, 4)``."""
    return float(np.cbrt(np.linalg.det(transform[:3, :3])))


def head_pose(reference_model: np.ndarray, points_world: np.ndarray, model_scale: float = 1.0,
              weights: np.ndarray | None = None) -> np.ndarray:
    """Head pose ``head2world`` from rigid head markers (Kabsch, scale fixed).

    The head frame is the face model's frame. ``head2world`` maps model coordinates into the
    capture world; it is rigid when capture and model share a scale, otherwise it carries the
    fixed ``model_scale`` (world mm per model mm) found by the coordinate alignment.

    Parameters
    ----------
    reference_model : ndarray, shape (n_head, 3)
        Head-marker positions in the model (head) frame.
    points_world : ndarray, shape (n_head, 3)
        Their positions this frame in the world frame; NaN where not seen.
    model_scale : float
        World millimetres per model millimetre.
    weights : ndarray, shape (n_head,), optional
        Non-negative weight per marker (default: all 1).

    Returns
    -------
    ndarray, shape (4, 4); all NaN with fewer than 3 markers seen.
    """
    reference = np.asarray(reference_model, dtype=np.float64) * model_scale
    world = np.ascontiguousarray(points_world, dtype=np.float64)
    w = np.ones(len(world)) if weights is None else np.ascontiguousarray(weights, dtype=np.float64)
    rigid = _umeyama(reference, world, w, False)
    rigid[:3, :3] *= model_scale  # R diag(s, s, s): the model's scale on the rotation's columns
    return rigid
