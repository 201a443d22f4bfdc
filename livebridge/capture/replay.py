"""Replay of recorded camera takes, and the writer that records them.

A recorded take is a folder with, per camera ``NAME``:

- either a folder ``NAME/`` of image files (PNG, JPEG, BMP, TIFF, PGM; played in file-name order),
  or a video ``NAME.avi`` / ``NAME.mkv`` / ``NAME.mp4`` (frames converted to grayscale);
- a timestamp file ``NAME.csv`` with a header row and one row per frame, in order: columns
  ``seq`` (int), ``t_capture`` (seconds, any monotonic clock), and optionally ``exposure_us``, ``gain``,
  ``sync_domain``, ``source_id`` (the camera's original name, e.g. ``DEVICE/CAM_B``, which the
  replayed frames carry so that a calibration matches them; default ``NAME``). Without the file,
  frames are numbered from 0 at ``fps`` (URL parameter, default 30).
  Images beyond the last row (a recording cut short between an image and its row) are ignored.

:class:`TakeWriter` writes this format incrementally and crash-safely (each image is written under a
temporary name and renamed; each timestamp row is flushed once its image is in place). A take directory
of :class:`livebridge.output.record.TakeRecorder` (``take.toml`` with raw frames) keeps the camera take
in its ``frames/`` folder; ``replay://`` opens that folder when given the take directory.

``replay://PATH?realtime=1&cameras=cam0,cam1&fps=30&loop=0`` opens one source per camera (all cameras
found, in name order, unless ``cameras`` picks some). ``realtime=1`` (default) plays with the original
timing: all cameras of the take share one clock, recorded times are shifted onto the host monotonic
clock at start; ``realtime=0`` plays as fast as the reader asks and keeps the recorded times.
"""

from __future__ import annotations

import csv
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from livebridge.capture.frame import Frame, FrameSet
from livebridge.capture.sources import Capabilities, ExposureSetting, SourceBase
from livebridge.devices.url import DeviceURL
from livebridge.errors import InputError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm")
VIDEO_SUFFIXES = (".avi", ".mkv", ".mp4")
COLUMNS = ("seq", "t_capture", "exposure_us", "gain", "sync_domain", "source_id")


@dataclass(frozen=True)
class _Row:
    seq: int
    t_capture: float
    exposure_us: float
    gain: float
    sync_domain: str
    source_id: str = ""


def read_timestamps(path: Path) -> list[_Row]:
    """Rows of a camera's timestamp file; errors name the file, the line and the column."""
    rows = []
    with Path(path).open(newline="") as stream:
        reader = csv.DictReader(stream)
        missing = [c for c in ("seq", "t_capture") if c not in (reader.fieldnames or [])]
        if missing:
            raise InputError(f"missing column(s) {', '.join(missing)}", path, "header")
        for line, row in enumerate(reader, start=2):
            try:
                rows.append(_Row(int(row["seq"]), float(row["t_capture"]),
                                 float(row.get("exposure_us") or "nan"), float(row.get("gain") or "nan"),
                                 row.get("sync_domain") or "", row.get("source_id") or ""))
            except (TypeError, ValueError) as error:
                raise InputError(f"bad value ({error})", path, f"line {line}") from None
    return rows


RECORDED_FRAMES = "frames"  # the camera take inside a recorder's take directory


def camera_take_folder(folder) -> Path:
    """The folder holding the camera take: ``folder`` itself, or its ``frames/`` when ``folder`` is a
    recorder's take directory (``take.toml``)."""
    folder = Path(folder)
    if (folder / "take.toml").is_file():
        frames = folder / RECORDED_FRAMES
        if not frames.is_dir():
            raise InputError("this take was recorded without raw frames (recording.raw_frames = false); "
                             "it cannot be replayed through the cameras", folder)
        return frames
    return folder


def take_cameras(folder: Path) -> list[str]:
    """Camera names in a take folder, in name order."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("no such take folder", folder)
    folder = camera_take_folder(folder)
    names = {p.name for p in folder.iterdir() if p.is_dir()}
    names |= {p.stem for p in folder.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES}
    if not names:
        raise InputError("no camera folders or videos in the take", folder)
    return sorted(names)


class _Clock:
    """Shared by the cameras of one take: maps recorded times onto host time."""

    def __init__(self):
        self.lock = threading.Lock()
        self.offset: float | None = None  # host - recorded
        self.t_first = math.inf

    def host_time(self, recorded: float) -> float:
        with self.lock:
            if self.offset is None:
                self.offset = time.monotonic() - self.t_first
            return recorded + self.offset


def _frame_period(rows: list[_Row], fps: float) -> float:
    """The camera's frame period: median time step per ``seq`` step (frames skipped while recording, e.g. by a
    busy host, leave gaps in ``seq`` and do not lengthen it)."""
    seq = np.array([r.seq for r in rows], dtype=np.float64)
    t = np.array([r.t_capture for r in rows])
    steps = np.diff(seq)
    ok = steps > 0
    if not ok.any():
        return 1.0 / fps
    period = float(np.median(np.diff(t)[ok] / steps[ok]))
    return period if period > 0 else 1.0 / fps


class ReplaySource(SourceBase):
    """One camera of a recorded take (see the module docstring).

    Parameters
    ----------
    folder : str or Path
        The take.
    camera : str
        Camera name in the take.
    realtime : bool
    fps : float
        Frame rate for numbering frames when the take has no timestamp file.
    loop : bool
        Start again at the end (recorded times continue increasing).
    """

    def __init__(self, folder, camera: str, realtime: bool = True, fps: float = 30.0, loop: bool = False,
                 clock: _Clock | None = None):
        self.folder, self.source_id = camera_take_folder(folder), camera
        self.realtime, self.fps, self.loop = realtime, float(fps), loop
        self._clock = clock or _Clock()
        image_dir = self.folder / camera
        videos = [self.folder / f"{camera}{s}" for s in VIDEO_SUFFIXES if (self.folder / f"{camera}{s}").exists()]
        self._files: list[Path] | None = None
        self._video_path = None
        if image_dir.is_dir():
            self._files = sorted(p for p in image_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            n_frames = len(self._files)
        elif videos:
            self._video_path = videos[0]
            n_frames = None
        else:
            raise InputError(f"no images or video for camera {camera!r}", self.folder)
        stamps = self.folder / f"{camera}.csv"
        if stamps.exists():
            self._rows = read_timestamps(stamps)
            if n_frames is not None and len(self._rows) > n_frames:
                raise InputError(f"{len(self._rows)} timestamps for {n_frames} images", stamps)
            if self._files is not None:
                self._files = self._files[:len(self._rows)]  # images past the last row: cut short
        else:
            count = n_frames if n_frames is not None else self._video_length()
            self._rows = [_Row(k, k / self.fps, math.nan, math.nan, "") for k in range(count)]
        if self._rows and self._rows[0].source_id:
            self.source_id = self._rows[0].source_id
        if self._rows:
            self._clock.t_first = min(self._clock.t_first, self._rows[0].t_capture)
        self._period = _frame_period(self._rows, self.fps)
        self._index = 0
        self._laps = 0
        self._video = None
        self._size: tuple[int, int] | None = None

    def _video_length(self) -> int:
        import cv2

        capture = cv2.VideoCapture(str(self._video_path))
        count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        capture.release()
        return max(count, 0)

    def __len__(self) -> int:
        return len(self._rows)

    def start(self) -> None:
        self._ended, self._error = False, None
        self._index, self._laps = 0, 0
        if self._video_path is not None:
            self._open_video()

    def _open_video(self) -> None:
        import cv2

        if self._video is not None:
            self._video.release()
        self._video = cv2.VideoCapture(str(self._video_path))
        if not self._video.isOpened():
            raise InputError("cannot open the video", self._video_path)

    def stop(self) -> None:
        if self._video is not None:
            self._video.release()
            self._video = None
        self._end(None)

    def _image(self, index: int) -> np.ndarray | None:
        import cv2

        if self._files is not None:
            image = cv2.imread(str(self._files[index]), cv2.IMREAD_GRAYSCALE)
            if image is None:
                raise InputError("cannot read the image", self._files[index])
            return image
        ok, image = self._video.read()
        if not ok:
            return None
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image

    def read(self, timeout: float | None = None) -> Frame | None:
        if self._ended:
            return None
        if self._index >= len(self._rows):
            if not self.loop or not self._rows:
                self._end(None)
                return None
            self._index, self._laps = 0, self._laps + 1
            if self._video_path is not None:
                self._open_video()
        row = self._rows[self._index]
        lap_shift = self._laps * (self._rows[-1].t_capture - self._rows[0].t_capture + self._period)
        recorded = row.t_capture + lap_shift
        t_capture = recorded
        if self.realtime:
            t_capture = self._clock.host_time(recorded)
            wait = t_capture - time.monotonic()
            if timeout is not None and wait > timeout:
                time.sleep(max(timeout, 0.0))
                return None
            if wait > 0:
                time.sleep(wait)
        image = self._image(self._index)
        self._index += 1
        if image is None:  # video shorter than its timestamp file
            self._end(f"{self.source_id}: video ended after {self._index - 1} frames")
            return None
        self._size = (image.shape[1], image.shape[0])
        seq = row.seq + self._laps * (self._rows[-1].seq - self._rows[0].seq + 1)
        return Frame(image, t_capture, seq, self.source_id, row.exposure_us, row.gain,
                     row.sync_domain or self.source_id)

    def set_exposure(self, manual: bool, exposure_us: float | None = None, gain: float | None = None):
        """A recording's exposure cannot change: returns what was recorded for the next frame."""
        row = self._rows[min(self._index, len(self._rows) - 1)] if self._rows else None
        return ExposureSetting(True, row.exposure_us if row else math.nan, row.gain if row else math.nan)

    @property
    def capabilities(self) -> Capabilities:
        return Capabilities(size=self._size or (0, 0), fps=1.0 / self._period if self._period > 0 else math.nan,
                            formats=("GREY",))


def open_take(folder, cameras=None, realtime: bool = True, fps: float = 30.0, loop: bool = False) -> list:
    """One :class:`ReplaySource` per camera of a take, sharing one clock."""
    names = take_cameras(folder) if cameras is None else list(cameras)
    clock = _Clock()
    return [ReplaySource(folder, name, realtime, fps, loop, clock) for name in names]


def open_url(url: DeviceURL) -> list[ReplaySource]:
    """The registry hook for ``replay://PATH?realtime=1&cameras=a,b&fps=30&loop=0``."""
    url.check_known({"realtime", "cameras", "fps", "loop"})
    path = url.netloc + url.path if url.netloc else url.path
    if not path:
        raise InputError("replay:// needs a take folder", url.url)
    cameras = url.query["cameras"].split(",") if url.query.get("cameras") else None
    return open_take(path, cameras, url.take("realtime", bool, True), url.take("fps", float, 30.0),
                     url.take("loop", bool, False))


class TakeWriter:
    """Records frames (or frame sets) as a take that :class:`ReplaySource` plays back.

    Crash-safe and incremental: each image is written under a temporary name (``.NAME.part``, ignored by
    the reader) and renamed, then its timestamp row is written and flushed, so a take cut short by a crash
    replays up to its last complete frame.

    Parameters
    ----------
    folder : str or Path
        Created if missing.
    image_format : str
        ``.png`` (lossless, default) or another OpenCV image suffix.
    """

    def __init__(self, folder, image_format: str = ".png"):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.image_format = image_format
        self._streams: dict[str, tuple] = {}
        self._counts: dict[str, int] = {}

    @staticmethod
    def camera_name(source_id: str) -> str:
        """The file-system name of a camera (``/`` and other unsafe characters become ``_``)."""
        return "".join(c if c.isalnum() or c in "-_." else "_" for c in str(source_id)).lstrip(".") or "camera"

    def write(self, frame: Frame) -> None:
        import os

        import cv2

        name = self.camera_name(frame.source_id)
        if name not in self._streams:
            (self.folder / name).mkdir(exist_ok=True)
            stream = (self.folder / f"{name}.csv").open("w", newline="", buffering=1)
            writer = csv.writer(stream, lineterminator="\n")
            writer.writerow(COLUMNS)
            self._streams[name] = (stream, writer)
            self._counts[name] = 0
        stream, writer = self._streams[name]
        index = self._counts[name]
        ok, data = cv2.imencode(self.image_format, np.asarray(frame.image))
        if not ok:
            raise InputError(f"OpenCV cannot encode {self.image_format} images", self.folder)
        target = self.folder / name / f"{index:06d}{self.image_format}"
        partial = target.with_name(f".{target.name}.part")
        partial.write_bytes(data.tobytes())
        os.replace(partial, target)
        writer.writerow([frame.seq, repr(frame.t_capture), repr(frame.exposure_us), repr(frame.gain),
                         frame.sync_domain, frame.source_id])  # line-buffered: on disk once written
        self._counts[name] = index + 1

    def write_set(self, frameset: FrameSet) -> None:
        for frame in frameset.frames:
            if frame is not None:
                self.write(frame)

    @property
    def counts(self) -> dict[str, int]:
        """Frames written per camera (file-system names)."""
        return dict(self._counts)

    def close(self) -> None:
        for stream, _ in self._streams.values():
            stream.close()
        self._streams.clear()

    def __enter__(self) -> TakeWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
