"""``livebridge demo``: the whole pipeline on simulators, scored against their ground truth.

The synthetic performer (built-in face) is filmed by a simulated 4-camera rig; the frames go through
the real pipeline (detection, correspondence, labelling, solve) to a simulated Dynamixel bus on a
pseudo-terminal driven by the real driver, to the render client, and optionally to VMC and a
recording. :class:`GroundTruthScore` compares every solved frame with what the performer did.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

DEMO_SERVO_URL = "simdynamixel://?ids=1-16&model=XL330-M288&process=1"  # the bus in its own process, as hardware


class GroundTruthScore:
    """Contraction error and label swaps of solved frames against the performer's ground truth.

    Parameters
    ----------
    performer : livebridge.simulators.performer.Performer
        The performer the simulated rig films (a deterministic function of time).
    skip : int
        Solved frames ignored at the start (the alignment's first frame).
    swap_margin_mm : float
        A labelled marker counts as swapped when it lies closer to another marker's true position
        than to its own, by more than this margin.
    """

    def __init__(self, performer, skip: int = 0, swap_margin_mm: float = 0.5):
        self.performer = performer
        self.skip = skip
        self.swap_margin_mm = swap_margin_mm
        self._lock = threading.Lock()
        self.squared = 0.0
        self.count = 0
        self.frames = 0
        self.swaps = 0
        self.marker_frames = 0
        self.worst_abs = 0.0

    def truth(self, seq: int) -> tuple[np.ndarray, np.ndarray]:
        """True contractions (n_muscles,) and world marker positions (n_markers, 3) of frame ``seq``."""
        p = self.performer
        t = np.array([seq / p.fps])
        x = p.script(t)[0]
        head2world = p.head(t)[0]
        local = p.markers.marker_positions(p.basis, x)
        return x, local @ head2world[:3, :3].T + head2world[:3, 3]

    def __call__(self, frame) -> None:
        with self._lock:
            self.frames += 1
            if self.frames <= self.skip:
                return
        x_true, world_true = self.truth(frame.seq)
        error = np.asarray(frame.contractions) - x_true
        seen = np.isfinite(frame.positions_world).all(axis=1)
        swaps = 0
        if seen.any():
            labelled = frame.positions_world[seen]
            distances = np.linalg.norm(labelled[:, None, :] - world_true[None, :, :], axis=2)  # (n_seen, n)
            own = distances[np.arange(len(labelled)), np.flatnonzero(seen)]
            distances[np.arange(len(labelled)), np.flatnonzero(seen)] = np.inf
            swaps = int(np.sum(distances.min(axis=1) + self.swap_margin_mm < own))
        with self._lock:
            self.squared += float(np.sum(error**2))
            self.count += error.size
            self.worst_abs = max(self.worst_abs, float(np.max(np.abs(error))))
            self.swaps += swaps
            self.marker_frames += int(seen.sum())

    @property
    def rmse(self) -> float:
        return math.sqrt(self.squared / self.count) if self.count else math.nan


class LeadIn:
    """A performer who first holds a still, neutral face for ``lead_in_s`` seconds, then performs.

    As an actor is asked to at the start of a capture: the first labelling (which can take most of a
    second on a busy machine) must see the neutral face, and the frames right after it should too. Same
    interface as :class:`livebridge.simulators.performer.Performer` where the rig and the scoring use it
    (``basis``, ``markers``, ``fps``, ``script(t)``, ``head(t)``, ``frames()``).
    """

    def __init__(self, performer, lead_in_s: float):
        self.performer = performer
        self.basis, self.markers, self.fps = performer.basis, performer.markers, performer.fps
        self.lead_in_s = float(lead_in_s)

    def script(self, t) -> np.ndarray:
        """Contractions (n_times, n_muscles) at times ``t``: zero during the lead-in."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        x = self.performer.script(np.maximum(t - self.lead_in_s, 0.0))
        x[t < self.lead_in_s] = 0.0
        return x

    def head(self, t) -> np.ndarray:
        """``head2world`` (n_times, 4, 4) at times ``t``: the rest pose during the lead-in."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        return self.performer.head(np.maximum(t - self.lead_in_s, 0.0))

    def frames(self, n_frames: int | None = None, chunk: int = 32):
        """:class:`~livebridge.simulators.performer.PerformerFrame` from 0, forever or ``n_frames``."""
        from livebridge.simulators.performer import PerformerFrame

        seq = 0
        while n_frames is None or seq < n_frames:
            count = chunk if n_frames is None else min(chunk, n_frames - seq)
            t = np.arange(seq, seq + count) / self.fps
            x, head2world = self.script(t), self.head(t)
            local = self.markers.marker_positions(self.basis, x)  # (count, n_markers, 3), model frame
            world = np.einsum("nij,nkj->nki", head2world[:, :3, :3], local) + head2world[:, None, :3, 3]
            for k in range(count):
                frame = PerformerFrame(seq + k, float(t[k]), x[k], head2world[k], world[k])
                for array in (frame.contractions, frame.head2world, frame.marker_positions):
                    array.setflags(write=False)
                yield frame
            seq += count


@dataclass
class DemoParts:
    """What :func:`build_demo` made: the pipeline and what scores and describes it."""

    pipeline: object
    score: GroundTruthScore
    rig: object
    url: str | None


def build_demo(cameras: int = 4, seed: int = 1, fps: float = 60.0, size=(1280, 800), realtime: bool = True,
               servo: bool = True, render: bool = True, host: str = "127.0.0.1", port: int = 8765,
               vmc: tuple[str, int] | None = None, record=None, noise: float = 2.0, script: str = "mixed",
               log=print, on_frame=None, record_frames: bool = False, lead_in_s: float | None = None) -> DemoParts:
    """Assemble the simulated demo pipeline (not started).

    Parameters
    ----------
    cameras : int
        Simulated cameras.
    seed : int
    fps : float
        Camera frame rate.
    size : (int, int)
        Image size of each simulated camera.
    realtime : bool
        Pace the cameras at ``fps``; False: as fast as the CPU allows (benchmarks, tests).
    servo : bool
        Drive 16 simulated Dynamixel servos (one per muscle) through the real driver.
    render : bool
        Serve the render page on ``host:port`` (0: any free port).
    vmc : (host, port), optional
        Also send VMC/OSC.
    record : Path, optional
        Record the take to this (new) directory (with the rig's calibration, ``calibration.toml``).
    record_frames : bool
        Also record the raw camera frames (replayable: ``replay://RECORD``).
    noise : float
        Sensor noise of the simulated cameras (grey levels).
    on_frame : callable, optional
        Also called with every solved frame.
    lead_in_s : float, optional
        The performer holds a still, neutral face this long before performing (see :class:`LeadIn`);
        default 2 s when ``realtime`` (the first labelling may take a second on a busy machine), else 0.
    """
    from livebridge.runtime.pipeline import Pipeline
    from livebridge.simulators.performer import Performer
    from livebridge.simulators.rig import RigConfig, SimRig, default_face

    basis, markers = default_face()
    performer = Performer(basis, markers, fps=fps, seed=seed, script=script, realtime=False)
    lead_in_s = (2.0 if realtime else 0.0) if lead_in_s is None else float(lead_in_s)
    if lead_in_s > 0:
        performer = LeadIn(performer, lead_in_s)
    rig = SimRig(basis, markers, n_cameras=cameras, config=RigConfig(size=tuple(size), fps=fps, noise_sigma=noise),
                 seed=seed, performer=performer)
    score = GroundTruthScore(performer, skip=1)
    servo_output = None
    if servo:
        from livebridge.servo.output import ServoOutput
        from livebridge.servo.rig import demo_rig

        servo_output = ServoOutput(demo_rig(DEMO_SERVO_URL, basis.names), basis.names, log=log, poll_every=15)
        servo_output.configure()
    render_server = None
    try:
        if render:
            from livebridge.output.render_server import RenderServer

            names = servo_output.servo_names if servo_output is not None else ()
            render_server = RenderServer(basis, markers, host=host, port=port, servo_names=names)
        vmc_output = None
        if vmc is not None:
            from livebridge.output.vmc import VMCOutput

            vmc_output = VMCOutput(basis.names, host=vmc[0], port=vmc[1])
        recorder = None
        if record is not None:
            from livebridge.take.recorder import TakeRecorder

            recorder = TakeRecorder(record, basis.names, markers.names, fps=fps, cameras=rig.cameras,
                                    record_frames=record_frames, lossless_frames=not realtime)

        def both(frame):
            score(frame)
            if on_frame is not None:
                on_frame(frame)

        sources = rig.sources(realtime=realtime)
        if recorder is not None:
            sources = recorder.wrap_sources(sources)
        pipeline = Pipeline(sources, rig.cameras, basis, markers, 1.0 / fps,
                            servo=servo_output, render=render_server, vmc=vmc_output, recorder=recorder,
                            realtime=realtime, log=log, on_frame=both)
    except BaseException:
        if servo_output is not None:
            servo_output.close(ease=False)
        raise
    return DemoParts(pipeline, score, rig, None)
