"""The take directory (``livebridge-take-dir``, version 1): its layout, its manifest, and reading it back.

:class:`~livebridge.take.recorder.TakeRecorder` writes it while the pipeline runs;
:func:`load_take_dir` reads it, :mod:`livebridge.take.replay` plays its raw frames as cameras and
:mod:`livebridge.take.c3d` exports its markers. This module is the one place that knows the layout.

``take.toml``
    Manifest: ``format``, ``version``, ``created`` (local wall-clock ISO time),
    ``t0`` (the monotonic time, s, of the first frame), ``muscle_names``,
    ``marker_names``, ``fps`` (nominal, or absent), ``units = "mm"``, and the
    names of the copied ``session`` and ``calibration`` files. With raw frames also
    ``raw_frames`` (the folder), and at close ``frames_written`` (per camera) and ``frames_dropped``.
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
    The labelled markers as C3D (see :mod:`livebridge.take.c3d`). C3D needs the
    frame count up front, so it is an export written from ``markers.csv`` at
    close; ``markers.csv`` stays the crash-safe record. A take whose close never
    ran (a crash) is exported with :func:`livebridge.take.c3d.export_c3d`
    (``livebridge take export-c3d TAKE_DIR``).
``session.toml``, ``calibration.*``
    Copies of the files the take was recorded with (``calibration.toml`` is
    written from the cameras themselves when there is no file, e.g. for a
    simulated rig).
``arkit.csv`` (a phone take, version 2)
    The Live Link Face packets the contractions were solved from, one row per row of ``contractions.csv``
    (:mod:`livebridge.take.phone`); the manifest then says ``source = "livelinkface"``, ``arkit``
    (the file), and the phone's ``device_id`` and ``subject``. A phone take has no markers
    (``marker_names = []``, ``markers.csv`` holds only ``frame,seq,t``) and no calibration;
    ``[source] url = "replay://TAKE_DIR"`` solves it again through the pipeline. Takes from cameras stay
    version 1.
``frames/`` (optional)
    Raw camera images in the format of :mod:`livebridge.take.raw_frames`: per camera
    ``frames/<camera>/000000.pgm ...`` (uncompressed binary PGM by default: ~1 ms
    per 1280x800 image, so four cameras at 60 fps keep up on one writer thread,
    where PNG took 10-40 ms an image and dropped most frame sets live; ``.png``
    on request, about half the size) and the timestamp file ``frames/<camera>.csv``.
    ``replay://TAKE_DIR`` plays them back as cameras, so a session with
    ``urls = ["replay://TAKE_DIR?realtime=0"]`` runs the take through the pipeline
    again, with the calibration recorded with the take.

All CSV files are plain RFC-4180 text with a header row, ``.`` as decimal
separator. The recorder writes them in whole lines, at least every
``flush_interval`` seconds, so a crash -- even SIGKILL -- loses at most the last
second, and a reader never sees half a line except possibly at the very end of a
file (which :func:`load_take_dir` drops).
"""

from __future__ import annotations

import datetime
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.errors import InputError
from livebridge.take.phone import ArkitTrack, parse_arkit
from livebridge.tomlio import load_toml, save_toml

TAKE_DIR_FORMAT = "livebridge-take-dir"
TAKE_DIR_VERSION = 2  # 2: phone takes (source, arkit, device_id, subject); camera takes are still written as 1
PHONE_VERSION = 2
SOURCES = ("cameras", "livelinkface")
MANIFEST = "take.toml"
CONTRACTIONS = "contractions.csv"
MARKERS = "markers.csv"
DISPLACEMENTS = "displacements.csv"
C3D_NAME = "markers.c3d"
RAW_FRAMES = "frames"
FRAME_FORMATS = (".pgm", ".png")  # image files of the raw frames


def is_take_dir(folder: str | Path) -> bool:
    """True when ``folder`` is a take directory (it has a ``take.toml``)."""
    return (Path(folder) / MANIFEST).is_file()


def new_manifest(muscle_names, marker_names, fps: float | None) -> dict:
    """The manifest of a take directory just created (now as its ``created`` time)."""
    manifest = {
        "format": TAKE_DIR_FORMAT, "version": 1,  # what a camera take needs (older livebridge reads it)
        "created": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        "units": "mm", "muscle_names": list(muscle_names), "marker_names": list(marker_names),
    }
    if fps:
        manifest["fps"] = float(fps)
    return manifest


def save_manifest(path: str | Path, manifest: dict) -> None:
    """Write ``take.toml`` into the take directory ``path``."""
    save_toml(Path(path) / MANIFEST, manifest)


def load_manifest(path: str | Path) -> dict:
    """``take.toml`` of the take directory ``path``, every key checked (:data:`MANIFEST_KEYS`): an unknown or
    missing key or a wrong type raises :class:`InputError` naming the file and the key."""
    path = Path(path)
    file = path / MANIFEST
    if not path.is_dir():
        raise InputError("no such take directory", path)
    if not file.is_file():
        raise InputError(f"not a take directory (no {MANIFEST})", path)
    try:
        manifest = load_toml(file)
    except UnicodeDecodeError:
        raise InputError("not UTF-8 text", file) from None
    except OSError as error:
        raise InputError(f"cannot read ({error.strerror})", file) from None
    _check_manifest(file, manifest)
    return manifest


def _is_names(value) -> bool:
    return isinstance(value, list) and all(isinstance(n, str) and n for n in value) and len(set(value)) == len(value)


def _is_count(value) -> bool:
    return type(value) is int and value >= 0


def _is_file_name(value) -> bool:
    """A plain file name inside the take (no folders, nothing outside it)."""
    return isinstance(value, str) and value not in ("", ".", "..") and "/" not in value and "\\" not in value


def _is_number(value) -> bool:
    return type(value) in (int, float) and math.isfinite(value)


MANIFEST_KEYS = {  # key: (required, check, what the check wants)
    "format": (True, lambda v: v == TAKE_DIR_FORMAT, repr(TAKE_DIR_FORMAT)),
    "version": (True, lambda v: type(v) is int and 1 <= v <= TAKE_DIR_VERSION,
                f"an integer from 1 to {TAKE_DIR_VERSION} (a newer version needs a newer livebridge)"),
    "created": (False, lambda v: isinstance(v, str), "an ISO date-time string"),
    "units": (False, lambda v: v == "mm", '"mm"'),
    "muscle_names": (True, _is_names, "a list of distinct non-empty names"),
    "marker_names": (True, _is_names, "a list of distinct non-empty names"),
    "fps": (False, lambda v: _is_number(v) and v > 0, "a positive finite number"),
    "session": (False, _is_file_name, "a file name inside the take"),
    "calibration": (False, _is_file_name, "a file name inside the take"),
    "raw_frames": (False, _is_file_name, "a folder name inside the take"),
    "frames_written": (False, lambda v: isinstance(v, dict) and all(map(_is_count, v.values())),
                       "a table of camera = frame count"),
    "frames_dropped": (False, _is_count, "a count (integer >= 0)"),
    "t0": (False, _is_number, "a finite number of seconds"),
    "frames": (False, _is_count, "a count (integer >= 0)"),
    "source": (False, lambda v: v in SOURCES, f"one of {', '.join(map(repr, SOURCES))}"),
    "arkit": (False, _is_file_name, "a file name inside the take"),
    "device_id": (False, lambda v: isinstance(v, str), "the phone's device id (text)"),
    "subject": (False, lambda v: isinstance(v, str), "the phone's subject name (text)"),
}
PHONE_KEYS = ("source", "arkit", "device_id", "subject")  # version 2 on


def _check_manifest(file: Path, manifest: dict) -> None:
    unknown = sorted(set(manifest) - set(MANIFEST_KEYS))
    if unknown:
        raise InputError(f"unknown key(s) {', '.join(unknown)}; known: {', '.join(MANIFEST_KEYS)}", file, unknown[0])
    for key, (required, check, wanted) in MANIFEST_KEYS.items():
        if key not in manifest:
            if required:
                raise InputError(f"missing (expected {wanted})", file, key)
        elif not check(manifest[key]):
            raise InputError(f"expected {wanted}, got {manifest[key]!r:.80}", file, key)
    newer = [key for key in PHONE_KEYS if key in manifest and manifest["version"] < PHONE_VERSION]
    if newer:
        raise InputError(f"a version {manifest['version']} take has no {newer[0]} (phone takes are version "
                         f"{PHONE_VERSION})", file, newer[0])
    if manifest.get("source") == "livelinkface" and "arkit" not in manifest:
        raise InputError("missing: a phone take names its ARKit file (arkit = \"arkit.csv\")", file, "arkit")


def contractions_header(muscle_names) -> list[str]:
    """Columns of ``contractions.csv``."""
    return ["frame", "seq", "t", *muscle_names, "error_upper_mm", "error_lower_mm"]


def markers_header(marker_names) -> list[str]:
    """Columns of ``markers.csv`` and ``displacements.csv``."""
    return ["frame", "seq", "t", *(f"{name}_{axis}" for name in marker_names for axis in "xyz")]


def raw_frames_folder(path: str | Path) -> Path:
    """The raw camera frames of the take directory ``path`` (an error names the take when it has none)."""
    frames = Path(path) / RAW_FRAMES
    if not frames.is_dir() and is_take_dir(path) and load_manifest(path).get("source") == "livelinkface":
        raise InputError("a phone take has no camera frames: solve it again with [source] kind = "
                         '"livelinkface", url = "replay://TAKE_DIR"', path)
    if not frames.is_dir():
        raise InputError("this take was recorded without raw frames (recording.raw_frames = false); "
                         "it cannot be replayed through the cameras", path)
    return frames


def calibration_file(path: str | Path) -> Path | None:
    """The calibration file recorded with the take directory ``path`` (its manifest's ``calibration``),
    or None when it has none."""
    name = load_manifest(path).get("calibration")
    if not name or not (Path(path) / name).is_file():
        return None
    return Path(path) / name


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
    arkit : ArkitTrack or None
        A phone take's packets (:mod:`livebridge.take.phone`), row for row with the contractions; None for a
        take from cameras.
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
    arkit: ArkitTrack | None = None

    @property
    def n_frames(self) -> int:
        return len(self.t)

    def to_take(self):
        """As a :class:`livebridge.take.npz.Take` (positions, displacements, solved contractions)."""
        from livebridge.take.npz import Take

        return Take(self.t, self.marker_names, displacements=self.displacements, positions=self.markers,
                    contractions=self.contractions, muscle_names=self.muscle_names, fps=self.manifest.get("fps"))


def read_text(path: Path) -> str:
    """The UTF-8 text of a take's file; a missing, unreadable or non-UTF-8 file raises :class:`InputError`."""
    try:
        return path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise InputError("file not found", path) from None
    except UnicodeDecodeError as error:
        raise InputError(f"not UTF-8 text (byte {error.start})", path) from None
    except OSError as error:
        raise InputError(f"cannot read ({error.strerror})", path) from None


def read_arkit(path: str | Path) -> ArkitTrack:
    """A phone take's ``arkit.csv`` at ``path``, read and checked (:func:`livebridge.take.phone.parse_arkit`)."""
    return parse_arkit(path, read_text(Path(path)))


def _read_csv(path: Path, header: list[str]) -> tuple[np.ndarray, bool]:
    """Float rows ``(n_rows, len(header))`` of a recorder CSV with exactly this header, and whether its last
    line was torn (cut short by a crash: dropped). An empty field is NaN, except in ``frame``, ``seq`` and
    ``t``; anything else malformed raises naming the file, the line and the column."""
    text = read_text(path)
    lines = text.split("\n")
    torn = not text.endswith("\n")
    lines = lines[:-1]  # the empty string after the last newline, or a line a crash cut short
    if not lines:
        raise InputError("empty file (no header)", path)
    found = lines[0].split(",")
    if found != header:
        column = next((k for k, (a, b) in enumerate(zip(found, header)) if a != b), min(len(found), len(header)))
        raise InputError(f"header column {column + 1}: expected {_at(header, column)!r}, got {_at(found, column)!r} "
                         f"(the header must match take.toml's names)", path, "line 1")
    rows = [_csv_row(path, number, line, header) for number, line in enumerate(lines[1:], start=2)]
    return np.array(rows, dtype=np.float64).reshape(len(rows), len(header)), torn


def _at(names: list[str], k: int) -> str:
    return names[k] if k < len(names) else "(end of line)"


def _csv_row(path: Path, number: int, line: str, header: list[str]) -> list[float]:
    fields = line.split(",")
    if len(fields) != len(header):
        raise InputError(f"{len(fields)} fields, expected {len(header)}", path, f"line {number}")
    row = []
    for column, (name, field) in enumerate(zip(header, fields), start=1):
        if not field and column > 3:
            row.append(np.nan)  # not seen
            continue
        try:
            value = float(field)
        except ValueError:
            value = math.nan
        if not math.isfinite(value):
            raise InputError(f"expected a finite number{' or an empty field' if column > 3 else ''}, got {field!r:.40}",
                             path, f"line {number}, column {column} ({name})")
        row.append(value)
    return row


def load_take_dir(path: str | Path) -> RecordedTake:
    """Read a take directory, including one cut short by a crash (up to its last flushed line).

    Frames present in some files but not yet in others (a crash between two
    files' flushes) are dropped, so every array has the same frames.
    """
    path = Path(path)
    manifest = load_manifest(path)
    muscles = tuple(manifest.get("muscle_names", ()))
    markers = tuple(manifest.get("marker_names", ()))
    c_rows, torn_c = _read_csv(path / CONTRACTIONS, contractions_header(muscles))
    m_rows, torn_m = _read_csv(path / MARKERS, markers_header(markers))
    d_rows, torn_d = None, False
    if (path / DISPLACEMENTS).exists():
        d_rows, torn_d = _read_csv(path / DISPLACEMENTS, markers_header(markers))
    arkit = read_arkit(path / manifest["arkit"]) if "arkit" in manifest else None
    n = min(len(c_rows), len(m_rows), len(d_rows) if d_rows is not None else len(c_rows),
            len(arkit.t) if arkit is not None else len(c_rows))
    c_rows, m_rows = c_rows[:n], m_rows[:n]
    if not np.array_equal(c_rows[:, :2], m_rows[:, :2]):
        raise InputError(f"{CONTRACTIONS} and {MARKERS} disagree on frame numbers", path)
    if arkit is not None:
        arkit = arkit.head(n)
        if not (np.array_equal(c_rows[:, 0], arkit.frame) and np.array_equal(c_rows[:, 1], arkit.seq)):
            raise InputError(f"{CONTRACTIONS} and {manifest['arkit']} disagree on frame numbers", path)
    displacements = None
    if d_rows is not None:
        displacements = d_rows[:n, 3:].reshape(n, len(markers), 3)
    complete = ("frames" in manifest and manifest["frames"] == n
                and not (torn_c or torn_m or torn_d or (arkit is not None and arkit.torn)))
    return RecordedTake(
        path=path, seq=c_rows[:, 1].astype(np.int64), t=c_rows[:, 2],
        contractions=c_rows[:, 3:3 + len(muscles)], region_errors=c_rows[:, 3 + len(muscles):],
        markers=m_rows[:, 3:].reshape(n, len(markers), 3), displacements=displacements,
        muscle_names=muscles, marker_names=markers, manifest=manifest, complete=complete, arkit=arkit,
    )


def read_markers(path: str | Path) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
    """Marker names, positions ``(n_frames, n_markers, 3)`` (mm, NaN unseen) and times ``(n_frames,)`` of the
    take directory ``path``.

    Reads ``markers.csv`` alone: every row flushed before a crash counts (a torn last line is dropped).
    """
    path = Path(path)
    names = tuple(load_manifest(path).get("marker_names", ()))
    rows, _ = _read_csv(path / MARKERS, markers_header(names))
    return names, rows[:, 3:].reshape(len(rows), len(names), 3), rows[:, 2]


def frame_rate(fps: float | None, t: np.ndarray) -> float | None:
    """A take's frame rate, Hz: the nominal ``fps``, else from the median step of the times ``t``
    (shape (n_frames,)); None when neither is known (one frame, no fps)."""
    if fps:
        return float(fps)
    steps = np.diff(t)
    steps = steps[steps > 0]
    if not len(steps):
        return None
    return round(1.0 / float(np.median(steps)), 3)
