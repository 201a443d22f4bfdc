"""C3D files: the export of a take's labelled markers (``markers.c3d``; ``livebridge take export-c3d
TAKE_DIR``) and the reader of other systems' C3D files (Vicon, OptiTrack, Qualisys; :func:`read_c3d`).

Export: one C3D point per marker, labelled with the marker name, one frame per sample period at the
take's ``fps`` (or the rate of its timestamps) -- a frame set the pipeline dropped is a frame of invalid
points, so later frames keep their times -- units mm, float storage; a marker not seen in a frame is an
invalid point (residual -1, coordinates 0). Written with ``c3d.Writer`` to a temporary name and renamed,
so a crash never leaves half a file, and a failed write leaves no temporary file. :func:`export_c3d`
checks the rate and the output path before it reads the take: the output's folder must exist, an
existing file is overwritten only when asked, and never one of the take's own records. A take cut short
(recorder never closed, last line torn) exports up to its last whole line.

Reading: the unit from ``POINT:UNITS`` (mm, cm, m), the frame rate from the header, names from
``POINT:LABELS`` (and ``LABELS2``... for more than 255 points; blanks trimmed), a point with residual < 0
or all three coordinates exactly 0 (how some systems write a gap) as NaN, analog channels ignored.
"""

from __future__ import annotations

import io
import math
import struct
import warnings
from pathlib import Path

import numpy as np

from livebridge.atomic import write_atomically
from livebridge.errors import InputError
from livebridge.take.directory import (
    C3D_NAME,
    CONTRACTIONS,
    DISPLACEMENTS,
    MANIFEST,
    MARKERS,
    frame_rate,
    load_manifest,
    read_markers,
)
from livebridge.take.tracks import Trajectories, file_units, on_frame_grid

MAX_RATE = 100_000.0  # Hz; C3D stores the rate as a float32, and no capture runs faster


def c3d_points(markers: np.ndarray) -> np.ndarray:
    """C3D point rows ``(n_frames, n_markers, 5)`` (x, y, z, residual, camera mask) from positions.

    Parameters
    ----------
    markers : ndarray, shape (n_frames, n_markers, 3)
        mm, NaN where a marker was not seen.

    Returns
    -------
    ndarray, shape (n_frames, n_markers, 5)
        Seen: the position, residual 0 (no residual is measured), camera mask 0. Unseen: zeros and
        residual -1, C3D's "invalid point".
    """
    markers = np.asarray(markers, dtype=np.float64)
    seen = np.all(np.isfinite(markers), axis=-1)
    points = np.zeros(markers.shape[:-1] + (5,))
    points[..., :3] = np.where(seen[..., None], markers, 0.0)
    points[..., 3] = np.where(seen, 0.0, -1.0)
    return points


def write_c3d(out: str | Path, marker_names, markers: np.ndarray, rate: float) -> Path:
    """Write labelled markers as a C3D file (no analog channels), atomically.

    Parameters
    ----------
    out : Path
        The file; written as ``<out>.partial`` and renamed, so a crash never leaves a half file at ``out``.
    marker_names : sequence of str
        Point labels, one per marker.
    markers : ndarray, shape (n_frames, n_markers, 3)
        Positions, mm, NaN unseen (written as invalid points).
    rate : float
        Frames per second.

    Returns
    -------
    Path
        ``out``.
    """
    import c3d

    points = c3d_points(markers)
    if not len(points):
        raise InputError("no frames to write", out)
    # point_scale < 0: float32 coordinates, no 16-bit quantisation of the millimetres
    writer = c3d.Writer(point_rate=float(rate), point_scale=-1.0, point_units="mm")
    writer.set_point_labels(list(marker_names))
    no_analog = np.zeros((0, 0))
    writer.add_frames([(frame, no_analog) for frame in points])
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "No analog data", UserWarning)  # markers only, by design
        writer.write(buffer)
    data = _zero_invalid_points(buffer.getbuffer(), points)
    return write_atomically(out, lambda handle: handle.write(data), "C3D file")


def _zero_invalid_points(data: memoryview, points: np.ndarray) -> bytes:
    """The C3D file ``data`` with every invalid point's coordinates 0.

    py-c3d 0.6 leaves an invalid point's x, y, z as that point's last valid ones; readers that go by the
    coordinates instead of the residual (or plot them) would see a frozen marker. The point block is the
    standard's (float32 x, y, z, residual word per point, frames in a row from the header's data block),
    and the written valid points are checked against ours before anything is replaced.
    """
    data = bytearray(data)
    start = 512 * (struct.unpack_from("<H", data, 16)[0] - 1)  # header word 9: first block of the data
    block = np.frombuffer(data, "<f4", points[..., :4].size, start).reshape(points.shape[:-1] + (4,)).copy()
    valid = points[..., 3] >= 0
    if not np.array_equal(block[valid], points[valid][:, :4].astype(np.float32)):
        raise RuntimeError("py-c3d wrote its point block in an unexpected layout")
    block[~valid] = (0.0, 0.0, 0.0, -1.0)
    data[start:start + block.nbytes] = block.tobytes()
    return bytes(data)


def check_rate(rate: float, field: str = "rate") -> float:
    """``rate`` (frames per second) as a float, finite and in ``(0, MAX_RATE]``, else :class:`InputError`."""
    if not 0.0 < float(rate) <= MAX_RATE:  # also refuses NaN
        raise InputError(f"must be a frame rate in (0, {MAX_RATE:g}] Hz, got {rate}", field=field)
    return float(rate)


def check_output(out: Path, take: Path, force: bool) -> Path:
    """``out`` if a C3D file may be written there: its folder exists, it is not a folder, not one of the
    take's own records, and not an existing file unless ``force``."""
    out = Path(out)
    if not out.parent.is_dir():
        raise InputError(f"the folder {str(out.parent)!r} does not exist; create it first", out)
    if out.is_dir():
        raise InputError("is a folder; give a file name", out)
    records = {(take / name).resolve() for name in (MANIFEST, CONTRACTIONS, MARKERS, DISPLACEMENTS)}
    if out.resolve() in records:
        raise InputError("is one of the take's own records; choose another file", out)
    if out.exists() and not force:
        raise InputError("exists; not overwritten without force (livebridge take export-c3d --force)", out)
    return out


def export_c3d(path: str | Path, out: str | Path | None = None, rate: float | None = None,
               force: bool = False) -> Path:
    """Write the markers of the take directory ``path`` as C3D (see the module docstring).

    For a take whose recorder was never closed (a crash), or to re-export one.

    Parameters
    ----------
    path : Path
        The take directory.
    out : Path, optional
        The C3D file; default ``<path>/markers.c3d``. Its folder must exist.
    rate : float, optional
        Frames per second, in (0, :data:`MAX_RATE`]; default the take's ``fps``, else the rate of its timestamps.
    force : bool
        Overwrite ``out`` when it exists.

    Returns
    -------
    Path
        The file written.
    """
    path = Path(path)
    if rate is not None:
        rate = check_rate(rate)
    manifest = load_manifest(path)
    out = check_output(path / C3D_NAME if out is None else Path(out), path, force)
    names, markers, t = read_markers(path)
    if not names:
        raise InputError("the take has no markers", path / MANIFEST, "marker_names")
    if not len(markers):
        raise InputError("no frames recorded", path / MARKERS)
    if rate is None:
        rate = frame_rate(manifest.get("fps"), t)
        if rate is None:
            raise InputError("the frame rate is unknown (one frame and no fps); give it", path / MANIFEST, "fps")
        if not rate <= MAX_RATE:
            raise InputError(f"the take's frame rate, {rate:g} Hz, is above {MAX_RATE:g} Hz; give it",
                             path / MANIFEST, "fps")
    return write_c3d(out, names, on_frame_grid(t, markers, rate), rate)


def export_closed_take(path: str | Path, fps: float | None) -> None:
    """``markers.c3d`` of a take directory just closed; skipped when one frame and no ``fps`` give no rate."""
    names, markers, t = read_markers(path)
    rate = frame_rate(fps, t)
    if rate is not None and len(markers):
        write_c3d(Path(path) / C3D_NAME, names, on_frame_grid(t, markers, rate), rate)


# ------------------------------------------------------------------------------------------------ reading
_NOT_C3D = (AssertionError, struct.error, ValueError, KeyError, TypeError, IndexError, UnicodeDecodeError,
            OverflowError, UnboundLocalError, OSError)
"""What py-c3d raises on bytes that are not a C3D file (it asserts the header's magic byte, among others; a count
too large for an index overflows; an unknown processor type leaves its float reader unbound; a section pointer of
0 seeks before the file's start)."""


def read_c3d(path: str | Path, units_mm: float | None = None) -> Trajectories:
    """The labelled points of a C3D file as :class:`Trajectories` (see the module docstring).

    Parameters
    ----------
    path : Path
    units_mm : float, optional
        Millimetres per unit for a file whose ``POINT:UNITS`` is missing or blank (else mm); one that
        contradicts the file's is refused.
    """
    import c3d

    path = Path(path)
    with open(path, "rb") as handle, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # py-c3d warns about analog data and EOF; both are checked below
        try:
            reader = c3d.Reader(handle)
            names = _point_labels(reader, path)
            units = reader.get("POINT:UNITS")
            stated = units.string_value if units is not None else ""
            rate = float(reader.point_rate)
            expected = reader.frame_count
            points = [p[:, :4].copy() for _, p, _ in reader.read_frames(copy=False, analog_transform=False)]
        except InputError:
            raise  # a ValueError too, but already says what is wrong
        except _NOT_C3D as error:
            detail = ("its processor type is none of Intel, DEC, MIPS" if isinstance(error, UnboundLocalError)
                      else str(error).strip() or type(error).__name__)
            raise InputError(f"not a C3D file, or a damaged one ({detail})", path) from None
    scale, unit = file_units(stated, units_mm, path, "POINT:UNITS")
    if not (math.isfinite(rate) and 0 < rate <= MAX_RATE):
        raise InputError(f"the header's frame rate is {rate:g} Hz", path, "header")
    if len(points) < expected:
        raise InputError(f"truncated: {len(points)} of the {expected} frames the header announces", path,
                         f"frame {len(points) + 1}")
    block = np.array(points, dtype=np.float64).reshape(len(points), len(names), 4)
    unseen = (block[..., 3] < 0) | np.all(block[..., :3] == 0, axis=-1) | ~np.all(np.isfinite(block), axis=-1)
    xyz = np.where(unseen[..., None], np.nan, block[..., :3] * scale)
    return Trajectories(names, np.arange(len(block)) / rate, xyz, path, unit)


def _point_labels(reader, path: Path) -> tuple[str, ...]:
    """The trimmed labels of the file's points (``LABELS``, then ``LABELS2``, ...); blank ones as ``P<k>``."""
    used = int(reader.point_used)
    if used == 0:
        raise InputError("no markers (POINT:USED = 0)", path, "POINT:USED")
    labels: list[str] = []
    for group in ["LABELS"] + [f"LABELS{k}" for k in range(2, 2 + used // 255 + 1)]:
        param = reader.get(f"POINT:{group}")
        if param is None:
            break
        labels.extend(str(label).strip() for label in param.string_array)
    labels = labels[:used] + [""] * (used - len(labels))
    names = tuple(label or f"P{k + 1}" for k, label in enumerate(labels))
    for k, name in enumerate(names):
        if names.index(name) != k:
            raise InputError(f"marker name {name!r} repeats (points {names.index(name) + 1} and {k + 1})", path,
                             "POINT:LABELS")
    return names
