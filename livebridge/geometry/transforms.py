"""Homogeneous transforms, rotation vectors, similarity fits between point sets, and cameras aimed at a point.

Transforms are homogeneous ``(4, 4)`` matrices named by their frames, ``a2b`` maps frame ``a`` into frame
``b`` (``cam2world``, ``head2world``, ``capture2model``); points are row vectors ``(..., 3)``.

:func:`umeyama` is the least-squares similarity (or rigid) transform of Umeyama (1991), the Kabsch
solution with optional scale. :func:`rotation_matrix` and :func:`rotation_vector` are Rodrigues' formula
and its inverse, compiled so that per-frame code (the tracker's motion model) and least-squares residuals
(bundle adjustment) can call them; code that runs once (building cameras) may as well use OpenCV's
``cv2.Rodrigues``, which gives the same rotations.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


def apply(a2b: np.ndarray, points_a: np.ndarray) -> np.ndarray:
    """Points of frame ``a`` in frame ``b``; NaN stays NaN.

    Parameters
    ----------
    a2b : ndarray, shape (4, 4) or (n, 4, 4)
        One transform, or one per set of points.
    points_a : ndarray, shape (..., 3) for one transform, (n, k, 3) for ``n`` transforms

    Returns
    -------
    ndarray, the shape of ``points_a``
    """
    points_a = np.asarray(points_a, dtype=np.float64)
    if a2b.ndim == 2:
        return points_a @ a2b[:3, :3].T + a2b[:3, 3]
    return np.einsum("nij,nkj->nki", a2b[:, :3, :3], points_a) + a2b[:, None, :3, 3]


def invert(a2b: np.ndarray) -> np.ndarray:
    """``b2a`` of a transform ``a2b`` (4, 4) (rigid, similarity or any affine)."""
    return np.linalg.inv(a2b)


def transform_scale(a2b: np.ndarray) -> float:
    """The uniform scale of a similarity transform ``(4, 4)``."""
    return float(np.cbrt(np.linalg.det(a2b[:3, :3])))


@njit(cache=True, nogil=True)
def rotation_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix ``(3, 3)`` of a rotation vector ``(3,)`` (Rodrigues' formula; first order below 1e-12 rad)."""
    angle = np.sqrt(rotvec[0] ** 2 + rotvec[1] ** 2 + rotvec[2] ** 2)
    if angle < 1e-12:
        rx, ry, rz = rotvec[0], rotvec[1], rotvec[2]
        return np.array([[1.0, -rz, ry], [rz, 1.0, -rx], [-ry, rx, 1.0]])
    kx, ky, kz = rotvec[0] / angle, rotvec[1] / angle, rotvec[2] / angle
    cross = np.array([[0.0, -kz, ky], [kz, 0.0, -kx], [-ky, kx, 0.0]])
    return np.eye(3) + np.sin(angle) * cross + (1.0 - np.cos(angle)) * (cross @ cross)


@njit(cache=True, nogil=True)
def rotation_matrices(rotvecs: np.ndarray) -> np.ndarray:
    """:func:`rotation_matrix` of each row of ``rotvecs (n, 3)``, shape (n, 3, 3)."""
    out = np.empty((rotvecs.shape[0], 3, 3))
    for i in range(rotvecs.shape[0]):
        out[i] = rotation_matrix(rotvecs[i])
    return out


@njit(cache=True, nogil=True)
def rotation_vector(rotation: np.ndarray) -> np.ndarray:
    """Rotation vector ``(3,)`` of a rotation matrix ``(3, 3)``, angle in ``[0, pi]``."""
    axis = np.array([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0], rotation[1, 0] - rotation[0, 1]])
    sine = 0.5 * np.sqrt(axis[0] ** 2 + axis[1] ** 2 + axis[2] ** 2)  # axis = 2 sin(angle) k
    cosine = 0.5 * (rotation[0, 0] + rotation[1, 1] + rotation[2, 2] - 1.0)
    angle = math.atan2(sine, cosine)  # well conditioned at every angle, unlike arccos near 0 and pi
    if cosine > -0.9:
        if sine < 1e-7:
            return axis / 2.0  # first order: R ~ I + [w]x
        return axis * (angle / (2.0 * sine))
    # near a half turn sin(angle) ~ 0 loses the axis; the symmetric part is cos I + (1 - cos) k k^T
    outer = (0.5 * (rotation + rotation.T) - cosine * np.eye(3)) / (1.0 - cosine)
    i = np.argmax(np.diag(outer))
    unit = outer[i] / np.sqrt(outer[i, i])
    if unit @ axis < 0:
        unit = -unit
    return unit * angle


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


def look_at(center: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 1.0, 0.0)) -> np.ndarray:
    """``world2cam`` (4, 4) of an OpenCV camera at ``center`` (3,) looking at ``target`` (3,).

    OpenCV camera axes: x right, y down, z forward; ``up`` (3,) is the world direction that appears upwards.
    """
    center, target, up = (np.asarray(a, dtype=np.float64) for a in (center, target, up))
    forward = target - center
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    world2cam = np.eye(4)
    world2cam[:3, :3] = np.stack([right, down, forward])  # rows: camera axes in world coordinates
    world2cam[:3, 3] = -world2cam[:3, :3] @ center
    return world2cam
