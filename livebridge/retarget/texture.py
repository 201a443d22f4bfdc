"""Colour from a textured scan mesh: image maps on texture coordinates, sampled into coloured points.

Most face scanners (structured light, photogrammetry, 3dMD-style stereo rigs) write a mesh with one or more
texture images (OBJ ``vt`` coordinates and an MTL file's ``map_Kd``; PLY ``texcoord`` and ``TextureFile``) rather
than a colour per vertex. The skin's pattern, which the skin tracking of :mod:`~livebridge.retarget.scans`
follows, is in those images at a finer resolution than the mesh's vertices (a vertex every 0.5-2 mm, a texel
every 0.05-0.3 mm), so per-vertex colours would blur it away. Instead the textured surface is sampled densely:
every triangle is split into ``n^2`` equal sub-triangles (``n = ceil(sqrt(area) / spacing)``: a point per
``spacing^2`` of surface), each sub-triangle's centroid is a point, and its colour is the texture's at its
texture coordinates, the image first blurred to the samples' footprint where its texels are much finer (pores
finer than the samples would alias into false pattern). What the rest of the pipeline sees is a coloured point
cloud with a point every ``spacing`` mm.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path, PureWindowsPath

import numpy as np

from livebridge.errors import InputError
from livebridge.face.meshio import triangle_areas
from livebridge.retarget.mesh_samples import SAMPLE_SPACING_MM, surface_samples

ANTI_ALIAS_TEXELS = 2.0
"""The texture is blurred before it is sampled where a sample spacing spans more than this many texels."""
LOOKUP_COLUMNS = 1024
"""Texture lookups go through OpenCV's remap in rows of this many samples (its maps are images)."""


@dataclass(frozen=True, eq=False)
class Texture:
    """Texture images on a triangle mesh.

    Attributes
    ----------
    uv : ndarray, shape (n_triangles, 3, 2)
        Texture coordinates of each triangle's corners (OBJ convention: u right, v up, the image in [0, 1]^2).
    image_index : ndarray of int, shape (n_triangles,)
        Which of ``images`` each triangle shows; -1: none (no texture coordinates or no image).
    images : tuple of ndarray, each shape (height, width, 3)
        RGB, row 0 at the top: uint8 or uint16 as the file holds it (its full scale is 1), or floats in [0, 1]
        (a photogrammetry texture of 8192 x 8192 texels takes 200 MB as bytes, 800 MB as floats).
    names : tuple of str
        The image files, for messages.
    """

    uv: np.ndarray
    image_index: np.ndarray
    images: tuple
    names: tuple


def read_materials(mtl: Path, obj: Path) -> dict[str, Path]:
    """``{material: image}`` from the ``newmtl`` / ``map_Kd`` lines of an MTL file (image paths relative to it).

    ``obj`` is the OBJ that named the MTL file (named in the error when the MTL file is missing).
    """
    try:
        text = mtl.read_text(encoding="utf-8-sig", errors="replace")
    except OSError:
        raise InputError(f"its material file {mtl.name} (mtllib) is not there: put it next to the OBJ, or remove "
                         "the mtllib line to read the scan without colour", obj, "mtllib") from None
    images, current = {}, None
    for line in text.splitlines():
        parts = line.strip().split(maxsplit=1)
        if len(parts) < 2:
            continue
        if parts[0] == "newmtl":
            current = parts[1].strip()
        elif parts[0] == "map_Kd" and current is not None:
            images[current] = image_path(mtl.parent, _map_file(parts[1]))
    return images


_MAP_OPTION_ARGUMENTS = {"-blendu": 1, "-blendv": 1, "-bm": 1, "-boost": 1, "-cc": 1, "-clamp": 1, "-imfchan": 1,
                         "-mm": 2, "-o": 3, "-s": 3, "-t": 3, "-texres": 1}
"""The most words each ``map_Kd`` option takes (-o, -s and -t take 1 to 3 numbers)."""
_NUMERIC_OPTIONS = ("-bm", "-boost", "-mm", "-o", "-s", "-t", "-texres")


def _map_file(text: str) -> str:
    """The file name of a ``map_Kd`` statement, after its options (``-s 1 1 1``, ``-clamp on`` ...)."""
    words = text.split()
    k = 0
    while k < len(words) - 1 and words[k] in _MAP_OPTION_ARGUMENTS:
        option, k = words[k], k + 1
        for _ in range(_MAP_OPTION_ARGUMENTS[option]):
            if k >= len(words) - 1 or (option in _NUMERIC_OPTIONS and not _NUMBER.fullmatch(words[k])):
                break
            k += 1
    return " ".join(words[k:])


_NUMBER = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?")


def image_path(folder: Path, name: str) -> Path:
    """Where the texture image ``name`` that a file in ``folder`` names is: relative to ``folder``, Windows
    separators read as such; a name not found there (an absolute path on the machine that made the scan) falls
    back to its bare file name in ``folder``."""
    named = folder / name.replace("\\", "/")
    if named.is_file():
        return named
    bare = folder / PureWindowsPath(name).name
    return bare if bare.is_file() else named


def read_image(path: Path, source: Path, field: str,
               remedy: str = "put it next to the material file, or remove the mtllib line to read the scan "
                             "without colour") -> np.ndarray:
    """An image file as RGB (height, width, 3), uint8 or uint16 as stored (floats kept as they are); an error
    names ``source`` (the file that named it) and ``field`` when it is missing (saying ``remedy``: how to go on)
    or not an image."""
    import cv2

    if not path.is_file():
        raise InputError(f"texture image {path.name} is not there (looked in {path.parent}): {remedy}", source,
                         field)
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None or image.ndim not in (2, 3) or image.size == 0:
        raise InputError(f"texture image {path.name} could not be read as an image", source, field)
    if image.ndim == 2:
        return np.repeat(image[..., None], 3, axis=2)
    return np.ascontiguousarray(image[..., 2::-1] if image.shape[2] >= 3 else np.repeat(image[..., :1], 3, axis=2))


def _as_float(image: np.ndarray) -> np.ndarray:
    """``image`` as float32 in [0, 1] (integers over their type's maximum)."""
    scale = float(np.iinfo(image.dtype).max) if np.issubdtype(image.dtype, np.integer) else 1.0
    return image.astype(np.float32) / np.float32(scale)


def sample_textured(points: np.ndarray, triangles: np.ndarray, texture: Texture, spacing: float | None = None,
                    keep: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Points every ``spacing`` mm over a textured mesh and their colours.

    ``points`` (n_points, 3), ``triangles`` (n_triangles, 3), ``spacing`` and ``keep`` as in
    :func:`~livebridge.retarget.mesh_samples.surface_samples`; ``texture`` on those triangles.

    Returns
    -------
    samples : ndarray, shape (n_samples, 3)
    colours : ndarray, shape (n_samples, 3)
        RGB in [0, 1]; NaN where the triangle has no texture.
    """
    spacing = SAMPLE_SPACING_MM if spacing is None else spacing
    samples, owner, bary = surface_samples(points, triangles, spacing, keep)
    uv = np.einsum("sk,skd->sd", bary, texture.uv[owner])
    chosen = np.flatnonzero(keep) if keep is not None else np.arange(len(triangles))
    area = triangle_areas(points, triangles[chosen])
    colours = np.full((len(samples), 3), np.nan)
    for index, image in enumerate(texture.images):
        mine = texture.image_index[owner] == index
        if mine.any():
            on_image = texture.image_index[chosen] == index
            own_uv = texture.uv[chosen[on_image]]
            footprint = spacing / _texel_mm(area[on_image], own_uv, image.shape)
            colours[mine] = _lookup(_blurred(image, footprint, own_uv), uv[mine])
    return samples, colours


def _texel_mm(area: np.ndarray, uv: np.ndarray, shape: tuple) -> float:
    """The median size (mm) of one texel of an image of ``shape`` on triangles of ``area`` (k,) mm^2 with
    texture coordinates ``uv`` (k, 3, 2) in it."""
    uv = uv * np.array([shape[1], shape[0]])
    d1, d2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    texels = 0.5 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    fine = (texels > 0) & (area > 0)
    return float(np.sqrt(np.median(area[fine] / texels[fine]))) if fine.any() else 1.0


def _coverage(uv: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The texels (height, width) uint8 1/0 that triangles with texture coordinates ``uv`` (k, 3, 2) cover (a
    blur normalised by them leaves the texels just outside a chart, which a lookup at its edge reads, an average
    of the chart's own)."""
    import cv2

    height, width = shape
    corners = np.round(np.stack([uv[..., 0] * width - 0.5, (1.0 - uv[..., 1]) * height - 0.5], axis=-1))
    mask = np.zeros((height, width), np.uint8)
    cv2.fillPoly(mask, list(corners.astype(np.int32)), 1)
    return mask


def _blurred(image: np.ndarray, footprint_texels: float, uv: np.ndarray) -> np.ndarray:
    """``image`` as float32 in [0, 1], blurred over a sample's footprint when that spans more than
    :data:`ANTI_ALIAS_TEXELS` texels: first shrunk by area averaging by a whole factor (in the image's own type,
    so that a fine texture is not held in floats at full size), the rest a Gaussian; both averaging only the
    texels the triangles with texture coordinates ``uv`` (k, 3, 2) cover (:func:`_coverage`), so that an
    atlas's padding (black, or another chart's skin) does not bleed into the skin at its charts' edges."""
    import cv2

    if footprint_texels <= ANTI_ALIAS_TEXELS:
        return _as_float(image)
    covered = _coverage(uv, image.shape[:2])
    factor = int(footprint_texels // ANTI_ALIAS_TEXELS)
    if factor > 1:
        height, width = image.shape[:2]
        size = (max(1, round(width / factor)), max(1, round(height / factor)))
        colour = _as_float(cv2.resize(image * covered[..., None].astype(image.dtype), size,
                                      interpolation=cv2.INTER_AREA))
        weight = cv2.resize(covered * np.uint8(255), size, interpolation=cv2.INTER_AREA).astype(np.float32) / 255
        footprint_texels *= size[0] / width
    else:
        weight = covered.astype(np.float32)
        colour = _as_float(image) * weight[..., None]
    sigma = 0.5 * footprint_texels
    total = cv2.GaussianBlur(colour, (0, 0), sigma)
    share = cv2.GaussianBlur(weight, (0, 0), sigma)
    return total / np.maximum(share, 1e-6)[..., None]


def _lookup(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear colours (k, 3) of ``image`` at texture coordinates ``uv`` (k, 2), clamped to the image: a scan's
    texture atlas does not repeat, and a coordinate at its edge (u = 1) takes the edge's texels."""
    import cv2

    height, width = image.shape[:2]
    count = len(uv)
    side = int(np.ceil(count / LOOKUP_COLUMNS)) * LOOKUP_COLUMNS
    u = np.zeros(side, np.float32)
    v = np.zeros(side, np.float32)
    u[:count], v[:count] = np.clip(uv[:, 0], 0.0, 1.0), np.clip(uv[:, 1], 0.0, 1.0)
    map_x = (u * width - 0.5).reshape(-1, LOOKUP_COLUMNS)
    map_y = ((1.0 - v) * height - 0.5).reshape(-1, LOOKUP_COLUMNS)
    looked = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return looked.reshape(-1, 3)[:count].astype(np.float64)

