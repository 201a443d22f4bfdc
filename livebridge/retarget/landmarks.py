"""Named facial landmarks on any mesh: the 22 of the thesis, shipped sets, and placing them on a user's mesh.

A landmark set is a marker set (:class:`~livebridge.face.markers.MarkerSet`): each landmark is a triangle
index plus barycentric coordinates, so it follows any deformation of the mesh, and its file is a
``livebridge-markers`` TOML file read and validated by the same code. (One format, not two: a landmark file
is also a valid ``--markers`` file, and a marker set whose names are landmark names is a landmark set.)

The 22 landmarks of Erdoğdu's thesis (Figure 5-2, the Bosphorus database's labels) are named here by the
subject's side (``_L``: the subject's left, +x in livebridge's frame, as ICT-FaceKit's ``_L`` shapes) and
placed from the 68 Multi-PIE/iBUG landmarks (:data:`THESIS_22`): 20 of them coincide with an iBUG point;
the two nose saddles (the sides of the nasal root) are the surface points nearest the midpoint of the
upper nose bridge (iBUG 28) and that side's inner eye corner (39, 42).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from livebridge.errors import InputError
from livebridge.face.markers import LANDMARKS_68_UPPER, MarkerSet, landmark_name
from livebridge.face.meshio import triangle_areas
from livebridge.retarget.point_files import POINT_FILE_SUFFIXES
from livebridge.tomlio import load_toml

DATA = Path(__file__).parent / "data"
SHIPPED_LANDMARK_SETS = ("builtin-22", "ict-22", "builtin-68", "ict-68")
"""Landmark sets shipped with livebridge, by name: the 22 thesis landmarks on the built-in face and on the
ICT-FaceKit face region (as ``livebridge basis import choe-ko-ict`` builds it), and the 68 Multi-PIE/iBUG
landmarks on the same two faces (the shipped marker sets of those names): any landmark detector's 68 points
pin the proportions between the thesis's 22 (the jaw line, the lips, the nose) and transfer better."""

SADDLE = "saddle"
THESIS_22 = (
    # (name, iBUG number it is taken from; SADDLE: between 28 and this inner eye corner)
    ("brow_outer_L", 26), ("brow_middle_L", 24), ("brow_inner_L", 22),
    ("brow_inner_R", 21), ("brow_middle_R", 19), ("brow_outer_R", 17),
    ("eye_outer_L", 45), ("eye_inner_L", 42), ("eye_inner_R", 39), ("eye_outer_R", 36),
    ("nose_saddle_L", (SADDLE, 42)), ("nose_saddle_R", (SADDLE, 39)),
    ("nose_peak_L", 35), ("nose_tip", 30), ("nose_peak_R", 31),
    ("mouth_corner_L", 54), ("lip_upper_outer", 51), ("mouth_corner_R", 48),
    ("lip_upper_inner", 62), ("lip_lower_inner", 66), ("lip_lower_outer", 57),
    ("chin", 8),
)
"""The thesis's 22 landmarks in its order (1-22) and where each comes from in the 68-point iBUG layout
(the subject's right is iBUG's first: 17-21 right brow outer to inner, 36/39 right eye outer/inner corner,
31 the right nostril wing, 48 the right mouth corner)."""
THESIS_22_NAMES = tuple(name for name, _ in THESIS_22)
SADDLE_BRIDGE = 28  # iBUG: the upper nose bridge, between the eyes
JAW_LINE_68 = range(17)
"""iBUG 0-16: the jaw line, ear to ear round the chin."""
MIRROR_PAIRS = tuple((name, name[:-1] + "R") for name in THESIS_22_NAMES if name.endswith("_L"))
"""(left, right) name pairs of the 22: mirror images on a symmetric face."""


class LandmarkSet(MarkerSet):
    """Named landmarks on a mesh (a :class:`MarkerSet`; see the module docstring)."""

    @classmethod
    def of(cls, markers: MarkerSet) -> LandmarkSet:
        """A marker set's points as a landmark set (same names, places, regions, roles, mesh)."""
        return cls(markers.names, markers.triangles, markers.barycentric, markers.regions, markers.roles,
                   markers.mesh_triangles)

    def index_of(self, names) -> np.ndarray:
        """Positions in this set of ``names``, shape (len(names),); a missing one raises naming them all."""
        where = {name: k for k, name in enumerate(self.names)}
        missing = [name for name in names if name not in where]
        if missing:
            raise InputError(f"{len(missing)} landmark{'s' if len(missing) > 1 else ''} missing: "
                             f"{', '.join(missing)}", field="landmarks")
        return np.array([where[name] for name in names], dtype=np.int64)

    def require_thesis_22(self, source=None) -> None:
        """Raise, naming ``source`` and the missing landmarks, unless all 22 thesis landmarks are here."""
        try:
            self.index_of(THESIS_22_NAMES)
        except InputError as error:
            raise InputError(error.message + " (of the thesis's 22)", source, error.field) from None

    def checked_on(self, n_triangles: int, source=None) -> LandmarkSet:
        """This set, after checking every triangle exists on a mesh of ``n_triangles``; errors name ``source``."""
        try:
            self.check_mesh(n_triangles)
        except InputError as error:
            raise InputError(error.message, source, error.field) from None
        return self

    def as_dict(self, vertices: np.ndarray, triangles: np.ndarray) -> dict[str, np.ndarray]:
        """``{name: position (3,)}`` on a mesh (neutral or deformed)."""
        return dict(zip(self.names, self.positions(vertices, triangles)))


# ------------------------------------------------------------------------------------------------ shipped sets
def load_landmark_set(spec: str | Path) -> LandmarkSet:
    """A landmark set by shipped name (:data:`SHIPPED_LANDMARK_SETS`) or from a landmark (marker-set) TOML file."""
    if isinstance(spec, str) and spec.endswith("-68") and spec in SHIPPED_LANDMARK_SETS:
        from livebridge.face.shipped import shipped_marker_set

        return LandmarkSet.of(shipped_marker_set(spec))
    if isinstance(spec, str) and spec in SHIPPED_LANDMARK_SETS:
        return LandmarkSet.load(DATA / f"{spec.replace('-', '_')}.toml")
    if Path(spec).suffix.lower() in set(POINT_FILE_SUFFIXES) - {".toml"}:
        raise InputError("points, not a landmark set: place them on the mesh first with `livebridge landmarks place "
                         f"MESH --points {Path(spec).name} --out landmarks.toml`", spec, "landmarks")
    return LandmarkSet.load(spec)


def thesis_22_from_68(markers_68: MarkerSet, vertices: np.ndarray, triangles: np.ndarray) -> LandmarkSet:
    """The thesis's 22 landmarks from a 68-point iBUG marker set on the same mesh (see :data:`THESIS_22`).

    The 20 that coincide with an iBUG point copy its triangle, barycentric coordinates, region and role;
    each nose saddle is the surface point nearest the midpoint of iBUG 28 and that side's inner eye corner.

    Parameters
    ----------
    markers_68 : MarkerSet
        Names ``lm_00`` .. ``lm_67`` (:func:`~livebridge.face.markers.landmark_name`).
    vertices : ndarray, shape (n_vertices, 3)
    triangles : ndarray of int, shape (n_triangles, 3)
    """
    where = {name: k for k, name in enumerate(markers_68.names)}
    missing = [landmark_name(i) for i in range(68) if landmark_name(i) not in where]
    if missing:
        raise InputError(f"not a 68-point set: {', '.join(missing[:5])} missing", field="markers")
    positions = markers_68.positions(vertices, triangles)
    rows = {"triangles": [], "barycentric": [], "regions": [], "roles": []}
    for _, source in THESIS_22:
        number = SADDLE_BRIDGE if isinstance(source, tuple) else source
        k = where[landmark_name(number)]
        triangle, barycentric = markers_68.triangles[k], markers_68.barycentric[k]
        if isinstance(source, tuple):
            middle = 0.5 * (positions[k] + positions[where[landmark_name(source[1])]])
            snapped, bary, _ = closest_surface_points(middle[None], vertices, triangles)
            triangle, barycentric = snapped[0], bary[0]
        for key, value in zip(rows, (triangle, barycentric, markers_68.regions[k], markers_68.roles[k])):
            rows[key].append(value)
    return LandmarkSet(THESIS_22_NAMES, **rows, mesh_triangles=markers_68.mesh_triangles)


def thesis_points_from_68(points: dict[str, np.ndarray], surface: np.ndarray, source=None) -> dict[str, np.ndarray]:
    """``points`` (name to (3,)) with the thesis's 22 names where a 68-point iBUG file numbers them instead.

    A landmark detector writes ``lm_00`` .. ``lm_67`` (:func:`~livebridge.face.markers.landmark_name`); each
    thesis name that is missing while its iBUG point (:data:`THESIS_22`) is there takes that point, which is then
    dropped (the two would be one control point twice). A nose saddle is the point of ``surface`` (n, 3; the
    scan's points) nearest the midpoint of iBUG 28 and that side's inner eye corner. The jaw line
    (:data:`JAW_LINE_68`) is left out: it runs round the face's outline to the ears, out of the face crop. A
    number over 67 (a file counted from 1) is an error naming ``source``. Every other point is kept: the brows',
    eyes', nose's and lips' contours join the landmark spline (on the bench's ICT scans without colour, seed 7 at
    60k points, mean relative RMS error 0.496 against 0.518 from the 22), the lids' (``lm_37`` ...) feed
    :mod:`~livebridge.retarget.eyelids` and join the spline only of a tracked warp
    (:func:`~livebridge.retarget.scans.shape_element`)."""
    beyond = sorted(name for name in points if name.startswith("lm_") and name[3:].isdigit() and int(name[3:]) > 67)
    if beyond:  # one too high throughout, silently, if read as they are
        raise InputError(f"{beyond[0]}: the 68 iBUG points are numbered lm_00 ... lm_67 (from 0, as dlib does); "
                         "a file numbered from 1 needs every number lowered by one", source, beyond[0])
    surface = np.asarray(surface, dtype=np.float64)
    out = dict(points)
    used = set()
    for name, origin in THESIS_22:
        if name in points:
            continue
        if isinstance(origin, tuple):
            ends = [landmark_name(SADDLE_BRIDGE), landmark_name(origin[1])]
            if all(end in points for end in ends) and len(surface):
                middle = 0.5 * (np.asarray(points[ends[0]], float) + np.asarray(points[ends[1]], float))
                nearest = np.argmin(np.einsum("nd,nd->n", surface - middle, surface - middle))
                out[name] = np.asarray(surface[nearest], dtype=np.float64)
        elif landmark_name(origin) in points:
            out[name] = np.asarray(points[landmark_name(origin)], dtype=np.float64)
            used.add(landmark_name(origin))
    outline = {landmark_name(number) for number in JAW_LINE_68}
    return {name: xyz for name, xyz in out.items() if name not in used and name not in outline}


# ------------------------------------------------------------------------------------------------ the surface
CLOSEST_CHUNK = 32768
"""Points are matched to the surface this many at a time: each holds some 40 candidate triangles' corners, and
a 600k-vertex target at once took 4.8 GB."""


def closest_surface_points(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray, near: int = 8,
                           normals: np.ndarray | None = None, min_cos: float = 0.0):
    """The closest point on a triangle mesh to each point, as triangle + barycentric coordinates.

    Searched among the triangles incident to the ``near`` mesh vertices nearest each point (scipy cKDTree).
    With ``normals``, only triangles facing the same way as the point's normal (cosine above ``min_cos``) are
    taken while any candidate does: the two sides of a closed lip seam, or of a thin lid, lie within a
    fraction of a millimetre of each other but face opposite ways.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    vertices : ndarray, shape (n_vertices, 3)
    triangles : ndarray of int, shape (n_triangles, 3)
    near : int
    normals : ndarray, shape (n, 3), optional
        Unit normals at ``points`` (of the surface the points come from).
    min_cos : float

    Returns
    -------
    triangle : ndarray of int, shape (n,)
    barycentric : ndarray, shape (n, 3)
        Non-negative, summing to 1.
    distance : ndarray, shape (n,)
        From each point to its closest surface point.
    """
    from scipy.sparse import csr_matrix
    from scipy.spatial import cKDTree

    points, vertices = np.asarray(points, dtype=np.float64).reshape(-1, 3), np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    if not len(points):
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0)
    normals = None if normals is None else np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    used = np.unique(triangles)  # vertices in no triangle cannot lead to the surface
    tree = cKDTree(vertices[used])
    incidence = csr_matrix((np.ones(triangles.size), (triangles.ravel(), np.repeat(np.arange(len(triangles)), 3))),
                           shape=(len(vertices), len(triangles)))
    parts = [_closest_among_near(points[start:start + CLOSEST_CHUNK], vertices, triangles, used, tree, incidence,
                                 min(near, len(used)),
                                 None if normals is None else normals[start:start + CLOSEST_CHUNK], min_cos)
             for start in range(0, len(points), CLOSEST_CHUNK)]
    return tuple(np.concatenate(arrays) for arrays in zip(*parts))


def surface_values(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray, values: np.ndarray
                   ) -> np.ndarray:
    """A per-vertex field ``values`` (n_vertices, d) of a mesh read at each of ``points`` (n, 3)'s closest surface
    place (:func:`closest_surface_points`, barycentric in its triangle), shape (n, d); ``values`` = ``vertices``
    snaps the points onto the surface."""
    triangle, barycentric, _ = closest_surface_points(points, vertices, triangles)
    return np.einsum("nk,nkd->nd", barycentric, np.asarray(values)[np.asarray(triangles)[triangle]])


def _closest_among_near(points, vertices, triangles, used, tree, incidence, k: int, normals, min_cos: float):
    """:func:`closest_surface_points` for one chunk of points, the mesh's vertex tree and vertex-triangle
    incidence given."""
    from scipy.sparse import csr_matrix

    _, nearest = tree.query(points, k=k)
    # a point so far off (1e300 mm) that its distance overflows has no neighbour: cKDTree answers len(used);
    # any vertex will do, the distance below is then infinite and the caller refuses it
    nearest = used[np.minimum(np.asarray(nearest).reshape(len(points), k), len(used) - 1)]
    selection = csr_matrix((np.ones(nearest.size), (np.repeat(np.arange(len(points)), k), nearest.ravel())),
                           shape=(len(points), len(vertices)))
    point_of, triangle_of = (selection @ incidence).nonzero()
    corners = vertices[triangles[triangle_of]]
    barycentric = _closest_on_triangles(points[point_of], corners)
    distance = np.linalg.norm(np.einsum("nk,nkd->nd", barycentric, corners) - points[point_of], axis=1)
    disagrees = np.zeros(len(distance), dtype=bool)
    if normals is not None:
        facing = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        facing /= np.maximum(np.linalg.norm(facing, axis=1, keepdims=True), np.finfo(float).tiny)
        along = np.einsum("nd,nd->n", facing, normals[point_of])
        disagrees = along <= min_cos
    order = np.lexsort((distance, disagrees, point_of))  # per point: agreeing first, then nearest first
    first = order[np.r_[True, point_of[order][1:] != point_of[order][:-1]]]
    return triangle_of[first], barycentric[first], distance[first]


def _closest_on_triangles(p: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Barycentric coordinates, shape (n, 3), of the closest point to ``p (n, 3)`` on triangles ``(n, 3, 3)``.

    Ericson, *Real-Time Collision Detection*, 5.1.5: the Voronoi region of the triangle holding ``p``'s
    closest point (a corner, an edge, or the face).
    """
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c

    def dot(u, v):
        return np.einsum("nd,nd->n", u, v)

    d1, d2, d3, d4, d5, d6 = dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        total = va + vb + vc
        out = np.stack([va / total, vb / total, vc / total], axis=1)  # inside the face
        edge_ab, edge_ac, edge_bc = d1 / (d1 - d3), d2 / (d2 - d6), (d4 - d3) / ((d4 - d3) + (d5 - d6))
    cases = [  # later cases take precedence, as the early returns of Ericson's routine
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), lambda: np.stack([0 * va, 1 - edge_bc, edge_bc], 1)),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), lambda: np.stack([1 - edge_ac, 0 * va, edge_ac], 1)),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), lambda: np.stack([1 - edge_ab, edge_ab, 0 * va], 1)),
        ((d6 >= 0) & (d5 <= d6), lambda: np.tile([0.0, 0.0, 1.0], (len(p), 1))),
        ((d3 >= 0) & (d4 <= d3), lambda: np.tile([0.0, 1.0, 0.0], (len(p), 1))),
        ((d1 <= 0) & (d2 <= 0), lambda: np.tile([1.0, 0.0, 0.0], (len(p), 1))),
    ]
    for mask, value in cases:
        if mask.any():
            with np.errstate(divide="ignore", invalid="ignore"):
                out[mask] = value()[mask]
    out = np.clip(np.nan_to_num(out, nan=1.0 / 3.0), 0.0, 1.0)  # a degenerate (zero-area) triangle: its centre
    return out / out.sum(axis=1, keepdims=True)


# ------------------------------------------------------------------------------------------------ placing
def _region(name: str) -> str:
    """``upper`` for brow and eye landmarks (thesis names, or iBUG ``lm_NN`` numbers), else ``lower``."""
    sources = dict(THESIS_22)
    source = sources.get(name)
    if name.startswith("lm_") and name[3:].isdigit():
        source = int(name[3:])
    return "upper" if isinstance(source, int) and source in LANDMARKS_68_UPPER else "lower"


def place_at_vertices(vertex_ids: dict[str, int], n_vertices: int, triangles: np.ndarray,
                      source=None, vertices: np.ndarray | None = None) -> LandmarkSet:
    """Landmarks exactly at mesh vertices (``{name: vertex id}``); errors name ``source`` and the landmark.

    Parameters
    ----------
    vertex_ids : dict of str to int
    n_vertices : int
    triangles : ndarray of int, shape (n_triangles, 3)
    source : str or Path, optional
        The file the ids came from, named in errors.
    vertices : ndarray, shape (n_vertices, 3), optional
        When given, each landmark takes the largest of its vertex's triangles: a sliver there (a scanner's or an
        exporter's, :func:`surface_triangles` says which) is no surface, and a landmark on it is refused by every
        transfer.
    """
    triangles = np.asarray(triangles, dtype=np.int64)
    areas = None
    if vertices is not None:
        areas = np.where(surface_triangles(vertices, triangles), triangle_areas(vertices, triangles), -1.0)
    chosen, bary = [], []
    for name, vertex in vertex_ids.items():
        rows, corners = np.nonzero(triangles == vertex)
        if not len(rows):
            why = "is in no triangle of the mesh" if 0 <= vertex < n_vertices else "does not exist"
            raise InputError(f"vertex {vertex} {why} (mesh vertices 0..{n_vertices - 1})", source, name)
        best = 0
        if areas is not None:
            best = int(np.argmax(areas[rows]))
            if not areas[rows[best]] > 0:
                raise InputError(f"vertex {vertex} is only in triangles with no area, or too little to be surface "
                                 "(their corners coincide or lie on a line, or all but): no surface there", source,
                                 name)
        chosen.append(int(rows[best]))
        bary.append(np.eye(3)[corners[best]])
    names = tuple(vertex_ids)
    return LandmarkSet(names, np.array(chosen), np.array(bary).reshape(-1, 3), tuple(map(_region, names)),
                       ("face",) * len(names))


FAR_MESH_SIZES = 1000.0
"""A point this many mesh sizes outside the mesh's bounds is refused by that gap alone (see
:func:`place_at_points`)."""
DEGENERATE_AREA = 1e-12
"""A triangle with less area than this fraction of the mesh's median triangle area has no surface (a scanner's or
an exporter's sliver, a face written with a repeated corner)."""


def surface_triangles(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Mask (n_triangles,) of the triangles that are surface: finite, with more than :data:`DEGENERATE_AREA` of the
    median triangle's area (the median, not the mean: one vertex thrown 1e30 mm away makes the mean any size)."""
    areas = triangle_areas(vertices, triangles)
    finite = np.isfinite(areas)
    typical = float(np.median(areas[finite])) if finite.any() else 0.0
    return finite & (areas > DEGENERATE_AREA * typical)


def place_at_points(points: dict[str, np.ndarray], vertices: np.ndarray, triangles: np.ndarray,
                    max_distance: float, source=None, units: str = "mm") -> LandmarkSet:
    """Landmarks at the surface points nearest 3D points (``{name: (3,)}``).

    A point farther than ``max_distance`` from the surface is an error naming ``source``, the landmark and
    how far it is (in ``units``).
    """
    names = tuple(points)
    xyz = np.array([points[n] for n in names], dtype=np.float64)
    # the largest gap to the mesh's bounding box along any axis, a lower bound of the distance found without
    # squaring: a point thousands of mesh sizes away (1e300 mm) would overflow the closest-point search
    extent = float(np.ptp(vertices, axis=0).max())
    outside = np.maximum(vertices.min(axis=0) - xyz, xyz - vertices.max(axis=0)).clip(min=0.0).max(axis=1)
    if (outside > max(max_distance, FAR_MESH_SIZES * extent)).any():
        k = int(np.argmax(outside))
        raise InputError(f"more than {outside[k]:.3g} {units} from the mesh surface (at most {max_distance:g} "
                         f"{units}): outside the mesh's bounds (same coordinates and units as the mesh?)",
                         source, names[k])
    # a sliver lies on its neighbours' edges, as near as they are: a landmark placed on it would be refused
    surface = np.flatnonzero(surface_triangles(vertices, triangles))
    if not len(surface):
        raise InputError("the mesh has no triangle with area: no surface to place landmarks on", source)
    triangle, barycentric, distance = closest_surface_points(xyz, vertices, np.asarray(triangles)[surface])
    triangle = surface[triangle]
    far = np.flatnonzero(distance > max_distance)
    if far.size:
        k = int(far[np.argmax(distance[far])])
        every = " (all of them: same coordinates and units as the mesh?)" if far.size == len(names) > 1 else ""
        raise InputError(f"{distance[k]:.3g} {units} from the mesh surface (at most {max_distance:g} {units}); "
                         f"{len(far)} point{'s' if far.size > 1 else ''} this far{every}", source, names[k])
    return LandmarkSet(names, triangle, barycentric, tuple(map(_region, names)), ("face",) * len(names))


def read_vertex_ids(path: str | Path) -> dict[str, int]:
    """``name = vertex id`` lines of a TOML file, in file order."""
    data = load_toml(path)
    if not data:
        raise InputError("no landmarks (expected lines like 'nose_tip = 1234')", path)
    for name, value in data.items():
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(f"expected a vertex id (a whole number), got {value!r}", path, name)
        if value < 0:
            raise InputError(f"expected a vertex id >= 0, got {value}", path, name)
    return dict(data)
