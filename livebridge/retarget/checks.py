"""Checks of a user's mesh and landmarks before a transfer: one clear error naming the file and the landmark."""

from __future__ import annotations

import dataclasses

import numpy as np

from livebridge.errors import InputError
from livebridge.retarget.landmarks import LandmarkSet, surface_triangles

OPENING_LANDMARKS = ("lip_", "mouth_", "eye_", "lm_")
"""Landmarks that may sit on the rim of an opening (the mouth, the eyes; iBUG ``lm_NN`` points include the lids
and the inner lips)."""
FAR_VERTEX = 1000.0
"""A vertex this many times farther from the mesh's middle than its typical vertex is thrown off the surface (a
corrupt file: a head's farthest vertex lies about twice as far as its typical one)."""


def non_manifold_edges(triangles: np.ndarray) -> np.ndarray:
    """Edges (k, 2) (sorted vertex ids) shared by more than two triangles."""
    from livebridge.face.meshio import edge_counts

    unique, counts = edge_counts(triangles)
    return unique[counts > 2]


UNWELDED_RIM_SHARE = 0.5
"""A mesh with more than this share of its edges on a rim is taken for unwelded (each triangle its own vertices,
as some exporters write them; STL files are welded as they are read): a face has rims only at its outline, mouth,
eyes and nostrils."""


WINDING_SLACK = 0.01
"""Share of a mesh's shared edges that may run the same way in both their triangles (a few flipped slivers)."""


INWARD_SHARE = 0.25
"""A mesh faces inwards when its triangles' area-weighted facing away from the vertices' centre sums below minus
this share of its magnitude (the built-in face +0.98, the ICT face region +0.87, its whole head with eyes and
mouth +0.58; flipped, as much below)."""


def check_mesh(vertices: np.ndarray, triangles: np.ndarray, source=None) -> None:
    """Raise an :class:`InputError` naming ``source`` (the mesh file) for faults of the whole mesh: a vertex thrown
    far off the rest, unwelded triangles, edges shared by more than two triangles (non-manifold), triangles wound
    every which way or all facing into the head (the transfer matches surfaces by the way they face). Triangles
    that repeat a vertex (no surface) are left out."""
    from livebridge.face.meshio import edge_counts

    triangles = _proper(np.asarray(triangles, dtype=np.int64))
    if not len(triangles):
        return
    _check_no_far_vertex(np.asarray(vertices, dtype=np.float64), triangles, source)
    edges, counts = edge_counts(triangles)
    rim_share = float(np.mean(counts == 1))
    if rim_share > UNWELDED_RIM_SHARE:
        raise InputError(f"{rim_share:.0%} of the mesh's edges belong to one triangle only: its triangles do not "
                         "share their vertices (unwelded, as some exporters write them); weld them (MeshLab: Filters > "
                         "Cleaning and Repairing > Merge Close Vertices) and place the landmarks again", source,
                         "triangles")
    bad = edges[counts > 2]
    if len(bad):
        raise InputError(f"non-manifold: {len(bad)} edge{'s' if len(bad) > 1 else ''} shared by more than two "
                         f"triangles (the first between vertices {int(bad[0][0])} and {int(bad[0][1])}; a triangle "
                         "written twice makes one too): repair the mesh (MeshLab: Filters > Cleaning and Repairing "
                         "> Remove Duplicate Faces, Repair non Manifold Edges) and place the landmarks again", source,
                         "triangles")
    _check_winding(vertices, triangles, int(np.sum(counts == 2)), source)


def _check_no_far_vertex(vertices: np.ndarray, triangles: np.ndarray, source) -> None:
    """Raise an :class:`InputError` naming ``source`` when a vertex of the ``triangles`` lies :data:`FAR_VERTEX`
    times farther from the mesh's middle (its vertices' median) than the median vertex does: every later step
    (closest points, bounding boxes, triangulations) would take it for part of the face."""
    used = np.unique(triangles)
    points = vertices[used]
    distance = np.linalg.norm(points - np.median(points, axis=0), axis=1)
    typical = float(np.median(distance))
    k = int(np.argmax(distance))
    if typical > 0 and distance[k] > FAR_VERTEX * typical:
        raise InputError(f"vertex {int(used[k])} lies {distance[k]:.3g} from the middle of the mesh, "
                         f"{distance[k] / typical:.3g} times as far as its typical vertex: a corrupt vertex (fix or "
                         "remove it)", source, "vertices")


def _check_winding(vertices: np.ndarray, triangles: np.ndarray, interior: int, source) -> None:
    """Refuse ``triangles`` (k, 3; all proper, every edge in at most two) wound inconsistently (more than
    :data:`WINDING_SLACK` of the ``interior`` edges run the same way in both their triangles) or facing inwards
    (their area-weighted normals point towards the vertices' centre: a face, a mask or a head, bulges outwards)."""
    base = int(triangles.max()) + 1
    directed = triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    _, counts = np.unique(directed[:, 0] * base + directed[:, 1], return_counts=True)
    same_way = int(np.sum(counts > 1))
    if same_way > WINDING_SLACK * max(interior, 1):
        raise InputError(f"its triangles are wound every which way ({same_way} of {interior} shared edges run the "
                         "same way in both triangles), so its normals point in and out at random: re-orient them "
                         "(MeshLab: Filters > Normals > Re-Orient all faces coherently) and place the landmarks "
                         "again", source, "triangles")
    corners = vertices[triangles]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])  # length: twice the area
    centre = vertices[np.unique(triangles)].mean(axis=0)
    outward = np.sum(normals * (corners.mean(axis=1) - centre), axis=1)
    if outward.sum() < -INWARD_SHARE * np.abs(outward).sum():  # a flat patch, neither way, passes
        raise InputError("its triangles face into the head (their normals point inwards, as after a mirroring or "
                         "a change of handedness): flip them (MeshLab: Filters > Normals > Invert Faces "
                         "Orientation) and place the landmarks again", source, "triangles")


def _proper(triangles: np.ndarray) -> np.ndarray:
    """The triangles (k, 3) whose three vertices differ."""
    return triangles[(triangles[:, 0] != triangles[:, 1]) & (triangles[:, 1] != triangles[:, 2])
                     & (triangles[:, 0] != triangles[:, 2])]


def check_landmarks_on(landmarks: LandmarkSet, vertices: np.ndarray, triangles: np.ndarray, source=None) -> None:
    """Raise an :class:`InputError` naming ``source`` (the landmark file) and the landmark when the mesh cannot
    carry a transfer at that landmark.

    Faults: a vertex of a landmark's triangle is not finite; a landmark's triangle has no area (the landmark is
    off any surface); a landmark's triangle is on the rim of a hole (a boundary edge; landmarks of the lips,
    mouth corners and eyes may sit on the mouth and eye openings); the mesh has an edge shared by more than two
    triangles (non-manifold: "the closest surface point" and the normals have no single answer there; the error
    names the landmark nearest it).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    corners = vertices[triangles[landmarks.triangles]]  # (n, 3, 3)
    for name, corner in zip(landmarks.names, corners):
        if not np.isfinite(corner).all():
            raise InputError("a vertex of this landmark's triangle is not finite", source, name)
    surface = surface_triangles(vertices, triangles)
    for name, triangle in zip(landmarks.names, landmarks.triangles):
        if not surface[triangle]:
            raise InputError(f"off the surface: its triangle {int(triangle)} has no area (its corners coincide or "
                             "lie on a line)", source, name)
    from livebridge.face.meshio import edge_counts

    edges, counts = edge_counts(_proper(triangles))
    base = len(vertices) + 1
    rim = set((edges[counts == 1, 0] * base + edges[counts == 1, 1]).tolist())
    for name, triangle in zip(landmarks.names, landmarks.triangles):
        if name.startswith(OPENING_LANDMARKS):
            continue
        a, b, c = np.sort(triangles[triangle])
        if {int(a) * base + int(b), int(b) * base + int(c), int(a) * base + int(c)} & rim:
            raise InputError(f"on the rim of a hole in the mesh: its triangle {int(triangle)} has an edge no other "
                             "triangle shares (fill the hole, or place the landmark on closed surface)", source, name)
    bad = non_manifold_edges(_proper(triangles))
    if len(bad):
        middle = vertices[bad[0]].mean(axis=0)
        positions = landmarks.positions(vertices, triangles)
        nearest = landmarks.names[int(np.argmin(np.linalg.norm(positions - middle, axis=1)))]
        raise InputError(f"the mesh is non-manifold: {len(bad)} edge{'s' if len(bad) > 1 else ''} shared by more "
                         f"than two triangles (the first between vertices {int(bad[0][0])} and {int(bad[0][1])}, "
                         f"{np.linalg.norm(positions - middle, axis=1).min():.1f} mm from this landmark); "
                         "repair the mesh (e.g. split the fan) and place the landmarks again", source, nearest)


def moved_off_rims(landmarks: LandmarkSet, vertices: np.ndarray, triangles: np.ndarray) -> LandmarkSet:
    """``landmarks`` with each one on a triangle at the rim of a hole (besides those of the openings,
    :data:`OPENING_LANDMARKS`) moved to the nearest point of a triangle off every rim, when that lies within one
    median edge of it: a scan's grid has small holes where its scan had none of its points (dark brows), and a
    landmark on their rim would be refused by :func:`check_landmarks_on` in every transfer."""
    from livebridge.face.meshio import edge_counts, median_edge_length, rim_vertices
    from livebridge.retarget.landmarks import closest_surface_points

    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    rim_triangles = np.isin(triangles, rim_vertices(_proper(triangles))).any(axis=1)
    moving = [k for k, name in enumerate(landmarks.names)
              if rim_triangles[landmarks.triangles[k]] and not name.startswith(OPENING_LANDMARKS)]
    inner = np.flatnonzero(~rim_triangles & surface_triangles(vertices, triangles))
    if not moving or not len(inner):
        return landmarks
    positions = landmarks.positions(vertices, triangles)[moving]
    triangle, barycentric, distance = closest_surface_points(positions, vertices, triangles[inner])
    edge = median_edge_length(vertices, edge_counts(_proper(triangles))[0])
    new_triangles, new_barycentric = landmarks.triangles.copy(), landmarks.barycentric.copy()
    for k, t, b, d in zip(moving, inner[triangle], barycentric, distance):
        if d <= edge:
            new_triangles[k], new_barycentric[k] = t, b
    return dataclasses.replace(landmarks, triangles=new_triangles, barycentric=new_barycentric)


def check_faces(triangles: np.ndarray, n_points: int, path) -> None:
    """A mesh file's triangles (m, 3) index its ``n_points`` vertices: else an error naming ``path`` and the first
    vertex index that does not exist."""
    if not len(triangles):
        return
    bad = np.flatnonzero((triangles < 0).any(axis=1) | (triangles >= n_points).any(axis=1))
    if len(bad):
        raise InputError(f"a face refers to vertex {int(triangles[bad[0]].max())}, which does not exist "
                         f"(vertices 0..{n_points - 1}; {len(bad)} such triangles)", path, "face")
