"""The tracked skin motion's noise kept down: smoothing, the still skin's correction, shrinkage.

The skin motion the flow tracks (:mod:`~livebridge.retarget.skin_flow`) is noisy, and its noise is what limits a
basis built from scans. Three things keep it down, each general (no knowledge of the muscle, the person or the
scanner's noise):

- the motion is smoothed over :data:`SMOOTH_SPACINGS` of the scan's own point spacing, the heights
  robustly (:func:`robust_heights`): a skin image's heights have outliers of several mm where two surfaces
  mix (the nostrils, the scan's rim) that a plain Gaussian spreads over centimetres; the motion along the
  face takes twice that width where it is flat enough that the wider window only averages more noise away,
  the flat places found from the data by Lepski's rule (:func:`adaptive_smooth`), and a less biased
  smoothing than the base width's (twicing, :func:`twiced`) where the motion curves far more than the noise
  explains (a closing lid's skin: its ~9 mm slide falls to none within a few mm at the lid's crease); on a
  moving lid's skin, whose slide falls monotonically away from the margin, a monotone fit along the closing
  direction replaces the smoothing there (:func:`monotone_lids`), keeping that edge sharp;
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
shrinkage).

Tried and not taken: every one of these smoothings fitted locally linear (a weighted plane per pixel, which
has no first-order bias where the window is one-sided: at the eye openings, the lips' seam, the outline) in
both trackings: the eyelids 0.195 / 0.177 -> 0.202 / 0.203, the mean of the 16 0.0867 -> 0.0890 (60k, seed 7);
with the true x-y motion in place of the flow, 0.127 / 0.123 -> 0.131 / 0.129. With the true motion, half the
eyelids' squared error is on the 62 / 75 grid vertices next to the eye's opening (0.68 / 0.61 mm RMS; those
sharing an edge with it lie 0.26 / 0.49 mm off the true face at the median: the resampling's fill over the
lids' rims), against 0.06 / 0.05 mm RMS on the moving vertices more than 8 mm from it.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.ndimage import map_coordinates

from livebridge.retarget.grid import FaceGrid

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
:func:`adaptive_smooth`): the base where the motion curves, twice it where the motion is flat (or zero) and
the wider window only averages more noise away. Mean relative error of the 8 smooth elements (seed 7) at 60k
points a scan 0.114 with the base alone, 0.108 with (1, 2); (1, 1.5, 2) 0.108, (1, 2, 4) 0.110, (1, 1.5, 2, 3)
0.109; (0.5, 1, 2) 0.108 (the eyelids 0.304 / 0.252 instead of 0.322 / 0.279 at 60k, but 0.251 instead of
0.242 at 150k). A fixed twice-wider smoothing is worse (0.138 for 8.5 spacings, above) and half-as-wide
too (frontalis 0.119 instead of 0.099). The heights follow the skin's new place along the surface
(:func:`surface_rise`): without that the chosen x-y left the points off the surface (mean surface error of the 16
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
twiced (:func:`twiced`: its curvature bias cancelled) instead, where the two differ by more than this times
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
"""A moving lid's skin takes its monotone fit (:func:`monotone_lids`) this many lid reaches
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
STILL_FRACTION = 0.4
"""The fraction of the face taken as not moved by an expression when the registration is corrected and
when the noise level is read (:func:`still_noise_variance`: the least moved skin up to this fraction)."""


def masked_blur(image: np.ndarray, valid: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of ``image`` over its ``valid`` pixels only (normalised convolution)."""
    weight = cv2.GaussianBlur(valid.astype(np.float32), (0, 0), sigma)
    total = cv2.GaussianBlur(np.where(valid, image, 0.0).astype(np.float32), (0, 0), sigma)
    return total / np.maximum(weight, 1e-6)


def monotone_lids(motion: np.ndarray, xy: np.ndarray, weight: np.ndarray, lids: list, sigma: float,
                   step: float) -> np.ndarray:
    """``motion`` (rows, cols, 2; the smoothed x-y motion, mm) with its motion along y (the lids' closing
    direction) over each moving lid's skin fitted to fall monotonically away from the lid's margin, a copy.

    When a lid closes (or opens wide) its skin's slide is largest at the margin and falls off away from it,
    never rising again: on the bench's closing eyes a ~9 mm plateau that falls to none over ~5 mm at the lid's
    crease. A Gaussian (twiced or not, :func:`adaptive_smooth`) rounds that edge by its width; a monotone
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


def shrink_noise(grid: FaceGrid, normals: np.ndarray, motion: np.ndarray, trust: np.ndarray,
                 window_mm: float = SHRINK_WINDOW_MM, view: np.ndarray | None = None) -> np.ndarray:
    """``motion`` (n_vertices, 3) with its motion along the skin shrunk where it is not above the noise.

    Parameters
    ----------
    grid : FaceGrid
        The output mesh's grid (``motion``'s vertices are its valid points).
    normals, motion : ndarray, shape (n_vertices, 3)
    trust : ndarray, shape (n_vertices,)
        The tracking's trust (:func:`~livebridge.retarget.skin_flow.skin_motion`): the noise level is read on the
        trusted skin, and untrusted vertices (the geometric warp's motion) are left as they are.
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
        power = masked_blur(image, grid.valid, window_mm / grid.spacing)[grid.valid]
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


def robust_heights(dz: np.ndarray, weight: np.ndarray, blur, z_use: np.ndarray | None = None) -> np.ndarray:
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

    The heights take the base width's smoothing alone, without the x-y motion's twicing or choice of width:
    in `livebridge bench scans`' draws (60k points a scan: seeds 7 and 8, the other face) twicing them (with
    these weights) gave means of the 16 elements 0.0857 / 0.0877 / 0.0894 against 0.0867 / 0.0886 / 0.0889
    (the other face's lip corner 0.126 -> 0.135), Lepski's choice among twiced, base and twice the base width
    0.0863 on seed 7: a closing lid's crease, which the heights' smoothing flattens by up to 0.6 mm, kept its
    figures within 0.002.
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


def twiced(blur, channels: list, weight: np.ndarray) -> list:
    """Tukey's twicing of a smoothing: the channels' smooth plus the smooth of what it left, ``s + B(f - s)``
    with ``s = B(f)``, a list like ``channels`` (each (rows, cols)); NaN where nothing is near.

    ``blur(channels, weight) -> means`` is a normalised smoothing (as in :func:`robust_heights`). A Gaussian
    of width ``sigma`` moves a curving motion ``f`` by about ``sigma^2 / 2`` times its Laplacian; twicing
    takes that back to fourth order (its kernel ``2 G_sigma - G_sigma*G_sigma``) for ~1.8 times the noise
    variance, far less than halving the width (4 times).
    """
    first = blur(channels, weight)
    left = [np.where(weight > 0, channel - np.nan_to_num(smooth), 0.0) for channel, smooth in zip(channels, first)]
    return [smooth + more for smooth, more in zip(first, blur(left, weight))]


def adaptive_smooth(means: list, weight: np.ndarray, sigma: float, sharp: np.ndarray | None = None) -> np.ndarray:
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
        A less biased smoothing at the base width (:func:`twiced`).
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
        local = weighted_blur(np.where(usable, difference, 0.0), usable.astype(np.float32),
                               sigma * widths[k + 1] * WIDEN_WINDOW)
        wider = np.clip(2.0 - local / max(thresholds[k] * noise, 1e-12), 0.0, 1.0)
        wider = np.where(np.isfinite(wider), wider, 0.0)[..., None]
        result = candidates[k] + wider * (np.nan_to_num(result) - candidates[k])
    return result


def surface_rise(heights: np.ndarray, step: float, motion: np.ndarray, shift: np.ndarray, sigma: float) -> np.ndarray:
    """How much the surface ``heights`` (rows, cols, mm on pixels of ``step`` mm; NaN: none), smoothed over
    ``sigma`` pixels, rises along ``shift`` (rows, cols, 2; mm) where ``motion`` (rows, cols, 2; mm, from each
    pixel) lands, to first order, shape (rows, cols): the height change that keeps a skin point moved along
    the surface on it."""
    finite = np.isfinite(heights)
    level = weighted_blur(np.nan_to_num(heights), finite.astype(np.float32), sigma)
    rows, cols = np.indices(heights.shape)
    at = [rows + np.nan_to_num(motion[..., 1]) / step, cols + np.nan_to_num(motion[..., 0]) / step]
    slope_y, slope_x = (map_coordinates(np.nan_to_num(g), at, order=1, cval=0.0) for g in np.gradient(level, step))
    return np.nan_to_num(slope_x * shift[..., 0] + slope_y * shift[..., 1])


def weighted_blur(image: np.ndarray, weight: np.ndarray, sigma: float) -> np.ndarray:
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
