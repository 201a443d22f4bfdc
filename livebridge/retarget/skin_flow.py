"""Skin motion along the face from the scans' colour: dense optical flow between two skin images.

Geometry tells how far a face moved along its normal; how far the skin slid ALONG the surface it cannot
see (a raised brow slides the forehead's skin up a surface of almost the same shape). The skin's own
pattern (pores, freckles, brows, lips) moves with it, so a coloured scanner sees that motion: resampled on
a fine regular grid (:mod:`~livebridge.retarget.grid`) of a chart of the face
(:mod:`~livebridge.retarget.chart`; its heights the chart's), a face scan is an image of its skin, and where
a neutral skin point went in an expression is where its pattern went between the two images.

Both images are contrast-normalised (the local mean subtracted and divided by the local spread, over
:data:`CONTRAST_MM`), so a scan's exposure and slow shading do not count as motion. OpenCV's DIS optical
flow (patches of :data:`PATCH_MM`) then finds the residual motion after a first guess (the landmark and
geometry warp), and a photometric check (how well the neutral skin matches the expressive skin where the
flow puts it) says where the flow is trusted: occluded skin (lips rolled in, the inside of an opened
mouth), holes and featureless skin fall back to the first guess.

The tracked motion is noisy, and its noise is what limits a basis built from scans:
:mod:`~livebridge.retarget.skin_smoothing` keeps it down (the motion smoothed to the scan's point spacing, the
registration's rigid slip taken out on the still skin, motion below the noise shrunk towards zero). The errors
of differently tuned flows are 0.8-0.97 correlated (patches of 4, 8 and 12 mm), and a dense Gauss-Newton
photometric refinement after DIS (a bilinear lattice of 1.5-2 mm nodes with a second-difference prior, over all
pixels) cut the per-pixel flow noise 2-3x but not the error at the element's scale (the mean relative error of
the 8 smooth elements of :mod:`~livebridge.retarget.skin_smoothing` 0.124 either way, 6 s more per element), so
what remains at 60k points is what the skin images themselves say, not the estimator: a low-pass of the images
before normalising (0.3-0.8 mm) was worse (0.158-0.187 against 0.159), so the finest pattern still carries
motion.

The same holds on a closing eye's lid, whose skin stretches about twice as the lid comes down (the eyelid scans
of seed 7 alone, 60k points a scan, 0.218 / 0.219 relative RMS): warped by the TRUE motion the expression's lid
skin matches the neutral's worse (local RMS residual 0.71 / 0.75 over the lids) than warped by the flow (0.63 /
0.67), both at the 0.6 two scans of one skin give, so the images do not pin the lid's motion; a Gauss-Newton
refinement on a 1.5 mm lattice there moved the flow further from the truth (0.72 -> 0.75 mm RMS over the lids),
and OpenCV's other dense flows were worse (DualTVL1 0.222 / 0.255, Farneback 0.241 / 0.259, DeepFlow 0.312 /
0.342); DIS's smoothness 5, 10 or 40 instead of 20 gave 0.231 / 0.241, 0.214 / 0.227, 0.237 / 0.382, and patches
of 4, 6 or 12 mm 0.206 / 0.225, 0.212 / 0.218, 0.234 / 0.313 (6 mm, the only one better for both eyes, with all
16 scans 0.204 / 0.231 against 0.207 / 0.245, but the brow, the smile and the lip press worse: frontalis_L 0.062
-> 0.066, zygomatic_major_R 0.047 -> 0.054, lips_pressor 0.111 -> 0.115). The true motion of every skin pixel
(all three components) put through the rest of the pipeline gives 0.134 / 0.120: the lids' margins near the eye's
corners and the lid's height change hold most of what is left. The true x-y motion in place of the flow's (the
pipeline as it is since, heights read from the scans) gives 0.127 / 0.123: the true motion there changes by up to 1 mm
per mm of skin (the inner corner, the margin), which any smoothing, and the 0.2-0.3 mm a resampled vertex lies off
the skin, turn into tenths of a mm. Taken unsmoothed (no monotone fit), and the closing eye's fill band left its
own, the true x-y motion gives 0.106 / 0.107, most of what is left in the heights (0.67 / 0.75 of the 1.13 /
1.15 hundredths of the element's squared motion that make it). Of that, 0.31 / 0.35 is 25 lid vertices per eye
that move over 1 mm and land BEHIND the closed eye's scanned front surface (median 0.8-2 mm: folded under the
lid, or into the inner corner's pocket), where no frontal scan sees them; without the 40 / 44 vertices that land
over 0.5 mm behind it, 0.098 / 0.099. So the lids' 10 % would need both a tangential motion as exact as the truth
and a model of the skin the closed lid hides.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
from scipy.ndimage import map_coordinates

from livebridge.retarget.grid import FaceGrid
from livebridge.retarget.shading import LUMINANCE
from livebridge.retarget.skin_smoothing import (
    WIDTHS,
    adaptive_smooth,
    masked_blur,
    monotone_lids,
    robust_heights,
    surface_rise,
    twiced,
    weighted_blur,
)

FINE_MM = 0.5
"""Spacing of the skin images (a structured-light face scan has a point every ~0.5-1 mm)."""
CONTRAST_MM = 3.0
"""Width of the local contrast normalisation (removes exposure and slow shading, keeps pores and freckles)."""
CHECK_MM = 1.5
"""Width of the window over which the photometric check averages."""
TRUSTED_RESIDUAL = 1.0
"""A match with a local RMS residual (contrast-normalised units; unrelated skin gives about 1.4) of at most
this is trusted fully; the trust falls to zero at twice it. Two scans of the same skin at 60k points differ
by about 0.6 (their finest pores are resolved differently), so 1.0 leaves true matches fully trusted: 0.8
gave 0.131 instead of 0.124 mean relative error on the 8 smooth elements (see above), 0.6 gave 0.18."""
PATCH_MM = 8.0
"""DIS patch width. A face's trackable pattern (freckles, brows, 3 mm blotches) is sparse: 8 mm patches
(16 px at the 0.5 mm skin image) always hold some, where the preset's 8 px (4 mm) often hold pores only.
Mean relative error of the 8 smooth elements at 60k points a scan: 0.145 with 8 px, 0.124 with 16 px,
0.126 with 20 px."""
PATCH_OVERLAP = 4
"""Patches start every ``1 / PATCH_OVERLAP`` of a patch (the DIS presets' ratio; half-overlap lost 0.005)."""
REFINEMENT_ITERATIONS = 20
"""Iterations of DIS's variational refinement at each pyramid level (the MEDIUM preset's 5 leave the dense
flow between the patches' estimates unsettled where the skin's pattern is weak). The flow against the true
motion (60k points a scan, seeds 7 and 8, depressor_anguli_oris / lips_pressor / frontalis_L, the second
tracking's inputs): RMS error on the moving skin 0.326 -> 0.298 mm, 0.165 -> 0.158 mm after a 5 mm
Gaussian; 10 iterations 0.309 / 0.161, 40 0.294 / 0.157. A full-resolution flow of a 490 x 490 px image
pair takes 0.41 s of one core instead of 0.32 s (40: 0.52 s). `livebridge bench
scans` (seed 7): every element but the jaw better (+0.0007 / +0.0002 at 60k / 150k points), lips_pressor
0.115 -> 0.109, depressor_anguli_oris 0.118 -> 0.114 at 60k; seed 8 at 60k lips_pressor 0.119 -> 0.114,
depressor_anguli_oris 0.120 -> 0.117, nothing worse by more than 0.003 (orbicularis_oculi_R)."""
OUTLINE_MM = (1.5 * PATCH_MM, 3 * PATCH_MM)
"""Within the first of these of the skin image's outline (:func:`outline_share`) a skin point's own flow is not
taken, beyond the second in full, linearly between; the carried motion of the skin tracked well takes the rest
(:func:`~livebridge.retarget.scans.tracked_motion`). A DIS patch that reaches past the outline matches the two
images' outlines, and two scans in different poses do not end at the same skin: the flow there kept its first
guess, the landmark spline extrapolated 70-100 mm out, trusted 0.9-0.99 (the photometric check sees the same
skin). DIS's coarser pyramid levels take the same patches in pixels, twice as wide in mm a level, so the
outline reaches further than one patch. On the bench's other face (60k points, seed 7) skin more than 30 mm from
everything an element moves kept up to 1.94 mm of motion at the face's sides and under the chin (mean over the
16 elements of its RMS 0.087 mm); mean relative error of the 16 elements 0.1014. With the flow given way over
(4, 8) mm: 1.24 mm, 0.1004; (8, 16): 0.76 mm, 0.0994; (12, 24): 0.72 mm, 0.0985; (16, 32): 0.73 mm, 0.0990.
With (12, 24) on the ICT face (60k points, seeds 7, 8, 11; 150k; textured meshes) no element is worse by more
than 0.001 and the lip corner is better in every draw (0.114 -> 0.113, 0.117 -> 0.115, 0.117 -> 0.110, 0.074 ->
0.070, 0.066 -> 0.057), the right eyelid 0.242 -> 0.228 at seed 7 (seeds 8 and 11 unchanged; the gain is on
its upper lid, 5-8 mm of motion, which lies beyond the outline's reach: the other scans' changed motion there
enters the second tracking through the template of the neutral skin). Letting the flow's trust itself fall
near the outline instead (fewer trusted skin points for the still-skin correction and the second tracking) cost
the jaw, whose chin the outline guides: 0.071 -> 0.078 (ICT face), 0.090 -> 0.101 (other face) for (4, 8)."""
COARSE_FACTOR = 2
"""Before the full-resolution passes, one flow on images this many times coarser (see :func:`_flow`).
Without it, zygomatic_major_R's smile at 60k points a scan measured 0.165 (seed 7) and 0.230 (seed 8) in
the cylinder chart: the landmark warp was 5-10 mm off at the face's lower outline and the full-resolution
flow settled on a wrong match there (trusted 0.97); with it 0.057 / 0.054, nothing else worse by more than
0.006 (`livebridge bench scans`). The coarse flow's images are contrast-normalised over this many times
:data:`CONTRAST_MM` (the same number of their own pixels as the full-resolution images): normalised at the
full-resolution width, the coarse images kept only the finest pattern that their pixels average away.
`livebridge bench scans` (seed 7, 60k / 150k points): orbicularis_oculi_R 0.272 -> 0.242 / 0.186 -> 0.181,
jaw 0.070 -> 0.067 at 60k, nothing worse by more than 0.004 (orbicularis_oculi_L 0.212 -> 0.217 at 60k,
levator_labii_R 0.046 -> 0.049 at 150k); seed 8 at 60k orbicularis_oculi_R 0.247 -> 0.243, nothing worse
by more than 0.001."""
PASSES = 2
"""Flow passes, each starting from the last one's motion (the first from the geometric warp)."""
BEHIND_MM = 4.0
"""A skin-image point this far behind the front surface around it (beyond what the front's own slope falls
over the window: see :func:`behind_front`) is another surface showing through gaps of the front one (a
nostril's inside), not skin: its height is left out of the heights' smoothing. The surfaces showing through
a nostril lie 10-30 mm behind; 3 / 4 / 5 mm measured alike (single-pass elements at 150k points a scan:
depressor_anguli_oris 0.099 / 0.097 / 0.097, lips_pressor 0.102 / 0.104 / 0.107; 0.110 and 0.113 without).
The nostrils had carried 29 % of depressor_anguli_oris's error^2 at 150k points (RMS 0.47 mm against 0.17 mm
on the rest; 0.20 mm with this): the robust smoothing's three rounds do not escape from a start spoiled by
20-50 % of points 25 mm off (8 rounds instead: 0.31 mm). In `livebridge bench scans` (seed 7; 60k / 150k
points): depressor_anguli_oris 0.144 / 0.103 -> 0.139 / 0.098, lips_pressor 0.138 / 0.110 -> 0.140 / 0.105
(with the lips' seam of :mod:`~livebridge.retarget.seams` on the groove's gentler flank)."""
FRONT_WINDOW_MM = 2.0
"""Width of the square window whose upper fifth of heights is the front surface for :func:`behind_front`."""


def fine_axes(x: np.ndarray, y: np.ndarray, spacing: float = FINE_MM) -> tuple[np.ndarray, np.ndarray, int]:
    """Grid lines ``factor`` times finer than ``x`` (n_cols,), ``y`` (n_rows,) so that every coarse grid
    point is a fine one, with steps of at most about ``spacing`` mm: (fine x, fine y, factor)."""
    step = float(max(np.diff(x).max(), np.diff(y).max()))
    factor = max(1, int(np.ceil(step / spacing - 1e-9)))
    return (np.linspace(x[0], x[-1], (len(x) - 1) * factor + 1), np.linspace(y[0], y[-1], (len(y) - 1) * factor + 1),
            factor)


def skin_image(grid: FaceGrid, contrast_mm: float = CONTRAST_MM) -> tuple[np.ndarray, np.ndarray]:
    """The luminance of a coloured grid contrast-normalised over ``contrast_mm``, (n_rows, n_cols) float32
    (0 where masked), and its valid mask."""
    valid = skin_valid(grid)
    luminance = np.where(valid, np.nan_to_num(grid.colours) @ LUMINANCE, 0.0)
    sigma = contrast_mm / grid.spacing
    mean = masked_blur(luminance, valid, sigma)
    detail = np.where(valid, luminance - mean, 0.0)
    spread = np.sqrt(masked_blur(detail ** 2, valid, sigma))
    scale = max(float(np.median(spread[valid])) * 0.1, 1e-6) if valid.any() else 1.0
    return np.where(valid, detail / np.maximum(spread, scale), 0.0).astype(np.float32), valid


def skin_valid(grid: FaceGrid) -> np.ndarray:
    """The pixels (n_rows, n_cols) bool of a grid that hold skin: a height, and a colour if it has colour."""
    valid = np.isfinite(grid.heights)
    return valid if grid.colours is None else valid & np.isfinite(grid.colours).all(axis=2)


def outline_share(grid: FaceGrid, at: np.ndarray, inner_mm: float = OUTLINE_MM[0],
                  outer_mm: float = OUTLINE_MM[1]) -> np.ndarray:
    """How much of its own flow each of the points ``at`` (n, 2; (row, column) pixels of the skin image ``grid``)
    may keep by its distance from the skin image's outline (see :data:`OUTLINE_MM`): 0 within ``inner_mm``, 1
    beyond ``outer_mm``, linear between; shape (n,).

    The outline is where the skin stops on the way out to the image's edge (the scan's silhouette and crop, the
    image's own edge); holes within the face (the eyes, the nostrils, a mouth) are not.
    """
    labels, outside = _gaps(skin_valid(grid))
    beyond = np.pad(labels == outside, 1, constant_values=True)  # the image's edge is an outline too
    distance = cv2.distanceTransform((~beyond).astype(np.uint8), cv2.DIST_L2, 5)[1:-1, 1:-1] * grid.spacing
    return ramp(np.nan_to_num(at_vertices(distance[..., None], at)[:, 0], nan=0.0), inner_mm, outer_mm)


def closing_holes(valid: np.ndarray, closing: np.ndarray) -> np.ndarray:
    """The holes of a skin image (``valid`` (n_rows, n_cols) bool, its skin) that ``closing`` (same shape, bool: the
    eye openings that close) touches, bool; the gap beyond the face's outline (open to the image's edge) is none.

    :func:`track_skin` shows the flow the expression's skin there, warped by the motion so far. Left empty, the
    opening matched no skin of the closed eye, and DIS patches across it pulled the lid's skin off its motion:
    in `livebridge bench scans` (60k points a scan, seed 7, the ICT face and the other one) the built upper lids
    lay 0.17-0.35 mm below the true ones on average, within 0.12 mm with the fill (their lid guess, 0.76-1.04 mm
    too low, is what the flow corrects).
    Eyelid elements, relative RMS, without -> with: 0.206 / 0.228 -> 0.198 / 0.180; seed 8 0.201 / 0.231 -> 0.195
    / 0.224; seed 11 0.205 / 0.208 -> 0.208 / 0.203; textured meshes 0.154 / 0.164 -> 0.153 / 0.157; the other
    face 0.296 / 0.192 -> 0.193 / 0.177 (its upper lid's share of the error^2 fell to a third); at 150k points
    0.173 / 0.182 -> 0.181 / 0.182, the one loss. No other element moved by more than 0.002 in any of them.
    Filling every hole of both images instead (the expression's opened mouth too) cost the jaw 0.002-0.010 in
    every draw; every hole of the neutral (a parted mouth's slit too), the other face's lip corner 0.128 ->
    0.137. On a synthetic opening squeezed shut (a textured plane, the flow started at the true motion) the fill
    was not better (0.117 against 0.084 mm RMS on the lid): the figures above, through the whole pipeline, are
    the case for it.
    """
    labels, outside = _gaps(valid)
    touched = np.unique(labels[closing & ~valid])
    return np.isin(labels, touched[(touched > 0) & (touched != outside)])


def _gaps(valid: np.ndarray) -> tuple[np.ndarray, int]:
    """The connected gaps of a skin image's skin (``valid`` (n_rows, n_cols) bool) as labels (same shape, 0 on the
    skin), and the label of the gap outside the face: the one joined to the image's edge (the frame joins every
    gap that reaches the edge)."""
    from scipy import ndimage

    labels, _ = ndimage.label(~np.pad(valid, 1, constant_values=False))
    return labels[1:-1, 1:-1], int(labels[0, 0])


def ramp(values: np.ndarray, low: float, high: float) -> np.ndarray:
    """0 up to ``low``, 1 from ``high``, linear between (a step at ``low`` when the two are equal)."""
    return np.clip((np.asarray(values, dtype=np.float64) - low) / max(high - low, 1e-9), 0.0, 1.0)


def _to_u8(image: np.ndarray) -> np.ndarray:
    return np.clip(128.0 + 40.0 * image, 0, 255).astype(np.uint8)


def _remap(image: np.ndarray, flow_px: np.ndarray, border: float = 0.0) -> np.ndarray:
    """``image`` (rows, cols[, c]) sampled at each pixel plus ``flow_px`` (rows, cols, 2) (x, y), bilinear."""
    rows, cols = flow_px.shape[:2]
    map_x = (np.arange(cols, dtype=np.float32)[None, :] + flow_px[..., 0]).astype(np.float32)
    map_y = (np.arange(rows, dtype=np.float32)[:, None] + flow_px[..., 1]).astype(np.float32)
    return cv2.remap(image.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=border)


def track_skin(neutral: FaceGrid, expression: FaceGrid, guess: np.ndarray,
               template: FaceGrid | None = None, closing: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Where each neutral skin point is in the expression, in x-y, and how much that is trusted.

    Parameters
    ----------
    neutral, expression : FaceGrid
        Coloured grids on the same grid lines (the face frame).
    guess : ndarray, shape (n_rows, n_cols, 2)
        First guess of the x-y motion (mm) of every grid point (finite everywhere).
    template : FaceGrid, optional
        A cleaner image of the neutral skin on its grid lines (:mod:`~livebridge.retarget.skin_template`):
        the flow is found against it, the trust still from the neutral scan's own skin (the residuals'
        scale :data:`TRUSTED_RESIDUAL` is that of two single scans).
    closing : ndarray of bool, shape (n_rows, n_cols), optional
        The neutral's eye openings that close in the expression (:func:`~livebridge.retarget.eyelids.closing_openings`):
        the neutral's holes they touch show the expression's skin to the flow (see :func:`closing_holes`).

    Returns
    -------
    motion : ndarray, shape (n_rows, n_cols, 2)
        x-y motion, mm.
    trust : ndarray, shape (n_rows, n_cols)
        In [0, 1]; 0 where the neutral has no surface, the motion leaves the expression's surface, or the
        skin there does not match.
    """
    step = neutral.spacing
    source, source_valid = skin_image(neutral)
    target, _ = skin_image(expression)
    total = (guess / step).astype(np.float32)
    reference = neutral if template is None else template
    # each flow's images normalised over the same number of its own pixels (see COARSE_FACTOR); the
    # full-resolution ones are those the trust is read from
    images = {COARSE_FACTOR: (skin_image(reference, CONTRAST_MM * COARSE_FACTOR)[0],
                              skin_image(expression, CONTRAST_MM * COARSE_FACTOR)[0]),
              1: (source if template is None else skin_image(template)[0], target)}
    filled = None if closing is None else closing_holes(source_valid, closing)
    for factor in (COARSE_FACTOR,) + (1,) * PASSES:
        flow_source, flow_target = images[factor]
        warped = _remap(flow_target, total)
        if filled is not None:
            flow_source = np.where(filled, warped, flow_source)
        flow = _flow(_to_u8(flow_source), _to_u8(warped), step, factor)  # source(p) ~ warped(p + flow)
        total = flow + _remap(total, flow)  # the previous motion where the flow lands
    matched = _remap(target, total)
    residual = np.where(source_valid, (source - matched) ** 2, 0.0)
    rms = np.sqrt(masked_blur(residual, source_valid, CHECK_MM / step))
    trust = np.clip(2.0 - rms / TRUSTED_RESIDUAL, 0.0, 1.0)
    landed = _remap(np.isfinite(expression.heights).astype(np.float32), total) > 0.999
    trust = np.where(source_valid & landed, trust, 0.0)
    return total * step, trust


def _flow(source_u8: np.ndarray, warped_u8: np.ndarray, step: float, factor: int = 1) -> np.ndarray:
    """The DIS flow (rows, cols, 2; pixels) between two skin images of ``step`` mm pixels, found on images
    ``factor`` times coarser (the same patches in mm) when ``factor`` > 1 (see :data:`COARSE_FACTOR`: where
    the first guess is several mm off, a landmark warp extrapolated to the face's outline, the
    full-resolution pyramid starting from it settles on a wrong match; the coarse flow brings it within the
    fine one's reach)."""
    if factor == 1:
        return _dis(step).calc(source_u8, warped_u8, None)
    rows, cols = source_u8.shape
    small = (cols // factor, rows // factor)
    flow = _dis(step * factor).calc(cv2.resize(source_u8, small, interpolation=cv2.INTER_AREA),
                                    cv2.resize(warped_u8, small, interpolation=cv2.INTER_AREA), None)
    return cv2.resize(flow, (cols, rows), interpolation=cv2.INTER_LINEAR) * factor


def _dis(step: float):
    """DIS optical flow at full resolution with :data:`PATCH_MM` patches on a skin image of ``step`` mm."""
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    dis.setFinestScale(0)
    patch = max(8, int(round(PATCH_MM / step)))
    dis.setPatchSize(patch)
    dis.setPatchStride(max(1, patch // PATCH_OVERLAP))
    dis.setVariationalRefinementIterations(REFINEMENT_ITERATIONS)
    return dis


def skin_motion(neutral_fine: FaceGrid, expression_fine: FaceGrid, at: np.ndarray,
                first_guess: np.ndarray, smooth_mm: float = 2.0, seam=None, not_skin: np.ndarray | None = None,
                template: FaceGrid | None = None, fill_from_beyond: bool = False,
                lids: list | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The 3D motion of the output mesh's vertices from skin tracking, and its trust.

    Parameters
    ----------
    neutral_fine, expression_fine : FaceGrid
        Coloured grids (skin images) on the same grid lines of a chart of the face
        (:mod:`~livebridge.retarget.chart`; the planar one: x, y with z as heights), reaching beyond the
        output mesh on every side.
    at : ndarray, shape (n_vertices, 2)
        The output mesh's vertices on the skin images, (row, column) pixels (see :func:`pixels_of`).
    first_guess : ndarray, shape (n_vertices, 3)
        The geometric estimate of the vertices' motion, in the chart (u, v, height).
    smooth_mm : float
        Gaussian sigma of the smoothing of the tracked motion (see
        :data:`~livebridge.retarget.skin_smoothing.SMOOTH_SPACINGS`).
    seam : LipSeam, optional
        The smoothing does not reach across it (:mod:`~livebridge.retarget.seams`).
    not_skin : ndarray of bool, shape of ``neutral_fine``, optional
        Points whose change in height is not the skin's (a closing eye's opening: see
        :func:`~livebridge.retarget.eyelids.closing_openings`), left out of the smoothing of the heights,
        as are the points of either image behind its front surface (:func:`behind_front`); the neutral's
        holes there show the flow the expression's skin (``closing`` of :func:`track_skin`).
    template : FaceGrid, optional
        See :func:`track_skin`.
    fill_from_beyond : bool
        The points of ``not_skin`` that the neutral has (a closing eye's fill band) take the motion of the
        skin beyond them (see :func:`_from_beyond`).
    lids : list of (dict of int to LidColumn, float), optional
        Every moving eye's lid columns and reach (mm), as
        :func:`~livebridge.retarget.eyelids.moving_lids` gives them: their skin's motion along y falls
        monotonically away from each margin that moved (:func:`~livebridge.retarget.skin_smoothing.monotone_lids`).

    Returns
    -------
    motion : ndarray, shape (n_vertices, 3)
        In the chart, to the expressive surface at the tracked skin point; the first guess where not trusted.
    trust : ndarray, shape (n_vertices,)
        In [0, 1]; the motion is ``trust * tracked + (1 - trust) * first_guess``.
    """
    guess = vertex_field(at, first_guess[:, :2], neutral_fine.shape)
    xy, trust = track_skin(neutral_fine, expression_fine, guess, template, not_skin)
    step = neutral_fine.spacing
    rows, cols = np.indices(neutral_fine.shape)
    landed_z = map_coordinates(expression_fine.heights, [rows + xy[..., 1] / step, cols + xy[..., 0] / step],
                               order=1, cval=np.nan)
    dz = landed_z - neutral_fine.heights
    behind = _landed(behind_front(expression_fine.heights, step), xy, step) | behind_front(neutral_fine.heights, step)
    opening = not_skin
    fill = None if not_skin is None or not fill_from_beyond else not_skin & np.isfinite(neutral_fine.heights)
    not_skin = behind if not_skin is None else (not_skin | behind)
    good = (trust > 0) & np.isfinite(dz)
    if fill is not None:
        good &= ~fill  # its flow scatters (see _from_beyond): it takes the motion beyond it below
    weight = np.where(good, trust, 0.0)
    sigma = smooth_mm / step
    if seam is None:
        def blur_at(width):
            return lambda channels, channel_weight: [weighted_blur(c, channel_weight, width) for c in channels]

        density = cv2.GaussianBlur(weight.astype(np.float32), (0, 0), sigma)
    else:
        smooth_apart = seam.smoother(neutral_fine.x, neutral_fine.y)

        def blur_at(width):
            return lambda channels, channel_weight: smooth_apart(channels, channel_weight, width)[0]

        density = smooth_apart([], weight, sigma)[1]
    # the heights at the base width; the x-y motion at each of WIDTHS (the first is the base width)
    height = robust_heights(np.nan_to_num(dz), weight, blur_at(sigma), ~not_skin)
    means = [np.dstack(blur_at(sigma * factor)([xy[..., 0], xy[..., 1]], weight)) for factor in WIDTHS]
    sharp = np.dstack(twiced(blur_at(sigma), [xy[..., 0], xy[..., 1]], weight))
    adaptive = adaptive_smooth(means, weight, sigma, sharp)
    if lids:
        adaptive = monotone_lids(adaptive, xy, weight, lids, sigma, step)
    height = height + surface_rise(expression_fine.heights, step, means[0], adaptive - means[0], sigma)
    smooth = np.dstack([adaptive, height])
    filled = fill is not None and fill.any()
    if filled:
        smooth = _from_beyond(smooth, opening, fill)
    tracked = at_vertices(smooth, at)
    finite = np.isfinite(tracked).all(axis=1)

    def at_tracked(share):
        return np.where(finite, np.clip(np.nan_to_num(at_vertices(share, at)), 0.0, 1.0), 0.0)

    trust_out = at_tracked(density)
    # the band's motion is taken in full; the trust reported stays its own flow's
    use = at_tracked(np.where(fill, 1.0, density)) if filled else trust_out
    motion = use[:, None] * np.nan_to_num(tracked) + (1.0 - use[:, None]) * first_guess
    return motion, trust_out


def _from_beyond(field: np.ndarray, hole: np.ndarray, fill: np.ndarray) -> np.ndarray:
    """``field`` (rows, cols[, k]) with each pixel of ``fill`` (rows, cols) bool set to its value at the
    nearest pixel outside ``hole`` (rows, cols) bool, the region ``fill`` lies in (a copy).

    Used in a tracking that starts from an earlier one's motion (:func:`~livebridge.retarget.scans.tracked_motion`
    with ``start``), the points of a ``not_skin`` region that the neutral's skin image still has (a closing eye's
    fill band: the one or two mm of the opening that the resampling filled from the lids' rims, see
    :func:`~livebridge.retarget.eyelids.closing_openings`) take the smoothed motion of the nearest skin beyond the
    region in full, instead of their own flow (the trust reported for them stays their own flow's): the rims curl
    back over the eye, their pattern in the band is not the expression's, and the band's flow scattered by 1.2-1.7
    mm about the margin's motion (its true motion: the band lies inside the eye's opening, the lid's margin is its
    nearest surface). Their flow is left out of the smoothing too, so that it does not pull the skin beyond the
    band. In `livebridge bench scans` (seed 7) the eyelid elements went from 0.229 / 0.290 to 0.216 / 0.279 at 60k
    points a scan, from 0.201 / 0.212 to 0.184 / 0.191 at 150k, every other element unchanged (their surface errors
    0.105 / 0.114 -> 0.111 / 0.111 and 0.100 / 0.102 -> 0.103 / 0.107: the band no longer lands on the closed lid's
    front); seed 8 at 60k 0.231 / 0.273 -> 0.215 / 0.245 (the others unchanged), its two eyelid scans alone at 150k
    0.240 / 0.208 -> 0.224 / 0.188. In the first tracking too it gained less and cost the jaw at 150k (0.217 / 0.270
    at 60k, 0.192 / 0.197 at 150k, jaw 0.074 -> 0.084 with the band's trust reported as 1, 0.081 with its own; the
    jaw's chin hangs on the template, which the first tracking's motion builds). Leaving the band untracked to the
    carried spline was much worse (0.42); a locally linear smoothing at the band's edge (without the one-sided
    window's first-order bias) 0.217 / 0.281, in a band of twice the smoothing width beyond the opening too 0.215 /
    0.314 (both in both trackings, 60k).
    """
    from scipy.ndimage import distance_transform_edt

    _, (near_r, near_c) = distance_transform_edt(hole, return_indices=True)
    out = field.copy()
    out[fill] = field[near_r[fill], near_c[fill]]
    return out


def behind_front(heights: np.ndarray, step: float, gap_mm: float = BEHIND_MM,
                 window_mm: float = FRONT_WINDOW_MM) -> np.ndarray:
    """The points (rows, cols) bool of a skin image's ``heights`` (rows, cols; mm on pixels of ``step`` mm,
    NaN: no surface) more than ``gap_mm`` behind the front surface around them: the 80th percentile of the
    heights in a square window ``window_mm`` wide.

    A resampled scan mixes two surfaces where the front one has gaps the scanner saw through (a nostril): its
    points there are sometimes the skin, sometimes 10-30 mm deeper, a speckle whose height changes between
    two scans are no skin's motion. The upper fifth, not the median, is the front: where the deeper surface
    shows through at most points, the skin's points are still the front ones. Where the front itself is
    steep (the face's side curving away, slopes up to ~15 at its outline) the gap grows by what the front
    falls over half the window at its least steep nearby (the least, so that a cliff of mixed points does
    not excuse itself): without that, the side of the face was taken for another surface
    (zygomatic_major 0.050 -> 0.052 at 150k points)."""
    return np.isfinite(heights) & (heights < _behind_limit(heights, step, gap_mm, window_mm))


def _behind_limit(heights: np.ndarray, step: float, gap_mm: float = BEHIND_MM,
                  window_mm: float = FRONT_WINDOW_MM) -> np.ndarray:
    """The height (rows, cols) below which a point of the skin image ``heights`` is behind its front (see
    :func:`behind_front`); -inf where no front is near."""
    from scipy.ndimage import minimum_filter, percentile_filter

    finite = np.isfinite(heights)
    size = max(3, int(round(window_mm / step)) | 1)
    front = percentile_filter(np.where(finite, heights, -np.inf), 80, size=size)
    slope = np.nan_to_num(np.hypot(*np.gradient(np.where(np.isfinite(front), front, np.nan), step)), nan=np.inf)
    rise = minimum_filter(slope, size=size) * window_mm / 2  # how far a steep front itself falls in the window
    limit = front - gap_mm - rise
    return np.where(np.isfinite(limit), limit, -np.inf)


def in_front(image: FaceGrid, points: np.ndarray) -> np.ndarray:
    """Mask (n,) of the ``points`` (n, 3; in the chart of the skin ``image``: u, v, height) not behind the
    image's front surface by more than :data:`BEHIND_MM` at their nearest pixel (as :func:`behind_front`
    judges the image's own points): the rest are another surface seen through a gap of the front one.
    Points beyond the image's pixels are kept.

    A scanner sees past the skin at its gaps and edges (into a nostril, under the chin); resampled with the
    skin, those points mix their colour and height into the skin image, which the flow then follows (the
    resampling's own occlusion test is per pixel and 10 mm deep: a point with no front point in its pixel,
    or less than 10 mm behind it, stays). On the bench's neutral scan at 60k points 425 of 57k points go,
    395 of them within 15 mm of the nose tip, the rest under the chin. Left out of every scan's skin images
    (:mod:`~livebridge.retarget.scans`), in `livebridge bench scans` (seed 7, 60k points a scan):
    lips_pressor 0.121 -> 0.115 (its nose's share of the error^2 2.5 -> 1.5 x 1e-3 of the element's RMS^2,
    unshrunk), depressor_anguli_oris 0.118 -> 0.117, orbicularis_oris 0.074 -> 0.071,
    zygomatic_major_R 0.057 -> 0.052."""
    points = np.asarray(points, dtype=np.float64)
    limit = _behind_limit(image.heights, image.spacing)
    at = pixels_of(image, points[:, :2])
    inside = ((at >= 0) & (at <= np.array(limit.shape) - 1)).all(axis=1)  # beyond the image: not judged
    pixel = np.rint(np.where(inside[:, None], at, 0.0)).astype(np.int64)
    below = np.full(len(points), -np.inf)
    below[inside] = limit[pixel[inside, 0], pixel[inside, 1]]
    return points[:, 2] >= below


def _landed(mask: np.ndarray, xy: np.ndarray, step: float) -> np.ndarray:
    """``mask`` (rows, cols) bool read where each pixel's motion ``xy`` (rows, cols, 2; mm) lands (any of
    the four pixels around it)."""
    rows, cols = np.indices(mask.shape)
    return map_coordinates(mask.astype(np.float32), [rows + xy[..., 1] / step, cols + xy[..., 0] / step],
                           order=1, cval=0.0) > 0


def pixels_of(fine: FaceGrid, uv: np.ndarray) -> np.ndarray:
    """Points ``uv`` (n, 2) on the grid lines of ``fine`` as (row, column) pixel positions, shape (n, 2)."""
    uv = np.asarray(uv, dtype=np.float64)
    return np.column_stack([(uv[:, 1] - fine.y[0]) / (fine.y[1] - fine.y[0]),
                            (uv[:, 0] - fine.x[0]) / (fine.x[1] - fine.x[0])])


def vertex_field(at: np.ndarray, values: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Values (n, k) given at pixel positions ``at`` (n, 2: row, column; a mesh's vertices on a skin image)
    as a field on the image's pixels, shape (``shape``, k): linear over their Delaunay triangulation within
    a mesh cell (the vertices' median spacing) of a vertex, the nearest vertex's value farther away (across
    a hole, an eye's opening, and beyond the mesh) as the vertices' nearest-filled grid gave it."""
    corners, weights = _vertex_weights(np.ascontiguousarray(at, dtype=np.float64).tobytes(), len(at), shape)
    values = np.asarray(values, dtype=np.float64)
    return np.einsum("pc,pck->pk", weights, values[corners]).reshape(shape + (values.shape[1],))


@lru_cache(maxsize=4)
def _vertex_weights(at_bytes: bytes, n: int, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's vertices (n_pixels, 3) and weights (n_pixels, 3) for :func:`vertex_field`, kept for the
    few vertex sets in use (one neutral's vertices serve its eyelids' guess, every flow and the template:
    0.23 s each to find for 19k vertices on a 490 x 490 image)."""
    from scipy.spatial import Delaunay, cKDTree
    from threadpoolctl import threadpool_limits

    at = np.frombuffer(at_bytes, dtype=np.float64).reshape(n, 2)
    rows, cols = np.indices(shape)
    pixels = np.column_stack([rows.ravel(), cols.ravel()]).astype(np.float64)
    tree = cKDTree(at)
    cell = float(np.median(tree.query(at, k=2)[0][:, 1]))
    distance, nearest = tree.query(pixels)
    corners = np.repeat(nearest[:, None], 3, axis=1)
    weights = np.zeros((len(pixels), 3))
    weights[:, 0] = 1.0
    near = np.flatnonzero(distance < cell)
    triangulation = Delaunay(at)
    with threadpool_limits(limits=1, user_api="blas"):  # see grid._linear
        simplex = triangulation.find_simplex(pixels[near])
    near, simplex = near[simplex >= 0], simplex[simplex >= 0]
    transform = triangulation.transform[simplex]
    partial = np.einsum("kij,kj->ki", transform[:, :2], pixels[near] - transform[:, 2])
    weights[near] = np.hstack([partial, 1 - partial.sum(axis=1, keepdims=True)])
    corners[near] = triangulation.simplices[simplex]
    return corners, weights


def at_vertices(field: np.ndarray, at: np.ndarray) -> np.ndarray:
    """``field`` (rows, cols[, k]) read bilinearly at pixel positions ``at`` (n, 2: row, column), shape
    (n[, k]); over its finite pixels only, NaN where those weigh less than half."""
    channels = field.reshape(field.shape[:2] + (-1,))
    finite = np.isfinite(channels).all(axis=2)
    coords = [at[:, 0], at[:, 1]]
    weight = map_coordinates(finite.astype(np.float64), coords, order=1, cval=0.0)
    out = np.column_stack([map_coordinates(np.where(finite, channels[..., c], 0.0), coords, order=1, cval=0.0)
                           for c in range(channels.shape[2])])
    out = np.where(weight[:, None] > 0.5, out / np.maximum(weight, 1e-12)[:, None], np.nan)
    return out if field.ndim == 3 else out[:, 0]
