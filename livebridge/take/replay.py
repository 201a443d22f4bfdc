"""Raw camera frames played back as camera sources (``replay://``).

``replay://PATH?realtime=1&cameras=cam0,cam1&fps=30&loop=0`` opens one source per camera of the raw-frame
take at ``PATH`` (format: :mod:`livebridge.take.raw_frames`), or of a take directory's raw frames when
``PATH`` is a take directory (:mod:`livebridge.take.directory`): all cameras found, in name order, unless
``cameras`` picks some. ``fps`` numbers the frames of a camera without a timestamp file. ``realtime=1``
(default) plays with the original timing: all cameras of the take share one clock, recorded times are
shifted onto the host monotonic clock at start; ``realtime=0`` plays as fast as the reader asks and
keeps the recorded times. A source replaying a take directory knows its camera's calibration as recorded
with the take (:attr:`ReplaySource.calibration`)."""

from __future__ import annotations

import functools
import math
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from livebridge.capture.frame import Frame
from livebridge.capture.sources import Capabilities, ExposureSetting, SourceBase
from livebridge.devices.url import DeviceURL
from livebridge.errors import InputError
from livebridge.take.directory import RAW_FRAMES, calibration_file, is_take_dir
from livebridge.take.raw_frames import (
    IMAGE_SUFFIXES,
    VIDEO_SUFFIXES,
    TimestampRow,
    camera_names,
    frames_folder,
    read_timestamps,
)

if TYPE_CHECKING:
    from livebridge.calibration.cameras import Camera


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


def _frame_period(rows: list[TimestampRow], fps: float) -> float:
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


def _take_dir(folder: Path, frames: Path) -> Path | None:
    """The take directory a replay of ``folder`` (raw frames in ``frames``) reads: ``folder`` itself, or the
    take whose ``frames/`` it is; None for a bare raw-frame take."""
    if is_take_dir(folder):
        return folder
    if frames.name == RAW_FRAMES and is_take_dir(frames.parent):
        return frames.parent
    return None


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
        self.folder, self.source_id = frames_folder(folder), camera
        self._take_dir = _take_dir(Path(folder), self.folder)
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
            self._rows = [TimestampRow(k, k / self.fps, math.nan, math.nan, "") for k in range(count)]
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

    @functools.cached_property
    def calibration(self) -> Camera | None:
        """This camera as calibrated when the take was recorded: the camera named ``source_id`` in the
        calibration file of the take directory; None for a take without one, or without this camera."""
        if self._take_dir is None or (path := calibration_file(self._take_dir)) is None:
            return None
        from livebridge.calibration.calibfile import load_calibration

        return {camera.name: camera for camera in load_calibration(path).cameras}.get(self.source_id)

    @property
    def capabilities(self) -> Capabilities:
        return Capabilities(size=self._size or (0, 0), fps=1.0 / self._period if self._period > 0 else math.nan,
                            formats=("GREY",))


def open_take(folder, cameras=None, realtime: bool = True, fps: float = 30.0, loop: bool = False) -> list:
    """One :class:`ReplaySource` per camera of a take, sharing one clock."""
    names = camera_names(folder) if cameras is None else list(cameras)
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
