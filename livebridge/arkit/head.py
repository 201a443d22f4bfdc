"""Head rotation as Live Link Face carries it: yaw, pitch, roll, normalised so that 1.0 is a quarter turn.

Yaw turns about the head's up axis (+y), pitch about its right axis (+x), roll about the axis out of the
face (+z), applied in that order (intrinsic Y-X-Z), in the face model's frame (+y up, +z out of the face)
so the identity is the performer facing the phone. The normalisation (1.0 = 90 degrees, range [-1, 1]) is
the one receivers of the app's curves apply (e.g. a head bone driven by ``HeadYaw * 90`` degrees).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

QUARTER_TURN = np.pi / 2


def head_pose_from_rotation(yaw_pitch_roll: np.ndarray) -> np.ndarray:
    """``head2world``, shape (4, 4) (rotation only), from normalised yaw, pitch, roll (3,); non-finite -> identity."""
    angles = np.asarray(yaw_pitch_roll, dtype=np.float64)
    pose = np.eye(4)
    if np.isfinite(angles).all():
        pose[:3, :3] = Rotation.from_euler("YXZ", np.clip(angles, -1.0, 1.0) * QUARTER_TURN).as_matrix()
    return pose


def rotation_from_head_pose(head2world: np.ndarray | None) -> np.ndarray:
    """Normalised yaw, pitch, roll (3,), each in [-1, 1], of a head pose (4, 4); None or non-finite -> zeros."""
    if head2world is None:
        return np.zeros(3)
    rotation = np.asarray(head2world, dtype=np.float64)[:3, :3]
    if not np.isfinite(rotation).all():
        return np.zeros(3)
    # orthonormalise first: a tracked pose carries rounding (and scale from an alignment)
    angles = Rotation.from_matrix(rotation).as_euler("YXZ") / QUARTER_TURN
    return np.clip(angles, -1.0, 1.0)
