"""The built-in default face: a procedural head and a Waters-style muscle model of its 16 elements.

So the demo and the simulated rig run on a fresh machine with no data. Everything is generated from
formulas (no randomness), in millimetres, +y up, +z out of the face, the performer's left at +x.

Surface
    A grid over (angle around the vertical axis, height) of elliptical cross-sections (head width and
    depth vary with height: forehead, temples, cheekbones, jaw, chin, neck), plus smooth offsets for
    the features: brow ridge, eye sockets with eyeballs and lids (crease and lid margins), nose (bridge,
    tip, alae), cheekbones, nasolabial folds, lips (vermilion, philtrum), the mentolabial groove and the
    chin. The grid is cut along the mouth line (the vertices between the mouth corners are doubled), so
    the lips part when the jaw opens. About 9k vertices, a face about 150 mm wide.

Elements (Waters, "A muscle model for animating three-dimensional facial expression", 1987)
    Linear muscles pull skin towards their bone attachment ``A`` from their skin insertion ``I``, with an
    angular fall-off ``cos(alpha / omega * pi / 2)`` (``alpha``: angle between ``p - A`` and ``I - A``) and a
    radial fall-off (rising to 1 at ``R_s`` from the attachment, falling to 0 at ``R_f``); the pull is kept
    mostly tangential to the skin. Sphincters (orbicularis oris, the ring of orbicularis oculi) contract
    towards a centre with an elliptical fall-off. The eyelids close by rotating about the eyeball's
    centre. The jaw rotates about a hinge axis near the ears, carrying the lower lip, chin and jaw line
    fully and the cheeks partly. Magnitudes are similar to the ICT-FaceKit basis.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.interpolate import PchipInterpolator
from scipy.spatial.transform import Rotation

from livebridge.face.basis import CHOE_KO_MUSCLES, Basis
from livebridge.face.markers import MarkerSet
from livebridge.face.meshio import vertex_normals

MOUTH_Y = -40.0  # height of the mouth line, mm
MOUTH_HALF_WIDTH = 24.0
EYE_X, EYE_Y = 32.0, 30.0  # centre of the left eye opening (right: -EYE_X)
EYE_HALF_WIDTH = 14.0
EYE_UPPER, EYE_LOWER = 5.0, 3.5  # lid margins above / below the eye's centre line
EYEBALL_RADIUS = 12.0
JAW_HINGE = np.array([0.0, 22.0, 8.0])  # a point on the hinge axis (the axis is along x)
JAW_ANGLE_DEG = 13.0

# rows of the grid: coarser on the neck and the top of the head, finer over the features
_ROWS = np.concatenate([np.linspace(-115.0, -60.0, 19)[:-1], np.arange(-60.0, 50.0, 2.0), np.linspace(50.0, 115.0, 22)])
_N_COLUMNS = 95  # odd: a column on the midline, so the mesh mirrors exactly
_PHI_MAX = 0.62 * np.pi

_HALF_WIDTH = PchipInterpolator([-115, -95, -85, -70, -55, -40, -10, 10, 30, 60, 90, 115],
                                [52, 50, 40, 52, 60, 65, 71, 73, 71, 68, 64, 56])
_DEPTH = PchipInterpolator([-115, -97, -85, -70, -40, 0, 30, 60, 90, 115],
                           [56, 62, 84, 90, 94, 94, 90, 93, 86, 66])
# nose: height above the face (mm) and half-width along the height, from bridge to tip to the lip
_NOSE_PROFILE = PchipInterpolator([-24, -19, -14, -8, 0, 15, 30, 40], [0, 4, 17, 26, 21, 11, 5, 0], extrapolate=False)
_NOSE_WIDTH = PchipInterpolator([-24, -10, 0, 20, 40], [12, 11, 8, 6.5, 8], extrapolate=True)


def _gauss(u: np.ndarray) -> np.ndarray:
    return np.exp(-np.square(u))


def _smoothstep(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def _eye_margins(dx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Heights (mm, relative to the eye's centre line) of the upper and lower lid margins at ``dx``."""
    shape = np.sqrt(np.clip(1.0 - np.square(dx / EYE_HALF_WIDTH), 0.0, None))
    skew = 1.0 + 0.15 * np.clip(dx / EYE_HALF_WIDTH, -1, 1)  # the upper lid peaks a little laterally
    return EYE_UPPER * shape * skew, -EYE_LOWER * shape


def _feature_height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Outward offset (mm) of the facial features at face coordinates ``x, y`` (any shape)."""
    ax = np.abs(x)
    h = np.zeros(np.broadcast(x, y).shape)
    # brow ridge and forehead
    h += 5.0 * _gauss((y - 44.0) / 6.5) * _gauss(np.clip(ax - 38.0, 0, None) / 14.0)
    h += 2.0 * _gauss((y - 75.0) / 25.0) * _gauss(x / 45.0)
    # eye sockets, eyeballs, lids
    dx, dy = ax - EYE_X, y - EYE_Y
    h -= 12.0 * _gauss(dx / 17.0) * _gauss(dy / 12.5)
    h += 8.5 * np.sqrt(np.clip(1.0 - np.square(dx / 15.0) - np.square(dy / 11.0), 0.0, None))
    upper, lower = _eye_margins(dx)
    inside = np.abs(dx) < EYE_HALF_WIDTH
    lid = np.where(inside, 1.0, 0.0) * _gauss(dx / 16.0)
    h += 1.3 * lid * _gauss((dy - upper) / 1.4)  # upper lid margin
    h += 0.9 * lid * _gauss((dy - lower) / 1.2)  # lower lid margin
    h -= 1.6 * _gauss(dx / 13.0) * _gauss((dy - upper - 5.0) / 1.6)  # upper lid crease
    # nose: bridge to tip, alae
    profile = np.nan_to_num(_NOSE_PROFILE(y))
    h += profile * _gauss(x / _NOSE_WIDTH(y))
    h += 6.0 * _gauss((ax - 14.0) / 5.0) * _gauss((y + 12.0) / 5.0)
    h -= 1.5 * _gauss((ax - 7.0) / 3.0) * _gauss((y + 18.0) / 2.0)  # nostrils
    # cheekbones and cheeks
    h += 6.0 * _gauss((ax - 46.0) / 20.0) * _gauss((y - 8.0) / 16.0)
    # nasolabial folds: a groove from the alae to beside the mouth corners
    t = np.clip((y + 14.0) / (-32.0), 0, 1)
    fold_x = 22.0 + 10.0 * t
    h -= 2.2 * _gauss((ax - fold_x) / 3.5) * (_smoothstep((y + 48.0) / 6.0) * _smoothstep((-8.0 - y) / 6.0))
    # lips: upper and lower vermilion meet at the mouth line; philtrum; mentolabial groove; chin
    lip = np.sqrt(np.clip(1.0 - np.square(x / (MOUTH_HALF_WIDTH + 2.0)), 0.0, None))  # thins to the corners
    bow = 1.0 + 0.25 * _gauss((ax - 5.0) / 4.0)  # cupid's bow
    h += 3.0 * _gauss(x / 30.0) * _gauss((y - MOUTH_Y + 2.0) / 16.0)  # the tooth arch under the lips
    h += 6.5 * lip * bow * _gauss((y - (MOUTH_Y + 4.0 * lip)) / (1.5 + 3.0 * lip)) * (y >= MOUTH_Y)
    h += 7.0 * lip * _gauss((y - (MOUTH_Y - 5.0 * lip)) / (1.5 + 3.5 * lip)) * (y <= MOUTH_Y)
    h -= 1.2 * _gauss(x / 3.0) * _gauss((y - (MOUTH_Y + 12.0)) / 5.0)  # philtrum
    h -= 3.0 * _gauss(x / 18.0) * _gauss((y - (MOUTH_Y - 16.0)) / 4.0)
    h += 7.0 * _gauss(x / 18.0) * _gauss((y - (MOUTH_Y - 31.0)) / 10.0)
    return h


def _surface(x_face: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Points on the face at face coordinates (``x_face``: the base surface's x), shape (..., 3)."""
    a = _HALF_WIDTH(y)
    phi = np.arcsin(np.clip(x_face / a, -1.0, 1.0))
    return _surface_phi(phi, y)


def _surface_phi(phi: np.ndarray, y: np.ndarray) -> np.ndarray:
    a, b = _HALF_WIDTH(y), _DEPTH(y)
    x = a * np.sin(phi)
    radial = np.stack([np.sin(phi), np.zeros_like(phi), np.cos(phi)], axis=-1)
    base = np.stack([x, y, b * np.cos(phi)], axis=-1)
    return base + _feature_height(x, y)[..., None] * radial


@dataclass(frozen=True)
class _Mesh:
    vertices: np.ndarray  # (V, 3)
    triangles: np.ndarray  # (T, 3)
    lower_lip: np.ndarray  # bool (V,): the doubled mouth-line vertices that belong to the lower lip
    upper_lip: np.ndarray  # bool (V,): their upper-lip twins


def _build_mesh() -> _Mesh:
    u = np.linspace(-1.0, 1.0, _N_COLUMNS)
    phi = _PHI_MAX * (0.55 * u + 0.45 * u**3)
    phi_grid, y_grid = np.meshgrid(phi, _ROWS)  # (rows, columns)
    vertices = _surface_phi(phi_grid, y_grid).reshape(-1, 3)
    n_rows = len(_ROWS)
    index = np.arange(n_rows * _N_COLUMNS).reshape(n_rows, _N_COLUMNS)
    a, b = index[:-1, :-1].copy(), index[:-1, 1:].copy()  # quad corners: row r (lower) ...
    c, d = index[1:, :-1].copy(), index[1:, 1:].copy()  # ... and row r + 1 (upper); rows go up in y
    # cut the mouth line: double its inner vertices; quads just below the line use the lower-lip copies
    row = int(np.flatnonzero(np.isclose(_ROWS, MOUTH_Y))[0])
    cut = np.flatnonzero(np.abs(vertices[index[row], 0]) < MOUTH_HALF_WIDTH)
    cut = cut[1:-1] if len(cut) > 2 else cut[:0]  # the corners stay joined
    originals = index[row, cut]
    twins = np.arange(len(vertices), len(vertices) + len(cut))
    copy_of = np.arange(len(vertices))
    copy_of[originals] = twins
    c[row - 1], d[row - 1] = copy_of[c[row - 1]], copy_of[d[row - 1]]
    # counter-clockwise seen from outside (+z at the front); the diagonals mirror about the midline
    left = np.broadcast_to(np.arange(_N_COLUMNS - 1) < (_N_COLUMNS - 1) // 2, a.shape).ravel()
    a, b, c, d = a.ravel(), b.ravel(), c.ravel(), d.ravel()
    triangles = np.concatenate([
        np.stack([a, b, c], 1)[left], np.stack([b, d, c], 1)[left],
        np.stack([a, b, d], 1)[~left], np.stack([a, d, c], 1)[~left],
    ])
    vertices = np.concatenate([vertices, vertices[originals]])
    lower_lip = np.zeros(len(vertices), dtype=bool)
    lower_lip[twins] = True
    upper_lip = np.zeros(len(vertices), dtype=bool)
    upper_lip[originals] = True
    return _Mesh(vertices, triangles, lower_lip, upper_lip)


def _tangential(displacement: np.ndarray, normals: np.ndarray, keep_normal: float = 0.25) -> np.ndarray:
    """Mostly slide along the skin: scale the normal component of ``displacement (V, 3)`` by ``keep_normal``."""
    along = np.einsum("vd,vd->v", displacement, normals)[:, None] * normals
    return displacement - (1.0 - keep_normal) * along


def _scale_to_peak(field: np.ndarray, peak_mm: float) -> np.ndarray:
    return field * (peak_mm / max(np.linalg.norm(field, axis=1).max(), 1e-12))


def _linear_muscle(vertices, normals, attachment, insertion, omega_deg, start, finish, peak_mm,
                   mask=None) -> np.ndarray:
    """Waters linear muscle: pull towards ``attachment (3,)`` with angular and radial fall-off, shape (V, 3).

    The radial fall-off rises to 1 at ``R_s = start * L`` from the attachment and falls to 0 at
    ``R_f = finish * L``, ``L`` the muscle's length ``|insertion - attachment|``.
    """
    axis = insertion - attachment
    length = np.linalg.norm(axis)
    r_start, r_finish = start * length, finish * length
    offset = vertices - attachment
    distance = np.linalg.norm(offset, axis=1)
    cos_alpha = offset @ axis / np.maximum(distance * np.linalg.norm(axis), 1e-12)
    alpha = np.arccos(np.clip(cos_alpha, -1.0, 1.0))
    omega = np.deg2rad(omega_deg)
    angular = np.where(alpha < omega, np.cos(alpha / omega * np.pi / 2), 0.0)
    radial = np.where(distance < r_start, np.cos((1.0 - distance / r_start) * np.pi / 2),
                      np.cos(np.clip((distance - r_start) / (r_finish - r_start), 0, 1) * np.pi / 2))
    weight = angular * radial * (distance <= r_finish)
    if mask is not None:
        weight = weight * mask
    pull = -offset / np.maximum(distance, 1e-12)[:, None]
    return _scale_to_peak(_tangential(weight[:, None] * pull, normals), peak_mm)


def _both_sides(make) -> np.ndarray:
    return make(1.0) + make(-1.0)


def _elements(mesh: _Mesh) -> dict[str, np.ndarray]:
    v, n = mesh.vertices, vertex_normals(mesh.vertices, mesh.triangles)
    upper_side = ~mesh.lower_lip & ((v[:, 1] > MOUTH_Y) | mesh.upper_lip)  # skin above the mouth line
    elements: dict[str, np.ndarray] = {}

    def point(px, py, depth=0.0):
        return _surface(np.asarray(px, float), np.asarray(py, float)) - np.array([0.0, 0.0, depth])

    for side, s in (("L", 1.0), ("R", -1.0)):
        elements[f"frontalis_{side}"] = _linear_muscle(
            v, n, point(s * 30, 112, 8), point(s * 30, 44), 30, 0.8, 1.12, 11.0)
        elements[f"corrugator_{side}"] = _linear_muscle(
            v, n, point(s * 9, 38, 4), point(s * 30, 47), 40, 0.75, 1.35, 6.5)
        elements[f"orbicularis_oculi_{side}"] = _orbicularis_oculi(v, n, s)
        elements[f"levator_labii_{side}"] = _linear_muscle(
            v, n, point(s * 20, 14, 6), point(s * 15, MOUTH_Y + 4), 28, 0.75, 1.12, 9.0, mask=upper_side)
        elements[f"zygomatic_major_{side}"] = _linear_muscle(
            v, n, point(s * 58, 6, 6), point(s * 25, MOUTH_Y), 24, 0.85, 1.2, 14.0)
        elements[f"risorius_{side}"] = _linear_muscle(
            v, n, point(s * 62, MOUTH_Y - 4, 6), point(s * 24, MOUTH_Y), 24, 0.85, 1.25, 10.0)
    elements["depressor_anguli_oris"] = _scale_to_peak(_both_sides(lambda s: _linear_muscle(
        v, n, point(s * 34, -78, 4), point(s * 25, MOUTH_Y), 28, 0.8, 1.2, 1.0)), 6.0)
    elements["orbicularis_oris"] = _orbicularis_oris(v, n)
    elements["lips_pressor"] = _lips_pressor(v, n, mesh)
    elements["jaw"] = _jaw(v, mesh)
    return elements


def _orbicularis_oculi(v: np.ndarray, n: np.ndarray, s: float) -> np.ndarray:
    """Eyelid closing (lids rotate about the eyeball's centre) plus the sphincter ring lifting the cheek."""
    centre = _surface(np.array(s * EYE_X), np.array(EYE_Y)) - np.array([0.0, 0.0, EYEBALL_RADIUS])
    dx = s * (v[:, 0] - centre[0])
    rel = v - centre
    radius = np.hypot(rel[:, 1], rel[:, 2])
    psi = np.arctan2(rel[:, 1], rel[:, 2])  # vertical angle about the eye's horizontal axis
    upper, lower = _eye_margins(dx)
    psi_u = np.arcsin(np.clip(upper / np.maximum(radius, 1e-9), -1, 1))
    psi_l = np.arcsin(np.clip(lower / np.maximum(radius, 1e-9), -1, 1))
    psi_c = psi_l + 0.25 * (psi_u - psi_l)  # where the lids meet
    near = (np.abs(dx) < EYE_HALF_WIDTH + 4) & (rel[:, 2] > 0) & (radius < 2.2 * EYEBALL_RADIUS)
    fall_up = 1.0 - _smoothstep((psi - psi_u - 0.2) / 0.4)
    fall_low = 1.0 - _smoothstep((psi_l - psi - 0.15) / 0.45)
    target = np.where(psi > psi_u, psi - (psi_u - psi_c) * fall_up,
                      np.where(psi < psi_l, psi + (psi_c - psi_l) * fall_low, psi_c))
    angle = np.where(near, target - psi, 0.0)
    # rotate about the x axis through the centre by `angle` (negative: downwards)
    cos, sin = np.cos(angle), np.sin(angle)
    new_y = cos * rel[:, 1] + sin * rel[:, 2]
    new_z = -sin * rel[:, 1] + cos * rel[:, 2]
    lids = np.stack([np.zeros(len(v)), new_y - rel[:, 1], new_z - rel[:, 2]], axis=1)
    # sphincter ring: skin around the orbit contracts towards the eye, lifting the cheek below
    q = np.hypot(dx / 24.0, (v[:, 1] - EYE_Y) / 18.0)
    ring = _gauss((q - 1.05) / 0.35) * (1.0 - _smoothstep((q - 1.5) / 0.4)) * (v[:, 2] > centre[2])
    towards = np.stack([centre[0] - v[:, 0], EYE_Y - v[:, 1], np.zeros(len(v))], axis=1)
    towards /= np.maximum(np.linalg.norm(towards, axis=1, keepdims=True), 1e-9)
    sphincter = _tangential(3.0 * ring[:, None] * towards, n)
    return lids + sphincter


def _mouth_coordinates(v: np.ndarray):
    return v[:, 0], v[:, 1] - MOUTH_Y


def _orbicularis_oris(v: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Sphincter of the mouth: lips narrow towards the centre and protrude (pucker)."""
    x, dy = _mouth_coordinates(v)
    q = np.hypot(x / 28.0, dy / 14.0)
    weight = 1.0 - _smoothstep((q - 0.5) / 0.9)
    weight *= v[:, 2] > 40
    displacement = np.stack([-0.4 * x, -0.12 * dy, 9.0 * np.ones(len(v))], axis=1) * weight[:, None]
    return _scale_to_peak(displacement, 12.0)


def _lips_pressor(v: np.ndarray, n: np.ndarray, mesh: _Mesh) -> np.ndarray:
    """Lips press together and roll in: the vermilion moves back and towards the mouth line."""
    x, dy = _mouth_coordinates(v)
    q = np.hypot(x / 27.0, dy / 11.0)
    weight = (1.0 - _smoothstep((q - 0.5) / 0.9)) * (v[:, 2] > 40)
    toward_line = -np.sign(dy + np.where(mesh.lower_lip, -1e-3, 1e-3)) * np.minimum(np.abs(dy), 4.0) * 0.5
    displacement = np.stack([-0.04 * x, toward_line, -4.5 * np.ones(len(v))], axis=1) * weight[:, None]
    return _scale_to_peak(displacement, 5.5)


def jaw_weight(v: np.ndarray, lower_lip: np.ndarray, upper_lip: np.ndarray) -> np.ndarray:
    """How fully each vertex follows the jaw, shape (n_vertices,): 1 on the lower lip, chin and jaw line."""
    ax, dy = np.abs(v[:, 0]), v[:, 1] - MOUTH_Y
    # a sharp split at the lips, a broad blend over the cheeks beside the mouth
    width = 3.0 + 35.0 * _smoothstep((ax - 0.6 * MOUTH_HALF_WIDTH) / (0.9 * MOUTH_HALF_WIDTH))
    centre = -3.0 * _smoothstep((ax - MOUTH_HALF_WIDTH) / 20.0) - 2.0  # the blend sits a little below the line
    weight = _smoothstep(0.5 - (dy - centre) / width)
    weight = np.where(lower_lip, 1.0, np.where(upper_lip, 0.0, weight))
    weight *= _smoothstep((v[:, 1] + 112.0) / 14.0)  # the neck stays
    return weight


def _jaw(v: np.ndarray, mesh: _Mesh) -> np.ndarray:
    """The jaw rotates open about a hinge axis (along x) near the ears, carrying the lower face."""
    weight = jaw_weight(v, mesh.lower_lip, mesh.upper_lip)
    angle = np.deg2rad(JAW_ANGLE_DEG) * weight
    rotation = Rotation.from_rotvec(np.stack([angle, np.zeros_like(angle), np.zeros_like(angle)], axis=1))
    rel = v - JAW_HINGE
    return rotation.apply(rel) - rel


@lru_cache(maxsize=1)
def builtin_basis() -> Basis:
    """The built-in face and its 16 Choe-Ko elements (deterministic; built once per process)."""
    mesh = _build_mesh()
    elements = _elements(mesh)
    stacked = np.stack([elements[m.name] for m in CHOE_KO_MUSCLES])
    return Basis(mesh.vertices, mesh.triangles, stacked, CHOE_KO_MUSCLES)


@lru_cache(maxsize=1)
def builtin_markers() -> MarkerSet:
    """A designed layout of 64 face markers and 5 head markers on :func:`builtin_basis` (cached)."""
    from livebridge.face.layout import design_markers

    return design_markers(builtin_basis(), count=64, n_head=5)


def _landmark_face_xy() -> np.ndarray:
    """Face coordinates (x, y), mm, of the 68 Multi-PIE/iBUG landmarks on the built-in face, shape (68, 2).

    iBUG numbering, the subject's right (-x here) first: 0-16 jaw line from the right ear round the chin to
    the left ear; 17-21 right brow (outer to inner), 22-26 left brow (inner to outer); 27-30 nose bridge to
    tip; 31-35 nostrils and subnasale, right to left; 36-41 right eye (36 outer corner, 37-38 upper lid,
    39 inner corner, 40-41 lower lid), 42-47 left eye (42 inner corner, 43-44 upper lid, 45 outer corner,
    46-47 lower lid); 48-59 outer lip contour (48 right corner, 51 top of the upper lip, 54 left corner,
    57 bottom of the lower lip); 60-67 inner lip contour (60 right corner, 62 upper, 64 left, 66 lower).
    Placed from the generator's own feature positions (eyes, lid margins, brow ridge, nose, mouth line).
    """
    angle = np.linspace(np.pi, 2 * np.pi, 17)  # the jaw: half an ellipse from ear to ear under the chin
    jaw = np.stack([63.0 * np.cos(angle), 25.0 + 105.0 * np.sin(angle)], axis=1)
    brow_x, brow_y = np.array([52.0, 44.0, 35.0, 26.0, 17.0]), np.array([40.0, 44.0, 46.0, 46.0, 44.0])
    brows = np.concatenate([np.stack([-brow_x, brow_y], 1), np.stack([brow_x, brow_y], 1)[::-1]])
    nose = np.array([[0.0, 30.0], [0.0, 18.0], [0.0, 6.0], [0.0, -7.0]])
    nostrils = np.array([[-12.0, -15.0], [-6.0, -18.0], [0.0, -20.0], [6.0, -18.0], [12.0, -15.0]])
    # eye points as lateral offsets from the eye's centre (+: towards the ear) and which lid margin
    lateral = np.array([13.0, 5.0, -5.0, -13.0, -5.0, 5.0])
    upper, lower = _eye_margins(lateral)
    heights = np.where([False, True, True, False, False, False], upper, np.where([0, 0, 0, 0, 1, 1], lower, 0.0))
    right_eye = np.stack([-(EYE_X + lateral), EYE_Y + heights], 1)
    left_order = [3, 2, 1, 0, 5, 4]  # 42 inner, 43-44 upper (inner first), 45 outer, 46-47 lower (outer first)
    left_eye = np.stack([EYE_X + lateral[left_order], EYE_Y + heights[left_order]], 1)
    outer_lip = np.array([[-24, 0], [-16, 6], [-6, 8.5], [0, 8], [6, 8.5], [16, 6], [24, 0], [16, -6], [7, -10],
                          [0, -11], [-7, -10], [-16, -6]], dtype=float)
    inner_lip = np.array([[-21, 0], [-8, 1], [0, 1], [8, 1], [21, 0], [8, -1], [0, -1], [-8, -1]], dtype=float)
    lips = np.concatenate([outer_lip, inner_lip]) + np.array([0.0, MOUTH_Y])
    return np.concatenate([jaw, brows, nose, nostrils, right_eye, left_eye, lips])


def _on_mesh(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray, candidates: int = 24):
    """Nearest triangle and barycentric coordinates of each point, shapes (n,) and (n, 3).

    Among the triangles with the nearest centroids, the one whose plane holds the point's projection inside
    it (or nearest to inside) and is closest.
    """
    from scipy.spatial import cKDTree

    corners = vertices[triangles]  # (T, 3, 3)
    _, near = cKDTree(corners.mean(axis=1)).query(points, k=candidates)
    a, b, c = (corners[near, k] for k in range(3))  # (n, k, 3)
    e1, e2, p = b - a, c - a, points[:, None] - a
    d11, d12, d22 = (e1 * e1).sum(-1), (e1 * e2).sum(-1), (e2 * e2).sum(-1)
    p1, p2 = (p * e1).sum(-1), (p * e2).sum(-1)
    det = d11 * d22 - d12 * d12
    v, w = (d22 * p1 - d12 * p2) / det, (d11 * p2 - d12 * p1) / det
    bary = np.stack([1.0 - v - w, v, w], axis=-1)
    outside = np.clip(-bary, 0.0, None).sum(-1)
    normal = np.cross(e1, e2)
    distance = np.abs((p * normal).sum(-1)) / np.linalg.norm(normal, axis=-1)
    best = np.argmin(distance + 1e3 * outside, axis=1)
    rows = np.arange(len(points))
    chosen = np.clip(bary[rows, best], 0.0, None)
    return near[rows, best], chosen / chosen.sum(axis=1, keepdims=True)


BUILTIN_68_HEAD = (0, 1, 2, 14, 15, 16, 29, 30, 36, 45)
"""Landmarks of ``builtin-68`` that no built-in muscle moves by 0.3 mm or more, the head markers of the set:
the jaw line at the ears (0-2, 14-16: above the jaw's reach), the lower nose bridge and tip (29, 30) and the
outer eye corners (36, 45). (The upper bridge 27 follows the corrugators, the inner eye corners the lids.)"""


@lru_cache(maxsize=1)
def builtin_landmarks() -> MarkerSet:
    """``builtin-68``: the 68 Multi-PIE/iBUG landmarks on :func:`builtin_basis` (see :func:`_landmark_face_xy`
    for the numbering); brows (17-26) and eyes (36-47) upper, the rest lower; :data:`BUILTIN_68_HEAD` head."""
    from livebridge.face.markers import LANDMARKS_68_UPPER, landmark_name

    basis = builtin_basis()
    xy = _landmark_face_xy()
    triangles, barycentric = _on_mesh(_surface(xy[:, 0], xy[:, 1]), basis.neutral, basis.triangles)
    regions = tuple("upper" if i in LANDMARKS_68_UPPER else "lower" for i in range(68))
    roles = tuple("head" if i in BUILTIN_68_HEAD else "face" for i in range(68))
    return MarkerSet(tuple(landmark_name(i) for i in range(68)), triangles, barycentric, regions, roles)
