"""TRC marker files (OpenSim, Pose2Sim, Motive, Cortex): read and write.

The layout, tab separated::

    PathFileType  4  (X/Y/Z)  name.trc
    DataRate  CameraRate  NumFrames  NumMarkers  Units  OrigDataRate  OrigDataStartFrame  OrigNumFrames
    60.00     60.00       300        41          mm     60.00         1                   300
    Frame#  Time  Head            RShoulder ...
                  X1   Y1   Z1    X2   Y2   Z2 ...
    (often a blank line)
    1       0.000 12.1 1.5  900.2 ...

Units from the header's ``Units`` (mm, cm, m), times from the ``Time`` column, empty cells where a marker
was not seen. The header's ``NumFrames`` is not trusted (edited files often disagree); ``NumMarkers`` must
match the marker-name row.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from livebridge.atomic import write_atomically
from livebridge.errors import InputError
from livebridge.take.text_table import (
    format_number,
    increasing_times,
    number,
    number_table,
    repeated,
    text_lines,
    where,
    whole_points,
)
from livebridge.take.tracks import Trajectories, file_units

HEADER_KEYS = ("DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units", "OrigDataRate",
               "OrigDataStartFrame", "OrigNumFrames")
FIRST_DATA_LINE = 6  # 1-based: after the five header lines


def read_trc(path: str | Path, units_mm: float | None = None) -> Trajectories:
    """The markers of a TRC file in millimetres (see the module docstring).

    Parameters
    ----------
    path : Path
    units_mm : float, optional
        Millimetres per unit when the header's ``Units`` is blank; one contradicting it is refused.
    """
    path = Path(path)
    lines = text_lines(path)
    if not lines or not lines[0].startswith("PathFileType"):
        raise InputError("not a TRC file (its first line should start with PathFileType)", path, where(1))
    split = _splitter(lines)
    header = _header(lines, split, path)
    scale, unit = file_units(header.get("Units", ""), units_mm, path, where(3, None, "Units"))
    names = _marker_names(lines, split, path, header)
    width = 2 + 3 * len(names)
    rows, line_numbers = [], []
    for line_number, line in enumerate(lines[FIRST_DATA_LINE - 1:], start=FIRST_DATA_LINE):
        if not line.strip():
            continue  # OpenSim writes a blank line before the data; trailing blank lines too
        fields = split(line)
        while len(fields) > width and not fields[-1].strip():
            fields.pop()  # a trailing tab
        if len(fields) != width:
            raise InputError(f"{len(fields)} fields, expected {width} (Frame#, Time and 3 per marker)", path,
                             where(line_number))
        rows.append(fields[1:])
        line_numbers.append(line_number)
    if not rows:
        raise InputError("no frames (no data lines after the header)", path, where(FIRST_DATA_LINE))
    column_names = ["Time", *(f"{name} {axis}" for name in names for axis in "XYZ")]
    table = number_table(rows, line_numbers, list(range(2, width + 1)), column_names, path)
    if np.isnan(table[:, 0]).any():
        k = int(np.argmax(np.isnan(table[:, 0])))
        number(rows[k][0], path, line_numbers[k], 2, "Time", missing_ok=False)  # raises: a frame needs its time
    t = increasing_times(table[:, 0], line_numbers, path, 2, "Time")
    xyz = whole_points(table[:, 1:].reshape(len(table), len(names), 3)) * scale
    return Trajectories(names, t, xyz, path, unit)


def _splitter(lines: list[str]):
    """Fields of a line: tab separated, or by blanks in files written without tabs (no empty cells then)."""
    if "\t" in "".join(lines[:5]):
        return lambda line: line.split("\t")
    return lambda line: line.split()


def _header(lines: list[str], split, path: Path) -> dict[str, str]:
    if len(lines) < 5:
        raise InputError(f"the header is cut short ({len(lines)} lines; a TRC header has 5)", path,
                         where(len(lines) + 1))
    keys = [key.strip() for key in split(lines[1])]
    values = [value.strip() for value in split(lines[2])]
    header = dict(zip(keys, values))
    for key in ("DataRate", "NumMarkers", "Units"):
        if key not in header:
            raise InputError(f"no {key} in the header (expected {' '.join(HEADER_KEYS)})", path, where(2))
    column = keys.index("DataRate") + 1
    if not number(header["DataRate"], path, 3, column, "DataRate", missing_ok=False) > 0:
        raise InputError("DataRate must be > 0", path, where(3, column, "DataRate"))
    count = header["NumMarkers"]
    if not count.isdigit():
        raise InputError(f"NumMarkers must be a whole number, got {count!r:.20}", path,
                         where(3, keys.index("NumMarkers") + 1, "NumMarkers"))
    return header


def _marker_names(lines: list[str], split, path: Path, header: dict[str, str]) -> tuple[str, ...]:
    fields = split(lines[3])
    if len(fields) < 2 or fields[0].strip().lower() not in ("frame#", "frame"):
        raise InputError("expected the marker-name row (Frame#, Time, names)", path, where(4))
    columns = [k + 1 for k, field in enumerate(fields) if k >= 2 and field.strip()]
    names = tuple(fields[c - 1].strip() for c in columns)
    if not names:
        raise InputError("no markers (the marker-name row names none)", path, where(4))
    if len(names) != int(header["NumMarkers"]):
        raise InputError(f"{len(names)} marker names, but the header says NumMarkers {header['NumMarkers']}", path,
                         where(4))
    repeated(names, path, 4, columns)
    return names


def write_trc(path: str | Path, trajectories: Trajectories) -> Path:
    """Write ``trajectories`` as a TRC file in millimetres (tab separated, empty cells unseen), atomically.

    Frame numbers count sample periods from 1 at the trajectories' rate, so a gap in the times is a gap in
    the frame numbers too; the times are written exactly (shortest round-trip text).
    """
    path = Path(path)
    rate = trajectories.rate
    if rate is None:
        raise InputError("one frame: a TRC file needs a frame rate", trajectories.source, "rate")
    t, points, names = trajectories.t, trajectories.points, trajectories.names
    frames = np.rint((t - t[0]) * rate).astype(np.int64) + 1
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "\t".join(HEADER_KEYS),
        "\t".join(map(str, (f"{rate:.6f}", f"{rate:.6f}", len(t), len(names), "mm", f"{rate:.6f}", 1, len(t)))),
        "\t".join(["Frame#", "Time", *(f"{name}\t\t" for name in names)]),
        "\t".join(["", "", *(f"{axis}{k}" for k in range(1, len(names) + 1) for axis in "XYZ")]),
        "",
    ]
    for frame, time, row in zip(frames, t, points.reshape(len(t), -1)):
        lines.append("\t".join([str(frame), format_number(time), *map(format_number, row)]))
    text = "\n".join(lines) + "\n"
    return write_atomically(path, lambda handle: handle.write(text.encode("utf-8")), "TRC file")
