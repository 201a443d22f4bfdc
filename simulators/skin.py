"""Procedural skin for the face-video simulator: a texture on the neutral face, skin strain, and the shader.

The texture is indexed by a cylindrical parameterisation of the NEUTRAL face (``u``: arc length around the
vertical axis, ``v``: height, both mm), so each skin point keeps its texture when the face deforms: the
texture moves and stretches with the skin. It holds an albedo map (pores, blotches, freckles, and, when
the face's landmarks are known, eyebrows, lips and eyes) and two wrinkle maps (lines along ``u`` and along
``v``). Wrinkles show where the skin is compressed across them: per triangle the stretch of the skin along
``u`` and ``v`` (the columns of the deformation's Jacobian in the parameterisation, deformed over neutral)
is averaged to the vertices; compression along ``v`` (brows raised: the forehead shortens) darkens the lines
along ``u``, and the other way round (corrugator: vertical lines between the brows).

:func:`shade` is the per-pixel shader over :mod:`~livebridge.simulators.raster`'s G-buffer: interpolated
vertex normals, Lambert diffuse plus a Blinn-Phong highlight from one directional light, ambient light, the
textured albedo; the inside of the mesh (seen through parted lips) is dark.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit

TEXEL_MM = 0.25  # texture resolution on the skin
MARGIN_MM = 4.0
RADIUS_MM = 80.0  # u is the angle around the vertical axis times this
MAX_LEVEL = 4  # coarsest pre-filtered texture level (16 texels to one)
COMPRESSION_FULL = 0.18  # relative shortening of the skin at which wrinkles are fully drawn


@dataclass(frozen=True, eq=False)
class SkinTexture:
    """A face's texture maps and each vertex's place in them.

    Attributes
    ----------
    albedo : ndarray of float32, shape (rows, columns)
        Reflectance in [0, 1].
    lines_u, lines_v : ndarray of float32, shape (rows, columns)
        Wrinkle line strength in [0, 1]: lines running along ``u`` (horizontal) and along ``v``.
    vertex_texels : ndarray of float32, shape (n_vertices, 2)
        Each vertex's ``(column, row)`` in the maps.
    """

    albedo: np.ndarray
    lines_u: np.ndarray
    lines_v: np.ndarray
    vertex_texels: np.ndarray

    def level(self, mm_per_pixel: float) -> SkinTexture:
        """The texture pre-filtered (Gaussian pyramid) down to texels no smaller than about half of
        ``mm_per_pixel``, the size of a pixel's footprint on the skin; ``vertex_texels`` scaled to match."""
        steps = int(np.clip(np.floor(np.log2(max(mm_per_pixel, 1e-9) / (2 * TEXEL_MM))), 0, MAX_LEVEL))
        maps = [self.albedo, self.lines_u, self.lines_v]
        for _ in range(steps):
            maps = [cv2.pyrDown(m) for m in maps]
        texels = (self.vertex_texels / 2**steps).astype(np.float32)
        return SkinTexture(*(np.ascontiguousarray(m, dtype=np.float32) for m in maps), texels)


def cylinder_uv(points: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Cylindrical skin coordinates ``(u, v)`` in mm of points ``(n, 3)`` about a vertical axis through
    ``axis (2,)`` = its ``(x, z)``; shape (n, 2)."""
    points = np.asarray(points, dtype=np.float64)
    angle = np.arctan2(points[:, 0] - axis[0], points[:, 2] - axis[1])
    return np.stack([RADIUS_MM * angle, points[:, 1]], axis=1)


def _field(rng: np.random.Generator, shape: tuple[int, int], sigma_mm: float) -> np.ndarray:
    """Smooth zero-mean noise of unit standard deviation and correlation length ``sigma_mm``."""
    noise = rng.standard_normal(shape).astype(np.float32)
    sigma = sigma_mm / TEXEL_MM
    if sigma > 0.3:
        # blurring a coarser grid and resizing is the same field at a fraction of the cost
        factor = max(1, int(sigma // 4))
        small = noise[::factor, ::factor].copy()
        small = cv2.GaussianBlur(small, (0, 0), sigma / factor)
        noise = cv2.resize(small, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    noise -= noise.mean()
    return noise / max(float(noise.std()), 1e-6)


def _lines(rng: np.random.Generator, shape: tuple[int, int], along: int) -> np.ndarray:
    """Thin irregular wrinkle lines (strength in [0, 1]) running along axis ``along`` (1: along u, i.e.
    horizontal lines stacked in v; 0: vertical lines)."""
    rows, columns = shape
    coordinate = (np.arange(rows) if along == 1 else np.arange(columns)) * TEXEL_MM
    coordinate = coordinate[:, None] if along == 1 else coordinate[None, :]
    wobble = _field(rng, shape, 6.0) * 1.2 + _field(rng, shape, 25.0) * 2.5  # mm
    phase = 2 * np.pi * (coordinate + wobble) / 4.0  # a line every ~4 mm
    lines = np.power(0.5 + 0.5 * np.cos(phase), 8).astype(np.float32)
    return lines * np.clip(0.6 + 0.4 * _field(rng, shape, 8.0), 0.0, 1.0)


def _distance_to_polyline(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """Distance of ``points (..., 2)`` to a polyline ``(k, 2)`` and the position along it in [0, 1]."""
    best = np.full(points.shape[:-1], np.inf)
    where = np.zeros(points.shape[:-1])
    lengths = np.linalg.norm(np.diff(polyline, axis=0), axis=1)
    start = np.concatenate([[0.0], np.cumsum(lengths)]) / max(lengths.sum(), 1e-9)
    for k in range(len(polyline) - 1):
        a, b = polyline[k], polyline[k + 1]
        ab = b - a
        s = np.clip(((points - a) @ ab) / max(ab @ ab, 1e-12), 0.0, 1.0)
        distance = np.linalg.norm(points - (a + s[..., None] * ab), axis=-1)
        closer = distance < best
        best = np.where(closer, distance, best)
        where = np.where(closer, start[k] + s * (start[k + 1] - start[k]), where)
    return best, where


def _paint_features(albedo: np.ndarray, rng: np.random.Generator, origin: np.ndarray, features: dict) -> None:
    """Eyebrows, lips and eyes on the albedo, from landmark positions ``features`` (name -> (u, v) mm)."""
    rows, columns = albedo.shape
    uu, vv = np.meshgrid(origin[0] + np.arange(columns) * TEXEL_MM, origin[1] + np.arange(rows) * TEXEL_MM)
    grid = np.stack([uu, vv], axis=-1)
    hair = np.clip(0.5 + 0.5 * _field(rng, albedo.shape, 0.35), 0, 1)
    for side in ("L", "R"):
        names = [f"brow_inner_{side}", f"brow_middle_{side}", f"brow_outer_{side}"]
        if all(n in features for n in names):
            brow = np.array([features[n] for n in names]) + np.array([0.0, 2.0])
            distance, along = _distance_to_polyline(grid, brow)
            half = 4.5 - 2.5 * along  # thick at the inner end, thin at the tail
            cover = np.clip((half - distance) / 1.2, 0.0, 1.0) * (0.55 + 0.45 * hair)
            albedo *= 1.0 - 0.75 * cover
        corners = [f"eye_inner_{side}", f"eye_outer_{side}"]
        if all(n in features for n in corners):
            inner, outer = (np.asarray(features[n]) for n in corners)
            centre = 0.5 * (inner + outer)
            half_width = 0.5 * np.linalg.norm(outer - inner)
            opening = np.square((uu - centre[0]) / half_width) + np.square((vv - centre[1]) / (0.32 * half_width))
            radius = np.hypot(uu - centre[0], vv - centre[1])
            eye = np.where(radius < 2.0, 0.05, np.where(radius < 5.5, 0.3 + 0.1 * hair, 0.85))
            blend = np.clip((1.0 - opening) / 0.15, 0.0, 1.0)
            albedo[:] = albedo * (1 - blend) + eye * blend
    lips = ["mouth_corner_L", "lip_upper_outer", "mouth_corner_R", "lip_lower_outer"]
    if all(n in features for n in lips):
        left, top, right, bottom = (np.asarray(features[n]) for n in lips)
        centre_u = 0.5 * (left[0] + right[0])
        half_width = 0.5 * abs(left[0] - right[0])
        mid = 0.5 * (left[1] + right[1])
        across = np.clip(1.0 - np.square((uu - centre_u) / half_width), 0.0, None)
        upper = mid + (top[1] - mid) * np.sqrt(across)
        lower = mid + (bottom[1] - mid) * np.sqrt(across)
        inside = np.minimum(upper - vv, vv - lower)
        albedo *= 1.0 - 0.3 * np.clip(inside / 1.0, 0.0, 1.0)


def make_skin(neutral: np.ndarray, seed: int = 0, features: dict[str, np.ndarray] | None = None) -> SkinTexture:
    """A procedural skin for a face.

    Parameters
    ----------
    neutral : ndarray, shape (n_vertices, 3)
        The neutral face, mm, +y up, +z out of the face.
    seed : int
    features : dict of str to ndarray (3,), optional
        Landmark positions on the neutral face (``brow_inner_L`` .., ``eye_inner_L`` .., ``mouth_corner_L``,
        ``lip_upper_outer``, ``lip_lower_outer``): eyebrows, eyes and lips are painted where given.

    Returns
    -------
    SkinTexture
    """
    neutral = np.asarray(neutral, dtype=np.float64)
    low, high = neutral.min(axis=0), neutral.max(axis=0)
    axis = np.array([0.5 * (low[0] + high[0]), 0.5 * (low[2] + high[2])])
    uv = cylinder_uv(neutral, axis)
    origin = uv.min(axis=0) - MARGIN_MM
    shape = tuple(int(np.ceil(v)) + 1 for v in ((uv.max(axis=0) + MARGIN_MM - origin) / TEXEL_MM)[::-1])
    rng = np.random.default_rng([int(seed), 41])
    albedo = 0.72 + 0.035 * _field(rng, shape, 18.0) + 0.03 * _field(rng, shape, 3.0) + 0.04 * _field(rng, shape, 0.35)
    _freckles(albedo, rng)
    if features:
        places = {name: cylinder_uv(np.asarray(point)[None], axis)[0] for name, point in features.items()}
        _paint_features(albedo, rng, origin, places)
    texels = ((uv - origin) / TEXEL_MM).astype(np.float32)
    return SkinTexture(np.clip(albedo, 0.0, 1.0).astype(np.float32), _lines(rng, shape, 1), _lines(rng, shape, 0),
                       texels)


def _freckles(albedo: np.ndarray, rng: np.random.Generator) -> None:
    """Small dark spots (0.4 to 1.5 mm) scattered over the skin, in place."""
    rows, columns = albedo.shape
    count = int(rows * columns * TEXEL_MM**2 / 60.0)  # one per ~60 mm^2
    centres = rng.uniform([0, 0], [columns, rows], size=(count, 2))
    radii = rng.uniform(0.4, 1.5, size=count) / TEXEL_MM
    darkness = rng.uniform(0.12, 0.3, size=count)
    spots = np.zeros_like(albedo)
    for (x, y), radius, dark in zip(centres, radii, darkness):
        cv2.circle(spots, (int(x * 4), int(y * 4)), int(radius * 4), float(dark), -1, cv2.LINE_AA, shift=2)
    albedo *= 1.0 - cv2.GaussianBlur(spots, (0, 0), 0.8)


def strain_reference(neutral: np.ndarray, triangles: np.ndarray, texels: np.ndarray) -> tuple[np.ndarray, ...]:
    """What :func:`strain_into` compares against: per triangle the inverse of its texel edge matrix
    ``(n_triangles, 2, 2)`` and the neutral lengths of ``dP/du`` and ``dP/dv`` ``(n_triangles, 2)``; a
    degenerate triangle gets zeros (it never shows strain)."""
    corner = np.asarray(texels, dtype=np.float64)[triangles]  # (T, 3, 2)
    edges_uv = np.stack([corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0]], axis=2)  # (T, 2, 2): columns
    determinant = np.linalg.det(edges_uv)
    ok = np.abs(determinant) > 1e-6
    inverse = np.zeros_like(edges_uv)
    inverse[ok] = np.linalg.inv(edges_uv[ok])
    p = neutral[triangles]
    edges = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]], axis=2)  # (T, 3, 2)
    jacobian = edges @ inverse  # (T, 3, 2)
    lengths = np.linalg.norm(jacobian, axis=1)
    lengths[~ok] = 0.0
    return inverse, lengths


@njit(cache=True, nogil=True)
def strain_into(vertices, triangles, inverse, neutral_lengths, compression, counts):
    """Per-vertex skin compression along ``u`` and ``v`` (0: none; 1: shortened by
    :data:`COMPRESSION_FULL` or more), the mean over the incident triangles.

    Parameters
    ----------
    vertices : ndarray, shape (n_vertices, 3)
        The deformed face (any rigid pose).
    triangles : ndarray of int, shape (n_triangles, 3)
    inverse, neutral_lengths : see :func:`strain_reference`
    compression : ndarray of float32, shape (n_vertices, 2)
        Out.
    counts : ndarray, shape (n_vertices,)
        Scratch.
    """
    compression[:] = 0.0
    counts[:] = 0.0
    for t in range(triangles.shape[0]):
        if neutral_lengths[t, 0] <= 0.0:
            continue
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        for column in range(2):
            length2 = 0.0
            for d in range(3):
                e1 = vertices[b, d] - vertices[a, d]
                e2 = vertices[c, d] - vertices[a, d]
                j = e1 * inverse[t, 0, column] + e2 * inverse[t, 1, column]
                length2 += j * j
            shortening = 1.0 - np.sqrt(length2) / neutral_lengths[t, column]
            value = min(max(shortening / COMPRESSION_FULL, 0.0), 1.0)
            for k in range(3):
                compression[triangles[t, k], column] += value
        for k in range(3):
            counts[triangles[t, k]] += 1.0
    for v in range(compression.shape[0]):
        if counts[v] > 0:
            compression[v, 0] /= counts[v]
            compression[v, 1] /= counts[v]


@njit(cache=True, nogil=True)
def _sample(texture, x, y):
    """Bilinear sample of ``texture (rows, columns)`` at ``(x, y)`` texels, clamped at the border."""
    rows, columns = texture.shape
    x = min(max(x, 0.0), columns - 1.001)
    y = min(max(y, 0.0), rows - 1.001)
    x0, y0 = int(x), int(y)
    fx, fy = x - x0, y - y0
    top = texture[y0, x0] * (1 - fx) + texture[y0, x0 + 1] * fx
    bottom = texture[y0 + 1, x0] * (1 - fx) + texture[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy


@njit(cache=True, nogil=True)
def shade(ids, bary, front, triangles, normals, texels, compression, albedo, lines_u, lines_v, light, halfway,
          lighting, background, out):
    """Shade the G-buffer into a float image (grey levels before noise, not clipped).

    Parameters
    ----------
    ids, bary, front : the G-buffer of :func:`~livebridge.simulators.raster.rasterize`
    triangles : ndarray of int, shape (n_triangles, 3)
    normals : ndarray, shape (n_vertices, 3)
        Unit vertex normals, world frame.
    texels : ndarray of float32, shape (n_vertices, 2)
    compression : ndarray of float32, shape (n_vertices, 2)
    albedo, lines_u, lines_v : ndarray of float32, shape (rows, columns)
    light : ndarray, shape (3,)
        Unit direction towards the light, world frame.
    halfway : ndarray, shape (3,)
        Unit Blinn-Phong halfway vector between ``light`` and the direction to the camera.
    lighting : ndarray, shape (6,)
        ``(gain, intensity, ambient, specular, shininess, wrinkle)``: grey level of a white surface fully lit
        (exposure included), the light's intensity, the ambient share, the highlight's strength and exponent,
        the darkening of fully drawn wrinkles.
    background : float
        Grey level where no surface is.
    out : ndarray of float32, shape (height, width)
    """
    gain, intensity, ambient, specular, shininess, wrinkle = (lighting[0], lighting[1], lighting[2], lighting[3],
                                                              lighting[4], lighting[5])
    cutoff = np.exp(np.log(1e-3) / shininess)
    height, width = ids.shape
    for y in range(height):
        for x in range(width):
            t = ids[y, x]
            if t < 0:
                out[y, x] = background
                continue
            if not front[t]:
                out[y, x] = gain * ambient * 0.12  # the inside of the mouth
                continue
            wa, wb = bary[y, x, 0], bary[y, x, 1]
            wc = 1.0 - wa - wb
            a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
            nx = wa * normals[a, 0] + wb * normals[b, 0] + wc * normals[c, 0]
            ny = wa * normals[a, 1] + wb * normals[b, 1] + wc * normals[c, 1]
            nz = wa * normals[a, 2] + wb * normals[b, 2] + wc * normals[c, 2]
            length = np.sqrt(nx * nx + ny * ny + nz * nz)
            if length > 0:
                nx, ny, nz = nx / length, ny / length, nz / length
            tx = wa * texels[a, 0] + wb * texels[b, 0] + wc * texels[c, 0]
            ty = wa * texels[a, 1] + wb * texels[b, 1] + wc * texels[c, 1]
            cu = wa * compression[a, 0] + wb * compression[b, 0] + wc * compression[c, 0]
            cv = wa * compression[a, 1] + wb * compression[b, 1] + wc * compression[c, 1]
            reflectance = _sample(albedo, tx, ty)
            if cu > 0.0 or cv > 0.0:
                folds = cv * _sample(lines_u, tx, ty) + cu * _sample(lines_v, tx, ty)
                reflectance *= 1.0 - wrinkle * min(folds, 1.0)
            diffuse = max(nx * light[0] + ny * light[1] + nz * light[2], 0.0)
            value = gain * reflectance * (ambient + intensity * diffuse)
            highlight = nx * halfway[0] + ny * halfway[1] + nz * halfway[2]
            if diffuse > 0.0 and highlight > cutoff:  # below the cutoff the highlight is < 1e-3 of its peak
                value += gain * intensity * specular * np.exp(shininess * np.log(highlight))
            out[y, x] = value
