"""STL files (binary and ASCII; binary written): the triangle mesh a sculpting or 3D-printing tool writes of a head.

An animatronic head's skin is sculpted and cast from printed moulds, so its mesh often exists only as STL. STL
gives each triangle its own three corners; corners written with the same coordinates are welded into one vertex
(numbered in the order they first appear), so the mesh has the shared edges every transfer needs. A binary file
is told from an ASCII one by its size (84 bytes plus 50 per triangle), not by its first word: binary headers may
begin with ``solid`` too. Every bad value is named by its triangle (binary) or its line (ASCII): a truncated
file, a wrong count, NaN or infinity, a facet without three corners.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from livebridge.errors import InputError

_HEADER = 80
_RECORD = np.dtype([("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attribute", "<u2")])


def read_stl(data: bytes, path: Path):
    """(points (n, 3), triangles (m, 3), no colours, no texture) of an STL file's bytes, corners welded."""
    corners = _binary(data, path) if _is_binary(data) else _ascii(data, path)
    if not len(corners):
        raise InputError("no triangles", path)
    bad = np.flatnonzero(~np.isfinite(corners).all(axis=(1, 2)))
    if len(bad):
        raise InputError(f"triangle {bad[0]} has a corner that is not finite ({corners[bad[0]].tolist()}; "
                         f"{len(bad)} such)", path, "triangle")
    points, triangles = weld(corners)
    return points, triangles, None


def weld(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (n, 3) float64, triangles (m, 3)) of triangle corners (m, 3, 3): corners with equal coordinates
    (in their own float type, -0 as 0) become one vertex, numbered in the order they first appear."""
    flat = np.ascontiguousarray(corners.reshape(-1, 3) + corners.dtype.type(0))  # -0.0 + 0 is +0.0
    # one opaque key per corner: 4x faster than np.unique(axis=0) on a 1M-triangle sculpt
    keys = flat.view(np.dtype((np.void, 3 * flat.itemsize))).ravel()
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return flat[first[order]].astype(np.float64), rank[inverse.reshape(-1)].reshape(-1, 3)


def stl_bytes(vertices: np.ndarray, triangles: np.ndarray, header: str = "") -> bytes:
    """A binary STL file of a triangle mesh (vertices (n, 3), triangles (m, 3)): float32 corners, unit normals
    (zero for a triangle without area), ``header`` (ASCII, at most 80 characters; never beginning with
    ``solid``, which readers take for ASCII)."""
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(triangles, dtype=np.int64)]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    records = np.zeros(len(corners), _RECORD)
    records["normal"] = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    records["corners"] = corners
    text = header.encode("ascii")[:80]
    text = b"binary " + text[:73] if text.lower().startswith(b"solid") else text
    return text.ljust(_HEADER, b" ") + np.uint32(len(corners)).tobytes() + records.tobytes()


def _is_binary(data: bytes) -> bool:
    if len(data) < _HEADER + 4:
        return False
    count = int(np.frombuffer(data, "<u4", 1, _HEADER)[0])
    return len(data) == _HEADER + 4 + count * _RECORD.itemsize or not data.lstrip().startswith(b"solid")


def _binary(data: bytes, path: Path) -> np.ndarray:
    count = int(np.frombuffer(data, "<u4", 1, _HEADER)[0])
    expected = _HEADER + 4 + count * _RECORD.itemsize
    if len(data) != expected:
        held = (len(data) - _HEADER - 4) / _RECORD.itemsize
        raise InputError(f"a binary STL of {count} triangles has {expected} bytes, this one {len(data)} (room for "
                         f"{held:.1f} triangles): truncated, or the count is wrong", path, "triangle count")
    return np.frombuffer(data, _RECORD, count, _HEADER + 4)["corners"]


def _ascii(data: bytes, path: Path) -> np.ndarray:
    try:
        lines = data.decode("ascii").splitlines()
    except UnicodeDecodeError as error:
        raise InputError(f"neither a binary STL (its size does not match its triangle count) nor ASCII text "
                         f"(byte {error.start} is not ASCII)", path) from None
    corners, facet, opened = [], [], 0
    for number, line in enumerate(lines, 1):
        words = line.split()
        if not words:
            continue
        keyword = words[0].lower()
        if keyword == "vertex":
            if len(words) != 4:
                raise InputError(f"line {number}: 'vertex' needs x y z, got {line.strip()!r}", path, "vertex")
            try:
                facet.append([float(word) for word in words[1:]])
            except ValueError:
                raise InputError(f"line {number}: {line.strip()!r} is not 'vertex x y z'", path, "vertex") from None
        elif keyword == "facet":
            facet, opened = [], number
        elif keyword == "endfacet":
            if len(facet) != 3:
                raise InputError(f"line {opened}: the facet has {len(facet)} corners, not 3", path, "facet")
            corners.append(facet)
            facet = []
    if facet:
        raise InputError(f"line {opened}: the last facet has no 'endfacet' (a truncated file?)", path, "facet")
    return np.asarray(corners, dtype=np.float64).reshape(-1, 3, 3)
