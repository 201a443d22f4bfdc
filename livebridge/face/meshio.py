"""Reading triangle meshes from OBJ files (quads and n-gons are fanned)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.errors import InputError, file_error
from livebridge.face.obj_file import read_obj_data


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
    """Read the vertices and faces of an OBJ file (:func:`~livebridge.face.obj_file.read_obj_data`: polygons
    become triangle fans; errors name the line at fault)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("mesh file not found", path)
    try:
        data = path.read_bytes()
    except OSError as error:
        raise file_error(error, path) from None
    obj = read_obj_data(data, path)
    if not len(obj.points):
        raise InputError("no vertices ('v' lines) found", path)
    return Mesh(obj.points, obj.triangles)


def edge_counts(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(edges (k, 2) as sorted vertex ids, how many triangles share each (k,)) of a triangle mesh.

    A collapsed triangle's zero-length edges (a vertex to itself) are not edges."""
    edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    edges = edges[edges[:, 0] != edges[:, 1]]
    base = int(edges.max()) + 1
    keys, counts = np.unique(edges[:, 0].astype(np.int64) * base + edges[:, 1], return_counts=True)
    return np.stack([keys // base, keys % base], axis=1), counts


def rim_vertices(triangles: np.ndarray) -> np.ndarray:
    """Vertex ids (k,) on an edge only one triangle has: the rims of a mesh's outline and of its holes."""
    edges, counts = edge_counts(triangles)
    return np.unique(edges[counts == 1])


def median_edge_length(vertices: np.ndarray, edges: np.ndarray) -> float:
    """The median length of ``edges`` (k, 2) between ``vertices`` (n, 3); 0 with no edge."""
    if not len(edges):
        return 0.0
    return float(np.median(np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)))


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


def triangle_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Each triangle's area, shape (n_triangles,), of ``vertices`` (n, 3) and ``triangles`` (n_triangles, 3); NaN
    where a corner is not finite."""
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(triangles, dtype=np.int64)]
    return 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)


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
