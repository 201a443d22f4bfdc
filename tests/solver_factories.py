"""Seeded marker sets and training takes for the solver, validation and refinement tests."""

from __future__ import annotations

import numpy as np

from livebridge.face.basis import Basis
from livebridge.face.markers import MarkerSet


def random_markers(basis: Basis, n_markers: int, rng: np.random.Generator, n_head: int = 0) -> MarkerSet:
    """Markers on random triangles of ``basis``; a face marker's region is the region whose muscles move it most."""
    triangles = rng.choice(len(basis.triangles), size=n_markers + n_head, replace=False)
    barycentric = rng.dirichlet(np.ones(3), size=n_markers + n_head)
    magnitude = np.linalg.norm(basis.elements, axis=2)[:, basis.triangles[triangles]].mean(axis=2)  # (M, n)
    upper = basis.region_mask("upper")
    regions = tuple("upper" if magnitude[upper, k].max() >= magnitude[~upper, k].max() else "lower"
                    for k in range(n_markers + n_head))
    roles = ("face",) * n_markers + ("head",) * n_head
    return MarkerSet(tuple(f"m{i}" for i in range(n_markers + n_head)), triangles, barycentric, regions, roles)


def noisy_training(basis: Basis, rng: np.random.Generator, seed: int, n_markers: int = 64, noise: float = 0.2):
    """Random face markers, the performer's training script on them (no head motion), noisy displacements.

    Draws the markers and then the noise from ``rng``; ``seed`` seeds the performance.

    Returns
    -------
    markers : MarkerSet
    performance : the :func:`livebridge.simulators.performer.perform` result
    observed : ndarray, shape (n_frames, n_markers, 3)
        ``performance.marker_displacements`` plus Gaussian noise of ``noise`` mm.
    """
    from livebridge.simulators.performer import perform

    markers = random_markers(basis, n_markers, rng)
    performance = perform(basis, markers, 1950, seed=seed, script="training", head_motion=False)
    observed = performance.marker_displacements + rng.normal(scale=noise, size=performance.marker_displacements.shape)
    return markers, performance, observed
