"""Random points on the triangles of a mesh that face a scanner looking along -z, or on all of them
(area-weighted), for the simulated scanners of :mod:`~livebridge.bench.scans` and :mod:`~livebridge.bench.scan_eyes`."""

from __future__ import annotations

import numpy as np

FACING_Z = 0.05
"""A triangle faces the scanner when its unit normal's z is above this."""


def facing_weights(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Each triangle's area (m,) where it faces +z, else 0 (mm², for ``vertices`` (n, 3) in mm)."""
    from livebridge.face.meshio import triangle_areas, triangle_normals

    facing = triangle_normals(vertices, triangles)[:, 2] > FACING_Z
    return np.where(facing, triangle_areas(vertices, triangles), 0.0)


def area_samples(vertices: np.ndarray, triangles: np.ndarray, count: int, rng: np.random.Generator,
                 facing_only: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``count`` points uniform over the area of the triangles facing +z (of all triangles unless
    ``facing_only``): (points (count, 3), the triangle each lies on (count,), its barycentric coordinates there
    (count, 3))."""
    from livebridge.face.meshio import triangle_areas

    weight = facing_weights(vertices, triangles) if facing_only else triangle_areas(vertices, triangles)
    chosen = rng.choice(len(triangles), count, p=weight / weight.sum())
    bary = random_barycentric(rng, (count,))
    return np.einsum("nk,nkd->nd", bary, vertices[triangles[chosen]]), chosen, bary


def triangle_samples(vertices: np.ndarray, triangles: np.ndarray, per_triangle: int, rng: np.random.Generator
                     ) -> np.ndarray:
    """``per_triangle`` points uniform over each of ``triangles`` (t, 3): (t, per_triangle, 3); what a simulated
    scanner judges whether it saw a triangle by."""
    bary = random_barycentric(rng, (len(triangles), per_triangle))
    return np.einsum("tsk,tkd->tsd", bary, vertices[triangles])


def random_barycentric(rng: np.random.Generator, shape: tuple) -> np.ndarray:
    """Barycentric coordinates (*shape, 3) of points uniform over a triangle: two uniform numbers, folded back
    into the triangle where they sum past 1."""
    a, b = rng.random((2, *shape))
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    return np.stack([1 - a - b, a, b], axis=-1)
