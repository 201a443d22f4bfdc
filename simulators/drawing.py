"""How the simulated cameras' images are drawn: anti-aliased discs (markers, LEDs, highlights), a cached
background moved with the head, the dark shaded face behind the markers, and sensor noise read from
pre-generated tiles. Shared by the marker rig (:mod:`~livebridge.simulators.rig`) and the face video
(:mod:`~livebridge.simulators.face_video`).

An image is drawn by three compiled kernels: the moved cached background (:func:`shift_into`), the discs
(:func:`_blend_discs`) and the noise (:func:`_add_noise`). They repeat the numpy formulation's operations in
the same order (no fast-math), so images are bit-identical to it; tests/test_rig.py checks them against it.
Their row loops index with unsigned integers: numba then leaves out its negative-index fix-up, and they
compile to vector code.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numba import njit, uint64

from livebridge.calibration.cameras import Camera
from livebridge.face.meshio import triangle_normals
from livebridge.geometry.transforms import apply


def render_discs(image: np.ndarray, centers: np.ndarray, radii: np.ndarray, levels: np.ndarray) -> None:
    """Draw anti-aliased bright discs in place (alpha-blended towards ``levels``), one after the other.

    Coverage of a pixel is ``clip(radius + 0.5 - distance, 0, 1)`` from the pixel centre (integer pixel
    coordinates are pixel centres, as in OpenCV). Motion blur: pass several ``centers`` per disc.

    Parameters
    ----------
    image : ndarray of uint8, shape (height, width)
    centers : ndarray, shape (n, 2) or (n, n_samples, 2)
        Disc centres in pixels; with samples, the disc is averaged over the sample positions.
    radii : ndarray, shape (n,)
    levels : ndarray, shape (n,)
        Grey level of a fully covered pixel.
    """
    if len(centers) == 0:
        return
    centers = np.asarray(centers, dtype=np.float64)
    if centers.ndim == 2:  # one sample per disc: it is the disc's mean position
        centers, mid, extent = centers[:, None, :], centers, 0.0
    else:
        mid = centers.mean(axis=1)  # (n, 2)
        extent = np.abs(centers - mid[:, None]).max(axis=(1, 2))
    radii = np.ascontiguousarray(radii, dtype=np.float64)
    # each disc its own patch: a covered pixel lies within radius + 0.5 of a sample, a sample within extent + 0.5
    # of the patch centre (a pixel no disc covers keeps its value, so the patch size does not change the image)
    halves = np.ceil(radii + extent).astype(np.int64) + 1
    _blend_discs(image, np.ascontiguousarray(centers), np.rint(mid).astype(np.int64), halves, radii,
                 np.ascontiguousarray(levels, dtype=np.float64))


@njit(cache=True, nogil=True)
def _blend_discs(image, centers, corners, halves, radii, levels):
    """The kernel of :func:`render_discs`: disc ``k`` (sample centres ``centers[k]``, shape (n_samples, 2)) in
    the patch of half-width ``halves[k]`` around pixel ``corners[k]``, after disc ``k - 1``. Offsets are taken
    from the patch centre, as in the numpy formulation, for the same rounding."""
    height, width = image.shape
    n_samples = centers.shape[1]
    for k in range(centers.shape[0]):
        cx, cy, half = corners[k, 0], corners[k, 1], halves[k]
        reach, level = radii[k] + 0.5, levels[k]
        for y in range(max(cy - half, 0), min(cy + half + 1, height)):
            for x in range(max(cx - half, 0), min(cx + half + 1, width)):
                alpha = 0.0
                for s in range(n_samples):
                    fx = (cx - centers[k, s, 0]) + (x - cx)
                    fy = (cy - centers[k, s, 1]) + (y - cy)
                    alpha += min(max(reach - math.sqrt(fy * fy + fx * fx), 0.0), 1.0)
                if n_samples > 1:  # the mean; x / 1 is x, and a division per pixel is not free
                    alpha /= n_samples
                if alpha > 0.0:  # an uncovered pixel keeps its value exactly, as in the blend below
                    value = float(image[y, x])
                    image[y, x] = int(min(max(value + alpha * (level - value) + 0.5, 0.0), 255.0))


@njit(cache=True, nogil=True)
def shift_into(out, background, dx, dy, fill):
    """``out`` = ``background`` moved right by ``dx`` and down by ``dy`` whole pixels, ``fill`` where nothing
    moves in.

    Parameters
    ----------
    out, background : ndarray of uint8, shape (height, width)
    """
    height, width = out.shape
    for y in range(height):
        row, source = uint64(y), uint64(max(y - dy, 0))
        lo, hi = (max(dx, 0), min(width + dx, width)) if 0 <= y - dy < height else (width, width)
        for x in range(lo):
            out[row, uint64(x)] = fill
        for x in range(hi, width):
            out[row, uint64(x)] = fill
        for x in range(lo, hi):
            out[row, uint64(x)] = background[source, uint64(x - dx)]


@njit(cache=True, nogil=True)
def _add_noise(image, noise, ox, oy):
    """Add the noise layers (see :class:`NoiseTiles`) read from ``(ox, oy)`` to ``image`` in place, saturating.

    Parameters
    ----------
    image : ndarray of uint8, shape (height, width)
    noise : ndarray of int8, shape (n_layers, >= oy + height, >= ox + width)
    """
    height, width = image.shape
    for layer in range(noise.shape[0]):
        for y in range(height):
            row, tile_row = uint64(y), uint64(oy + y)
            for x in range(width):
                # a signed saturating add, which LLVM makes a vector instruction of: the pixel moved to int8 by
                # flipping its top bit (x - 128), the sum clamped to int8, the bit flipped back
                moved = np.int16(np.int8(image[row, uint64(x)] ^ np.uint8(0x80)))
                total = moved + np.int16(noise[layer, tile_row, uint64(ox + x)])
                total = min(max(total, np.int16(-128)), np.int16(127))
                image[row, uint64(x)] = np.uint8(np.int8(total)) ^ np.uint8(0x80)


def shaded_face(camera: Camera, vertices: np.ndarray, triangles: np.ndarray, face_level: float,
                 ambient_level: float) -> np.ndarray:
    """The dark shaded face seen by ``camera`` (painter's algorithm, Lambert lit from the camera).

    Returns
    -------
    ndarray of float32, shape (height, width)
    """
    width, height = camera.size
    image = np.full((height, width), ambient_level, dtype=np.float32)
    pixels = camera.project(vertices)
    cam_points = apply(camera.world2cam, vertices)
    normals = triangle_normals(vertices, triangles)
    centroids = vertices[triangles].mean(axis=1)
    to_camera = camera.center - centroids
    to_camera /= np.linalg.norm(to_camera, axis=1, keepdims=True)
    lambert = np.einsum("nd,nd->n", normals, to_camera)
    depth = cam_points[triangles, 2].mean(axis=1)
    visible = (lambert > 0) & (depth > 0) & np.isfinite(pixels[triangles]).all(axis=(1, 2))
    shade = ambient_level + (face_level - ambient_level) * (0.35 + 0.65 * lambert)
    fixed = np.rint(pixels * 16).astype(np.int32)  # 4 fractional bits
    for tri in np.flatnonzero(visible)[np.argsort(-depth[visible])]:
        cv2.fillConvexPoly(image, fixed[triangles[tri]], float(shade[tri]), lineType=cv2.LINE_8, shift=4)
    return cv2.GaussianBlur(image, (0, 0), 1.2)


class NoiseTiles:
    """Pre-generated zero-mean noise in whole grey levels, read at a random offset per frame.

    Kept as int8 layers whose sum is the noise, each layer of the noise's sign, added to an image one after the
    other with saturation: the same as adding the positive part and subtracting the negative part, each
    saturating, in half the memory of two uint8 tiles (one layer unless the noise reaches 128 grey levels).

    Attributes
    ----------
    layers : ndarray of int8, shape (n_layers, height + PAD, width + PAD)
    """

    PAD = 97

    def __init__(self, size: tuple[int, int], sigma: float, seed: int):
        width, height = size
        rng = np.random.default_rng([int(seed), 13])
        noise = rng.normal(0.0, sigma, size=(height + self.PAD, width + self.PAD)).astype(np.float32)
        rest = np.clip(np.rint(noise), -255, 255).astype(np.int16)  # beyond 255 a uint8 pixel saturates anyway
        layers = [np.clip(rest, -127, 127)]
        while (rest := rest - layers[-1]).any():
            layers.append(np.clip(rest, -127, 127))
        self.layers = np.stack(layers).astype(np.int8)

    def apply(self, image: np.ndarray, rng: np.random.Generator) -> None:
        """Add noise to ``image`` (uint8, shape (height, width)) in place, read at an offset drawn from ``rng``."""
        ox, oy = rng.integers(0, self.PAD, size=2)
        _add_noise(image, self.layers, int(ox), int(oy))
