"""C3D export of a take's labelled markers (``markers.c3d``; ``livebridge take export-c3d TAKE_DIR``).

One C3D point per marker, labelled with the marker name, one frame per row of the take's
``markers.csv``, at the take's ``fps`` (or the rate of its timestamps), units mm, float storage; a
marker not seen in a frame is an invalid point (residual -1). Written with ``c3d.Writer`` to a
temporary name and renamed, so a crash never leaves half a file, and a failed write leaves no temporary
file. :func:`export_c3d` checks the rate and the output path before it reads the take: the output's folder
must exist, an existing file is overwritten only when asked, and never one of the take's own records.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

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

    out = Path(out)
    points = c3d_points(markers)
    # point_scale < 0: float32 coordinates, no 16-bit quantisation of the millimetres
    writer = c3d.Writer(point_rate=float(rate), point_scale=-1.0, point_units="mm")
    writer.set_point_labels(list(marker_names))
    # py-c3d 0.6 leaves an invalid point's x, y, z in the file as that point's last valid ones; C3D readers
    # go by the residual -1, not the coordinates
    no_analog = np.zeros((0, 0))
    writer.add_frames([(frame, no_analog) for frame in points])
    partial = out.with_name(out.name + ".partial")
    try:
        with open(partial, "wb") as handle, warnings.catch_warnings():
            warnings.filterwarnings("ignore", "No analog data", UserWarning)  # markers only, by design
            writer.write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(partial, out)
    except OSError as error:
        raise InputError(f"cannot write the C3D file ({error.strerror or error})", out) from None
    finally:
        partial.unlink(missing_ok=True)  # after a failure; gone already after the rename
    return out


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
    return write_c3d(out, names, markers, rate)


def export_closed_take(path: str | Path, fps: float | None) -> None:
    """``markers.c3d`` of a take directory just closed; skipped when one frame and no ``fps`` give no rate."""
    names, markers, t = read_markers(path)
    rate = frame_rate(fps, t)
    if rate is not None:
        write_c3d(Path(path) / C3D_NAME, names, markers, rate)
