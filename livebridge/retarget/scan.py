"""Reading 3D scans: point clouds and meshes from PLY (ASCII, binary little/big endian), OBJ and XYZ/CSV.

A scan is what a scanner wrote: points, and triangles when the scanner meshed them (faces with more than
three corners become triangle fans). Every reader checks what it reads and names the file and the line
(text) or the element (binary) of the first bad value: a truncated file, a wrong count, NaN or infinity, a
face that points at a vertex that does not exist.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.errors import InputError, file_error

SCAN_SUFFIXES = (".ply", ".obj", ".xyz", ".csv", ".txt", ".pts", ".asc")
"""Suffixes :func:`read_scan` knows (all but .ply and .obj are read as x y z point lists)."""


@dataclass(frozen=True, eq=False)
class Scan:
    """Points of a scanned surface, and its triangles when the scan is a mesh.

    Attributes
    ----------
    points : ndarray, shape (n_points, 3)
        Finite, in the file's units times the reader's ``scale``.
    triangles : ndarray of int, shape (n_triangles, 3)
        Empty (0, 3) for a point cloud.
    """

    points: np.ndarray
    triangles: np.ndarray

    def __post_init__(self):
        for name, dtype in (("points", np.float64), ("triangles", np.int64)):
            array = np.array(getattr(self, name), dtype=dtype).reshape(-1, 3)
            array.setflags(write=False)
            object.__setattr__(self, name, array)

    @property
    def is_mesh(self) -> bool:
        return len(self.triangles) > 0


def read_scan(path: str | Path, scale: float = 1.0) -> Scan:
    """Read a scan by its suffix (:data:`SCAN_SUFFIXES`); coordinates are multiplied by ``scale`` (to mm)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SCAN_SUFFIXES:
        raise InputError(f"unknown scan type {suffix or '(no suffix)'!r}: give one of {', '.join(SCAN_SUFFIXES)}",
                         path)
    try:
        data = path.read_bytes()
    except OSError as error:
        raise file_error(error, path) from None
    if not data.strip():
        raise InputError("empty file: no points", path)
    reader = {".ply": _read_ply, ".obj": _read_obj}.get(suffix, _read_xyz)
    points, triangles = reader(data, path)
    if not len(points):
        raise InputError("no points", path)
    _check_faces(triangles, len(points), path)
    return Scan(points * scale, triangles)


# ------------------------------------------------------------------------------------------------ XYZ / CSV
_SEPARATORS = re.compile(r"[,;\s]+")


def _read_xyz(data: bytes, path: Path):
    """``x y z [more columns]`` per line, separated by spaces, tabs, commas or semicolons.

    A first line that is not numbers is a header (when it names x, y and z, those columns are read); lines
    starting with ``#`` or ``//`` are comments.
    """
    columns = (0, 1, 2)
    rows, first = [], True
    for number, line in enumerate(_text(data, path).splitlines(), 1):
        text = line.strip()
        if not text or text.startswith(("#", "//")):
            continue
        cells = [cell for cell in _SEPARATORS.split(text) if cell]
        if first and not _is_number(cells[0]):
            columns, first = _header_columns(cells, columns, path, number), False
            continue
        first = False
        if len(cells) <= max(columns):
            raise InputError(f"line {number}: expected at least {max(columns) + 1} values (x y z), got "
                             f"{len(cells)}: {text[:60]!r}", path)
        try:
            xyz = [float(cells[k]) for k in columns]
        except ValueError:
            raise InputError(f"line {number}: x, y, z must be numbers, got {[cells[k] for k in columns]}",
                             path) from None
        if not all(map(math.isfinite, xyz)):
            raise InputError(f"line {number}: x, y, z must be finite, got {[cells[k] for k in columns]}", path)
        rows.append(xyz)
    return np.array(rows, dtype=np.float64).reshape(-1, 3), np.zeros((0, 3), np.int64)


def _header_columns(cells, default, path, number):
    names = [cell.strip().strip('"').lower() for cell in cells]
    if all(axis in names for axis in "xyz"):
        return tuple(names.index(axis) for axis in "xyz")
    if any(_is_number(cell) for cell in cells[1:]):
        raise InputError(f"line {number}: x, y, z must be numbers, got {cells[:3]}", path)
    return default


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _text(data: bytes, path: Path) -> str:
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise InputError(f"not UTF-8 text (byte {data[error.start:error.start + 1]!r} at offset {error.start})",
                         path) from None


# ------------------------------------------------------------------------------------------------ OBJ
def _read_obj(data: bytes, path: Path):
    """``v x y z [r g b]`` and ``f a b c ...`` lines (``a/t/n`` corners, negative = relative); the rest ignored."""
    vertices, triangles = [], []
    for number, line in enumerate(data.decode("utf-8", errors="replace").splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v":
            try:
                xyz = [float(value) for value in parts[1:4]]
            except ValueError:
                raise InputError(f"line {number}: vertex coordinates must be numbers, got {parts[1:4]}",
                                 path) from None
            if len(xyz) < 3:
                raise InputError(f"line {number}: a vertex needs x y z, got {len(xyz)} values", path)
            if not all(map(math.isfinite, xyz)):
                raise InputError(f"line {number}: vertex {len(vertices) + 1} is not finite: {parts[1:4]}", path)
            vertices.append(xyz)
        elif parts[0] == "f":
            try:
                corners = [int(token.split("/")[0]) for token in parts[1:]]
            except ValueError:
                raise InputError(f"line {number}: malformed face {line.strip()!r}", path) from None
            if len(corners) < 3 or 0 in corners:
                raise InputError(f"line {number}: a face needs 3 or more vertex numbers from 1 (or negative), "
                                 f"got {line.strip()!r}", path)
            corners = [c - 1 if c > 0 else len(vertices) + c for c in corners]
            bad = [c for c in corners if not 0 <= c < len(vertices)]
            if bad:
                raise InputError(f"line {number}: face refers to vertex {bad[0] + 1}, only {len(vertices)} "
                                 "defined so far", path)
            triangles.extend((corners[0], corners[k], corners[k + 1]) for k in range(1, len(corners) - 1))
    return np.array(vertices, dtype=np.float64).reshape(-1, 3), np.array(triangles, dtype=np.int64).reshape(-1, 3)


# ------------------------------------------------------------------------------------------------ PLY
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
_FACE_LISTS = ("vertex_indices", "vertex_index")


@dataclass(frozen=True)
class _Property:
    name: str
    dtype: str  # numpy type code without byte order
    count_dtype: str | None = None  # a list property: the type of its length

    @property
    def is_list(self) -> bool:
        return self.count_dtype is not None


@dataclass(frozen=True)
class _Element:
    name: str
    count: int
    properties: tuple[_Property, ...]


def _read_ply(data: bytes, path: Path):
    """The ``vertex`` element's x, y, z and the ``face`` element's vertex index lists; other elements skipped."""
    order, elements, body = _ply_header(data, path)
    names = [element.name for element in elements]
    if "vertex" not in names:
        raise InputError("no 'element vertex' in the PLY header", path)
    vertex = elements[names.index("vertex")]
    missing = [axis for axis in "xyz" if axis not in [p.name for p in vertex.properties]]
    if missing:
        raise InputError(f"the vertex element has no property {', '.join(missing)}", path, "vertex")
    if order is None:
        tables = _ply_ascii(body, elements, path, data[:len(data) - len(body)].count(b"\n"))
    else:
        tables = _ply_binary(body, elements, order, path)
    table = tables["vertex"]
    points = np.stack([np.asarray(table[axis], dtype=np.float64) for axis in "xyz"], axis=1)
    bad = np.flatnonzero(~np.isfinite(points).all(axis=1))
    if len(bad):
        raise InputError(f"vertex {bad[0]} is not finite ({points[bad[0]].tolist()}; {len(bad)} such)", path,
                         "vertex")
    faces = tables.get("face", {})
    lists = [faces[name] for name in _FACE_LISTS if name in faces]
    triangles = np.zeros((0, 3), np.int64)
    if lists:
        triangles = _fan(lists[0], path)
    return points, triangles


def _ply_header(data: bytes, path: Path):
    if not data.startswith(b"ply"):
        raise InputError("not a PLY file (it must start with 'ply')", path)
    end = re.search(rb"end_header[ \t]*\r?\n", data)
    if end is None:
        raise InputError("the PLY header has no 'end_header' line", path)
    order, elements = "missing", []
    lines = data[:end.start()].decode("ascii", errors="replace").splitlines()
    for number, line in enumerate(lines[1:], 2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        where = f"header line {number}"
        if words[0] == "format":
            if len(words) < 2 or words[1] not in _PLY_FORMATS:
                raise InputError(f"{where}: unknown format {' '.join(words[1:2])!r}; known: "
                                 f"{', '.join(_PLY_FORMATS)}", path)
            order = _PLY_FORMATS[words[1]]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise InputError(f"{where}: expected 'element NAME COUNT', got {line.strip()!r}", path)
            elements.append(_Element(words[1], int(words[2]), ()))
        elif words[0] == "property":
            if not elements:
                raise InputError(f"{where}: a property before any element", path)
            prop = _ply_property(words, where, path)
            last = elements[-1]
            elements[-1] = _Element(last.name, last.count, last.properties + (prop,))
        else:
            raise InputError(f"{where}: unknown header keyword {words[0]!r}", path)
    if order == "missing":
        raise InputError("the PLY header has no 'format' line", path)
    return order, elements, data[end.end():]


def _ply_property(words, where, path) -> _Property:
    try:
        if words[1] == "list":
            return _Property(words[4], _PLY_TYPES[words[3]], _PLY_TYPES[words[2]])
        return _Property(words[2], _PLY_TYPES[words[1]])
    except (IndexError, KeyError):
        raise InputError(f"{where}: malformed property {' '.join(words)!r} (types: "
                         f"{', '.join(sorted(_PLY_TYPES))})", path) from None


def _ply_ascii(body: bytes, elements, path: Path, header_lines: int) -> dict:
    lines = body.decode("ascii", errors="replace").splitlines()
    tables, at = {}, 0
    for element in elements:
        columns = {p.name: [] for p in element.properties}
        for k in range(element.count):
            while at < len(lines) and not lines[at].strip():
                at += 1
            if at >= len(lines):
                raise InputError(f"the file ends at {element.name} {k} of {element.count} (the header promises "
                                 f"{element.count})", path, element.name)
            line_number = header_lines + at + 1
            values = lines[at].split()
            at += 1
            try:
                _ascii_row(values, element, columns)
            except (ValueError, IndexError):
                raise InputError(f"line {line_number} ({element.name} {k}): expected "
                                 f"{_describe(element)}, got {' '.join(values)[:60]!r}", path,
                                 element.name) from None
        tables[element.name] = columns
    return tables


def _ascii_row(values, element, columns) -> None:
    at = 0
    for prop in element.properties:
        if prop.is_list:
            n = int(values[at])
            items = [int(v) if prop.dtype[0] in "iu" else float(v) for v in values[at + 1:at + 1 + n]]
            if len(items) != n or n < 0:
                raise ValueError
            columns[prop.name].append(items)
            at += 1 + n
        else:
            columns[prop.name].append(float(values[at]) if prop.dtype[0] == "f" else int(values[at]))
            at += 1
    if at != len(values):
        raise ValueError


def _describe(element) -> str:
    return " ".join(f"[n {p.name}...]" if p.is_list else p.name for p in element.properties)


def _ply_binary(body: bytes, elements, order: str, path: Path) -> dict:
    tables, at = {}, 0
    for element in elements:
        if not any(p.is_list for p in element.properties):
            dtype = np.dtype([(p.name, order + p.dtype) for p in element.properties])
            needed = dtype.itemsize * element.count
            if at + needed > len(body):
                got = (len(body) - at) // max(dtype.itemsize, 1)
                raise InputError(f"the file ends at {element.name} {got} of {element.count} (the header promises "
                                 f"{element.count})", path, element.name)
            table = np.frombuffer(body, dtype, element.count, at)
            tables[element.name] = {p.name: table[p.name] for p in element.properties}
            at += needed
        else:
            tables[element.name], at = _binary_lists(body, at, element, order, path)
    return tables


def _binary_lists(body: bytes, at: int, element: _Element, order: str, path: Path):
    """An element with list properties: every row of the same length read at once, else row by row."""
    fixed = _binary_fixed_rows(body, at, element, order)
    if fixed is not None:
        return fixed
    columns = {p.name: [] for p in element.properties}
    for k in range(element.count):
        for prop in element.properties:
            try:
                if prop.is_list:
                    n = int(np.frombuffer(body, order + prop.count_dtype, 1, at)[0])
                    at += np.dtype(prop.count_dtype).itemsize
                    columns[prop.name].append(np.frombuffer(body, order + prop.dtype, n, at).tolist())
                    at += n * np.dtype(prop.dtype).itemsize
                else:
                    columns[prop.name].append(np.frombuffer(body, order + prop.dtype, 1, at)[0])
                    at += np.dtype(prop.dtype).itemsize
            except ValueError:
                raise InputError(f"the file ends inside {element.name} {k} of {element.count} (the header promises "
                                 f"{element.count})", path, element.name) from None
    return columns, at


def _binary_fixed_rows(body: bytes, at: int, element: _Element, order: str):
    """Rows whose lists all have the first row's lengths, read with one structured dtype; None if they do not."""
    fields, offset = [], at
    for prop in element.properties:
        if prop.is_list:
            if offset + np.dtype(prop.count_dtype).itemsize > len(body):
                return None
            n = int(np.frombuffer(body, order + prop.count_dtype, 1, offset)[0])
            fields += [(prop.name + "#n", order + prop.count_dtype), (prop.name, order + prop.dtype, (n,))]
            offset += np.dtype(prop.count_dtype).itemsize + n * np.dtype(prop.dtype).itemsize
        else:
            fields.append((prop.name, order + prop.dtype))
            offset += np.dtype(prop.dtype).itemsize
    dtype = np.dtype(fields)
    if at + dtype.itemsize * element.count > len(body):
        return None
    table = np.frombuffer(body, dtype, element.count, at)
    for prop in element.properties:
        if prop.is_list and np.any(table[prop.name + "#n"] != table[prop.name].shape[1]):
            return None
    return {p.name: table[p.name] for p in element.properties}, at + dtype.itemsize * element.count


def _fan(faces, path: Path) -> np.ndarray:
    """Triangles from face index lists (an (m, k) array or a list of lists): polygons become fans."""
    if isinstance(faces, np.ndarray) and faces.ndim == 2:
        rows = [faces]
    else:
        rows = [np.asarray(face, dtype=np.int64)[None] for face in faces]
    triangles = []
    for k, row in enumerate(rows):
        if row.shape[1] < 3:
            raise InputError(f"face {k} has {row.shape[1]} corners (at least 3)", path, "face")
        triangles += [np.stack([row[:, 0], row[:, j], row[:, j + 1]], axis=1) for j in range(1, row.shape[1] - 1)]
    return np.concatenate(triangles).astype(np.int64) if triangles else np.zeros((0, 3), np.int64)


def _check_faces(triangles: np.ndarray, n_points: int, path: Path) -> None:
    if not len(triangles):
        return
    bad = np.flatnonzero((triangles < 0).any(axis=1) | (triangles >= n_points).any(axis=1))
    if len(bad):
        raise InputError(f"a face refers to vertex {int(triangles[bad[0]].max())}, which does not exist "
                         f"(vertices 0..{n_points - 1}; {len(bad)} such triangles)", path, "face")


# ------------------------------------------------------------------------------------------------ writing
def write_ply(path: str | Path, points: np.ndarray, triangles: np.ndarray | None = None,
              encoding: str = "binary_little_endian") -> None:
    """Write points (n, 3) and optional triangles (m, 3) as PLY (``ascii``, ``binary_little_endian`` or
    ``binary_big_endian``): float32 x y z, faces as ``uchar``-counted ``int`` lists."""
    points = np.asarray(points, dtype=np.float64)
    triangles = np.zeros((0, 3), np.int64) if triangles is None else np.asarray(triangles, dtype=np.int64)
    header = [f"ply\nformat {encoding} 1.0\nelement vertex {len(points)}\nproperty float x\nproperty float y\n"
              "property float z\n"]
    if len(triangles):
        header.append(f"element face {len(triangles)}\nproperty list uchar int vertex_indices\n")
    header.append("end_header\n")
    with open(path, "wb") as stream:
        stream.write("".join(header).encode("ascii"))
        if encoding == "ascii":
            stream.write("".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in points).encode("ascii"))
            stream.write("".join(f"3 {a} {b} {c}\n" for a, b, c in triangles).encode("ascii"))
            return
        order = _PLY_FORMATS[encoding]
        stream.write(points.astype(order + "f4").tobytes())
        faces = np.zeros(len(triangles), np.dtype([("n", "u1"), ("i", order + "i4", (3,))]))
        faces["n"], faces["i"] = 3, triangles
        stream.write(faces.tobytes())
