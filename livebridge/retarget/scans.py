"""An actuation basis from scans of one person: a neutral scan and one scan per muscle (Erdoğdu §5.4-5.5).

Preprocessing (§5.4): the neutral scan is normalised (nose tip to the origin, its outer eye corners, chin
and nose tip onto a reference face's; :mod:`~livebridge.retarget.normalise`), cropped to the face, rid of its
stray points (:func:`~livebridge.retarget.grid.spikes`) and resampled onto a regular x-y grid
(:mod:`~livebridge.retarget.grid`). Each expression scan is registered onto it rigidly (skull landmarks, then
trimmed ICP: the person's head moved between scans, their skull did not change), rid of its stray points and
resampled on the same grid lines; how far its skin then lies off the neutral's says whether it is one muscle's
motion on the same face (:mod:`~livebridge.retarget.same_face`).

Modeling (§5.5): a landmark TPS ``f`` carries the neutral face towards the expressive one; control points
(every ``stride``-th grid vertex) go through ``f`` and are snapped to the closest point of the expressive
surface (dropped where that point is on the edge of the scan or of a hole: the surface is not known there),
and a TPS through the control points' moves warps the whole neutral grid. The warp minus the neutral grid
is the muscle's element.

That geometry fixes the motion normal to the skin; the motion ALONG the skin (most of a brow raise, a smile)
it knows only at the landmarks. When the scans carry colour, the skin's pattern is tracked from the neutral
to each expression (:mod:`~livebridge.retarget.skin_flow`, starting from the geometric warp) on a finer
image of both scans (in a chart of the face that does not compress its sides,
:mod:`~livebridge.retarget.chart`), and each grid vertex moves to the expressive surface where its skin
went. Where the skin cannot be tracked (occluded, a hole, no pattern, gone out of the frontal scanner's
view) the tracked skin's motion is carried over by a spline through it, with the lips' seam cut
(:mod:`~livebridge.retarget.seams`: nothing is smoothed or carried from one lip to the other). Around a
closing eye the flow starts from where the eye openings say the lids went
(:mod:`~livebridge.retarget.eyelids`), not from the geometric warp. The skin that did not move then corrects
the shape-only rigid registration (which can slide a fraction of a mm along the face), and tracked motion
along the skin that is not above the flow's noise (estimated on that still skin) is shrunk towards zero.
With more than one coloured expression, the skin is tracked twice: the second time against a template of the
neutral skin averaged from the neutral and the OTHER expressions' skin images, warped back by their first
tracked motion (:mod:`~livebridge.retarget.skin_template`), so the neutral scan's own noise no longer sits
in every element's flow. The second tracking starts from the first one's motion, not from the geometric warp
again: the template's averaged skin is softer than one scan's, and from the warp's first guess the opened
jaw's chin was lost in it (jaw 0.073 after the first tracking, 0.115 after the second from the warp, 0.054
from the first's motion; 150k points a scan, cylinder chart); and it trusts no skin more than the first
tracking did (:func:`_within`: the chin's underside, seen from below the neutral's view, was claimed by
wrong flows against the template). Around a closing eye the second tracking's start
has the lids' margins pinned again where the eye openings say they went (:mod:`~livebridge.retarget.eyelids`,
on top of the first motion): the first tracking's smoothing pulls a margin's motion back towards the still skin
around it (the upper margin's grid vertices of the bench's closed eyes moved 4.7 mm instead of 6.5, their skin
pixels' flow 5.7), and a flow started there lands between its start and the skin's true place again. In
`livebridge bench scans` (seed 7) the eyelid elements went from 0.302 / 0.319 to 0.294 / 0.271 at 60k points a
scan, from 0.238 / 0.241 to 0.217 / 0.233 at 150k (every other element unchanged); with the two eyelid scans
alone, seed 8 at 60k, 0.337 / 0.339 -> 0.293 / 0.321. Starting the lids' skin from the first tracking's own
guess instead (the eyelids' guess on the shape warp, not on the first motion) gained less (the two alone, seed
7: 0.302 / 0.326 at 60k, 0.205 / 0.247 at 150k, against 0.294 / 0.335 and 0.210 / 0.235). The pin needs the
openings read right: a squint's slit narrower than the skin image's gap reads as a closed eye, and pinned there
the synthetic squint's lid of tests/test_eyelids.py was tracked to 0.43-0.52 of its motion instead of 0.06
(the openings are read at the scan's own point spacing: :func:`opening_gap_mm`).

The untracked skin of a closing eye's lids (the vertices whose first guess the eye openings set,
:func:`~livebridge.retarget.eyelids.eyelid_guess`: the lids up to their reach beyond the margins) keeps that
guess instead of the carried motion of the tracked skin: the spline through the tracked skin is smooth over
the whole face, and across an eye it averages the upper lid's ~6-10 mm slide with the lower lid's stillness (the
margins' skin, trusted 0.87-0.95, took 5-13 % of that average). In `livebridge bench scans` (seed 7) the eyelid
elements went from 0.294 / 0.271 to 0.258 / 0.283 at 60k points a scan, from 0.217 / 0.233 to 0.210 / 0.226 at
150k, every other element within 0.0006 (they share the template); their surface errors 0.118 / 0.114 -> 0.107 /
0.117 at 60k, but 0.096 / 0.097 -> 0.100 / 0.100 at 150k. Seed 8 at 60k (all 16 elements): 0.289 / 0.311 ->
0.249 / 0.282, the others within 0.0003. Keeping the guess only inside the openings (between the margins)
gained less (the two eyelid scans alone, seed 8 at 60k: 0.267 / 0.298 against 0.251 / 0.280); carrying nothing
for these two elements gained as much as this (0.253 / 0.278) but the carrying is what keeps an opened jaw's
chin.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.face.meshio import vertex_normals
from livebridge.face.muscle_place import muscle_for
from livebridge.geometry.transforms import apply, invert, transform_scale
from livebridge.retarget.chart import PLANAR, SkinChart, face_chart
from livebridge.retarget.eyelids import closing_openings, eyelid_guess, moving_lids
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
    closest_surface_points,
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
from livebridge.retarget.seams import LipSeam
from livebridge.retarget.skin_flow import fine_axes, in_front, outline_share, pixels_of, ramp, skin_motion
from livebridge.retarget.skin_smoothing import SMOOTH_SPACINGS, shrink_noise, still_skin_correction
from livebridge.retarget.skin_template import skin_templates
from livebridge.retarget.surface_fit import fitted_heights, noise_level
from livebridge.retarget.tps import Kernel, fit_tps

CROP_FACTOR = 1.2
"""Default crop radius: this times the farthest landmark from the nose tip."""
CONTROL_STRIDE = 3
"""Every this many grid rows and columns, a control point."""
LANDMARK_SMOOTHING = 1.0
"""TPS smoothing of the landmark spline (landmarks are placed by hand or detected: never exact)."""
CONTROL_SMOOTHING = 0.1
"""TPS smoothing of the control-point warp (the snapped points carry the scanner's noise)."""
STILL_SPACING_MM = 9.0
"""Candidate still anchors of the shape-only warp (:func:`still_anchors`) lie on grid lines about this far apart
(every 6th of the bench's 1.47 mm grid)."""
STILL_GAP_MM = 0.3
"""A still anchor's expressive surface lies within this of its neutral vertex (the bench's 0.2 mm scans: a still
face's gaps 0.07-0.09 mm at the lower quartile, 0.13-0.16 at the median)."""
MOVED_LANDMARK_MM = 2.0
"""A landmark that moved about this much (over a hand-placed landmark's noise) holds the still anchors off."""
STILL_REACH_MM = 30.0
"""How far from a moved landmark the skin may move with it."""
ANCHOR_CLEARANCE_MM = 3.0
"""No still anchor this near a landmark: the spline would bend sharply between the two."""
MIN_STILLNESS = 0.01
"""Still anchors held more loosely than 100 times a landmark are left out of the spline."""
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
TYPICAL_SPACING_MM = 0.35
"""The point spacing assumed for a face scan whose own is not known (60k points over a face)."""
TRUSTED_TRACKING = 0.97
"""Vertices whose tracking is trusted at least this much carry their motion to the untrusted skin. Measured in
`livebridge bench scans` (60k points): 0.97 beat 0.9 and 0.99 (jaw 0.129 against 0.137 and 0.132)."""
MIN_CARRIERS = 20
"""Fewer trusted control vertices than this carry nothing (the geometric warp stays the fallback)."""
CHART_KIND = "cylinder"
"""The skin images' chart (:mod:`~livebridge.retarget.chart`): a cylinder about a vertical axis fitted to the
neutral face (``"planar"``: the x-y projection, ``"sphere"``); see the chart module for the figures."""
LANDMARK_MAX_DISTANCE_MM = 5.0
"""A landmark farther than this from the resampled surface is an error (off the face, or in a hole)."""
MIN_DEPTH = 0.05
"""A neutral face whose crop lies closer to a plane (RMS) than this fraction of the crop radius is refused as
flat: a face's nose stands 20-35 mm in front of its cheeks, over a crop of about 100 mm."""


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

    def skin_pixels(self) -> np.ndarray:
        """The grid's vertices on the skin image, (row, column) pixels (n_vertices, 2): where the tracked
        motion is read back and the first guesses are given."""
        return pixels_of(self.skin, self.chart.to_chart(self.vertices)[:, :2])

    def landmark_set(self, source=None) -> LandmarkSet:
        """The landmarks at their closest points of the grid mesh (an error names any farther than
        :data:`LANDMARK_MAX_DISTANCE_MM`: off the crop or in a hole)."""
        return place_at_points(self.landmarks, self.vertices, self.triangles, LANDMARK_MAX_DISTANCE_MM, source)


SPARSE_CELLS = 4.0
"""A scan's points may lie at most this many grid cells apart, on average over the face crop's disc."""


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
                    mesh_spacing: float | None = None) -> FaceScan:
    """The neutral scan normalised onto ``reference`` by ``method`` (see
    :func:`~livebridge.retarget.normalise.normalisation`), cropped to a sphere of ``radius`` around the nose
    tip and resampled on a ``shape`` grid over ``[-radius, radius]^2``; its skin images in a ``chart`` fitted
    to it (:func:`~livebridge.retarget.chart.face_chart`); its surface fitted to its points at the grid's
    vertices (:mod:`~livebridge.retarget.surface_fit`). A mesh is first sampled into points every
    ``mesh_spacing`` mm (default 0.5: :mod:`~livebridge.retarget.mesh_samples`), coloured from its texture or
    vertices. Errors name ``source`` (the landmark file) or ``scan_source`` (the scan file: a flat scan).
    Landmarks numbered as the 68-point iBUG layout are named as the thesis's
    (:func:`~livebridge.retarget.landmarks.thesis_points_from_68`)."""
    landmarks = thesis_points_from_68(landmarks, scan.points, source)
    scan2face = normalisation(landmarks, reference, method, source)
    moved = transform_landmarks(scan2face, landmarks)
    check_sides(moved, reference, source)
    radius = crop_radius(moved) if radius is None else float(radius)
    scan = _as_points(scan, landmarks, radius / abs(transform_scale(scan2face)), mesh_spacing, scan2face)
    whole = scan.points
    scan, points = _without_spikes(scan, apply(scan2face, scan.points), radius)
    if not len(points):  # the crop holds no point: say how far apart the scan's and the landmarks' places are
        size = float(np.ptp(whole, axis=0).max())
        spread = float(np.ptp(np.array(list(landmarks.values())), axis=0).max())
        raise InputError(f"no point of the scan within {radius:.3g} mm of the nose tip: the scan spans {size:.3g} mm, "
                         f"its landmarks {spread:.3g} mm: are both in the same units and coordinates?",
                         scan_source or source, "points")
    x, y = square_axes(radius, shape)
    face = _resampled(scan, points, x, y, radius, moved, scan2face, source, chart)
    off_plane = face.vertices - face.vertices.mean(axis=0)
    depth = float(np.linalg.svd(off_plane, compute_uv=False)[-1] / np.sqrt(len(off_plane)))  # RMS off its plane
    if depth < MIN_DEPTH * radius:  # a plane has no face to register the expressions on
        raise InputError(f"flat: its face crop lies within {depth:.2g} mm (RMS) of a plane over {2 * radius:.3g} mm "
                         "(a face is tens of mm deep)", scan_source or source, "points")
    face.landmark_set(source)  # every landmark on the resampled face, or a clear error
    inside = crop_sphere(points, np.zeros(3), radius)
    return replace(face, fitted_heights=fitted_heights(points[inside], face.grid))


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
    return _points_where(samples, front_surface(apply(scan2face, samples.points), cell, HIDDEN_DEPTH_MM))


def _without_spikes(scan: Scan, points: np.ndarray, radius: float) -> tuple[Scan, np.ndarray]:
    """A scan's points (``scan``, a point cloud) and the same points in the face frame (``points``, (n, 3))
    within what the resampling reads (``radius`` of the face's crop and :data:`SKIN_MARGIN_MM`), without their
    flying points (:func:`~livebridge.retarget.grid.spikes`)."""
    keep = crop_sphere(points, np.zeros(3), radius + SKIN_MARGIN_MM)
    keep[keep] = ~spikes(points[keep])
    if keep.all():
        return scan, points
    return _points_where(scan, keep), points[keep]


def _on_the_face(scan: Scan, points: np.ndarray, vertices: np.ndarray) -> tuple[Scan, np.ndarray, float]:
    """An expression scan (``scan``, and ``points`` (n, 3) registered in the face frame) without the points
    more than :data:`OFF_FACE_MM` from every vertex of the neutral (``vertices``, (m, 3)), and the share of its
    points that were: something between the scanner and the face (a hand, glasses, a microphone) that the
    resampling, which keeps the surface the scanner saw first, would take for the face."""
    far = cKDTree(vertices).query(points, distance_upper_bound=OFF_FACE_MM)[0] > OFF_FACE_MM
    if not far.any():
        return scan, points, 0.0
    return _points_where(scan, ~far), points[~far], float(far.mean())


def _points_where(scan: Scan, keep: np.ndarray) -> Scan:
    """A point cloud's points where ``keep`` (n,) bool, with their colours."""
    return Scan(scan.points[keep], np.zeros((0, 3), np.int64), None if scan.colours is None else scan.colours[keep])


def _resampled(scan: Scan, points: np.ndarray, x: np.ndarray, y: np.ndarray, radius: float, landmarks: dict,
               scan2face: np.ndarray, source, chart: SkinChart | str = CHART_KIND,
               skin_axes: tuple | None = None) -> FaceScan:
    """Points in the face frame cropped and resampled on ``x``, ``y``, and on the skin grid too (an image of
    the skin with colour, heights alone without): in ``chart`` (a kind: one of that kind fitted to this scan's
    grid), on ``skin_axes`` (fine u, fine v, factor, margin; None: over this scan's grid)."""
    inside = crop_sphere(points, np.zeros(3), radius)
    _check_dense(points[inside], x, y, source)
    grid = resample(points[inside], x, y, source=source)
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
    colours = None if colours is None else colours[wider]
    skin = resample(on_chart, fine_x, fine_y, skin_gap_mm(step), source, colours)
    visible = in_front(skin, on_chart)  # not another surface seen through a gap of the skin (a nostril)
    if not visible.all():
        on_chart, colours = on_chart[visible], None if colours is None else colours[visible]
        skin = resample(on_chart, fine_x, fine_y, skin_gap_mm(step), source, colours)
    skin_holes = holes(on_chart, fine_x, fine_y, opening_gap_mm(spacing, step))
    return FaceScan(grid, landmarks, scan2face, skin, factor, margin, spacing, chart=chart, skin_holes=skin_holes)


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


def skin_gap_mm(step: float) -> float:
    """A skin-image point farther than this from any scan point is a hole (``step``: the grid's cell, mm): so
    every hole of a skin image (an eye's opening) lies this far inside the scan's."""
    return step * GAP_SPACINGS / 2


def opening_gap_mm(spacing: float, step: float) -> float:
    """A skin-image point farther than this from any scan point is in one of the scan's holes at its own
    resolution (``spacing``: its median point spacing; ``step``: the grid's cell, mm): the gap by which
    :func:`~livebridge.retarget.grid.resample` masks holes by default (:data:`~livebridge.retarget.grid.GAP_SPACINGS`
    point spacings), at most the skin image's own (:func:`skin_gap_mm`)."""
    gap = skin_gap_mm(step)
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
    normals = vertex_normals(neutral.vertices, neutral.triangles)
    scan2face = register_rigid(scan.points, landmarks, neutral.vertices, normals, neutral.landmarks, radius,
                               source=source, first_guess=first_guess)
    scan, points = _without_spikes(scan, apply(scan2face, scan.points), radius)
    scan, points, off_face = _on_the_face(scan, points, neutral.vertices)
    moved = transform_landmarks(scan2face, landmarks)
    check_not_folded(neutral.landmarks, moved, landmarks_source or source)
    axes = None if neutral.skin is None else (neutral.skin.x, neutral.skin.y, neutral.skin_factor, neutral.skin_margin)
    face = _resampled(scan, points, neutral.grid.x, neutral.grid.y, radius, moved, scan2face, source, neutral.chart,
                      axes)
    inside = points[crop_sphere(points, np.zeros(3), radius)]
    return replace(face, gap_mm=surface_gap(inside, neutral.vertices, normals),
                   noise_mm=noise_level(inside, face.grid), off_face_share=off_face)


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
        several = f"; {far.size} landmarks this far" if far.size > 1 else ""
        raise InputError(f"{distance[k]:.3g} mm from the nearest point of {scan_name} (at most "
                         f"{LANDMARK_MAX_DISTANCE_MM:g} mm{several}): off the scan's surface or in a hole of it "
                         "(same coordinates and units as the scan?)",
                         source, names[k])


def expression_element(neutral: FaceScan, expression: FaceScan, stride: int = CONTROL_STRIDE,
                       kernel: Kernel | str = Kernel.BIHARMONIC, source=None, colour: bool = True,
                       start: np.ndarray | None = None, start_trust: np.ndarray | None = None) -> np.ndarray:
    """The displacement (n_vertices, 3) of every neutral grid vertex into the expressive surface (§5.5):
    the geometric warp, refined by skin tracking when both scans have colour (and ``colour``), from
    ``start`` (see :func:`tracked_motion`; trusted ``start_trust``) when given."""
    if not (colour and neutral.coloured and expression.coloured):
        return shape_element(neutral, expression, stride, kernel, source)
    element, trust = tracked_motion(neutral, expression, stride, kernel, source, start, start_trust)
    correction = still_skin_correction(neutral.vertices, element, trust)
    element = apply(correction, neutral.vertices + element) - neutral.vertices
    return shrink_noise(neutral.grid, vertex_normals(neutral.vertices, neutral.triangles), element, trust,
                        view=neutral.chart.view_directions(neutral.vertices))  # the noise is the chart's images'


def shape_element(neutral: FaceScan, expression: FaceScan, stride: int = CONTROL_STRIDE,
                  kernel: Kernel | str = Kernel.BIHARMONIC, source=None) -> np.ndarray:
    """The displacement (n_vertices, 3) from the scans' shape alone: the geometric warp, with each closing
    eyelid's slide read from where the eye opening went (:func:`_lids_guess`), which no landmark knows.

    On the bench's ICT scans (seed 7, 60k points) the eyelid elements 0.94 / 1.02 relative RMS from the warp,
    0.56 / 0.57 with the lids' guess."""
    base = geometric_element(neutral, expression, stride, kernel, source)
    if neutral.skin is None or expression.skin is None:
        return base
    guess, _, eyes = _lids_guess(neutral, expression, base)
    return neutral.chart.motion_from_chart(neutral.vertices, guess) if eyes else base


def _lids_guess(neutral: FaceScan, expression: FaceScan, base: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, list]:
    """``base`` (n_vertices, 3; face frame) in the skin images' chart with the lids' motion from the eye openings
    on top (:func:`~livebridge.retarget.eyelids.eyelid_guess`), the vertices that sets (n_vertices,) bool, and
    the moving eyes (:func:`~livebridge.retarget.eyelids.moving_lids`)."""
    chart, vertices = neutral.chart, neutral.vertices
    before, after = chart.landmarks(neutral.landmarks), chart.landmarks(expression.landmarks)
    seen, seen_grow = _seen_openings(expression)
    eyes = moving_lids(neutral.skin, seen, before, after, skin_gap_mm(neutral.grid.spacing), seen_grow)
    guess, lids = eyelid_guess(neutral.skin, seen, neutral.skin_pixels(), chart.motion_to_chart(vertices, base), eyes)
    return guess, lids, eyes


def smoothing_mm(point_spacings, pixel: float) -> float:
    """The Gaussian sigma (mm) the tracked skin motion is smoothed over: :data:`SMOOTH_SPACINGS` times the
    larger scan's median point spacing in the chart (``point_spacings``; NaN or 0 unknown:
    :data:`TYPICAL_SPACING_MM`), but at least times half the skin images' ``pixel`` (mm).

    Points denser than about one a pixel (random points so dense lie half a pixel apart) make the skin images no
    finer, so the flow's noise stops falling with their spacing. Smoothed by the spacing alone, scans of 1.7M
    points (0.083 mm apart) gave the eyelids 0.196 / 0.220 relative RMS, with this floor 0.172 / 0.201 (the two
    eyelid scans alone; floors of 0.38 and 0.5 mm gave 0.167 / 0.194 and 0.170 / 0.194). The bench's 60k and
    150k points (0.47, 0.30 mm) and a textured mesh's samples (0.28 mm) lie above it.
    """
    spacing = float(np.nanmax([*point_spacings, 0.0]))
    spacing = spacing if spacing > 0 else TYPICAL_SPACING_MM
    return SMOOTH_SPACINGS * max(spacing, pixel / 2)


def tracked_motion(neutral: FaceScan, expression: FaceScan, stride: int = CONTROL_STRIDE,
                   kernel: Kernel | str = Kernel.BIHARMONIC, source=None, start: np.ndarray | None = None,
                   start_trust: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Where each neutral grid vertex's skin went in the (registered) expression scan, (n_vertices, 3), and
    how much that is trusted (n_vertices,), before the still skin corrects the registration: both scans
    must have colour. The flow starts from ``start`` (n_vertices, 3; an earlier tracking's motion) when
    given, else from the geometric warp; either way with the eyelids' guess (:func:`eyelid_guess`: each lid
    margin's motion from the openings, falling off over the lid) on top. With ``start_trust`` (n_vertices,; how
    much that earlier tracking was trusted) no vertex is trusted more than that (:func:`_within`)."""
    smooth = smoothing_mm((neutral.point_spacing, expression.point_spacing), neutral.skin.spacing)
    chart, vertices = neutral.chart, neutral.vertices
    at = neutral.skin_pixels()
    base = geometric_element(neutral, expression, stride, kernel, source, still=False) if start is None else start
    # with a start too, the lids' margins are pinned again where the openings say: see the module's docstring
    guess, lids, eyes = _lids_guess(neutral, expression, base)
    seam = _lip_seam(chart.landmarks(neutral.landmarks), neutral.skin)
    motion, trust = skin_motion(neutral.skin, expression.skin, at, guess, smooth, seam,
                                closing_openings(neutral.skin.shape, eyes), neutral.template,
                                fill_from_beyond=start is not None, lids=eyes)
    if start_trust is not None:
        motion, trust = _within(motion, trust, guess, start_trust)
    # Where the skin was not tracked, the motion of the tracked skin around it is a better guess than the
    # geometric warp: the skin went out of the scanner's view (under an opened jaw's chin, round the face's
    # outline) or into a hole, where the warp snaps it to the wrong, visible, surface. Not around a closing
    # eye, where the eyelids' guess stands (see the module's docstring).
    # Near the skin images' outline the flow is taken less and the carried motion more (see OUTLINE_MM).
    fallback = _carried(neutral.grid, chart, motion, trust, stride, kernel, seam)
    if fallback is not None:
        kept = outline_share(neutral.skin, at)
        motion = guess + kept[:, None] * (motion - guess)
        carried = np.where(lids, 0.0, 1.0 - trust * kept)
        motion = motion + carried[:, None] * (fallback - guess)
    return chart.motion_from_chart(vertices, motion), trust


def _within(motion: np.ndarray, trust: np.ndarray, guess: np.ndarray, most: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """``motion`` (n, 3; ``trust`` times the tracked motion plus the rest of ``guess``) with its trust capped
    at ``most`` (n,): the same blend of the same tracked motion and guess, at the lower trust.

    The second tracking (against the template) trusts no vertex more than the first tracking did: it refines
    the motion of the skin the first one tracked, and where the first could not (skin the neutral scan sees at a
    grazing angle: an opened jaw's chin from underneath) the first's carried motion stays, carried again. The
    template is the other scans' view of the neutral skin warped back by their first motions: no better a view
    of skin none of them saw well, and a flow found against it there can land on a wrong match that the check
    against the neutral's own image (lenient where that image is a smear) partly trusts. Measured on the jaw at
    150k points a scan, second tracking (error^2 share of the chin's underside, in 1e-3 of the element's RMS^2):
    seed 11 0.110 -> 0.064 (10.7 -> 2.8; the lowest rows of the underside had a flow 4.7 mm short of the truth
    trusted 0.3-0.45, where the first tracking's trust was 0.01-0.26), seed 7 0.074 -> 0.056 (4.6 -> 2.0), seed 8
    0.079 -> 0.071 (3.2 -> 2.1); every other element within 0.0001 or better (the eyelids up to 0.0009 better).
    The first tracking alone gave 0.065 / 0.058 / 0.073: the template still helps the skin both trackings trust.
    In `livebridge bench scans` (seed 7) the jaw went 0.070 -> 0.069 at 60k, 0.074 -> 0.056 at 150k, every other
    element within 0.0001 (all 16 at 60k: seed 11 0.067 -> 0.065, seed 8 0.069 -> 0.071, the one loss seen);
    its surface error rose 0.047 -> 0.053 and 0.041 -> 0.047 (seed 11: 0.043 -> 0.056), the
    carried spline's heights being off the expressive surface where the wrong flow's were on it (reading them
    from the expression at the carried place instead: jaw 0.064 -> 0.120 on seed 11, 0.056 -> 0.098 on seed 7).
    """
    capped = np.minimum(trust, most)
    share = np.divide(capped, trust, out=np.zeros_like(trust), where=trust > 0)
    return guess + share[:, None] * (motion - guess), capped


def _seen_openings(expression: FaceScan) -> tuple[FaceGrid, float]:
    """The expression's skin image with its holes at the scan's own resolution masked (``skin_holes``: a
    squinting eye's slit), and how far inside the true edges those holes lie, mm (see :func:`opening_gap_mm`);
    the skin image itself and its gap when the scan has no such mask."""
    skin, gap = expression.skin, skin_gap_mm(expression.grid.spacing)
    if expression.skin_holes is None:
        return skin, gap
    return (replace(skin, heights=np.where(expression.skin_holes, np.nan, skin.heights)),
            opening_gap_mm(expression.point_spacing, expression.grid.spacing))


def _lip_seam(landmarks: dict, skin: FaceGrid) -> LipSeam | None:
    """Where the neutral's lips meet (None without its mouth landmarks, given in ``skin``'s chart): nothing is
    smoothed or carried across it, since an opened mouth takes the lips apart. From the landmarks, moved onto
    the groove between the lips (the skin image's depth), which is more exact than a landmark."""
    seam = LipSeam.from_landmarks(landmarks)
    if seam is None:
        return None
    return seam.along_groove(skin)


def _carried(grid: FaceGrid, chart: SkinChart, motion: np.ndarray, trust: np.ndarray, stride: int,
             kernel: Kernel | str, seam: LipSeam | None) -> np.ndarray | None:
    """The motion (n_vertices, 3; in ``chart``) of the skin whose tracking is trusted (see
    :data:`TRUSTED_TRACKING`) carried over every vertex of ``grid`` by a 3D spline through it, on each side
    of the ``seam`` (in ``chart``) apart (None when too little is trusted). The spline is fitted in the face
    frame: a jaw's rotation is affine there, not in a curved chart, and the spline's affine part carries it
    out to the face's outline (in the cylinder chart the jaw's untrusted skin kept 11.0 mm of error
    instead of 5.2 with the spline fitted in the chart, 60k points)."""
    controls = _control_vertices(grid, stride)
    controls = controls[trust[controls] >= TRUSTED_TRACKING]
    if len(controls) < MIN_CARRIERS:
        return None
    points = chart.to_chart(grid.vertices)
    start = points[controls]
    end = start + motion[controls]

    def fit(begin, to):
        warp = fit_tps(chart.from_chart(begin), chart.from_chart(to), kernel, CONTROL_SMOOTHING)
        return lambda at: chart.to_chart(warp(chart.from_chart(at)))

    warp = fit(start, end) if seam is None else seam.split_fit(start, end, fit)
    return warp(points) - points


def geometric_element(neutral: FaceScan, expression: FaceScan, stride: int = CONTROL_STRIDE,
                      kernel: Kernel | str = Kernel.BIHARMONIC, source=None, still: bool = True) -> np.ndarray:
    """The displacement (n_vertices, 3) from the landmark TPS, control points snapped to the expressive
    surface and the TPS warp through them (§5.5): the motion along the skin is known at the landmarks only.

    With ``still`` the landmark TPS also holds the skin still where the scans say it is (:func:`still_anchors`):
    the thesis's spline through the landmarks alone carries a moved landmark's motion over every part of the
    face no landmark pins (a lip corner's 11 mm out to the cheek's edge). The skin flow starts from the thesis's
    warp (``still=False``): from this one, in `livebridge bench scans`, the other face's jaw was 0.167 relative
    RMS instead of 0.090 (the chin's skin that goes out of the scanner's view under the opened jaw), the other
    elements within 0.007 but for the right eyelid at 60k points (0.242 -> 0.226)."""
    names = [name for name in neutral.landmarks if name in expression.landmarks]
    if len(names) < 4:
        raise InputError(f"the expression scan shares {len(names)} landmarks with the neutral (at least 4)",
                         source, "landmarks")
    before = np.array([neutral.landmarks[n] for n in names])
    after = np.array([expression.landmarks[n] for n in names])
    smoothing = LANDMARK_SMOOTHING
    if still:
        anchors, stillness = still_anchors(neutral, expression, before, after)
        held = neutral.vertices[anchors]
        before, after = np.vstack([before, held]), np.vstack([after, held])
        smoothing = np.concatenate([np.full(len(names), LANDMARK_SMOOTHING), LANDMARK_SMOOTHING / stillness])
    f = fit_tps(before, after, kernel, smoothing)
    controls = _control_vertices(neutral.grid, stride)
    start = neutral.vertices[controls]
    end, known = _on_expression(f(start), expression)
    if known.sum() < 4:
        raise InputError("the expression scan does not overlap the neutral face", source, "points")
    warp = fit_tps(start[known], end[known], kernel, CONTROL_SMOOTHING)
    return warp(neutral.vertices) - neutral.vertices


def still_anchors(neutral: FaceScan, expression: FaceScan, before: np.ndarray, after: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Where a shape-only expression is taken to leave the skin still: vertex ids (k,) of the neutral grid, and
    how surely, (k,) in (0, 1] (the landmark TPS holds each with ``1 / stillness`` times a landmark's smoothing).

    ``before``, ``after``: the landmarks on the neutral and on the expression, (n, 3). The candidates are grid
    points :data:`STILL_SPACING_MM` apart, inside the expression scan and :data:`ANCHOR_CLEARANCE_MM` from every
    landmark. A scan with one muscle contracted moves the skin near that muscle's landmarks and changes the
    surface there, so a candidate is the surer still the nearer the expressive surface passes it (sure within
    :data:`STILL_GAP_MM`, or the scan's own noise if larger; not at all beyond twice that) and the farther it is
    from every landmark that moved (not at all within 0.75 :data:`STILL_REACH_MM` of one that moved over 1.5
    :data:`MOVED_LANDMARK_MM`; sure beyond 1.25 of it, or from one that moved under half of it). Graded, not
    cut: one scan point more or fewer must not tip a candidate in or out (cut at the thresholds, a jaw element
    changed by 16 % of its RMS motion with a hand's points left out of its scan; graded, 0.8 %).

    The skin can slide without changing the surface (a cheek raised by the levator labii): there this is
    wrong. Measured without colour on the bench's ICT scans (seeds 7, 8 at 60k points, seed 11 at 150k,
    textured meshes, another face): see the README's figures."""
    candidates = _control_vertices(neutral.grid, max(1, round(STILL_SPACING_MM / neutral.grid.spacing)))
    points = neutral.vertices[candidates]
    on, inside = _on_expression(points, expression)
    noise = expression.noise_mm if np.isfinite(expression.noise_mm) else 0.0
    limit = max(STILL_GAP_MM, noise)
    stillness = inside * (1.0 - ramp(np.linalg.norm(on - points, axis=1), limit, 2.0 * limit))
    stillness *= cKDTree(before).query(points)[0] > ANCHOR_CLEARANCE_MM
    moved = ramp(np.linalg.norm(after - before, axis=1), 0.5 * MOVED_LANDMARK_MM, 1.5 * MOVED_LANDMARK_MM)
    for landmark in np.flatnonzero(moved):
        near = 1.0 - ramp(np.linalg.norm(points - before[landmark], axis=1), 0.75 * STILL_REACH_MM,
                           1.25 * STILL_REACH_MM)
        stillness *= 1.0 - moved[landmark] * near
    keep = stillness > MIN_STILLNESS
    return candidates[keep], stillness[keep]


def _on_expression(points: np.ndarray, expression: FaceScan) -> tuple[np.ndarray, np.ndarray]:
    """The closest points (n, 3) of the expression's grid surface to ``points`` (n, 3), and whether each lies
    inside the scan (n,): not on a triangle touching its edge or a hole, where the closest point is no match."""
    triangle, barycentric, _ = closest_surface_points(points, expression.vertices, expression.triangles)
    corners = expression.triangles[triangle]
    known = ~_border_vertices(expression.grid)[corners].any(axis=1)
    return np.einsum("nk,nkd->nd", barycentric, expression.vertices[corners]), known


def basis_from_scans(neutral: FaceScan, expressions: dict[str, FaceScan],
                     kernel: Kernel | str = Kernel.BIHARMONIC, colour: bool = True, log=None) -> Basis:
    """One element per expression scan (by muscle name) on the neutral's grid mesh (skin tracked where the
    scans have colour, unless not ``colour``). With colour, each expression is tracked against a template
    of the neutral skin averaged from all the scans (:mod:`~livebridge.retarget.skin_template`). ``log``
    (a callable taking a line) hears of each element as it is built: the build takes tens of seconds each."""
    names = list(expressions)
    neutrals = [neutral] * len(names)
    coloured = [face for face in expressions.values() if face.coloured]
    starts = trusts = [None] * len(names)
    say = log or (lambda line: None)
    passes = 1
    if colour and neutral.coloured and len(coloured) == len(names) > 1:
        passes = 2
        neutrals, starts, trusts = _with_templates(neutral, expressions, kernel, say)
    elements = []
    for k, (own, name, start, trust) in enumerate(zip(neutrals, names, starts, trusts), 1):
        tracking = colour and own.coloured and expressions[name].coloured
        say(f"  {name}: {'tracking the skin' if tracking else 'shape only'} "
            f"({k}/{len(names)}{', second pass, against the template' if passes == 2 else ''})")
        elements.append(expression_element(own, expressions[name], kernel=kernel, source=name, colour=colour,
                                           start=start, start_trust=trust))
    elements = np.stack(elements)
    muscles = tuple(muscle_for(name, element, neutral.vertices, neutral.landmarks)
                    for name, element in zip(expressions, elements))
    return Basis(neutral.mesh_vertices, neutral.triangles, elements, muscles)


def in_scan_frame(basis: Basis, neutral: FaceScan) -> Basis:
    """``basis`` (built on ``neutral``'s grid, in the face frame) in the neutral scan's own coordinates, mm:
    its neutral mesh taken back by the inverse of ``scan2face``, its elements by that map's linear part, so the
    basis lies on the scan and each element moves it as it moved the normalised face (an affine
    normalisation's change of proportions undone too)."""
    face2scan = invert(neutral.scan2face)
    return Basis(apply(face2scan, basis.neutral), basis.triangles, basis.elements @ face2scan[:3, :3].T,
                 basis.muscles)


def _with_templates(neutral: FaceScan, expressions: dict[str, FaceScan], kernel: Kernel | str, say
                    ) -> tuple[list[FaceScan], list[np.ndarray], list[np.ndarray]]:
    """The neutral once per expression, with the template of the other scans' skin to track against, each
    expression warped back by its tracked motion (one round of groupwise registration); each expression's
    tracked motion (n_vertices, 3), where its second tracking starts; and how much that motion is trusted
    (n_vertices,), the most its second tracking may trust (:func:`_within`); ``say`` hears of each."""
    vertices, chart = neutral.vertices, neutral.chart
    tracked, motions, trusts = [], [], []
    for k, (name, face) in enumerate(expressions.items(), 1):
        say(f"  {name}: tracking the skin ({k}/{len(expressions)}, first pass, against the neutral)")
        motion, trust = tracked_motion(neutral, face, kernel=kernel, source=name)
        tracked.append((face.skin, chart.motion_to_chart(vertices, motion), trust))
        motions.append(motion)
        trusts.append(trust)
    templates = skin_templates(neutral.skin, neutral.skin_pixels(), tracked)
    return [replace(neutral, template=template) for template in templates], motions, trusts


def _control_vertices(grid: FaceGrid, stride: int) -> np.ndarray:
    """Vertex ids of every ``stride``-th valid grid point in rows and columns."""
    index = grid.index[::stride, ::stride]
    return index[index >= 0]


def _border_vertices(grid: FaceGrid) -> np.ndarray:
    """Vertices with a masked grid point (or the grid's edge) among their 8 neighbours, shape (n_vertices,)."""
    valid = np.pad(grid.valid, 1)
    inner = np.ones(grid.shape, bool)
    for dr in (0, 1, 2):
        for dc in (0, 1, 2):
            inner &= valid[dr:dr + grid.shape[0], dc:dc + grid.shape[1]]
    return ~inner[grid.valid]
