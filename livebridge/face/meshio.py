"""Reading triangle meshes from OBJ files (quads and n-gons are fanned)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.errors import InputError


@dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh.

    Attributes
    ----------
    vertices : ndarray, shape (n_vertices, 3)
    triangles : ndarray of int, shape (n_triangles, 3)
    """

    vertices: np.ndarray
    triangles: np.ndarray


def read_obj(path: str | Path) -> Mesh:
    """Read the vertices and faces of an OBJ file; polygons become triangle fans."""
    path = Path(path)
    if not path.is_file():
        raise InputError("mesh file not found", path)
    vertices, triangles = [], []
    with path.open("r", errors="replace") as stream:
        for line_no, line in enumerate(stream, 1):
            if line.startswith("v "):
                vertices.append(line.split()[1:4])
            elif line.startswith("f "):
                try:
                    corners = [int(token.split("/")[0]) for token in line.split()[1:]]
                except ValueError:
                    raise InputError(f"line {line_no}: malformed face {line.strip()!r}", path) from None
                corners = [c - 1 if c > 0 else len(vertices) + c for c in corners]
                triangles.extend((corners[0], corners[k], corners[k + 1]) for k in range(1, len(corners) - 1))
    if not vertices:
        raise InputError("no vertices ('v' lines) found", path)
    try:
        vertex_array = np.asarray(vertices, dtype=np.float64)
    except ValueError:
        raise InputError("a vertex line has fewer than 3 numeric coordinates", path) from None
    bad = np.flatnonzero(~np.isfinite(vertex_array).all(axis=1))
    if len(bad):  # a NaN or infinite vertex poisons every nearest-point search and spline that touches the mesh
        raise InputError(f"vertex {bad[0] + 1} is not finite ({' '.join(vertices[bad[0]])}; {len(bad)} such)", path,
                         "v")
    triangle_array = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if triangle_array.size and (triangle_array.min() < 0 or triangle_array.max() >= len(vertex_array)):
        raise InputError("a face refers to a vertex that does not exist", path)
    return Mesh(vertex_array, triangle_array)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals, of one mesh or a batch of deformations of it.

    Parameters
    ----------
    vertices : ndarray, shape (..., n_vertices, 3)
    triangles : ndarray of int, shape (n_triangles, 3)

    Returns
    -------
    ndarray, shape (..., n_vertices, 3)
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    if vertices.ndim > 2:
        flat = vertices.reshape(-1, vertices.shape[-2], 3)
        return np.stack([vertex_normals(v, triangles) for v in flat]).reshape(vertices.shape)
    corner = vertices[triangles]  # (T, 3, 3)
    face_normals = np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])  # length = 2 * area
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, triangles[:, k], face_normals)
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    return normals / np.where(length > 0, length, 1.0)


def triangle_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit normals of the given triangles, of one mesh or a batch of deformations of it.

    Parameters
    ----------
    vertices : ndarray, shape (..., n_vertices, 3)
    triangles : ndarray of int, shape (n_triangles, 3)

    Returns
    -------
    ndarray, shape (..., n_triangles, 3)
    """
    a = vertices[..., triangles[:, 0], :]
    normal = np.cross(vertices[..., triangles[:, 1], :] - a, vertices[..., triangles[:, 2], :] - a)
    return normal / np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
