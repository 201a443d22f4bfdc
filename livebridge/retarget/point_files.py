"""Named 3D points as people pick them on a scan: CSV, TOML, MeshLab PickPoints files; and MeshLab's templates.

A scan's landmarks come from a person clicking them in a mesh viewer or from a landmark detector. The most
common free tool for the clicking is MeshLab's PickPoints editor (Edit > PickPoints): it saves a ``.pp`` XML
file of ``<point x= y= z= name= active=/>`` elements, by default as ``SCAN_picked_points.pp`` beside the scan,
and it can load a template (``.pptpl``: the names to pick, in order) so that every scan gets the same names.
:func:`write_pick_template` writes one (``livebridge landmarks template``); :func:`read_points` reads the
``.pp`` files as they come, with CSV (``name,x,y,z``) and TOML (``name = [x, y, z]``) for everything else.
Coordinates are in the scan's own frame and units.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from xml.etree import ElementTree
from xml.sax.saxutils import quoteattr

import numpy as np

from livebridge.errors import InputError
from livebridge.tomlio import load_toml

POINT_FILE_SUFFIXES = (".csv", ".toml", ".pp")
"""Suffixes :func:`read_points` reads (any other is read as CSV)."""
PICKED_POINTS_SUFFIX = "_picked_points.pp"
"""What MeshLab appends to a mesh's name (less its extension) to name its picked points file."""


def read_points(path: str | Path, scale: float = 1.0) -> dict[str, np.ndarray]:
    """Named points (name -> (3,) array, times ``scale``: to mm) of a landmark file, in file order, by its
    suffix: ``.pp`` (MeshLab PickPoints), ``.toml`` (``name = [x, y, z]``), otherwise CSV (``name,x,y,z`` rows);
    a MeshLab template (``.pptpl``) is refused, it has no points."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".pptpl":
        raise InputError("a MeshLab PickPoints template holds names, not points: pick them on the scan in MeshLab "
                         "(Edit > PickPoints) and give the .pp file it saves", path)
    reader = {".pp": read_picked_points, ".toml": read_points_toml}.get(suffix, read_points_csv)
    points = {name: xyz * scale for name, xyz in reader(path).items()}
    _check_apart(points, path)
    return points


def _check_apart(points: dict[str, np.ndarray], path: Path) -> None:
    """Refuse two landmarks at one point (a row copied and not edited), naming both: the splines through the
    landmarks cannot tell them apart."""
    seen = {}
    for name, xyz in points.items():
        other = seen.setdefault(tuple(xyz.tolist()), name)
        if other != name:
            raise InputError(f"{other} and {name} are both at {xyz.tolist()}: was a row copied and not edited?",
                             path, name)


def picked_points_file(scan: str | Path) -> Path:
    """Where MeshLab saves a scan's picked points by default: ``smile.ply`` -> ``smile_picked_points.pp``."""
    scan = Path(scan)
    return scan.with_name(scan.stem + PICKED_POINTS_SUFFIX)


def read_points_csv(path: str | Path) -> dict[str, np.ndarray]:
    """``name,x,y,z`` rows of a CSV file (a first row ``name,x,y,z`` is a header), in file order."""
    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8-sig") as stream:  # a byte order mark is no part of a name
            rows = list(csv.reader(stream))
    except UnicodeDecodeError as error:
        raise InputError(f"not UTF-8 text (byte {error.object[error.start:error.start + 1]!r} at offset "
                         f"{error.start})", path) from None
    points = {}
    for line, row in enumerate(rows, 1):
        cells = [cell.strip() for cell in row]
        header = line == 1 and [cell.lower() for cell in cells] == ["name", "x", "y", "z"]
        if header or not any(cells) or cells[0].startswith("#"):
            continue
        if len(cells) != 4:
            raise InputError(f"line {line}: expected 4 fields name,x,y,z, got {len(cells)}", path)
        if not cells[0]:  # an unnamed landmark cannot be matched to another face's, nor named in an error
            raise InputError(f"line {line}: the landmark has no name (expected name,x,y,z)", path)
        _add(points, cells[0], cells[1:], f"line {line}: ", "name,x,y,z", path)
    if not points:
        raise InputError("no landmarks (expected rows name,x,y,z)", path)
    return points


def read_points_toml(path: str | Path) -> dict[str, np.ndarray]:
    """``name = [x, y, z]`` lines of a TOML file, in file order."""
    points, data = {}, load_toml(path)
    if data.get("format") == "livebridge-markers":
        raise InputError("a landmark set placed on a mesh (triangles and barycentric coordinates, as `landmarks place` "
                         "and --landmarks-out write), not points: give each landmark's x, y, z on this scan (CSV "
                         "name,x,y,z, TOML name = [x, y, z] or a MeshLab .pp file)", path, "format")
    for name, value in data.items():
        if (not isinstance(value, list) or len(value) != 3
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                           for v in value)):
            raise InputError(f"expected [x, y, z] (three finite numbers), got {value!r}", path, name)
        points[name] = np.array(value, dtype=np.float64)
    if not points:
        raise InputError("no landmarks (expected lines like 'nose_tip = [0.0, 0.0, 0.0]')", path)
    return points


def read_picked_points(path: str | Path) -> dict[str, np.ndarray]:
    """The picked points of a MeshLab PickPoints file (``.pp``), in file order.

    A point MeshLab marks ``active="0"`` was not picked (a template's name the person skipped, or unticked),
    and is left out, as MeshLab leaves it out; a missing ``active`` counts as picked, as in MeshLab.
    """
    path = Path(path)
    try:
        root = ElementTree.parse(path).getroot()
    except ElementTree.ParseError as error:
        line, column = error.position
        raise InputError(f"not a MeshLab PickPoints file: the XML breaks at line {line}, column {column + 1} "
                         f"({str(error).split(':')[0]})", path) from None
    if root.tag != "PickedPoints":
        raise InputError(f"not a MeshLab PickPoints file: its root element is <{root.tag}>, expected "
                         "<PickedPoints>", path)
    points = {}
    elements = root.findall("point")
    for number, element in enumerate(elements, 1):
        name = (element.get("name") or "").strip()
        if not name:
            raise InputError(f"point {number}: it has no name (expected name=\"...\")", path)
        if element.get("active", "1").strip() == "0":
            continue
        _add(points, name, [element.get(axis) for axis in "xyz"], f"point {number}: ", "x=, y= and z=", path)
    if not points:
        raise InputError(f"no picked landmarks ({len(elements)} <point> elements, none of them active)", path)
    return points


def write_pick_template(path: str | Path, names) -> None:
    """A MeshLab PickPoints template (``.pptpl``) listing ``names`` in order, as MeshLab writes one."""
    lines = ["<!DOCTYPE PickPointsTemplate>", "<PickPointsTemplate>"]
    lines += [f" <point name={quoteattr(name)}/>" for name in names]
    lines.append("</PickPointsTemplate>")
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


def _add(points: dict, name: str, cells, where: str, expected: str, path: Path) -> None:
    """Check one named point's coordinate texts and add it to ``points``."""
    if name in points:
        raise InputError(f"{where}landmark {name!r} appears twice", path, name)
    if any(cell is None for cell in cells):
        raise InputError(f"{where}x, y, z must all be given ({expected})", path, name)
    try:
        xyz = [float(cell) for cell in cells]
    except ValueError:
        raise InputError(f"{where}x, y, z must be numbers, got {list(cells)}", path, name) from None
    if not all(map(math.isfinite, xyz)):
        raise InputError(f"{where}x, y, z must be finite, got {list(cells)}", path, name)
    points[name] = np.array(xyz)
