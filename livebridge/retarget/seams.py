"""The lips' seam: where a face's skin is cut, so that motion is carried, smoothed and warped on each side apart.

Closed lips touch along a line; an opened jaw takes the lower lip 20 mm or more away from the upper one, so
two neutral skin points a millimetre apart across that line move very differently. A warp or a smoothing
over the whole face (a spline through control points, a Gaussian over the tracked skin) averages them and
drags each lip towards the other. Here the seam is the curve through the mouth corners and between the
inner lip landmarks (a parabola in the face frame's x-y: the normalised face looks along +z, +y up); every
such operation is done once on each side of it and once over the whole face, and a point takes its own
side's result between the mouth corners, the whole face's beyond them (a linear taper over
:data:`TAPER_MM` past each corner: the cheeks are one piece of skin).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

TAPER_MM = 6.0
"""Past a mouth corner, a point's own side counts fully at the corner and not at all this far beyond it."""
CORNERS = ("mouth_corner_R", "mouth_corner_L")
INNER_LIPS = ("lip_upper_inner", "lip_lower_inner")
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
    """

    right: np.ndarray
    left: np.ndarray
    middle: np.ndarray
    taper_mm: float = TAPER_MM

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
        width = float(np.linalg.norm(self.left - self.right))
        along = (self.left - self.right) / width
        up = np.array([-along[1], along[0]])
        if up[1] < 0:
            up = -up
        relative = np.asarray(xy, dtype=np.float64) - self.right
        u = relative @ along / width
        v = relative @ up
        u_mid = float(np.clip((self.middle - self.right) @ along / width, 0.05, 0.95))
        v_mid = float((self.middle - self.right) @ up)
        inside = np.clip(u, 0.0, 1.0)
        seam_v = v_mid * inside * (1.0 - inside) / (u_mid * (1.0 - u_mid))
        beyond = np.maximum(-u, u - 1.0) * width
        strength = np.clip(1.0 - np.maximum(beyond, 0.0) / max(self.taper_mm, 1e-9), 0.0, 1.0)
        return v > seam_v, strength

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
            pieces[side] = fit(start[member], end[member])

        def warp(points: np.ndarray) -> np.ndarray:
            above, weight = self.sides(points[:, :2])
            out = whole(points)
            near = weight > 0
            own = np.where(above[near, None], pieces[True](points[near]), pieces[False](points[near]))
            out[near] = weight[near, None] * own + (1.0 - weight[near, None]) * out[near]
            return out

        return warp

    def smoothed(self, x: np.ndarray, y: np.ndarray, channels: list[np.ndarray], weight: np.ndarray,
                 sigma: float) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
        """Weighted Gaussian smoothing of image channels that does not reach across the seam.

        Parameters
        ----------
        x, y : ndarray, shape (n_cols,), (n_rows,)
            The images' grid lines, mm.
        channels : list of ndarray, shape (n_rows, n_cols)
            Values (finite where ``weight`` > 0).
        weight : ndarray, shape (n_rows, n_cols)
            In [0, 1] (0: no value).
        sigma : float
            Gaussian sigma in pixels.

        Returns
        -------
        sums : list of ndarray, shape (n_rows, n_cols)
            Each channel's smoothed value times ``density``.
        density : ndarray, shape (n_rows, n_cols)
            The smoothed weight that ``sums`` are relative to.
        cover : ndarray, shape (n_rows, n_cols)
            How much of a pixel's neighbourhood (on its own side between the corners) had a value, in [0, 1].
        """
        xx, yy = np.meshgrid(x, y)
        upper, strength = self.sides(np.stack([xx.ravel(), yy.ravel()], axis=1))
        upper, strength = upper.reshape(xx.shape), strength.reshape(xx.shape)

        def blur(image):
            return cv2.GaussianBlur(image.astype(np.float32), (0, 0), sigma).astype(np.float64)

        weight = np.where(weight > 0, weight, 0.0)
        values = [np.where(weight > 0, channel, 0.0) for channel in channels]
        density_all = blur(weight)
        mean = [blur(v * weight) / np.maximum(density_all, 1e-9) for v in values]
        cover = density_all.copy()
        own_mean = [np.zeros_like(density_all) for _ in values]
        own_cover = np.zeros_like(density_all)
        for side in (True, False):
            piece = (upper == side).astype(np.float64)
            density = blur(weight * piece)
            area = blur(piece)
            at = upper == side
            for k, v in enumerate(values):
                own_mean[k][at] = (blur(v * weight * piece) / np.maximum(density, 1e-9))[at]
            own_cover[at] = (density / np.maximum(area, 1e-9))[at]
        has_own = own_cover > 1e-6
        blend = np.where(has_own, strength, 0.0)
        sums = [blend * o + (1.0 - blend) * m for o, m in zip(own_mean, mean)]
        cover = np.clip(blend * own_cover + (1.0 - blend) * cover, 0.0, 1.0)
        return sums, np.ones_like(cover), cover
