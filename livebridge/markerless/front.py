"""The markerless front: one camera -> pose and lighting normalisation -> CR states -> contractions.

Runs on the pipeline's front thread (:mod:`livebridge.runtime.pipeline`). The camera is read through the
same synchroniser as the marker front's cameras (one camera: it brings newest-wins dropping when live, and
in-step reading of unpaced sources); as there, the camera's reader thread stamps each frame's arrival and
detects its blobs (the head rig's LEDs), so a frame's latency counts from its arrival, the wait for the
front included. Each frame's contractions are finite and in [0, 1]; regions that lose the face, and every
region while the head rig's LEDs are lost, hold their last state (``SolvedFrame.held``) and report low
confidence.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from livebridge.capture.frame import Frame
from livebridge.errors import InputError
from livebridge.markerless.analysis import Analyser
from livebridge.markerless.model import MarkerlessModel
from livebridge.markerless.normalise import Normalisation, PoseState, detect_leds, normalise
from livebridge.reconstruct.detect import ReaderDetectingSource
from livebridge.runtime.frame import FrameTiming, SolvedFrame
from livebridge.runtime.front import FrontStats, shown


class LedDetectingSource(ReaderDetectingSource):
    """A camera source that finds the head rig's LED candidates (:func:`detect_leds`) on its reader thread;
    without a head rig it only stamps each frame's arrival.

    Parameters
    ----------
    source : CameraSource
    normalisation : Normalisation
        The model's (its ``head_rig`` and ``input_size``).
    clock : callable
        Monotonic seconds (the pipeline's clock).
    """

    def __init__(self, source, normalisation: Normalisation, clock: Callable[[], float] = time.monotonic):
        super().__init__(source, clock=clock)
        self._normalisation = normalisation

    def detect(self, frame) -> np.ndarray:
        """LED candidates of one frame, shape (n, 2) pixels, brightest first; none without a head rig or in an
        image of another size than the model's (which the front refuses)."""
        if self._normalisation.head_rig is None or frame.size != self._normalisation.input_size:
            return np.zeros((0, 2))
        return detect_leds(frame.image)


class MarkerlessFront:
    """A face filmed by one camera, analysed with a trained :class:`MarkerlessModel`.

    Parameters
    ----------
    source : CameraSource
        Frames of ``model.normalisation.input_size``.
    model : MarkerlessModel
    period_s : float
        Nominal frame period of the camera.
    realtime : bool
        False for a source that runs as fast as it is read (unpaced simulator, replay): frames are read in
        step with the outputs and none is dropped.
    min_confidence : float
        Regions below it hold their last state.
    clock : callable
        Monotonic seconds.
    """

    kind = "markerless"
    input_name = "camera"

    def __init__(self, source, model: MarkerlessModel, period_s: float, realtime: bool = True,
                 min_confidence: float = 0.3, clock: Callable[[], float] = time.monotonic):
        from livebridge.capture.sync import SyncedCapture

        self.model = model
        self.muscle_names = model.muscle_names
        self.source = LedDetectingSource(source, model.normalisation, clock=clock)
        self.realtime = bool(realtime)
        self.clock = clock
        self.analyser = Analyser(model, min_confidence)
        self.capture = SyncedCapture([self.source], float(period_s), queue_size=1, realtime=self.realtime,
                                     tolerance_s=0.5 * float(period_s), in_flight=None if self.realtime else 1,
                                     clock=clock)
        self._pose = PoseState()
        self._state = self.analyser.initial_state()
        self.frames = 0
        self.lost_frames = 0
        self.held_frames = 0
        self.cpu_s = 0.0

    def warm_up(self) -> None:
        """LED detection (compiled; on the reader thread when live) and one analysis, on a dark image with four
        bright spots (a blank one would leave the detection's blob kernels cold)."""
        width, height = self.model.normalisation.input_size
        image = np.zeros((height, width), np.uint8)
        for x in (0.3, 0.4, 0.6, 0.7):
            image[height // 3:height // 3 + 3, int(x * width):int(x * width) + 3] = 255
        leds = self.source.detect(Frame(image, 0.0, 0, self.source.source_id))
        pose, frame = normalise(image, self.model.normalisation, candidates=leds)
        self.analyser.step(self.analyser.initial_state(), frame)

    def start(self) -> None:
        self.capture.start()

    @property
    def ended(self) -> bool:
        return self.capture.ended

    def read(self, timeout: float) -> SolvedFrame | None:
        frameset = self.capture.read(timeout=timeout)
        if frameset is None:
            return None
        t0 = time.thread_time()
        try:
            return self._analyse(frameset)
        finally:
            self.cpu_s += time.thread_time() - t0

    def _analyse(self, frameset) -> SolvedFrame:
        dequeued = self.clock()
        frame = frameset.frames[0]
        image = frame.image
        width, height = self.model.normalisation.input_size
        if image.shape[:2] != (height, width):
            raise InputError(f"the camera gives {image.shape[1]}x{image.shape[0]} images, the markerless model "
                             f"was trained on {width}x{height}: film at that size or train again")
        leds = self.source.result(frame)
        self._pose, normalised = normalise(image, self.model.normalisation, self._pose, leds.points_2d)
        reconstructed = self.clock()
        self._state, result = self.analyser.step(self._state, normalised)
        solved = self.clock()
        self.frames += 1
        self.lost_frames += result.lost
        self.held_frames += bool(result.held.any())
        contractions = np.clip(np.nan_to_num(result.contractions, nan=0.0, posinf=0.0, neginf=0.0), 0.0, 1.0)
        contractions.setflags(write=False)
        quality = (("confidence", result.mean_confidence), ("leds", 0.0 if result.lost else 1.0),
                   ("held", float(np.mean([s.held for s in result.regions])) if result.regions else 0.0))
        timing = FrameTiming(frameset.t, leds.arrived, leds.detected, dequeued, reconstructed, solved)
        return SolvedFrame(frame.seq, frameset.index, timing, contractions, held=result.held, quality=quality,
                           head_pose=normalised.head2cam, regions=result.regions)

    def done(self, frame: SolvedFrame) -> None:
        if not self.realtime:
            self.capture.done(frame.timing.capture)

    def faults(self) -> dict[str, str]:
        return dict(self.capture.faults)

    def waiting(self) -> str | None:
        return None

    def status(self, summary) -> str:
        figures = dict(summary.quality)
        confidence, leds, held = (figures.get(k, math.nan) for k in ("confidence", "leds", "held"))
        part = f"markerless confidence {shown(confidence, '.2f')} | regions held {shown(100 * held, '.0f', '%')}"
        if self.model.normalisation.head_rig is not None:
            part += f" | LEDs seen {shown(100 * leds, '.0f', '%')}"
        stats = self.stats()
        return part + (f" | camera dead: {stats.dead[0]}" if stats.dead else "")

    def stats(self) -> FrontStats:
        sync = self.capture.sync
        faults = self.capture.faults
        errors = tuple((name, faults[name]) for name in (self.source.source_id,) if name in faults)
        return FrontStats(inputs=1, dead=tuple(sync.dead), errors=errors,
                          dropped=int(self.capture.dropped_framesets),
                          input_frame_drops=sum(sync.stats.drops.values()), attempts=self.frames,
                          cpu_s=self.cpu_s + self.source.cpu_s, input_cpu_s=self.source.cpu_s)

    def stop(self) -> None:
        self.capture.stop()
