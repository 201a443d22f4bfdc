"""Closed parts inside a target head (teeth, eyeballs) move with the bone they sit on, not with the skin.

A character's head often carries, besides its skin, separate closed meshes inside it: teeth, eyeballs, a tongue.
No face-skin basis holds their motion, and taking the motion of the skin nearest them is wrong: the upper teeth
would follow the upper lip, an eyeball would be squashed by a closing lid. A tooth or an eye moves as its bone
does: with the skull (not at all, in a face's actuation basis) or with the jaw.

Which parts: connected components of the target that hold no landmark, have no open edge (a closed surface) and
lie behind the face's front (:data:`BEHIND`). Open parts (eyelashes, the mouth's inner bag, eye blend meshes) are
attached to the skin at their rim and keep the skin's motion, as do closed shells on the outside of the skin.
Which bone: a part whose centre lies below the bite's plane (:data:`BITE_TILT`) is on the jaw, any other on the
skull. Only the elements that turn the jaw (:data:`JAW_MUSCLES`) move the jaw's parts, by the rigid motion (no
scale) that best fits the element's motion of the skin around the chin (:data:`CHIN_REACH`); soft tissue lags
the bone, so this under-reads a jaw's swing (ICT's ``jawOpen``: 20.6 degrees read off the skin for its teeth's
25.3). In every other element the jaw's parts stay still: a smile, a chin raiser or a lip press moves the chin's
skin, not the bone under it (read off that skin, ICT's lower teeth moved 3.3 mm RMS in its basis's smile, 3.5 mm in
the thesis's AU12 and 5.0 mm in AU17, where ICT's own ``mouthSmile_L`` keeps them still).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from livebridge.face.meshio import rim_vertices

CHIN_REACH = 0.2
"""The jaw's motion is read off the skin within this fraction of the face's height (eye corners' middle to
chin) of the chin landmark."""
BEHIND = 0.02
"""A closed part is on a bone when its vertices lie, in the median, more than this fraction of the face's
height behind the face's front (eyes and mouth closed over); nearer, or in front (a brow or beard shell, glasses),
it keeps the skin's motion."""
BITE_TILT = 12.0
"""Degrees the plane between the jaw's parts and the skull's rises towards the back of the head, from the plane
through the lips' meeting point square to the chin-to-eyes line: the line of the bite. Measured on ICT's head,
where it leaves each tooth's centre 6-7 mm from the plane."""
JAW_MUSCLES = ("jaw",)
"""The muscles that turn the jaw (the Choe-Ko basis's jaw opening). A basis naming none of them has every element
move the jaw's parts as its chin's skin moves."""
FRAME_LANDMARKS = ("eye_outer_L", "eye_outer_R", "chin", "nose_tip", "lip_upper_inner", "lip_lower_inner")
"""The landmarks that place the face, its front and the jaw; without them the parts keep the skin's motion."""


@dataclass(frozen=True)
class BoneParts:
    """The target's vertices on each bone.

    Attributes
    ----------
    skull, jaw : ndarray of bool, shape (n_vertices,)
        Vertices of closed inner parts on the skull (still) and on the jaw.
    chin : ndarray of bool, shape (n_vertices,)
        The skin the jaw's motion is read from.
    """

    skull: np.ndarray
    jaw: np.ndarray
    chin: np.ndarray

    @property
    def any(self) -> bool:
        return bool(self.skull.any() or self.jaw.any())


def bone_parts(vertices: np.ndarray, triangles: np.ndarray, landmarks) -> BoneParts:
    """Find the closed parts inside the head and the bone each is on.

    Parameters
    ----------
    vertices : ndarray, shape (n_vertices, 3)
    triangles : ndarray of int, shape (n_triangles, 3)
    landmarks : LandmarkSet
        On this mesh; the components holding a landmark are its skin.
    """
    n = len(vertices)
    none = np.zeros(n, dtype=bool)
    at = landmarks.as_dict(vertices, triangles)
    if any(name not in at for name in FRAME_LANDMARKS):
        return BoneParts(none, none, none)
    label = _components(triangles, n)
    skin = np.isin(label, label[np.unique(triangles[landmarks.triangles])])
    closed = ~np.isin(label, label[rim_vertices(triangles)])
    candidates = np.unique(label[~skin & closed & (np.bincount(triangles.ravel(), minlength=n) > 0)])
    if not len(candidates):
        return BoneParts(none, none, none)
    axes, height = _face_axes(at)
    skin_triangles = triangles[skin[triangles].all(axis=1)]
    off_skin = _behind_face(vertices, skin_triangles, label, candidates, axes, BEHIND * height)
    below = np.array([_below_bite(vertices[label == c].mean(axis=0), at, axes) for c in off_skin], dtype=bool)
    chin = skin & (np.linalg.norm(vertices - at["chin"], axis=1) < CHIN_REACH * height)
    return BoneParts(np.isin(label, off_skin[~below]), np.isin(label, off_skin[below]), chin)


def on_bones(elements: np.ndarray, vertices: np.ndarray, parts: BoneParts, turns_jaw) -> np.ndarray:
    """``elements`` (k, n_vertices, 3) with the skull's parts still and the jaw's parts moved rigidly as the
    chin's skin moves in the elements that turn the jaw (``turns_jaw``, k bools; see :func:`jaw_turners`), still
    in the others (a new array)."""
    from livebridge.geometry.transforms import apply, umeyama

    out = np.array(elements, dtype=np.float64, copy=True)
    out[:, parts.skull | parts.jaw] = 0.0
    if not parts.jaw.any() or parts.chin.sum() < 3:
        return out
    chin, jaw = vertices[parts.chin], vertices[parts.jaw]
    for k, element in enumerate(elements):
        if turns_jaw[k] and np.any(element[parts.chin]):
            out[k, parts.jaw] = apply(umeyama(chin, chin + element[parts.chin], with_scale=False), jaw) - jaw
    return out


def jaw_turners(muscle_names) -> np.ndarray:
    """Which of a basis's muscles (names) turn the jaw, shape (k,) bool: those in :data:`JAW_MUSCLES`, or all of
    them when it names none (their chin's skin is all that says)."""
    turns = np.isin(list(muscle_names), JAW_MUSCLES)
    return turns if turns.any() else np.ones(len(turns), dtype=bool)


def _components(triangles: np.ndarray, n: int) -> np.ndarray:
    """Connected-component label (n,) of each vertex over the triangles' edges."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def _face_axes(at: dict) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], float]:
    """((across, up, front) unit vectors (3,), height) of the face from its landmarks: up from the chin to the
    eye corners' middle, across from the right eye corner to the left, front the two's normal towards the nose
    tip, height the chin's distance from the eye corners' middle."""
    eyes = 0.5 * (at["eye_outer_L"] + at["eye_outer_R"])
    up = eyes - at["chin"]
    height = float(np.linalg.norm(up))
    up = up / height
    across = at["eye_outer_L"] - at["eye_outer_R"]
    across = across - (across @ up) * up
    across /= np.linalg.norm(across)
    front = np.cross(across, up)
    if (at["nose_tip"] - eyes) @ front < 0:
        front = -front
    return (across, up, front), height


def _below_bite(point: np.ndarray, at: dict, axes: tuple[np.ndarray, np.ndarray, np.ndarray]) -> bool:
    """Whether ``point`` (3,) lies below the bite's plane (:data:`BITE_TILT`) through the lips' meeting point."""
    tilt = np.radians(BITE_TILT)
    normal = np.cos(tilt) * axes[1] + np.sin(tilt) * axes[2]
    return bool((point - 0.5 * (at["lip_upper_inner"] + at["lip_lower_inner"])) @ normal < 0)


def _behind_face(vertices: np.ndarray, skin_triangles: np.ndarray, label: np.ndarray, candidates: np.ndarray,
                 axes: tuple[np.ndarray, np.ndarray, np.ndarray], depth: float) -> np.ndarray:
    """The candidate components whose vertices lie, in the median, more than ``depth`` behind the face's front
    envelope: the front-most skin seen along ``axes`` = (across, up, front), its openings (eyes, mouth) filled by
    linear interpolation from their rims. Parts in front of the skin (a brow shell, glasses) or beside it are
    not."""
    from scipy.interpolate import griddata

    across, up, front = axes
    skin = np.unique(skin_triangles)
    plane = vertices @ np.stack([across, up], axis=1)
    cell = 2.0 * float(np.median(np.linalg.norm(vertices[skin_triangles[:, 0]] - vertices[skin_triangles[:, 1]],
                                                axis=1)))
    cells = np.floor(plane[skin] / cell).astype(np.int64)
    keys, where = np.unique(cells, axis=0, return_inverse=True)
    front_most = np.full(len(keys), -np.inf)
    np.maximum.at(front_most, where.ravel(), vertices[skin] @ front)
    chosen = np.isin(label, candidates)
    envelope = griddata((keys + 0.5) * cell, front_most, plane[chosen], method="linear")
    behind = np.nan_to_num(envelope - vertices[chosen] @ front, nan=-np.inf)  # beside the face: not behind it
    owner = label[chosen]
    return np.array([c for c in candidates if np.median(behind[owner == c]) > depth], dtype=np.int64)
