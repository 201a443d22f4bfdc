"""Reading 3D scans: point clouds and meshes from PLY (ASCII, binary little/big endian:
:mod:`~livebridge.retarget.ply_file`), OBJ, STL (:mod:`~livebridge.retarget.stl_file`; no colour) and XYZ/CSV.

A scan is what a scanner wrote: points, their colours when the scanner recorded them (structured light,
photogrammetry and depth cameras with a colour camera do), and triangles when the scanner meshed them (faces
with more than three corners become triangle fans). Colour is read from PLY ``red green blue`` (or
``diffuse_red ..``; integers scaled by their type's maximum, floats taken as 0-1), OBJ ``v x y z r g b`` and
XYZ/CSV columns named ``r g b`` / ``red green blue`` (or, without a header, three whole numbers 0-255 after
x y z on every line), or from the texture images of a textured mesh (OBJ ``vt`` with ``mtllib`` / ``map_Kd``;
PLY ``comment TextureFile`` with face ``texcoord`` lists or vertex ``s t``). A point cloud's normals, when the
scanner or its software wrote them (PLY ``nx ny nz``, XYZ/CSV columns so named, or three unit-length numbers
after x y z [r g b] on every line), say which way each point's surface faces: the face's preparation drops the
points facing away from the front (:mod:`~livebridge.retarget.facing`). Every reader checks what it reads and
names the file and the line (text) or the element (binary) of the first bad value: a truncated file, a
wrong count, NaN or infinity, a face that points at a vertex that does not exist.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.errors import InputError, file_error
from livebridge.face.obj_file import read_obj_data
from livebridge.retarget.checks import check_faces
from livebridge.retarget.mesh_samples import surface_samples
from livebridge.retarget.ply_file import NORMAL_NAMES, read_ply
from livebridge.retarget.stl_file import read_stl
from livebridge.retarget.texture import Texture, sample_textured

SCAN_SUFFIXES = (".ply", ".obj", ".stl", ".xyz", ".csv", ".txt", ".pts", ".asc")
"""Suffixes :func:`read_scan` knows (all but .ply, .obj and .stl are read as x y z point lists)."""


@dataclass(frozen=True, eq=False)
class Scan:
    """Points of a scanned surface, and its triangles when the scan is a mesh.

    Attributes
    ----------
    points : ndarray, shape (n_points, 3)
        Finite, in the file's units times the reader's ``scale``.
    triangles : ndarray of int, shape (n_triangles, 3)
        Empty (0, 3) for a point cloud.
    colours : ndarray, shape (n_points, 3), or None
        RGB in [0, 1] per point, None when the scan has no colour per point.
    texture : Texture or None
        Texture images on the triangles (:mod:`~livebridge.retarget.texture`): a textured mesh's colour, which
        :meth:`as_points` samples into coloured points.
    normals : ndarray, shape (n_points, 3), or None
        A point cloud's unit normals as the file gives them (a row of zeros: not known), None without.
    """

    points: np.ndarray
    triangles: np.ndarray
    colours: np.ndarray | None = None
    texture: Texture | None = None
    normals: np.ndarray | None = None

    def __post_init__(self):
        for name, dtype in (("points", np.float64), ("triangles", np.int64), ("colours", np.float64),
                            ("normals", np.float64)):
            if getattr(self, name) is None:
                continue
            array = np.array(getattr(self, name), dtype=dtype).reshape(-1, 3)
            array.setflags(write=False)
            object.__setattr__(self, name, array)
        if self.colours is not None and len(self.colours) != len(self.points):
            raise InputError(f"{len(self.colours)} colours for {len(self.points)} points", field="colours")
        if self.normals is not None and len(self.normals) != len(self.points):
            raise InputError(f"{len(self.normals)} normals for {len(self.points)} points", field="normals")

    def where(self, keep: np.ndarray) -> Scan:
        """A point cloud's points where ``keep`` (n_points,) bool, with their colours and normals."""
        return Scan(self.points[keep], np.zeros((0, 3), np.int64), None if self.colours is None else self.colours[keep],
                    normals=None if self.normals is None else self.normals[keep])

    @property
    def is_mesh(self) -> bool:
        return len(self.triangles) > 0

    @property
    def has_colour(self) -> bool:
        return self.colours is not None or self.texture is not None

    def as_points(self, centre: np.ndarray | None = None, radius: float = np.inf,
                  spacing: float | None = None) -> Scan:
        """A mesh as a point cloud: points every ``spacing`` mm (default 0.5, see
        :mod:`~livebridge.retarget.mesh_samples`) over its triangles with a corner within ``radius`` of
        ``centre`` (all without a centre), coloured from its texture
        (:func:`~livebridge.retarget.texture.sample_textured`) or its vertices' colours; a point cloud as it is."""
        if not self.is_mesh:
            return self
        keep = None
        if centre is not None:
            near = np.linalg.norm(self.points - np.asarray(centre, dtype=np.float64), axis=1) <= radius
            keep = near[self.triangles].any(axis=1)
        if self.texture is not None:
            points, colours = sample_textured(self.points, self.triangles, self.texture, spacing, keep)
            return Scan(points, np.zeros((0, 3), np.int64), colours)
        points, owner, bary = surface_samples(self.points, self.triangles, spacing, keep)
        colours = None if self.colours is None else np.einsum("sk,skd->sd", bary, self.colours[self.triangles[owner]])
        return Scan(points, np.zeros((0, 3), np.int64), colours)


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
    reader = {".ply": read_ply, ".obj": _read_obj, ".stl": _read_stl}.get(suffix, _read_xyz)
    points, triangles, colours, texture, normals = reader(data, path)
    if not len(points):
        raise InputError("no points", path)
    check_faces(triangles, len(points), path)
    if colours is not None:
        bad = np.flatnonzero(~(np.isfinite(colours).all(axis=1) & (colours >= 0).all(axis=1)
                               & (colours <= 1).all(axis=1)))
        if len(bad):
            raise InputError(f"point {bad[0]}: colour {colours[bad[0]].tolist()} is not in 0-1 ({len(bad)} such)",
                             path, "colour")
    # a mesh's own triangles say which way it faces
    normals = None if normals is None or len(triangles) else unit_normals(normals, path)
    return Scan(points * scale, triangles, colours, texture, normals)


def unit_normals(normals: np.ndarray, path) -> np.ndarray:
    """A file's normals (n, 3) made unit length; zero rows kept (not known). An error names the file and the
    first point whose normal is not finite."""
    length = np.linalg.norm(normals, axis=1)
    bad = np.flatnonzero(~np.isfinite(length))
    if len(bad):
        raise InputError(f"point {bad[0]}: normal {normals[bad[0]].tolist()} is not a direction ({len(bad)} such)",
                         path, "normal")
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(length[:, None] > 0, normals / length[:, None], 0.0)


def _read_stl(data: bytes, path: Path):
    return *read_stl(data, path), None, None


# ------------------------------------------------------------------------------------------------ XYZ / CSV
_SEPARATORS = re.compile(r"[,;\s]+")


def _read_xyz(data: bytes, path: Path):
    """``x y z [more columns]`` per line, separated by spaces, tabs, commas or semicolons.

    A first line that is not numbers is a header (when it names x, y and z, those columns are read, r g b /
    red green blue and nx ny nz / normal_x normal_y normal_z when it names them; CloudCompare's ``//X,Y,Z,...``
    too); other lines starting with ``#`` or ``//`` are comments. Without a header, columns 4-6 are colour when
    they are whole numbers 0-255 on every line, and normals are the first of columns 4-6 and 7-9 that are not the
    colour and are unit length (or zero) on every line.
    """
    columns, colour_columns, normal_columns, headed = (0, 1, 2), None, None, False
    rows, tails, first = [], [], True
    for number, line in enumerate(_text(data, path).splitlines(), 1):
        text = line.strip()
        comment = text.startswith(("#", "//"))
        if first and comment and text.startswith("//") and _names_xyz(text[2:]):
            text, comment = text[2:], False  # CloudCompare's header
        if not text or comment:
            continue
        if ";" in text and "," in text:  # the European CSV: ';' between the numbers, ',' inside them
            raise InputError(f"line {number}: ';' between values and ',' within them ({text[:40]!r}): write the "
                             "numbers with a decimal point", path)
        cells = [cell for cell in _SEPARATORS.split(text) if cell]
        if first and not _is_number(cells[0]):
            columns, first, headed = _header_columns(cells, columns, path, number), False, True
            colour_columns = _named_columns(cells, _COLOUR_NAMES)
            normal_columns = _named_columns(cells, NORMAL_NAMES)
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
        if not headed:
            tails.append(cells[3:9])
        elif colour_columns is not None or normal_columns is not None:
            tails.append((_named_values(cells, colour_columns, "r, g, b", number, path),
                          _named_values(cells, normal_columns, "nx, ny, nz", number, path)))
    points = np.array(rows, dtype=np.float64).reshape(-1, 3)
    if headed:
        colours = None if colour_columns is None else _scaled_colours(np.array([c for c, _ in tails]).reshape(-1, 3))
        normals = None if normal_columns is None else np.array([n for _, n in tails], dtype=np.float64).reshape(-1, 3)
        return points, np.zeros((0, 3), np.int64), colours, None, normals
    colours = _headerless_colours(tails)
    return points, np.zeros((0, 3), np.int64), colours, None, _headerless_normals(tails, colours is not None)


_COLOUR_NAMES = (("r", "g", "b"), ("red", "green", "blue"))
NORMAL_LENGTHS = (0.9, 1.1)
"""Lengths a headerless file's normals have on every line (unit vectors, rounded as written), or zero."""


def _cell_names(cells) -> list[str]:
    """A header's cells as names: unquoted, lower case."""
    return [cell.strip().strip('"').lower() for cell in cells]


def _names_xyz(text: str) -> bool:
    names = _cell_names(cell for cell in _SEPARATORS.split(text.strip()) if cell)
    return all(axis in names for axis in "xyz")


def _named_columns(cells, choices) -> tuple[int, int, int] | None:
    names = _cell_names(cells)
    for triple in choices:
        if all(name in names for name in triple):
            return tuple(names.index(name) for name in triple)
    return None


def _named_values(cells, columns, what: str, number: int, path):
    """The row's cells in ``columns`` as floats (None without columns)."""
    if columns is None:
        return None
    try:
        return [float(cells[k]) for k in columns]
    except (ValueError, IndexError):
        raise InputError(f"line {number}: {what} must be numbers", path) from None


def _scaled_colours(colours: np.ndarray) -> np.ndarray:
    """Named colour columns in 0-1 (0-255 when any exceeds 1)."""
    return colours / 255.0 if colours.size and colours.max() > 1 else colours


def _headerless_colours(tails) -> np.ndarray | None:
    """Colours in 0-1 from every row's cells 4-6 when they are whole numbers 0-255 on every row, else None."""
    if not tails or any(len(cells) < 3 or not all(cell.isdigit() for cell in cells[:3]) for cells in tails):
        return None
    colours = np.array([cells[:3] for cells in tails], dtype=np.float64)
    return colours / 255.0 if colours.max() <= 255 else None


def _headerless_normals(tails, coloured: bool) -> np.ndarray | None:
    """Normals from every row's cells 4-6 (not when they are the colour) or else 7-9, the first that are unit
    length or zero on every row; None when neither is."""
    for start in (0, 3)[coloured:]:
        try:
            normals = np.array([[float(cell) for cell in cells[start:start + 3]] for cells in tails])
        except ValueError:
            continue
        if normals.shape != (len(tails), 3):
            continue
        length = np.linalg.norm(normals, axis=1)
        if np.all((length == 0) | ((length >= NORMAL_LENGTHS[0]) & (length <= NORMAL_LENGTHS[1]))):
            return normals
    return None


def _header_columns(cells, default, path, number):
    names = _cell_names(cells)
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
        return data.decode("utf-8-sig")  # a byte order mark is no part of the first number
    except UnicodeDecodeError as error:
        raise InputError(f"not UTF-8 text (byte {data[error.start:error.start + 1]!r} at offset {error.start})",
                         path) from None


# ------------------------------------------------------------------------------------------------ OBJ
def _read_obj(data: bytes, path: Path):
    """``v x y z [r g b]`` and ``f a b c ...`` lines (``a/t/n`` corners, negative = relative), and with ``vt``
    lines, ``mtllib`` and ``usemtl`` the texture images of the faces' materials (their ``map_Kd``); the rest
    ignored (:func:`~livebridge.face.obj_file.read_obj_data`)."""
    obj = read_obj_data(data, path)
    rgb = obj.colours
    if rgb is not None:
        rgb = rgb / 255.0 if rgb.max() > 1 else rgb  # 0-1 by the convention; some writers put 0-255
    texture = None
    if obj.libraries and len(obj.texcoords):
        texture = _obj_texture(path, obj.libraries, obj.texcoords, obj.corner_uv, obj.face_material)
        rgb = None if texture is not None else rgb  # the images hold the skin's pattern finer than the vertices
    return obj.points, obj.triangles, rgb, texture, None


def _obj_texture(path: Path, libraries: list[str], texcoords: np.ndarray, corner_uv: np.ndarray,
                 face_material: list):
    """The :class:`~livebridge.retarget.texture.Texture` of an OBJ's faces: each material's ``map_Kd`` image
    from the ``mtllib`` files (next to the OBJ); None when no face (with texture coordinates) shows an image: no
    ``usemtl`` line, or one naming another material, leaves the vertices' colours, if any, as the colour."""
    from livebridge.retarget.texture import Texture, read_image, read_materials

    images_of, library_of = {}, {}  # a material's image, and the MTL file that named it (for errors)
    for library in libraries:
        found = read_materials(path.parent / library, path)
        images_of.update(found)
        library_of.update(dict.fromkeys(found, library))
    if not images_of:
        return None
    used = sorted({m for m in face_material if m in images_of})
    index_of = {material: k for k, material in enumerate(used)}
    images = tuple(read_image(images_of[m], path.parent / library_of[m], f"{m}.map_Kd") for m in used)
    image_index = np.array([index_of.get(m, -1) for m in face_material], dtype=np.int64)
    image_index[(corner_uv < 0).any(axis=1)] = -1
    if not (image_index >= 0).any():
        return None
    uv = texcoords[np.clip(corner_uv, 0, None)][..., :2]
    return Texture(uv, image_index, images, tuple(images_of[m].name for m in used))



# ------------------------------------------------------------------------------------------------ writing
def write_textured_obj(path: str | Path, points: np.ndarray, triangles: np.ndarray, uv: np.ndarray,
                       image: np.ndarray) -> None:
    """Write a mesh with one texture as a scanner does: ``path`` (.obj: ``v``, ``vt`` and ``f v/vt`` lines),
    its material file (``path`` with .mtl) and image (``path`` with .png, 16-bit RGB).

    ``points`` (n, 3), ``triangles`` (m, 3), ``uv`` (n, 2) texture coordinates per vertex (OBJ convention: v
    up), ``image`` (height, width, 3) RGB in [0, 1], row 0 at the top.
    """
    import cv2

    from livebridge.face.obj_file import mesh_obj

    path = Path(path)
    mtl, png = path.with_suffix(".mtl"), path.with_suffix(".png")
    bgr = np.round(np.clip(np.asarray(image, dtype=np.float64), 0, 1)[..., ::-1] * 65535).astype(np.uint16)
    if not cv2.imwrite(str(png), bgr):
        raise InputError("could not write the texture image", png)
    mtl.write_text(f"newmtl skin\nKd 1 1 1\nmap_Kd {png.name}\n", encoding="utf-8")
    path.write_bytes(mesh_obj(points, triangles, uv=uv, material=(mtl.name, "skin")))
