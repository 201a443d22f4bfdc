"""Marker CSV files: one column per coordinate, from spreadsheets, scripts and landmark detectors.

Columns
    ``NAME_x``, ``NAME_y``, ``NAME_z`` or ``X_NAME``, ``Y_NAME``, ``Z_NAME`` (case-insensitive) for the
    marker ``NAME``; an optional time column (``time``, ``timestamp`` or ``t``, seconds) or frame column
    (``frame``, ``frame#``: frame numbers, the frame rate given by the user). Other columns are ignored.
OpenFace 2.x (``FeatureExtraction``)
    Recognised by its ``X_0``, ``Y_0``, ``Z_0`` 3D-landmark columns beside its own (``success``, ``x_0``
    2D landmarks, ``face_id``). Only the 3D landmarks ``X_k``, ``Y_k``, ``Z_k`` are read, as markers named
    ``"0"`` ... ``"67"`` (the landmark number of the 68-point Multi-PIE/iBUG layout, 0-based as OpenFace
    counts), in millimetres, times from ``timestamp``; a row with ``success`` 0 (no face found) is a frame
    where nothing was seen. A file with several faces (``face_id`` other than one value) is refused.
Text
    Comma, semicolon or tab separated (the most frequent of the three in the header line), blanks around
    fields ignored (OpenFace writes ``", "``), a decimal comma accepted in semicolon-separated files;
    missing values empty, ``NA`` or ``NaN``.
Units
    The file does not say: the user's (``--units``), else millimetres (and
    :attr:`~livebridge.take.trajectories.Trajectories.unit` None to say so).
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.atomic import write_atomically
from livebridge.errors import InputError
from livebridge.take.text_table import (
    format_number,
    increasing_times,
    number_table,
    repeated,
    text_lines,
    where,
    whole_points,
)
from livebridge.take.tracks import Trajectories, file_units, unit_name

TIME_COLUMNS = ("time", "timestamp", "t")
FRAME_COLUMNS = ("frame", "frame#")
DELIMITERS = (",", ";", "\t")
_SUFFIX = re.compile(r"(.+)_([xyz])", re.IGNORECASE)
_PREFIX = re.compile(r"([xyz])_(.+)", re.IGNORECASE)
_OPENFACE_3D = re.compile(r"([XYZ])_(\d+)")  # upper case: OpenFace's lower-case x_k, y_k are 2D pixels


@dataclass(frozen=True)
class Layout:
    """Where things are in a marker CSV's columns (0-based indices).

    Attributes
    ----------
    names : tuple of str
        Marker names, in the order of their first column.
    xyz : ndarray of int, shape (n_markers, 3)
        The x, y, z column of each marker.
    time, frame, success, face : int or None
        The time, frame-number, OpenFace ``success`` and ``face_id`` columns, when present.
    openface : bool
    """

    names: tuple[str, ...]
    xyz: np.ndarray
    time: int | None
    frame: int | None
    success: int | None
    face: int | None
    openface: bool


def read_marker_csv(path: str | Path, units_mm: float | None = None, rate: float | None = None) -> Trajectories:
    """The markers of a marker CSV file in millimetres (see the module docstring).

    Parameters
    ----------
    path : Path
    units_mm : float, optional
        Millimetres per unit of the file (default mm; OpenFace files are mm and one contradicting it is refused).
    rate : float, optional
        Frames per second, needed when the file has frame numbers but no times (or neither).
    """
    path = Path(path)
    lines = text_lines(path)
    if not lines:
        raise InputError("empty file (no header)", path, where(1))
    delimiter = max(DELIMITERS, key=lines[0].count)
    rows = list(csv.reader(lines, delimiter=delimiter, skipinitialspace=True))
    header = [name.strip() for name in rows[0]]
    layout = _layout(header, path)
    if layout.openface:
        scale, unit = file_units("mm", units_mm, path, "X_0")
    else:
        scale, unit = (units_mm or 1.0), unit_name(units_mm)
    data = [(line, row) for line, row in enumerate(rows[1:], start=2) if any(field.strip() for field in row)]
    if not data:
        raise InputError("no frames (only a header)", path, where(2))
    for line, row in data:
        if len(row) != len(header):
            raise InputError(f"{len(row)} fields, the header has {len(header)}", path, where(line))
    line_numbers = [line for line, _ in data]
    comma = delimiter == ";"
    t = _times(layout, data, header, path, rate, decimal_comma=comma)
    columns = [int(c) for c in layout.xyz.ravel()]
    xyz = number_table([[row[c] for c in columns] for _, row in data], line_numbers, [c + 1 for c in columns],
                       [header[c] for c in columns], path, decimal_comma=comma).reshape(len(data), len(layout.names), 3)
    if layout.success is not None:
        found = _column(layout.success, data, header, path, comma)
        xyz[found == 0] = np.nan  # OpenFace writes zeros where it found no face
    _one_face(layout, data, path)
    return Trajectories(layout.names, increasing_times(t, line_numbers, path, *_time_column(layout, header)),
                        whole_points(xyz) * scale, path, unit)


def _layout(header: list[str], path: Path) -> Layout:
    openface = "X_0" in header and ({"x_0", "success", "face_id"} & set(header)) != set()
    coordinates: dict[str, dict[str, int]] = {}
    for column, name in enumerate(header):
        marker, axis = _coordinate(name, openface)
        if marker is None:
            continue
        axes = coordinates.setdefault(marker, {})
        if axis in axes:
            raise InputError(f"two columns for {marker!r} {axis} (columns {axes[axis] + 1} and {column + 1})", path,
                             where(1, column + 1, name))
        axes[axis] = column
    if not coordinates:
        raise InputError("no marker columns (expected NAME_x, NAME_y, NAME_z or X_NAME, Y_NAME, Z_NAME)", path,
                         where(1))
    for marker, axes in coordinates.items():
        if len(axes) < 3:
            missing = [axis for axis in "xyz" if axis not in axes]
            first = min(axes.values()) + 1
            raise InputError(f"marker {marker!r} has no {' or '.join(missing)} column (a marker needs x, y and z)",
                             path, where(1, first, header[first - 1]))
    names = tuple(coordinates)
    repeated(names, path, 1, [min(axes.values()) + 1 for axes in coordinates.values()])
    lower = [name.lower() for name in header]

    def find(options) -> int | None:
        return next((lower.index(option) for option in options if option in lower), None)

    return Layout(names, np.array([[coordinates[m][a] for a in "xyz"] for m in names]),
                  find(TIME_COLUMNS), find(FRAME_COLUMNS),
                  find(("success",)) if openface else None, find(("face_id",)) if openface else None, openface)


def _coordinate(name: str, openface: bool) -> tuple[str | None, str | None]:
    """(marker, axis) a column holds, or (None, None) for any other column."""
    if openface:
        match = _OPENFACE_3D.fullmatch(name)
        return (match[2], match[1].lower()) if match else (None, None)
    match = _SUFFIX.fullmatch(name)
    if match:
        return match[1], match[2].lower()
    match = _PREFIX.fullmatch(name)
    return (match[2], match[1].lower()) if match else (None, None)


def _column(c: int, data, header: list[str], path: Path, decimal_comma: bool = False) -> np.ndarray:
    """The numbers of column ``c`` (0-based), none missing, shape (n_rows,)."""
    return number_table([[row[c]] for _, row in data], [line for line, _ in data], [c + 1], [header[c]], path,
                        missing_ok=False, decimal_comma=decimal_comma)[:, 0]


def _times(layout: Layout, data, header, path: Path, rate: float | None, decimal_comma: bool) -> np.ndarray:
    if layout.time is not None:
        return _column(layout.time, data, header, path, decimal_comma)
    if rate is None:
        what = "frame numbers but no time column" if layout.frame is not None else "no time or frame column"
        raise InputError(f"the file has {what} ({', '.join(TIME_COLUMNS)}); give the frame rate (--rate)", path,
                         where(1))
    if layout.frame is None:
        return np.arange(len(data)) / rate
    return _column(layout.frame, data, header, path) / rate


def _time_column(layout: Layout, header: list[str]) -> tuple[int, str]:
    column = layout.time if layout.time is not None else layout.frame
    return (column + 1, header[column]) if column is not None else (1, "row order")


def _one_face(layout: Layout, data, path: Path) -> None:
    if layout.face is None:
        return
    faces = sorted({row[layout.face].strip() for _, row in data})
    if len(faces) > 1:
        raise InputError(f"rows of {len(faces)} faces (face_id {', '.join(faces[:4])}); livebridge reads one face: "
                         "keep one face's rows", path, where(1, layout.face + 1, "face_id"))


def write_marker_csv(path: str | Path, trajectories: Trajectories) -> Path:
    """Write ``trajectories`` as a marker CSV in millimetres, atomically.

    Columns ``time,NAME_x,NAME_y,NAME_z,...``; tab separated for a ``.tsv`` file, else comma; empty fields
    where a marker was not seen; numbers as the shortest text that reads back exactly.
    """
    path = Path(path)
    lines: list[str] = []

    class _Lines:
        def write(self, text: str) -> None:
            lines.append(text)

    writer = csv.writer(_Lines(), delimiter="\t" if path.suffix.lower() == ".tsv" else ",", lineterminator="\n")
    writer.writerow(["time", *(f"{name}_{axis}" for name in trajectories.names for axis in "xyz")])
    points = trajectories.points.reshape(len(trajectories.t), -1)
    for time, row in zip(trajectories.t, points):
        writer.writerow([format_number(time), *map(format_number, row)])
    text = "".join(lines)
    return write_atomically(path, lambda handle: handle.write(text.encode("utf-8")), "CSV file")
