"""Which face sites a calibrated camera rig sees well at the neutral pose: the constraint of a rig-aware marker
layout (:mod:`~livebridge.face.layout`), and where the rig says the face is (:func:`facing_pose`).

The visibility model is :mod:`livebridge.geometry.visibility`'s, by which the simulated rig draws markers too.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.geometry.transforms import apply
from livebridge.geometry.visibility import depth_cell_mm, sees

if TYPE_CHECKING:
    from livebridge.calibration.cameras import Camera, CameraGroup

MAX_VIEW_DEG = 75.0  # a camera finds a marker whose normal is within this angle of it (more oblique: a smear)
VIEW_MARGIN_DEG = 10.0  # a seated performer turns the head ~6 deg per axis and moves it a few cm: keep this spare


@dataclass(frozen=True, eq=False)
class RigVisibility:
    """Which face sites a camera rig sees well: the constraint of a rig-aware layout.

    A camera sees a site, at the neutral pose placed in the cameras' world by ``model2world``, when the
    site is in front of the camera and inside its image, the face surface is not in front of it, and its
    normal is within ``max_view_deg - margin_deg`` of the direction to the camera. The margin keeps the
    site seen while the head turns and moves. This is the visibility model of
    :mod:`livebridge.geometry.visibility`, by which the simulated rig draws markers too.

    Attributes
    ----------
    cameras : CameraGroup
        The calibrated rig (mm).
    min_views : int
        Cameras that must see every marker: 2 to triangulate it, and each one more is a spare for when
        the marker is occluded in another view.
    max_view_deg : float
        Largest angle between a marker's normal and its direction to a camera at which the camera finds it.
    margin_deg : float
        Taken off ``max_view_deg`` at the neutral pose, for head motion.
    model2world : ndarray, shape (4, 4), optional
        Rigid pose of the neutral face in the cameras' world frame; default :func:`facing_pose`
        (where the cameras' optical axes meet, facing them).
    """

    cameras: CameraGroup
    min_views: int = 3
    max_view_deg: float = MAX_VIEW_DEG
    margin_deg: float = VIEW_MARGIN_DEG
    model2world: np.ndarray | None = None

    def __post_init__(self):
        n_cams = len(self.cameras)
        if n_cams == 0:
            raise InputError("the rig has no cameras", field="cameras")
        if not 1 <= self.min_views <= n_cams:
            raise InputError(f"must be between 1 and the rig's {n_cams} cameras, got {self.min_views}",
                             field="min_views")
        if not 0 <= self.margin_deg < self.max_view_deg <= 90:
            raise InputError(f"need 0 <= margin_deg < max_view_deg <= 90, got margin_deg {self.margin_deg} and "
                             f"max_view_deg {self.max_view_deg}", field="max_view_deg")
        if self.model2world is not None:
            pose = np.asarray(self.model2world, dtype=np.float64)
            rigid = (pose.shape == (4, 4) and np.allclose(pose[3], [0, 0, 0, 1])
                     and np.allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-6)
                     and np.linalg.det(pose[:3, :3]) > 0)
            if not rigid:
                raise InputError("must be a rigid transform (rotation and translation), shape (4, 4)",
                                 field="model2world")
            object.__setattr__(self, "model2world", pose)

    @property
    def view_limit_deg(self) -> float:
        """Largest angle (deg) between a site's normal and a camera that counts as seen at the neutral pose."""
        return self.max_view_deg - self.margin_deg

    def describe(self) -> str:
        """The constraint in words, for messages."""
        return (f"seen by at least {self.min_views} of the {len(self.cameras)} cameras (normal within "
                f"{self.view_limit_deg:g} deg of the camera: {self.max_view_deg:g} less {self.margin_deg:g} for "
                f"head motion)")

    def seen(self, basis: Basis, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Which cameras see each site of the neutral face, shape (n_cams, n_sites) bool.

        Parameters
        ----------
        basis : Basis
            Its neutral mesh is the surface that can hide a site.
        points : ndarray, shape (n_sites, 3)
            Sites on the neutral face, model frame, mm.
        normals : ndarray, shape (n_sites, 3)
            Their unit surface normals, model frame.
        """
        model2world = facing_pose(basis, self.cameras) if self.model2world is None else self.model2world
        rotation = model2world[:3, :3]
        points, normals, vertices = apply(model2world, points), normals @ rotation.T, apply(model2world, basis.neutral)
        cell_mm = depth_cell_mm(basis.neutral, basis.triangles)
        cos_limit = np.cos(np.deg2rad(self.view_limit_deg))
        return np.stack([_seen_by(camera, points, normals, cos_limit, vertices, cell_mm)
                         for camera in self.cameras.cameras])


def optical_axes_meet(cameras: CameraGroup) -> np.ndarray:
    """The point nearest every camera's optical axis (least squares): where the rig looks, mm, shape (3,).

    Raises
    ------
    InputError
        When the axes do not meet in front of the cameras (one camera, parallel axes).
    """
    world2cam = np.stack([camera.world2cam for camera in cameras.cameras])
    centers = np.stack([camera.center for camera in cameras.cameras])
    axes = world2cam[:, 2, :3]  # camera z (forward) in the world
    projectors = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]  # onto the plane across each axis
    normal_matrix = projectors.sum(axis=0)
    if np.linalg.eigvalsh(normal_matrix)[0] < 1e-3 * len(axes):
        raise InputError("cannot place the face: the cameras' optical axes do not converge (one camera, or "
                         "parallel axes); give the face pose (model2world)", field="cameras")
    target = np.linalg.solve(normal_matrix, np.einsum("kij,kj->i", projectors, centers))
    if (np.einsum("kd,kd->k", target - centers, axes) <= 0).any():
        raise InputError("cannot place the face: the cameras' optical axes meet behind a camera; give the face "
                         "pose (model2world)", field="cameras")
    return target


def facing_pose(basis: Basis, cameras: CameraGroup) -> np.ndarray:
    """``model2world`` of a neutral face that sits where the cameras look, facing them, upright as they stand.

    The face centre (middle of the neutral bounding box) goes to :func:`optical_axes_meet`, the face's +z
    points at the cameras' mean centre and its +y along the cameras' mean up direction: a performer seated
    in front of the rig. Calibration files put the world frame on the board, so this is where the rig
    says the face is.

    Returns
    -------
    ndarray, shape (4, 4)

    Raises
    ------
    InputError
        When the axes do not meet in front of the cameras, or the cameras have no common front or up.
    """
    target = optical_axes_meet(cameras)
    centers = np.stack([camera.center for camera in cameras.cameras])
    forward = centers.mean(axis=0) - target
    up = -np.stack([camera.world2cam[1, :3] for camera in cameras.cameras]).mean(axis=0)  # camera -y: up
    up -= (up @ forward) / max(forward @ forward, 1e-300) * forward
    if np.linalg.norm(forward) < 1e-6 or np.linalg.norm(up) < 1e-6:
        raise InputError("cannot place the face: the cameras surround it (no front or no up); give the face "
                         "pose (model2world)", field="cameras")
    forward, up = forward / np.linalg.norm(forward), up / np.linalg.norm(up)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([np.cross(up, forward), up, forward], axis=1)
    pose[:3, 3] = target - pose[:3, :3] @ (0.5 * (basis.neutral.min(axis=0) + basis.neutral.max(axis=0)))
    return pose


def _seen_by(camera: Camera, points: np.ndarray, normals: np.ndarray, cos_limit: float, vertices: np.ndarray,
             cell_mm: float) -> np.ndarray:
    """Sites ``camera`` sees (:func:`livebridge.geometry.visibility.sees`).

    Parameters
    ----------
    points, normals : ndarray, shape (n_sites, 3)
        World frame.
    vertices : ndarray, shape (n_vertices, 3)
        The face surface, world frame.
    cell_mm : float
        Cell of the depth test at the face.

    Returns
    -------
    ndarray of bool, shape (n_sites,)
    """
    to_camera = camera.center - points
    cosine = np.einsum("nd,nd->n", normals, to_camera) / np.linalg.norm(to_camera, axis=1)
    world2cam = camera.world2cam
    return sees(apply(world2cam, points), cosine, camera.project(points), camera.size, cos_limit,
                apply(world2cam, vertices), cell_mm)
