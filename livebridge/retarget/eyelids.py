"""The eyelids' motion between two scans from where the eye opening is: a first guess for the skin flow.

A closing eyelid slides the upper lid's skin ~10 mm down over the eye, and the lid turns from a steep fold
(seen almost edge-on by a frontal scanner, its pattern compressed) to a surface facing the scanner. The 22
landmarks know nothing of it (the eye corners do not move), and the skin flow
(:mod:`~livebridge.retarget.skin_flow`) started from the geometric warp follows only a third of it: the
stretched lid pattern matches almost as well at the wrong place, and in the simulated scans a 1-D search
along each column of the lid (dynamic programming over monotone stretches) did not find it either (its
best match had 0.1-0.3 of the cost of unrelated skin all along the column; measured on the bench scans).

What the scans do show is the opening. In the neutral it is a hole in the skin image between the lids'
margins; in the expression it is gone (a closed eye) or smaller (a squint). Along each column across the
eye (x fixed; the lids close along y), the upper margin must end at the expression's opening's upper edge,
or at the lower margin where the opening is gone (the lower lid barely moves in a blink); the lower margin
likewise. The skin between the margin and :data:`REACH_EYE_WIDTHS` eye widths away follows with a weight
falling from 1 at the margin to 0 (a half cosine), columns between the opening's end and an eye corner taper
to no motion at the corner. The skin flow refines that guess.

The opening of a resampled scan is smaller than the eye's: a grid point counts as surface when a scan point
lies within the resampling's gap distance (:data:`~livebridge.retarget.grid.GAP_SPACINGS`), so every edge of
a hole moves that far in; the margins are put back by it. The skin images' gap (2.2 mm on the bench's grid)
fills a squint's slit up to twice that tall, which then reads as a closed eye (a synthetic squint's 2.5 mm
margin motion taken for 8 mm); the expression's opening is therefore read from its holes at the scan's own
point spacing (:func:`~livebridge.retarget.face_scan.opening_gap_mm`: 1.4 mm at 60k points a scan), keeping only
holes long along the eye (:data:`MIN_OPENING_EYE_WIDTHS`: a stray gap between scan points is none).

When the neutral shows no opening (a scanner that fills holes, a mesh closed over the eye) and the landmark
files also name the lids' points of the 68-point iBUG layout (37, 38, 40, 41 on the subject's right eye, 43,
44, 46, 47 on the left, as ``lm_37`` ...; a landmark detector on each scan's texture gives them), the margins
and their motion come from those landmarks. Where the opening is seen it is used first: in `livebridge bench
scans` with the 8 lid landmarks added (0.5 mm noise, 60k points a scan) the margins from the landmarks gave 0.40
and 0.41 relative RMS for the two eyelid elements, from the openings 0.36 and 0.35 (the lid landmarks also join
the landmark spline of the warp a skin flow starts from; a warp from shape alone leaves them out:
:func:`~livebridge.retarget.scans.shape_element`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from livebridge.retarget.grid import FaceGrid

REACH_EYE_WIDTHS = 0.35
"""The lid's skin moves with its margin up to this many eye widths (corner to corner) away from it."""
MIN_MOTION_MM = 1.5
"""An eye whose margins moved less than this in the median column (the edges of a resampled hole are uncertain
by about a fine grid step) keeps the first guess."""
TAPER_BEYOND_EYE_WIDTHS = 0.1
"""Past the opening's ends the lids' motion falls to none this many eye widths beyond the corners (the ring
muscle moves the skin past the corners too; on the bench scans at 60k points 0.1 measured 0.345 and 0.384 for
the two eyelids, 0 gave 0.363 and 0.386, 0.2 gave 0.376 and 0.392)."""
COLUMN_MEDIAN_MM = 2.0
"""The margins' motion is the median over columns this wide."""
MIN_OPENING_EYE_WIDTHS = 0.3
"""A hole of the expression's skin image is an eye opening only where it spans at least this many eye widths
along the eye: an opening (a squint's slit too) runs along most of the eye, where a gap between scan points
the mask's gap distance wide is a blob of a mm or two (at the scan's own point spacing, a closed eye of
`livebridge bench scans` showed one, which read as an opening and moved the upper margin 4.3 mm instead of 9.4
over a few columns, the lower one 1.8 mm up). With this, the bench's figures are those of the skin image's own
holes."""
LID_LANDMARKS = {"L": (("lm_43", "lm_44"), ("lm_47", "lm_46")), "R": (("lm_38", "lm_37"), ("lm_40", "lm_41"))}
"""Per side, the iBUG landmarks of the upper lid and of the lower lid, each from the inner corner outwards."""
LID_LANDMARK_NAMES = tuple(name for side in LID_LANDMARKS.values() for margin in side for name in margin)
"""The 8 of :data:`LID_LANDMARKS`, left eye first."""


@dataclass(frozen=True)
class LidColumn:
    """One column across an eye: the neutral's margins (fine rows) and where each went (mm along y)."""

    upper: float
    lower: float
    upper_motion: float
    lower_motion: float


def lid_columns(neutral: FaceGrid, expression: FaceGrid, inner: np.ndarray, outer: np.ndarray,
                grow_mm: float, seen_grow_mm: float | None = None) -> dict[int, LidColumn]:
    """The margins and their motion along every column of one eye, from the openings of both skin grids.

    Parameters
    ----------
    neutral, expression : FaceGrid
        Fine grids (skin images) on the same grid lines, in the face frame (+y up).
    inner, outer : ndarray, shape (2,)
        The eye's corners in x-y (neutral).
    grow_mm : float
        How far each edge of a hole of the grids lies inside the true edge (the resampling's gap distance).
    seen_grow_mm : float, optional
        The same for ``expression``'s holes when they were masked with another gap (default ``grow_mm``): a
        gap at the scan's own point spacing shows a squinting eye's slit that the skin image's wider one fills.

    Returns
    -------
    dict of int to LidColumn
        By column index; columns between the opening and a corner taper to the corner.
    """
    step = neutral.spacing
    seen_grow = grow_mm if seen_grow_mm is None else seen_grow_mm
    has_n, has_e = np.isfinite(neutral.heights), np.isfinite(expression.heights)
    rows = np.arange(neutral.shape[0])
    left, right = sorted((inner[0], outer[0]))
    width = float(np.linalg.norm(outer - inner))
    has_e = ~_long_holes(~has_e, MIN_OPENING_EYE_WIDTHS * width / step)  # no stray gap between scan points
    columns: dict[int, LidColumn] = {}
    for col in np.flatnonzero((neutral.x > left) & (neutral.x < right)):
        centre = int(round(np.interp(_corner_line_y(inner, outer, neutral.x[col]), neutral.y, rows)))
        opening = _run_around(~has_n[:, col], centre, int(round(0.25 * width / step)))
        if opening is None:
            continue
        low, high = opening
        upper, lower = high + 1 + grow_mm / step, low - 1 - grow_mm / step
        seen = _run_around(~has_e[:, col], centre, int(round(0.25 * width / step)))
        if seen is not None:  # an opening still: each margin goes to its edge (grown back like the neutral's)
            up = (seen[1] + 1 + seen_grow / step - upper) * step
            down = (seen[0] - 1 - seen_grow / step - lower) * step
        else:  # closed: the upper lid comes down onto the lower one
            up, down = (lower - upper) * step, 0.0
        columns[int(col)] = LidColumn(upper, lower, up, down)
    columns = _median_across(columns, max(1, int(round(COLUMN_MEDIAN_MM / step / 2))))
    _taper_to_corners(columns, neutral, inner, outer, TAPER_BEYOND_EYE_WIDTHS * width)
    return columns


def lid_columns_from_landmarks(neutral: FaceGrid, before: dict, after: dict, side: str, inner: np.ndarray,
                               outer: np.ndarray) -> dict[int, LidColumn]:
    """The margins and their motion along every column of one eye from its lid landmarks
    (:data:`LID_LANDMARKS`), piecewise linear in x between the corners (which do not move)."""
    rows = np.arange(neutral.shape[0])
    ends = [(inner[0], _corner_line_y(inner, outer, inner[0])), (outer[0], _corner_line_y(inner, outer, outer[0]))]

    def margin(names):
        """(x, y, y motion) of a margin through the corners and its landmarks, sorted by x."""
        points = [(x, y, 0.0) for x, y in ends] + [(before[n][0], before[n][1], after[n][1] - before[n][1])
                                                  for n in names]
        return np.array(sorted(points)).T

    upper, lower = (margin(names) for names in LID_LANDMARKS[side])
    columns = {}
    left, right = sorted((inner[0], outer[0]))
    for col in np.flatnonzero((neutral.x > left) & (neutral.x < right)):
        x = neutral.x[col]
        up_y, up_d = (np.interp(x, upper[0], values) for values in upper[1:])
        lo_y, lo_d = (np.interp(x, lower[0], values) for values in lower[1:])
        columns[int(col)] = LidColumn(float(np.interp(up_y, neutral.y, rows)), float(np.interp(lo_y, neutral.y, rows)),
                                      float(up_d), float(lo_d))
    return columns


def lid_motion(neutral: FaceGrid, columns: dict[int, LidColumn], reach_mm: float, base: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """The y motion (n_rows, n_cols) of the lids' skin: each margin's motion at and beyond it (towards the
    eye), falling as a half cosine to ``base`` (n_rows, n_cols; the first guess) ``reach_mm`` away; and the
    mask of the points it sets."""
    step = neutral.spacing
    dy = base.copy()
    touched = np.zeros(neutral.shape, bool)
    n_rows = neutral.shape[0]
    reach = reach_mm / step
    for col, lid in columns.items():
        middle = 0.5 * (lid.upper + lid.lower)
        for margin, motion, away in ((lid.upper, lid.upper_motion, 1), (lid.lower, lid.lower_motion, -1)):
            # from the middle of the opening out to reach beyond the margin
            start, stop = sorted((int(np.floor(middle)), int(np.ceil(margin + away * reach))))
            rows = np.arange(max(start, 0), min(stop + 1, n_rows))
            rows = rows[away * (rows - middle) >= 0]
            u = np.clip(away * (rows - margin) / reach, 0.0, 1.0)
            weight = 0.5 * (1.0 + np.cos(np.pi * u))
            dy[rows, col] = (1.0 - weight) * base[rows, col] + weight * motion
            touched[rows, col] = True
    return dy, touched


def eyelid_guess(neutral_fine: FaceGrid, expression_fine: FaceGrid, at: np.ndarray, first_guess: np.ndarray,
                 lids: list[tuple[dict[int, LidColumn], float]]) -> tuple[np.ndarray, np.ndarray]:
    """``first_guess`` (n_vertices, 3) of a mesh's vertices with the lids' motion (y from
    :func:`lid_motion`, z onto the expressive surface there) wherever an eye's lids are found, and which
    vertices those are, (n_vertices,) bool.

    ``neutral_fine``, ``expression_fine``, ``at`` (the vertices on the skin images) as in
    :func:`~livebridge.retarget.skin_flow.skin_motion`, ``first_guess`` in the skin images' chart (x, y, z
    here: the chart's u, v, height); ``lids``: the moving eyes, as :func:`moving_lids` finds them.
    """
    from scipy.ndimage import map_coordinates

    from livebridge.retarget.skin_flow import at_vertices, vertex_field

    guess = vertex_field(at, first_guess[:, 1:2], neutral_fine.shape)[..., 0]
    dy, touched = guess, np.zeros(neutral_fine.shape, bool)
    for columns, reach in lids:
        dy, hit = lid_motion(neutral_fine, columns, reach, dy)
        touched |= hit
    hit = at_vertices(touched.astype(np.float64), at) > 0.5
    out = first_guess.copy()
    out[hit, 1] = at_vertices(dy, at[hit])
    step = neutral_fine.spacing
    landed = map_coordinates(expression_fine.heights, [at[hit, 0] + out[hit, 1] / step,
                                                       at[hit, 1] + out[hit, 0] / step], order=1, cval=np.nan)
    dz = landed - at_vertices(neutral_fine.heights, at[hit])
    out[hit, 2] = np.where(np.isfinite(dz), dz, out[hit, 2])
    return out, hit


def closing_openings(shape: tuple[int, int], lids: list[tuple[dict[int, LidColumn], float]]
                     ) -> np.ndarray | None:
    """The neutral's eye openings whose lids moved, between the lids' margins, (n_rows, n_cols) = ``shape``
    bool on the neutral skin image's grid; None when no eye's lids moved. ``lids``: as :func:`moving_lids`
    finds them.

    The skin image's hole lies inside the opening by ``grow_mm``; the heights in that band are the
    resampling's fill from the last scan points of the lids' rims, which curl back over the eye, away from
    the scanner. Once the opening closes, the expression's surface there is the lid's front, so the change in
    height there is not the skin's motion: read as such it brought the lids' edges forward (+0.5 to +2 mm by
    the lower lid's margin in `livebridge bench scans`, where the lower lid hardly moves). The skin flow leaves
    these points out of the depth change (:func:`~livebridge.retarget.skin_flow.skin_motion`'s ``not_skin``):
    eyelid elements at 150k points a scan 0.242 / 0.248 relative RMS -> 0.228 / 0.237 (60k: 0.322 / 0.279 ->
    0.319 / 0.280), with another seed's scans 0.246 / 0.235 -> 0.225 / 0.222 (60k: 0.248 / 0.270 -> 0.243 /
    0.269). Leaving out every hole's fill band the same way (nostrils, the face's outline) cost other elements
    up to 0.003.
    """
    opening = np.zeros(shape, bool)
    rows = np.arange(shape[0])
    for columns, _ in lids:
        for col, lid in columns.items():
            opening[:, col] |= (rows >= lid.lower) & (rows <= lid.upper)
    return opening if opening.any() else None


def moving_lids(neutral_fine: FaceGrid, expression_fine: FaceGrid, before: dict, after: dict, grow_mm: float,
                seen_grow_mm: float | None = None) -> list[tuple[dict[int, LidColumn], float]]:
    """(lid columns, reach in mm) of every eye whose lids moved.

    ``neutral_fine``, ``expression_fine``: the neutral's and the expression's skin images; ``before``,
    ``after``: their landmarks in the images' chart (the eye corners ``eye_inner_L`` ... name the eyes; an eye
    without both corners is left alone; lid landmarks :data:`LID_LANDMARKS` in both are used when there);
    ``grow_mm``, ``seen_grow_mm``: see :func:`lid_columns`. The reach is :data:`REACH_EYE_WIDTHS` eye widths.
    """
    found = []
    for side in ("L", "R"):
        if f"eye_inner_{side}" not in before or f"eye_outer_{side}" not in before:
            continue
        inner = np.asarray(before[f"eye_inner_{side}"], dtype=np.float64)[:2]
        outer = np.asarray(before[f"eye_outer_{side}"], dtype=np.float64)[:2]
        columns = lid_columns(neutral_fine, expression_fine, inner, outer, grow_mm, seen_grow_mm)
        names = [name for margin in LID_LANDMARKS[side] for name in margin]
        if not columns and all(n in before and n in after for n in names):  # no opening in the neutral
            columns = lid_columns_from_landmarks(neutral_fine, before, after, side, inner, outer)
        if not columns or np.median([max(abs(c.upper_motion), abs(c.lower_motion)) for c in columns.values()]
                                    ) < MIN_MOTION_MM:
            continue  # this eye's lids did not move (a thin opening at a corner may read as closed): the guess stays
        found.append((columns, REACH_EYE_WIDTHS * float(np.linalg.norm(outer - inner))))
    return found


def _long_holes(hole: np.ndarray, length: float) -> np.ndarray:
    """The points of ``hole`` (rows, cols) bool in connected pieces spanning at least ``length`` columns."""
    from scipy.ndimage import find_objects, label

    labels, _ = label(hole)
    keep = np.zeros(labels.max() + 1, bool)
    for k, box in enumerate(find_objects(labels), start=1):
        keep[k] = box is not None and box[1].stop - box[1].start >= length
    return keep[labels]


def _corner_line_y(inner: np.ndarray, outer: np.ndarray, x: float) -> float:
    """y of the line through the eye's corners at ``x``."""
    if outer[0] == inner[0]:
        return float(0.5 * (inner[1] + outer[1]))
    return float(inner[1] + (outer[1] - inner[1]) * (x - inner[0]) / (outer[0] - inner[0]))


def _run_around(mask: np.ndarray, centre: int, reach: int) -> tuple[int, int] | None:
    """The first and last index of the run of True in ``mask`` (n,) nearest ``centre`` within ``reach``."""
    lo, hi = max(centre - reach, 0), min(centre + reach + 1, len(mask))
    near = lo + np.flatnonzero(mask[lo:hi])
    if not len(near):
        return None
    at = int(near[np.argmin(np.abs(near - centre))])
    low, high = at, at
    while low > 0 and mask[low - 1]:
        low -= 1
    while high + 1 < len(mask) and mask[high + 1]:
        high += 1
    return low, high


def _median_across(columns: dict[int, LidColumn], half: int) -> dict[int, LidColumn]:
    """Each column's motions the median over the found columns within ``half`` columns of it (one column's
    opening edge can be off by a stray scan point or a thin end of the opening)."""
    keys = sorted(columns)
    up = np.array([columns[k].upper_motion for k in keys])
    down = np.array([columns[k].lower_motion for k in keys])
    out = {}
    for i, key in enumerate(keys):
        near = slice(max(i - half, 0), i + half + 1)
        out[key] = LidColumn(columns[key].upper, columns[key].lower, float(np.median(up[near])),
                             float(np.median(down[near])))
    return out


def _taper_to_corners(columns: dict[int, LidColumn], grid: FaceGrid, inner: np.ndarray, outer: np.ndarray,
                      beyond_mm: float) -> None:
    """Columns between the opening's ends and ``beyond_mm`` past the eye's corners: margins meeting at the
    corner line, motion falling linearly to none there (in place)."""
    if not columns:
        return
    rows = np.arange(grid.shape[0])
    ends = sorted(columns)
    outwards = np.sign(outer[0] - inner[0])
    for corner, away in ((inner, -outwards), (outer, outwards)):
        at = int(np.argmin(np.abs(grid.x - (corner[0] + away * beyond_mm))))
        end = ends[0] if at < ends[0] else ends[-1]
        if at == end or ends[0] <= at <= ends[-1]:
            continue
        lid = columns[end]
        for col in range(min(at, end) + 1, max(at, end)):
            w = abs(col - at) / abs(end - at)  # 0 at the corner, 1 at the opening's end
            line = float(np.interp(_corner_line_y(inner, outer, grid.x[col]), grid.y, rows))
            mid = line + w * (0.5 * (lid.upper + lid.lower) - line)
            half = w * 0.5 * (lid.upper - lid.lower)
            columns[col] = LidColumn(mid + half, mid - half, w * lid.upper_motion, w * lid.lower_motion)
