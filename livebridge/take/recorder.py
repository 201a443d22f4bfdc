"""Recording live takes: :class:`TakeRecorder` writes a take directory (:mod:`livebridge.take.directory`)
incrementally while the pipeline runs.

The CSV files are written by a background thread in whole lines, one ``write`` per flush, at least every
``flush_interval`` seconds (0.5 s by default) on the recorder's clock, so a crash -- even SIGKILL -- loses
at most the last second. Raw camera frames (:mod:`livebridge.take.raw_frames`) go to the disk on the same
thread; a live camera never waits for it (frame sets the disk cannot take are dropped and counted).
"""

from __future__ import annotations

import os
import queue
import shutil
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path

import numpy as np

from livebridge.capture.sources import SourceWrapper
from livebridge.errors import InputError
from livebridge.take.c3d import export_closed_take
from livebridge.take.directory import (
    CONTRACTIONS,
    DISPLACEMENTS,
    FRAME_FORMATS,
    MARKERS,
    PHONE_VERSION,
    RAW_FRAMES,
    contractions_header,
    markers_header,
    new_manifest,
    save_manifest,
)
from livebridge.take.phone import ARKIT, arkit_header, arkit_row
from livebridge.take.raw_frames import RawFrameWriter


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


def _line(lead: str, fields: str) -> str:
    """A CSV line: the lead columns, then ``fields`` unless there are none (a take without markers)."""
    return f"{lead},{fields}\n" if fields else f"{lead}\n"


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
        Also write raw camera images (:mod:`livebridge.take.raw_frames`) from :meth:`record_frames` or from the sources
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
    phone : bool
        A phone take: also write each frame's Live Link Face packet (``arkit.csv``, :mod:`livebridge.take.phone`;
        :meth:`record` then needs ``packet``), the phone's device id and subject and, without ``fps``, the
        packets' frame rate in the manifest.
    clock : callable () -> float
        Monotonic seconds, for the flush timing (tests pass a fake one).
    """

    def __init__(self, path: str | Path, muscle_names, marker_names, session_file=None, calibration_file=None,
                 fps: float | None = None, record_displacements: bool = True, record_frames: bool = False,
                 flush_interval: float = 0.5, cameras=None, lossless_frames: bool = False, frame_queue: int = 64,
                 frame_format: str = ".pgm", phone: bool = False, clock: Callable[[], float] = time.monotonic):
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
        self._clock = clock
        self._manifest = new_manifest(self.muscle_names, self.marker_names, fps)
        if phone:
            self._manifest.update(version=PHONE_VERSION, source="livelinkface", arkit=ARKIT)
        self._copy_inputs(session_file, calibration_file, cameras)
        save_manifest(self.path, self._manifest)
        self._contractions = _CsvStream(self.path / CONTRACTIONS, contractions_header(self.muscle_names))
        self._markers = _CsvStream(self.path / MARKERS, markers_header(self.marker_names))
        self._displacements = _CsvStream(self.path / DISPLACEMENTS, markers_header(self.marker_names)) \
            if record_displacements else None
        self._arkit = _CsvStream(self.path / ARKIT, arkit_header()) if phone else None
        self._frame_writer: RawFrameWriter | None = None
        self._frame_queue: queue.Queue | None = None
        self._frames_lock = threading.Lock()  # frame-set decisions and frames_dropped: reader threads share them
        self.lossless_frames = bool(lossless_frames)
        if record_frames:
            self._frame_writer = RawFrameWriter(self.path / RAW_FRAMES, frame_format)
            self._frame_soft_limit = max(1, int(frame_queue))  # a new frame set is dropped beyond this
            self._frame_queue = queue.Queue(maxsize=4 * self._frame_soft_limit)  # the rest of a kept set fits
            self._frame_decisions: OrderedDict[tuple[str, int], bool] = OrderedDict()
            self._manifest["raw_frames"] = RAW_FRAMES
            save_manifest(self.path, self._manifest)
        self.frames = 0
        self.frames_dropped = 0
        self._t0: float | None = None
        self._closed = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._flush_loop, name="take-recorder", daemon=True)
        self._thread.start()

    def _copy_inputs(self, session_file, calibration_file, cameras) -> None:
        """Copy the session and calibration files into the take (or write the cameras' calibration) and name
        them in the manifest."""
        for key, source in (("session", session_file), ("calibration", calibration_file)):
            if source is not None:
                source = Path(source)
                target = self.path / (f"{key}{source.suffix}" if key == "calibration" else "session.toml")
                shutil.copyfile(source, target)
                self._manifest[key] = target.name
        if calibration_file is None and cameras is not None:
            from livebridge.calibration.calibfile import save_calibration

            save_calibration(self.path / "calibration.toml", cameras,
                             {"source": "the cameras this take was recorded with"})
            self._manifest["calibration"] = "calibration.toml"

    def record(self, seq: int, t: float, contractions: np.ndarray, markers: np.ndarray | None = None,
               displacements: np.ndarray | None = None, region_errors=(float("nan"), float("nan")),
               packet=None) -> None:
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
        packet : LiveLinkPacket, optional
            The phone's packet the frame was solved from (needed by a phone take, ignored otherwise).
        """
        if self._closed:
            raise RuntimeError("the recorder is closed")
        if self._arkit is not None and packet is None:
            raise ValueError("a phone take records the packet of every frame")
        if self._t0 is None:
            self._t0 = float(t)
        frame = self.frames
        lead = f"{frame},{int(seq)},{t:.6f}"
        self._contractions.append(f"{lead},{_fmt(contractions, 6)},{_fmt(region_errors, 4)}\n")
        blank = ",".join([""] * (3 * len(self.marker_names)))
        self._markers.append(_line(lead, blank if markers is None else _fmt(markers, 4)))
        if self._displacements is not None:
            self._displacements.append(_line(lead, blank if displacements is None else _fmt(displacements, 4)))
        if self._arkit is not None:
            if self.frames == 0:
                self._name_phone(packet)
            self._arkit.append(f"{lead},{arkit_row(packet)}\n")
        self.frames += 1

    def _name_phone(self, packet) -> None:
        """The phone of a phone take (its first packet's) in the manifest, on disk now: a crash keeps it."""
        numerator, denominator = packet.rate
        self._manifest.update(device_id=packet.device_id, subject=packet.subject)
        if "fps" not in self._manifest and numerator > 0 and denominator > 0:
            self._manifest["fps"] = numerator / denominator
        save_manifest(self.path, self._manifest)

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
                self._wait_and_queue(frame)
            elif not self._queue_if_kept(frame):
                with self._frames_lock:
                    self.frames_dropped += 1

    def _wait_and_queue(self, frame) -> None:
        """Queue ``frame``, waiting for room as long as the recorder is open."""
        while not self._closed:
            try:
                self._frame_queue.put(frame, timeout=0.1)
                return
            except queue.Full:
                continue

    def _queue_if_kept(self, frame) -> bool:
        """Queue ``frame`` when its frame set is kept and there is room; False when it is dropped.

        The first frame of a set (same ``sync_domain`` and ``seq``) decides for the whole set, by the
        queue's length then, so that sets are kept or dropped whole, not single frames.
        """
        with self._frames_lock:
            key = (frame.sync_domain, int(frame.seq))
            keep = self._frame_decisions.get(key)
            if keep is None:
                keep = self._frame_decisions[key] = self._frame_queue.qsize() < self._frame_soft_limit
                while len(self._frame_decisions) > 1024:
                    self._frame_decisions.popitem(last=False)
        if not keep:
            return False
        try:
            self._frame_queue.put_nowait(frame)
        except queue.Full:
            return False
        return True

    def wrap_sources(self, sources) -> list:
        """Camera sources whose every frame read is also recorded (see :meth:`record_frames`); the sources
        are returned unchanged when this recorder writes no raw frames."""
        if self._frame_queue is None:
            return list(sources)
        return [RecordingSource(source, self) for source in sources]

    def _flush_loop(self) -> None:
        next_flush = self._clock() + self.flush_interval
        while not self._stop.is_set():
            timeout = max(0.0, next_flush - self._clock())
            if self._frame_queue is not None:
                try:
                    self._write_image(self._frame_queue.get(timeout=min(timeout, 0.05)))
                except queue.Empty:
                    pass
            else:
                self._stop.wait(timeout)
            if self._clock() >= next_flush:
                self._flush_all()
                next_flush = self._clock() + self.flush_interval

    def _write_image(self, frame) -> None:
        self._frame_writer.write(frame)

    def _flush_all(self, sync: bool = False) -> None:
        for stream in self._streams():
            stream.flush(sync)

    def _streams(self) -> list[_CsvStream]:
        return [s for s in (self._contractions, self._markers, self._displacements, self._arkit) if s is not None]

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
        for stream in self._streams():
            stream.close()
        if self._frame_writer is not None:
            self._frame_writer.close()
            with self._frames_lock:
                dropped = self.frames_dropped
            self._manifest.update(frames_written={k: int(v) for k, v in self._frame_writer.counts.items()},
                                  frames_dropped=int(dropped))
        if self._t0 is not None:
            self._manifest.update(t0=self._t0, frames=self.frames)
        if self._t0 is not None or self._frame_writer is not None:
            save_manifest(self.path, self._manifest)
        if self.frames and self.marker_names:
            export_closed_take(self.path, self._manifest.get("fps"))

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
