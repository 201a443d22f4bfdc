"""The lighting in a scan's colours: the part of its brightness a smooth function of the surface's normal explains.

A scanner's colour is the skin's own (its albedo) times the light the skin caught, and that light changes with
the surface's normal: an opened jaw turns the chin's underside towards the flash, a frown tilts the brow's
skin. The skin tracking (:mod:`~livebridge.retarget.skin_flow`) normalises each image's contrast over a few mm,
which takes out shading that changes slowly, but not shading that bends within a few mm (the chin's and the
lips' curvature): lit by a flash on the scanner's axis with half the light ambient (`livebridge bench scans`,
``lit_scans``: 60k points, seed 7), the built jaw is 0.144 off with the shading left in, where the same scans
unlit give 0.071.

The albedo of skin does not follow its normal, so a low-order function of the normal fitted to a scan's
log-brightness (the nine real spherical harmonics up to order 2, which hold a distant light's Lambertian
shading to a few per cent; a robust fit, so brows and lips do not pull it) is its shading. The normals come
from the scan's own points, over :data:`NEIGHBOURS` points spaced :data:`NORMAL_CELL_MM` apart (a disc of
about 4.5 mm): finer ones are too noisy at a scanner's 0.2 mm, and the creases finer than that keep their
shading. Each scan is fitted on its own (its head pose and shape change its shading) and divided by it. On the
bench's lit scans that gives the jaw 0.080 and the frown 0.092 / 0.097 (0.100 / 0.106 left in), 12 of the 16
elements within 10 % as unlit (10 left in); but the eyelids 0.229 / 0.232 (0.224 / 0.205) and the lip corner
and press 0.120 / 0.126 (0.115 / 0.122). From textured meshes with the flash in their texture
(``lit_textured_meshes``): the jaw 0.101 -> 0.056, 14 of 16 within 10 % as unlit (13 left in), the eyelids
0.163 / 0.162 -> 0.175 / 0.164. What costs the eyelids is how sensitive their tracking is to what little
shading the fit leaves: divided by the simulator's true shading the lit scans give the unlit figures (0.198 /
0.181), but the fit with the simulator's exact normals, within 2-5 % of the true shading near the eyes, gives
0.245 / 0.360 (the jaw 0.073, the frown 0.080 / 0.093), and a smooth brightness field of +-3 % (30 mm across)
on unshaded scans moves the right eyelid 0.181 -> 0.209. The normals' reach (16 or 32 neighbours on the
textured meshes: 0.168 / 0.184, 0.181 / 0.174), fitting the brightness rather than its logarithm (0.231 /
0.228) and the neutral's fit, turned into each expression scan's frame, in place of each scan's own (0.237 /
0.220) change nothing; a correction faded out where a normal's neighbourhood is far from a plane, or near the
eyes, was far worse (its fading is a pattern to the flow).

A scan whose colour has no shading left (a texture the scanner already took the lighting out of) still
correlates a little with its normals (brows, lips and the eyes' rims are darker where the face turns):
dividing that out of the bench's unlit scans moved the right eyelid 0.180 -> 0.187 and the jaw 0.071 -> 0.076.
So the shading is removed only when it explains at least :data:`MIN_EXPLAINED` of the neutral scan's
log-brightness, and then from every scan of the person. It explains 0.025-0.037 of the bench's unlit scans,
0.435 of its lit scans and 0.316 of its lit textured meshes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from livebridge.retarget.grid import cell_index

NEIGHBOURS = 64
"""Points a normal is fitted to (on the points thinned to :data:`NORMAL_CELL_MM`). Measured with a flash on
the axis fixed to the face (60k points, every scan's shading removed): 24 gave the jaw 0.077 but the risorius_L
0.138 (noisy normals), 64 0.078 / 0.084, 150 0.081 / 0.083 with the corrugator_R 0.135."""
NORMAL_CELL_MM = 1.0
"""The points are thinned to one per cell this wide before the normals are fitted, so that their reach is in
mm whatever the scan's density."""
MIN_EXPLAINED = 0.1
"""The share of the neutral's log-brightness variance the fitted shading must explain to be removed."""
LUMINANCE = np.array([0.299, 0.587, 0.114])
"""The weights of brightness, here and in the skin images (Rec. 601)."""
HUBER_K = 1.345
ROBUST_STEPS = 5
DARKEST = 1e-3
"""Points darker than this (0-1 scale) are left out of the fit (no logarithm)."""
N_HARMONICS = 9
MIN_POINTS = 100
"""Fewer points brighter than :data:`DARKEST` fit no shading."""


@dataclass(frozen=True)
class Shading:
    """A scan's fitted shading.

    Attributes
    ----------
    coefficients : ndarray, shape (N_HARMONICS,)
        Of the log-brightness over :func:`harmonics` of the normal (the first, the constant, is the albedo's
        mean and is not divided out).
    explained : float
        The share of the scan's log-brightness variance the fit explains, in [0, 1].
    """

    coefficients: np.ndarray
    explained: float


def surface_normals(points: np.ndarray) -> np.ndarray:
    """Unit normals (n, 3) of a point cloud (n, 3; +z out of the face), each from a plane fitted to the
    :data:`NEIGHBOURS` nearest of the points thinned to :data:`NORMAL_CELL_MM`, facing +z."""
    first = np.unique(cell_index(points, NORMAL_CELL_MM), return_index=True)[1]
    thinned = points[first]
    tree = cKDTree(thinned)
    k = min(NEIGHBOURS, len(thinned))
    neighbours = thinned[tree.query(thinned, k)[1].reshape(len(thinned), k)]
    spread = neighbours - neighbours.mean(axis=1, keepdims=True)
    normals = np.linalg.eigh(np.einsum("nki,nkj->nij", spread, spread))[1][:, :, 0]
    normals *= np.where(normals[:, 2:] < 0, -1.0, 1.0)
    return normals[tree.query(points)[1]]


def harmonics(normals: np.ndarray) -> np.ndarray:
    """The nine real spherical harmonics up to order 2 of unit ``normals`` (n, 3), unnormalised: (n, 9)."""
    x, y, z = normals.T
    return np.stack([np.ones_like(x), x, y, z, x * y, x * z, y * z, x * x - y * y, 3 * z * z - 1], axis=1)


def fit_shading(points: np.ndarray, colours: np.ndarray, normals: np.ndarray | None = None) -> Shading:
    """The shading of a coloured point cloud (``points`` (n, 3), ``colours`` (n, 3) RGB in [0, 1]): a robust
    (Huber) least-squares fit of its log-brightness over the harmonics of its normals (``normals`` (n, 3), by
    default :func:`surface_normals`)."""
    normals = surface_normals(points) if normals is None else normals
    brightness = colours @ LUMINANCE
    lit = brightness > DARKEST
    if lit.sum() < MIN_POINTS:  # nothing to fit: no shading found
        return Shading(np.zeros(N_HARMONICS), 0.0)
    basis, values = harmonics(normals[lit]), np.log(brightness[lit])
    weights = np.ones(len(values))
    for _ in range(ROBUST_STEPS):
        coefficients = np.linalg.lstsq(basis * weights[:, None], values * weights, rcond=None)[0]
        residual = values - basis @ coefficients
        scale = 1.4826 * float(np.median(np.abs(residual))) + 1e-12
        weights = np.sqrt(np.minimum(1.0, HUBER_K * scale / np.maximum(np.abs(residual), 1e-12)))
    variance = float(values.var())
    explained = 1.0 - float(residual.var()) / variance if variance > 0 else 0.0
    return Shading(coefficients, float(np.clip(explained, 0.0, 1.0)))


def unshaded(colours: np.ndarray, normals: np.ndarray, shading: Shading) -> np.ndarray:
    """``colours`` (n, 3) divided by ``shading`` at ``normals`` (n, 3): the skin's albedo up to one factor."""
    varying = harmonics(normals)[:, 1:] @ shading.coefficients[1:]
    return colours * np.exp(-varying)[:, None]


def lighting_said(shading: Shading, removed: bool) -> str:
    """What was done with a person's scans' lighting, for the build's log (``shading`` the neutral's)."""
    return (f"lighting: {'removed from' if removed else 'left in'} the scans' colours (it explains "
            f"{shading.explained:.0%} of the neutral's brightness)")
