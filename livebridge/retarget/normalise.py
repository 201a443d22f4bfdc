"""Pose and size normalisation of a scanned face onto a reference face (Erdoğdu §5.4, eqs. 5.1-5.4).

The nose tip goes to the origin; then the map from four landmarks (outer eye corners, chin middle, nose
tip) onto the reference face's: the thesis's exact affine ``T = A B^-1`` (rotation, scale and shear: the
face takes the reference's proportions), or, keeping the person's shape in millimetres, the least-squares
similarity or rigid motion of the same four landmarks. The reference's nose tip is its origin too, so a
normalised face looks along +z with +y up when the reference does.

Expression scans of one person are registered onto that person's normalised neutral face by
:func:`register_rigid` instead: the chin and the brows move with expressions, the skull does not.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from livebridge.errors import InputError
from livebridge.geometry.transforms import apply, rotation_matrix, transform_scale, umeyama

NORMALISATION_LANDMARKS = ("eye_outer_L", "eye_outer_R", "chin", "nose_tip")
"""``l_1 .. l_4`` of eq. 5.1: the landmarks the normalisation maps onto the reference face's."""
RIGID_LANDMARKS = ("eye_outer_L", "eye_outer_R", "eye_inner_L", "eye_inner_R", "nose_saddle_L", "nose_saddle_R",
                   "nose_tip")
"""Landmarks that stay on the skull through the 16 Choe-Ko expressions (the first guess of a registration)."""
METHODS = ("affine", "similarity", "rigid")
ICP_POINTS = 8000
"""At most this many scan points (evenly picked) take part in a registration."""
ICP_MIN_POINTS = 6
"""Fewer scan points than this near the face cannot fix a rigid motion (6 unknowns)."""
SIZE_RATIO = 1.25
"""Two scans of one person whose skull landmarks differ in size by more than this factor are refused: another
unit or another person. Hand-placed landmarks' noise (a few mm over the 30-100 mm between them) stays well
inside; the 16 ICT-FaceKit expressions' skull landmarks are within 0.5 % of the neutral's."""


def normalisation(landmarks: dict[str, np.ndarray], reference: dict[str, np.ndarray], method: str = "affine",
                  source=None) -> np.ndarray:
    """``scan2face`` (4, 4): the scan's nose tip to the origin, its four landmarks onto the reference's.

    Parameters
    ----------
    landmarks : dict of str to ndarray, shape (3,)
        The scan's landmarks; needs :data:`NORMALISATION_LANDMARKS`.
    reference : dict of str to ndarray, shape (3,)
        The reference face's; its nose tip is taken as its origin.
    method : {"affine", "similarity", "rigid"}
        ``affine``: the thesis's ``T = A B^-1`` (the four landmarks land exactly on the reference's).
        ``similarity`` / ``rigid``: least squares over the four, keeping the face's shape (and size).
    source : str or Path, optional
        Named in errors (the landmark file).
    """
    if method not in METHODS:
        raise InputError(f"unknown normalisation {method!r}; known: {', '.join(METHODS)}", field="normalise")
    scan = _centred(landmarks, source)
    face = _centred(reference, "the reference face")
    if method != "affine":
        transform = umeyama(scan, face, with_scale=method == "similarity")
    else:
        a, b = _columns(face), _columns(scan)
        if np.linalg.cond(b) > 1e8:
            raise InputError("the outer eye corners, chin and nose tip lie on one plane: no affine map from them",
                             source, "landmarks")
        transform = a @ np.linalg.inv(b)  # eq. 5.3
    to_origin = np.eye(4)
    to_origin[:3, 3] = -np.asarray(landmarks["nose_tip"], dtype=np.float64)
    return transform @ to_origin


def _centred(landmarks, source) -> np.ndarray:
    missing = [name for name in NORMALISATION_LANDMARKS if name not in landmarks]
    if missing:
        raise InputError(f"normalisation needs the landmarks {', '.join(NORMALISATION_LANDMARKS)}; missing: "
                         f"{', '.join(missing)}", source, "landmarks")
    points = np.array([landmarks[name] for name in NORMALISATION_LANDMARKS], dtype=np.float64)
    centred = points - points[-1]
    spread = np.linalg.svd(centred, compute_uv=False)
    if not spread[1] > 1e-3 * spread[0]:  # on one line (or one point): no rotation is fixed by them
        raise InputError(f"the landmarks {', '.join(NORMALISATION_LANDMARKS)} coincide or lie on one line "
                         f"(spread {spread[0]:.3g} by {spread[1]:.3g} mm): no pose from them", source, "landmarks")
    return centred


def _columns(centred: np.ndarray) -> np.ndarray:
    """Eq. 5.1/5.2: ``[[p_1 p_2 p_3 0], [1 1 1 1]]`` of nose-tip-centred landmarks (n, 3) -> (4, 4)."""
    out = np.zeros((4, 4))
    out[:3, :3] = centred[:3].T
    out[3] = 1.0
    return out


def transform_landmarks(scan2face: np.ndarray, landmarks: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Each landmark carried by ``scan2face`` (4, 4)."""
    names = list(landmarks)
    moved = apply(scan2face, np.array([landmarks[name] for name in names], dtype=np.float64))
    return dict(zip(names, moved))


def register_rigid(points: np.ndarray, landmarks: dict[str, np.ndarray], target_points: np.ndarray,
                   target_normals: np.ndarray, target_landmarks: dict[str, np.ndarray], radius: float,
                   iterations: int = 30, keep: float = 0.6, source=None,
                   first_guess: np.ndarray | None = None) -> np.ndarray:
    """``scan2face`` (4, 4): the rigid motion putting a scan of the same person onto a normalised face.

    First guess: Kabsch on :data:`RIGID_LANDMARKS` (those both sides name). Then trimmed point-to-plane ICP
    against the face's surface points: each round keeps the ``keep`` fraction of scan points nearest the
    face, so the parts an expression moves (a brow, the jaw) do not pull the head along; only scan points
    within ``radius`` of the face's nose tip (the origin) take part.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        The scan.
    landmarks : dict of str to ndarray, shape (3,)
        The scan's landmarks.
    target_points, target_normals : ndarray, shape (m, 3)
        The normalised face's surface points and unit normals.
    target_landmarks : dict of str to ndarray, shape (3,)
    radius : float
        mm.
    first_guess : ndarray, shape (4, 4), optional
        :func:`landmark_rigid` of these landmarks when already computed.
    """
    transform = landmark_rigid(landmarks, target_landmarks, source) if first_guess is None else first_guess
    tree = cKDTree(target_points)
    points = np.asarray(points, dtype=np.float64)[::max(1, len(points) // ICP_POINTS)]
    for _ in range(iterations):
        moved = apply(transform, points)
        near = np.linalg.norm(moved, axis=1) < radius
        if near.sum() < ICP_MIN_POINTS:
            raise InputError(f"{int(near.sum())} of its points lie within {radius:.3g} mm of the neutral's nose tip "
                             "once its landmarks are put on the neutral's: the scan does not overlap the face",
                             source, "points")
        distance, nearest = tree.query(moved[near])
        trimmed = distance <= np.quantile(distance, keep)
        step = _point_to_plane_step(moved[near][trimmed], target_points[nearest[trimmed]],
                                    target_normals[nearest[trimmed]])
        transform = step @ transform
        if np.abs(step[:3, 3]).max() < 1e-5 and np.abs(step[:3, :3] - np.eye(3)).max() < 1e-7:
            break
    return transform


def landmark_rigid(landmarks: dict[str, np.ndarray], target_landmarks: dict[str, np.ndarray], source=None
                   ) -> np.ndarray:
    """The rigid motion (4, 4) putting a scan's :data:`RIGID_LANDMARKS` (those both sides name, 3 or more) onto
    the normalised face's (Kabsch): :func:`register_rigid`'s first guess. A scan whose landmarks are not the
    face's size (:data:`SIZE_RATIO`) is refused, naming ``source``."""
    shared = [name for name in RIGID_LANDMARKS if name in landmarks and name in target_landmarks]
    if len(shared) < 3:
        raise InputError(f"registering a scan needs 3 or more of {', '.join(RIGID_LANDMARKS)}, got "
                         f"{', '.join(shared) or 'none'}", source, "landmarks")
    own, theirs = np.array([landmarks[n] for n in shared]), np.array([target_landmarks[n] for n in shared])
    # a rigid motion cannot undo a change of size: a scan in other units (or of another person) registers
    # nowhere near the face, so say so before the registration lands it there
    size = abs(transform_scale(umeyama(own, theirs, with_scale=True)))
    if not 1 / SIZE_RATIO <= size <= SIZE_RATIO:
        raise InputError(f"its landmarks {', '.join(shared)} are {1 / size:.3g} times as far apart as the neutral's "
                         "(scans of one person, in one unit, are the same size: --units applies to every scan)",
                         source, "landmarks")
    return umeyama(own, theirs, with_scale=False)


def _point_to_plane_step(source: np.ndarray, target: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """The small rigid motion (4, 4) minimising ``sum ((R p + t - q) . n)^2`` (linearised rotation)."""
    centre = source.mean(axis=0)
    p = source - centre
    rows = np.hstack([np.cross(p, normals), normals])  # (k, 6): d/d(omega, t)
    rhs = np.einsum("kd,kd->k", target - source, normals)
    omega_t = np.linalg.solve(rows.T @ rows, rows.T @ rhs)
    step = np.eye(4)
    step[:3, :3] = rotation_matrix(omega_t[:3])
    step[:3, 3] = omega_t[3:] + centre - step[:3, :3] @ centre
    return step
