"""The actuation basis: a neutral face plus one displacement field per muscle.

Any expression is ``E = E0 + sum_i x_i e_i`` (Choe & Ko). A basis is data,
not code: it is imported from an artist's meshes through a TOML manifest
(:mod:`livebridge.face.basis_import`) or generated (:mod:`livebridge.face.builtin`),
and stored as one versioned ``.npz`` file with an embedded JSON manifest.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.errors import InputError
from livebridge.npzio import read_npz

BASIS_FORMAT = "livebridge-basis"
BASIS_VERSION = 1
REGIONS = ("upper", "lower")
SIDES = ("L", "R", None)


@dataclass(frozen=True)
class Muscle:
    """One element of the basis: its name, face region, side and description."""

    name: str
    region: str
    side: str | None = None
    description: str = ""

    def __post_init__(self):
        if self.region not in REGIONS:
            raise InputError(f"region must be one of {REGIONS}, got {self.region!r}", field=f"muscle {self.name}")
        if self.side not in SIDES:
            raise InputError(f"side must be 'L', 'R' or none, got {self.side!r}", field=f"muscle {self.name}")


# The 16-element reference basis of Choe & Ko, in the order used throughout.
CHOE_KO_MUSCLES = (
    Muscle("frontalis_L", "upper", "L", "raises the left brow, wrinkles the forehead"),
    Muscle("frontalis_R", "upper", "R", "raises the right brow, wrinkles the forehead"),
    Muscle("corrugator_L", "upper", "L", "pulls the left brow down and in (frown)"),
    Muscle("corrugator_R", "upper", "R", "pulls the right brow down and in (frown)"),
    Muscle("orbicularis_oculi_L", "upper", "L", "closes the left eyelid, lifts the cheek below"),
    Muscle("orbicularis_oculi_R", "upper", "R", "closes the right eyelid, lifts the cheek below"),
    Muscle("levator_labii_L", "lower", "L", "raises the left upper lip, wrinkles the nose side"),
    Muscle("levator_labii_R", "lower", "R", "raises the right upper lip, wrinkles the nose side"),
    Muscle("zygomatic_major_L", "lower", "L", "pulls the left mouth corner up and out (smile)"),
    Muscle("zygomatic_major_R", "lower", "R", "pulls the right mouth corner up and out (smile)"),
    Muscle("risorius_L", "lower", "L", "pulls the left mouth corner sideways"),
    Muscle("risorius_R", "lower", "R", "pulls the right mouth corner sideways"),
    Muscle("depressor_anguli_oris", "lower", None, "pulls both mouth corners down"),
    Muscle("orbicularis_oris", "lower", None, "purses and protrudes the lips"),
    Muscle("lips_pressor", "lower", None, "presses the lips together"),
    Muscle("jaw", "lower", None, "rotates the jaw open about its hinge"),
)
CHOE_KO_BY_NAME = {muscle.name: muscle for muscle in CHOE_KO_MUSCLES}


@dataclass(frozen=True, eq=False)
class Basis:
    """A neutral mesh and one displacement field per muscle, in millimetres.

    Attributes
    ----------
    neutral : ndarray, shape (n_vertices, 3)
        The neutral face ``E0`` in millimetres.
    triangles : ndarray of int, shape (n_triangles, 3)
    elements : ndarray, shape (n_muscles, n_vertices, 3)
        ``e_i``: the face with muscle ``i`` fully contracted, minus neutral.
    muscles : tuple of Muscle, length n_muscles
    """

    neutral: np.ndarray
    triangles: np.ndarray
    elements: np.ndarray
    muscles: tuple[Muscle, ...]

    def __post_init__(self):
        neutral = np.asarray(self.neutral, dtype=np.float64)
        triangles = np.asarray(self.triangles, dtype=np.int64)
        elements = np.asarray(self.elements, dtype=np.float64)
        if neutral.ndim != 2 or neutral.shape[1] != 3:
            raise InputError(f"neutral must have shape (n_vertices, 3), got {neutral.shape}", field="neutral")
        if triangles.ndim != 2 or triangles.shape[1] != 3:
            raise InputError(f"triangles must have shape (n, 3), got {triangles.shape}", field="triangles")
        if triangles.size and (triangles.min() < 0 or triangles.max() >= len(neutral)):
            raise InputError("triangles refer to vertices that do not exist", field="triangles")
        if elements.shape != (len(self.muscles),) + neutral.shape:
            raise InputError(
                f"elements must have shape {(len(self.muscles),) + neutral.shape}, got {elements.shape}",
                field="elements",
            )
        for name, array in (("neutral", neutral), ("elements", elements)):
            if not np.isfinite(array).all():
                raise InputError("contains NaN or infinity", field=name)
        names = [m.name for m in self.muscles]
        if len(set(names)) != len(names):
            raise InputError(f"muscle names repeat: {names}", field="muscles")
        for array in (neutral, triangles, elements):
            array.setflags(write=False)
        object.__setattr__(self, "neutral", neutral)
        object.__setattr__(self, "triangles", triangles)
        object.__setattr__(self, "elements", elements)
        object.__setattr__(self, "muscles", tuple(self.muscles))

    @property
    def n_muscles(self) -> int:
        return len(self.muscles)

    @property
    def n_vertices(self) -> int:
        return len(self.neutral)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(m.name for m in self.muscles)

    def index(self, name: str) -> int:
        """Position of muscle ``name``; an unknown name raises naming the known ones."""
        try:
            return self.names.index(name)
        except ValueError:
            raise InputError(f"unknown muscle {name!r}; the basis has {', '.join(self.names)}") from None

    def region_mask(self, region: str) -> np.ndarray:
        """Boolean mask, shape (n_muscles,), of the muscles in ``region``."""
        return np.array([m.region == region for m in self.muscles])

    def synthesize(self, contractions: np.ndarray) -> np.ndarray:
        """Face vertices for contractions ``x``: ``E0 + sum_i x_i e_i``.

        Parameters
        ----------
        contractions : ndarray, shape (..., n_muscles)

        Returns
        -------
        ndarray, shape (..., n_vertices, 3)
        """
        contractions = np.asarray(contractions, dtype=np.float64)
        if contractions.shape[-1] != self.n_muscles:
            raise ValueError(f"contractions have {contractions.shape[-1]} values, the basis {self.n_muscles}")
        flat = self.elements.reshape(self.n_muscles, -1)
        return self.neutral + (contractions @ flat).reshape(contractions.shape[:-1] + self.neutral.shape)

    def with_elements(self, elements: np.ndarray) -> Basis:
        """A copy with other displacement fields (same neutral, topology and muscles)."""
        return Basis(self.neutral, self.triangles, elements, self.muscles)

    def save(self, path: str | Path) -> None:
        """Write the basis as one ``.npz`` file with an embedded manifest."""
        manifest = {
            "format": BASIS_FORMAT,
            "version": BASIS_VERSION,
            "units": "mm",
            "muscles": [
                {"name": m.name, "region": m.region, "side": m.side, "description": m.description}
                for m in self.muscles
            ],
        }
        path = Path(path)
        with path.open("wb") as stream:
            np.savez_compressed(
                stream,
                manifest=np.array(json.dumps(manifest)),
                neutral=self.neutral,
                triangles=self.triangles.astype(np.int32),
                elements=self.elements,
            )

    @classmethod
    def load(cls, path: str | Path) -> Basis:
        """Read a basis written by :meth:`save`; anything wrong raises :class:`InputError` naming the field."""
        path = Path(path)
        arrays = read_npz(path, "livebridge basis", ("manifest", "neutral", "triangles", "elements"))
        muscles = _read_manifest(arrays["manifest"], path)
        for key, kinds, what in (("neutral", "fiu", "numbers"), ("elements", "fiu", "numbers"),
                                 ("triangles", "iu", "whole numbers")):
            if arrays[key].dtype.kind not in kinds:
                raise InputError(f"expected {what}, got dtype {arrays[key].dtype}", path, key)
        try:
            return cls(arrays["neutral"], arrays["triangles"], arrays["elements"], muscles)
        except InputError as error:
            raise InputError(error.message, path, error.field) from None


def _read_manifest(array: np.ndarray, path: Path) -> tuple[Muscle, ...]:
    """The muscles of the JSON manifest embedded in a basis file, every field checked."""
    if array.shape != () or array.dtype.kind != "U":
        raise InputError(f"expected one JSON text, got an array of {array.dtype} shape {array.shape}", path,
                         "manifest")
    try:
        manifest = json.loads(str(array))
    except json.JSONDecodeError as error:
        raise InputError(f"not valid JSON ({error})", path, "manifest") from None
    if not isinstance(manifest, dict):
        raise InputError(f"expected a JSON object, got {type(manifest).__name__}", path, "manifest")
    if manifest.get("format") != BASIS_FORMAT:
        raise InputError(f"format is {manifest.get('format')!r}, expected {BASIS_FORMAT!r}", path, "format")
    version = manifest.get("version", BASIS_VERSION)
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise InputError(f"expected a whole number >= 1, got {version!r}", path, "version")
    if version > BASIS_VERSION:
        raise InputError(f"version {version} is newer than this livebridge reads", path, "version")
    if manifest.get("units", "mm") != "mm":
        raise InputError(f"expected 'mm', got {manifest['units']!r}", path, "units")
    rows = manifest.get("muscles")
    if not isinstance(rows, list) or not rows:
        raise InputError(f"expected a non-empty list of muscles, got {rows!r}", path, "muscles")
    return tuple(_muscle(row, path, f"muscles[{k}]") for k, row in enumerate(rows))


def _muscle(row, path: Path, field: str) -> Muscle:
    if not isinstance(row, dict):
        raise InputError(f"expected an object, got {row!r}", path, field)
    for key, kinds, required in (("name", (str,), True), ("region", (str,), True),
                                 ("side", (str, type(None)), False), ("description", (str,), False)):
        if required and key not in row:
            raise InputError("missing", path, f"{field}.{key}")
        if key in row and not isinstance(row[key], kinds):
            raise InputError(f"expected text, got {row[key]!r}", path, f"{field}.{key}")
    if not row["name"]:
        raise InputError("empty muscle name", path, f"{field}.name")
    try:
        return Muscle(row["name"], row["region"], row.get("side"), row.get("description", ""))
    except InputError as error:
        raise InputError(error.message, path, f"{field} ({row['name']})") from None
