"""Rigid and similarity transforms between point sets, and the head pose from rigid head markers.

:func:`umeyama` is the least-squares similarity (or rigid) transform of Umeyama (1991), the
Kabsch solution with optional scale. Transforms are homogeneous ``(4, 4)`` matrices named by their
frames (``src2dst``).
"""

from __future__ import annotations

import numpy as np


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
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    valid = np.isfinite(src).all(axis=1) & np.isfinite(dst).all(axis=1)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    valid &= w > 0
    if valid.sum() < 3:
        return np.full((4, 4), np.nan)
    src, dst, w = src[valid], dst[valid], w[valid] / w[valid].sum()
    src_mean, dst_mean = w @ src, w @ dst
    src_c, dst_c = src - src_mean, dst - dst_mean
    covariance = (dst_c * w[:, None]).T @ src_c  # (3, 3)
    u, sigma, vt = np.linalg.svd(covariance)
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2] = -1.0
    rotation = (u * sign) @ vt
    scale = 1.0
    if with_scale:
        variance = float(w @ (src_c**2).sum(axis=1))
        scale = float((sigma * sign).sum() / variance) if variance > 0 else 1.0
    transform = np.eye(4)
    transform[:3, :3] = scale * rotation
    transform[:3, 3] = dst_mean - scale * rotation @ src_mean
    return transform


def apply(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a homogeneous transform ``(4, 4)`` to points ``(..., 3)``; NaN stays NaN."""
    points = np.asarray(points, dtype=np.float64)
    return points @ transform[:3, :3].T + transform[:3, 3]


def transform_scale(transform: np.ndarray) -> float:
    """The uniform scale of a similarity transform ``(4, 4)``."""
    return float(np.cbrt(np.linalg.det(transform[:3, :3])))


def head_pose(reference_model: np.ndarray, points_world: np.ndarray, model_scale: float = 1.0) -> np.ndarray:
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

    Returns
    -------
    ndarray, shape (4, 4); all NaN with fewer than 3 markers seen.
    """
    rigid = umeyama(np.asarray(reference_model) * model_scale, points_world, with_scale=False)
    return rigid @ np.diag([model_scale, model_scale, model_scale, 1.0])
