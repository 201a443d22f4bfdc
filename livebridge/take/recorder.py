"""Recording live takes to a directory, written incrementally, and reading them back.

Take directory format (``livebridge-take-dir``, version 1)
---------------------------------------------------------
``take.toml``
    Manifest: ``format``, ``version``, ``created`` (local wall-clock ISO time),
    ``t0`` (the monotonic time, s, of the first frame), ``muscle_names``,
    ``marker_names``, ``fps`` (nominal, or absent), ``units = "mm"``, and the
    names of the copied ``session`` and ``calibration`` files.
``contractions.csv``
    Header ``frame,seq,t,<muscle>...,error_upper_mm,error_lower_mm``; one row
    per solved frame set. ``t`` is seconds on the runtime's monotonic clock
    (the frame set's capture time); ``frame`` counts rows from 0; ``seq`` is
    the frame-set number (gaps = frame sets the pipeline dropped).
``markers.csv``
    Header ``frame,seq,t,<marker>_x,<marker>_y,<marker>_z,...``: the labelled
    marker positions in the capture (world) frame, mm. An empty field means
    the marker was not seen in that frame set.
``displacements.csv`` (when recorded)
    Same layout: each labelled marker's displacement from neutral in the face
    model frame, mm (what the solver consumed).
``markers.c3d`` (written when the take is closed)
    The labelled markers as a C3D file (``c3d.Writer``): one point per marker,
    labelled with the marker name, one frame per row of ``markers.csv``, at the
    take's ``fps`` (or the rate of its timestamps), units mm, float storage; a
    marker not seen in a frame is an invalid point (residual -1). C3D needs the
    frame count up front, so it is an export written from ``markers.csv`` at
    close, to a temporary name and renamed; ``markers.csv`` stays the
    crash-safe record. A take whose close never ran (a crash) is exported with
    :func:`export_c3d` (``livebridge take export-c3d TAKE_DIR``).
``session.toml``, ``calibration.*``
    Copies of the files the take was recorded with (``calibration.toml`` is
    written from the cameras themselves when there is no file, e.g. for a
    simulated rig).
``frames/`` (optional)
    Raw camera images in the replay format of :mod:`livebridge.take.replay`
    (written by its :class:`~livebridge.take.replay.TakeWriter`): per camera
    ``frames/<camera>/000000.pgm ...`` (uncompressed binary PGM by default: ~1 ms
    per 1280x800 image, so four cameras at 60 fps keep up on one writer thread,
    where PNG took 10-40 ms an image and dropped most frame sets live; ``.png``
    on request, about half the size) and the timestamp file
    ``frames/<camera>.csv`` (``seq,t_capture,exposure_us,gain,sync_domain,
    source_id``). ``replay://TAKE_DIR`` plays them back as cameras, so a
    session with ``urls = ["replay://TAKE_DIR?realtime=0"]`` and
    ``calibration = "TAKE_DIR/calibration.toml"`` runs the take through the
    pipeline again.

All CSV files are plain RFC-4180 text with a header row, ``.`` as decimal
separator. They are written by a background thread in whole lines, one
``write`` per flush, at least every ``flush_interval`` seconds (0.5 s by
default), so a crash -- even SIGKILL -- loses at most the last second, and a
reader never sees half a line except possibly at the very end of a file
(which :func:`load_take_dir` drops).
"""

from __future__ import annotations

import datetime
import os
import queue
import shutil
import threading
import time
import warnings
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.capture.sources import SourceWrapper
from livebridge.errors import InputError
from livebridge.tomlio import load_toml, save_toml

TAKE_DIR_FORMAT = "livebridge-take-dir"
TAKE_DIR_VERSION = 1
C3D_NAME = "markers.c3d"
FRAME_FORMATS = (".pgm", ".png")


class _CsvStream:
    """Whole lines appended in memory and written with one ``os.write`` per flush."""

    def __init__(self, path: Path, header: list[str]):
        self.path = path
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_APPEND, 0o644)
        self._pending: list[str] = [",".join(header) + "\n"]
        self._lock = threading.Lock()
        self.flush()  # the header is on disk from the start

    def append(self, line: str) -> None:
        with self._lock:
            self._pending.append(line)

    def flush(self, sync: bool = False) -> None:
        with self._lock:
            lines, self._pending = self._pending, []
        if lines:
            data = "".join(lines).encode()
            while data:
                written = os.write(self._fd, data)
                data = data[written:]
        if sync:
            os.fsync(self._fd)

    def close(self) -> None:
        self.flush(sync=True)
        os.close(self._fd)


def _fmt(values: np.ndarray, digits: int) -> str:
    return ",".join("" if v != v else f"{v:.{digits}f}" for v in np.asarray(values, dtype=np.float64).ravel().tolist())


class TakeRecorder:
    """Writes a take directory while the pipeline runs.

    Parameters
    ----------
    path : Path
        The take directory; created, and must not exist or be empty.
    muscle_names : sequence of str
    marker_names : sequence of str
    session_file, calibration_file : Path, optional
        Copied into the take.
    fps : float, optional
        Nominal frame-set rate, for the manifest.
    record_displacements : bool
        Also write ``displacements.csv``.
    record_frames : bool
        Also write raw camera images (replay format) from :meth:`record_frames` or from the sources
        :meth:`wrap_sources` returns.
    frame_format : {".pgm", ".png"}
        Image files of the raw frames: uncompressed PGM (default, fast enough for live cameras) or PNG.
    flush_interval : float
        Seconds between flushes to the OS (at most 1).
    cameras : CameraGroup, optional
        Written as ``calibration.toml`` when no ``calibration_file`` is given.
    lossless_frames : bool
        True: :meth:`record_frames` waits for the disk instead of dropping frames (for unpaced runs, whose
        cameras can wait; a live camera cannot, so the default drops and counts).
    frame_queue : int
        Raw frames waiting for the disk beyond which a new frame set is dropped.
    """

    def __init__(self, path: str | Path, muscle_names, marker_names, session_file=None, calibration_file=None,
                 fps: float | None = None, record_displacements: bool = True, record_frames: bool = False,
                 flush_interval: float = 0.5, cameras=None, lossless_frames: bool = False, frame_queue: int = 64,
                 frame_format: str = ".pgm"):
        self.path = Path(path)
        if self.path.exists() and (not self.path.is_dir() or any(self.path.iterdir())):
            raise InputError("the take directory exists and is not empty; choose a new one", self.path)
        if not 0 < flush_interval <= 1.0:
            raise InputError("flush_interval must be in (0, 1] seconds", field="flush_interval")
        if frame_format not in FRAME_FORMATS:
            raise InputError(f"frame_format must be one of {FRAME_FORMATS}, got {frame_format!r}",
                             field="frame_format")
        self.path.mkdir(parents=True, exist_ok=True)
        self.muscle_names = tuple(muscle_names)
        self.marker_names = tuple(marker_names)
        self.flush_interval = flush_interval
        manifest = {
            "format": TAKE_DIR_FORMAT, "version": TAKE_DIR_VERSION,
            "created": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
            "units": "mm", "muscle_names": list(self.muscle_names), "marker_names": list(self.marker_names),
        }
        if fps:
            manifest["fps"] = float(fps)
        for key, source in (("session", session_file), ("calibration", calibration_file)):
            if source is not None:
                source = Path(source)
                target = self.path / (f"{key}{source.suffix}" if key == "calibration" else "session.toml")
                shutil.copyfile(source, target)
                manifest[key] = target.name
        if calibration_file is None and cameras is not None:
            from livebridge.calibration.calibfile import save_calibration

            save_calibration(self.path / "calibration.toml", cameras,
                             {"source": "the cameras this take was recorded with"})
            manifest["calibration"] = "calibration.toml"
        self._manifest = manifest
        save_toml(self.path / "take.toml", manifest)
        xyz = [f"{name}_{axis}" for name in self.marker_names for axis in "xyz"]
        self._contractions = _CsvStream(self.path / "contractions.csv",
                                        ["frame", "seq", "t", *self.muscle_names, "error_upper_mm", "error_lower_mm"])
        self._markers = _CsvStream(self.path / "markers.csv", ["frame", "seq", "t", *xyz])
        self._displacements = _CsvStream(self.path / "displacements.csv", ["frame", "seq", "t", *xyz]) \
            if record_displacements else None
        self._frame_writer = None
        self._frame_queue: queue.Queue | None = None
        self.lossless_frames = bool(lossless_frames)
        if record_frames:
            from livebridge.take.replay import RECORDED_FRAMES, TakeWriter

            self._frame_writer = TakeWriter(self.path / RECORDED_FRAMES, frame_format)
            self._frame_soft_limit = max(1, int(frame_queue))  # a new frame set is dropped beyond this
            self._frame_queue = queue.Queue(maxsize=4 * self._frame_soft_limit)  # the rest of a kept set fits
            self._frames_lock = threading.Lock()
            self._frame_decisions: OrderedDict[tuple[str, int], bool] = OrderedDict()
            manifest["raw_frames"] = RECORDED_FRAMES
            save_toml(self.path / "take.toml", manifest)
        self.frames = 0
        self.frames_dropped = 0
        self._t0: float | None = None
        self._closed = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._flush_loop, name="take-recorder", daemon=True)
        self._thread.start()

    def record(self, seq: int, t: float, contractions: np.ndarray, markers: np.ndarray | None = None,
               displacements: np.ndarray | None = None, region_errors=(float("nan"), float("nan"))) -> None:
        """Append one frame set.

        Parameters
        ----------
        seq : int
        t : float
            Monotonic seconds (capture time of the frame set).
        contractions : ndarray, shape (n_muscles,)
        markers : ndarray, shape (n_markers, 3), optional
            Labelled positions in the capture frame, mm; NaN unseen.
        displacements : ndarray, shape (n_markers, 3), optional
            Displacements in the model frame, mm; NaN unseen.
        region_errors : (float, float)
            RMS marker error of the upper and lower solve, mm.
        """
        if self._closed:
            raise RuntimeError("the recorder is closed")
        if self._t0 is None:
            self._t0 = float(t)
        frame = self.frames
        lead = f"{frame},{int(seq)},{t:.6f},"
        self._contractions.append(lead + _fmt(contractions, 6) + "," + _fmt(region_errors, 4) + "\n")
        n = len(self.marker_names)
        blank = ",".join([""] * (3 * n))
        self._markers.append(lead + (blank if markers is None else _fmt(markers, 4)) + "\n")
        if self._displacements is not None:
            self._displacements.append(lead + (blank if displacements is None else _fmt(displacements, 4)) + "\n")
        self.frames += 1

    def record_frames(self, frames) -> None:
        """Queue raw camera frames (:class:`~livebridge.capture.frame.Frame`) for the ``frames/`` take.

        Never blocks unless ``lossless_frames``: frames arriving faster than the disk takes them are
        dropped and counted in ``frames_dropped`` -- whole frame sets at a time (the frames of one
        ``sync_domain`` and ``seq`` are all kept or all dropped), so that the recording replays as
        complete frame sets.
        """
        if self._frame_queue is None:
            return
        for frame in frames:
            if frame is None:
                continue
            if self.lossless_frames:
                while not self._closed:
                    try:
                        self._frame_queue.put(frame, timeout=0.1)
                        break
                    except queue.Full:
                        continue
                continue
            with self._frames_lock:  # keep or drop whole frame sets (same domain and seq), not single frames
                key = (frame.sync_domain, int(frame.seq))
                keep = self._frame_decisions.get(key)
                if keep is None:
                    keep = self._frame_decisions[key] = self._frame_queue.qsize() < self._frame_soft_limit
                    while len(self._frame_decisions) > 1024:
                        self._frame_decisions.popitem(last=False)
            if keep:
                try:
                    self._frame_queue.put_nowait(frame)
                    continue
                except queue.Full:
                    pass
            self.frames_dropped += 1

    def wrap_sources(self, sources) -> list:
        """Camera sources whose every frame read is also recorded (see :meth:`record_frames`); the sources
        are returned unchanged when this recorder writes no raw frames."""
        if self._frame_queue is None:
            return list(sources)
        return [RecordingSource(source, self) for source in sources]

    def _flush_loop(self) -> None:
        next_flush = time.monotonic() + self.flush_interval
        while not self._stop.is_set():
            timeout = max(0.0, next_flush - time.monotonic())
            if self._frame_queue is not None:
                try:
                    self._write_image(self._frame_queue.get(timeout=min(timeout, 0.05)))
                except queue.Empty:
                    pass
            else:
                self._stop.wait(timeout)
            if time.monotonic() >= next_flush:
                self._flush_all()
                next_flush = time.monotonic() + self.flush_interval

    def _write_image(self, frame) -> None:
        self._frame_writer.write(frame)

    def _flush_all(self, sync: bool = False) -> None:
        for stream in (self._contractions, self._markers, self._displacements):
            if stream is not None:
                stream.flush(sync)

    def close(self) -> None:
        """Write everything still pending, fsync, and close the files (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self._thread.join()
        if self._frame_queue is not None:
            while True:
                try:
                    self._write_image(self._frame_queue.get_nowait())
                except queue.Empty:
                    break
        for stream in (self._contractions, self._markers, self._displacements):
            if stream is not None:
                stream.close()
        if self._frame_writer is not None:
            self._frame_writer.close()
            self._manifest.update(frames_written={k: int(v) for k, v in self._frame_writer.counts.items()},
                                  frames_dropped=int(self.frames_dropped))
        if self._t0 is not None:
            self._manifest.update(t0=self._t0, frames=self.frames)
        if self._t0 is not None or self._frame_writer is not None:
            save_toml(self.path / "take.toml", self._manifest)
        if self.frames and self.marker_names:
            self._export_c3d()

    def _export_c3d(self) -> None:
        """``markers.c3d`` from the closed ``markers.csv``; skipped when one frame and no fps give no rate."""
        names, markers, t = _read_markers(self.path)
        rate = _take_rate(self._manifest.get("fps"), t)
        if rate is not None:
            write_c3d(self.path / C3D_NAME, names, markers, rate)

    def __enter__(self) -> TakeRecorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class RecordingSource(SourceWrapper):
    """A camera source that hands every frame it reads to a :class:`TakeRecorder` (raw frames).

    Wraps any :class:`~livebridge.capture.sources.CameraSource`; everything else is the inner source's.
    """

    def __init__(self, source, recorder: TakeRecorder):
        super().__init__(source)
        self.recorder = recorder

    def read(self, timeout: float | None = None):
        frame = self.source.read(timeout)
        if frame is not None:
            self.recorder.record_frames((frame,))
        return frame


@dataclass(frozen=True, eq=False)
class RecordedTake:
    """A take directory read back.

    Attributes
    ----------
    path : Path
    seq : ndarray of int, shape (n_frames,)
    t : ndarray, shape (n_frames,)
    contractions : ndarray, shape (n_frames, n_muscles)
    region_errors : ndarray, shape (n_frames, 2)
    markers : ndarray, shape (n_frames, n_markers, 3)
        Capture-frame positions, mm, NaN unseen.
    displacements : ndarray, shape (n_frames, n_markers, 3) or None
    muscle_names, marker_names : tuple of str
    manifest : dict
    complete : bool
        False when the take was cut short (no final manifest, or a torn last line).
    """

    path: Path
    seq: np.ndarray
    t: np.ndarray
    contractions: np.ndarray
    region_errors: np.ndarray
    markers: np.ndarray
    displacements: np.ndarray | None
    muscle_names: tuple[str, ...]
    marker_names: tuple[str, ...]
    manifest: dict
    complete: bool

    @property
    def n_frames(self) -> int:
        return len(self.t)

    def to_take(self):
        """As a :class:`livebridge.take.npz.Take` (positions, displacements, solved contractions)."""
        from livebridge.take.npz import Take

        return Take(self.t, self.marker_names, displacements=self.displacements, positions=self.markers,
                    contractions=self.contractions, muscle_names=self.muscle_names, fps=self.manifest.get("fps"))


def _read_csv(path: Path, n_columns: int) -> tuple[list[str], np.ndarray, bool]:
    """Header and float rows of a recorder CSV; a torn or malformed last line is dropped."""
    text = path.read_text()
    lines = text.split("\n")
    torn = not text.endswith("\n")
    lines = lines[:-1]  # the empty string after the last newline, or a line a crash cut short
    if not lines:
        raise InputError("empty file (no header)", path)
    header = lines[0].split(",")
    if len(header) != n_columns:
        raise InputError(f"header has {len(header)} columns, expected {n_columns}", path)
    rows = []
    for number, line in enumerate(lines[1:], start=2):
        fields = line.split(",")
        if len(fields) != n_columns:
            raise InputError(f"line {number} has {len(fields)} fields, expected {n_columns}", path)
        try:
            rows.append([float(f) if f else np.nan for f in fields])
        except ValueError as error:
            raise InputError(f"line {number}: {error}", path) from None
    return header, np.array(rows, dtype=np.float64).reshape(len(rows), n_columns), torn


def _load_manifest(path: Path) -> dict:
    """``take.toml`` of the take directory ``path``, format and version checked."""
    manifest = load_toml(path / "take.toml")
    if manifest.get("format") != TAKE_DIR_FORMAT:
        raise InputError(f"format must be {TAKE_DIR_FORMAT!r}", path / "take.toml", "format")
    if manifest.get("version", 0) > TAKE_DIR_VERSION:
        raise InputError(f"version {manifest['version']} is newer than this livebridge reads",
                         path / "take.toml", "version")
    return manifest


def load_take_dir(path: str | Path) -> RecordedTake:
    """Read a take directory, including one cut short by a crash (up to its last flushed line).

    Frames present in some files but not yet in others (a crash between two
    files' flushes) are dropped, so every array has the same frames.
    """
    path = Path(path)
    manifest = _load_manifest(path)
    muscles = tuple(manifest.get("muscle_names", ()))
    markers = tuple(manifest.get("marker_names", ()))
    _, c_rows, torn_c = _read_csv(path / "contractions.csv", 3 + len(muscles) + 2)
    _, m_rows, torn_m = _read_csv(path / "markers.csv", 3 + 3 * len(markers))
    d_rows, torn_d = None, False
    if (path / "displacements.csv").exists():
        _, d_rows, torn_d = _read_csv(path / "displacements.csv", 3 + 3 * len(markers))
    n = min(len(c_rows), len(m_rows), len(d_rows) if d_rows is not None else len(c_rows))
    c_rows, m_rows = c_rows[:n], m_rows[:n]
    if not np.array_equal(c_rows[:, :2], m_rows[:, :2]):
        raise InputError("contractions.csv and markers.csv disagree on frame numbers", path)
    displacements = None
    if d_rows is not None:
        displacements = d_rows[:n, 3:].reshape(n, len(markers), 3)
    complete = "frames" in manifest and manifest["frames"] == n and not (torn_c or torn_m or torn_d)
    return RecordedTake(
        path=path, seq=c_rows[:, 1].astype(np.int64), t=c_rows[:, 2],
        contractions=c_rows[:, 3:3 + len(muscles)], region_errors=c_rows[:, 3 + len(muscles):],
        markers=m_rows[:, 3:].reshape(n, len(markers), 3), displacements=displacements,
        muscle_names=muscles, marker_names=markers, manifest=manifest, complete=complete,
    )


# -- C3D export ------------------------------------------------------------------------------------------------


def _read_markers(path: Path) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
    """Marker names, positions ``(n_frames, n_markers, 3)`` (mm, NaN unseen) and times ``(n_frames,)`` of a take.

    Reads ``markers.csv`` alone: every row flushed before a crash counts (a torn last line is dropped).
    """
    names = tuple(_load_manifest(path).get("marker_names", ()))
    if not (path / "markers.csv").is_file():
        raise InputError("file not found", path / "markers.csv")
    _, rows, _ = _read_csv(path / "markers.csv", 3 + 3 * len(names))
    return names, rows[:, 3:].reshape(len(rows), len(names), 3), rows[:, 2]


def _take_rate(fps: float | None, t: np.ndarray) -> float | None:
    """The take's frame rate, Hz: the nominal ``fps``, else from the median step of the times ``t``
    (shape (n_frames,)); None when neither is known (one frame, no fps)."""
    if fps:
        return float(fps)
    steps = np.diff(t)
    steps = steps[steps > 0]
    if not len(steps):
        return None
    return round(1.0 / float(np.median(steps)), 3)


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
    with open(partial, "wb") as handle, warnings.catch_warnings():
        warnings.filterwarnings("ignore", "No analog data", UserWarning)  # markers only, by design
        writer.write(handle)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(partial, out)
    return out


def export_c3d(path: str | Path, out: str | Path | None = None, rate: float | None = None) -> Path:
    """Write the markers of the take directory ``path`` as C3D (see the module docstring).

    For a take whose recorder was never closed (a crash), or to re-export one.

    Parameters
    ----------
    path : Path
        The take directory.
    out : Path, optional
        The C3D file; default ``<path>/markers.c3d``.
    rate : float, optional
        Frames per second; default the take's ``fps``, else the rate of its timestamps.

    Returns
    -------
    Path
        The file written.
    """
    path = Path(path)
    names, markers, t = _read_markers(path)
    if not names:
        raise InputError("the take has no markers", path / "take.toml", "marker_names")
    if not len(markers):
        raise InputError("no frames recorded", path / "markers.csv")
    rate = rate or _take_rate(_load_manifest(path).get("fps"), t)
    if rate is None or not rate > 0:
        raise InputError("the frame rate is unknown (one frame and no fps); give it", path / "take.toml", "fps")
    return write_c3d(path / C3D_NAME if out is None else out, names, markers, rate)
