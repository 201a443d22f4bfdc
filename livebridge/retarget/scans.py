"""An actuation basis from scans of one person: a neutral scan and one scan per muscle (Erdoğdu §5.4-5.5).

Preprocessing (§5.4) makes each scan a :class:`~livebridge.retarget.face_scan.FaceScan` (cropped, resampled
and in the face frame: :mod:`~livebridge.retarget.face_scan`).

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
neutral skin averaged from the neutral and the OTHER expressions' skin images, warped back by their first tracked
motion (:mod:`~livebridge.retarget.skin_template`), so the neutral scan's own image noise no longer sits in every
element's flow. Where that noise misplaced the neutral's skin, it still does (the template lies where the neutral
put the skin): that shared motion is read off the skin each expression leaves still and taken out of every tracked
element (:mod:`~livebridge.retarget.neutral_noise`). The second tracking starts from the first one's motion, not
from the geometric warp again: the template's averaged skin is softer than one scan's, and from the warp's first
guess the opened jaw's chin was lost in it (jaw 0.073 after the first tracking, 0.115 after the second from the
warp, 0.054 from the first's motion; 150k points a scan, cylinder chart); and it trusts no skin more than the
first tracking did (:func:`_within`: the chin's underside, seen from below the neutral's view, was claimed by
wrong flows against the template). Around a closing eye the second tracking's start has the lids' margins pinned
again where the eye openings say they went (:mod:`~livebridge.retarget.eyelids`, on top of the first motion): the
first tracking's smoothing pulls a margin's motion back towards the still skin around it (the upper margin's grid
vertices of the bench's closed eyes moved 4.7 mm instead of 6.5, their skin pixels' flow 5.7), and a flow started
there lands between its start and the skin's true place again. In `livebridge bench scans` (seed 7) the eyelid
elements went from 0.302 / 0.319 to 0.294 / 0.271 at 60k points a scan, from 0.238 / 0.241 to 0.217 / 0.233 at
150k (every other element unchanged); with the two eyelid scans alone, seed 8 at 60k, 0.337 / 0.339 -> 0.293 /
0.321. Starting the lids' skin from the first tracking's own guess instead (the eyelids' guess on the shape warp,
not on the first motion) gained less (the two alone, seed 7: 0.302 / 0.326 at 60k, 0.205 / 0.247 at 150k, against
0.294 / 0.335 and 0.210 / 0.235). The pin needs the openings read right: a squint's slit narrower than the skin
image's gap reads as a closed eye, and pinned there the synthetic squint's lid of tests/test_eyelids.py was
tracked to 0.43-0.52 of its motion instead of 0.06 (the openings are read at the scan's own point spacing:
:func:`~livebridge.retarget.face_scan.opening_gap_mm`).

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

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.face.meshio import vertex_normals
from livebridge.face.muscle_place import muscle_for
from livebridge.geometry.transforms import apply, invert
from livebridge.retarget.chart import SkinChart
from livebridge.retarget.eyelids import LID_LANDMARK_NAMES, closing_openings, eyelid_guess, moving_lids
from livebridge.retarget.face_scan import LANDMARK_SMOOTHING, FaceScan, opening_gap_mm
from livebridge.retarget.grid import (
    FaceGrid,
)
from livebridge.retarget.landmarks import (
    closest_surface_points,
)
from livebridge.retarget.neutral_noise import neutral_noise
from livebridge.retarget.seams import LipSeam
from livebridge.retarget.skin_flow import outline_share, ramp, skin_motion
from livebridge.retarget.skin_smoothing import SMOOTH_SPACINGS, shrink_noise, still_skin_correction
from livebridge.retarget.skin_template import skin_templates
from livebridge.retarget.tps import Kernel, fit_tps

CONTROL_STRIDE = 3
"""Every this many grid rows and columns, a control point."""
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
TYPICAL_SPACING_MM = 0.35
"""The point spacing assumed for a face scan whose own is not known (60k points over a face)."""
TRUSTED_TRACKING = 0.97
"""Vertices whose tracking is trusted at least this much carry their motion to the untrusted skin. Measured in
`livebridge bench scans` (60k points): 0.97 beat 0.9 and 0.99 (jaw 0.129 against 0.137 and 0.132)."""
MIN_CARRIERS = 20
"""Fewer trusted control vertices than this carry nothing (the geometric warp stays the fallback)."""


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
    0.56 / 0.57 with the lids' guess.

    The lids' iBUG landmarks (:data:`~livebridge.retarget.eyelids.LID_LANDMARK_NAMES`), when the files name them,
    give the guess its margins where no opening is seen, and stay out of the warp's landmark spline: there they
    carried the lids' 10 mm to the skin around the eyes, which no flow corrects without colour (the bench's
    scans with the 8 lid landmarks, eyelids 0.603 / 0.552 instead of 1.103 / 1.019; with the eyeballs seen and
    no colour to leave them out by, 0.580 / 0.562 instead of 0.970 / 0.903). A flow started from the warp
    does better with them (0.204 / 0.227 against 0.206 / 0.247), so :func:`tracked_motion` keeps them."""
    base = geometric_element(neutral, expression, stride, kernel, source, left_out=LID_LANDMARK_NAMES)
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
    eyes = moving_lids(neutral.skin, seen, before, after, neutral.skin_gap, seen_grow)
    guess, lids = eyelid_guess(neutral.skin, seen, neutral.skin_pixels(), chart.motion_to_chart(vertices, base), eyes)
    return guess, lids, eyes


def smoothing_mm(point_spacings, pixel: float) -> float:
    """The Gaussian sigma (mm) the tracked skin motion is smoothed over:
    :data:`~livebridge.retarget.skin_smoothing.SMOOTH_SPACINGS` times the
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
    given, else from the geometric warp; either way with the eyelids' guess
    (:func:`~livebridge.retarget.eyelids.eyelid_guess`: each lid
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
    squinting eye's slit), and how far inside the true edges those holes lie, mm (see
    :func:`~livebridge.retarget.face_scan.opening_gap_mm`);
    the skin image itself and its gap when the scan has no such mask."""
    skin, gap = expression.skin, expression.skin_gap
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
                      kernel: Kernel | str = Kernel.BIHARMONIC, source=None, still: bool = True,
                      left_out: tuple = ()) -> np.ndarray:
    """The displacement (n_vertices, 3) from the landmark TPS, control points snapped to the expressive
    surface and the TPS warp through them (§5.5): the motion along the skin is known at the landmarks only.

    With ``still`` the landmark TPS also holds the skin still where the scans say it is (:func:`still_anchors`):
    the thesis's spline through the landmarks alone carries a moved landmark's motion over every part of the
    face no landmark pins (a lip corner's 11 mm out to the cheek's edge). The skin flow starts from the thesis's
    warp (``still=False``): from this one, in `livebridge bench scans`, the other face's jaw was 0.167 relative
    RMS instead of 0.090 (the chin's skin that goes out of the scanner's view under the opened jaw), the other
    elements within 0.007 but for the right eyelid at 60k points (0.242 -> 0.226). The landmarks named in
    ``left_out`` do not join the landmark TPS."""
    names = [name for name in neutral.landmarks if name in expression.landmarks and name not in left_out]
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
    elements, tracked = [], []
    for k, (own, name, start, trust) in enumerate(zip(neutrals, names, starts, trusts), 1):
        tracking = colour and own.coloured and expressions[name].coloured
        tracked.append(tracking)
        say(f"  {name}: {'tracking the skin' if tracking else 'shape only'} "
            f"({k}/{len(names)}{', second pass, against the template' if passes == 2 else ''})")
        elements.append(expression_element(own, expressions[name], kernel=kernel, source=name, colour=colour,
                                           start=start, start_trust=trust))
    elements = np.stack(elements)
    tracked = np.array(tracked)
    shared = neutral_noise(elements[tracked])
    if shared.any():
        elements[tracked] -= shared
        say(f"  the neutral scan's own noise, which every tracked element shares: "
            f"{np.sqrt(np.mean(np.sum(shared ** 2, axis=1))):.2f} mm RMS, taken out of all {tracked.sum()}")
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
