"""A face scan prepared for building a basis: cropped, resampled on the face grid and in the face frame.

Preprocessing (§5.4): the neutral scan is normalised (nose tip to the origin, its outer eye corners, chin
and nose tip onto a reference face's; :mod:`~livebridge.retarget.normalise`), cropped to the face, rid of its
stray points (:func:`~livebridge.retarget.grid.spikes`) and resampled onto a regular x-y grid
(:mod:`~livebridge.retarget.grid`). Each expression scan is registered onto it rigidly (skull landmarks, then
trimmed ICP: the person's head moved between scans, their skull did not change), rid of its stray points and
resampled on the same grid lines; how far its skin then lies off the neutral's says whether it is one muscle's
motion on the same face (:mod:`~livebridge.retarget.same_face`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from livebridge.errors import InputError
from livebridge.face.meshio import vertex_normals
from livebridge.geometry.transforms import apply, transform_scale
from livebridge.retarget.chart import PLANAR, SkinChart, face_chart
from livebridge.retarget.eyeballs import eyeball_points
from livebridge.retarget.facing import Facing, facing_points
from livebridge.retarget.grid import (
    GAP_SPACINGS,
    GRID_SHAPE,
    FaceGrid,
    crop_sphere,
    front_surface,
    holes,
    point_spacing,
    resample,
    spikes,
    square_axes,
)
from livebridge.retarget.landmarks import (
    THESIS_22_NAMES,
    LandmarkSet,
    place_at_points,
    thesis_points_from_68,
)
from livebridge.retarget.mesh_samples import SAMPLE_SPACING_MM
from livebridge.retarget.normalise import (
    RIGID_LANDMARKS,
    landmark_rigid,
    normalisation,
    register_rigid,
    transform_landmarks,
)
from livebridge.retarget.same_face import surface_gap
from livebridge.retarget.scan import Scan
from livebridge.retarget.shading import MIN_EXPLAINED, Shading, fit_shading, surface_normals, unshaded
from livebridge.retarget.skin_flow import fine_axes, in_front, pixels_of
from livebridge.retarget.surface_fit import fitted_heights, noise_level
from livebridge.retarget.tps import Kernel, fit_tps

CROP_FACTOR = 1.2
"""Default crop radius: this times the farthest landmark from the nose tip."""
LANDMARK_SMOOTHING = 1.0
"""TPS smoothing of the landmark spline (landmarks are placed by hand or detected: never exact)."""
SKIN_MARGIN_MM = 10.0
"""The skin images of coloured scans reach this far beyond the grid (tracking is poor at an image's edge)."""
OFF_FACE_MM = 25.0
"""An expression scan's registered points farther than this from every vertex of the neutral are not the face
(a hand, glasses or a microphone between the scanner and the face), and left out: the resampling keeps the
surface the scanner saw first. The bench's 16 ICT expressions reach at most 14 mm from the neutral (the opened
jaw's chin; the pucker's lips 9 mm); a copy of the jaw scan 80 mm in front of it was its jaw element's 129 mm
largest motion, 41.8 mm with the cut, as without the copy."""
TEXTURE_REACH = 1.5
"""A textured scan is sampled into points out to this times the face crop's radius from its nose tip (the
expressions' crop is the neutral's, and an opened jaw reaches below it)."""
HIDDEN_DEPTH_MM = 2.0
"""A mesh's sample more than this behind the front-most sample of its x-y cell (the samples' spacing wide) in the
face frame is hidden from a scanner in front of the face: a modelled head's teeth, gums and tongue behind the
lips, its eyeballs behind the lids. The resampling's own cut (:data:`~livebridge.retarget.grid.FRONT_DEPTH_MM`,
10 mm over a grid cell) is for a scan's noisy points, and lets them through: ICT-FaceKit's full head read as
scans (its mouth and eyes modelled) built a brow raise, a smile and a jaw of 1.17 / 0.63 / 0.54 relative RMS
from the shape alone, against 0.73 / 0.58 / 0.32 from its face region alone; without the mouth's inside,
0.72 / 0.62 / 0.39; with this cut, 0.73 / 0.59 / 0.32."""
CHART_KIND = "cylinder"
"""The skin images' chart (:mod:`~livebridge.retarget.chart`): a cylinder about a vertical axis fitted to the
neutral face (``"planar"``: the x-y projection, ``"sphere"``); see the chart module for the figures."""
LANDMARK_MAX_DISTANCE_MM = 5.0
"""A landmark farther than this from the resampled surface is an error (off the face, or in a hole)."""
MIN_DEPTH = 0.05
"""A neutral face whose crop lies closer to a plane (RMS) than this fraction of the crop radius is refused as
flat: a face's nose stands 20-35 mm in front of its cheeks, over a crop of about 100 mm."""
SPARSE_CELLS = 4.0
"""A scan's points may lie at most this many grid cells apart, on average over the face crop's disc."""
SKIN_GAP_SPACINGS = 4.0
"""A skin image's holes are at least this many of its scan's median point spacings wide (:func:`skin_gap_mm`):
among random points that far from every point is a pixel in 2^-16 (2^-(k^2) for k spacings), where at 3 it is one
in 512, a few hundred stray holes in a face's skin image."""


@dataclass(frozen=True, eq=False)
class FaceScan:
    """A scan cropped, resampled and in the face frame.

    Attributes
    ----------
    grid : FaceGrid
    landmarks : dict of str to ndarray, shape (3,)
        The scan's landmarks in the face frame (where the landmark file puts them, carried by ``scan2face``).
    scan2face : ndarray, shape (4, 4)
        From the scan's coordinates to the face frame (nose tip of the neutral at the origin, facing +z).
    skin : FaceGrid or None
        The scan in ``chart``'s coordinates resampled on grid lines (u, v) ``skin_factor`` times finer than the
        chart's coarse lines over the face, reaching ``skin_margin`` coarse cells beyond them on every side: the
        chart's heights, and an image of the skin when the scan has colour (:attr:`coloured`); where the eyes
        open (:mod:`~livebridge.retarget.eyelids`) with or without. None when not made (a FaceScan built by hand).
    skin_factor, skin_margin : int
    point_spacing : float
        The scan's median distance between neighbouring points in the chart's u-v (x-y in the planar one),
        mm (NaN when not known).
    template : FaceGrid or None
        A neutral's skin image averaged from all of the person's scans, tracked against instead of ``skin``
        (:mod:`~livebridge.retarget.skin_template`).
    chart : SkinChart
        The chart of ``skin`` (:mod:`~livebridge.retarget.chart`; fitted to the neutral, shared by its
        expressions).
    skin_holes : ndarray of bool, shape of ``skin``'s heights, or None
        The skin image's points with no scan point within :func:`opening_gap_mm` (the scan's own holes at its
        resolution: a squinting eye's slit, which the skin image's wider gap fills); None without ``skin``.
    fitted_heights : ndarray, shape of ``grid``'s heights, or None
        The neutral's surface fitted to its points (:mod:`~livebridge.retarget.surface_fit`): the heights of
        the mesh a basis is written on (:attr:`mesh_vertices`); None: the grid's own.
    gap_mm, noise_mm : float
        An expression's: how far its registered points lie from the neutral's surface (median) and its own
        noise (:mod:`~livebridge.retarget.same_face`); NaN for a neutral.
    off_face_share : float
        An expression's: the share of its points (in the crop) left out as lying over :data:`OFF_FACE_MM`
        from the neutral's face (:func:`_on_the_face`).
    shading : Shading or None
        The lighting fitted to the scan's colours (:mod:`~livebridge.retarget.shading`); None without colour,
        and for an expression whose neutral's shading was left in (nothing to divide out, nothing fitted).
    shading_removed : bool
        Whether ``skin`` is the colours divided by ``shading`` (the neutral's shading explained enough of its
        brightness; its expressions follow the neutral).
    eyeball_points : int
        How many of the scan's points were eyeballs seen through the eye openings, left out
        (:mod:`~livebridge.retarget.eyeballs`).
    eyeballs_left_out : bool
        Whether they were sought (the neutral's choice; its expressions follow it).
    facing : Facing
        What the point cloud's normals said, and how many points they left out as facing away from the front
        (:mod:`~livebridge.retarget.facing`).
    """

    grid: FaceGrid
    landmarks: dict
    scan2face: np.ndarray
    skin: FaceGrid | None = None
    skin_factor: int = 1
    skin_margin: int = 0
    point_spacing: float = float("nan")
    template: FaceGrid | None = None
    chart: SkinChart = PLANAR
    skin_holes: np.ndarray | None = None
    fitted_heights: np.ndarray | None = None
    gap_mm: float = float("nan")
    noise_mm: float = float("nan")
    off_face_share: float = 0.0
    shading: Shading | None = None
    shading_removed: bool = False
    eyeball_points: int = 0
    eyeballs_left_out: bool = True
    facing: Facing = Facing()

    @property
    def coloured(self) -> bool:
        """Whether the scan has a skin image to track (colour with a pattern)."""
        return self.skin is not None and self.skin.colours is not None

    @property
    def vertices(self) -> np.ndarray:
        """The grid's vertices (n_vertices, 3): the interpolated scan, what the scans are registered and
        tracked on."""
        return self.grid.vertices

    @property
    def mesh_grid(self) -> FaceGrid:
        """The grid with the fitted heights when there are any: the mesh a basis is written on."""
        return self.grid if self.fitted_heights is None else replace(self.grid, heights=self.fitted_heights)

    @property
    def mesh_vertices(self) -> np.ndarray:
        """The grid's vertices (n_vertices, 3) on the fitted surface when there is one: the basis's neutral."""
        return self.mesh_grid.vertices

    @property
    def triangles(self) -> np.ndarray:
        return self.grid.triangles

    @property
    def skin_gap(self) -> float:
        """How far inside the scan's own holes those of its skin image lie, mm (:func:`skin_gap_mm`)."""
        return skin_gap_mm(self.grid.spacing, self.point_spacing)

    def skin_pixels(self) -> np.ndarray:
        """The grid's vertices on the skin image, (row, column) pixels (n_vertices, 2): where the tracked
        motion is read back and the first guesses are given."""
        return pixels_of(self.skin, self.chart.to_chart(self.vertices)[:, :2])

    def landmark_set(self, source=None) -> LandmarkSet:
        """The landmarks at their closest points of the grid mesh (an error names any farther than
        :data:`LANDMARK_MAX_DISTANCE_MM`: off the crop or in a hole), moved off the rims of the grid's small
        holes (:func:`~livebridge.retarget.checks.moved_off_rims`), where a transfer would refuse them."""
        from livebridge.retarget.checks import moved_off_rims

        placed = place_at_points(self.landmarks, self.vertices, self.triangles, LANDMARK_MAX_DISTANCE_MM, source)
        return moved_off_rims(placed, self.vertices, self.triangles)


def crop_radius(landmarks: dict[str, np.ndarray]) -> float:
    """:data:`CROP_FACTOR` times the farthest of the thesis's 22 landmarks (of any, without them) from the nose
    tip, mm: a 68-point file's jaw line runs round the face's outline to the ears, and 1.2 times that (148 mm
    on the ICT face, 110 from the 22) would crop the neck and ears too."""
    tip = np.asarray(landmarks["nose_tip"], dtype=np.float64)
    named = [landmarks[name] for name in THESIS_22_NAMES if name in landmarks] or list(landmarks.values())
    return CROP_FACTOR * max(float(np.linalg.norm(np.asarray(p) - tip)) for p in named)


def prepare_neutral(scan: Scan, landmarks: dict[str, np.ndarray], reference: dict[str, np.ndarray],
                    method: str = "rigid", shape: tuple[int, int] = GRID_SHAPE, radius: float | None = None,
                    source=None, chart: str = CHART_KIND, scan_source=None,
                    mesh_spacing: float | None = None, remove_shading: bool | None = None,
                    leave_out_eyeballs: bool = True) -> FaceScan:
    """The neutral scan normalised onto ``reference`` by ``method`` (see
    :func:`~livebridge.retarget.normalise.normalisation`), cropped to a sphere of ``radius`` around the nose
    tip and resampled on a ``shape`` grid over ``[-radius, radius]^2``; its skin images in a ``chart`` fitted
    to it (:func:`~livebridge.retarget.chart.face_chart`); its surface fitted to its points at the grid's
    vertices (:mod:`~livebridge.retarget.surface_fit`). A mesh is first sampled into points every
    ``mesh_spacing`` mm (default 0.5: :mod:`~livebridge.retarget.mesh_samples`), coloured from its texture or
    vertices. The colours' lighting (:mod:`~livebridge.retarget.shading`) is divided out if ``remove_shading``
    (None: if it explains enough of the scan's brightness), and then from every expression scan too. The eyeballs
    seen through the eye openings are left out (:mod:`~livebridge.retarget.eyeballs`) if ``leave_out_eyeballs``,
    and then from every expression scan too. Errors name ``source`` (the landmark file) or ``scan_source`` (the
    scan file: a flat scan). Landmarks numbered as the 68-point iBUG layout are named as the thesis's
    (:func:`~livebridge.retarget.landmarks.thesis_points_from_68`).
    """
    landmarks = thesis_points_from_68(landmarks, scan.points, source)
    scan2face = normalisation(landmarks, reference, method, source)
    moved = transform_landmarks(scan2face, landmarks)
    check_sides(moved, reference, source)
    radius = crop_radius(moved) if radius is None else float(radius)
    scan = _as_points(scan, landmarks, radius / abs(transform_scale(scan2face)), mesh_spacing, scan2face)
    whole = scan.points
    scan, facing = facing_points(scan, scan2face, radius)
    scan, points = _without_spikes(scan, apply(scan2face, scan.points), radius)
    scan, points, eyeballs = _without_eyeballs(scan, points, moved, leave_out_eyeballs)
    if not len(points):  # the crop holds no point: say how far apart the scan's and the landmarks' places are
        size = float(np.ptp(whole, axis=0).max())
        spread = float(np.ptp(np.array(list(landmarks.values())), axis=0).max())
        raise InputError(f"no point of the scan within {radius:.3g} mm of the nose tip: the scan spans {size:.3g} mm, "
                         f"its landmarks {spread:.3g} mm: are both in the same units and coordinates?",
                         scan_source or source, "points")
    x, y = square_axes(radius, shape)
    face = _resampled(scan, points, x, y, radius, moved, scan2face, source, chart, remove_shading=remove_shading,
                      fit_surface=True)
    off_plane = face.vertices - face.vertices.mean(axis=0)
    depth = float(np.linalg.svd(off_plane, compute_uv=False)[-1] / np.sqrt(len(off_plane)))  # RMS off its plane
    if depth < MIN_DEPTH * radius:  # a plane has no face to register the expressions on
        raise InputError(f"flat: its face crop lies within {depth:.2g} mm (RMS) of a plane over {2 * radius:.3g} mm "
                         "(a face is tens of mm deep)", scan_source or source, "points")
    face.landmark_set(source)  # every landmark on the resampled face, or a clear error
    return replace(face, eyeball_points=eyeballs, eyeballs_left_out=leave_out_eyeballs, facing=facing)


def _as_points(scan: Scan, landmarks: dict[str, np.ndarray], radius: float, spacing: float | None,
               scan2face: np.ndarray) -> Scan:
    """A mesh sampled into points (:meth:`~livebridge.retarget.scan.Scan.as_points`: coloured from its texture or
    its vertices) around its nose tip, out to :data:`TEXTURE_REACH` times the crop ``radius`` (in the scan's
    units) and the skin images' margin beyond, keeping those a scanner in front of the face sees (``scan2face``
    (4, 4): the face frame, +z out of the face; :data:`HIDDEN_DEPTH_MM`); a point cloud as it is."""
    if not scan.is_mesh:
        return scan
    samples = scan.as_points(landmarks["nose_tip"], TEXTURE_REACH * radius + SKIN_MARGIN_MM, spacing)
    cell = SAMPLE_SPACING_MM if spacing is None else spacing
    return samples.where(front_surface(apply(scan2face, samples.points), cell, HIDDEN_DEPTH_MM))


def _without_spikes(scan: Scan, points: np.ndarray, radius: float) -> tuple[Scan, np.ndarray]:
    """A scan's points (``scan``, a point cloud) and the same points in the face frame (``points``, (n, 3))
    within what the resampling reads (``radius`` of the face's crop and :data:`SKIN_MARGIN_MM`), without their
    flying points (:func:`~livebridge.retarget.grid.spikes`)."""
    keep = crop_sphere(points, np.zeros(3), radius + SKIN_MARGIN_MM)
    keep[keep] = ~spikes(points[keep])
    if keep.all():
        return scan, points
    return scan.where(keep), points[keep]


def _on_the_face(scan: Scan, points: np.ndarray, vertices: np.ndarray) -> tuple[Scan, np.ndarray, float]:
    """An expression scan (``scan``, and ``points`` (n, 3) registered in the face frame) without the points
    more than :data:`OFF_FACE_MM` from every vertex of the neutral (``vertices``, (m, 3)), and the share of its
    points that were: something between the scanner and the face (a hand, glasses, a microphone) that the
    resampling, which keeps the surface the scanner saw first, would take for the face."""
    far = cKDTree(vertices).query(points, distance_upper_bound=OFF_FACE_MM)[0] > OFF_FACE_MM
    if not far.any():
        return scan, points, 0.0
    return scan.where(~far), points[~far], float(far.mean())


def _without_eyeballs(scan: Scan, points: np.ndarray, landmarks: dict, leave_out: bool = True
                      ) -> tuple[Scan, np.ndarray, int]:
    """A point cloud (``scan``; ``points`` (n, 3) the same in the face frame, ``landmarks`` too) without the
    eyeballs seen through the eye openings (:mod:`~livebridge.retarget.eyeballs`) if ``leave_out``, and how
    many points they were."""
    if not leave_out:
        return scan, points, 0
    eyes = eyeball_points(points, scan.colours, landmarks)
    if not eyes.any():
        return scan, points, 0
    return scan.where(~eyes), points[~eyes], int(eyes.sum())


def _resampled(scan: Scan, points: np.ndarray, x: np.ndarray, y: np.ndarray, radius: float, landmarks: dict,
               scan2face: np.ndarray, source, chart: SkinChart | str = CHART_KIND,
               skin_axes: tuple | None = None, remove_shading: bool | None = None,
               report_shading: bool = True, fit_surface: bool = False) -> FaceScan:
    """Points in the face frame cropped and resampled on ``x``, ``y``, and on the skin grid too (an image of
    the skin with colour, heights alone without): in ``chart`` (a kind: one of that kind fitted to this scan's
    grid), on ``skin_axes`` (fine u, fine v, factor, margin; None: over this scan's grid); the colours' shading
    divided out if ``remove_shading`` (None: if it explains :data:`~livebridge.retarget.shading.MIN_EXPLAINED`
    of this scan's brightness), and fitted when it is left in only if ``report_shading`` (the neutral's, for the
    build's log); the surface fitted at the grid's vertices too if ``fit_surface`` (the neutral's:
    :attr:`FaceScan.fitted_heights`), straight after the grid's resampling, whose triangulation of the same points
    it reuses (:func:`~livebridge.retarget.grid.containing_triangles` keeps the last one; the skin images'
    resampling triangulates others)."""
    inside = crop_sphere(points, np.zeros(3), radius)
    _check_dense(points[inside], x, y, source)
    grid = resample(points[inside], x, y, source=source, seeded_holes=True)  # the basis's mesh: no pinholes
    fitted = fitted_heights(points[inside], grid) if fit_surface else None
    if isinstance(chart, str):
        chart = face_chart(grid.vertices, chart)
    colours = scan.colours
    if colours is not None and np.ptp(colours[inside], axis=0).max() < 1 / 255:
        colours = None  # one colour all over the face (some exporters write white) has no pattern to track
    spacing = point_spacing(chart.to_chart(points[inside])[:, :2])  # in the skin images' chart
    step = float(max(np.diff(x).max(), np.diff(y).max()))
    if skin_axes is None:
        skin_axes = _skin_axes(chart, x, y, points[inside])
    fine_x, fine_y, factor, margin = skin_axes
    wider = crop_sphere(points, np.zeros(3), radius + SKIN_MARGIN_MM)
    on_chart = chart.to_chart(points[wider])
    shading = None
    if colours is not None and (remove_shading is not False or report_shading):
        normals = surface_normals(points[wider])
        shading = fit_shading(points[inside], colours[inside], normals[inside[wider]])
        if remove_shading is None:
            remove_shading = shading.explained >= MIN_EXPLAINED
    colours = None if colours is None else colours[wider]
    if remove_shading and shading is not None:
        colours = unshaded(colours, normals, shading)
    skin_gap = skin_gap_mm(step, spacing)
    skin = resample(on_chart, fine_x, fine_y, skin_gap, source, colours)
    visible = in_front(skin, on_chart)  # not another surface seen through a gap of the skin (a nostril)
    if not visible.all():
        on_chart, colours = on_chart[visible], None if colours is None else colours[visible]
        skin = resample(on_chart, fine_x, fine_y, skin_gap, source, colours)
    skin_holes = holes(on_chart, fine_x, fine_y, opening_gap_mm(spacing, step))
    return FaceScan(grid, landmarks, scan2face, skin, factor, margin, spacing, chart=chart, skin_holes=skin_holes,
                    shading=shading, shading_removed=bool(remove_shading) and shading is not None,
                    fitted_heights=fitted)


def _check_dense(points: np.ndarray, x: np.ndarray, y: np.ndarray, source) -> None:
    """Refuse a scan whose points (n, 3; the face crop) lie more than :data:`SPARSE_CELLS` cells of the grid
    ``x``, ``y`` apart on average over the crop's disc: the grid would be a spline through a few points (a
    landmark file given as the scan built a 36 mm jaw from its 22 points)."""
    step = float(max(np.diff(x).max(), np.diff(y).max()))
    if not len(points):
        return  # the resampling says so
    spacing = float(np.sqrt(np.pi * x[-1] ** 2 / len(points)))  # clustered points (landmarks) lie nearer
    if spacing > SPARSE_CELLS * step:
        raise InputError(f"{len(points)} points in the face crop, {spacing:.3g} mm apart: too sparse for the grid's "
                         f"{step:.3g} mm cells (a landmark file given as the scan?); give a denser scan or a coarser "
                         "--grid", source, "points")


def _skin_axes(chart: SkinChart, x: np.ndarray, y: np.ndarray, points: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, int, int]:
    """The skin images' grid lines in ``chart``: (fine u, fine v, factor, margin): coarse lines of the grid
    ``x``, ``y``'s step over the chart's image of the cropped ``points`` (n, 3) and at least the grid's span
    (the planar chart: the grid's own lines; an expression's skin may go where the neutral has none, a
    jaw's chin below the neutral's), ``margin`` of them more on every side, each cell split ``factor`` times
    (see :func:`~livebridge.retarget.skin_flow.fine_axes`)."""
    step = float(max(np.diff(x).max(), np.diff(y).max()))
    if not chart.planar:
        uv = chart.to_chart(points)[:, :2]
        low = np.minimum(uv.min(axis=0), [x[0], y[0]])
        high = np.maximum(uv.max(axis=0), [x[-1], y[-1]])
        count = np.ceil((high - low) / step - 1e-9).astype(int) + 1
        x, y = (low[k] + step * np.arange(count[k]) for k in (0, 1))
    margin = int(np.ceil(SKIN_MARGIN_MM / step))  # the crop's edge is no skin edge: keep it off the grid
    fine_x, fine_y, factor = fine_axes(np.linspace(x[0] - margin * step, x[-1] + margin * step, len(x) + 2 * margin),
                                       np.linspace(y[0] - margin * step, y[-1] + margin * step, len(y) + 2 * margin))
    return fine_x, fine_y, factor, margin


def skin_gap_mm(step: float, spacing: float = float("nan")) -> float:
    """A skin-image point farther than this from any scan point is a hole (``step``: the grid's cell, mm;
    ``spacing``: the scan's median point spacing in the skin images' chart, mm, NaN unknown): so every hole of a
    skin image (an eye's opening) lies this far inside the scan's.

    Half the resampling's gap (:data:`~livebridge.retarget.grid.GAP_SPACINGS` cells), but never under
    :data:`SKIN_GAP_SPACINGS` point spacings: on a finer grid than the scan's points fill, the skin images were
    speckled with holes where no point happened to fall, which the flow and the eyes' openings read as the
    skin's. 60k points a scan (`livebridge bench scans`' draw, seed 7) on a 200 x 200 grid built the eyelids
    0.256 / 0.167 relative RMS, on 250 x 250 0.267 / 0.262 (mean of the 16 elements 0.0894, 0.0965); with this
    floor 0.198 / 0.172 and 0.197 / 0.225 (0.0863, 0.0903). On the default 150 x 150 grid the floor (1.9 mm at
    60k points) lies under the grid's own gap (2.2 mm) and changes nothing (0.195 / 0.177, 0.0867); 30k points
    a scan (2.6 mm) built the eyelids 0.302 / 0.287 instead of 0.318 / 0.296, every other element within 0.003
    (mean 0.1420 -> 0.1408).
    """
    gap = step * GAP_SPACINGS / 2
    return max(gap, SKIN_GAP_SPACINGS * spacing) if np.isfinite(spacing) and spacing > 0 else gap


def opening_gap_mm(spacing: float, step: float) -> float:
    """A skin-image point farther than this from any scan point is in one of the scan's holes at its own
    resolution (``spacing``: its median point spacing; ``step``: the grid's cell, mm): the gap by which
    :func:`~livebridge.retarget.grid.resample` masks holes by default (:data:`~livebridge.retarget.grid.GAP_SPACINGS`
    point spacings), at most the skin image's own (:func:`skin_gap_mm`)."""
    gap = skin_gap_mm(step, spacing)
    return float(min(GAP_SPACINGS * spacing, gap)) if np.isfinite(spacing) and spacing > 0 else gap


def prepare_expression(scan: Scan, landmarks: dict[str, np.ndarray], neutral: FaceScan, source=None,
                       landmarks_source=None, mesh_spacing: float | None = None) -> FaceScan:
    """An expression scan of the neutral's person, registered onto it and resampled on its grid lines.

    Parameters
    ----------
    scan : Scan
    landmarks : dict of str to ndarray, shape (3,)
        In the scan's coordinates; each within :data:`LANDMARK_MAX_DISTANCE_MM` of a scan point.
    neutral : FaceScan
    source, landmarks_source : str or Path, optional
        The scan file and its landmark file, named in errors.
    mesh_spacing : float, optional
        A mesh is sampled into points this far apart, mm (default 0.5:
        :mod:`~livebridge.retarget.mesh_samples`), coloured from its texture or vertices.
    """
    landmarks = thesis_points_from_68(landmarks, scan.points, landmarks_source or source)  # see prepare_neutral
    check_on_points(landmarks, scan.points, landmarks_source, source)
    radius = float(neutral.grid.x[-1])
    first_guess = landmark_rigid(landmarks, neutral.landmarks, source)
    scan = _as_points(scan, landmarks, radius, mesh_spacing, first_guess)
    scan, facing = facing_points(scan, first_guess, radius)  # the skull landmarks' frame is near enough
    normals = vertex_normals(neutral.vertices, neutral.triangles)
    scan2face = register_rigid(scan.points, landmarks, neutral.vertices, normals, neutral.landmarks, radius,
                               source=source, first_guess=first_guess)
    scan, points = _without_spikes(scan, apply(scan2face, scan.points), radius)
    scan, points, off_face = _on_the_face(scan, points, neutral.vertices)
    moved = transform_landmarks(scan2face, landmarks)
    scan, points, eyeballs = _without_eyeballs(scan, points, moved, neutral.eyeballs_left_out)
    check_not_folded(neutral.landmarks, moved, landmarks_source or source)
    axes = None if neutral.skin is None else (neutral.skin.x, neutral.skin.y, neutral.skin_factor, neutral.skin_margin)
    face = _resampled(scan, points, neutral.grid.x, neutral.grid.y, radius, moved, scan2face, source, neutral.chart,
                      axes, neutral.shading_removed, report_shading=False)
    inside = points[crop_sphere(points, np.zeros(3), radius)]
    return replace(face, gap_mm=surface_gap(inside, neutral.vertices, normals),
                   noise_mm=noise_level(inside, face.grid), off_face_share=off_face, eyeball_points=eyeballs,
                   eyeballs_left_out=neutral.eyeballs_left_out, facing=facing)


def check_sides(landmarks: dict[str, np.ndarray], reference: dict[str, np.ndarray], source=None) -> None:
    """Raise an :class:`InputError` naming ``source`` (the neutral's landmark file) when the normalised face
    (``landmarks`` in the face frame) is the ``reference`` face's mirror image: its nose tip behind the outer eye
    corners (the rigid normalisation turns a mirrored face round to face away), or most of its ``_L`` / ``_R``
    pairs the other way round. Left and right swapped in the file, or a mirrored scan: the expressions' checks
    would blame their own files."""
    eyes = ("eye_outer_L", "eye_outer_R")
    if all(name in landmarks and name in reference for name in (*eyes, "nose_tip")):
        ahead = [marks["nose_tip"][2] - 0.5 * (marks[eyes[0]][2] + marks[eyes[1]][2])
                 for marks in (landmarks, reference)]
        if ahead[0] * ahead[1] < 0:
            raise InputError(f"normalised, the nose tip lies {abs(ahead[0]):.3g} mm behind the outer eye corners: "
                             "are left and right swapped, or is the scan mirrored?", source, "nose_tip")
    pairs = [name[:-2] for name in landmarks if name.endswith("_L") and name[:-2] + "_R" in landmarks
             and name in reference and name[:-2] + "_R" in reference]
    swapped = [stem for stem in pairs if (landmarks[stem + "_L"][0] - landmarks[stem + "_R"][0])
               * (reference[stem + "_L"][0] - reference[stem + "_R"][0]) < 0]
    if 2 * len(swapped) > len(pairs) > 0:
        raise InputError(f"left and right are the other way round ({len(swapped)} of {len(pairs)} _L / _R pairs, "
                         f"{swapped[0]}_L on the right): are the names swapped, or is the scan mirrored?", source,
                         f"{swapped[0]}_L")


def check_not_folded(neutral: dict[str, np.ndarray], expression: dict[str, np.ndarray], source=None) -> None:
    """Raise an :class:`InputError` naming ``source`` (the expression's landmark file) and a skull landmark
    where the landmark spline from the ``neutral``'s landmarks to the ``expression``'s (both in the face
    frame) turns the face inside out (its Jacobian's determinant <= 0).

    Two scans of one person are carried onto each other without folding; left and right landmarks swapped
    (or two landmarks' names exchanged) are a reflection there, which the rigid registration cannot undo and
    the landmark warp then spreads over the face (249 mm of 'motion' with the left and right landmarks of
    an ICT smile swapped). On the bench's 16 ICT expressions the determinant at the skull landmarks
    (:data:`~livebridge.retarget.normalise.RIGID_LANDMARKS`) is 0.6-1.0; with the swapped smile, -1.1.
    Only the skull landmarks are judged: a lip press brings the inner lips' landmarks together (0.35 there),
    and a noisy press could cross them.
    """
    names = [name for name in neutral if name in expression]
    skull = [name for name in RIGID_LANDMARKS if name in names]
    if len(names) < 5 or not skull:
        return
    warp = fit_tps(np.array([neutral[n] for n in names]), np.array([expression[n] for n in names]),
                   Kernel.BIHARMONIC, LANDMARK_SMOOTHING)
    determinant = np.linalg.det(warp.jacobian(np.array([neutral[n] for n in skull])))
    worst = int(np.argmin(determinant))
    if determinant[worst] <= 0:
        raise InputError(f"the landmarks turn the face inside out here (the spline from the neutral's landmarks has "
                         f"Jacobian determinant {determinant[worst]:.2f}): are left and right swapped, or two "
                         "landmarks' names exchanged?", source, skull[worst])


def check_on_points(landmarks: dict[str, np.ndarray], points: np.ndarray, source=None, scan=None) -> None:
    """Raise an :class:`InputError` naming ``source`` (the landmark file) and the landmark farthest from the
    scan's ``points`` (n, 3) when it is farther than :data:`LANDMARK_MAX_DISTANCE_MM` from all of them.

    The expression's landmarks drive its landmark spline: one off the scan (misplaced, another file's, or in
    other units) would warp the face towards nothing. The scan's own points are the reference, not its
    resampled grid, which the neutral's crop may cut short of an opened jaw's chin.
    """
    from pathlib import Path

    names = list(landmarks)
    distance, _ = cKDTree(points).query(np.array([landmarks[name] for name in names], dtype=np.float64))
    far = np.flatnonzero(distance > LANDMARK_MAX_DISTANCE_MM)
    if far.size:
        k = int(far[np.argmax(distance[far])])
        scan_name = Path(scan).name if scan is not None else "the scan"
        others = [names[i] for i in far if i != k]
        several = f"; {len(others)} more this far: {', '.join(others)}" if others else ""
        raise InputError(f"{distance[k]:.3g} mm from the nearest point of {scan_name} (at most "
                         f"{LANDMARK_MAX_DISTANCE_MM:g} mm{several}): off the scan's surface, in a hole of it or on "
                         "skin it did not see (same coordinates and units as the scan? a head turned away from the "
                         "scanner: leave out of the file the landmarks it could not see)",
                         source, names[k])
