"""Building a basis from an artist's meshes through a TOML manifest.

A manifest names the neutral mesh, the units, and for each muscle the shape
meshes that make it, with weights: ``element = sum_k w_k (shape_k - neutral)``.

.. code-block:: toml

    format = "livebridge-basis-manifest"
    version = 1
    neutral = "generic_neutral_mesh"   # shape name; the file is NAME + suffix
    suffix = ".obj"
    units = "cm"                       # mm, cm or m
    keep_vertices = 9409               # optional: use the first N vertices (a face region)

    [muscles]
    frontalis_L = { browInnerUp_L = 1.0, browOuterUp_L = 1.0 }
    jaw = { jawOpen = 1.0 }

    [info.my_extra_muscle]             # needed for names outside the Choe-Ko 16
    region = "lower"
    side = "L"
    description = "..."

Shapes come from a folder of mesh files, or from an ``.npz`` holding
``names``, ``deltas (n_shapes, n_vertices, 3)`` and ``neutral``.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np

from livebridge.errors import InputError
from livebridge.face.basis import CHOE_KO_BY_NAME, Basis, Muscle
from livebridge.face.meshio import read_obj
from livebridge.npzio import read_npz
from livebridge.tomlio import load_toml, require

UNITS_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
MANIFEST_FORMAT = "livebridge-basis-manifest"
SHIPPED_MANIFESTS = {"choe-ko-ict": "choe_ko_ict.toml"}


def shipped_manifest(name: str) -> Path:
    """Path of a manifest shipped in the package (e.g. ``choe-ko-ict``)."""
    if name not in SHIPPED_MANIFESTS:
        raise InputError(f"no shipped manifest {name!r}; known: {', '.join(SHIPPED_MANIFESTS)}")
    return Path(str(resources.files("livebridge.face") / "data" / SHIPPED_MANIFESTS[name]))


def import_basis(manifest_path: str | Path, shapes: str | Path | None = None) -> Basis:
    """Build a :class:`Basis` from a manifest and a source of shape meshes.

    Parameters
    ----------
    manifest_path : path
        The TOML manifest, or the name of a shipped one (``choe-ko-ict``).
    shapes : path, optional
        A folder of mesh files or an ``.npz`` of named deltas. Defaults to the
        manifest's ``folder`` key, relative to the manifest.
    """
    if str(manifest_path) in SHIPPED_MANIFESTS:
        manifest_path = shipped_manifest(str(manifest_path))
    manifest_path = Path(manifest_path)
    manifest = load_toml(manifest_path)
    if manifest.get("format", MANIFEST_FORMAT) != MANIFEST_FORMAT:
        raise InputError(f"format must be {MANIFEST_FORMAT!r}", manifest_path, "format")
    units = require(manifest, "units", str, manifest_path)
    if units not in UNITS_TO_MM:
        raise InputError(f"unknown unit {units!r}; use one of {', '.join(UNITS_TO_MM)}", manifest_path, "units")
    muscle_shapes = require(manifest, "muscles", dict, manifest_path)
    if not muscle_shapes:
        raise InputError("no muscles listed", manifest_path, "muscles")
    if shapes is None:
        shapes = manifest_path.parent / manifest.get("folder", ".")
    source = _shape_source(Path(shapes), manifest, manifest_path)
    keep = manifest.get("keep_vertices")
    neutral, triangles = source.neutral, source.triangles
    if keep is not None:
        neutral, triangles = _keep_first(neutral, triangles, int(keep), manifest_path)
    n_vertices = len(neutral)
    muscles, elements = [], []
    for name, weights in muscle_shapes.items():
        field = f"muscles.{name}"
        if not isinstance(weights, dict) or not weights:
            raise InputError("expected a table of shape = weight", manifest_path, field)
        element = np.zeros((n_vertices, 3))
        for shape_name, weight in weights.items():
            if not isinstance(weight, (int, float)) or isinstance(weight, bool):
                raise InputError(f"weight of {shape_name!r} must be a number", manifest_path, field)
            element += weight * source.delta(shape_name)[:n_vertices]
        muscles.append(_muscle_info(name, manifest.get("info", {}).get(name), manifest_path))
        elements.append(element)
    scale = UNITS_TO_MM[units]
    return Basis(neutral * scale, triangles, np.asarray(elements) * scale, tuple(muscles))


def _muscle_info(name: str, info: dict | None, manifest_path: Path) -> Muscle:
    known = CHOE_KO_BY_NAME.get(name)
    if info is None and known is None:
        raise InputError(
            "not one of the Choe-Ko muscles: give its region (and side) in [info." + name + "]",
            manifest_path, f"muscles.{name}",
        )
    info = info or {}
    try:
        return Muscle(
            name,
            info.get("region", known.region if known else None),
            info.get("side", known.side if known else None),
            info.get("description", known.description if known else ""),
        )
    except InputError as error:
        raise InputError(error.message, manifest_path, f"info.{name}") from None


def _keep_first(neutral: np.ndarray, triangles: np.ndarray, keep: int, path: Path):
    if not 3 <= keep <= len(neutral):
        raise InputError(f"must be between 3 and {len(neutral)}", path, "keep_vertices")
    inside = (triangles < keep).all(axis=1)
    return neutral[:keep], triangles[inside]


class _FolderShapes:
    """Shapes read from mesh files ``FOLDER/NAME + suffix``, checked against the neutral's topology."""

    def __init__(self, folder: Path, manifest: dict, manifest_path: Path):
        if not folder.is_dir():
            raise InputError("shape folder not found", folder)
        self.folder = folder
        self.suffix = manifest.get("suffix", ".obj")
        if self.suffix.lower() != ".obj":
            raise InputError(f"unsupported mesh format {self.suffix!r}; use .obj", manifest_path, "suffix")
        neutral_name = require(manifest, "neutral", str, manifest_path)
        self.neutral_path = self._path(neutral_name)
        mesh = read_obj(self.neutral_path)
        self.neutral, self.triangles = mesh.vertices, mesh.triangles

    def _path(self, name: str) -> Path:
        path = self.folder / (name if name.endswith(self.suffix) else name + self.suffix)
        if not path.is_file():
            raise InputError("shape file not found", path)
        return path

    def delta(self, name: str) -> np.ndarray:
        path = self._path(name)
        mesh = read_obj(path)
        if mesh.vertices.shape != self.neutral.shape:
            raise InputError(
                f"topology mismatch: {len(mesh.vertices)} vertices, the neutral "
                f"{self.neutral_path.name} has {len(self.neutral)}", path,
            )
        if not np.array_equal(mesh.triangles, self.triangles):
            raise InputError(f"topology mismatch: faces differ from the neutral {self.neutral_path.name}", path)
        return mesh.vertices - self.neutral


class _ArchiveShapes:
    """Shapes from an ``.npz`` holding ``names``, ``deltas``, ``neutral`` and ``triangles``."""

    def __init__(self, archive: Path):
        arrays = read_npz(archive, "shape archive", ("names", "deltas", "neutral", "triangles"))
        self.names = [str(n) for n in np.atleast_1d(arrays["names"])]
        self.deltas, self.neutral, self.triangles = (_numbers(arrays, key, dtype, archive) for key, dtype in
                                                     (("deltas", np.float64), ("neutral", np.float64),
                                                      ("triangles", np.int64)))
        self.archive = archive

    def delta(self, name: str) -> np.ndarray:
        if name not in self.names:
            raise InputError(f"shape {name!r} not in the archive", self.archive)
        return self.deltas[self.names.index(name)]


def _numbers(arrays: dict[str, np.ndarray], key: str, dtype, archive: Path) -> np.ndarray:
    """``arrays[key]`` as ``dtype``; an array of text or other things raises InputError naming it."""
    if arrays[key].dtype.kind not in "biuf":
        raise InputError(f"expected numbers, got dtype {arrays[key].dtype}", archive, key)
    return arrays[key].astype(dtype)


def _shape_source(shapes: Path, manifest: dict, manifest_path: Path):
    if shapes.suffix == ".npz":
        if not shapes.is_file():
            raise InputError("shape archive not found", shapes)
        return _ArchiveShapes(shapes)
    return _FolderShapes(shapes, manifest, manifest_path)
