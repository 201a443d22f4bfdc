"""Virtual markers: physical markers as points on the face surface.

Each marker is a triangle index plus barycentric coordinates, so its
position follows any deformation of the mesh. ``face`` markers move with
expression; ``head`` markers sit on the rigid head rig and do not.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.errors import InputError
from livebridge.face.basis import REGIONS, Basis
from livebridge.tomlio import load_toml, require, save_toml

MARKERS_FORMAT = "livebridge-markers"
MARKERS_VERSION = 1
ROLES = ("face", "head")


@dataclass(frozen=True, eq=False)
class MarkerSet:
    """Named markers on a mesh.

    Attributes
    ----------
    names : tuple of str, length n_markers
    triangles : ndarray of int, shape (n_markers,)
        The mesh triangle each marker lies on.
    barycentric : ndarray, shape (n_markers, 3)
        Barycentric coordinates inside that triangle (non-negative, sum 1).
    regions : tuple of str, length n_markers
        ``upper`` or ``lower``: which half of the face solve uses the marker.
    roles : tuple of str, length n_markers
        ``face`` (moves with expression) or ``head`` (rigid head rig).
    mesh_triangles : int or None
        The triangle count of the mesh the set was made for, when known (the shipped sets of another
        topology carry it): a mesh of another count is refused even where every index fits.
    """

    names: tuple[str, ...]
    triangles: np.ndarray
    barycentric: np.ndarray
    regions: tuple[str, ...]
    roles: tuple[str, ...]
    mesh_triangles: int | None = None

    def __post_init__(self):
        n = len(self.names)
        triangles = np.asarray(self.triangles, dtype=np.int64).reshape(-1)
        barycentric = np.asarray(self.barycentric, dtype=np.float64).reshape(-1, 3)
        if not (len(triangles) == len(barycentric) == len(self.regions) == len(self.roles) == n):
            raise InputError("names, triangles, barycentric, regions and roles differ in length")
        if len(set(self.names)) != n:
            raise InputError("marker names repeat", field="names")
        for name, region, role in zip(self.names, self.regions, self.roles):
            if region not in REGIONS:
                raise InputError(f"region must be one of {REGIONS}, got {region!r}", field=f"marker {name}")
            if role not in ROLES:
                raise InputError(f"role must be one of {ROLES}, got {role!r}", field=f"marker {name}")
        bad = ~(np.all(barycentric >= -1e-9, axis=1) & (np.abs(barycentric.sum(axis=1) - 1) < 1e-6))
        if bad.any():
            name = self.names[int(np.flatnonzero(bad)[0])]
            raise InputError(f"barycentric coordinates must be finite, >= 0 and sum to 1, got "
                             f"{barycentric[bad][0].tolist()}", field=f"marker {name}")
        _check_apart(self.names, triangles, barycentric)
        for array in (triangles, barycentric):
            array.setflags(write=False)
        object.__setattr__(self, "triangles", triangles)
        object.__setattr__(self, "barycentric", barycentric)
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "regions", tuple(self.regions))
        object.__setattr__(self, "roles", tuple(self.roles))

    def __len__(self) -> int:
        return len(self.names)

    @property
    def face_mask(self) -> np.ndarray:
        """Boolean mask, shape (n_markers,), of the markers that move with expression."""
        return np.array([role == "face" for role in self.roles])

    @property
    def head_mask(self) -> np.ndarray:
        """Boolean mask, shape (n_markers,), of the rigid head-rig markers."""
        return ~self.face_mask

    def region_mask(self, region: str) -> np.ndarray:
        """Boolean mask, shape (n_markers,), of face markers in ``region``."""
        return self.face_mask & np.array([r == region for r in self.regions])

    def subset(self, mask: np.ndarray) -> MarkerSet:
        """The markers selected by a boolean mask or index array, in order."""
        index = np.flatnonzero(mask) if np.asarray(mask).dtype == bool else np.asarray(mask)
        return MarkerSet(
            tuple(self.names[i] for i in index), self.triangles[index], self.barycentric[index],
            tuple(self.regions[i] for i in index), tuple(self.roles[i] for i in index), self.mesh_triangles,
        )

    def check_mesh(self, n_triangles: int) -> None:
        """Raise if the set was made for another mesh, or a marker refers to a triangle the mesh does not have."""
        if self.mesh_triangles is not None and n_triangles != self.mesh_triangles:
            raise InputError(f"made for a mesh of {self.mesh_triangles} triangles; this mesh has {n_triangles} "
                             "(another topology: place the markers on this mesh)", field="mesh_triangles")
        bad = np.flatnonzero((self.triangles < 0) | (self.triangles >= n_triangles))
        if bad.size:
            raise InputError(f"triangle {self.triangles[bad[0]]} does not exist (mesh has {n_triangles})",
                             field=f"marker {self.names[bad[0]]}")

    def positions(self, vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
        """Marker positions on a (deformed) mesh by barycentric interpolation.

        Parameters
        ----------
        vertices : ndarray, shape (..., n_vertices, 3)
        triangles : ndarray of int, shape (n_triangles, 3)

        Returns
        -------
        ndarray, shape (..., n_markers, 3)
        """
        corners = np.asarray(vertices)[..., triangles[self.triangles], :]  # (..., n, 3, 3)
        return np.einsum("...nkd,nk->...nd", corners, self.barycentric)

    def displacement_matrix(self, basis: Basis) -> np.ndarray:
        """Per-marker displacement of every basis element: ``d_ij``.

        Head markers do not move with expression, so their rows are zero.

        Returns
        -------
        ndarray, shape (n_markers, n_muscles, 3)
        """
        self.check_mesh(len(basis.triangles))
        per_element = self.positions(basis.elements, basis.triangles)  # (M, n, 3)
        displacement = np.transpose(per_element, (1, 0, 2)).copy()
        displacement[self.head_mask] = 0.0
        return displacement

    def neutral_positions(self, basis: Basis) -> np.ndarray:
        """Marker positions on the neutral face, shape (n_markers, 3)."""
        self.check_mesh(len(basis.triangles))
        return self.positions(basis.neutral, basis.triangles)

    def marker_positions(self, basis: Basis, contractions: np.ndarray) -> np.ndarray:
        """Marker positions in the model frame for contractions, shape (..., n_markers, 3).

        Equal to interpolating the synthesised mesh, without building it.
        """
        contractions = np.asarray(contractions, dtype=np.float64)
        displacement = self.displacement_matrix(basis)  # (n, M, 3)
        return self.neutral_positions(basis) + np.einsum("...m,nmd->...nd", contractions, displacement)

    def save(self, path: str | Path) -> None:
        """Write the marker set as TOML."""
        mesh = {} if self.mesh_triangles is None else {"mesh_triangles": int(self.mesh_triangles)}
        save_toml(path, {
            "format": MARKERS_FORMAT,
            "version": MARKERS_VERSION,
            **mesh,
            "marker": [
                {"name": n, "triangle": int(t), "barycentric": [float(b) for b in bary], "region": r, "role": o}
                for n, t, bary, r, o in zip(self.names, self.triangles, self.barycentric, self.regions, self.roles)
            ],
        })

    @classmethod
    def load(cls, path: str | Path) -> MarkerSet:
        """Read a marker set written by :meth:`save`; every error names the file and the marker's field."""
        data = load_toml(path)
        unknown = sorted(set(data) - {"format", "version", "mesh_triangles", "marker"})
        if unknown:
            raise InputError(f"unknown key {unknown[0]!r}", path, unknown[0])
        if data.get("format") != MARKERS_FORMAT:
            raise InputError(f"format must be {MARKERS_FORMAT!r}", path, "format")
        version = data.get("version", MARKERS_VERSION)
        if isinstance(version, bool) or not isinstance(version, int) or version < 1:
            raise InputError(f"expected a whole number >= 1, got {version!r}", path, "version")
        if version > MARKERS_VERSION:
            raise InputError(f"version {version} is newer than this livebridge reads", path, "version")
        rows = require(data, "marker", list, path)
        if not rows:
            raise InputError("no markers ([[marker]] tables)", path, "marker")
        fields = {"names": [], "triangles": [], "barycentric": [], "regions": [], "roles": []}
        for k, row in enumerate(rows):
            for key, value in zip(fields, _marker_row(row, path, f"marker[{k}]")):
                fields[key].append(value)
        mesh_triangles = data.get("mesh_triangles")
        if mesh_triangles is not None and (isinstance(mesh_triangles, bool) or not isinstance(mesh_triangles, int)
                                           or mesh_triangles < 1):
            raise InputError(f"expected a whole number >= 1, got {mesh_triangles!r}", path, "mesh_triangles")
        try:
            return cls(**fields, mesh_triangles=mesh_triangles)
        except InputError as error:
            raise InputError(error.message, path, error.field) from None


_MARKER_KEYS = {"name", "triangle", "barycentric", "region", "role"}


def _marker_row(row, path, prefix: str) -> tuple[str, int, list[float], str, str]:
    """One ``[[marker]]`` table checked: (name, triangle, barycentric, region, role)."""
    if not isinstance(row, dict):
        raise InputError(f"expected a table, got {row!r}", path, prefix)
    unknown = sorted(set(row) - _MARKER_KEYS)
    if unknown:
        raise InputError(f"unknown key {unknown[0]!r}", path, f"{prefix}.{unknown[0]}")
    name = require(row, "name", str, path, prefix)
    triangle = require(row, "triangle", int, path, prefix)
    if triangle < 0:
        raise InputError(f"expected a triangle index >= 0, got {triangle}", path, f"{prefix}.triangle")
    bary = require(row, "barycentric", list, path, prefix)
    if len(bary) != 3 or not all(isinstance(b, (int, float)) and not isinstance(b, bool) for b in bary):
        raise InputError(f"needs 3 barycentric coordinates (numbers), got {bary!r}", path, f"{prefix}.barycentric")
    region = require(row, "region", str, path, prefix)
    role = row.get("role", "face")
    if not isinstance(role, str):
        raise InputError(f"expected str, got {type(role).__name__} {role!r}", path, f"{prefix}.role")
    return name, triangle, [float(b) for b in bary], region, role


# ------------------------------------------------------------------------------------------------ shipped sets
LANDMARKS_68_UPPER = (*range(17, 27), *range(36, 48))
"""Landmark numbers of the 68-point layout on the upper face: the brows (17-26) and the eyes (36-47)."""


def landmark_name(number: int) -> str:
    """The marker name of landmark ``number`` (0..67) in the shipped 68-point sets: ``lm_07``."""
    return f"lm_{number:02d}"


_NUMBERED = re.compile(r"^(?:[A-Za-z]+[_ ]?)?(\d+)$")


def landmark_number(name: str) -> int | None:
    """The landmark number a marker or column name carries (``"17"``, ``"X_17"``, ``"lm_17"``, ``"p17"``),
    or None."""
    match = _NUMBERED.match(name.strip())
    return int(match.group(1)) if match else None


def match_markers(names, marker_set: MarkerSet, allow_missing: bool = False, ignore_extra: bool = False,
                  source=None) -> np.ndarray:
    """Where each marker of ``marker_set`` is among a file's marker ``names``.

    Names match exactly; the markers left over are matched by landmark number when both sides are numbered
    (OpenFace's ``0`` .. ``67`` / ``X_0``-style columns against ``lm_00`` .. ``lm_67``).

    Parameters
    ----------
    names : sequence of str
        The file's marker names, in its order.
    marker_set : MarkerSet
    allow_missing : bool
        A marker of the set the file lacks gets -1 instead of an error.
    ignore_extra : bool
        File markers that are in no marker set are left out instead of an error.
    source : str or Path, optional
        The file, for error messages.

    Returns
    -------
    ndarray of int, shape (n_markers of the set,)
        Index into ``names`` of each marker of the set (-1: missing, when allowed).

    Raises
    ------
    InputError
        Naming the markers the file lacks, or the file's markers the set does not have.
    """
    names = [str(name) for name in names]
    position = {}
    for k, name in enumerate(names):
        if name in position:
            raise InputError(f"marker {name!r} appears twice", source)
        position[name] = k
    index = np.array([position.get(name, -1) for name in marker_set.names], dtype=np.int64)
    _match_numbers(names, marker_set.names, index, source)
    used = set(index[index >= 0].tolist())
    extra = [name for k, name in enumerate(names) if k not in used]
    missing = [name for name, k in zip(marker_set.names, index) if k < 0]
    problems = []  # both at once: a renamed marker shows up as one missing and one extra
    if missing and not allow_missing:
        problems.append(f"{len(missing)} marker{'s' if len(missing) > 1 else ''} of the marker set missing from "
                        f"the file: {_listing(missing)}")
    if extra and not ignore_extra:
        problems.append(f"{len(extra)} marker{'s' if len(extra) > 1 else ''} not in the marker set: "
                        f"{_listing(extra)}")
    if problems:
        raise InputError("; ".join(problems), source)
    return index


def _match_numbers(names: list[str], wanted, index: np.ndarray, source) -> None:
    """Fill ``index`` (in place) for the still-unmatched markers by landmark number."""
    used = set(index[index >= 0].tolist())
    by_number: dict[int, int] = {}
    for k, name in enumerate(names):
        number = landmark_number(name)
        if k in used or number is None:
            continue
        if number in by_number:
            raise InputError(f"markers {names[by_number[number]]!r} and {name!r} both carry landmark number "
                             f"{number}", source)
        by_number[number] = k
    for i, name in enumerate(wanted):
        number = landmark_number(name)
        if index[i] < 0 and number is not None and number in by_number:
            index[i] = by_number.pop(number)


def _listing(names: list[str], limit: int = 12) -> str:
    shown = ", ".join(map(repr, names[:limit]))
    return shown + (f" and {len(names) - limit} more" if len(names) > limit else "")


def _check_apart(names, triangles: np.ndarray, barycentric: np.ndarray) -> None:
    """Refuse two markers at one place (the same triangle and barycentric coordinates: a marker table copied
    and not edited), naming both: a spline through them, or a solve, cannot tell them apart."""
    seen = {}
    for name, triangle, weights in zip(names, triangles.tolist(), np.round(barycentric, 9).tolist()):
        other = seen.setdefault((triangle, *weights), name)
        if other != name:
            raise InputError(f"markers {other!r} and {name!r} are at the same place (triangle {triangle}, "
                             f"barycentric {weights}): was a marker copied and not moved?", field=f"marker {name}")
