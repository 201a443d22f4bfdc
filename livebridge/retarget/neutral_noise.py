"""The neutral scan's own noise, which every element tracked against it shares, taken out of them all.

Every element of a basis built from scans is where the neutral's skin went in one expression. The skin's place in
the neutral is read once, from the neutral scan's image of its pattern, and that image's noise (the scan's
sampling, its points' noise) misplaces the pattern by a field of a few tenths of a mm that is the same in every
element: the flow against each expression starts from the same misplaced skin. The template of the neutral skin
(:mod:`~livebridge.retarget.skin_template`) does not remove it: it is built by warping the expressions back by
motions that carry it, so it lies where the neutral scan put the skin.

What reveals it is the skin an expression leaves still: there, the element's tracked motion is that shared field
plus the expression's own noise. A brow raise leaves the mouth still, a smile the forehead, so at every vertex
some of the scans see it. :func:`neutral_noise` averages, per vertex, the motions of the elements that barely move
it (weighted by how still, :data:`STILL_MM`); :func:`~livebridge.retarget.scans.basis_from_scans` takes that from
every tracked element, where it moves the vertex too.

Measured on the bench's scans (`livebridge bench scans`; 60k points a scan, 16 elements): the tracked flows'
errors on the skin correlate 0.6-0.7 with the mean of the other 15 elements' errors after an 8 mm blur (about
45 % of their low-frequency error is shared); taking out the shared part found from the truth brought the lip
corner's 0.113 to 0.091. Found from the still elements as here (after the still skin's correction, vertex by
vertex): mean relative error of the 16 elements 0.0895 -> 0.0867 (seed 7), 0.0908 -> 0.0886 (seed 8), 0.0912 ->
0.0889 (another face), no element worse; the lip corner 0.113 -> 0.108. The normal part alone gains a fifth of
it, the tangential part four fifths. Taken out in 3D, the neutral's own noise along the normal stays in every
expression as it is in the neutral, instead of each expression cancelling it its own way (elements added together
counted it twice): the expressions' distance from the true expressive surfaces rose by up to 0.004 of the
elements' motion (at most 0.087 at 60k points, 0.080 at 150k).
"""

from __future__ import annotations

import numpy as np

STILL_MM = 0.15
"""An element counts as still at a vertex with a weight ``exp(-|motion|^2 / (2 STILL_MM^2))``: about the flow's
noise on still skin after smoothing (0.1-0.3 mm gave the same figures within 0.0005 of the mean)."""
PRIOR_WEIGHT = 1.0
"""The estimate is shrunk towards no noise as if this many still elements said 0: where few elements are still
it is a noisy mean of few (1 or 3 measured within 0.0007 of the mean at 16 elements)."""
MIN_ELEMENTS = 2
"""With one tracked element nothing is taken out: its own noise and the shared noise cannot be told apart. A few
are enough (the bench's 60k scans, seed 7; mean relative error without -> with): two (brow, lip press) 0.0936 ->
0.0925, three (brow, smile, lip press) 0.0773 -> 0.0761, five 0.0991 -> 0.0973, six of the mouth only 0.0907 ->
0.0898; three of the mouth only (lip corner, lip press, jaw), which leave no skin by the mouth still, the same
within 0.0001."""


def neutral_noise(elements: np.ndarray) -> np.ndarray:
    """The motion shared by every element that is the neutral scan's noise, per vertex, shape (n_vertices, 3).

    ``elements`` (k, n_vertices, 3): the tracked elements on the neutral's grid, mm. Zeros when k is under
    :data:`MIN_ELEMENTS`.
    """
    elements = np.asarray(elements, dtype=np.float64)
    if len(elements) < MIN_ELEMENTS:
        return np.zeros(elements.shape[1:])
    size = np.linalg.norm(elements, axis=2)
    weight = np.exp(-0.5 * (size / STILL_MM) ** 2)
    return np.einsum("kn,knd->nd", weight, elements) / (weight.sum(axis=0) + PRIOR_WEIGHT)[:, None]
