"""Calibrated cameras: pinhole model with distortion, and a group of them.

Conventions (aniposelib-compatible): ``rotation`` is a Rodrigues vector and
``translation`` a vector in mm, together the ``world2cam`` transform
``X_cam = R @ X_world + t``. Arrays are camera-first and NaN means "not seen".
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np


@dataclass(frozen=True, eq=False)
class Camera:
    """One calibrated camera.

    Attributes
    ----------
    name : str
    size : tuple of int
        Image ``(width, height)`` in pixels.
    matrix : ndarray, shape (3, 3)
        Intrinsic matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``.
    distortions : ndarray, shape (5,)
        OpenCV ``(k1, k2, p1, p2, k3)``, or ``(k1, k2, k3, k4)`` when ``fisheye``.
    rotation : ndarray, shape (3,)
        Rodrigues vector of ``world2cam``.
    translation : ndarray, shape (3,)
        Translation of ``world2cam`` in mm.
    fisheye : bool
    """

    name: str
    size: tuple[int, int]
    matrix: np.ndarray
    distortions: np.ndarray
    rotation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    fisheye: bool = False

    def __post_init__(self):
        for name in ("matrix", "distortions", "rotation", "translation"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.float64))
        object.__setattr__(self, "size", (int(self.size[0]), int(self.size[1])))

    @property
    def world2cam(self) -> np.ndarray:
        """Homogeneous world-to-camera transform, shape (4, 4)."""
        transform = np.eye(4)
        transform[:3, :3] = cv2.Rodrigues(self.rotation)[0]
        transform[:3, 3] = self.translation
        return transform

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates (mm), shape (3,)."""
        rotation = cv2.Rodrigues(self.rotation)[0]
        return -rotation.T @ self.translation

    @property
    def projection(self) -> np.ndarray:
        """Projection matrix ``K [R | t]`` for undistorted pixels, shape (3, 4)."""
        return self.matrix @ self.world2cam[:3]

    def project(self, points_3d: np.ndarray) -> np.ndarray:
        """Distorted pixel coordinates of world points.

        Parameters
        ----------
        points_3d : ndarray, shape (n_points, 3)

        Returns
        -------
        ndarray, shape (n_points, 2); NaN rows stay NaN.
        """
        return _on_finite_rows(np.asarray(points_3d, dtype=np.float64).reshape(-1, 3), self._project_finite)

    def _project_finite(self, points_3d: np.ndarray) -> np.ndarray:
        objects = points_3d.reshape(-1, 1, 3)
        if self.fisheye:
            pixels, _ = cv2.fisheye.projectPoints(objects, self.rotation, self.translation, self.matrix,
                                                  self.distortions[:4])
        else:
            pixels, _ = cv2.projectPoints(objects, self.rotation, self.translation, self.matrix, self.distortions)
        return pixels.reshape(-1, 2)

    def undistort_points(self, points_2d: np.ndarray) -> np.ndarray:
        """Distorted pixels to undistorted pixels (same intrinsic matrix).

        Parameters
        ----------
        points_2d : ndarray, shape (n_points, 2)

        Returns
        -------
        ndarray, shape (n_points, 2); NaN rows stay NaN.
        """
        return self.normalised_rays(points_2d) * self.matrix[[0, 1], [0, 1]] + self.matrix[:2, 2]

    def normalised_rays(self, points_2d: np.ndarray) -> np.ndarray:
        """Distorted pixels to undistorted normalised image coordinates ``(x/z, y/z)``.

        Parameters
        ----------
        points_2d : ndarray, shape (n_points, 2)

        Returns
        -------
        ndarray, shape (n_points, 2); NaN rows stay NaN.
        """
        return _on_finite_rows(np.asarray(points_2d, dtype=np.float64).reshape(-1, 2),
                               lambda finite: undistort_normalised(finite, self.matrix, self.distortions, self.fisheye))


def _on_finite_rows(points: np.ndarray, function) -> np.ndarray:
    """``function(finite rows) -> (n_finite, 2)`` on the rows of ``points`` (n, d) that are all finite.

    Returns
    -------
    ndarray, shape (n, 2); rows with a NaN (or inf) are NaN.
    """
    out = np.full((len(points), 2), np.nan)
    valid = np.isfinite(points).all(axis=1)
    if valid.any():
        out[valid] = function(points[valid])
    return out


_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


def undistort_normalised(points_2d: np.ndarray, matrix: np.ndarray, distortions: np.ndarray,
                         fisheye: bool = False) -> np.ndarray:
    """Invert the lens model to high precision (OpenCV's default stops after 5 iterations).

    Parameters
    ----------
    points_2d : ndarray, shape (n_points, 2)
        Distorted pixels, all finite.
    matrix : ndarray, shape (3, 3)
    distortions : ndarray, shape (5,) or (4,) for fisheye

    Returns
    -------
    ndarray, shape (n_points, 2): undistorted normalised coordinates.
    """
    pixels = np.asarray(points_2d, dtype=np.float64).reshape(-1, 1, 2)
    matrix = np.asarray(matrix, dtype=np.float64)
    distortions = np.asarray(distortions, dtype=np.float64)
    if fisheye:
        result = cv2.fisheye.undistortPoints(pixels, matrix, distortions[:4], criteria=_UNDISTORT_CRITERIA)
    elif hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
        result = cv2.undistortPointsIter(pixels, matrix, distortions, None, None, _UNDISTORT_CRITERIA)
    else:  # OpenCV 5: undistortPoints takes the criteria
        result = cv2.undistortPoints(pixels, matrix, distortions, None, np.eye(3), np.eye(3), _UNDISTORT_CRITERIA)
    return result.reshape(-1, 2)


@dataclass(frozen=True, eq=False)
class CameraGroup:
    """Several calibrated cameras sharing one world frame (mm)."""

    cameras: tuple[Camera, ...]

    def __post_init__(self):
        object.__setattr__(self, "cameras", tuple(self.cameras))

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(camera.name for camera in self.cameras)

    def project(self, points_3d: np.ndarray) -> np.ndarray:
        """Distorted pixels of world points in every camera.

        Parameters
        ----------
        points_3d : ndarray, shape (n_points, 3)

        Returns
        -------
        ndarray, shape (n_cams, n_points, 2)
        """
        return np.stack([camera.project(points_3d) for camera in self.cameras])

    def undistort_points(self, points_2d: np.ndarray) -> np.ndarray:
        """Undistort pixels per camera: ``(n_cams, n_points, 2)`` in and out."""
        return np.stack([camera.undistort_points(p) for camera, p in zip(self.cameras, points_2d)])

    def reprojection_error(self, points_3d: np.ndarray, points_2d: np.ndarray) -> np.ndarray:
        """Pixel distance between projections and observations, shape (n_cams, n_points); NaN where unseen."""
        return np.linalg.norm(self.project(points_3d) - points_2d, axis=-1)
