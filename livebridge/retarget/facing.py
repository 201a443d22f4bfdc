"""A point cloud's points whose normals face away from the front of the face: skin no frontal view sees.

A cloud fused from cameras all round a head, or sampled from a mesh, holds skin that no scanner in front of
the face sees: the lips' inner sides, the upper lids' folds, under the nose and the chin. Its points lie
behind the front surface, a third of them within 10 mm of it (the ICT face), where the resampling's own cut
(:data:`~livebridge.retarget.grid.FRONT_DEPTH_MM`) keeps them and mixes them into the heights and the skin
images. From the points alone they cannot be told from a pit's visible bottom (an opened mouth, the eye
openings, the nostrils): a cut by their neighbours in front took visible margins too and cost frontal scans.
Their normals tell them: that skin faces away from the front. `livebridge bench scans`'s clouds sampled over
the whole ICT mesh (60k points, seed 7; 12 % of the points face away): mean relative error of the 16 elements
0.106 with the normals ignored, 0.097 with them (the eyelids 0.255 / 0.233 -> 0.209 / 0.197; surfaces at most
0.129 -> 0.095); with normals estimated from the points (the plane through each one's 16 nearest, signed out of
the face) 0.099. At 70k points with the true normals, 0.0863, as with the truly hidden points taken out by a ray
cast on the true mesh (0.0864; 0.0940 keeping them). A frontal scan's noisy normals leave out 0.5 % of its points
(lid margins, the face's sides) and change nothing: 0.0902 either way on one 60k draw.

A file's normals may point out of the surface (most writers), into it, or either way (estimated without a
viewpoint); the front surface's points that are not seen edge-on say which (:data:`ORIENTED_SHARE`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from livebridge.geometry.transforms import apply
from livebridge.retarget.grid import crop_sphere, front_surface
from livebridge.retarget.scan import Scan

ORIENTED_SHARE = 0.8
"""The normals are taken as written when at least this share of the front surface's points face the front,
turned round when at most ``1 -`` this share do; between, they are not oriented and not used."""
FRONT_CELL_MM = 2.0
"""The front surface, for the orientation's vote: the points within a cell's width of the front-most in
their x-y cell of this width (the face frame)."""
EDGE_ON = 0.5
"""Points whose normal is this close to edge-on (``|n_z|`` below it) do not vote on the orientation."""


@dataclass(frozen=True)
class Facing:
    """What :func:`facing_points` did with a scan's normals.

    Attributes
    ----------
    orientation : str
        ``""`` (no normals, or a mesh), ``"outward"``, ``"inward"`` (turned round) or ``"unoriented"`` (not used).
    left_out : int
        Points left out as facing away from the front.
    """

    orientation: str = ""
    left_out: int = 0


def facing_points(scan: Scan, scan2face: np.ndarray, radius: float) -> tuple[Scan, Facing]:
    """A point cloud without its points whose normal faces away from the front of the face (``n_z <= 0`` in the
    face frame), when its normals are oriented; points without a normal (a zero row) are kept.

    Parameters
    ----------
    scan : Scan
        A point cloud; a mesh, or a cloud without normals, comes back as it is.
    scan2face : ndarray, shape (4, 4)
        From the scan's coordinates to the face frame (nose tip at the origin, +z out of the face).
    radius : float
        The face crop's radius in the face frame, mm: the orientation is read from the points within it.
    """
    if scan.is_mesh or scan.normals is None:
        return scan, Facing()
    points = apply(scan2face, scan.points)
    normals = scan.normals @ np.linalg.inv(scan2face[:3, :3])  # a normal turns by the inverse transpose
    length = np.linalg.norm(normals, axis=1)
    known = length > 0
    if not known.any():  # a writer's placeholder zeros
        return scan, Facing()
    facing_z = np.where(known, normals[:, 2] / np.where(known, length, 1.0), 0.0)
    voters = crop_sphere(points, np.zeros(3), radius) & known
    voters[voters] = front_surface(points[voters], FRONT_CELL_MM, FRONT_CELL_MM)
    voters &= np.abs(facing_z) >= EDGE_ON
    share = float(np.mean(facing_z[voters] > 0)) if voters.any() else 0.5
    if share >= ORIENTED_SHARE:
        orientation = "outward"
    elif share <= 1.0 - ORIENTED_SHARE:
        orientation, facing_z = "inward", -facing_z
    else:
        return scan, Facing("unoriented")
    away = known & (facing_z <= 0)
    return (scan.where(~away) if away.any() else scan), Facing(orientation, int(away.sum()))


def facing_said(facing: Facing, name: str) -> str | None:
    """What to tell of a scan's normals (``name`` the scan's file), None when it had none."""
    if facing.orientation == "unoriented":
        return (f"note: {name}'s normals point both ways (as many into the face as out of it): not used, so skin "
                "no frontal view sees (the lips' inner sides, under the nose) may show in its heights")
    if not facing.orientation:
        return None
    turned = ", which point into the face (turned round)" if facing.orientation == "inward" else ""
    return f"normals: {facing.left_out} points of {name} face away from the front by its normals{turned}: left out"
