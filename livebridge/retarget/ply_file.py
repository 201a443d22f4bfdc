"""PLY files (ASCII, binary little and big endian): a scan's points, colours, faces and texture, and writing them.

The ``vertex`` element's x, y, z, colour (``red green blue`` or ``diffuse_red ..``: integers scaled by their
type's maximum, floats taken as 0-1) and normal (``nx ny nz`` or ``normal_x ..``), the ``face`` element's vertex
index lists (faces with more than three corners become triangle fans) and, with ``comment TextureFile`` lines
(as MeshLab writes them), the texture on the faces' ``texcoord`` lists or the vertices' ``s t``. Other elements
are skipped. Every bad value is named by its element and row: a truncated file, a wrong count, NaN or infinity,
a face that points at a vertex that does not exist. :func:`~livebridge.retarget.scan.read_scan` reads PLY scans
through :func:`read_ply`.
"""

from __future__ import annotations

import itertools
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.errors import InputError
from livebridge.retarget.checks import check_faces
from livebridge.retarget.texture import Texture

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


def read_ply(data: bytes, path: Path):
    """The ``vertex`` element's x, y, z (and colour, normal), the ``face`` element's vertex index lists and, with
    ``comment TextureFile`` lines, their texture (:func:`_ply_texture`); other elements skipped."""
    order, elements, body, comments = _ply_header(data, path)
    names = [element.name for element in elements]
    if "vertex" not in names:
        raise InputError("no 'element vertex' in the PLY header", path)
    vertex = elements[names.index("vertex")]
    missing = [axis for axis in "xyz" if axis not in [p.name for p in vertex.properties]]
    if missing:
        raise InputError(f"the vertex element has no property {', '.join(missing)}", path, "vertex")
    lists = [p.name for p in vertex.properties if p.name in ("x", "y", "z") and p.is_list]
    if lists:
        raise InputError(f"the vertex element's {', '.join(lists)} is a list, not a number", path, "vertex")
    if order is None:
        tables = _ply_ascii(body, elements, path, data[:len(data) - len(body)].count(b"\n"))
    else:
        tables = _ply_binary(body, elements, order, path)
    table = tables["vertex"]
    with np.errstate(invalid="ignore"):  # a signalling NaN warns as it widens; it is refused just below
        points = np.stack([np.asarray(table[axis], dtype=np.float64) for axis in "xyz"], axis=1)
    bad = np.flatnonzero(~np.isfinite(points).all(axis=1))
    if len(bad):
        raise InputError(f"vertex {bad[0]} is not finite ({points[bad[0]].tolist()}; {len(bad)} such)", path,
                         "vertex")
    faces = tables.get("face", {})
    lists = [faces[name] for name in _FACE_LISTS if name in faces]
    triangles, texture = np.zeros((0, 3), np.int64), None
    if lists:
        triangles, corners, face_of = _fan(lists[0], path)
        check_faces(triangles, len(points), path)  # before the vertices' texture coordinates are indexed
        texture = _ply_texture(path, comments, table, faces, triangles, corners, face_of)
    colours = _ply_colours(vertex, table)
    # as for OBJ: the images hold the skin's pattern finer than the vertices
    return points, triangles, None if texture is not None else colours, texture, _ply_normals(vertex, table)


NORMAL_NAMES = (("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z"))
"""The names a point's normal is written under (PLY vertex properties, XYZ/CSV header columns)."""


def _ply_normals(vertex: _Element, table: dict) -> np.ndarray | None:
    """The vertices' normals (n, 3) as written, None without."""
    names = {p.name for p in vertex.properties if not p.is_list}
    for triple in NORMAL_NAMES:
        if all(name in names for name in triple):
            with np.errstate(invalid="ignore"):  # a signalling NaN: refused by the scan's reader, naming the point
                return np.stack([np.asarray(table[name], dtype=np.float64) for name in triple], axis=1)
    return None


_PLY_TEXCOORDS = (("s", "t"), ("u", "v"), ("texture_u", "texture_v"), ("texture_s", "texture_t"))


def _ply_texture(path: Path, comments: list[str], vertex_table: dict, faces: dict, triangles: np.ndarray,
                 corners: np.ndarray, face_of: np.ndarray) -> Texture | None:
    """The :class:`~livebridge.retarget.texture.Texture` of a PLY mesh (as MeshLab writes it): the images of its
    ``comment TextureFile`` lines (next to the PLY), one per face by its ``texnumber`` (default the first), on
    the faces' ``texcoord`` lists (u v per corner, v up as in OBJ) or else the vertices' ``s t`` (or ``u v``,
    ``texture_u texture_v``, ``texture_s texture_t``); None without images or texture coordinates.

    ``triangles``, ``corners`` and ``face_of``: the faces' fans (:func:`_fan`).
    """
    from livebridge.retarget.texture import image_path, read_image

    files = [words[1].strip() for words in (comment.split(maxsplit=1) for comment in comments)
             if len(words) == 2 and words[0].lower() == "texturefile"]
    if not files:
        return None
    if "texcoord" in faces:
        uv = _ply_face_uv(path, faces["texcoord"], corners, face_of)
    else:
        uv = _ply_vertex_uv(path, vertex_table, triangles)
    if uv is None:
        return None
    number = np.zeros(len(face_of))
    if "texnumber" in faces:
        number = np.asarray(faces["texnumber"], dtype=np.float64)[face_of]
    bad = np.flatnonzero(~((number == np.round(number)) & (number >= 0) & (number < len(files))))
    if len(bad):
        raise InputError(f"face {face_of[bad[0]]}: texnumber {number[bad[0]]:g} picks none of the {len(files)} "
                         f"TextureFile comments (0..{len(files) - 1})", path, "texnumber")
    used, image_index = np.unique(number.astype(np.int64), return_inverse=True)
    remedy = "put it next to the PLY, or remove the TextureFile comment to read the scan as shape only"
    images = tuple(read_image(image_path(path.parent, files[k]), path, "TextureFile", remedy) for k in used)
    return Texture(uv, image_index.reshape(-1).astype(np.int64), images, tuple(Path(files[k]).name for k in used))


def _ply_face_uv(path: Path, texcoord, corners: np.ndarray, face_of: np.ndarray) -> np.ndarray:
    """Texture coordinates (n_triangles, 3, 2) from the faces' ``texcoord`` lists, fanned as their vertices."""
    lengths = _lengths(texcoord)
    n_corners = np.bincount(face_of, minlength=len(lengths)) + 2  # a polygon of k corners fans into k - 2
    bad = np.flatnonzero(lengths != 2 * n_corners)
    if len(bad):
        raise InputError(f"face {bad[0]}: {lengths[bad[0]]} texcoord values for {n_corners[bad[0]]} corners (u v "
                         f"for each; {len(bad)} such faces)", path, "texcoord")
    uv = _flat(texcoord, np.float64).reshape(-1, 2)[corners]
    bad = np.flatnonzero(~np.isfinite(uv).all(axis=(1, 2)))
    if len(bad):
        raise InputError(f"face {face_of[bad[0]]}: texcoord is not finite ({uv[bad[0]].ravel().tolist()})", path,
                         "texcoord")
    return uv


def _ply_vertex_uv(path: Path, table: dict, triangles: np.ndarray) -> np.ndarray | None:
    """Texture coordinates (n_triangles, 3, 2) from the vertices' (:data:`_PLY_TEXCOORDS`); None without."""
    for names in _PLY_TEXCOORDS:
        if all(name in table for name in names):
            uv = np.stack([np.asarray(table[name], dtype=np.float64) for name in names], axis=1)
            bad = np.flatnonzero(~np.isfinite(uv).all(axis=1))
            if len(bad):
                raise InputError(f"vertex {bad[0]}: texture coordinates {uv[bad[0]].tolist()} are not finite "
                                 f"({len(bad)} such)", path, " ".join(names))
            return uv[triangles]
    return None


_PLY_COLOURS = (("red", "green", "blue"), ("diffuse_red", "diffuse_green", "diffuse_blue"), ("r", "g", "b"))


def _ply_colours(vertex: _Element, table: dict) -> np.ndarray | None:
    """RGB in 0-1 from the vertex colour properties: integers over their type's maximum, floats as they are."""
    types = {p.name: p.dtype for p in vertex.properties}
    for names in _PLY_COLOURS:
        if all(name in types for name in names):
            channels = []
            for name in names:
                values = np.asarray(table[name], dtype=np.float64)
                if types[name][0] == "u":
                    values = values / float(np.iinfo(np.dtype(types[name])).max)
                channels.append(values)
            return np.stack(channels, axis=1)
    return None


def _ply_header(data: bytes, path: Path):
    """The body's byte order (None: ascii), the elements, the body and the ``comment`` lines' text."""
    if not data.startswith(b"ply"):
        raise InputError("not a PLY file (it must start with 'ply')", path)
    end = re.search(rb"end_header[ \t]*\r?\n", data)
    if end is None:
        raise InputError("the PLY header has no 'end_header' line", path)
    order, elements, comments = "missing", [], []
    lines = data[:end.start()].decode("utf-8", errors="replace").splitlines()  # TextureFile names may be UTF-8
    for number, line in enumerate(lines[1:], 2):
        words = line.split()
        if words[:1] == ["comment"]:
            comments.append(line.split(maxsplit=1)[1] if len(words) > 1 else "")  # TextureFile names are here
            continue
        if not words or words[0] == "obj_info":
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
    return order, elements, data[end.end():], comments


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
        fixed = _ascii_fixed_rows(lines[at:at + element.count], element)
        if fixed is not None:
            tables[element.name] = fixed
            at += element.count
            continue
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
    extra = [k for k in range(at, len(lines)) if lines[k].strip()]
    if extra and elements:
        last = elements[-1]
        raise InputError(f"line {header_lines + extra[0] + 1}: {len(extra)} more rows than the header promises "
                         f"(it ends with {last.count} {last.name} rows): is its count right?", path, last.name)
    return tables


def _ascii_fixed_rows(rows: list[str], element: _Element) -> dict | None:
    """An element's ``rows`` (its lines) read at once, as arrays, when every row has the first row's list
    lengths and whole numbers where the types are integers; None if not (the rows are then read one by one,
    which names the first bad line): 1M faces in ~1 s instead of ~10."""
    if not rows or len(rows) < element.count:
        return None
    words = rows[0].split()
    layout, width = [], 0
    for prop in element.properties:
        n = None
        if prop.is_list:
            if width >= len(words) or not words[width].isdigit():
                return None
            n = int(words[width])
            width += 1
        layout.append((prop, width, n))
        width += 1 if n is None else n
    if np.any(np.fromiter(map(len, map(str.split, rows)), np.int64, len(rows)) != width):
        return None  # also a blank line among them
    try:
        table = np.array(" ".join(rows).split(), dtype=np.float64).reshape(len(rows), width)
    except ValueError:
        return None
    out = {}
    for prop, start, n in layout:
        if n is not None and np.any(table[:, start - 1] != n):
            return None
        values = table[:, start] if n is None else table[:, start:start + n]
        if prop.dtype[0] in "iu":
            if not np.array_equal(values, np.round(values)):
                return None
            values = values.astype(np.int64)
        out[prop.name] = values
    return out


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
    if body[at:].strip() and elements:  # a trailing line break is harmless; rows the header does not count are not
        last = elements[-1]
        raise InputError(f"{len(body) - at} bytes after the {last.count} {last.name} rows the header promises: is "
                         "its count right?", path, last.name)
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
                    if n < 0:
                        raise InputError(f"{element.name} {k}: its {prop.name} list has {n} entries", path,
                                         element.name)
                    at += np.dtype(prop.count_dtype).itemsize
                    columns[prop.name].append(np.frombuffer(body, order + prop.dtype, n, at).tolist())
                    at += n * np.dtype(prop.dtype).itemsize
                else:
                    columns[prop.name].append(np.frombuffer(body, order + prop.dtype, 1, at)[0])
                    at += np.dtype(prop.dtype).itemsize
            except InputError:
                raise
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
            if n < 0:  # the row-by-row reader names it
                return None
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


def _fan(faces, path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangles from face index lists (an (m, k) array or a list of lists): polygons become fans.

    Returns
    -------
    triangles : ndarray of int, shape (n_triangles, 3)
    corners : ndarray of int, shape (n_triangles, 3)
        Each triangle corner's place among all the faces' corners in file order: values per face corner
        (``texcoord``), flattened, are fanned exactly as the vertices by indexing them with it.
    face_of : ndarray of int, shape (n_triangles,)
        The face each triangle is part of.
    """
    lengths = _lengths(faces)
    if isinstance(faces, np.ndarray) and faces.ndim == 2:
        rows = [np.arange(faces.size).reshape(faces.shape)]
    else:
        starts = np.cumsum(lengths) - lengths
        rows = [np.arange(start, start + n)[None] for start, n in zip(starts, lengths)]
    fans = []
    for k, row in enumerate(rows):
        if row.shape[1] < 3:
            raise InputError(f"face {k} has {row.shape[1]} corners (at least 3)", path, "face")
        fans += [np.stack([row[:, 0], row[:, j], row[:, j + 1]], axis=1) for j in range(1, row.shape[1] - 1)]
    corners = np.concatenate(fans) if fans else np.zeros((0, 3), np.int64)
    face_of = np.repeat(np.arange(len(lengths)), lengths)[corners[:, 0]]
    return _flat(faces, np.int64)[corners], corners, face_of


def _lengths(lists) -> np.ndarray:
    """The length of each list of a list property (an (m, k) array or a list of lists)."""
    if isinstance(lists, np.ndarray) and lists.ndim == 2:
        return np.full(len(lists), lists.shape[1], dtype=np.int64)
    return np.array([len(items) for items in lists], dtype=np.int64)


def _flat(lists, dtype) -> np.ndarray:
    """A list property's values, all rows one after the other."""
    if isinstance(lists, np.ndarray):
        return lists.astype(dtype).reshape(-1)
    return np.fromiter(itertools.chain.from_iterable(lists), dtype=dtype)


def write_ply(path: str | Path, points: np.ndarray, triangles: np.ndarray | None = None,
              encoding: str = "binary_little_endian", colours: np.ndarray | None = None) -> None:
    """Write :func:`ply_bytes` of the arguments to ``path``."""
    Path(path).write_bytes(ply_bytes(points, triangles, encoding, colours))


def ply_bytes(points: np.ndarray, triangles: np.ndarray | None = None, encoding: str = "binary_little_endian",
              colours: np.ndarray | None = None) -> bytes:
    """A PLY file of points (n, 3), optional triangles (m, 3) and colours (n, 3) in 0-1 (``ascii``,
    ``binary_little_endian`` or ``binary_big_endian``): float32 x y z, uchar red green blue, faces as
    ``uchar``-counted ``int`` lists."""
    points = np.asarray(points, dtype=np.float64)
    triangles = np.zeros((0, 3), np.int64) if triangles is None else np.asarray(triangles, dtype=np.int64)
    header = [f"ply\nformat {encoding} 1.0\nelement vertex {len(points)}\nproperty float x\nproperty float y\n"
              "property float z\n"]
    rgb = None
    if colours is not None:
        rgb = np.round(np.clip(np.asarray(colours, dtype=np.float64), 0, 1) * 255).astype(np.uint8)
        header.append("property uchar red\nproperty uchar green\nproperty uchar blue\n")
    if len(triangles):
        header.append(f"element face {len(triangles)}\nproperty list uchar int vertex_indices\n")
    header.append("end_header\n")
    parts = ["".join(header).encode("ascii")]
    if encoding == "ascii":
        rows = [f"{x:.6f} {y:.6f} {z:.6f}" for x, y, z in points]
        if rgb is not None:
            rows = [f"{row} {r} {g} {b}" for row, (r, g, b) in zip(rows, rgb)]
        parts.append("".join(row + "\n" for row in rows).encode("ascii"))
        parts.append("".join(f"3 {a} {b} {c}\n" for a, b, c in triangles).encode("ascii"))
        return b"".join(parts)
    order = _PLY_FORMATS[encoding]
    if rgb is None:
        parts.append(points.astype(order + "f4").tobytes())
    else:
        table = np.zeros(len(points), np.dtype([("p", order + "f4", (3,)), ("c", "u1", (3,))]))
        table["p"], table["c"] = points, rgb
        parts.append(table.tobytes())
    faces = np.zeros(len(triangles), np.dtype([("n", "u1"), ("i", order + "i4", (3,))]))
    faces["n"], faces["i"] = 3, triangles
    parts.append(faces.tobytes())
    return b"".join(parts)
