"""Action units carried from a source face to a target face (Erdoğdu §5.5-5.6): modeling, then animation.

Modeling (§5.5): the control points of the chosen AUs sit on the neutral source face; on the expressive
source face they have moved by ``v_i``. Given an expressive mesh of the source person (any topology, any head
pose), :func:`control_point_moves` puts it on the neutral's pose (skull landmarks, then trimmed ICP) and carries
the points there by the landmark spline and the nearest surface point (eq. 5.6); with a basis as the source
the expression shares the neutral's topology and :func:`basis_moves` reads ``v_i`` exactly at each point.

Animation (§5.6): the control points are carried to the neutral target face, moved by ``m v_i`` (upper face,
eq. 5.10) or ``m v_i s_t / s_s`` (lower face, eq. 5.8; ``s``: the mouth-corner distance), and the target is
warped by one thin-plate spline per region through the moved points and fixed anchor points (the landmarks
away from the moving points, and a band of target vertices along the border between the regions). A region
with no moving point is not touched: a brow expression never moves the mouth. Closed parts inside a target
head (teeth, eyeballs) then move with their bone, not with the spline (:mod:`~livebridge.retarget.inner_parts`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.retarget.control_points import ControlPointSet, carry_control_points
from livebridge.retarget.inner_parts import JAW_MUSCLES, BoneParts, bone_parts, on_bones
from livebridge.retarget.landmarks import LandmarkSet, surface_values
from livebridge.retarget.tps import Kernel, fit_tps

MERGE_DISTANCE = 1.0
"""Control points of combined AUs closer than this (mm) are one point (their moves add)."""
ANCHOR_CLEARANCE = 0.12
"""A landmark closer than this fraction of the face's landmark extent to a moving point is not an anchor."""
BORDER_SPACING = 0.06
"""Spacing of the anchors along the border between the regions, as a fraction of the landmark extent."""
MESH_OUTPUTS = {".obj": "OBJ file", ".ply": "PLY file", ".stl": "STL file"}
"""Mesh files :func:`save_mesh` writes, by suffix."""


@dataclass(frozen=True)
class FaceRegions:
    """Which vertices of a face are upper face and which lower (thesis §5.6.2), from its landmarks.

    The border is a plane across the face between the eyes' corners and the nose tip (40% of the way down),
    perpendicular to the face's up direction (chin to the inner brows, orthogonal to the eye line).
    """

    up: np.ndarray
    """Unit up direction (3,)."""
    border: float
    """Height of the border along ``up``, mm."""

    @classmethod
    def of(cls, landmarks: dict[str, np.ndarray]) -> FaceRegions:
        _require(landmarks, ("eye_outer_L", "eye_outer_R", "eye_inner_L", "eye_inner_R", "nose_tip", "chin",
                             "brow_inner_L", "brow_inner_R"))
        across = landmarks["eye_outer_L"] - landmarks["eye_outer_R"]
        across /= np.linalg.norm(across)
        up = 0.5 * (landmarks["brow_inner_L"] + landmarks["brow_inner_R"]) - landmarks["chin"]
        up -= (up @ across) * across
        up /= np.linalg.norm(up)
        eyes = np.mean([landmarks[n] for n in ("eye_outer_L", "eye_outer_R", "eye_inner_L", "eye_inner_R")], axis=0)
        border = float(eyes @ up - 0.4 * (eyes - landmarks["nose_tip"]) @ up)
        return cls(up, border)

    def upper(self, points: np.ndarray) -> np.ndarray:
        """Boolean mask (n,) of points (n, 3) in the upper face."""
        return points @ self.up > self.border


def _require(landmarks: dict, names) -> None:
    missing = [n for n in names if n not in landmarks]
    if missing:
        raise InputError(f"{len(missing)} landmark{'s' if len(missing) > 1 else ''} missing: {', '.join(missing)}",
                         field="landmarks")


def mouth_width(landmarks: dict[str, np.ndarray]) -> float:
    """``s``: the distance between the mouth corners, mm."""
    _require(landmarks, ("mouth_corner_L", "mouth_corner_R"))
    return float(np.linalg.norm(landmarks["mouth_corner_L"] - landmarks["mouth_corner_R"]))


# ------------------------------------------------------------------------------------------------ modeling
def control_point_moves(points: np.ndarray, neutral_mesh, neutral_landmarks: LandmarkSet, expressive_mesh,
                        expressive_landmarks: LandmarkSet, kernel: Kernel | str = Kernel.BIHARMONIC,
                        source=None) -> np.ndarray:
    """``v_i`` (n, 3): points (n, 3) on the neutral source face carried to the expressive one, minus where
    they were.

    The expressive face is first put on the neutral's pose (:func:`on_neutral_pose`): the person's head
    moved between the two, which is no part of the expression. An expressive mesh with the neutral's
    triangles (a blendshape) moves each point as its triangle's corners move; any other (a scan, another
    topology) by the thesis's way (§5.5.3): the landmark spline carries each point and it is snapped to the
    nearest point of the expressive surface, which knows the motion along the skin at the landmarks only.
    ``*_mesh``: (vertices, triangles); the landmarks are on each mesh; ``source`` (the expressive mesh's
    file) is named in errors.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    neutral_vertices, neutral_triangles = (np.asarray(a) for a in neutral_mesh)
    vertices, triangles = (np.asarray(a) for a in expressive_mesh)
    posed = on_neutral_pose(neutral_mesh, neutral_landmarks, vertices,
                            expressive_landmarks.as_dict(vertices, triangles), source)
    if vertices.shape == neutral_vertices.shape and np.array_equal(triangles, neutral_triangles):
        return surface_values(points, neutral_vertices, neutral_triangles, posed - neutral_vertices)
    return carry_control_points(points, neutral_mesh, neutral_landmarks, (posed, triangles), expressive_landmarks,
                                kernel) - points


def on_neutral_pose(neutral_mesh, neutral_landmarks: LandmarkSet, vertices: np.ndarray,
                    landmarks: dict[str, np.ndarray], source=None) -> np.ndarray:
    """An expressive mesh's ``vertices`` (m, 3; ``landmarks`` on it) moved rigidly onto the neutral face's
    pose, shape (m, 3): Kabsch on the skull's landmarks, then trimmed point-to-plane ICP against the neutral's
    surface (:func:`~livebridge.retarget.normalise.register_rigid`, as for expression scans)."""
    from livebridge.face.meshio import vertex_normals
    from livebridge.geometry.transforms import apply
    from livebridge.retarget.face_scan import crop_radius
    from livebridge.retarget.normalise import register_rigid

    neutral_vertices, neutral_triangles = (np.asarray(a) for a in neutral_mesh)
    marks = neutral_landmarks.as_dict(neutral_vertices, neutral_triangles)
    _require(marks, ("nose_tip",))
    origin = marks["nose_tip"]  # the registration works about the neutral's nose tip
    normals = vertex_normals(neutral_vertices, neutral_triangles)
    to_neutral = register_rigid(vertices, landmarks, neutral_vertices - origin, normals,
                                {name: p - origin for name, p in marks.items()}, crop_radius(marks),
                                source=source)
    return apply(to_neutral, vertices) + origin


def basis_moves(points: np.ndarray, basis: Basis, contractions: dict[str, float]) -> np.ndarray:
    """``v_i`` (n, 3) of points on a basis's neutral face under ``contractions`` (``{muscle: x}``), exactly:
    the synthesized displacement at each point's place on the surface."""
    unknown = [name for name in contractions if name not in basis.names]
    if unknown:
        raise InputError(f"the source basis has no muscle {', '.join(unknown)} (it has {', '.join(basis.names)})",
                         field="muscles")
    x = np.zeros(basis.n_muscles)
    for name, value in contractions.items():
        x[basis.index(name)] = value
    return surface_values(points, basis.neutral, basis.triangles, np.tensordot(x, basis.elements, axes=1))


# ------------------------------------------------------------------------------------------------ animation
@dataclass(frozen=True)
class Motion:
    """Control points on the target and how far each moves at magnitude 1 (already scaled for its region).

    positions, moves : ndarray, shape (n, 3); upper : ndarray of bool, shape (n,).
    """

    positions: np.ndarray
    moves: np.ndarray
    upper: np.ndarray


def merged(positions: np.ndarray, moves: np.ndarray, upper: np.ndarray) -> Motion:
    """Points closer than :data:`MERGE_DISTANCE` become one (mean place, summed move, upper if any is)."""
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    pairs = cKDTree(positions).query_pairs(MERGE_DISTANCE, output_type="ndarray")
    n = len(positions)
    from scipy.sparse import coo_matrix

    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n)) if len(pairs) else \
        coo_matrix((n, n))
    count, label = connected_components(graph, directed=False)
    weight = np.bincount(label, minlength=count)[:, None]
    place = np.zeros((count, 3))
    move = np.zeros((count, 3))
    np.add.at(place, label, positions)
    np.add.at(move, label, moves)
    region = np.zeros(count, dtype=bool)
    np.logical_or.at(region, label, upper)
    return Motion(place / weight, move, region)


def warp_regions(vertices: np.ndarray, triangles: np.ndarray, landmarks: dict[str, np.ndarray], motion: Motion,
                 magnitude: float, kernel: Kernel | str = Kernel.BIHARMONIC) -> np.ndarray:
    """The target face with its control points moved by ``magnitude`` times their moves, shape (m, 3).

    One spline per region (§5.6.2) through the region's moved points and fixed anchors; only that region's
    vertices move. Parameters: ``vertices (m, 3)``, ``triangles (t, 3)``, ``landmarks {name: (3,)}`` on it.
    """
    if not (np.isfinite(magnitude) and 0.0 <= magnitude <= 1.0):
        raise InputError(f"the magnitude m must be in [0, 1], got {magnitude}", field="magnitude")
    regions = FaceRegions.of(landmarks)
    extent = float(np.ptp(np.array(list(landmarks.values())), axis=0).max())
    in_upper = regions.upper(vertices)
    border = border_points(vertices, triangles, in_upper, BORDER_SPACING * extent)
    out = np.array(vertices, dtype=np.float64)
    for upper in (True, False):
        moving = (motion.upper == upper) & (np.linalg.norm(motion.moves, axis=1) > 0)
        if not moving.any() or magnitude == 0.0:
            continue
        points = motion.positions[moving]
        anchors = [p for p in landmarks.values()
                   if np.linalg.norm(points - p, axis=1).min() > ANCHOR_CLEARANCE * extent]
        fixed = np.vstack([np.array(anchors).reshape(-1, 3), border])
        fixed = fixed[np.linalg.norm(fixed[:, None] - points[None], axis=2).min(axis=1) > MERGE_DISTANCE]
        spline = fit_tps(np.vstack([points, fixed]), np.vstack([points + magnitude * motion.moves[moving], fixed]),
                         kernel)
        chosen = in_upper if upper else ~in_upper
        out[chosen] = spline(vertices[chosen])
    return out


def border_points(vertices: np.ndarray, triangles: np.ndarray, in_upper: np.ndarray, spacing: float) -> np.ndarray:
    """Vertices (k, 3) along the border between the regions (on an edge that crosses it), ``spacing`` apart."""
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    crossing = edges[in_upper[edges[:, 0]] != in_upper[edges[:, 1]]]
    candidates = vertices[np.unique(crossing)]
    chosen: list[np.ndarray] = []
    for point in candidates[np.argsort(candidates[:, 0])]:
        if not chosen or np.linalg.norm(np.array(chosen) - point, axis=1).min() >= spacing:
            chosen.append(point)
    return np.array(chosen).reshape(-1, 3)


# ------------------------------------------------------------------------------------------------ the whole way
@dataclass(frozen=True)
class AUTransfer:
    """Everything an AU mesh of the target needs, prepared once; :meth:`mesh` per magnitude."""

    vertices: np.ndarray
    triangles: np.ndarray
    landmarks: dict
    motion: Motion
    kernel: Kernel
    parts: BoneParts
    """The target's closed inner parts on the skull and the jaw."""
    turns_jaw: bool
    """Whether the AUs turn the jaw (else the jaw's parts stay still, as the skull's)."""

    def mesh(self, magnitude: float) -> np.ndarray:
        """The target's vertices (m, 3) at AU magnitude ``m`` in [0, 1]: the regions' splines, then the inner
        parts on their bones (the skull's still, the jaw's moved rigidly as the chin's skin moves)."""
        warped = warp_regions(self.vertices, self.triangles, self.landmarks, self.motion, magnitude, self.kernel)
        if not self.parts.any:
            return warped
        moved = on_bones((warped - self.vertices)[None], self.vertices, self.parts, [self.turns_jaw])[0]
        on_bone = self.parts.skull | self.parts.jaw
        warped[on_bone] = self.vertices[on_bone] + moved[on_bone]
        return warped


def prepare_transfer(control_points: ControlPointSet, groups, source, source_landmarks: LandmarkSet,
                     target_mesh, target_landmarks: LandmarkSet, sides=("L", "R", "C"),
                     kernel: Kernel | str = Kernel.BIHARMONIC, expression=None) -> AUTransfer:
    """AUs (``groups``: ``au12``, or muscle names; several combine) of a source face, ready for the target.

    Parameters
    ----------
    control_points : ControlPointSet
        On its reference face; carried to the source and to the target by their landmarks.
    groups : sequence of str
    source : Basis or (vertices (n, 3), triangles (t, 3))
        The neutral source face. Without ``expression`` it must be a basis: its recipes' contractions make
        the expressive source (:func:`basis_moves`).
    source_landmarks, target_landmarks : LandmarkSet
    target_mesh : (vertices (m, 3), triangles (t, 3))
    sides : sequence of str
        Sides whose points move (``("L",)``: the subject's left only); the others' points stay fixed, and the
        midline's move half as far when only one side moves.
    expression : ((vertices (k, 3), triangles (u, 3)), LandmarkSet, source), optional
        The expressive source face (§5.5): the source person showing the AUs, any topology and head pose,
        its landmarks, and its file (named in errors). Every chosen group's points move as it shows
        (:func:`control_point_moves`).
    """
    kernel = Kernel.parse(kernel)
    chosen = control_points.subset(control_points.select(groups))
    target_vertices, target_triangles = (np.asarray(a) for a in target_mesh)
    source_mesh = (source.neutral, source.triangles) if isinstance(source, Basis) else \
        tuple(np.asarray(a) for a in source)
    on_source = chosen.on(*source_mesh, source_landmarks, kernel)
    on_target = chosen.on(target_vertices, target_triangles, target_landmarks, kernel)
    if expression is not None:
        expressive_mesh, expressive_landmarks, expressive_file = expression
        moves = control_point_moves(on_source, source_mesh, source_landmarks, expressive_mesh, expressive_landmarks,
                                    kernel, expressive_file)
    elif isinstance(source, Basis):
        moves = _recipe_moves(control_points, chosen, on_source, source)
    else:
        raise InputError("a source mesh without a basis needs its expressive face (--expression) to show the AUs",
                         field="--expression")
    sides = tuple(sides)
    share = np.array([1.0 if side in sides else (0.5 if side == "C" and len(sides) < 3 else 0.0)
                      for side in chosen.sides])
    source_marks = source_landmarks.as_dict(*source_mesh)
    target_marks = target_landmarks.as_dict(target_vertices, target_triangles)
    upper = np.array([region == "upper" for region in chosen.regions])
    ratio = mouth_width(target_marks) / mouth_width(source_marks)
    # the source's moves in the target's frame: the landmark spline's Jacobian at each point (sizes and pose)
    from livebridge.retarget.basis import landmark_pairs

    pairs = landmark_pairs(source_landmarks, source_mesh, target_landmarks, (target_vertices, target_triangles))
    jacobian = fit_tps(*pairs, kernel).jacobian(on_source)
    rotation = np.array([_rotation_of(j) for j in jacobian])
    turned = np.einsum("nij,nj->ni", rotation, moves)
    scaled = turned * np.where(upper, 1.0, ratio)[:, None] * share[:, None]
    return AUTransfer(target_vertices, target_triangles, target_marks, merged(on_target, scaled, upper), kernel,
                      bone_parts(target_vertices, target_triangles, target_landmarks),
                      _turns_jaw(control_points, chosen.group_names))


def _recipe_moves(control_points: ControlPointSet, chosen: ControlPointSet, on_source: np.ndarray, source: Basis
                  ) -> np.ndarray:
    """``v_i`` (n, 3) of the chosen points (on the source's neutral) under each group's muscle recipe."""
    moves = np.zeros_like(on_source)
    for group in chosen.group_names:
        recipe = control_points.recipes.get(group)
        if recipe is None or not recipe.muscles:
            raise InputError(f"group {group} has no muscle recipe: add muscles = {{...}} to its [[group]]",
                             field=group)
        mask = np.array([g == group for g in chosen.groups])
        moves[mask] += basis_moves(on_source[mask], source, recipe.muscles)
    return moves


def _turns_jaw(control_points: ControlPointSet, groups) -> bool:
    """Whether any of ``groups`` turns the jaw: a jaw muscle (:data:`~livebridge.retarget.inner_parts.JAW_MUSCLES`)
    by name or in its recipe; a group without a recipe may (only its chin's skin says)."""
    for group in groups:
        recipe = control_points.recipes.get(group)
        if group in JAW_MUSCLES or recipe is None or not recipe.muscles or set(recipe.muscles) & set(JAW_MUSCLES):
            return True
    return False


def _rotation_of(jacobian: np.ndarray) -> np.ndarray:
    """The rotation (3, 3) nearest a Jacobian (polar decomposition): the thesis scales moves only by ``s_t/s_s``
    (lower face), so only the pose difference is taken from the spline."""
    u, _, vt = np.linalg.svd(jacobian)
    rotation = u @ vt
    if np.linalg.det(rotation) < 0:
        u[:, -1] *= -1
        rotation = u @ vt
    return rotation


def parse_aus(values) -> list[str]:
    """Group names from ``--au`` values: ``12`` -> ``au12``, ``au12`` and muscle names as given.

    A group named twice (``--au 12 --au au12``) is an :class:`InputError`: combined, its control points would
    move twice as far, an expression at twice the magnitude asked for.
    """
    out = []
    for value in values:
        text = str(value).strip()
        name = f"au{int(text)}" if text.isdigit() else text
        if name in out:
            raise InputError(f"{name} is given more than once (each --au is added to the others)", field="--au")
        out.append(name)
    return out


def save_moved_obj(path: str | Path, target: str | Path, vertices: np.ndarray, mm_per_unit: float) -> bool:
    """The ``target`` OBJ file with its vertices moved to ``vertices`` (n, 3; mm), in the file's own units
    (``mm_per_unit``), written atomically to ``path``: its texture coordinates, polygons, groups and materials
    kept, its normals dropped (:class:`~livebridge.face.obj_file.ObjLayout`). False (nothing written) when its
    ``v`` lines are not the n vertices."""
    from livebridge.atomic import write_bytes_atomically
    from livebridge.face.obj_file import ObjLayout

    layout = ObjLayout.of(Path(target).read_bytes())
    if layout.n_vertices != len(vertices):
        return False
    write_bytes_atomically(path, layout.moved(np.asarray(vertices, dtype=np.float64) / mm_per_unit), "OBJ file")
    return True


def save_mesh(path: str | Path, vertices: np.ndarray, triangles: np.ndarray, mm_per_unit: float = 1.0,
              units: str = "mm") -> None:
    """A triangle mesh (vertices (n, 3) in mm) written atomically in ``units`` (``mm_per_unit``) as its suffix
    says (:data:`MESH_OUTPUTS`): Wavefront OBJ, binary PLY or binary STL."""
    from livebridge.atomic import write_bytes_atomically
    from livebridge.face.obj_file import mesh_obj
    from livebridge.retarget.ply_file import ply_bytes
    from livebridge.retarget.stl_file import stl_bytes

    suffix = Path(path).suffix.lower()
    scaled = np.asarray(vertices, dtype=np.float64) / mm_per_unit
    comment = f"livebridge retarget au: {len(vertices)} vertices, {len(triangles)} triangles, {units}"
    if suffix == ".stl":
        data = stl_bytes(scaled, triangles, comment)
    elif suffix == ".ply":
        data = ply_bytes(scaled, triangles)
    else:
        data = mesh_obj(scaled, triangles, comment)
    write_bytes_atomically(path, data, MESH_OUTPUTS[suffix])
