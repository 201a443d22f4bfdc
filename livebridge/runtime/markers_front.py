"""The marker front: cameras -> frame sets -> markers -> contractions (the Choe & Ko method, live).

Threads: one reader per camera detects the markers of each frame right where it is read (detection
is compiled and releases the GIL); the synchroniser (:mod:`livebridge.capture.sync`) groups the frames
into sets; :meth:`MarkerFront.read`, on the pipeline's front thread, tracks the markers at their
predicted projections, finds the correspondence of the rest, triangulates (:mod:`livebridge.reconstruct`)
and solves the contractions (:mod:`livebridge.solve.solver`).

Nothing is solved before the first labelling, which needs a frame set from every camera on the
neutral face; past ``labelling_timeout_s`` without one, :meth:`read` raises :class:`LabellingTimeout`
saying what it saw.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from livebridge.capture.sync import SyncedCapture
from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.face.markers import MarkerSet
from livebridge.runtime.frame import FrameTiming, SolvedFrame
from livebridge.runtime.front import FrontStats, shown
from livebridge.runtime.session import LABELLING_TIMEOUT_S


class LabellingTimeout(InputError):
    """The first labelling did not happen in time (``labelling_timeout_s``); the message says what was seen."""


@dataclass
class LabellingProgress:
    """What the reconstruct stage saw before the first labelling (for the message when it gives up).

    Attributes
    ----------
    framesets : int
        Frame sets tried.
    most_2d : dict of str to int
        Per camera: most markers detected in one frame.
    most_3d : int
        Most markers triangulated (seen by two cameras or more) in one frame set.
    """

    framesets: int = 0
    most_2d: dict = field(default_factory=dict)
    most_3d: int = 0

    def add(self, source_ids, points_2d, n_points_3d: int) -> None:
        self.framesets += 1
        for name, points in zip(source_ids, points_2d):
            self.most_2d[name] = max(self.most_2d.get(name, 0), len(points))
        self.most_3d = max(self.most_3d, int(n_points_3d))

    def why(self, seconds: float, n_markers: int) -> str:
        """Why nothing was labelled in ``seconds``, from what was seen."""
        hint = "; raise [runtime] labelling_timeout_s to wait longer"
        if not self.framesets:
            return f"no frame set from the cameras in {seconds:g} s{hint}"
        per_camera = ", ".join(f"{name} {count}" for name, count in self.most_2d.items())
        if not self.most_3d:
            return (f"no marker seen by 2 cameras in {seconds:g} s ({self.framesets} frame sets; most markers "
                    f"seen by each camera: {per_camera}){hint}")
        return (f"markers seen but never labelled in {seconds:g} s: at most {self.most_3d} of the {n_markers} "
                f"markers seen by 2 cameras ({self.framesets} frame sets; most seen by each camera: {per_camera});"
                f" the first labelling needs about half of them, 3 head markers among them, on a neutral face{hint}")


class MarkerFront:
    """Calibrated cameras filming face markers, solved per frame set (see the module docstring).

    Parameters
    ----------
    sources : list of CameraSource
        In the calibration's camera order (``cameras``).
    cameras : CameraGroup
        Calibration of the sources.
    basis : Basis
    markers : MarkerSet
    period_s : float
        Nominal frame period of the cameras.
    reconstruct_config : ReconstructConfig, optional
    solver_config : SolverConfig, optional
    sync_tolerance : float
        Frame periods; cross-domain grouping tolerance.
    realtime : bool
        False for sources that run as fast as they can (``realtime=False`` simulators and replays):
        they are read in step, in frame-time order, the synchroniser follows frame time only, and no
        frame set is dropped.
    unpaced_in_flight : int or None
        Unpaced sources only: frame sets in the pipeline at once (``SyncedCapture(in_flight=)``); 1
        (default): the cameras read the next frame set once the previous one's servo bytes are written, so
        no frame set waits behind another (lowest latency); 2: the next set is detected while the previous
        one is reconstructed; None: the cameras read ahead as far as the bounded queues allow.
    clock : callable
        Monotonic seconds: stage times and the labelling timeout.
    labelling_timeout_s : float
        Seconds (on ``clock``) from the start for the first labelling. 0: wait forever.
    """

    kind = "markers"
    input_name = "camera"

    def __init__(self, sources, cameras, basis: Basis, markers: MarkerSet, period_s: float,
                 reconstruct_config=None, solver_config=None, sync_tolerance: float = 0.5, realtime: bool = True,
                 unpaced_in_flight: int | None = 1, clock: Callable[[], float] = time.monotonic,
                 labelling_timeout_s: float = LABELLING_TIMEOUT_S):
        from livebridge.reconstruct.detect import DetectingSource
        from livebridge.reconstruct.pipeline import ReconstructConfig, Reconstructor
        from livebridge.solve.solver import SolverConfig

        if len(sources) != len(cameras):
            raise ValueError(f"{len(sources)} camera sources for {len(cameras)} calibrated cameras")
        self.clock = clock
        self.cameras = cameras
        self.basis, self.markers = basis, markers
        self.muscle_names = tuple(basis.names)
        self.period_s = float(period_s)
        self.reconstruct_config = reconstruct_config or ReconstructConfig()
        self.solver_config = solver_config or SolverConfig()
        self.reconstructor = Reconstructor(cameras, markers, basis, self.reconstruct_config)
        self.sources = [DetectingSource(source, camera, self.reconstruct_config.detect, clock=clock)
                        for source, camera in zip(sources, cameras.cameras)]
        self.realtime = bool(realtime)
        self.capture = SyncedCapture(self.sources, self.period_s, queue_size=1, realtime=self.realtime,
                                     tolerance_s=sync_tolerance * self.period_s,
                                     in_flight=None if self.realtime else unpaced_in_flight, clock=clock)
        self.labelling_timeout_s = float(labelling_timeout_s)
        self.labelling = LabellingProgress()
        self.framesets = 0
        self.unlabelled_attempts = 0
        self.cpu_s = 0.0
        self._state = None
        self._solver = None
        self._solver_state = None
        self._start_t = math.nan
        self._dead_at_stop: tuple[str, ...] | None = None

    def warm_up(self) -> None:
        """Detection, reconstruction and the solver, once each (the solver is built only after the first
        labelling, so a throw-away one is stepped here, also with a marker unseen and read-only input:
        compiled code tells them apart)."""
        from livebridge.reconstruct.detect import detect_blobs
        from livebridge.solve.solver import ContractionSolver

        image = np.zeros((16, 16), np.uint8)
        image[6:9, 6:9] = 255
        detect_blobs(image, self.reconstruct_config.detect)
        self.reconstructor.warm_up()
        solver = ContractionSolver(self.basis, self.markers, self.solver_config)
        displacements = np.zeros((len(self.markers), 3))
        state, _ = solver.step(solver.initial_state(), displacements)
        displacements[0] = np.nan
        displacements.setflags(write=False)
        solver.step(state, displacements)

    def start(self) -> None:
        self._start_t = self.clock()
        self._state = self.reconstructor.initial_state()
        self.capture.start()

    @property
    def ended(self) -> bool:
        return self.capture.ended

    def read(self, timeout: float) -> SolvedFrame | None:
        frameset = self.capture.read(timeout=timeout)
        if self._solver is None:
            self._check_labelling_timeout()
        if frameset is None:
            return None
        t0 = time.thread_time()
        try:
            return self._solve(frameset)
        finally:
            self.cpu_s += time.thread_time() - t0

    def _solve(self, frameset) -> SolvedFrame | None:
        dequeued = self.clock()
        points_2d, complete, detected = [], -math.inf, -math.inf
        present = 0
        for source, frame in zip(self.sources, frameset.frames):
            if frame is None:
                points_2d.append(np.zeros((0, 2)))
                continue
            detection = source.result(frame)
            points_2d.append(detection.points_2d)
            complete, detected = max(complete, detection.arrived), max(detected, detection.detected)
            present += 1
        seq = next(f.seq for f in frameset.frames if f is not None)
        state = self._state
        if not state.labelled and present < len(self.sources) - len(self.capture.sync.dead):
            self._skip(frameset.t)
            return None  # the first labelling (on the neutral face) waits for a frame set from every camera
        state, labelled = self.reconstructor.step(state, points_2d, frameset.t)
        self._state = state
        if not state.labelled:
            self.unlabelled_attempts += 1
            if self._solver is None:
                self.labelling.add(frameset.source_ids, points_2d, labelled.n_stray)
        reconstructed = self.clock()
        if self._solver is None and state.alignment is not None:
            from livebridge.solve.solver import ContractionSolver

            self._solver = ContractionSolver(self.basis, state.alignment.markers, self.solver_config)
            self._solver_state = self._solver.initial_state()
        self.framesets += 1
        if self._solver is None:
            self._skip(frameset.t)
            return None  # not labelled yet (the first frames must show the neutral face)
        self._solver_state, result = self._solver.step(self._solver_state, labelled.displacements)
        solved = self.clock()
        timing = FrameTiming(frameset.t, complete, detected, dequeued, reconstructed, solved)
        return SolvedFrame(
            seq, frameset.index, timing, result.contractions, labelled.positions, labelled.positions_world,
            labelled.displacements, (float(result.rms_error_mm[0]), float(result.rms_error_mm[1])),
            labelled.labelled_fraction, labelled.n_stray, present)

    def _check_labelling_timeout(self) -> None:
        timeout = self.labelling_timeout_s
        if timeout and self.clock() - self._start_t > timeout:
            raise LabellingTimeout(self.labelling.why(timeout, len(self.markers)))

    def _skip(self, t: float) -> None:
        if not self.realtime:  # unpaced sources wait for the pipeline (SyncedCapture in_flight)
            self.capture.done(t)

    def done(self, frame: SolvedFrame) -> None:
        self._skip(frame.timing.capture)

    def faults(self) -> dict[str, str]:
        return dict(self.capture.faults)

    def waiting(self) -> str | None:
        if self._solver is not None or not self.unlabelled_attempts:
            return None
        return (f"waiting for the first labelling: show the neutral face to every camera "
                f"({self.unlabelled_attempts} frame sets tried) | {self._cameras_part()}")

    def status(self, summary) -> str:
        return (f"labelled {shown(100 * summary.labelled_fraction, '.1f', '%')} | error upper "
                f"{shown(summary.error_upper_mm, '.3f')} lower {shown(summary.error_lower_mm, '.3f')} mm | "
                f"{self._cameras_part()}")

    def _cameras_part(self) -> str:
        stats = self.stats()
        part = f"cameras {len(self.sources) - len(stats.dead)}/{len(self.sources)}"
        if stats.dead:
            part += f" (dead: {', '.join(stats.dead)})"
        skipped = sum(n for _, n in stats.frames_skipped)
        if skipped:
            part += f" | frames skipped {skipped}"
        reports = [f"{source.source_id} {text}" for source in self.sources if (text := source.status_text())]
        if reports:
            part += " | " + "; ".join(reports)
        return part

    def stats(self) -> FrontStats:
        sync = self.capture.sync
        dead = sync.dead if self._dead_at_stop is None else self._dead_at_stop
        detect_cpu = sum(s.cpu_s for s in self.sources)
        return FrontStats(
            inputs=len(self.sources), dead=tuple(dead), errors=self._camera_errors(dead),
            frames_skipped=tuple((s.source_id, n) for s in self.sources if (n := getattr(s, "frames_skipped", 0))),
            dropped=int(self.capture.dropped_framesets), input_frame_drops=sum(sync.stats.drops.values()),
            attempts=self.framesets, cpu_s=self.cpu_s + detect_cpu, input_cpu_s=detect_cpu)

    def _camera_errors(self, dead) -> tuple[tuple[str, str], ...]:
        """Cameras that failed (ended with an error, their read raised), and cameras silent at the end of a live
        run (dead without ending); a camera that ended without an error (a finished take) is no error."""
        faults, gone = self.capture.faults, self.capture.gone
        errors = []
        for source in self.sources:
            name = source.source_id
            if name in faults:
                errors.append((name, faults[name]))
            elif name in dead and name not in gone:
                errors.append((name, f"no frame for more than {self.capture.sync.dead_after_s:g} s"))
        return tuple(errors)

    def stop(self) -> None:
        self._dead_at_stop = self.capture.sync.dead  # stopping the cameras is not a camera failing
        self.capture.stop()
