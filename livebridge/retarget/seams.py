"""The lips' seam: where a face's skin is cut, so that motion is carried, smoothed and warped on each side apart.

Closed lips touch along a line; an opened jaw takes the lower lip 20 mm or more away from the upper one, so
two neutral skin points a millimetre apart across that line move very differently. A warp or a smoothing
over the whole face (a spline through control points, a Gaussian over the tracked skin) averages them and
drags each lip towards the other. Here the seam is the curve through the mouth corners and between the
inner lip landmarks (a parabola in the face frame's x-y: the normalised face looks along +z, +y up); every
such operation is done once on each side of it and once over the whole face, and a point takes its own
side's result between the mouth corners, the whole face's beyond them (a linear taper over
:data:`TAPER_MM` past each corner: the cheeks are one piece of skin).

Moved onto the groove between the closed lips (:meth:`LipSeam.along_groove`), the seam passes half a skin
pixel beside the groove's bottom, on the side of the steeper flank (the overhanging lip): the bottom itself
is the other lip's skin. In `livebridge bench scans` (seed 7) the jaw's element went from 0.114 / 0.100 to
0.107 / 0.089 at 60k / 150k points a scan (with the nostrils left out of the heights, ``skin_flow.BEHIND_MM``).
Not better: a soft side for points within a pixel of the seam (both lips' motions, weighted by a Gaussian
of the distance: jaw 0.101 -> 0.099 only, costing the points the hard side had right), a photometric choice
of side near the seam (the lips carry no pattern a 0.5 mm check can use), each lip's flow tracked with the
other lip blanked (jaw 0.093 -> 0.098, depressor_anguli_oris 0.097 -> 0.101, single-pass).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from livebridge.errors import InputError

TAPER_MM = 6.0
"""Past a mouth corner, a point's own side counts fully at the corner and not at all this far beyond it."""
CORNERS = ("mouth_corner_R", "mouth_corner_L")
INNER_LIPS = ("lip_upper_inner", "lip_lower_inner")
GROOVE_WINDOW_MM = 2.0
"""How far across the landmarks' seam the groove between the lips is looked for (their noise: ~0.5 mm)."""
GROOVE_MEDIAN_MM = 3.0
"""The groove's offsets are median-filtered over this length along the seam (the scanner's noise)."""
STEEPER = 1.1
"""A groove's flank is the steeper one (see :func:`_steeper_flank`) when its steepest rise is this many times the
other's (a symmetric groove's two flanks differ by a few % where the image's pixels fall unevenly)."""
MIN_PIECE_POINTS = 10
"""A side with fewer points than this is not fitted on its own (the whole face's fit stands in)."""


@dataclass(frozen=True)
class LipSeam:
    """Where the lips meet, in the face frame's x-y.

    Attributes
    ----------
    right, left : ndarray, shape (2,)
        The mouth corners (the subject's right at -x).
    middle : ndarray, shape (2,)
        Between the inner lip landmarks.
    taper_mm : float
    groove : ndarray, shape (k,), or None
        How far the seam is above the parabola through the corners and ``middle`` (mm, along the up
        direction) at ``k`` evenly spaced points from the right corner to the left one (see
        :meth:`along_groove`); None: on the parabola.
    """

    right: np.ndarray
    left: np.ndarray
    middle: np.ndarray
    taper_mm: float = TAPER_MM
    groove: np.ndarray | None = None

    @classmethod
    def from_landmarks(cls, landmarks: dict[str, np.ndarray], taper_mm: float = TAPER_MM) -> LipSeam | None:
        """The seam of a face's landmarks (face frame), None without the mouth corners and inner lip points."""
        if not all(name in landmarks for name in CORNERS + INNER_LIPS):
            return None
        right, left = (np.asarray(landmarks[name], dtype=np.float64)[:2] for name in CORNERS)
        if np.linalg.norm(left - right) < 1e-6:
            return None
        middle = 0.5 * sum(np.asarray(landmarks[name], dtype=np.float64)[:2] for name in INNER_LIPS)
        return cls(right, left, middle, float(taper_mm))

    def _frame(self) -> tuple[float, np.ndarray, np.ndarray]:
        """(corner distance, unit vector from the right corner to the left, unit up vector)."""
        width = float(np.linalg.norm(self.left - self.right))
        along = (self.left - self.right) / width
        up = np.array([-along[1], along[0]])
        return width, along, (up if up[1] >= 0 else -up)

    def _seam_v(self, u: np.ndarray) -> np.ndarray:
        """The seam's offset along the up direction at ``u`` in [0, 1] (0 at the right corner, 1 at the left)."""
        width, along, up = self._frame()
        u_mid = float(np.clip((self.middle - self.right) @ along / width, 0.05, 0.95))
        v = float((self.middle - self.right) @ up) * u * (1.0 - u) / (u_mid * (1.0 - u_mid))
        if self.groove is not None:
            v = v + np.interp(u, np.linspace(0.0, 1.0, len(self.groove)), self.groove)
        return v

    def along_groove(self, grid, window_mm: float = GROOVE_WINDOW_MM, step_mm: float = 0.5) -> LipSeam:
        """This seam moved onto the groove where the closed lips meet.

        Between the corners, the seam goes through the deepest point (lowest z: the face looks along +z) of
        ``grid`` (a :class:`~livebridge.retarget.grid.FaceGrid`) within ``window_mm`` of this seam across it
        (the landmarks are off by their noise); where there is no surface there (the lips apart), through the
        middle of the gap. The offsets are median-filtered along the seam and fade to nothing at the corners
        (landmarks themselves). The groove's bottom pixel itself is given to the lip of the gentler flank (the
        seam passes half a pixel towards the steeper one: see :func:`_steeper_flank`)."""
        from scipy.ndimage import map_coordinates, median_filter

        width, along, up = self._frame()
        u = np.linspace(0.0, 1.0, max(int(np.ceil(width / step_mm)) + 1, 3))
        across = np.arange(-window_mm, window_mm + 1e-9, step_mm / 4)
        on_seam = self.right + u[:, None] * width * along + self._seam_v(u)[:, None] * up  # (k, 2)
        xy = on_seam[:, None, :] + across[None, :, None] * up  # (k, m, 2)
        rows = (xy[..., 1] - grid.y[0]) / (grid.y[1] - grid.y[0])
        cols = (xy[..., 0] - grid.x[0]) / (grid.x[1] - grid.x[0])
        z = map_coordinates(grid.heights, [rows.ravel(), cols.ravel()], order=1, cval=np.nan).reshape(rows.shape)
        depth = np.where(np.isfinite(z), z, -np.inf)  # no surface: the lips are apart there
        deepest = depth <= depth.min(axis=1, keepdims=True)
        offset = (deepest * across).sum(axis=1) / deepest.sum(axis=1)
        pixel = float(max(abs(grid.x[1] - grid.x[0]), abs(grid.y[1] - grid.y[0])))
        touching = np.isfinite(depth.min(axis=1))  # not where the lips are apart
        offset = offset + 0.5 * pixel * _steeper_flank(z, across, offset, window_mm / 2) * touching
        offset = median_filter(offset, size=int(GROOVE_MEDIAN_MM / step_mm) | 1, mode="nearest")
        offset *= np.clip(np.minimum(u, 1.0 - u) * width / window_mm, 0.0, 1.0)
        if self.groove is not None:
            offset = offset + np.interp(u, np.linspace(0.0, 1.0, len(self.groove)), self.groove)
        return LipSeam(self.right, self.left, self.middle, self.taper_mm, offset)

    def sides(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Which side each point is on and how much that counts.

        Parameters
        ----------
        xy : ndarray, shape (n, 2)

        Returns
        -------
        upper : ndarray of bool, shape (n,)
            Above the seam (towards +y).
        strength : ndarray, shape (n,)
            1 between the corners (along the corner-to-corner line), falling linearly to 0 at ``taper_mm``
            beyond them.
        """
        across, strength = self.across(xy)
        return across > 0, strength

    def across(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """How far each point (n, 2) is above the seam (mm along the up direction; negative: below), shape
        (n,), and how much its side counts (see :meth:`sides`), shape (n,)."""
        width, along, up = self._frame()
        relative = np.asarray(xy, dtype=np.float64) - self.right
        u = relative @ along / width
        v = relative @ up
        seam_v = self._seam_v(np.clip(u, 0.0, 1.0))
        beyond = np.maximum(-u, u - 1.0) * width
        strength = np.clip(1.0 - np.maximum(beyond, 0.0) / max(self.taper_mm, 1e-9), 0.0, 1.0)
        return v - seam_v, strength

    def split_fit(self, start: np.ndarray, end: np.ndarray,
                  fit: Callable[[np.ndarray, np.ndarray], Callable[[np.ndarray], np.ndarray]]
                  ) -> Callable[[np.ndarray], np.ndarray]:
        """A warp ``fit(start, end)`` fitted on each side of the seam and over all, blended point by point.

        Parameters
        ----------
        start, end : ndarray, shape (n, 3)
            Points (face frame) and where they go.
        fit : callable
            ``fit(start, end)`` returns a warp: points (m, 3) to (m, 3).

        Returns
        -------
        callable
            points (m, 3) to (m, 3): a point's own side's warp between the corners, the whole face's beyond.
        """
        whole = fit(start, end)
        upper, strength = self.sides(start[:, :2])
        shared = strength < 0.5  # well past the corners: one piece of skin, in both fits
        pieces = {}
        for side in (True, False):
            member = shared | (upper == side)
            if member.sum() < MIN_PIECE_POINTS or member.all():
                return whole
            try:
                pieces[side] = fit(start[member], end[member])
            except InputError:  # that side's points are degenerate (on one plane): the whole face's warp serves
                return whole

        def warp(points: np.ndarray) -> np.ndarray:
            above, weight = self.sides(points[:, :2])
            out = whole(points)
            near = weight > 0
            own = np.where(above[near, None], pieces[True](points[near]), pieces[False](points[near]))
            out[near] = weight[near, None] * own + (1.0 - weight[near, None]) * out[near]
            return out

        return warp

    def smoother(self, x: np.ndarray, y: np.ndarray
                 ) -> Callable[[list[np.ndarray], np.ndarray, float], tuple[list[np.ndarray], np.ndarray]]:
        """Weighted Gaussian smoothing of images on the grid lines ``x`` (n_cols,), ``y`` (n_rows,) (mm) that
        does not reach across the seam; which side each pixel is on is found once, here.

        The returned ``smooth(channels, weight, sigma) -> (means, cover)`` takes ``channels``, a list of
        (n_rows, n_cols) values (finite where ``weight`` > 0), ``weight`` (n_rows, n_cols) in [0, 1] (0: no
        value) and ``sigma`` (Gaussian sigma in pixels); ``means`` are the channels smoothed, ``cover``
        (n_rows, n_cols) how much of a pixel's neighbourhood (on its own side between the corners) had a
        value, in [0, 1].
        """
        xx, yy = np.meshgrid(x, y)
        upper, strength = self.sides(np.stack([xx.ravel(), yy.ravel()], axis=1))
        upper, strength = upper.reshape(xx.shape), strength.reshape(xx.shape)
        pieces = [(upper == side).astype(np.float64) for side in (True, False)]

        def smooth(channels: list[np.ndarray], weight: np.ndarray, sigma: float):
            def blur(image):
                return cv2.GaussianBlur(image.astype(np.float32), (0, 0), sigma).astype(np.float64)

            weight = np.where(weight > 0, weight, 0.0)
            values = [np.where(weight > 0, channel, 0.0) for channel in channels]
            density_all = blur(weight)
            mean = [blur(v * weight) / np.maximum(density_all, 1e-9) for v in values]
            own_mean = [np.zeros_like(density_all) for _ in values]
            own_cover = np.zeros_like(density_all)
            for piece in pieces:
                density = blur(weight * piece)
                area = blur(piece)
                at = piece > 0
                for k, v in enumerate(values):
                    own_mean[k][at] = (blur(v * weight * piece) / np.maximum(density, 1e-9))[at]
                own_cover[at] = (density / np.maximum(area, 1e-9))[at]
            # no skin of its own side around: not tracked (nothing taken from the other lip)
            means = [strength * o + (1.0 - strength) * m for o, m in zip(own_mean, mean)]
            cover = np.clip(strength * own_cover + (1.0 - strength) * density_all, 0.0, 1.0)
            return means, cover

        return smooth


def _steeper_flank(z: np.ndarray, across: np.ndarray, bottom: np.ndarray, flank_mm: float) -> float:
    """+1 when the groove's upper flank is the steeper one along the mouth, -1 when the lower one is, 0 when
    neither is :data:`STEEPER` times the other (or nothing is known).

    Parameters
    ----------
    z : ndarray, shape (k, m)
        Heights across the seam at ``k`` places along it, at the offsets ``across`` (m,) mm (NaN: no surface).
    bottom : ndarray, shape (k,)
        The groove's deepest offset at each place.
    flank_mm : float
        How far above and below the bottom each flank's steepest rise is looked for; the medians of the
        places' steepest rises are compared (one place's are noisy: on the ICT face the upper/lower ratio
        ranges 0.4-5 with a median of 1.3).

    Where closed lips touch, the groove's deepest point in a frontal scan is on the lip whose flank the
    scanner sees face-on: the other lip overhangs it, its flank a steep face ending at the bottom. On the
    ICT face the upper lip overhangs and the grid vertices within 0.1 mm of the deepest point are on the
    lower lip (13 of 14): with the bottom pixel given to the upper lip, 8 vertices of an opened jaw took the
    upper lip's motion (31 mm off each; 78 % of the error on the lips' line of the jaw's element, 32 % of
    all of it, at 150k points a scan).
    """
    slope = np.gradient(z, across, axis=1)
    offset = across[None, :] - bottom[:, None]
    up = np.where((offset >= 0) & (offset <= flank_mm), slope, np.nan)
    down = np.where((offset <= 0) & (offset >= -flank_mm), -slope, np.nan)
    with np.errstate(all="ignore"):  # a place whose flank has no surface (the lips apart) is not known
        rise_up = np.nanmax(np.where(np.isfinite(up), up, -np.inf), axis=1)
        rise_down = np.nanmax(np.where(np.isfinite(down), down, -np.inf), axis=1)
    known = np.isfinite(rise_up) & np.isfinite(rise_down)
    if not known.any():
        return 0.0
    rise_up, rise_down = float(np.median(rise_up[known])), float(np.median(rise_down[known]))
    return 1.0 if rise_up > STEEPER * rise_down else -1.0 if rise_down > STEEPER * rise_up else 0.0
