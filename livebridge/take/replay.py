"""Raw camera frames played back as camera sources (``replay://``).

``replay://PATH?realtime=1&cameras=cam0,cam1&fps=30&loop=0`` opens one source per camera of the raw-frame
take at ``PATH`` (format: :mod:`livebridge.take.raw_frames`), or of a take directory's raw frames when
``PATH`` is a take directory (:mod:`livebridge.take.directory`): all cameras found, in name order, unless
``cameras`` picks some. ``fps`` numbers the frames of a camera without a timestamp file. ``realtime=1``
(default) plays with the original timing: all cameras of the take share one clock, recorded times are
shifted onto the host monotonic clock at start; ``realtime=0`` plays as fast as the reader asks and
keeps the recorded times. A source replaying a take directory knows its camera's calibration as recorded
with the take (:attr:`ReplaySource.calibration`).

A damaged take replays what it can: a frame whose image is missing, truncated or undecodable is skipped
and counted (:attr:`ReplaySource.frames_skipped`, logged once per :data:`SKIP_LOG_EVERY` skips), and the
source plays on. A source that cannot go on (its camera folder vanished, no image of a whole pass could be
read, its video cannot be opened or ends before its timestamp file) ends with ``ended`` True and ``error``
naming the file; :meth:`ReplaySource.read` never raises."""

from __future__ import annotations

import functools
import logging
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

log = logging.getLogger(__name__)

SKIP_LOG_EVERY = 100  # a damaged take logs its 1st, 101st, 201st, ... skipped frame, not every one



def wait_until_due(wait: float, timeout: float | None) -> bool:
    """Sleep until a paced replay's next item is due, ``wait`` seconds from now: True then; False (after
    sleeping ``timeout`` seconds) when it is not due within ``timeout`` (None: no limit)."""
    if timeout is not None and wait > timeout:
        time.sleep(max(timeout, 0.0))
        return False
    if wait > 0:
        time.sleep(wait)
    return True

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


def _numbered_images(files: list[Path], n_rows: int) -> list[Path] | None:
    """Image number ``k`` for each ``k < n_rows`` when every name is a number (``000000.pgm``, as
    :class:`~livebridge.take.raw_frames.RawFrameWriter` writes them), the path it would have where it is
    missing; None when the names are not numbers."""
    if not files or not all(p.stem.isdigit() for p in files):
        return None
    numbered = {int(p.stem): p for p in files}
    width, suffix = len(files[0].stem), files[0].suffix
    return [numbered.get(k, files[0].with_name(f"{k:0{width}d}{suffix}")) for k in range(n_rows)]


def _decode(path: Path) -> tuple[np.ndarray | None, str]:
    """A grayscale image from ``path``, or None and why it cannot be read."""
    import cv2

    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as error:
        return None, error.strerror or type(error).__name__
    image = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE) if len(data) else None
    if image is None:
        return None, "damaged, truncated or not an image"
    return image, ""


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

    Attributes
    ----------
    frames_skipped : int
        Frames skipped since :meth:`start` because their image was missing, truncated or undecodable.
    """

    def __init__(self, folder, camera: str, realtime: bool = True, fps: float = 30.0, loop: bool = False,
                 clock: _Clock | None = None):
        self.folder, self.source_id = frames_folder(folder), camera
        self._take_dir = _take_dir(Path(folder), self.folder)
        self.realtime, self.fps, self.loop = realtime, float(fps), loop
        self._clock = clock or _Clock()
        self._image_dir = image_dir = self.folder / camera
        videos = [self.folder / f"{camera}{s}" for s in VIDEO_SUFFIXES if (self.folder / f"{camera}{s}").exists()]
        self._files: list[Path] | None = None
        self._video_path = None
        stamps = self.folder / f"{camera}.csv"
        self._rows = read_timestamps(stamps) if stamps.exists() else None
        if image_dir.is_dir():
            self._files = self._image_files(image_dir, stamps)
        elif videos:
            self._video_path = videos[0]
        else:
            raise InputError(f"no images or video for camera {camera!r}", self.folder)
        if self._rows is None:
            count = len(self._files) if self._files is not None else self._video_length()
            self._rows = [TimestampRow(k, k / self.fps, math.nan, math.nan, "") for k in range(count)]
        if self._rows and self._rows[0].source_id:
            self.source_id = self._rows[0].source_id
        if self._rows:
            self._clock.t_first = min(self._clock.t_first, self._rows[0].t_capture)
        self._period = _frame_period(self._rows, self.fps)
        self._index = 0
        self._laps = 0
        self.frames_skipped, self._delivered_in_lap = 0, 0
        self._video = None
        self._size: tuple[int, int] | None = None

    def _image_files(self, image_dir: Path, stamps: Path) -> list[Path]:
        """The image of each frame: with a timestamp file and numbered images, row ``k`` is image number
        ``k`` (one that is missing is skipped on replay); otherwise the images in name order, cut to the
        timestamp rows."""
        files = sorted(p for p in image_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise InputError(f"no images ({', '.join(IMAGE_SUFFIXES)}) for camera {self.source_id!r}", image_dir)
        if self._rows is None:
            return list(files)
        numbered = _numbered_images(files, len(self._rows))
        if numbered is not None:
            return numbered
        if len(self._rows) > len(files):
            raise InputError(f"{len(self._rows)} timestamps for {len(files)} images", stamps)
        return list(files[:len(self._rows)])  # images past the last row: cut short

    def _video_length(self) -> int:
        import cv2

        capture = cv2.VideoCapture(str(self._video_path))
        try:
            if not capture.isOpened():
                raise InputError("cannot open the video (damaged, or a codec OpenCV lacks)", self._video_path)
            return max(int(capture.get(cv2.CAP_PROP_FRAME_COUNT)), 0)
        finally:
            capture.release()

    def start(self) -> None:
        self._ended, self._error = False, None
        self._index, self._laps = 0, 0
        self.frames_skipped, self._delivered_in_lap = 0, 0
        if self._video_path is not None:
            self._open_video()

    def _open_video(self) -> None:
        """(Re)open the video; a video that cannot be opened ends the source."""
        import cv2

        if self._video is not None:
            self._video.release()
        self._video = cv2.VideoCapture(str(self._video_path))
        if not self._video.isOpened():
            self._end(f"{self._video_path}: cannot open the video (damaged, or a codec OpenCV lacks)")

    def stop(self) -> None:
        if self._video is not None:
            self._video.release()
            self._video = None
        self._end(None)

    def _image(self, index: int) -> np.ndarray | None:
        """The image of frame ``index``; None when it is skipped or the source has ended."""
        import cv2

        if self._files is None:
            ok, image = self._video.read()
            if not ok:
                self._end(f"{self._video_path}: video ended after {self._index} of {len(self._rows)} frames")
                return None
            return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
        file = self._files[index]
        image, why = _decode(file)
        if image is None:
            if not self._image_dir.is_dir():
                self._end(f"{self._image_dir}: the camera folder vanished during the replay")
            else:
                self._skip(file, why)
        return image

    def _skip(self, file: Path, why: str) -> None:
        self.frames_skipped += 1
        if (self.frames_skipped - 1) % SKIP_LOG_EVERY == 0:
            log.warning("%s: skipped a frame: %s: %s (%d skipped so far)", self.source_id, file, why,
                        self.frames_skipped)

    def _next_lap(self) -> bool:
        """Rewind at the end of the take; False (and ended) when it does not loop or nothing could be read."""
        if self._files is not None and self._rows and self._delivered_in_lap == 0:
            self._end(f"{self._image_dir}: none of the {len(self._rows)} images could be read")
            return False
        if not self.loop or not self._rows:
            self._end(None)
            return False
        self._index, self._laps, self._delivered_in_lap = 0, self._laps + 1, 0
        if self._video_path is not None:
            self._open_video()
        return not self._ended

    def read(self, timeout: float | None = None) -> Frame | None:
        """The next readable frame (skipping damaged ones), None at the end, on timeout or after an error."""
        while not self._ended:
            if self._index >= len(self._rows) and not self._next_lap():
                return None
            row = self._rows[self._index]
            lap_shift = self._laps * (self._rows[-1].t_capture - self._rows[0].t_capture + self._period)
            recorded = row.t_capture + lap_shift
            t_capture = recorded
            if self.realtime:
                t_capture = self._clock.host_time(recorded)
                if not wait_until_due(t_capture - time.monotonic(), timeout):
                    return None
            image = self._image(self._index)
            self._index += 1
            if image is None:
                continue
            self._delivered_in_lap += 1
            self._size = (image.shape[1], image.shape[0])
            seq = row.seq + self._laps * (self._rows[-1].seq - self._rows[0].seq + 1)
            return Frame(image, t_capture, seq, self.source_id, row.exposure_us, row.gain,
                         row.sync_domain or self.source_id)
        return None

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
