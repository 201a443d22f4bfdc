"""Automatic marker placement: a marker set for a layout livebridge did not design.

From one neutral frame of labelled markers (any names, any capture frame and unit) and a basis:

1. a rough capture-to-model similarity: from >= 4 named correspondences to basis vertices, or without
   them from the marker cloud's centroid and principal axes matched to the face's, trying every proper
   rotation that maps one set of axes onto the other (the face's near-symmetries make several plausible)
   and keeping the one whose rigid closest-point fit (ICP) to the neutral surface ends nearest it;
2. the coordinate alignment of Choe & Ko (:func:`livebridge.reconstruct.align.align_to_model`, the live
   path's): similarity, projection onto the surface, repeat until the error stops falling; each marker is
   placed at its surface point;
3. the region of each marker from where it sits: above or below the height that best separates the
   vertices the basis's upper-face muscles move from those its lower-face muscles move;
4. the rigid head markers from the take: after a rigid fit of every frame to the neutral frame (iterated
   on the markers that fit), the markers whose deviation stays within ``rigid_tolerance_mm`` and that sit
   where the basis barely moves the skin (forehead, nose bridge, temples) or off the skin (a head band).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.face.markers import MarkerSet
from livebridge.geometry.transforms import apply, transform_scale, umeyama
from livebridge.reconstruct.align import MeshSurface, align_to_model

MIN_CORRESPONDENCES = 4
RIGID_TOLERANCE_MM = 0.75
"""Largest deviation (95th percentile over the take, model mm) of a marker counted as moving with the head."""
STEADY_SITE_MM = 1.0
"""A rigid marker is a head marker where no basis element moves the skin by more than this (model mm)..."""
OFF_SKIN_MM = 2.0
"""...or where it sits this far off the neutral surface (a head band): model mm."""


@dataclass(frozen=True, eq=False)
class Placement:
    """A marker set found for a captured layout.

    Attributes
    ----------
    markers : MarkerSet
        Names as in the capture, on the basis mesh, regions and roles assigned.
    capture2model : ndarray, shape (4, 4)
        Similarity from the capture frame to the model frame.
    rms_mm : float
        RMS distance (model mm) of the aligned neutral markers from the surface.
    deviation_mm : ndarray, shape (n_markers,)
        95th-percentile deviation of each marker from the head's rigid motion over the take (model mm);
        NaN without head motion to judge by.
    how : str
        How the rough alignment was found (for the user).
    """

    markers: MarkerSet
    capture2model: np.ndarray
    rms_mm: float
    deviation_mm: np.ndarray
    how: str


def _proper_axis_maps() -> list[np.ndarray]:
    """The 24 rotations that map the coordinate axes onto themselves (signed permutations, det +1)."""
    maps = []
    for order in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            matrix = np.zeros((3, 3))
            matrix[np.arange(3), order] = signs
            if np.linalg.det(matrix) > 0:
                maps.append(matrix)
    return maps


def _principal_axes(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(centroid (3,), axes as rows (3, 3) by falling variance, RMS spread) of a point cloud."""
    centre = points.mean(axis=0)
    _, singular, axes = np.linalg.svd(points - centre, full_matrices=False)
    axes[2] *= np.sign(np.linalg.det(axes))  # a right-handed frame: rotations between two such are proper
    return centre, axes, float(np.sqrt((singular**2).sum() / len(points)))


def _similarity_icp(points: np.ndarray, surface: MeshSurface, start: np.ndarray, iterations: int = 40) -> tuple[
        np.ndarray, float]:
    """Closest-point ICP (similarity) of ``points (n, 3)`` to ``surface`` from ``start (4, 4)``.

    Returns the transform and its RMS distance from the surface in the points' own unit (model mm divided by
    the scale), so that shrinking the cloud onto a patch of the surface does not look like a better fit.
    """
    transform, error = start, np.inf
    for _ in range(iterations):
        moved = apply(transform, points)
        _, _, target = surface.closest(moved)
        new_error = float(np.sqrt(np.mean(((moved - target) ** 2).sum(-1)))) / transform_scale(transform)
        if new_error >= error * (1 - 1e-6):
            break
        error = new_error
        candidate = umeyama(points, target, with_scale=True)
        if not transform_scale(candidate) > 0:  # the closest points mirror the cloud: no fit from this start
            break
        transform = candidate
    return transform, error


def _face_cloud(basis: Basis, points: np.ndarray) -> np.ndarray:
    """The neutral vertices a marker cloud is compared with: the front of the face (facing +z, in the front
    half of the head's depth), where markers go."""
    vertices = basis.neutral
    normals = np.zeros_like(vertices)
    corners = vertices[basis.triangles]
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    for k in range(3):
        np.add.at(normals, basis.triangles[:, k], face_normals)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    front = (normals[:, 2] > 0.5) & (vertices[:, 2] > low[2] + 0.45 * (high[2] - low[2]))
    return vertices[front] if front.sum() >= 3 else vertices


def rough_alignment(points: np.ndarray, basis: Basis, surface: MeshSurface) -> tuple[np.ndarray, str]:
    """Capture-to-model similarity without correspondences: principal axes, then rigid ICP per orientation.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Neutral-frame marker positions (capture frame), all finite.

    Returns
    -------
    (ndarray (4, 4), str): the transform and how it was chosen.
    """
    centre, axes, spread = _principal_axes(points)
    face_centre, face_axes, face_spread = _principal_axes(_face_cloud(basis, points))
    scale = face_spread / spread
    results = []
    for axis_map in _proper_axis_maps():
        rotation = face_axes.T @ axis_map @ axes
        start = np.eye(4)
        start[:3, :3] = scale * rotation
        start[:3, 3] = face_centre - scale * rotation @ centre
        results.append(_similarity_icp(points, surface, start))
    errors = np.array([error for _, error in results])
    best = int(np.argmin(errors))
    second = float(np.partition(errors, 1)[1]) if len(errors) > 1 else np.inf
    how = (f"similarity fit of the marker cloud to the face (principal axes, {len(results)} orientations tried, "
           f"best surface RMS {errors[best]:.2f}, next best {second:.2f}, in the file's unit)")
    return results[best][0], how


def correspondence_alignment(points: np.ndarray, names: tuple[str, ...], correspond: dict[str, int],
                             basis: Basis) -> tuple[np.ndarray, str]:
    """Capture-to-model similarity from named markers at known basis vertices.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    names : tuple of str, length n
    correspond : dict of marker name -> vertex index of the basis neutral mesh
    """
    unknown = sorted(set(correspond) - set(names))
    if unknown:
        raise InputError(f"--correspond names markers the file does not have: {', '.join(unknown)}",
                         field="correspond")
    bad = sorted(name for name, vertex in correspond.items() if not 0 <= vertex < len(basis.neutral))
    if bad:
        raise InputError(f"--correspond vertex out of range 0..{len(basis.neutral) - 1} for {', '.join(bad)}",
                         field="correspond")
    rows = [names.index(name) for name in correspond]
    seen = np.isfinite(points[rows]).all(axis=1)
    if seen.sum() < MIN_CORRESPONDENCES:
        raise InputError(f"--correspond needs at least {MIN_CORRESPONDENCES} markers seen in the neutral frame, "
                         f"got {int(seen.sum())}", field="correspond")
    vertices = basis.neutral[[correspond[name] for name in correspond]]
    transform = umeyama(points[rows][seen], vertices[seen], with_scale=True)
    return transform, f"{int(seen.sum())} named correspondences"


def region_height(basis: Basis, share: float = 0.1) -> float:
    """Model-frame height (y) that best separates the vertices moved by upper-face and by lower-face muscles.

    A vertex belongs to a region when that region's muscles move it by more than ``share`` of the largest
    motion of any vertex; the height minimises the vertices on the wrong side.
    """
    reach = np.linalg.norm(basis.elements, axis=2)  # (M, V)
    upper = np.array([m.region == "upper" for m in basis.muscles])
    moved_upper = reach[upper].max(axis=0, initial=0.0) if upper.any() else np.zeros(reach.shape[1])
    moved_lower = reach[~upper].max(axis=0, initial=0.0) if (~upper).any() else np.zeros(reach.shape[1])
    limit = share * reach.max(initial=0.0)
    y = basis.neutral[:, 1]
    only_upper, only_lower = y[(moved_upper > limit) & (moved_lower <= moved_upper)], \
        y[(moved_lower > limit) & (moved_upper < moved_lower)]
    if not len(only_upper) or not len(only_lower):
        return float(np.median(y))
    candidates = np.unique(np.concatenate([only_upper, only_lower]))
    wrong = (np.searchsorted(np.sort(only_upper), candidates, side="right")
             + len(only_lower) - np.searchsorted(np.sort(only_lower), candidates, side="right"))
    # ties: the middle of the best run of heights
    best = np.flatnonzero(wrong == wrong.min())
    return float(0.5 * (candidates[best[0]] + candidates[best[-1]]))


def rigid_deviation(points: np.ndarray, neutral: int, rounds: int = 4,
                    tolerance_mm: float = RIGID_TOLERANCE_MM) -> np.ndarray:
    """Each marker's 95th-percentile deviation from the head's rigid motion over a take.

    Every frame is fitted rigidly (Kabsch) to the neutral frame on the markers that fitted in the round
    before (all of them first); the deviation is each marker's distance from where that motion puts it.

    Parameters
    ----------
    points : ndarray, shape (n_frames, n_markers, 3)
        Capture frame, NaN unseen.
    neutral : int
        The reference frame.

    Returns
    -------
    ndarray, shape (n_markers,); NaN for markers never seen with the reference.
    """
    reference = points[neutral]
    use = np.isfinite(reference).all(axis=1)
    deviation = np.full(points.shape[1], np.nan)
    for _ in range(rounds):
        residual = np.full(points.shape[:2], np.nan)
        for f, frame in enumerate(points):
            fit = use & np.isfinite(frame).all(axis=1)
            if fit.sum() < 3:
                continue
            motion = umeyama(reference[fit], frame[fit], with_scale=False)
            residual[f] = np.linalg.norm(apply(motion, reference) - frame, axis=1)
        seen = np.isfinite(residual).any(axis=0)
        deviation = np.full(points.shape[1], np.nan)
        deviation[seen] = np.nanpercentile(residual[:, seen], 95, axis=0)
        # the next round fits on the steadiest markers: the head's motion, not the expression's
        keep = np.isfinite(deviation) & (deviation <= max(tolerance_mm, np.nanpercentile(deviation, 25)))
        if keep.sum() < 3 or np.array_equal(keep, use):
            break
        use = keep
    return deviation


def fill_unseen(points: np.ndarray, neutral: int) -> np.ndarray:
    """The neutral frame (n_markers, 3) with each marker it misses taken from the nearest frame that shows it,
    carried over by that frame's rigid motion to the neutral frame (fitted on the markers both show)."""
    frame = points[neutral].copy()
    for f in np.argsort(np.abs(np.arange(len(points)) - neutral), kind="stable")[1:]:
        missing = ~np.isfinite(frame).all(axis=1)
        if not missing.any():
            break
        other = points[f]
        common = ~missing & np.isfinite(other).all(axis=1)
        fill = missing & np.isfinite(other).all(axis=1)
        if common.sum() >= 3 and fill.any():
            frame[fill] = apply(umeyama(other[common], frame[common], with_scale=False), other[fill])
    return frame


def place_markers(points: np.ndarray, names: tuple[str, ...], basis: Basis, neutral: int,
                  correspond: dict[str, int] | None = None,
                  rigid_tolerance_mm: float = RIGID_TOLERANCE_MM, rough: np.ndarray | None = None) -> Placement:
    """Place a captured layout on ``basis`` (module docstring).

    Parameters
    ----------
    points : ndarray, shape (n_frames, n_markers, 3)
        The take (capture frame, NaN unseen); ``points[neutral]`` is the neutral face.
    names : tuple of str, length n_markers
    basis : Basis
    neutral : int
    correspond : dict of name -> basis vertex index, optional
        At least 4: the rough alignment from them instead of from the cloud's shape.
    rigid_tolerance_mm : float
        Largest 95th-percentile deviation from rigid head motion of a head marker (model mm).
    rough : ndarray, shape (4, 4), optional
        A capture-to-model similarity already known (e.g. from a placement on another frame of the take):
        the rough alignment, instead of finding one.

    Returns
    -------
    Placement
    """
    points = np.asarray(points, dtype=np.float64)
    frame = fill_unseen(points, neutral)
    seen = np.isfinite(frame).all(axis=1)
    if seen.sum() < 4:
        raise InputError(f"the neutral frame {neutral} shows {int(seen.sum())} markers; placement needs at least 4",
                         field="neutral-frame")
    surface = MeshSurface(basis.neutral, basis.triangles)
    if rough is not None:
        how = "carried over from a placement on another frame"
    elif correspond:
        rough, how = correspondence_alignment(frame, names, correspond, basis)
    else:
        rough, how = rough_alignment(frame[seen], basis, surface)
    # a provisional set at the rough fit's surface points: align_to_model (the live path's alignment) refines it
    provisional_points = apply(rough, np.where(seen[:, None], frame, frame[seen].mean(axis=0)))
    triangles, barycentric, _ = surface.closest(provisional_points)
    n = len(names)
    provisional = MarkerSet(names, triangles, barycentric, ("upper",) * n, ("face",) * n)
    alignment = align_to_model(frame, provisional, basis)
    height = region_height(basis)
    model = alignment.markers.neutral_positions(basis)
    regions = tuple("upper" if y > height else "lower" for y in model[:, 1])
    scale = transform_scale(alignment.capture2model)  # model mm per capture unit
    deviation = rigid_deviation(points, neutral, tolerance_mm=rigid_tolerance_mm / scale) * scale \
        if len(points) > 1 else np.full(n, np.nan)
    # rigid in this take, and either a site the model barely moves (forehead, nose bridge, temples) or off the
    # skin (a head-band marker): a face marker the take happens not to move keeps its place in the solve
    reach = np.linalg.norm(MarkerSet(names, alignment.markers.triangles, alignment.markers.barycentric,
                                     regions, ("face",) * n).displacement_matrix(basis), axis=2).max(axis=1)
    off_skin = np.linalg.norm(apply(alignment.capture2model, frame) - model, axis=1) > OFF_SKIN_MM
    roles = tuple("head" if d <= rigid_tolerance_mm and (r <= STEADY_SITE_MM or o) else "face"
                  for d, r, o in zip(deviation, reach, off_skin))
    if roles.count("face") == 0:  # a take without expression shows nothing but rigid markers: keep them face
        roles = ("face",) * n
    placed = MarkerSet(names, alignment.markers.triangles, alignment.markers.barycentric, regions, roles)
    return Placement(placed, alignment.capture2model, alignment.rms_mm, deviation, how)
