"""A character on disk: a folder with ``character.toml``, a neutral image, samples and region masks.

Layout of ``character.toml`` (paths relative to the folder)::

    format = "livebridge-character"
    version = 1
    name = "maggie"
    neutral = "neutral.png"            # the canvas: its size is the character's size
    feather_px = 10.0                  # optional: width of the samples' alpha ramp (the paper's 10 px)

    [warp]                             # optional: where masks drawn on the performer's face land
    face_points = [[x, y], ...]        #   points on the face (e.g. the markerless model's canonical image)
    character_points = [[x, y], ...]   #   the same points on the character (>= 3; 3: affine, more: TPS)

    [[regions]]                        # composited in this order (later regions over earlier ones)
    name = "mouth"
    muscles = ["jaw", "zygomatic_major_L+zygomatic_major_R"]
    states = [3, 2]                    # per muscle: samples K (states 1..K at levels k/K; 0 is neutral)
    mask = "masks/mouth.png"           # optional: where this region may draw (white), canvas-sized ...
    mask_space = "character"           # ... or "face": drawn on the face, carried here by [warp]
    [regions.actuations]               # optional: what a pseudo-muscle means in basis contractions
    "zygomatic+risorius" = { zygomatic_major_L = 1.0, risorius_L = 0.5 }   # (default: "a+b" -> a, b at 1)

    [[regions.samples]]                # one per muscle and state
    muscle = "jaw"
    state = 1
    image = "mouth/jaw_1.png"          # grey, RGB or RGBA (its alpha: what was drawn)
    at = [x, y]                        # top-left corner on the canvas, pixels

Images are 8- or 16-bit PNG (anything OpenCV reads); the canvas is grey when the neutral image is, RGB
otherwise, and samples are converted to it. Bad input raises :class:`~livebridge.errors.InputError` naming
the file and the field: a state without a sample, a sample that reaches outside the canvas or lies outside
its region's mask, a mask not the size of the canvas (or of the face, for ``mask_space = "face"``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from livebridge.errors import InputError
from livebridge.tomlio import load_toml, require, save_toml

FORMAT = "livebridge-character"
VERSION = 1
MANIFEST = "character.toml"


@dataclass(frozen=True, eq=False)
class Sample:
    """One appearance sample: a region's look at one state of one muscle.

    Attributes
    ----------
    image : ndarray of float32, shape (h, w, n_channels)
        Colours in [0, 1], the canvas's channels.
    opacity : ndarray of float32, shape (h, w)
        What was drawn, in [0, 1] (1 everywhere for an image without alpha).
    origin : (int, int)
        ``(x, y)`` of its top-left pixel on the canvas.
    source : str
        The file it came from (named in errors), or a description.
    """

    image: np.ndarray
    opacity: np.ndarray
    origin: tuple[int, int]
    source: str = ""

    @property
    def rect(self) -> tuple[int, int, int, int]:
        """``(x, y, width, height)`` on the canvas."""
        return self.origin[0], self.origin[1], self.image.shape[1], self.image.shape[0]


@dataclass(frozen=True, eq=False)
class CharacterRegion:
    """A co-articulation region of a character.

    Attributes
    ----------
    name : str
    muscles : tuple of str
        Its muscles and pseudo-muscles (``"a+b"``).
    samples : tuple of tuple of Sample
        Per muscle, its samples for states ``1..K`` (levels ``k / K``).
    mask : ndarray of bool, shape (height, width), optional
        Where on the canvas the region may draw; None: wherever its samples were drawn.
    actuations : mapping of str to mapping of str to float
        Pseudo-muscle -> {basis muscle: level at full actuation}, for those whose name does not say it.
    """

    name: str
    muscles: tuple[str, ...]
    samples: tuple[tuple[Sample, ...], ...]
    mask: np.ndarray | None = None
    actuations: Mapping[str, Mapping[str, float]] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class Character:
    """A neutral canvas and its regions' samples.

    Attributes
    ----------
    name : str
    neutral : ndarray of float32, shape (height, width, n_channels)
        The neutral face, colours in [0, 1] (1 channel: grey, 3: RGB).
    regions : tuple of CharacterRegion
        In compositing order.
    feather_px : float
        Width of every sample's alpha ramp, pixels.
    """

    name: str
    neutral: np.ndarray
    regions: tuple[CharacterRegion, ...]
    feather_px: float = 10.0

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` of the canvas."""
        return self.neutral.shape[1], self.neutral.shape[0]

    @property
    def n_channels(self) -> int:
        return self.neutral.shape[2]

    @property
    def region_names(self) -> tuple[str, ...]:
        return tuple(region.name for region in self.regions)

    @property
    def region_muscles(self) -> tuple[tuple[str, ...], ...]:
        return tuple(region.muscles for region in self.regions)

    @property
    def region_actuations(self) -> tuple[Mapping[str, Mapping[str, float]], ...]:
        return tuple(region.actuations for region in self.regions)


# ------------------------------------------------------------------------------------------------ images
def read_image(path: Path, field: str | None = None) -> np.ndarray:
    """An image file as float32 in [0, 1], shape (h, w) grey or (h, w, 3) RGB or (h, w, 4) RGBA."""
    if not path.is_file():
        raise InputError("file not found" if not path.exists() else "is a directory, not a file", path, field)
    data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if data is None:
        raise InputError("not an image OpenCV can read", path, field)
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(data.dtype)
    if scale is None:
        raise InputError(f"unsupported image type {data.dtype} (8- or 16-bit images)", path, field)
    image = data.astype(np.float32) / np.float32(scale)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    if image.ndim == 3:
        order = [2, 1, 0, 3][:image.shape[2]]  # OpenCV's BGR(A) -> RGB(A)
        image = image[..., order]
    return image


def write_image(path: Path, image: np.ndarray) -> None:
    """Write float [0, 1] grey (h, w), RGB (h, w, 3) or RGBA (h, w, 4) as an 8-bit PNG."""
    data = np.clip(np.rint(np.asarray(image, dtype=np.float32) * 255.0), 0, 255).astype(np.uint8)
    if data.ndim == 3 and data.shape[2] == 1:
        data = data[..., 0]
    if data.ndim == 3:
        data = data[..., [2, 1, 0, 3][:data.shape[2]]]
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), data):
        raise OSError(f"could not write {path}")


def to_channels(image: np.ndarray, n_channels: int) -> tuple[np.ndarray, np.ndarray]:
    """``(colour (h, w, n_channels), opacity (h, w))`` of a grey, RGB or RGBA image."""
    image = np.asarray(image, dtype=np.float32)
    if image.ndim == 2:
        image = image[..., None]
    opacity = image[..., 3] if image.shape[2] == 4 else np.ones(image.shape[:2], np.float32)
    colour = image[..., :3] if image.shape[2] >= 3 else image[..., :1]
    if colour.shape[2] == 3 and n_channels == 1:
        colour = cv2.cvtColor(np.ascontiguousarray(colour), cv2.COLOR_RGB2GRAY)[..., None]
    elif colour.shape[2] == 1 and n_channels == 3:
        colour = np.repeat(colour, 3, axis=2)
    return np.ascontiguousarray(colour), np.ascontiguousarray(opacity)


# ------------------------------------------------------------------------------------------------ warp
def warp_to_character(mask: np.ndarray, face_points: np.ndarray, character_points: np.ndarray,
                      size: tuple[int, int]) -> np.ndarray:
    """Carry a mask drawn on the face onto the character's canvas.

    Parameters
    ----------
    mask : ndarray of bool, shape (face_height, face_width)
    face_points, character_points : ndarray, shape (n, 2)
        The same ``n >= 3`` points (x, y pixels) on the face and on the character: an affine map for 3, a
        thin-plate spline (exact at the points, affine far away) for more.
    size : (int, int)
        ``(width, height)`` of the canvas.

    Returns
    -------
    ndarray of bool, shape (height, width)
    """
    from scipy.interpolate import RBFInterpolator

    width, height = size
    step = 4  # the map is smooth: evaluate it on a coarse grid and resize
    gx, gy = np.meshgrid(np.arange(0, width + step, step, dtype=np.float64),
                         np.arange(0, height + step, step, dtype=np.float64))
    grid = np.stack([gx.ravel(), gy.ravel()], axis=1)
    kernel = "linear" if len(face_points) == 3 else "thin_plate_spline"
    to_face = RBFInterpolator(np.asarray(character_points, float), np.asarray(face_points, float),
                              kernel=kernel, degree=1)
    coarse = to_face(grid).reshape(gy.shape + (2,)).astype(np.float32)
    # sample the coarse map at pixel / step (grid point k sits at pixel k * step)
    px, py = np.meshgrid(np.arange(width, dtype=np.float32) / step, np.arange(height, dtype=np.float32) / step)
    full = cv2.remap(coarse, px, py, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    warped = cv2.remap(mask.astype(np.float32), np.ascontiguousarray(full[..., 0]),
                       np.ascontiguousarray(full[..., 1]), cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return warped >= 0.5


# ------------------------------------------------------------------------------------------------ loading
def load_character(folder: str | Path) -> Character:
    """Read a character folder (layout in the module docstring).

    Raises
    ------
    InputError
        Naming the file and field of what is wrong (see the module docstring).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("folder not found" if not folder.exists() else "is a file, not a character folder",
                         folder)
    path = folder / MANIFEST
    table = load_toml(path)
    if table.get("format") != FORMAT:
        raise InputError(f"not a character file (format is {table.get('format')!r}, expected {FORMAT!r})",
                         path, "format")
    version = require(table, "version", int, path)
    if version != VERSION:
        raise InputError(f"version {version} is not supported (this livebridge reads {VERSION})", path, "version")
    neutral_image = read_image(folder / require(table, "neutral", str, path), "neutral")
    n_channels = 1 if neutral_image.ndim == 2 else 3
    neutral, _ = to_channels(neutral_image, n_channels)
    feather = float(require(table, "feather_px", (int, float), path)) if "feather_px" in table else 10.0
    if not 0.0 <= feather <= 1000.0:
        raise InputError(f"expected 0..1000 pixels, got {feather}", path, "feather_px")
    warp = _read_warp(table, path)
    regions_table = require(table, "regions", list, path)
    size = (neutral.shape[1], neutral.shape[0])
    regions, seen = [], set()
    for r, entry in enumerate(regions_table):
        region = _read_region(folder, path, entry, f"regions[{r}]", size, n_channels, warp)
        if region.name in seen:
            raise InputError(f"region {region.name!r} appears twice", path, f"regions[{r}].name")
        seen.add(region.name)
        regions.append(region)
    return Character(str(table.get("name", folder.name)), neutral, tuple(regions), feather)


def _read_warp(table: dict, path: Path) -> tuple[np.ndarray, np.ndarray, tuple[int, int] | None] | None:
    if "warp" not in table:
        return None
    warp = require(table, "warp", dict, path)
    points = []
    for key in ("face_points", "character_points"):
        try:
            array = np.asarray(require(warp, key, list, path, "warp"), dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError("expected a list of [x, y] pairs", path, f"warp.{key}") from None
        if array.ndim != 2 or array.shape[1] != 2 or len(array) < 3 or not np.isfinite(array).all():
            raise InputError("expected at least 3 finite [x, y] pairs", path, f"warp.{key}")
        points.append(array)
    if len(points[0]) != len(points[1]):
        raise InputError(f"{len(points[0])} face points for {len(points[1])} character points", path,
                         "warp.character_points")
    face_size = tuple(require(warp, "face_size", list, path, "warp")) if "face_size" in warp else None
    return points[0], points[1], face_size


def _read_region(folder: Path, path: Path, entry, where: str, size: tuple[int, int], n_channels: int,
                 warp) -> CharacterRegion:
    if not isinstance(entry, dict):
        raise InputError("expected a table", path, where)
    name = require(entry, "name", str, path, where)
    muscles = require(entry, "muscles", list, path, where)
    states = require(entry, "states", list, path, where)
    if not muscles or not all(isinstance(m, str) and m for m in muscles) or len(set(muscles)) != len(muscles):
        raise InputError("expected distinct muscle names", path, f"{where}.muscles")
    if len(states) != len(muscles) or not all(isinstance(k, int) and not isinstance(k, bool) and 1 <= k <= 1000
                                              for k in states):
        raise InputError(f"expected one count 1..1000 per muscle ({len(muscles)})", path, f"{where}.states")
    mask = _read_mask(folder, path, entry, where, size, warp)
    found: dict[tuple[str, int], Sample] = {}
    for s, sample_entry in enumerate(require(entry, "samples", list, path, where)):
        field = f"{where}.samples[{s}]"
        if not isinstance(sample_entry, dict):
            raise InputError("expected a table", path, field)
        muscle = require(sample_entry, "muscle", str, path, field)
        state = require(sample_entry, "state", int, path, field)
        if muscle not in muscles:
            raise InputError(f"muscle {muscle!r} is not one of the region's ({', '.join(muscles)})", path,
                             f"{field}.muscle")
        k_max = states[muscles.index(muscle)]
        if not 1 <= state <= k_max:
            raise InputError(f"state {state} of {muscle!r}: expected 1..{k_max}", path, f"{field}.state")
        if (muscle, state) in found:
            raise InputError(f"state {state} of {muscle!r} has two samples", path, field)
        found[(muscle, state)] = _read_sample(folder, path, sample_entry, field, name, muscle, state, size,
                                              n_channels, mask)
    missing = [f"{m} state {k}" for m, K in zip(muscles, states) for k in range(1, K + 1) if (m, k) not in found]
    if missing:
        raise InputError(f"region {name!r}: no sample for {', '.join(missing)}", path, f"{where}.samples")
    samples = tuple(tuple(found[(m, k)] for k in range(1, K + 1)) for m, K in zip(muscles, states))
    return CharacterRegion(name, tuple(muscles), samples, mask, _read_actuations(path, entry, where, muscles))


def _read_actuations(path: Path, entry: dict, where: str, muscles: list[str]) -> dict[str, dict[str, float]]:
    table = require(entry, "actuations", dict, path, where) if "actuations" in entry else {}
    actuations = {}
    for muscle, parts in table.items():
        field_name = f"{where}.actuations.{muscle}"
        if muscle not in muscles:
            raise InputError(f"{muscle!r} is not one of the region's muscles ({', '.join(muscles)})", path,
                             field_name)
        if not isinstance(parts, dict) or not parts or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in parts.values()):
            raise InputError("expected a table of basis muscle = finite level", path, field_name)
        actuations[muscle] = {part: float(v) for part, v in parts.items()}
    return actuations


def _read_mask(folder: Path, path: Path, entry: dict, where: str, size: tuple[int, int], warp):
    if "mask" not in entry:
        return None
    mask_path = folder / require(entry, "mask", str, path, where)
    space = entry.get("mask_space", "character")
    if space not in ("character", "face"):
        raise InputError(f"expected 'character' or 'face', got {space!r}", path, f"{where}.mask_space")
    image = read_image(mask_path, f"{where}.mask")
    mask = (image if image.ndim == 2 else image[..., :3].mean(axis=2)) >= 0.5
    if space == "face":
        if warp is None:
            raise InputError("a mask drawn on the face needs a [warp] table to place it", path,
                             f"{where}.mask_space")
        face_points, character_points, face_size = warp
        if face_size is not None and tuple(face_size) != (mask.shape[1], mask.shape[0]):
            raise InputError(f"mask is {mask.shape[1]}x{mask.shape[0]}, the face (warp.face_size) "
                             f"{face_size[0]}x{face_size[1]}", mask_path, f"{where}.mask")
        mask = warp_to_character(mask, face_points, character_points, size)
    elif (mask.shape[1], mask.shape[0]) != size:
        raise InputError(f"mask is {mask.shape[1]}x{mask.shape[0]}, the canvas {size[0]}x{size[1]}", mask_path,
                         f"{where}.mask")
    if not mask.any():
        raise InputError("the mask is empty (white marks the region)", mask_path, f"{where}.mask")
    return mask


def _read_sample(folder: Path, path: Path, entry: dict, field: str, region: str, muscle: str, state: int,
                 size: tuple[int, int], n_channels: int, mask) -> Sample:
    image_path = folder / require(entry, "image", str, path, field)
    at = require(entry, "at", list, path, field)
    if len(at) != 2 or not all(isinstance(v, int) and not isinstance(v, bool) for v in at):
        raise InputError("expected [x, y] in whole pixels", path, f"{field}.at")
    colour, opacity = to_channels(read_image(image_path, f"{field}.image"), n_channels)
    sample = Sample(colour, opacity, (at[0], at[1]), str(image_path))
    what = f"region {region!r}, {muscle} state {state}"
    check_sample(sample, size, mask, what, image_path, f"{field}.at")
    return sample


def check_sample(sample: Sample, size: tuple[int, int], mask: np.ndarray | None, what: str, path,
                 field: str | None = None) -> None:
    """Refuse a sample that reaches outside the canvas, or that its region's mask does not touch."""
    x, y, w, h = sample.rect
    if x < 0 or y < 0 or x + w > size[0] or y + h > size[1]:
        raise InputError(f"{what}: the sample ({w}x{h} at [{x}, {y}]) reaches outside the "
                         f"{size[0]}x{size[1]} canvas", path, field)
    if mask is not None and not (mask[y:y + h, x:x + w] & (sample.opacity > 0)).any():
        raise InputError(f"{what}: the sample ({w}x{h} at [{x}, {y}]) lies outside the region's mask", path,
                         field)


# ------------------------------------------------------------------------------------------------ saving
def save_character(character: Character, folder: str | Path) -> Path:
    """Write ``character`` as a folder (created; files in it are replaced). Returns the manifest's path."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    write_image(folder / "neutral.png", _squeeze(character.neutral))
    regions = []
    for region in character.regions:
        entry = {"name": region.name, "muscles": list(region.muscles),
                 "states": [len(samples) for samples in region.samples], "samples": []}
        if region.actuations:
            entry["actuations"] = {m: dict(parts) for m, parts in region.actuations.items()}
        if region.mask is not None:
            entry["mask"] = f"masks/{_file_name(region.name)}.png"
            write_image(folder / entry["mask"], region.mask.astype(np.float32))
        for muscle, samples in zip(region.muscles, region.samples):
            for k, sample in enumerate(samples, start=1):
                name = f"{_file_name(region.name)}/{_file_name(muscle)}_{k}.png"
                image = _squeeze(sample.image)
                if not np.all(sample.opacity >= 1.0):
                    rgb = image if image.ndim == 3 else np.repeat(image[..., None], 3, axis=2)
                    image = np.concatenate([rgb, sample.opacity[..., None]], axis=2)
                write_image(folder / name, image)
                entry["samples"].append({"muscle": muscle, "state": k, "image": name,
                                         "at": [int(sample.origin[0]), int(sample.origin[1])]})
        regions.append(entry)
    manifest = folder / MANIFEST
    save_toml(manifest, {"format": FORMAT, "version": VERSION, "name": character.name, "neutral": "neutral.png",
                         "feather_px": float(character.feather_px), "regions": regions})
    return manifest


def _squeeze(image: np.ndarray) -> np.ndarray:
    return image[..., 0] if image.ndim == 3 and image.shape[2] == 1 else image


def _file_name(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name)
