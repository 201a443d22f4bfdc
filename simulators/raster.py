"""A compiled z-buffer rasteriser for triangle meshes seen by a pinhole camera (deferred shading).

:func:`rasterize` fills, per pixel, the nearest triangle and its perspective-correct barycentric coordinates
(a small G-buffer); a shader then interpolates whatever per-vertex attributes it needs (normals, texture
coordinates, skin strain) once per visible pixel. Both faces of every triangle are drawn: the side a pixel
sees is ``front[triangle]``, so a shader can darken the inside of an open mesh (the mouth when the lips
part).

Pixel centres are at integer coordinates (as in OpenCV). A pixel belongs to a triangle when its centre is
inside it or on an edge; depth is compared as ``1 / z`` (linear in screen space, so exact at every pixel).
Triangles with a vertex at or behind ``NEAR_MM`` are skipped. The kernels are compiled once per installation
(numba ``cache=True``) and release the GIL.
"""

from __future__ import annotations

import numpy as np
from numba import njit

NEAR_MM = 1.0  # vertices closer to the camera plane than this are not drawn


@njit(cache=True, nogil=True)
def project_vertices(vertices, world2cam, matrix, pixels, depth):
    """Pinhole projection (no distortion) of world points.

    Parameters
    ----------
    vertices : ndarray, shape (n, 3)
        World points, mm.
    world2cam : ndarray, shape (4, 4)
    matrix : ndarray, shape (3, 3)
        Intrinsics ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``.
    pixels : ndarray, shape (n, 2)
        Out: pixel coordinates.
    depth : ndarray, shape (n,)
        Out: camera-frame z, mm.
    """
    fx, fy, cx, cy = matrix[0, 0], matrix[1, 1], matrix[0, 2], matrix[1, 2]
    for i in range(vertices.shape[0]):
        x, y, z = vertices[i, 0], vertices[i, 1], vertices[i, 2]
        xc = world2cam[0, 0] * x + world2cam[0, 1] * y + world2cam[0, 2] * z + world2cam[0, 3]
        yc = world2cam[1, 0] * x + world2cam[1, 1] * y + world2cam[1, 2] * z + world2cam[1, 3]
        zc = world2cam[2, 0] * x + world2cam[2, 1] * y + world2cam[2, 2] * z + world2cam[2, 3]
        depth[i] = zc
        if zc > NEAR_MM:
            pixels[i, 0] = fx * xc / zc + cx
            pixels[i, 1] = fy * yc / zc + cy
        else:
            pixels[i, 0] = np.nan
            pixels[i, 1] = np.nan


@njit(cache=True, nogil=True)
def vertex_normals_into(vertices, triangles, normals):
    """Area-weighted unit vertex normals (the sum of the incident triangles' cross products, normalised).

    Parameters
    ----------
    vertices : ndarray, shape (n_vertices, 3)
    triangles : ndarray of int, shape (n_triangles, 3)
        Counter-clockwise seen from outside.
    normals : ndarray, shape (n_vertices, 3)
        Out.
    """
    normals[:] = 0.0
    for t in range(triangles.shape[0]):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        ux, uy, uz = vertices[b, 0] - vertices[a, 0], vertices[b, 1] - vertices[a, 1], vertices[b, 2] - vertices[a, 2]
        vx, vy, vz = vertices[c, 0] - vertices[a, 0], vertices[c, 1] - vertices[a, 1], vertices[c, 2] - vertices[a, 2]
        nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
        for k in range(3):
            v = triangles[t, k]
            normals[v, 0] += nx
            normals[v, 1] += ny
            normals[v, 2] += nz
    for v in range(normals.shape[0]):
        length = np.sqrt(normals[v, 0] ** 2 + normals[v, 1] ** 2 + normals[v, 2] ** 2)
        if length > 0.0:
            normals[v, 0] /= length
            normals[v, 1] /= length
            normals[v, 2] /= length


@njit(cache=True, nogil=True)
def rasterize(pixels, depth, triangles, ids, bary, inverse_depth, front):
    """Z-buffer the triangles: per pixel the nearest triangle and its barycentric coordinates.

    Parameters
    ----------
    pixels : ndarray, shape (n_vertices, 2)
    depth : ndarray, shape (n_vertices,)
        Camera-frame z of each vertex, mm.
    triangles : ndarray of int, shape (n_triangles, 3)
    ids : ndarray of int32, shape (height, width)
        Out: triangle index per pixel, -1 where none.
    bary : ndarray of float32, shape (height, width, 2)
        Out: perspective-correct barycentric weights of the triangle's first two vertices (the third is
        ``1 - sum``).
    inverse_depth : ndarray of float32, shape (height, width)
        Out: ``1 / z`` of the nearest surface, 0 where none.
    front : ndarray of bool, shape (n_triangles,)
        Out: the camera sees the triangle's outside (counter-clockwise on the sensor, whose y axis points down).
    """
    height, width = ids.shape
    ids[:] = -1
    inverse_depth[:] = 0.0
    for t in range(triangles.shape[0]):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        za, zb, zc = depth[a], depth[b], depth[c]
        if not (za > NEAR_MM and zb > NEAR_MM and zc > NEAR_MM):
            front[t] = False
            continue
        ax, ay = pixels[a, 0], pixels[a, 1]
        bx, by = pixels[b, 0], pixels[b, 1]
        cx, cy = pixels[c, 0], pixels[c, 1]
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        front[t] = area < 0.0  # y down: a counter-clockwise outside turns clockwise on the sensor
        if area == 0.0:
            continue
        x0 = max(int(np.ceil(min(ax, bx, cx))), 0)
        x1 = min(int(np.floor(max(ax, bx, cx))), width - 1)
        y0 = max(int(np.ceil(min(ay, by, cy))), 0)
        y1 = min(int(np.floor(max(ay, by, cy))), height - 1)
        if x0 > x1 or y0 > y1:
            continue
        inv_area = 1.0 / area
        iza, izb, izc = 1.0 / za, 1.0 / zb, 1.0 / zc
        for y in range(y0, y1 + 1):
            for x in range(x0, x1 + 1):
                wa = ((bx - x) * (cy - y) - (by - y) * (cx - x)) * inv_area
                wb = ((cx - x) * (ay - y) - (cy - y) * (ax - x)) * inv_area
                wc = 1.0 - wa - wb
                if wa < 0.0 or wb < 0.0 or wc < 0.0:
                    continue
                iz = wa * iza + wb * izb + wc * izc
                if iz <= inverse_depth[y, x]:
                    continue
                inverse_depth[y, x] = iz
                ids[y, x] = t
                bary[y, x, 0] = wa * iza / iz
                bary[y, x, 1] = wb * izb / iz


class GBuffer:
    """Reusable per-pixel buffers of :func:`rasterize` for one image size and mesh.

    Attributes
    ----------
    ids : ndarray of int32, shape (height, width)
    bary : ndarray of float32, shape (height, width, 2)
    inverse_depth : ndarray of float32, shape (height, width)
    front : ndarray of bool, shape (n_triangles,)
    """

    def __init__(self, size: tuple[int, int], n_triangles: int):
        width, height = size
        self.ids = np.full((height, width), -1, dtype=np.int32)
        self.bary = np.zeros((height, width, 2), dtype=np.float32)
        self.inverse_depth = np.zeros((height, width), dtype=np.float32)
        self.front = np.zeros(n_triangles, dtype=np.bool_)

    def fill(self, pixels: np.ndarray, depth: np.ndarray, triangles: np.ndarray) -> None:
        """Rasterise a mesh (see :func:`rasterize`) into these buffers."""
        rasterize(pixels, depth, triangles, self.ids, self.bary, self.inverse_depth, self.front)
