"""The eyeballs a scanner sees through the eye openings, told from the skin by their colour and left out.

The scan pipeline reads an eye's opening as a hole in the skin (:mod:`~livebridge.retarget.eyelids`: where
the lids' margins are, and where they went in an expression). A scanner sees the eyes too, the white sclera
and the iris between the lids; resampled with the skin they fill the opening, and the closing lid's skin is
then tracked against a surface that never moves.

Within an ellipse around each eye (:data:`REGION_EYE_WIDTHS`, from the two eye corners' landmarks), a point
is unlike skin when its chromaticity lies far from that of the skin in a ring around the ellipse
(:data:`CHROMA_SPREADS` of the ring's robust spread, at least :data:`MIN_CHROMA`), or when it is much darker
(:data:`DARK`: a pupil, a dark iris). Light (flash, shading) scales the three channels alike and leaves the
chromaticity as it is. The opening is the convex hull of the cells of a raster of :data:`CELL_MM` where most
points are unlike skin, in the pieces that reach the line between the corners and together span at least
:data:`~livebridge.retarget.eyelids.MIN_OPENING_EYE_WIDTHS` eye widths along the eye: a mole or a lash's
shadow is none, and an iris as like skin as the skin around it (a brown iris by a brown skin) is inside the
hull of the whites either side of it, all but a crescent along each lid about a mm wide. Well inside the hull
every point is the eye's; at its edge (:data:`HULL_EDGE_CELLS`) and around it (:data:`RIM_CELLS`) only those
unlike skin. A closed eye shows lid skin only and loses nothing.

`livebridge bench scans` (``scanned_eyes``: the 60k-point scans also seeing the ICT head's eyeballs, sclera
and a brown iris, between the lids): left out, 946 points of the neutral, the eyelids 0.200 / 0.208 relative
RMS, as without eyes (0.198 / 0.180 from another draw); kept, 0.688 / 1.151. With a second eyeball simulation
(seeds 7 and 8) every element came within 0.006 of the same scans with every eyeball point dropped; 7-19 skin
points a scan were taken, all on the lids' rims.

A scan without colour keeps its eyeballs: the eyelids are then read from the lids' landmarks, if given (see
:mod:`~livebridge.retarget.eyelids`).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from livebridge.retarget.eyelids import MIN_OPENING_EYE_WIDTHS

REGION_EYE_WIDTHS = (0.6, 0.4)
"""Semi-axes of the ellipse searched for an eyeball, along and across the eye, in eye widths (corner to
corner): a wide-open eye's opening reaches 0.25 of them above and below the corners' line, the brows lie
beyond 0.55."""
RING = 1.6
"""The skin the eyeball is told from: between the ellipse and this times it."""
CELL_MM = 0.5
"""The raster on which the opening is found."""
CHROMA_SPREADS = 4.0
"""A point is unlike skin this many robust spreads (1.4826 MAD) of the ring's chromaticity away from its
median."""
MIN_CHROMA = 0.02
"""... and at least this far (chromaticity, the channels over their sum): skin's hue varies little, the
sclera's white lies 0.05-0.07 from a light skin's, a brown iris as far the other way."""
DARK = 0.2
"""A point darker than this times the ring's median brightness is unlike skin whatever its hue."""
MOST = 0.5
"""A raster cell is in the opening when more than this share of its points is unlike skin."""
LINE_EYE_WIDTHS = 0.15
"""Between the corners and within this many eye widths of their line, every point unlike skin is the eye's,
in an opening or not: a closed eye's lids may leave a slit of eyeball too short to be an opening, a
squint's may break into pieces."""
HULL_EDGE_CELLS = 1
"""Within this many cells of the hull's edge a point is the eye's only if unlike skin (the edge's cells hold
lid skin too: taking every point there took 40-60 skin points a scan at 60k points, up to 1 mm from the
eye's)."""
RIM_CELLS = 2
"""... and within this many cells around the hull, outside it."""
SIDES = ("L", "R")


def eyeball_points(points: np.ndarray, colours: np.ndarray | None, landmarks: dict[str, np.ndarray]
                   ) -> np.ndarray:
    """Which points are an eyeball seen through an eye's opening.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        The scan in the face frame (+z out of the face).
    colours : ndarray, shape (n, 3), or None
        RGB in [0, 1]; None: nothing is found.
    landmarks : dict of str to ndarray, shape (3,)
        In the face frame; the eyes searched are those with ``eye_inner_<side>`` and ``eye_outer_<side>``.

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    found = np.zeros(len(points), dtype=bool)
    if colours is None or not len(points):
        return found
    for side in SIDES:
        corners = [landmarks.get(f"eye_{which}_{side}") for which in ("inner", "outer")]
        if any(corner is None for corner in corners):
            continue
        found |= _one_eye(points, colours, np.asarray(corners[0], float), np.asarray(corners[1], float))
    return found


def _one_eye(points: np.ndarray, colours: np.ndarray, inner: np.ndarray, outer: np.ndarray) -> np.ndarray:
    """The eyeball points (n,) bool of the eye between corners ``inner`` and ``outer`` (3,)."""
    along = (outer - inner)[:2]
    width = float(np.linalg.norm(along))
    if width <= 0:
        return np.zeros(len(points), dtype=bool)
    along /= width
    local = (points[:, :2] - 0.5 * (inner + outer)[:2]) @ np.array([along, [-along[1], along[0]]]).T
    reach = np.hypot(local[:, 0] / (REGION_EYE_WIDTHS[0] * width), local[:, 1] / (REGION_EYE_WIDTHS[1] * width))
    # the eye's own depth: not the nose's side or a cheek seen past the ellipse in x-y
    near = np.abs(points[:, 2] - 0.5 * (inner[2] + outer[2])) < width
    region, ring = near & (reach <= 1.0), near & (reach > 1.0) & (reach <= RING)
    if region.sum() < 10 or ring.sum() < 10:
        return np.zeros(len(points), dtype=bool)
    unlike = _unlike_skin(colours[region], colours[ring])
    on_line = (np.abs(local[region, 0]) < 0.5 * width) & (np.abs(local[region, 1]) < LINE_EYE_WIDTHS * width)
    opening = _opening(local[region], unlike, width) | (unlike & on_line)
    found = np.zeros(len(points), dtype=bool)
    found[np.flatnonzero(region)[opening]] = True
    return found


def _unlike_skin(colours: np.ndarray, skin: np.ndarray) -> np.ndarray:
    """Which of ``colours`` (m, 3) are unlike the ``skin`` colours (k, 3): far in chromaticity or much darker."""
    def chroma(rgb):
        total = rgb.sum(axis=1, keepdims=True)
        return rgb[:, :2] / np.maximum(total, 1e-6), total[:, 0]

    skin_chroma, skin_total = chroma(skin)
    centre = np.median(skin_chroma, axis=0)
    spread = 1.4826 * np.median(np.linalg.norm(skin_chroma - centre, axis=1))
    limit = max(CHROMA_SPREADS * spread, MIN_CHROMA)
    own, total = chroma(colours)
    return (np.linalg.norm(own - centre, axis=1) > limit) | (total < DARK * np.median(skin_total))


def _opening(local: np.ndarray, unlike: np.ndarray, width: float) -> np.ndarray:
    """Which points (``local``: (m, 2) mm along and across the eye; ``unlike``: (m,) bool) lie in the eye's
    opening: the convex hull of the cells of :data:`CELL_MM` where most points are unlike skin, joined and
    holes filled, in the pieces that reach the corners' line, together at least
    :data:`~livebridge.retarget.eyelids.MIN_OPENING_EYE_WIDTHS` eye widths long.

    The hull, because between the lids an opening is convex, and an iris may be as like skin as the skin is
    (a brown iris by a brown skin) and split the whites into two pieces either side of it."""
    low = local.min(axis=0)
    cell = np.floor((local - low) / CELL_MM).astype(int)
    voted = _voted(cell, unlike)
    labels, _ = ndimage.label(ndimage.binary_fill_holes(ndimage.binary_closing(voted)))
    centres = low + (np.indices(voted.shape).transpose(1, 2, 0) + 0.5) * CELL_MM
    line = (np.abs(centres[..., 0]) < 0.5 * width) & (np.abs(centres[..., 1]) < LINE_EYE_WIDTHS * width)
    pieces = np.isin(labels, np.setdiff1d(labels[line], 0))
    extent = centres[pieces, 0]
    if not extent.size or np.ptp(extent) + CELL_MM < MIN_OPENING_EYE_WIDTHS * width:
        return np.zeros(len(local), dtype=bool)
    # well inside the hull of the pieces' cells, every point (a stray point left in the hole would be resampled
    # into a disc of surface); at its edge and around it, whose cells hold lid skin too, only those unlike skin
    hull = _hull(pieces)
    at = tuple(cell.T)
    inside = ndimage.binary_erosion(hull, iterations=HULL_EDGE_CELLS)[at]
    near = ndimage.binary_dilation(hull, iterations=RIM_CELLS)[at]
    return inside | (near & unlike)


def _hull(cells: np.ndarray) -> np.ndarray:
    """The cells (a bool raster) whose centres lie in the convex hull of the centres of ``cells`` (bool, the
    same raster)."""
    from scipy.spatial import Delaunay, QhullError

    try:
        triangulation = Delaunay(np.argwhere(cells))
    except QhullError:  # all in a line: no area
        return cells
    return (triangulation.find_simplex(np.indices(cells.shape).reshape(2, -1).T) >= 0).reshape(cells.shape)


def _voted(cell: np.ndarray, unlike: np.ndarray) -> np.ndarray:
    """The raster (bool) of the cells where more than :data:`MOST` of the points (in cells ``cell`` (m, 2)) are
    ``unlike`` (m,) skin; a cell no point fell in (a sparse scan leaves gaps inside the opening too) takes the
    vote of the 3 x 3 cells around it."""
    shape = tuple(cell.max(axis=0) + 1)
    count, share = np.zeros(shape), np.zeros(shape)
    np.add.at(count, tuple(cell.T), 1.0)
    np.add.at(share, tuple(cell.T), unlike.astype(float))
    around, around_share = (ndimage.uniform_filter(a, 3) for a in (count, share))
    return np.where(count > 0, share > MOST * count, around_share > MOST * np.maximum(around, 1e-9))
