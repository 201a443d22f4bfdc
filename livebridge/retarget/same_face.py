"""Is an expression scan one muscle's motion on the neutral's face? How far its registered skin lies from the
neutral's surface, against the scan's own noise.

One muscle moves part of the face; the rest (the skull's skin: forehead, temples, the nose's bridge) stays where
the neutral has it, so once registered, most of a one-muscle scan's points lie on the neutral's surface within
the scanner's noise. Another person's scan, or one of the person with another neutral (another day, weight,
swelling), lies off it all over: a rigid registration cannot undo a change of shape. So does a scan that moves
most of the face (several muscles at once). The build would go on and put the difference into the element as
motion, so :func:`another_face` words a warning naming both causes: the gap alone cannot tell them apart.

The gap is the median distance of the registered points from the neutral's surface (point-to-plane at the
nearest neutral vertex, points within :data:`REACH_MM` of it); the noise is the scan's own scatter about local
quadratics (:func:`~livebridge.retarget.surface_fit.noise_level`: 0.25-0.28 for these scans' 0.2 mm noise).
Measured on ICT-FaceKit scans of `livebridge bench scans` (seed 7; gap mm, and over the noise):

- the person's own 16 expressions, 60k points a scan: 0.17-0.34 mm, 0.62-1.26 (the lips' and jaw's the
  largest: more of the face moves); at 150k 0.30-0.34, 1.20-1.23; from textured meshes 0.21 (their samples
  lie on triangles: 0.02 of noise, so the floor :data:`GAP_FLOOR_MM` is the limit there);
- the ICT face under the known warp of `livebridge bench retarget` (other proportions) at 0.1 / 0.2 / 0.3 / 1.0
  of its strength, a neutral scan: 0.34 / 0.51 / 0.61 / 0.83 mm (1.23 / 1.79 / 2.21 / 2.98), a smile on it 0.46 /
  0.67 / 0.76 / 0.96 (1.68 / 2.41 / 2.76 / 3.55);
- the built-in face (another face altogether, its landmarks put on ICT's): 1.03 mm (3.77);
- ICT's own face with 7 elements at once (the jaw opened, both smiles, both brows raised, both eyes closed):
  0.73 mm (2.85), told too. Its 25th percentile (0.35 mm, 1.36) was no better a judge: 1.30 for the warped
  face's neutral, 0.56 for the opened jaw.

So a scan is judged another face when its gap exceeds both :data:`GAP_NOISES` times its noise and
:data:`GAP_FLOOR_MM`: from 0.2-0.3 of the warp's strength on at this noise. A noisier scanner hides smaller
differences (noise 0.5 mm reads about 0.7, so only gaps over 1.4 mm are told).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

GAP_NOISES = 2.0
"""A scan lying farther than this many of its noise levels from the neutral's surface is another face."""
GAP_FLOOR_MM = 0.5
"""... and farther than this (a mesh's samples have almost no noise; its triangles' chords do)."""
REACH_MM = 3.0
"""Only points within this of a neutral vertex count (not the neck or hair beyond the neutral's crop)."""
GAP_POINTS = 8000
"""At most this many points (evenly picked) are measured."""
OFF_NEUTRAL_SHARE = 0.001
"""The neutral's vertices that no expression comes near are told when they are at least this share of it."""


def surface_gap(points: np.ndarray, vertices: np.ndarray, normals: np.ndarray) -> float:
    """The median distance (mm) of ``points`` (n, 3; registered in the face frame) from the surface of the
    neutral's ``vertices`` (m, 3) with unit ``normals`` (m, 3), point-to-plane at the nearest vertex, over the
    points within :data:`REACH_MM` of one; NaN when none is."""
    points = np.asarray(points, dtype=np.float64)[::max(1, len(points) // GAP_POINTS)]
    distance, nearest = cKDTree(vertices).query(points, distance_upper_bound=REACH_MM)
    near = np.isfinite(distance)
    if not near.any():
        return float("nan")
    off = np.einsum("nd,nd->n", points[near] - vertices[nearest[near]], normals[nearest[near]])
    return float(np.median(np.abs(off)))


def gap_limit(noise_mm: float) -> float:
    """The gap (mm) past which a scan of ``noise_mm`` noise is another face: :data:`GAP_NOISES` times its noise,
    at least :data:`GAP_FLOOR_MM` (only that without a noise figure)."""
    return max(GAP_NOISES * noise_mm, GAP_FLOOR_MM) if np.isfinite(noise_mm) else GAP_FLOOR_MM


def another_face(gap_mm: float, noise_mm: float) -> str | None:
    """The warning's words when an expression scan's ``gap_mm`` from the neutral's surface (see
    :func:`surface_gap`) says it is not one muscle's motion on the neutral's face, given the scan's
    ``noise_mm``; None if not."""
    limit = gap_limit(noise_mm)
    if not np.isfinite(gap_mm) or gap_mm <= limit:
        return None
    return (f"registered on the neutral, half its skin lies over {gap_mm:.2f} mm off the neutral's surface, more "
            f"than the {limit:.2f} mm (at least {GAP_FLOOR_MM:g} mm, {GAP_NOISES:g} times its noise, {noise_mm:.2f} "
            "mm) that a one-muscle scan of the neutral's face stays within: is it another person, or the person "
            "with another neutral, or does it move more than one muscle? The element takes the difference as motion")


def neutral_off_expressions(neutral_vertices: np.ndarray, expression_vertices: list, reach_mm: float
                            ) -> np.ndarray:
    """Which of the neutral's grid vertices (n, 3) lie farther than ``reach_mm`` from every point of every
    expression's resampled surface (``expression_vertices``: arrays (m_k, 3), registered in the face frame),
    shape (n,) bool. Each expression lies near the neutral's face but where it moves or has a hole; what no
    expression comes near is not the face the expressions show: something between the scanner and the face in
    the neutral scan (a hand, glasses). The resampled surfaces of the bench's 16 ICT expressions (60k points)
    come within 9.3 mm of every neutral vertex, the opened jaw's within 19.4 mm."""
    far = np.ones(len(neutral_vertices), dtype=bool)
    for vertices in expression_vertices:
        far &= cKDTree(vertices).query(neutral_vertices, distance_upper_bound=reach_mm)[0] > reach_mm
    return far


def off_expressions(far: np.ndarray, neutral_vertices: np.ndarray, reach_mm: float, count: int) -> str | None:
    """The warning's words when the neutral's vertices ``far`` ((n,) bool, :func:`neutral_off_expressions`)
    are a share of it worth telling (:data:`OFF_NEUTRAL_SHARE`; ``count`` expressions), with where they are
    (``neutral_vertices`` (n, 3), face frame: x left, y up, nose tip at the origin); None if not."""
    if far.mean() < OFF_NEUTRAL_SHARE:
        return None
    centre = neutral_vertices[far].mean(axis=0)
    which = "the expression scan's" if count == 1 else f"any of the {count} expression scans'"
    hole = "a hole in the expression scan there, or " if count == 1 else ""
    return (f"{far.mean():.1%} of the neutral's face, around ({centre[0]:.0f}, {centre[1]:.0f}, {centre[2]:.0f}) mm "
            f"from its nose tip (x to its left, y up), lies over {reach_mm:g} mm from {which} surface: {hole}is "
            "something between the scanner and the face in the neutral scan (a hand, glasses, a microphone)? The "
            "elements there are no muscle's motion")
