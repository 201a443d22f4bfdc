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

The tracked motion is noisy, and its noise is what limits a basis built from scans. Three things keep it
down, each general (no knowledge of the muscle, the person or the scanner's noise):

- the motion is smoothed over :data:`SMOOTH_SPACINGS` of the scan's own point spacing, the heights
  robustly (:func:`_robust_heights`): a skin image's heights have outliers of several mm where two surfaces
  mix (the nostrils, the scan's rim) that a plain Gaussian spreads over centimetres; the motion along the
  face takes twice that width where it is flat enough that the wider window only averages more noise away,
  the flat places found from the data by Lepski's rule (:func:`_adaptive_smooth`), and a less biased
  smoothing than the base width's (twicing, :func:`_twiced`) where the motion curves far more than the noise
  explains (a closing lid's skin: its ~9 mm slide falls to none within a few mm at the lid's crease); on a
  moving lid's skin, whose slide falls monotonically away from the margin, a monotone fit along the closing
  direction replaces the smoothing there (:func:`_monotone_lids`), keeping that edge sharp;
- the rigid slip the shape-only registration leaves is taken out on the skin that did not move
  (:func:`still_skin_correction`);
- the motion along the skin is shrunk towards zero where it is not above the noise, the noise level read
  from the still skin of the same scan pair (:func:`shrink_noise`), so skin an expression does not move
  stays still instead of carrying 0.2-0.5 mm blotches.

Measured in `livebridge bench scans` (seed 7, 16 elements; the 8 "smooth" elements frontalis_L,
corrugator_L, zygomatic_major_L, risorius_L, levator_labii_L, depressor_anguli_oris, lips_pressor,
orbicularis_oris): mean relative RMS error of those 8 at 60k points a scan 0.159 before these changes, 0.124
after; each change undone alone gives 0.155 (heights smoothed plainly), 0.145 (the DIS preset's 4 mm
patches), 0.138 (the former 8.5-spacing smoothing), 0.131 (the former trust threshold 0.8), 0.127 (no
shrinkage). The errors of differently tuned flows are 0.8-0.97 correlated (patches of 4, 8 and 12 mm), and
a dense Gauss-Newton photometric refinement after DIS (a bilinear lattice of 1.5-2 mm nodes with a
second-difference prior, over all pixels) cut the per-pixel flow noise 2-3x but not the error at the
element's scale (0.124 either way, 6 s more per element), so what remains at 60k points is what the skin
images themselves say, not the estimator: a low-pass of the images before normalising (0.3-0.8 mm) was
worse (0.158-0.187 against 0.159), so the finest pattern still carries motion.

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
corners and the lid's height change hold most of what is left.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
from scipy.ndimage import map_coordinates

from livebridge.retarget.grid import FaceGrid

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
SMOOTH_SPACINGS = 5.0
"""The skin motion is smoothed (Gaussian sigma) over this many of the scan's point spacings before it is
sampled at the grid vertices: the flow's noise grows with the spacing (in the cylinder chart 0.47 mm at 60k
points a scan, 0.30 mm at 150k, 0.28 mm for a textured mesh's samples: bench scans, seed 7), down to half a
skin pixel (:func:`~livebridge.retarget.scans.smoothing_mm`). With the
heights smoothed robustly, outliers no longer ask for a wide window: mean
relative error of the 8 smooth elements 0.126 / 0.124 / 0.125 / 0.138 at 4 / 5 / 6 / 8.5 spacings (60k
points), 0.093 / 0.092 at 5 / 7 (150k)."""
WIDTHS = (1.0, 2.0)
"""The x-y motion's smoothing chooses per place between these multiples of the base width (see
:func:`_adaptive_smooth`): the base where the motion curves, twice it where the motion is flat (or zero) and
the wider window only averages more noise away. Mean relative error of the 8 smooth elements (seed 7) at 60k
points a scan 0.114 with the base alone, 0.108 with (1, 2); (1, 1.5, 2) 0.108, (1, 2, 4) 0.110, (1, 1.5, 2, 3)
0.109; (0.5, 1, 2) 0.108 (the eyelids 0.304 / 0.252 instead of 0.322 / 0.279 at 60k, but 0.251 instead of
0.242 at 150k). A fixed twice-wider smoothing is worse (0.138 for 8.5 spacings, above) and half-as-wide
too (frontalis 0.119 instead of 0.099). The heights follow the skin's new place along the surface
(:func:`_rise`): without that the chosen x-y left the points off the surface (mean surface error of the 16
elements 0.0709 instead of 0.0695; with it 0.0696). Not better: choosing the heights' width the same way
(orbicularis_oris 0.103 instead of 0.088, mean surface error 0.0739), and narrowing the x-y width where the
skin is steep so that it spans the same skin as on flat skin (levator_labii 0.101 / 0.096 instead of
0.098 / 0.094, risorius 0.117 / 0.125 instead of 0.110 / 0.118): the noise, not the bias, rules there."""
WIDEN_THRESHOLD = 3.0
"""A place takes the wider smoothing fully while the two widths' local mean square difference is at most
this times the noise's (1, 2, 3, 5: 0.111 / 0.109 / 0.108 / 0.111 mean relative error of the 8 smooth
elements, 60k points)."""
WIDEN_WINDOW = 1.0
"""Width over which that difference is averaged, in wider widths (0.5, 1, 2: 0.110 / 0.109 / 0.108 mean
relative error of the 8 smooth elements): 2 let a sharp bump (sigma the base width) take a third of the
wider window's bias in tests/test_scans.py, 1 none."""
SHARP_THRESHOLD = 10.0
"""Where the motion curves more than even the base width follows, the adaptive smoothing takes the base width
twiced (:func:`_twiced`: its curvature bias cancelled) instead, where the two differ by more than this times
what lets a place take a wider width (:data:`WIDEN_THRESHOLD` times the noise's mean square): the twiced
smoothing keeps about 1.8 times the base width's noise variance, and the flow's noise is heavier than its
median in places (the lips, the chin) that the plain threshold took for curving motion. The noise-free
flow (the true motion along the skin put through the rest of the pipeline) showed the smoothing as most of
what kept the eyelids over the bar: 0.240 / 0.243 relative RMS at 60k points a scan (seed 7) with the base
width's Gaussian, 0.026 / 0.025 unsmoothed (true heights), 0.155 / 0.159 with this. With the real flow
(`livebridge bench scans`, eyelids L / R): 0.302 / 0.319 -> 0.251 / 0.251 at 60k points, 0.238 / 0.241 -> 0.205 /
0.208 at 150k, seed 8 at 60k 0.355 / 0.335 -> 0.270 / 0.290; no other element worse by more than 0.001 at 60k
(jaw), 0.003 at 150k (levator_labii_L 0.049 -> 0.053), and frontalis 0.074 / 0.076 -> 0.067 / 0.070 (60k),
jaw 0.072 -> 0.058 (150k); seed 8 at 150k 0.244 / 0.243 -> 0.221 / 0.218, nothing else worse by more than
0.0013. Other values (60k, seed 7): 5 gave the eyelids 0.242 / 0.245 but zygomatic_major_R 0.057 -> 0.072 (a
noisy stretch taken for curving motion); 20 gave 0.258 / 0.259, nothing else worse by more than 0.001; 1 (6 of
the elements) 0.247 / 0.262 but jaw 0.081 -> 0.095."""
LID_FIT_REACHES = 2.0
"""A moving lid's skin takes its monotone fit (:func:`_monotone_lids`) this many lid reaches
(:data:`~livebridge.retarget.eyelids.REACH_EYE_WIDTHS` eye widths) from its margin: past the crease and the
skin the margin's motion reaches (one reach), into skin that barely moves, so that the fit's tail ends there."""
LID_FIT_BLEND = 0.25
"""Over the last this fraction of its span the lid's monotone fit hands over linearly to the smoothing of the
rest of the face, so that no seam is left where it ends."""
ROBUST_ROUNDS = 3
"""Rounds of re-weighting in the robust smoothing of the heights (none: 0.155 instead of 0.124)."""
ROBUST_SCALE = 5.0
"""Cauchy scale of the robust smoothing of the heights, in median absolute residuals: a skin pixel whose
height change is this far from the smooth one counts half (3: 0.124, 5: 0.124, 10: 0.126)."""
SHRINK_WINDOW_MM = 8.0
"""Width (Gaussian sigma) over which :func:`shrink_noise` measures the local strength of the tangential
motion: wide enough that a muscle's own motion is not mistaken for noise, narrow enough that still skin
next to a moving region is still found still (4 mm: 0.143, 8 mm: 0.140, 15 mm: 0.141 mean relative error,
measured with the former 4 mm patches; stronger shrinkage, 2 or 4 times the estimated noise variance, was
worse: 0.150 / 0.176). Now (mean relative error of the 16 elements at 60k / 150k points a scan) 4 mm gives
0.1138 / 0.0916, 8 mm 0.1137 / 0.0914, 12 mm 0.1142 / 0.0919."""
EDGE_ON = 0.1
"""The smallest ``|n . view|`` (the surface normal along the skin images' view) by which the flow's noise is
lifted onto the slope in :func:`shrink_noise`: skin turned further away is nearly edge-on to the skin images.
With x-y images 0.05, 0.1 and 0.2 gave the same bench figures (mean relative error 0.1137 at 60k points a
scan), 0.3 0.1139. With the cylinder chart's view (60k / 150k points, seed 7) 0.2 and 0.3 traded
lips_pressor (0.121 -> 0.120 / 0.119 at 60k) against risorius_L (0.059 -> 0.060 / 0.062 at 150k)."""
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
STILL_FRACTION = 0.4
"""The fraction of the face taken as not moved by an expression when the registration is corrected and
when the noise level is read (:func:`still_noise_variance`: the least moved skin up to this fraction)."""
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
    luminance = np.where(valid, np.nan_to_num(grid.colours) @ np.array([0.299, 0.587, 0.114]), 0.0)
    sigma = contrast_mm / grid.spacing
    mean = _masked_blur(luminance, valid, sigma)
    detail = np.where(valid, luminance - mean, 0.0)
    spread = np.sqrt(_masked_blur(detail ** 2, valid, sigma))
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


def _masked_blur(image: np.ndarray, valid: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of ``image`` over its ``valid`` pixels only (normalised convolution)."""
    weight = cv2.GaussianBlur(valid.astype(np.float32), (0, 0), sigma)
    total = cv2.GaussianBlur(np.where(valid, image, 0.0).astype(np.float32), (0, 0), sigma)
    return total / np.maximum(weight, 1e-6)


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
    rms = np.sqrt(_masked_blur(residual, source_valid, CHECK_MM / step))
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
        Gaussian sigma of the smoothing of the tracked motion (see :data:`SMOOTH_SPACINGS`).
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
        monotonically away from each margin that moved (:func:`_monotone_lids`).

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
            return lambda channels, channel_weight: [_weighted_blur(c, channel_weight, width) for c in channels]

        density = cv2.GaussianBlur(weight.astype(np.float32), (0, 0), sigma)
    else:
        smooth_apart = seam.smoother(neutral_fine.x, neutral_fine.y)

        def blur_at(width):
            return lambda channels, channel_weight: smooth_apart(channels, channel_weight, width)[0]

        density = smooth_apart([], weight, sigma)[1]
    # the heights at the base width; the x-y motion at each of WIDTHS (the first is the base width)
    height = _robust_heights(np.nan_to_num(dz), weight, blur_at(sigma), ~not_skin)
    means = [np.dstack(blur_at(sigma * factor)([xy[..., 0], xy[..., 1]], weight)) for factor in WIDTHS]
    sharp = np.dstack(_twiced(blur_at(sigma), [xy[..., 0], xy[..., 1]], weight))
    adaptive = _adaptive_smooth(means, weight, sigma, sharp)
    if lids:
        adaptive = _monotone_lids(adaptive, xy, weight, lids, sigma, step)
    height = height + _rise(expression_fine.heights, step, means[0], adaptive - means[0], sigma)
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


def _monotone_lids(motion: np.ndarray, xy: np.ndarray, weight: np.ndarray, lids: list, sigma: float,
                   step: float) -> np.ndarray:
    """``motion`` (rows, cols, 2; the smoothed x-y motion, mm) with its motion along y (the lids' closing
    direction) over each moving lid's skin fitted to fall monotonically away from the lid's margin, a copy.

    When a lid closes (or opens wide) its skin's slide is largest at the margin and falls off away from it,
    never rising again: on the bench's closing eyes a ~9 mm plateau that falls to none over ~5 mm at the lid's
    crease. A Gaussian (twiced or not, :func:`_adaptive_smooth`) rounds that edge by its width; a monotone
    (isotonic) fit along each column keeps it sharp while still averaging the flow's noise over the plateau and
    the tail. The fit is of the flow ``xy`` (rows, cols, 2) smoothed along x only (across the columns, over
    ``sigma`` pixels, with ``weight`` (rows, cols), the flow's trust), each pixel weighing what that smoothing
    gathered; it spans each margin's :data:`LID_FIT_REACHES` lid reaches (from ``lids``: pairs of a moving
    eye's lid columns, :class:`~livebridge.retarget.eyelids.LidColumn` by fine column, and its reach, mm, as
    :func:`~livebridge.retarget.eyelids.moving_lids` gives them), taking over from ``motion`` fully up to the
    last :data:`LID_FIT_BLEND` of that span and linearly less over it. A margin that did not move (a closing
    eye's lower lid) has no direction to fall from and keeps ``motion``. ``step``: pixel size, mm.

    In `livebridge bench scans` (seed 7) the eyelid elements went from 0.216 / 0.279 to 0.201 / 0.265 relative
    RMS at 60k points a scan, from 0.184 / 0.191 to 0.177 / 0.187 at 150k, every other element within 0.0003;
    seed 8 at 60k 0.219 / 0.251 -> 0.207 / 0.236 and seed 11 at 150k 0.171 / 0.191 -> 0.165 / 0.187 (with
    corrugator, frontalis and levator_labii, which stayed within 0.0003). With the true motion along the skin
    fed into the rest of the pipeline (the eyelid scans of seed 7 at 60k points): 0.131 / 0.127 -> 0.127 / 0.123,
    the unsmoothed true motion 0.121 / 0.109; with correlated noise of the flow's level (0.22 mm, 2 mm) 0.181 /
    0.168 -> 0.170 / 0.165; with the DIS flow's own error when started at the truth 0.199 / 0.216 -> 0.183 /
    0.209. Not better there: the fit's value at the margin capped by the margin's motion from the openings
    (0.145 / 0.141 with the true motion), a closing eye's still lower lid fitted too (its direction from the
    flow by the margin: 0.128 / 0.123), the motion along x fitted the same way (0.128 / 0.124), the columns
    smoothed at equal distance from their margins instead of on equal rows (0.139 / 0.137), and the heights read
    from the surfaces where the fitted motion lands instead of smoothed (0.124-0.131 / 0.130-0.135).
    """
    from scipy.ndimage import gaussian_filter1d
    from scipy.optimize import isotonic_regression

    weight = weight.astype(np.float64)
    gathered = gaussian_filter1d(weight, sigma, axis=1, mode="constant")
    total = gaussian_filter1d(np.where(weight > 0, xy[..., 1] * weight, 0.0), sigma, axis=1, mode="constant")
    along = np.where(gathered > 1e-6, total / np.maximum(gathered, 1e-6), np.nan)
    out = motion.copy()
    for columns, reach_mm in lids:
        span = LID_FIT_REACHES * reach_mm / step
        for col, lid in columns.items():
            for margin, moved, away in ((lid.upper, lid.upper_motion, 1), (lid.lower, lid.lower_motion, -1)):
                if moved == 0:
                    continue
                first = int(np.ceil(margin)) if away > 0 else int(np.floor(margin))
                rows = first + away * np.arange(int(span))
                rows = rows[(rows >= 0) & (rows < len(out))]
                rows = rows[np.isfinite(along[rows, col]) & (gathered[rows, col] > 1e-3)]
                if len(rows) < 3:
                    continue
                sign = np.sign(moved)
                fit = sign * isotonic_regression(sign * along[rows, col], weights=gathered[rows, col],
                                                 increasing=False).x
                share = np.clip((span - np.abs(rows - margin)) / (LID_FIT_BLEND * span), 0.0, 1.0)
                smooth = out[rows, col, 1]
                out[rows, col, 1] = np.where(np.isfinite(smooth), smooth + share * (fit - smooth), smooth)
    return out


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


def shrink_noise(grid: FaceGrid, normals: np.ndarray, motion: np.ndarray, trust: np.ndarray,
                 window_mm: float = SHRINK_WINDOW_MM, view: np.ndarray | None = None) -> np.ndarray:
    """``motion`` (n_vertices, 3) with its motion along the skin shrunk where it is not above the noise.

    Parameters
    ----------
    grid : FaceGrid
        The output mesh's grid (``motion``'s vertices are its valid points).
    normals, motion : ndarray, shape (n_vertices, 3)
    trust : ndarray, shape (n_vertices,)
        The tracking's trust (:func:`skin_motion`): the noise level is read on the trusted skin, and
        untrusted vertices (the geometric warp's motion) are left as they are.
    window_mm : float
        Width (Gaussian sigma) of the local mean square of the motion (see :data:`SHRINK_WINDOW_MM`).
    view : ndarray, shape (n_vertices, 3), optional
        Unit vectors the skin images looked at each vertex's skin from
        (:meth:`~livebridge.retarget.chart.SkinChart.view_directions` of their chart); default ``+z`` (the
        x-y images of the planar chart).

    The noise model: the flow's error is the same in both axes of the skin image everywhere, of a variance
    per axis read from the data (:func:`still_noise_variance` of the x-y motion's sizes on the trusted
    skin). Lifted onto the surface, it stays that along the skin's level line (level with respect to the
    ``view``) but grows by ``1 / |n . view|`` along its steepest direction (an image step ``d`` on skin
    turned away from the view is a step ``d / |n . view|`` along the skin). Each of the two components of
    the tangential motion is scaled by the positive-part James-Stein (local Wiener) factor
    ``max(0, 1 - v / P)``, with ``v`` its noise variance and ``P`` its local mean square over
    ``window_mm`` (Gaussian sigma).

    The lift must follow the chart the skin was tracked in. Measured (x-y images) with the lift by
    ``1 / |n_z|``, in `livebridge bench scans` (mean relative error of the 16 elements, 60k / 150k points a
    scan): no shrinkage 0.1159 / 0.0928; one noise level for both directions 0.1153 / 0.0926 (the same
    with a gain per direction, 0.1152 / 0.0925); the level grown along the slope 0.1137 / 0.0914, every
    element better than with the one level or within 0.0005 (depressor_anguli_oris 0.145 -> 0.136 /
    0.101 -> 0.096, risorius_R 0.107 -> 0.103; lips_pressor 0.1288 -> 0.1293 at 60k): near the face's
    outline the skin is steep (|n_z| 0.2-0.45) and its flow error 2-3 times larger, which one level left
    as motion. A level grown by the slope but the same in both directions gave 0.1144 / 0.0920. In the
    cylinder chart the face's sides face the images and the lift by ``1 / |n_z|`` took real motion for
    noise: depressor_anguli_oris 0.121 / 0.081 unshrunk, 0.126 / 0.086 shrunk so (seed 7, 60k / 150k),
    lips_pressor 0.117 / 0.077 and 0.122 / 0.078 (a third of that at the nose's flanks, whose motion back
    was shrunk by up to half); lifted by the chart's view 0.119 / 0.080 and 0.121 / 0.077, no element worse
    by more than 0.0005 (seed 8, 60k: depressor 0.127 -> 0.120, lips_pressor 0.126 -> 0.125).

    The motion along the normal is left as it is: shrunk the same way, with its own noise level, it changed
    those means by 0.0001-0.0002 (also with the still skin's true noise levels): the heights' errors on
    barely moved skin are few large ones (a scan's occluded or mixed surface), not noise a local gain can
    tell from motion.
    """
    normal = np.sum(motion * normals, axis=1)
    tangential = motion - normal[:, None] * normals
    trusted = trust > 0.9
    if trusted.sum() < 100:
        return motion
    if view is None:
        view = np.tile([0.0, 0.0, 1.0], (len(normals), 1))
    variance = still_noise_variance(np.linalg.norm(motion[trusted, :2], axis=1))
    steepest, level = _slope_directions(normals, view)
    lift = 1.0 / np.maximum(np.abs(np.sum(normals * view, axis=1)), EDGE_ON)
    shrunk = normal[:, None] * normals
    for direction, noise in ((steepest, variance * lift ** 2), (level, np.full(len(lift), variance))):
        along = np.sum(tangential * direction, axis=1)
        image = np.zeros(grid.shape)
        image[grid.valid] = along ** 2
        power = _masked_blur(image, grid.valid, window_mm / grid.spacing)[grid.valid]
        factor = np.clip(1.0 - noise / np.maximum(power, 1e-12), 0.0, 1.0)
        factor = np.where(trust > 0, factor, 1.0)
        shrunk += (factor * along)[:, None] * direction
    return shrunk


def _slope_directions(normals: np.ndarray, view: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit tangents (n, 3) along the surface's steepest direction (towards the ``view``, unit vectors (n, 3))
    and along its level line, at vertices of ``normals`` (n, 3); on skin facing the view squarely, any
    tangent (the first of +x, +y not along the normal) and its perpendicular."""
    up = view - np.sum(view * normals, axis=1, keepdims=True) * normals
    size = np.linalg.norm(up, axis=1, keepdims=True)
    flat = size[:, 0] < 1e-9
    steepest = np.where(flat[:, None], np.array([1.0, 0.0, 0.0]), up / np.maximum(size, 1e-12))
    steepest[flat] -= np.sum(steepest[flat] * normals[flat], axis=1)[:, None] * normals[flat]
    degenerate = flat & (np.linalg.norm(steepest, axis=1) < 1e-6)  # the normal along +x
    steepest[degenerate] = np.array([0.0, 1.0, 0.0]) - normals[degenerate, 1:2] * normals[degenerate]
    steepest /= np.linalg.norm(steepest, axis=1, keepdims=True)
    return steepest, np.cross(normals, steepest)


def still_noise_variance(sizes: np.ndarray, highest: float = STILL_FRACTION) -> float:
    """The variance per axis of 2D Gaussian noise on the still skin, from the sizes (n,) of 2D motions of
    which an unknown fraction (at least ``highest``) is that noise alone and the rest moved more.

    Below the sizes' ``highest`` quantile ``r_c`` nearly all are still skin (moved skin hardly ever moves
    less than the noise), so they are a sample of the noise's Rayleigh distribution truncated at ``r_c``,
    whatever fraction of the face moved: ``sigma`` is its maximum-likelihood fit. It is at most what reading
    ``r_c`` as the noise's own ``highest`` quantile gives (all of the face still), which took moved skin for
    noise where an expression moves more than 60 % of the face: the noise level 0.28-0.30 mm instead of the
    still skin's 0.12 (levator labii, 60k points a scan), 0.22 instead of 0.105 (lips pressor), which shrank
    their motion. In `livebridge bench scans` this fit is 0.74-1.03 times the RMS of the still skin's
    motion (60k points; 0.66-1.09 at 150k, where a few gross errors raise that RMS), and lips_pressor's error
    0.129 with it, 0.138 with the former level, 0.129 with the still skin's true level (60k; 0.104 / 0.110 /
    0.104 at 150k). A least-squares fit of both the still fraction and ``sigma`` to the sizes' quantiles gave
    the same bench figures but scattered twice as much on independent samples (0.88-1.21 against 0.92-1.12
    times the true level, 20 draws of 6000).
    """
    from scipy.optimize import minimize_scalar

    cut = float(np.quantile(sizes, highest))
    below = sizes[sizes <= cut]
    if cut <= 0.0 or len(below) == 0:
        return 0.0
    square_sum = float(np.sum(below ** 2))
    most = cut / np.sqrt(-2.0 * np.log(1.0 - highest))

    def minus_log_likelihood(sigma):
        inside = -np.expm1(-cut ** 2 / (2.0 * sigma ** 2))  # the Rayleigh probability of a size below the cut
        return len(below) * (2.0 * np.log(sigma) + np.log(inside)) + square_sum / (2.0 * sigma ** 2)

    fit = minimize_scalar(minus_log_likelihood, bounds=(most * 1e-3, most), method="bounded",
                          options={"xatol": most * 1e-6})
    return float(fit.x) ** 2


def _robust_heights(dz: np.ndarray, weight: np.ndarray, blur, z_use: np.ndarray | None = None) -> np.ndarray:
    """The height change ``dz`` (rows, cols) smoothed by ``blur`` with ``weight`` (rows, cols), its outliers
    down-weighted; NaN where nothing is near.

    Iteratively re-weighted: each of :data:`ROBUST_ROUNDS` rounds weights every pixel by the Cauchy function
    of its distance from the last smooth ``dz``, the scale :data:`ROBUST_SCALE` times the median distance.
    The x-y motion is not smoothed this way: its residual from the smooth field is mostly the flow's
    correlated noise and the motion's own curvature, and down-weighting that biased a clean flow (0.07 -> 0.17
    relative error in the known-slide test of tests/test_scans.py) for no gain on the bench.

    ``blur(channels, weight) -> means`` smooths a list of channels with one weight (a normalised Gaussian
    convolution, or a lip seam's that keeps each lip apart). ``z_use`` (rows, cols) bool: the pixels whose
    heights count (default: all).
    """
    if z_use is not None:
        weight = np.where(z_use, weight, 0.0)
    z_weight = weight
    for _ in range(ROBUST_ROUNDS):
        residual = np.abs(dz - blur([dz], z_weight)[0])
        usable = (weight > 0) & np.isfinite(residual)
        scale = max(float(np.median(residual[usable])) * ROBUST_SCALE, 1e-9) if usable.any() else 1.0
        z_weight = np.where(usable, weight / (1.0 + (residual / scale) ** 2), 0.0)
    return blur([dz], z_weight)[0]


def _twiced(blur, channels: list, weight: np.ndarray) -> list:
    """Tukey's twicing of a smoothing: the channels' smooth plus the smooth of what it left, ``s + B(f - s)``
    with ``s = B(f)``, a list like ``channels`` (each (rows, cols)); NaN where nothing is near.

    ``blur(channels, weight) -> means`` is a normalised smoothing (as in :func:`_robust_heights`). A Gaussian
    of width ``sigma`` moves a curving motion ``f`` by about ``sigma^2 / 2`` times its Laplacian; twicing
    takes that back to fourth order (its kernel ``2 G_sigma - G_sigma*G_sigma``) for ~1.8 times the noise
    variance, far less than halving the width (4 times).
    """
    first = blur(channels, weight)
    left = [np.where(weight > 0, channel - np.nan_to_num(smooth), 0.0) for channel, smooth in zip(channels, first)]
    return [smooth + more for smooth, more in zip(first, blur(left, weight))]


def _adaptive_smooth(means: list, weight: np.ndarray, sigma: float, sharp: np.ndarray | None = None) -> np.ndarray:
    """``values`` (rows, cols, 2: x-y motion) smoothed with ``weight`` (rows, cols) over a width chosen per
    place among :data:`WIDTHS` times ``sigma`` pixels, shape (rows, cols, 2); NaN where nothing is near.

    Lepski's rule (the intersection of confidence intervals), from the narrowest width up: a place takes the
    next wider smoothing while the two differ by no more than the flow's noise makes them differ. Where the
    motion is flat over the wider window their difference is noise; where it curves, the wider one's bias
    adds to it. The noise level of each difference is read from the data, as the median over the trusted
    skin of its squared size (most of a face does not curve at these widths; 2D Gaussian noise makes that
    square exponential, its mean the median over ln 2), so it holds for any scanner. The test is on the
    difference's local mean square (over :data:`WIDEN_WINDOW` times the wider width, so that one noisy
    pixel does not decide): up to :data:`WIDEN_THRESHOLD` times the noise's the place takes the wider
    smoothing, at twice that none, linearly between, which keeps the blend free of seams. The widest width
    a place may take is the first one rejected on the way up, as in Lepski's rule. Below the base width
    comes ``sharp`` when given (less biased, noisier): a place keeps the base width's smoothing unless the
    two differ by :data:`SHARP_THRESHOLD` times more than a wider width may.

    Parameters
    ----------
    means : list of ndarray, shape (rows, cols, 2)
        The motion smoothed at each of :data:`WIDTHS` times ``sigma`` (NaN where nothing is near).
    weight : ndarray, shape (rows, cols)
        The smoothing's weights (the flow's trust).
    sigma : float
        The base width, pixels.
    sharp : ndarray, shape (rows, cols, 2), optional
        A less biased smoothing at the base width (:func:`_twiced`).
    """
    trusted = weight > 0.9
    candidates, widths, thresholds = list(means), list(WIDTHS), [WIDEN_THRESHOLD] * len(WIDTHS)
    if sharp is not None:  # its window the base width's
        candidates, widths, thresholds = [sharp] + candidates, [WIDTHS[0]] + widths, [
            SHARP_THRESHOLD * WIDEN_THRESHOLD] + thresholds
    result = candidates[-1]
    for k in range(len(candidates) - 2, -1, -1):  # result: the smoothing from candidate k + 1 up
        difference = np.sum((candidates[k + 1][..., :2] - candidates[k][..., :2]) ** 2, axis=2)
        usable = trusted & np.isfinite(difference)
        if usable.sum() < 100:
            return means[0]
        noise = float(np.median(difference[usable])) / np.log(2.0)
        local = _weighted_blur(np.where(usable, difference, 0.0), usable.astype(np.float32),
                               sigma * widths[k + 1] * WIDEN_WINDOW)
        wider = np.clip(2.0 - local / max(thresholds[k] * noise, 1e-12), 0.0, 1.0)
        wider = np.where(np.isfinite(wider), wider, 0.0)[..., None]
        result = candidates[k] + wider * (np.nan_to_num(result) - candidates[k])
    return result


def _rise(heights: np.ndarray, step: float, motion: np.ndarray, shift: np.ndarray, sigma: float) -> np.ndarray:
    """How much the surface ``heights`` (rows, cols, mm on pixels of ``step`` mm; NaN: none), smoothed over
    ``sigma`` pixels, rises along ``shift`` (rows, cols, 2; mm) where ``motion`` (rows, cols, 2; mm, from each
    pixel) lands, to first order, shape (rows, cols): the height change that keeps a skin point moved along
    the surface on it."""
    finite = np.isfinite(heights)
    level = _weighted_blur(np.nan_to_num(heights), finite.astype(np.float32), sigma)
    rows, cols = np.indices(heights.shape)
    at = [rows + np.nan_to_num(motion[..., 1]) / step, cols + np.nan_to_num(motion[..., 0]) / step]
    slope_y, slope_x = (map_coordinates(np.nan_to_num(g), at, order=1, cval=0.0) for g in np.gradient(level, step))
    return np.nan_to_num(slope_x * shift[..., 0] + slope_y * shift[..., 1])


def _weighted_blur(image: np.ndarray, weight: np.ndarray, sigma: float) -> np.ndarray:
    """Normalised convolution of ``image`` (rows, cols) with ``weight``; NaN where no weight is near."""
    total = cv2.GaussianBlur((image * weight).astype(np.float32), (0, 0), sigma)
    norm = cv2.GaussianBlur(weight.astype(np.float32), (0, 0), sigma)
    return np.where(norm > 1e-6, total / np.maximum(norm, 1e-6), np.nan)


def still_skin_correction(vertices: np.ndarray, motion: np.ndarray, trust: np.ndarray,
                          keep: float = STILL_FRACTION, rounds: int = 8) -> np.ndarray:
    """The rigid motion (4, 4) that brings the tracked skin where the face did not move back onto itself.

    The expression scan was registered onto the neutral by its shape alone (point-to-plane ICP), which
    leaves it free to slide a fraction of a millimetre along the face. The tracked skin pins that: each
    round fits a rigid motion (Kabsch) to the ``keep`` fraction of trusted vertices whose skin moved least
    once corrected, so the muscle's own motion is left out.

    Parameters
    ----------
    vertices, motion : ndarray, shape (n, 3)
        Grid vertices and where their skin went (the tracked motion).
    trust : ndarray, shape (n,)
    """
    from livebridge.geometry.transforms import apply, umeyama

    landed = vertices + motion
    trusted = trust > 0.9
    correction = np.eye(4)
    if trusted.sum() < 100:
        return correction
    for _ in range(rounds):
        residual = np.linalg.norm(apply(correction, landed[trusted]) - vertices[trusted], axis=1)
        still = residual <= np.quantile(residual, keep)
        correction = umeyama(landed[trusted][still], vertices[trusted][still], with_scale=False)
    return correction


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
