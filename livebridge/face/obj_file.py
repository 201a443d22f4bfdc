"""Reading OBJ files: vertices (with colours), texture coordinates, faces (fanned into triangles), materials.

:func:`read_obj_data` reads any OBJ. An OBJ file of the regular layout scanners write is parsed in bulk
(:func:`read_obj_bulk`): every ``v`` line with the same number of
values, every ``f`` line with the same number of corners written the same way, no relative indices.

Reading a million-face scan line by line in Python takes 8 s (490k `v`, 490k `vt` and 977k `f v/vt` lines,
66 MB); in bulk, 3 s (without `vt`: 6 s and 2.2 s; ICT-FaceKit's head, quads and triangles, 0.3-0.4 s and 0.1 s):
the lines are sorted by keyword once, each kind is checked whole (a regular expression over the faces) and parsed
as one run of numbers by NumPy. Anything this
cannot read exactly as the line-by-line reader (:func:`read_obj_lines`) would, a line it
does not expect, a mixed layout, a bad number, an index out of range, makes it return None, and the line-by-line
reader then reads the file and names the line at fault.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.errors import InputError

_OTHER_LINE_BREAKS = (b"\x0b", b"\x0c", b"\x1c", b"\x1d", b"\x1e", b"\xc2\x85", b"\xe2\x80\xa8", b"\xe2\x80\xa9")
"""Characters Python's text lines break at (the line-by-line reader's) and bytes lines do not."""
_IGNORED = (b"vn", b"vp", b"#", b"o ", b"g ", b"s ", b"l ")


@dataclass(frozen=True)
class ObjData:
    """What an OBJ file holds for a scan: vertices (n, 3), colours (n, 3) as written (None unless every vertex
    has one), texture coordinates (k, 2), triangles (m, 3) (polygons fanned), each triangle's corners'
    texture coordinate indices (m, 3; -1 without), its material (m,; None before any ``usemtl``), and the
    ``mtllib`` files named."""

    points: np.ndarray
    colours: np.ndarray | None
    texcoords: np.ndarray
    triangles: np.ndarray
    corner_uv: np.ndarray
    face_material: list
    libraries: list


_BOM = b"\xef\xbb\xbf"


def read_obj_data(data: bytes, path: Path) -> ObjData:
    """An OBJ file's contents (``data``, its bytes; ``path`` for errors), in bulk when it has the regular layout,
    else line by line, naming the line at fault. A UTF-8 byte order mark (some Windows tools write one) is
    skipped."""
    data = data[len(_BOM):] if data.startswith(_BOM) else data
    return read_obj_bulk(data) or read_obj_lines(data, path)


def read_obj_bulk(data: bytes) -> ObjData | None:
    """``data`` (an OBJ file's bytes) parsed in bulk, or None when its layout is not the regular one."""
    if any(mark in data for mark in _OTHER_LINE_BREAKS):
        return None
    vertex_lines, texcoord_lines, face_lines = [], [], []
    faces_after = []  # per face line: (vertices, texture coordinates) defined before it
    materials, libraries, material = [], [], None
    for line in data.splitlines():
        head = line[:2]
        if head == b"v ":
            vertex_lines.append(line[2:])
        elif head == b"f ":
            face_lines.append(line[2:])
            faces_after.append((len(vertex_lines), len(texcoord_lines)))
            materials.append(material)
        elif head == b"vt" and line[2:3] == b" ":
            texcoord_lines.append(line[3:])
        elif line.startswith((b"usemtl ", b"mtllib ")):
            name = line.decode("utf-8", errors="replace").split(maxsplit=1)[1:]
            if line.startswith(b"usemtl"):
                material = name[0].strip() if name else None
            elif name:
                libraries.append(name[0].strip())
        elif line.startswith(_IGNORED) or not line.strip():
            continue
        elif line[:1] in (b"v", b"f", b"u", b"m") or line[:1].isspace():
            return None  # a keyword spelt otherwise (tabs, leading blanks): the line-by-line reader's
    points = _numbers(vertex_lines, (3, 6), np.float64)
    texcoords = _numbers(texcoord_lines, (2, 3), np.float64) if texcoord_lines else np.zeros((0, 2))
    faces = _faces(face_lines, faces_after, materials)
    if points is None or texcoords is None or faces is None:
        return None
    triangles, corner_uv, face_material = faces
    return ObjData(points[:, :3], points[:, 3:6] if points.shape[1] == 6 else None, texcoords[:, :2], triangles,
                   corner_uv, face_material, libraries)


def _numbers(lines: list, widths: tuple, dtype) -> np.ndarray | None:
    """The lines' numbers (n_lines, width), every line holding the same count (one of ``widths``), all finite;
    None otherwise."""
    if not lines:
        return np.zeros((0, widths[0]), dtype)
    counts = {len(line.split()) for line in lines}
    if len(counts) != 1 or (width := counts.pop()) not in widths:
        return None
    values = _parsed(b" ".join(lines), dtype, len(lines) * width)
    if values is None or not np.isfinite(values).all():
        return None
    return values.reshape(len(lines), width)


_CORNERS = {(0, False): rb"[0-9]+", (1, False): rb"[0-9]+/[0-9]+", (2, True): rb"[0-9]+//[0-9]+",
            (2, False): rb"[0-9]+/[0-9]+/[0-9]+"}
"""A face corner's forms, by its slashes and whether two are side by side: ``a``, ``a/b``, ``a//c``, ``a/b/c``."""


def _faces(lines: list, defined: list, materials: list):
    """The face lines fanned into triangles, as the line-by-line reader fans them: vertex indices (m, 3) and
    texture coordinate indices (m, 3; -1 without), from 0, and each triangle's material; None unless every
    corner of every line is written in the first one's form (:data:`_CORNERS`), 3 or more a line, every index
    from 1 and defined before its line."""
    import re

    if not lines:
        return np.zeros((0, 3), np.int64), np.zeros((0, 3), np.int64), []
    first = lines[0].split()
    form = (first[0].count(b"/"), b"//" in first[0]) if first else None
    if form not in _CORNERS:
        return None
    corner = _CORNERS[form]
    line = corner + rb"(?:[ \t]+" + corner + rb"){2,}[ \t]*"
    joined = b"\n".join(lines)
    if re.fullmatch(rb"(?:" + line + rb"\n)*" + line, joined) is None:
        return None
    counts = np.fromiter((len(text.split()) for text in lines), np.int64, len(lines))  # corners a face
    fields = 1 + form[0] - form[1]  # numbers a corner
    values = _parsed(joined.replace(b"/", b" "), np.int64, int(counts.sum()) * fields)
    if values is None:
        return None
    values = values.reshape(-1, fields)
    before = np.repeat(np.array(defined, dtype=np.int64).reshape(-1, 2), counts, axis=0)
    with_uv = form[0] > 0 and not form[1]
    for column in range(1 + with_uv):
        if (values[:, column] < 1).any() or (values[:, column] > before[:, column]).any():
            return None
    fans = counts - 2
    face = np.repeat(np.arange(len(lines)), fans)
    k = 1 + np.arange(len(face)) - np.repeat(np.cumsum(fans) - fans, fans)
    first_corner = (np.cumsum(counts) - counts)[face]
    corners = first_corner[:, None] + np.stack([np.zeros_like(k), k, k + 1], axis=1)  # (0, k, k + 1) a face
    triangles = values[corners, 0] - 1
    corner_uv = values[corners, 1] - 1 if with_uv else np.full(triangles.shape, -1, np.int64)
    return triangles, corner_uv, [materials[f] for f in face]


def _parsed(text: bytes, dtype, count: int) -> np.ndarray | None:
    """``count`` numbers of ``dtype`` separated by blanks in ``text``, or None when it holds anything else."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # NumPy warns, and stops, at the first thing that is not a number
        try:
            values = np.fromstring(text, dtype=dtype, sep=" ")
        except (ValueError, DeprecationWarning):
            return None
    return values if len(values) == count else None


def read_obj_lines(data: bytes, path: Path) -> ObjData:
    """An OBJ file read line by line: any layout, and an error naming the line at fault."""
    vertices, triangles, colours, texcoords = [], [], [], []
    corner_uv, face_material, libraries, material = [], [], [], None
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
            colours.append(_obj_colour(parts[4:7], number, path))
        elif parts[0] == "vt":
            texcoords.append(_obj_texcoord(parts[1:3], number, path))
        elif parts[0] == "f":
            corners, uv_corners = _obj_face(parts[1:], len(vertices), len(texcoords), line, number, path)
            fan = [(0, k, k + 1) for k in range(1, len(corners) - 1)]
            triangles.extend((corners[a], corners[b], corners[c]) for a, b, c in fan)
            corner_uv.extend((uv_corners[a], uv_corners[b], uv_corners[c]) if uv_corners else (-1, -1, -1)
                             for a, b, c in fan)
            face_material.extend([material] * len(fan))
        elif parts[0] == "mtllib" and len(parts) > 1:
            libraries.append(line.split(maxsplit=1)[1].strip())
        elif parts[0] == "usemtl":
            material = line.split(maxsplit=1)[1].strip() if len(parts) > 1 else None
    every_colour = colours and all(c is not None for c in colours)  # colour only when every vertex has one
    return ObjData(np.array(vertices, dtype=np.float64).reshape(-1, 3),
                   np.array(colours, dtype=np.float64) if every_colour else None,
                   np.array(texcoords, dtype=np.float64).reshape(-1, 2),
                   np.array(triangles, dtype=np.int64).reshape(-1, 3),
                   np.array(corner_uv, dtype=np.int64).reshape(-1, 3), face_material, libraries)


def _obj_face(tokens, n_vertices: int, n_texcoords: int, line: str, number: int, path: Path):
    """The vertex indices (from 0) of an ``f`` line's corners, and their texture coordinate indices (from 0;
    an empty list when the corners have none)."""
    try:
        fields = [token.split("/") for token in tokens]
        corners = [int(field[0]) for field in fields]
        uv = [int(field[1]) for field in fields] if all(len(f) > 1 and f[1] for f in fields) else []
    except ValueError:
        raise InputError(f"line {number}: malformed face {line.strip()!r}", path) from None
    if len(corners) < 3 or 0 in corners or 0 in uv:
        raise InputError(f"line {number}: a face needs 3 or more vertex numbers from 1 (or negative), "
                         f"got {line.strip()!r}", path)
    corners = [c - 1 if c > 0 else n_vertices + c for c in corners]
    bad = [c for c in corners if not 0 <= c < n_vertices]
    if bad:
        raise InputError(f"line {number}: face refers to vertex {bad[0] + 1}, only {n_vertices} "
                         "defined so far", path)
    uv = [t - 1 if t > 0 else n_texcoords + t for t in uv]
    bad = [t for t in uv if not 0 <= t < n_texcoords]
    if bad:
        raise InputError(f"line {number}: face refers to texture coordinate {bad[0] + 1}, only {n_texcoords} "
                         "defined so far", path)
    return corners, uv


def _obj_texcoord(cells, number, path):
    try:
        uv = [float(value) for value in cells]
    except ValueError:
        raise InputError(f"line {number}: texture coordinates must be numbers, got {cells}", path) from None
    if len(uv) < 2 or not all(map(math.isfinite, uv)):
        raise InputError(f"line {number}: a texture coordinate needs finite u v, got {cells}", path)
    return uv


def _obj_colour(cells, number, path):
    if len(cells) < 3:
        return None
    try:
        return [float(value) for value in cells]
    except ValueError:
        raise InputError(f"line {number}: vertex colour must be numbers, got {cells}", path) from None


_LINE_ENDS = "\r\n\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029"


@dataclass(frozen=True)
class ObjLayout:
    """An OBJ file with its vertex positions left open, parsed once: :meth:`moved` writes it with any positions.

    Each ``v`` line's x y z are replaced, what follows them on the line (a vertex colour) kept; the normals are
    dropped (the ``vn`` lines and the faces' normal indices: they no longer fit a moved surface, and a renderer
    computes them when a file has none); every other line stays as written (texture coordinates, polygons,
    groups, materials, comments, line ends, a byte order mark). Lines are read as :func:`read_obj_lines` reads
    them, so the ``v`` lines are the vertices :func:`read_obj_data` gives.

    Attributes
    ----------
    between : tuple of str
        The text before the first ``v`` line's position, between each two, and after the last (n + 1).
    tails : tuple of str
        What follows each ``v`` line's x y z, its line end included (n).
    bom : bool
    """

    between: tuple
    tails: tuple
    bom: bool

    @classmethod
    def of(cls, data: bytes) -> ObjLayout:
        """The layout of an OBJ file's bytes."""
        bom = data.startswith(_BOM)
        text = data[len(_BOM) if bom else 0:].decode("utf-8", errors="surrogateescape")
        between, tails, pending = [], [], []
        for line in text.splitlines(keepends=True):
            body = line.rstrip(_LINE_ENDS)
            ending, parts = line[len(body):], body.split()
            keyword = parts[0] if parts else ""
            if keyword == "v":
                between.append("".join(pending) + "v ")
                tails.append("".join(f" {part}" for part in parts[4:]) + ending)
                pending = []
            elif keyword == "f":
                pending.append(" ".join(["f", *(_without_normal(token) for token in parts[1:])]) + ending)
            elif keyword != "vn":
                pending.append(line)
        between.append("".join(pending))
        return cls(tuple(between), tuple(tails), bom)

    @property
    def n_vertices(self) -> int:
        return len(self.tails)

    def moved(self, vertices: np.ndarray) -> bytes:
        """The file with its vertices at ``vertices`` (n_vertices, 3; in the file's units, 9 significant
        digits)."""
        vertices = np.asarray(vertices, dtype=np.float64)
        if vertices.shape != (self.n_vertices, 3):
            raise ValueError(f"{self.n_vertices} vertices expected, got an array of shape {vertices.shape}")
        pieces = [self.between[0]]
        for (x, y, z), tail, after in zip(vertices.tolist(), self.tails, self.between[1:]):
            pieces.append(f"{x:.9g} {y:.9g} {z:.9g}{tail}{after}")
        return (_BOM if self.bom else b"") + "".join(pieces).encode("utf-8", errors="surrogateescape")


def _without_normal(corner: str) -> str:
    """A face corner ``v``, ``v/t``, ``v//n`` or ``v/t/n`` without its normal index."""
    fields = corner.split("/")
    return fields[0] if len(fields) < 2 or not fields[1] else f"{fields[0]}/{fields[1]}"


def mesh_obj(vertices: np.ndarray, faces: np.ndarray, comment: str = "", uv: np.ndarray | None = None,
             material: tuple[str, str] | None = None) -> bytes:
    """A polygon mesh's OBJ file: ``vertices`` (n, 3) as written (6 decimals), ``faces`` (m, k) from 0 (k corners
    each: triangles, quads), ``comment`` as its first line.

    ``uv`` (n, 2): one texture coordinate per vertex (7 decimals, OBJ convention: v up), each corner written
    ``v/vt``. ``material`` = (material file name, material name): the ``mtllib`` and ``usemtl`` lines.
    """
    lines = [f"# {comment}"] if comment else []
    if material is not None:
        lines.append(f"mtllib {material[0]}")
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in np.asarray(vertices, dtype=np.float64)]
    if uv is not None:
        lines += [f"vt {u:.7f} {v:.7f}" for u, v in np.asarray(uv, dtype=np.float64)]
    if material is not None:
        lines.append(f"usemtl {material[1]}")
    corner = "{0}/{0}" if uv is not None else "{0}"
    lines += ["f " + " ".join(corner.format(i) for i in face) for face in np.asarray(faces, dtype=np.int64) + 1]
    return ("\n".join(lines) + "\n").encode()
