"""What a rig needs before it can ever solve, checked when the pipeline is built.

A configuration that can never label the face would otherwise wait forever on "waiting for the first
labelling". What can be known from the files is checked here, each failure an
:class:`~livebridge.errors.InputError` naming what is missing and the session field to change:

- the cameras: two or more, at least two of them at distinct places (:data:`MIN_BASELINE_MM`) whose views
  overlap (a point on one camera's optical axis, :data:`VIEW_DEPTHS_MM` in front of it, inside the other's
  image and in front of it);
- the markers: enough to label (:data:`MIN_MARKERS`), :data:`MIN_HEAD_MARKERS` head markers for the head
  pose, and per solver region with muscles a face marker for every 3 of its muscles (3 coordinates each);
- the calibration: every calibrated camera is opened by a camera URL (and every camera has a calibration,
  :func:`~livebridge.runtime.build.open_session_cameras`).

What only the live frames tell (the face out of view, markers seen by one camera only) ends the pipeline
after ``[runtime] labelling_timeout_s`` instead (:class:`~livebridge.runtime.markers_front.LabellingTimeout`).
"""

from __future__ import annotations

import math

import numpy as np

from livebridge.errors import InputError
from livebridge.face.basis import REGIONS

MIN_BASELINE_MM = 5.0  # camera centres closer than this are one viewpoint: nothing to triangulate
VIEW_DEPTHS_MM = np.geomspace(100.0, 5000.0, 50)  # where along a camera's axis another camera may see
MIN_MARKERS = 4  # the first labelling matches at least 4 markers (a similarity needs 3, one to check)
MIN_HEAD_MARKERS = 3  # a rigid head pose needs 3 points


def check_cameras(cameras, session) -> None:
    """Refuse a calibrated rig that cannot triangulate (see the module docstring).

    Parameters
    ----------
    cameras : CameraGroup
        The cameras the session opened, with their calibration.
    session : Session
    """
    field = "calibration" if session.calibration is not None else "cameras.urls"
    names = ", ".join(cameras.names)
    if len(cameras) < 2:
        raise InputError(f"{len(cameras)} camera ({names}): markers are triangulated from 2 or more cameras",
                         session.path, field)
    centers = np.array([camera.center for camera in cameras.cameras])
    pairs = [(i, j) for i in range(len(centers)) for j in range(i + 1, len(centers))
             if np.linalg.norm(centers[i] - centers[j]) >= MIN_BASELINE_MM]
    if not pairs:
        raise InputError(f"the cameras ({names}) are all at one place (centres within {MIN_BASELINE_MM:g} mm): "
                         f"triangulation needs 2 cameras at different places", session.path, field)
    if not any(_views_overlap(cameras.cameras[i], cameras.cameras[j]) for i, j in pairs):
        raise InputError(f"no two of the cameras ({names}) at different places see a common point in front of "
                         f"them within {VIEW_DEPTHS_MM[-1] / 1000:g} m: their views do not overlap",
                         session.path, field)


def _views_overlap(first, second) -> bool:
    """Either camera's optical axis passes, in front of it, through the other's image in front of that one."""
    return _axis_seen(first, second) or _axis_seen(second, first)


def _axis_seen(camera, other) -> bool:
    """Points on ``camera``'s optical axis (:data:`VIEW_DEPTHS_MM` in front) that ``other`` images."""
    cam2world = np.linalg.inv(camera.world2cam)
    axis_cam = np.stack([np.zeros_like(VIEW_DEPTHS_MM), np.zeros_like(VIEW_DEPTHS_MM), VIEW_DEPTHS_MM], axis=1)
    points = axis_cam @ cam2world[:3, :3].T + cam2world[:3, 3]
    in_other = points @ other.world2cam[:3, :3].T + other.world2cam[:3, 3]
    front = in_other[:, 2] > 0
    if not front.any():
        return False
    pixels = in_other[front] @ other.matrix.T
    pixels = pixels[:, :2] / pixels[:, 2:]
    width, height = other.size
    inside = (pixels[:, 0] >= 0) & (pixels[:, 0] < width) & (pixels[:, 1] >= 0) & (pixels[:, 1] < height)
    return bool(inside.any())


def check_markers(markers, basis, session) -> None:
    """Refuse a marker set the pipeline can never label or solve with (see the module docstring).

    Parameters
    ----------
    markers : MarkerSet
    basis : Basis
    session : Session
    """
    where = (session.path, "face.markers")
    if len(markers) < MIN_MARKERS:
        raise InputError(f"{len(markers)} markers: the first labelling needs {MIN_MARKERS} or more", *where)
    head = int(markers.head_mask.sum())
    if head < MIN_HEAD_MARKERS:
        raise InputError(f"{head} head markers (role = \"head\"): the head pose needs {MIN_HEAD_MARKERS} or more",
                         *where)
    for region in REGIONS:
        muscles = int(basis.region_mask(region).sum())
        needed = math.ceil(muscles / 3)
        have = int(markers.region_mask(region).sum())
        if have < needed:
            raise InputError(f"{have} face markers in the {region} region for its {muscles} muscles: the solve "
                             f"needs {needed} or more (3 coordinates each)", *where)


def check_calibration_used(cameras, calibrated, session) -> None:
    """Refuse a calibration with cameras that no camera URL opened (the rig would run with fewer, silently).

    Parameters
    ----------
    cameras : CameraGroup
        The cameras opened.
    calibrated : CameraGroup
        The session's calibration file.
    session : Session
    """
    unused = [name for name in calibrated.names if name not in cameras.names]
    if unused:
        raise InputError(f"calibrated camera{'s' if len(unused) > 1 else ''} {', '.join(unused)} not opened by any "
                         f"camera URL (opened: {', '.join(cameras.names)}); list every calibrated camera in "
                         f"cameras.urls, or calibrate only the cameras used", session.path, "calibration")
