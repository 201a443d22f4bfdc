"""Basis retargeting: every element of an actuation basis carried onto another face (any topology) by a TPS.

A landmark thin-plate spline ``f`` maps the source neutral face onto the target neutral face. Each target
vertex ``v`` finds its source surface point ``p`` through the inverse spline ``g`` (fitted target -> source on
the same landmarks) followed by the closest point on the source surface; the source element's displacement
``d`` there (barycentric interpolation) becomes ``f(p + d) - f(p)`` on the target, so the motion follows the
local scale and proportions of ``f``. Upper- and lower-face elements use the same ``f`` (the thesis warps the
two regions separately when animating, §5.6; a basis element is already confined to its region).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.face.meshio import edge_counts, median_edge_length, rim_vertices, triangle_normals, vertex_normals
from livebridge.retarget.inner_parts import BoneParts, bone_parts, jaw_turners, on_bones
from livebridge.retarget.landmarks import LandmarkSet, closest_surface_points
from livebridge.retarget.tps import Kernel, ThinPlateSpline, fit_tps

SURFACE_SAMPLES = 150
"""Points spread over each surface to pin the spline onto the other surface (:func:`surface_splines`)."""
SURFACE_ROUNDS = 2
SURFACE_SMOOTHING = 8.0
"""Smoothing (:func:`~livebridge.retarget.tps.fit_tps`) of the surface-pinned splines, mm for the ``r`` kernel
(other kernels: :func:`smoothing`)."""
BOUNDARY_STEP = 0.2
"""How far a boundary vertex looks into its own triangles for its point on the other face (:func:`inside_boundary`)."""
CORRESPOND_NEAR = 5
"""Nearest source vertices whose triangles are searched for each target vertex's closest point."""
STRETCH_LIMIT = 1.6
"""Largest local stretch of a carried motion, relative to the landmark map's overall scale (either way)."""
COVERED, UNCOVERED = 0.02, 0.08
"""A target vertex farther than these fractions of the face from the source surface starts to / stops moving."""
LINEAR_MOVE = 0.03
"""Moves shorter than this fraction of the landmarks' extent are carried by the spline's Jacobian."""
PAIR_SPACING = 0.01
"""Closest two control points of a surface-pinned spline, as a fraction of the landmarks' extent."""
NORMAL_WEIGHT = 0.25
"""Weight of a difference of unit normals against distance when a surface pin finds its partner on the other
surface (:class:`SurfaceMatcher`), as a fraction of the landmarks' extent."""
PAIR_GAP, PAIR_RIM_GAP = COVERED, UNCOVERED
"""A source sample carried past the target's outline by more than the first of these fractions of the landmarks'
extent (the second for a sample on the source's own rim: two outlines of one topology meet rim to rim) has no
partner there and pins nothing (:func:`surface_splines`)."""
TARGET_PAIR_GAP = 0.12
"""A target sample carried past the source's outline by more than this fraction of the landmarks' extent pins
nothing: a whole face beyond a scan's tight crop, pinned to the crop's rim, stretched a scanned person's jaw 2-4x
onto their own face. Nearer, it stays pinned to the rim (a whole head's mouth bag onto a face's lips: without
those pins ICT's smile on its whole head was 0.45 off instead of 0.29)."""
SLIDE_LIMIT = 0.04
"""Farthest a surface pin slides along the surface from its closest point towards its like-facing match
(:class:`SurfaceMatcher`), as a fraction of the landmarks' extent: a different face's cheek may bend like a
far-off part of the source; a pin may slide to correct the landmark spline, not jump."""
SMOOTHING_LENGTH = 0.1
"""Length, as a fraction of the landmarks' extent, at which the smoothing of a surface-pinned spline is
expressed in the kernel's units (:func:`smoothing`)."""
SAMPLED_MOTION = 0.01
"""Surface pins are spread over the vertices an element moves by more than this fraction of its largest move."""
JACOBIAN_REACH = 0.11
"""How far the spline's Jacobian is averaged over the target (:func:`smooth_jacobian`), a fraction of the
landmarks' extent (15 mm on a face)."""
MAX_DIFFUSION_STEPS = 2000
DIFFUSION_CELL = 0.1
"""A target mesh with edges shorter than this fraction of the averaging's reach is averaged over cells this wide
(:func:`surface_average`): 1.5 mm on a face, below the 2-3 mm edges of ICT-FaceKit's face (and of its narrower
warped copy in `livebridge bench retarget`) and of the built-in face, which are averaged over their own edges."""
JUMP_START, JUMP_FULL = 1.5, 3.0
"""Two neighbouring target vertices whose source points lie this many times farther apart than the vertices
themselves (carried into source space) start to be / are fully smoothed (:func:`smooth_jumps`)."""
JUMP_SMOOTHING = 30
"""Diffusion steps of :func:`smooth_jumps` (each reaches one more ring of neighbours)."""
JUMP_SPREAD = 2
"""Rings of neighbours around a jump that are smoothed with it."""


@dataclass(frozen=True)
class Correspondence:
    """Where each target vertex lies on the source surface.

    Attributes
    ----------
    triangle : ndarray of int, shape (n_target_vertices,)
        Source triangle.
    barycentric : ndarray, shape (n_target_vertices, 3)
    distance : ndarray, shape (n_target_vertices,)
        From the target vertex carried into source space (by ``g``) to that surface point, mm: large values
        mark target regions the source face does not cover.
    """

    triangle: np.ndarray
    barycentric: np.ndarray
    distance: np.ndarray
    carried: np.ndarray | None = None
    """(n_target_vertices, 3): the target vertices carried into source space, whose surface points these are."""

    def interpolate(self, values: np.ndarray, triangles: np.ndarray) -> np.ndarray:
        """Per-vertex ``values (..., n_source_vertices, 3)`` at the surface points, shape (..., n_target, 3)."""
        corners = values[..., triangles[self.triangle], :]  # (..., n_target, 3 corners, 3)
        return np.einsum("nk,...nkd->...nd", self.barycentric, corners)


def landmark_pairs(source_landmarks: LandmarkSet, source_mesh, target_landmarks: LandmarkSet,
                   target_mesh) -> tuple[np.ndarray, np.ndarray]:
    """(source positions (n, 3), target positions (n, 3)) of the source set's landmarks, matched by name.

    ``*_mesh`` are (vertices, triangles). Every landmark of the source set must be in the target set.
    """
    index = target_landmarks.index_of(source_landmarks.names)
    source = source_landmarks.positions(*source_mesh)
    target = target_landmarks.positions(*target_mesh)[index]
    return source, target


def landmark_splines(source_points: np.ndarray, target_points: np.ndarray,
                     kernel: Kernel | str = Kernel.BIHARMONIC) -> tuple[ThinPlateSpline, ThinPlateSpline]:
    """(``f`` source -> target, ``g`` target -> source): the two landmark splines of a transfer."""
    return fit_tps(source_points, target_points, kernel), fit_tps(target_points, source_points, kernel)


def correspond(target_vertices: np.ndarray, target_triangles: np.ndarray, to_source: ThinPlateSpline,
               source_vertices: np.ndarray, source_triangles: np.ndarray) -> Correspondence:
    """Each target vertex's point on the source surface: ``g(v)`` snapped to the closest surface point that
    faces the same way (the normal of the target mesh carried by ``g``), so the two lips of a closed mouth,
    or the two sides of a lid, each find their own side."""
    carried = to_source(inside_boundary(target_vertices, target_triangles))
    normals = vertex_normals(carried, target_triangles)
    triangle, barycentric, distance = closest_surface_points(carried, source_vertices, source_triangles,
                                                             near=CORRESPOND_NEAR, normals=normals)
    return Correspondence(triangle, barycentric, distance, carried)


def inside_boundary(vertices: np.ndarray, triangles: np.ndarray, step: float = BOUNDARY_STEP) -> np.ndarray:
    """``vertices`` (n, 3) with each seam vertex moved ``step`` of the way towards the centroid of its triangles'
    centroids (the others unchanged): a seam vertex is on a boundary edge and has a twin, another boundary
    vertex within a tenth of the median edge length.

    A seam cut through a mesh (the built-in face's closed mouth: the vertices between the mouth corners are
    doubled) leaves two coincident copies of each seam vertex, one in the upper lip, one in the lower lip,
    facing the same way; moved into its own triangles each copy finds its own lip on the other face.
    """
    unique, counts = edge_counts(triangles)
    boundary = np.unique(unique[counts == 1])
    if len(boundary) < 2:
        return vertices
    from scipy.spatial import cKDTree

    twin_distance = cKDTree(vertices[boundary]).query(vertices[boundary], k=2)[0][:, 1]
    edge = median_edge_length(vertices, unique)
    boundary = boundary[twin_distance < 0.1 * edge]
    if not len(boundary):
        return vertices
    centroids = vertices[triangles].mean(axis=1)  # (n_triangles, 3)
    total = np.zeros_like(vertices)
    count = np.zeros(len(vertices))
    for corner in range(3):
        np.add.at(total, triangles[:, corner], centroids)
        np.add.at(count, triangles[:, corner], 1.0)
    moved = vertices.copy()
    inner = total[boundary] / np.maximum(count[boundary], 1.0)[:, None]
    moved[boundary] += step * (inner - vertices[boundary])
    return moved


def surface_splines(source_points: np.ndarray, target_points: np.ndarray, source_mesh, target_mesh,
                    kernel: Kernel | str = Kernel.BIHARMONIC, samples: int = SURFACE_SAMPLES,
                    rounds: int = SURFACE_ROUNDS, source_region: np.ndarray | None = None,
                    ) -> tuple[ThinPlateSpline, ThinPlateSpline]:
    """(``f``, ``g``) fitted through the landmarks and through surface pairs, so each maps surface onto surface.

    The landmark splines bend the space between the landmarks as little as they can, which leaves the source
    surface floating above or sunk below the target's between them, and slid sideways along it; the tangent
    planes, and with them the direction of every carried displacement, tilt, and each target point takes its
    motion from a source spot millimetres to the side. Each round spreads ``samples`` points over each surface
    (over ``source_region`` and the part of the target it covers, when given), carries them with the current
    spline to the other surface, where each finds the surface point nearest in place and in facing
    (:class:`SurfaceMatcher`: the same bend of a cheek, a jaw line, a brow), and refits through the landmarks
    and these pairs (smoothed: the pairs are approximate).

    ``*_mesh`` are (vertices, triangles); the points are (n, 3) landmark positions matched row by row;
    ``source_region`` (n_source_vertices,) bool: where the surfaces must match best (where the basis moves).
    """
    kernel = Kernel.parse(kernel)
    to_target, to_source = landmark_splines(source_points, target_points, kernel)
    if rounds <= 0 or samples <= 0:
        return to_target, to_source
    source_extent, extent = (float(np.ptp(points, axis=0).max()) for points in (source_points, target_points))
    spacing = PAIR_SPACING * extent
    target_region = None if source_region is None else covered_region(target_mesh, to_source, source_mesh,
                                                                         source_region)
    source_samples = spread_surface_points(source_mesh, samples, source_region)
    target_samples = spread_surface_points(target_mesh, samples, target_region)
    source_on_rim = np.isin(source_samples[2], rim_vertices(source_mesh[1]))
    onto_source_surface = SurfaceMatcher(source_mesh, NORMAL_WEIGHT * source_extent)
    onto_target_surface = SurfaceMatcher(target_mesh, NORMAL_WEIGHT * extent)
    for _ in range(rounds):
        onto_target, off_target = onto_target_surface.carry(*source_samples[:2], to_target)
        onto_source, off_source = onto_source_surface.carry(*target_samples[:2], to_source)
        # a sample carried past the other surface's outline (a face mask's sides onto a scan cropped tighter, a
        # whole face onto a scan's crop) has no partner there: pinned to the rim tens of mm off, it folds the
        # splines
        on_target = _partnered(off_target, source_on_rim, extent)
        on_source = off_source <= TARGET_PAIR_GAP * source_extent
        pairs_source = np.vstack([source_points, source_samples[0][on_target], onto_source[on_source]])
        pairs_target = np.vstack([target_points, onto_target[on_target], target_samples[0][on_source]])
        keep = spaced(pairs_source, pairs_target, spacing, first=len(source_points))
        to_target = fit_tps(pairs_source[keep], pairs_target[keep], kernel, smoothing(kernel, extent))
        to_source = fit_tps(pairs_target[keep], pairs_source[keep], kernel, smoothing(kernel, source_extent))
    return to_target, to_source


def smoothing(kernel: Kernel, extent: float) -> float:
    """The regularisation of a surface-pinned spline for ``kernel`` on landmarks ``extent`` mm across:
    :data:`SURFACE_SMOOTHING` times ``U(l) / l`` at ``l`` = :data:`SMOOTHING_LENGTH` of the extent.

    The regulariser adds to the kernel matrix, whose entries are mm for ``U = r`` but mm^2 (times a log) for
    ``r^2 ln r^2``: the same number would smooth the second kernel hundreds of times less. Measured as a kernel
    value per length, both smooth alike (``U = r``: exactly :data:`SURFACE_SMOOTHING`).
    """
    length = SMOOTHING_LENGTH * extent
    value = float(kernel.matrix(np.zeros((1, 3)), np.array([[length, 0.0, 0.0]]))[0, 0])
    return SURFACE_SMOOTHING * abs(value) / length if length > 0 else SURFACE_SMOOTHING


def covered_region(target_mesh, to_source: ThinPlateSpline, source_mesh, source_region: np.ndarray) -> np.ndarray:
    """Target vertices (n_target_vertices,) bool whose nearest source vertex, once carried by ``to_source``, is in
    ``source_region`` (n_source_vertices,) bool."""
    from scipy.spatial import cKDTree

    used = np.unique(source_mesh[1])
    _, nearest = cKDTree(source_mesh[0][used]).query(to_source(target_mesh[0]))
    return np.asarray(source_region, dtype=bool)[used[nearest]]


def _partnered(off: np.ndarray, on_rim: np.ndarray, extent: float) -> np.ndarray:
    """Which carried samples (k,) have a partner on the other surface: the offset ``off`` (k,) of each past the
    other surface's outline within :data:`PAIR_GAP` of ``extent``, or within :data:`PAIR_RIM_GAP` for a sample
    on its own surface's rim (``on_rim`` (k,) bool: two outlines of one topology meet rim to rim)."""
    return off <= np.where(on_rim, PAIR_RIM_GAP, PAIR_GAP) * extent


def spread_surface_points(mesh, n: int, region: np.ndarray | None = None
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (k, 3), unit normals (k, 3), vertex ids (k,)) at ``k <= n`` vertices of ``mesh`` spread by
    farthest-point sampling.

    Only vertices of some triangle count, and of ``region`` (n_vertices,) bool when it holds at least 4 of
    them; deterministic (starts at the lowest vertex).
    """
    vertices, triangles = mesh
    used = np.unique(triangles)
    if region is not None and np.count_nonzero(region[used]) >= 4:
        used = used[region[used]]
    points = vertices[used]
    chosen = [int(np.argmin(points[:, 1]))]
    offsets = points - points[chosen[0]]
    distance = np.einsum("nd,nd->n", offsets, offsets)  # squared: the same farthest point, no square roots
    for _ in range(min(n, len(points)) - 1):
        chosen.append(int(np.argmax(distance)))
        offsets = points - points[chosen[-1]]
        np.minimum(distance, np.einsum("nd,nd->n", offsets, offsets), out=distance)
    normals = vertex_normals(vertices, triangles)[used]
    return points[chosen], normals[chosen], used[chosen]


class SurfaceMatcher:
    """Finds, for points with normals, the surface point of a mesh nearest in place and in facing.

    The cost of a surface point ``x`` (normal ``n_x``) for a point ``p`` (normal ``n_p``) is
    ``|p - x|^2 + (normal_scale |n_p - n_x|)^2``: a pure closest point only pulls a point onto the surface,
    while the normal term also slides it along the surface to where the surface bends the same way. The surface
    points searched are the vertices and the edge midpoints (normals interpolated), in a 6D k-d tree.

    Parameters
    ----------
    mesh : (vertices (n, 3), triangles (m, 3))
    normal_scale : float
        mm per unit of normal difference.
    """

    def __init__(self, mesh, normal_scale: float):
        from scipy.spatial import cKDTree

        vertices, triangles = mesh
        normals = vertex_normals(vertices, triangles)
        edges, _ = edge_counts(triangles)
        used = np.unique(triangles)
        self.points = np.vstack([vertices[used], vertices[edges].mean(axis=1)])
        facing = np.vstack([normals[used], normals[edges].mean(axis=1)])
        facing /= np.maximum(np.linalg.norm(facing, axis=1, keepdims=True), np.finfo(float).tiny)
        self.normal_scale = float(normal_scale)
        self.mesh = mesh
        self.slide_limit = SLIDE_LIMIT * normal_scale / NORMAL_WEIGHT if NORMAL_WEIGHT > 0 else 0.0
        self.tree = cKDTree(np.hstack([self.points, self.normal_scale * facing]), balanced_tree=False,
                            compact_nodes=False)

    def carry(self, points: np.ndarray, normals: np.ndarray, spline: ThinPlateSpline) -> tuple[np.ndarray, np.ndarray]:
        """(``spline(points)`` matched onto the surface (k, 3), how far (k,) each carried point lies past the
        surface's outline: its offset from its closest surface point facing its way, along the surface
        (:func:`_beside`)).

        ``normals`` (k, 3) are the points' unit normals; the spline turns them by the inverse transpose of its
        Jacobian.
        """
        turned = np.linalg.solve(np.transpose(spline.jacobian(points), (0, 2, 1)), normals[..., None])[..., 0]
        turned /= np.maximum(np.linalg.norm(turned, axis=1, keepdims=True), np.finfo(float).tiny)
        carried = spline(points)
        _, index = self.tree.query(np.hstack([carried, self.normal_scale * turned]))
        matched = self.points[index]
        vertices, triangles = self.mesh
        triangle, barycentric, _ = closest_surface_points(carried, vertices, triangles, normals=turned)
        closest = np.einsum("nk,nkd->nd", barycentric, vertices[triangles[triangle]])
        off = _beside(carried - closest, triangle_normals(vertices, triangles[triangle]))
        if SLIDE_LIMIT <= 0:
            return matched, off
        slide = matched - closest
        length = np.linalg.norm(slide, axis=1, keepdims=True)
        far = length[:, 0] > self.slide_limit
        if not far.any():
            return matched, off
        capped = closest[far] + slide[far] * (self.slide_limit / length[far])
        triangle, barycentric, _ = closest_surface_points(capped, vertices, triangles, normals=turned[far])
        matched[far] = np.einsum("nk,nkd->nd", barycentric, vertices[triangles[triangle]])
        return matched, off


def _beside(offsets: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Length (k,) of each offset (k, 3) from a closest surface point along that surface (its triangle's unit
    normal (k, 3) taken out): zero where the point lies above or below the surface, the distance past its rim
    where it lies beyond the outline."""
    along = offsets - np.einsum("kd,kd->k", offsets, normals)[:, None] * normals
    return np.linalg.norm(along, axis=1)


def spaced(source: np.ndarray, target: np.ndarray, spacing: float, first: int) -> np.ndarray:
    """Indices of the pairs kept, greedily, so that no two kept points are closer than ``spacing`` on either
    side (a spline through two near-coincident points with different targets kinks); the ``first`` pairs
    (the landmarks) are always kept."""
    keep = list(range(first))
    for k in range(first, len(source)):
        if (np.linalg.norm(source[keep] - source[k], axis=1).min() >= spacing
                and np.linalg.norm(target[keep] - target[k], axis=1).min() >= spacing):
            keep.append(k)
    return np.array(keep)


def transfer_elements(elements: np.ndarray, source: Basis, correspondence: Correspondence,
                      to_target: ThinPlateSpline, jacobian: np.ndarray | None = None) -> np.ndarray:
    """Source elements ``(k, n_source, 3)`` as target elements ``(k, n_target, 3)``: ``f(p + d) - f(p)``.

    Small moves (below :data:`LINEAR_MOVE` of the spline's extent, most of an element's reach) go through the
    spline's Jacobian, ``J(p) d``, which differs from the exact difference by the spline's curvature times
    ``|d|^2``; larger ones are carried exactly. An element that is zero at a surface point stays exactly zero.
    ``jacobian`` (n_target, 3, 3): the spline's Jacobian at each target vertex's surface point, if already known
    (:func:`smooth_jacobian`).
    """
    points = correspondence.interpolate(source.neutral, source.triangles)  # p, (n_target, 3)
    moves = correspondence.interpolate(elements, source.triangles)  # d, (k, n_target, 3)
    moving = np.any(moves != 0, axis=(0, 2))  # f only where something moves: the rest stays exactly 0
    out = np.zeros(moves.shape)
    if not moving.any():
        return out
    jacobian = to_target.jacobian(points[moving]) if jacobian is None else jacobian[moving]
    jacobian = bounded_stretch(jacobian, to_target)
    out[:, moving] = np.einsum("noi,kni->kno", jacobian, moves[:, moving])
    limit = LINEAR_MOVE * float(np.ptp(to_target.centres, axis=0).max())
    element, vertex = np.nonzero(np.linalg.norm(moves, axis=2) > limit)
    if len(vertex):
        start = points[vertex]
        out[element, vertex] = to_target(start + moves[element, vertex]) - to_target(start)
    return out * uncovered_fade(correspondence.distance, limit / LINEAR_MOVE)[None, :, None]


def smooth_jacobian(to_target: ThinPlateSpline, points: np.ndarray, target_mesh, reach: float) -> np.ndarray:
    """``to_target``'s Jacobian at ``points`` (n_target, 3), the target vertices' source surface points, averaged
    over the target mesh within about ``reach`` mm (:func:`surface_average`), shape (n_target, 3, 3).

    A spline pinned to a surface bends at each of its surface control points (the ``r`` kernel's gradient is
    discontinuous there), so its Jacobian, and every motion it carries, ripples between them: the carried
    elements come out rougher than the source's. Averaging it over the mesh keeps its slow variation, the face's
    changing proportions. An affine spline (a self-transfer) has one Jacobian everywhere and is unchanged.
    """
    vertices, triangles = target_mesh
    jacobian = to_target.jacobian(points).reshape(len(points), 9)
    return surface_average(jacobian, np.asarray(vertices, dtype=np.float64), triangles, reach).reshape(-1, 3, 3)


def surface_average(values: np.ndarray, vertices: np.ndarray, triangles: np.ndarray, reach: float) -> np.ndarray:
    """Per-vertex ``values`` (n, m) averaged over the mesh within about ``reach`` mm, shape (n, m): explicit
    diffusion steps, enough for a spread of ``reach`` at the mesh's median edge length.

    The steps grow as the square of the mesh's density, so a mesh whose edges are shorter than
    :data:`DIFFUSION_CELL` times ``reach`` (a sculpted head of 150k-600k vertices) is averaged over its vertices
    gathered in cubic cells that wide (linked where its edges cross between them), and the cells' values are
    then smoothed over its own edges across one cell: the same spread at a cost that no longer grows with the
    tessellation (the Jacobian of 150k vertices taken and averaged in 1 s instead of 10, of 600k in 6 s instead
    of 128).
    """
    edges, _ = edge_counts(triangles)
    edge = median_edge_length(vertices, edges)
    if edge <= 0 or reach <= 0:
        return values
    cell = DIFFUSION_CELL * reach
    mean = neighbour_mean(edges, len(vertices))
    if edge >= cell:
        return diffuse(values, mean, _diffusion_steps(reach, edge), 0.5)
    from livebridge.retarget.grid import cell_index

    cluster = cell_index(vertices, cell)
    count = np.bincount(cluster).astype(np.float64)[:, None]
    coarse, centres = (np.zeros((len(count), a.shape[1])) for a in (values, vertices))
    np.add.at(coarse, cluster, values)
    np.add.at(centres, cluster, vertices)
    coarse, centres = coarse / count, centres / count
    links = np.unique(np.sort(cluster[edges], axis=1), axis=0)
    links = links[links[:, 0] != links[:, 1]]
    coarse = diffuse(coarse, neighbour_mean(links, len(count)),
                     _diffusion_steps(reach, median_edge_length(centres, links)), 0.5)
    return diffuse(coarse[cluster], mean, _diffusion_steps(cell, edge), 0.5)


def _diffusion_steps(reach: float, edge: float) -> int:
    """Explicit steps of weight 1/2 that spread a value about ``reach`` over a graph of ``edge``-long links."""
    return int(min(np.ceil(2.0 * (reach / edge) ** 2), MAX_DIFFUSION_STEPS))


def bounded_stretch(jacobian: np.ndarray, spline: ThinPlateSpline) -> np.ndarray:
    """Jacobians (n, 3, 3) with their singular values clipped to :data:`STRETCH_LIMIT` times the spline's overall
    scale either way (the cube root of its affine part's determinant).

    Far from every control point (the back of a head, behind the ears) a spline extrapolates, ``r^2 ln r^2``
    most of all, and its local stretch can grow many times a face's real proportions; a small motion there
    would be blown up into spikes.
    """
    scale = abs(float(np.linalg.det(spline.affine[1:]))) ** (1.0 / 3.0)
    u, stretch, vt = np.linalg.svd(jacobian)
    stretch = np.clip(stretch, scale / STRETCH_LIMIT, scale * STRETCH_LIMIT)
    return np.einsum("nij,nj,njk->nik", u, stretch, vt)


def uncovered_fade(distance: np.ndarray, extent: float) -> np.ndarray:
    """Weight (n,) of each target vertex's carried motion by how far its source point is: 1 up to
    :data:`COVERED` of ``extent``, smoothly 0 at :data:`UNCOVERED`.

    Where the target reaches beyond the source surface (a whole head onto a face mask: the scalp, the ears,
    the neck) the closest source point is on the source's border, and copying the border's motion outwards
    would tear those regions; the motion fades out instead.
    """
    t = np.clip((distance / extent - COVERED) / (UNCOVERED - COVERED), 0.0, 1.0)
    return 1.0 - t * t * (3.0 - 2.0 * t)


def correspondence_jumps(correspondence: Correspondence, source: Basis, target_triangles: np.ndarray) -> np.ndarray:
    """Per target vertex, the most its source point moves apart from a neighbour's, shape (n_target_vertices,).

    For each target edge, the distance between its two ends' source surface points over their distance carried
    into source space; 1 where the correspondence is continuous (a self-transfer: 1 everywhere), large where
    it tears (neighbours on either side of a nose wing, an eyelid, an ear fold land on different source parts).
    The largest over a vertex's edges; vertices on no edge get 1.
    """
    points = correspondence.interpolate(source.neutral, source.triangles)
    carried = correspondence.carried if correspondence.carried is not None else points
    edges, _ = edge_counts(target_triangles)
    a, b = edges.T
    near = np.linalg.norm(carried[a] - carried[b], axis=1)
    apart = np.linalg.norm(points[a] - points[b], axis=1)
    ratio = np.divide(apart, near, out=np.ones_like(apart), where=near > 1e-9 * max(float(near.max()), 1e-300))
    out = np.ones(len(points))
    np.maximum.at(out, a, ratio)
    np.maximum.at(out, b, ratio)
    return out


def smooth_jumps(elements: np.ndarray, triangles: np.ndarray, jumps: np.ndarray,
                 steps: int = JUMP_SMOOTHING) -> np.ndarray:
    """Target elements ``(k, n, 3)`` diffused over the mesh where the correspondence tears (``jumps (n,)`` from
    :func:`correspondence_jumps`), unchanged where it is continuous.

    Where neighbouring target vertices take their motion from far-apart source points, the transferred field
    is as rough as the source's geometry there (nose wings, eye corners, the mouth, an ear): each step moves such
    a vertex towards its neighbours' mean, by a weight from 0 at :data:`JUMP_START` to 1 at :data:`JUMP_FULL`,
    spread :data:`JUMP_SPREAD` rings; the continuous surroundings hold the field, so the smoothed part blends
    into them (a membrane). An element that is zero stays zero; a self-transfer is untouched.
    """
    t = np.clip((jumps - JUMP_START) / (JUMP_FULL - JUMP_START), 0.0, 1.0)
    weight = t * t * (3.0 - 2.0 * t)
    if not weight.any() or steps <= 0:
        return elements
    mean = neighbour_mean(edge_counts(triangles)[0], len(jumps))
    for _ in range(JUMP_SPREAD):
        weight = np.maximum(weight, 0.5 * (mean @ weight))
    weight[weight < 1e-3] = 0.0
    field = diffuse(np.moveaxis(elements, 1, 0).reshape(len(jumps), -1), mean, steps, weight)
    return np.moveaxis(field.reshape(len(jumps), elements.shape[0], 3), 0, 1)


def neighbour_mean(edges: np.ndarray, n: int):
    """The sparse (n, n) operator averaging a per-vertex value over each vertex's neighbours along ``edges``
    ((k, 2) vertex pairs, each once: :func:`edge_counts` of a mesh's triangles); a vertex on no edge keeps 0."""
    from scipy.sparse import csr_matrix, diags

    adjacency = csr_matrix((np.ones(2 * len(edges)), (edges.ravel(), edges[:, ::-1].ravel())), shape=(n, n))
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    return (diags(1.0 / np.maximum(degree, 1.0)) @ adjacency).tocsr()


def diffuse(values: np.ndarray, mean, steps: int, weight) -> np.ndarray:
    """``values (n, m)`` after ``steps`` explicit steps ``v += weight (mean v - v)``; ``weight`` a scalar or
    (n,) in [0, 1] (0 holds a vertex); vertices on no edge are held. Only the rows that move are computed."""
    held = np.asarray(mean.sum(axis=1)).ravel() == 0
    weight = np.where(held, 0.0, np.broadcast_to(weight, held.shape))
    rows = np.flatnonzero(weight > 0)
    if not len(rows):
        return values
    average, step = mean[rows], weight[rows, None]
    values = np.array(values, dtype=np.float64)
    for _ in range(steps):
        values[rows] += step * (average @ values - values[rows])
    return values


def moved_vertices(elements: np.ndarray, fraction: float = SAMPLED_MOTION) -> np.ndarray:
    """Vertices (n_vertices,) bool that some element ``(k, n_vertices, 3)`` moves by more than ``fraction`` of
    its largest move."""
    size = np.linalg.norm(elements, axis=2)
    return np.any(size > fraction * size.max(axis=1, keepdims=True), axis=0) if len(size) else np.zeros(0, bool)


def retarget_basis(source: Basis, source_landmarks: LandmarkSet, target_neutral: np.ndarray,
                   target_triangles: np.ndarray, target_landmarks: LandmarkSet,
                   kernel: Kernel | str = Kernel.BIHARMONIC, parts: BoneParts | None = None) -> Basis:
    """The source basis carried onto the target mesh: same muscles (names, regions, sides), target topology.

    Parameters
    ----------
    source : Basis
    source_landmarks : LandmarkSet
        On the source mesh; at least 4 landmarks, not all on one plane (the thesis's 22 are the intent).
    target_neutral : ndarray, shape (n_target_vertices, 3)
        The target's neutral face, mm, in any pose (the landmark spline absorbs pose and size).
    target_triangles : ndarray of int, shape (n_target_triangles, 3)
    target_landmarks : LandmarkSet
        On the target mesh; must name every landmark of ``source_landmarks``.
    kernel : Kernel or str
    parts : BoneParts, optional
        The target's closed inner parts (:func:`~livebridge.retarget.inner_parts.bone_parts`, found when not
        given).

    Returns
    -------
    Basis
        Neutral ``target_neutral``; muscles with no effect in the source stay exactly zero. Closed parts inside
        the target's head (teeth, eyeballs) move with their bone (:mod:`~livebridge.retarget.inner_parts`).
    """
    target_neutral = np.asarray(target_neutral, dtype=np.float64)
    target_triangles = np.asarray(target_triangles, dtype=np.int64)
    if target_neutral.ndim != 2 or target_neutral.shape[1] != 3 or not len(target_triangles):
        raise InputError(f"the target needs vertices (n, 3) and triangles, got {target_neutral.shape} vertices "
                         f"and {len(target_triangles)} triangles", field="target")
    source_points, target_points = landmark_pairs(source_landmarks, (source.neutral, source.triangles),
                                                  target_landmarks, (target_neutral, target_triangles))
    to_target, to_source = surface_splines(source_points, target_points, (source.neutral, source.triangles),
                                           (target_neutral, target_triangles), kernel,
                                           source_region=moved_vertices(source.elements))
    correspondence = correspond(target_neutral, target_triangles, to_source, source.neutral, source.triangles)
    points = correspondence.interpolate(source.neutral, source.triangles)
    reach = JACOBIAN_REACH * float(np.ptp(target_points, axis=0).max())
    jacobian = smooth_jacobian(to_target, points, (target_neutral, target_triangles), reach)
    elements = transfer_elements(source.elements, source, correspondence, to_target, jacobian)
    elements = smooth_jumps(elements, target_triangles, correspondence_jumps(correspondence, source, target_triangles))
    parts = bone_parts(target_neutral, target_triangles, target_landmarks) if parts is None else parts
    if parts.any:
        elements = on_bones(elements, target_neutral, parts, jaw_turners(source.names))
    return Basis(target_neutral, target_triangles, elements, source.muscles)


# ------------------------------------------------------------------------------------------------ measuring
MOVED_FRACTION = 0.01
"""A vertex is moved by an element when it moves more than this fraction of the element's largest motion."""


def relative_errors(elements: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per element, the RMS error over the vertices it moves over its RMS displacement there, shape (k,).

    ``elements`` and ``truth``: (k, n_vertices, 3). NaN for an element that moves nothing.
    """
    size = np.linalg.norm(truth, axis=2)
    error = np.linalg.norm(elements - truth, axis=2)
    out = np.full(len(truth), np.nan)
    for k in range(len(truth)):
        moved = size[k] > MOVED_FRACTION * size[k].max()
        if moved.any():
            out[k] = np.sqrt(np.mean(error[k, moved] ** 2) / np.mean(size[k, moved] ** 2))
    return out


def naive_transfer(source: Basis, source_landmarks: LandmarkSet, target_neutral: np.ndarray,
                   target_triangles: np.ndarray, target_landmarks: LandmarkSet) -> np.ndarray:
    """The baseline: each target vertex copies the displacement of its nearest source vertex.

    The target is first aligned onto the source by the similarity of the landmarks (Umeyama); the copied
    displacement is turned and scaled back by that similarity. Returns elements (k, n_target_vertices, 3).
    """
    from scipy.spatial import cKDTree

    from livebridge.geometry.transforms import apply, umeyama

    source_points, target_points = landmark_pairs(source_landmarks, (source.neutral, source.triangles),
                                                  target_landmarks, (target_neutral, target_triangles))
    target2source = umeyama(target_points, source_points)
    _, nearest = cKDTree(source.neutral).query(apply(target2source, target_neutral))
    back = np.linalg.inv(target2source[:3, :3])
    return source.elements[:, nearest] @ back.T
