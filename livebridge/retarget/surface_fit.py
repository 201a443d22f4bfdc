"""The neutral face's surface fitted to a scan's points: the heights of the basis's neutral mesh.

:func:`~livebridge.retarget.grid.resample` interpolates the scan's points linearly (thesis §5.4), so each grid
vertex carries the scanner's noise of the two or three points around it: 0.095 mm median, 0.186 mm RMS off
the true surface for the bench's neutral scan (0.2 mm noise, 60k points a scan, seed 7). The expressions the
basis gives are that neutral plus the elements, whose heights are smoothed: they inherited the neutral's
noise, which was most of how far they lay off the true expressive surfaces. A moving least squares fit (a
quadratic in x-y through the points within :data:`FIT_SPACINGS` point spacings, Gaussian-weighted and robust
to outliers), trusted only where it stays within the noise of the interpolated height
(:data:`TRUSTED_DEVIATION`), keeps the face's curvature and averages the noise. Where the interpolation blends
two surfaces (:data:`MIXED_DEPTH_MM`: a nostril's rim and the lip 25 mm behind it, which left the vertex in the
air, up to 6.9 mm off the face) the vertex takes the fit to one of them. Off the true neutral, median / RMS mm:
0.095 / 0.186 -> 0.048 / 0.099 (seed 7, 60k points), 0.097 / 0.236 -> 0.046 / 0.102 (seed 8, 60k), 0.095 /
0.158 -> 0.044 / 0.099 (seed 7, 150k); the rest of the tail is where no fit is trusted (the lips' seam, the
eyes' rims, the face's steep sides).

In `livebridge bench scans` (seed 7) the surface errors fell from 0.042-0.111 to 0.023-0.085 of the elements'
RMS motion at 60k points a scan (the lip corner 0.109 -> 0.056, the lip press 0.099 -> 0.059, the eyelids 0.110
/ 0.111 -> 0.085 / 0.082, the brows 0.057 -> 0.029), from 0.029-0.105 to 0.018-0.081 at 150k (the eyelids
0.102 / 0.105 -> 0.074 / 0.081). Seed 8 (60k): 0.050-0.149 -> 0.023-0.085. The elements are unchanged, but
their truth is read where the moved vertices now lie, which moved their errors by at most 0.002 except the
jaw's, 0.068 -> 0.071: one vertex on the lips' seam, 0.34 mm lower, has its closest point of the ICT face on
the other lip. Without the two-surface rule seed 8's lip corner and lip press stayed at 0.134 / 0.119; with
it judged on the three nearest points and the fit to all of them, 0.113 / 0.102.

Tried and not taken (before the two-surface rule): fitting (and falling back to) only the points the skin images keep
(:func:`~livebridge.retarget.skin_flow.in_front`, judged on a fine height image of the points): the nostrils'
vertices came onto the face (RMS off the true neutral, seed 8 / 7 at 60k: 0.202 / 0.141 -> 0.121 / 0.118;
bench surfaces of seed 8's lip corner and lip press 0.134 / 0.119 -> 0.073 / 0.073), but at 150k points the
bottom of the crease beside the nose's wings, narrower than the 2 mm window, was taken for a surface seen
through a gap and spanned 1-2.6 mm above (RMS 0.102 -> 0.109; judged on the grid's own cells, 0.124). Leaving
out instead every point with another 10 mm in front of it within a grid cell in x-y (what the resampling's
per-cell test misses where its cells split the two depths) did the same: 0.202 / 0.141 -> 0.123 / 0.119 at 60k,
0.102 -> 0.113 at 150k, where the nose's wing overhangs that crease and the deeper points, continuous with the
cheek, are the surface the grid's vertices lie on. A test that tells a nostril's speckle of two depths from
an overhang over skin that goes on would take the gain.

Only the neutral mesh the basis is written on takes these heights: the skin tracking and the shape warp work
on the interpolated grids as before (tracking on fitted expression grids too moved the eyelids and the jaw by
+0.009 and +0.005 relative RMS, unguarded, for nothing).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from livebridge.retarget.grid import FaceGrid, _cell, containing_triangles, front_surface, point_spacing

FIT_SPACINGS = 10.0
"""Radius of the points a grid vertex's quadratic is fitted to, in the scan's median point spacings (3.8 mm
at 60k points a scan over the bench's face); the weights are a Gaussian of half that sigma."""
NOISE_FIT_SPACINGS = 6.0
"""Radius of the fits of :func:`noise_level`, in point spacings: the least model error with points enough."""
MIN_POINTS = 12
"""A vertex with fewer points in reach (or points that do not pin a quadratic: all on one line) keeps the
interpolated height."""
ROBUST_ROUNDS = 2
"""Rounds of re-weighting by the Cauchy function of each point's residual."""
ROBUST_SCALE = 4.0
"""Cauchy scale in median absolute residuals (over the :data:`CHUNK` vertices fitted together)."""
TRUSTED_DEVIATION = 2.0
"""The fitted height replaces the interpolated one fully while the two differ by at most this many times the
points' noise (their robust residual scale from the fits), and not at all at twice that: more than noise
apart, the quadratic does not describe the surface there (a nostril's rim, the face's steep sides, a hole's
edge, where fits moved vertices by 1-30 mm)."""
MIXED_DEPTH_MM = 5.0
"""A vertex whose interpolation blends points (its Delaunay triangle's corners) more than this apart in depth
lies between two surfaces, in the air (a nostril's rim and the lip seen past it): it takes the fit to the
points of one surface, those within this depth of the corners' majority (or of the third corner where that
surface has too few points in reach), whatever it deviates from the interpolation."""
CHUNK = 4000
"""Vertices fitted at once (bounds the memory of the per-point products)."""


def fitted_heights(points: np.ndarray, grid: FaceGrid, spacing: float | None = None) -> np.ndarray:
    """The heights (n_rows, n_cols) of the surface of ``points`` fitted by moving least squares at the grid's
    vertices; NaN where ``grid`` has none.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        The scan's points in the grid's frame, cropped as for :func:`~livebridge.retarget.grid.resample`
        (only the front surface is used).
    grid : FaceGrid
        The interpolated grid: its mask is kept, and its heights stay where no quadratic can be fitted.
    spacing : float, optional
        The points' median spacing in x-y, mm (measured when not given).
    """
    points = np.asarray(points, dtype=np.float64)
    points = points[front_surface(points, _cell(grid.x, grid.y))]
    if spacing is None:
        spacing = point_spacing(points[:, :2])
    radius = FIT_SPACINGS * spacing
    heights = grid.heights.copy()
    gx, gy = np.meshgrid(grid.x, grid.y)
    at = np.flatnonzero(np.isfinite(heights))
    queries = np.column_stack([gx.ravel()[at], gy.ravel()[at]])
    tree = cKDTree(points[:, :2])
    chunks = [_fit(points, tree, queries[k:k + CHUNK], radius) for k in range(0, len(queries), CHUNK)]
    fitted = np.concatenate([c[0] for c in chunks])
    residuals = np.concatenate([c[1] for c in chunks])
    noise = _robust_scale(residuals)
    flat = heights.ravel()
    deviation = np.abs(fitted - flat[at])
    share = np.clip(2.0 - deviation / max(TRUSTED_DEVIATION * noise, 1e-12), 0.0, 1.0)
    corners = _interpolated_from(points[:, :2], queries)
    depths = np.where(corners[:, :1] >= 0, points[:, 2][np.maximum(corners, 0)], np.nan)
    mixed = np.ptp(depths, axis=1) > MIXED_DEPTH_MM  # the interpolation spans two surfaces: no height of either
    if mixed.any():  # fitted again to the surface two of the three corners lie on, else to the third's
        majority = np.median(depths[mixed], axis=1)
        odd = depths[mixed][np.arange(mixed.sum()), np.argmax(np.abs(depths[mixed] - majority[:, None]), axis=1)]
        on_layer = _fit(points, tree, queries[mixed], radius, majority)[0]
        on_layer = np.where(np.isfinite(on_layer), on_layer, _fit(points, tree, queries[mixed], radius, odd)[0])
        fitted[mixed] = on_layer
        share = np.where(mixed, 1.0, share)
    flat[at] += np.where(np.isfinite(fitted), share * (fitted - flat[at]), 0.0)
    return flat.reshape(heights.shape)


def noise_level(points: np.ndarray, grid: FaceGrid, n_fits: int = 1000) -> float:
    """The scanner's noise (mm): the robust scale of ``points`` (n, 3; in the grid's frame) about the local
    quadratics of :func:`fitted_heights` (over :data:`NOISE_FIT_SPACINGS`), fitted at up to ``n_fits`` of
    ``grid``'s vertices (evenly picked).

    A scale, not the noise's standard deviation: on ICT scans with 0.1 / 0.2 / 0.5 mm noise it read 0.15 / 0.29 /
    0.70 (the points' noise is 3D, their residuals are in depth, and a quadratic does not follow a face exactly;
    over 3 / 4 / 5 / 7 / 10 spacings, at 0.2 mm: 0.60 / 0.38 / 0.29 / 0.29 / 0.32)."""
    points = np.asarray(points, dtype=np.float64)
    points = points[front_surface(points, _cell(grid.x, grid.y))]
    gx, gy = np.meshgrid(grid.x, grid.y)
    at = np.flatnonzero(np.isfinite(grid.heights))
    at = at[::max(1, len(at) // n_fits)]
    queries = np.column_stack([gx.ravel()[at], gy.ravel()[at]])
    radius = NOISE_FIT_SPACINGS * point_spacing(points[:, :2])
    return _robust_scale(_fit(points, cKDTree(points[:, :2]), queries, radius)[1])


def _robust_scale(residuals: np.ndarray) -> float:
    """1.4826 times the median absolute residual: the standard deviation of Gaussian noise, robustly."""
    return 1.4826 * float(np.median(np.abs(residuals))) if len(residuals) else 0.0


def _interpolated_from(points_xy: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """The three points (indices, (m, 3); -1 outside their hull) whose Delaunay triangle holds each query: the
    corners :func:`~livebridge.retarget.grid.resample`'s linear interpolation blends there."""
    triangulation, simplex = containing_triangles(points_xy, queries)
    return np.where(simplex[:, None] >= 0, triangulation.simplices[simplex], -1)


def _fit(points: np.ndarray, tree: cKDTree, queries: np.ndarray, radius: float, layer: np.ndarray | None = None
         ) -> tuple[np.ndarray, np.ndarray]:
    """The fitted height at each query (m, 2), NaN where none can be fitted, shape (m,); and the residuals of
    the points in reach of the fitted queries (by the last fit; a point once per query it reaches). With
    ``layer`` (m,), only the points within :data:`MIXED_DEPTH_MM` of that depth count for each query."""
    near = tree.query_ball_point(queries, radius)
    counts = np.fromiter((len(n) for n in near), int, len(near))
    out = np.full(len(queries), np.nan)
    if counts.sum() == 0:
        return out, np.zeros(0)
    index = np.concatenate([n for n in near if n]).astype(np.intp)
    owner = np.repeat(np.arange(len(queries)), counts)
    offset = (points[index, :2] - queries[owner]) / radius  # scaled: a well-conditioned design
    z = points[index, 2]
    design = np.column_stack([np.ones(len(z)), offset[:, 0], offset[:, 1], offset[:, 0] ** 2,
                              offset[:, 0] * offset[:, 1], offset[:, 1] ** 2])
    prior = np.exp(-2.0 * np.sum(offset ** 2, axis=1))  # sigma = radius / 2
    if layer is not None:
        prior = np.where(np.abs(z - layer[owner]) < MIXED_DEPTH_MM, prior, 0.0)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    has = counts > 0
    enough = np.bincount(owner, weights=(prior > 0).astype(float), minlength=len(queries)) >= MIN_POINTS
    weight = prior
    for _ in range(ROBUST_ROUNDS + 1):
        normal = np.zeros((len(queries), 6, 6))
        right = np.zeros((len(queries), 6))
        normal[has] = np.add.reduceat(weight[:, None, None] * design[:, :, None] * design[:, None, :],
                                      starts[has], axis=0)
        right[has] = np.add.reduceat(weight[:, None] * design * z[:, None], starts[has], axis=0)
        scale = np.linalg.eigvalsh(normal)
        usable = enough & (scale[:, 0] > 1e-6 * np.maximum(scale[:, -1], 1e-300))
        normal[~usable] = np.eye(6)
        coefficients = np.linalg.solve(normal, right[..., None])[..., 0]
        residual = z - np.einsum("nk,nk->n", design, coefficients[owner])
        typical = max(float(np.median(np.abs(residual))) * ROBUST_SCALE, 1e-12)
        weight = prior / (1.0 + (residual / typical) ** 2)
    out[usable] = coefficients[usable, 0]
    return out, residual[usable[owner]]
