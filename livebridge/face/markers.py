"""Virtual markers: physical markers as points on the face surface.

Each marker is a triangle index plus barycentric coordinates, so its
position follows any deformation of the mesh. ``face`` markers move with
expression; ``head`` markers sit on the rigid head rig and do not.
"""

from __future__ import annotations

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
    """

    names: tuple[str, ...]
    triangles: np.ndarray
    barycentric: np.ndarray
    regions: tuple[str, ...]
    roles: tuple[str, ...]

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
            raise InputError("barycentric coordinates must be >= 0 and sum to 1", field=f"marker {name}")
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
            tuple(self.regions[i] for i in index), tuple(self.roles[i] for i in index),
        )

    def check_mesh(self, n_triangles: int) -> None:
        """Raise if a marker refers to a triangle the mesh does not have."""
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
        save_toml(path, {
            "format": MARKERS_FORMAT,
            "version": MARKERS_VERSION,
            "marker": [
                {"name": n, "triangle": int(t), "barycentric": [float(b) for b in bary], "region": r, "role": o}
                for n, t, bary, r, o in zip(self.names, self.triangles, self.barycentric, self.regions, self.roles)
            ],
        })

    @classmethod
    def load(cls, path: str | Path) -> MarkerSet:
        """Read a marker set written by :meth:`save`; errors name the file and marker."""
        data = load_toml(path)
        if data.get("format") != MARKERS_FORMAT:
            raise InputError(f"format must be {MARKERS_FORMAT!r}", path, "format")
        if data.get("version", 0) > MARKERS_VERSION:
            raise InputError(f"version {data['version']} is newer than this livebridge reads", path, "version")
        rows = require(data, "marker", list, path)
        fields = {"names": [], "triangles": [], "barycentric": [], "regions": [], "roles": []}
        for k, row in enumerate(rows):
            prefix = f"marker[{k}]"
            fields["names"].append(require(row, "name", str, path, prefix))
            fields["triangles"].append(require(row, "triangle", int, path, prefix))
            bary = require(row, "barycentric", list, path, prefix)
            if len(bary) != 3:
                raise InputError("needs 3 barycentric coordinates", path, f"{prefix}.barycentric")
            fields["barycentric"].append(bary)
            fields["regions"].append(require(row, "region", str, path, prefix))
            fields["roles"].append(row.get("role", "face"))
        try:
            return cls(**fields)
        except InputError as error:
            raise InputError(error.message, path, error.field) from None
