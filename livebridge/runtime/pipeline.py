"""The live pipeline: cameras -> frame sets -> markers -> contractions -> outputs, on threads.

Stages and threads::

    camera reader threads (one per source)       read a frame, detect its markers (2D centroids,
        │                                        undistorted) right there -- detection is compiled
        │                                        and releases the GIL, so the cameras detect in parallel
    synchroniser (livebridge.capture.sync)       frame sets; bounded queue, keeps the newest
        ▼
    "reconstruct" thread                         tracking at the predicted projections, correspondence
        │                                        of the rest, triangulation (livebridge.reconstruct),
        │                                        the contraction solve (livebridge.solve.solver), then
        │                                        the servo write right after the solve (ServoOutput:
        │                                        safety stage + one write per bus), on this thread
    bounded queue, keeps the newest (1)
        ▼
    "outputs" thread                             the render client (publish never blocks), VMC
                                                 datagrams, the recorder, statistics, then the servo
                                                 status read-back (every few frame sets; a serial bus
                                                 is half duplex, so a write waits for a poll)

Unpaced sources (simulators, replays) are read one frame set at a time: the cameras read the next
set once the outputs of the previous one are done (``SyncedCapture(in_flight=1)``), so no stage of
one frame set competes with another's for the CPU, and nothing is dropped.

Every frame set carries a :class:`FrameTiming` (monotonic seconds per stage). "Complete" is the
moment the last frame of the set reached the host; latencies are measured from there to the servo
bytes written and to the render message handed to a client socket.

Stopping (:meth:`Pipeline.stop`, also on Ctrl-C / SIGTERM through :func:`run_until_stopped`) goes in
order: the cameras stop, the frame sets in flight are finished, the servos ease to neutral and torque
off, the recording is flushed and closed, then the render server and VMC socket close.
"""

from __future__ import annotations

import math
import signal
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from livebridge.capture.queue import NewestQueue
from livebridge.capture.sync import SyncedCapture
from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.face.markers import MarkerSet
from livebridge.runtime.session import LABELLING_TIMEOUT_S


class LabellingTimeout(InputError):
    """The first labelling did not happen in time (``labelling_timeout_s``); the message says what was seen."""


@dataclass(frozen=True)
class FrameTiming:
    """Monotonic seconds at each stage of one frame set.

    Attributes
    ----------
    capture : float
        Mean mid-exposure time of the frames of the set.
    complete : float
        The last frame of the set reached the host (its reader thread returned it).
    detected : float
        The last camera's detection of the set finished.
    dequeued : float
        The reconstruct stage took the set.
    reconstructed, solved : float
    servo : float
        Servo bytes written (NaN without servos).
    outputs : float
        Every output done.
    """

    capture: float
    complete: float
    detected: float
    dequeued: float
    reconstructed: float
    solved: float
    servo: float = math.nan
    outputs: float = math.nan


@dataclass(frozen=True, eq=False)
class SolvedFrame:
    """One frame set through reconstruction and solve (what the outputs receive).

    Attributes
    ----------
    seq : int
        Frame number of the cameras (of the first camera present).
    index : int
        Frame-set number from the synchroniser.
    timing : FrameTiming
    contractions : ndarray, shape (n_muscles,)
    positions_model : ndarray, shape (n_markers, 3)
        Labelled markers in the model frame, NaN unlabelled.
    positions_world : ndarray, shape (n_markers, 3)
    displacements : ndarray, shape (n_markers, 3)
    region_errors : tuple of float
        RMS marker error (upper, lower), mm.
    labelled_fraction : float
    n_stray : int
    n_cameras : int
        Cameras that contributed a frame.
    """

    seq: int
    index: int
    timing: FrameTiming
    contractions: np.ndarray
    positions_model: np.ndarray
    positions_world: np.ndarray
    displacements: np.ndarray
    region_errors: tuple[float, float]
    labelled_fraction: float
    n_stray: int
    n_cameras: int


@dataclass(frozen=True, eq=False)
class OutputWork:
    """What the reconstruct stage hands the outputs stage for one frame set.

    Attributes
    ----------
    frame : SolvedFrame
    servo_targets : ndarray, shape (n_servos,) or None
        The servo targets written, scaled to [0, 1] between each servo's limits (None without servos).
    poll_servos : bool
        The outputs stage reads the servos' status back after this frame set.
    """

    frame: SolvedFrame
    servo_targets: np.ndarray | None
    poll_servos: bool


@dataclass(frozen=True)
class PipelineSummary:
    """Figures of a run (:meth:`Pipeline.summary`); latencies in ms, NaN when nothing was measured.

    Attributes
    ----------
    framesets, solved : int
        Frame sets reconstructed; solved (their outputs done).
    fps : float
        Solved frame sets per second.
    drops : int
        Frame sets dropped between stages.
    camera_frame_drops : int
        Frame sets missing a live camera's frame.
    latency_p50_ms, latency_p99_ms, latency_max_ms : float
        Frame set complete -> servo bytes written (without servos: -> solved).
    solve_latency_p50_ms, solve_latency_p99_ms : float
        Frame set complete -> solved.
    render_latency_p50_ms, render_latency_p99_ms : float
        Frame set complete -> render message handed to a client socket.
    labelled_fraction : float
    error_upper_mm, error_lower_mm : float
        Mean RMS marker error per region.
    cameras, cameras_alive : int
    dead_cameras : tuple of str
        Cameras not delivering at the end (failed, silent, or ended like a finished take).
    camera_errors : tuple of (str, str)
        The cameras that failed during the run and why (name, error), in camera order.
    frames_skipped : tuple of (str, int)
        Per camera with any: frames a source skipped (a replay's damaged or missing images).
    cpu_per_frameset_ms : float
        Process CPU time per solved frame set.
    pipeline_cpu_per_frameset_ms, detect_cpu_per_frameset_ms, reconstruct_solve_cpu_per_frameset_ms,
    outputs_cpu_per_frameset_ms : float
        CPU time of the pipeline's own threads (all; detection; reconstruct and solve; outputs).
    wall_s : float
        Seconds since the start.
    """

    framesets: int
    solved: int
    fps: float
    drops: int
    camera_frame_drops: int
    latency_p50_ms: float
    latency_p99_ms: float
    latency_max_ms: float
    solve_latency_p50_ms: float
    solve_latency_p99_ms: float
    render_latency_p50_ms: float
    render_latency_p99_ms: float
    labelled_fraction: float
    error_upper_mm: float
    error_lower_mm: float
    cameras: int
    cameras_alive: int
    dead_cameras: tuple[str, ...]
    camera_errors: tuple[tuple[str, str], ...]
    frames_skipped: tuple[tuple[str, int], ...]
    cpu_per_frameset_ms: float
    pipeline_cpu_per_frameset_ms: float
    detect_cpu_per_frameset_ms: float
    reconstruct_solve_cpu_per_frameset_ms: float
    outputs_cpu_per_frameset_ms: float
    wall_s: float

    @property
    def frames_skipped_total(self) -> int:
        return sum(count for _, count in self.frames_skipped)


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


class GarbageCollection:
    """Python's cyclic garbage collector, run between frame sets instead of whenever it is due.

    Left to itself the collector runs inside whatever thread allocates when a count is reached: in the
    middle of a frame set, a young-generation pass cost 2-5 ms in the live pipeline (the p99 latency).
    While the pipeline runs, everything allocated before it started is frozen (:func:`gc.freeze`: never
    scanned again), automatic collection is off, and :meth:`collect` -- called by the outputs thread once
    a frame set is done -- collects the youngest generation every call, the middle one every
    ``every[0]`` calls and the oldest every ``every[1]`` calls, so cyclic garbage is still freed on a
    long take. :meth:`stop` gives the collector back as it was. One collector per process: with two
    pipelines running at once, the first to stop turns automatic collection back on.
    """

    def __init__(self, every: tuple[int, int] = (10, 3600)):
        self.every = every
        self.calls = 0
        self._was_enabled: bool | None = None

    def start(self) -> None:
        import gc

        gc.collect()
        gc.freeze()
        self._was_enabled = gc.isenabled()
        gc.disable()

    def collect(self) -> None:
        import gc

        self.calls += 1
        generation = 2 if self.calls % self.every[1] == 0 else 1 if self.calls % self.every[0] == 0 else 0
        gc.collect(generation)

    def stop(self) -> None:
        import gc

        if self._was_enabled is None:
            return
        gc.unfreeze()
        if self._was_enabled:
            gc.enable()
        self._was_enabled = None


class SwitchInterval:
    """The interpreter's thread switch interval (:func:`sys.setswitchinterval`), short while the pipeline runs.

    A thread that wants the GIL while another runs Python code waits up to the switch interval (5 ms by
    default) before the holder is asked to let go: a camera reader, the render server's event loop or a
    driver callback running Python at the wrong moment delayed the reconstruct thread by that much (p99
    latency of ``livebridge bench pipeline`` 8.4 -> 7.2 ms, mean of three runs each). :meth:`stop` restores
    the previous value.
    """

    def __init__(self, seconds: float = 0.0005):
        self.seconds = seconds
        self._previous: float | None = None

    def start(self) -> None:
        import sys

        self._previous = sys.getswitchinterval()
        sys.setswitchinterval(min(self._previous, self.seconds))

    def stop(self) -> None:
        import sys

        if self._previous is not None:
            sys.setswitchinterval(self._previous)
            self._previous = None


def _percentile(values, q) -> float:
    values = np.asarray(values, dtype=np.float64)
    values = values[np.isfinite(values)]
    return float(np.percentile(values, q)) if values.size else math.nan


@dataclass
class PipelineStats:
    """Counters and recent figures of a running pipeline (read by the status line and the summary)."""

    framesets: int = 0
    solved: int = 0
    unlabelled_attempts: int = 0
    first_t: float = math.nan
    last_t: float = math.nan
    servo_latency: deque = field(default_factory=lambda: deque(maxlen=100_000))
    solve_latency: deque = field(default_factory=lambda: deque(maxlen=100_000))
    labelled: deque = field(default_factory=lambda: deque(maxlen=100_000))
    errors: deque = field(default_factory=lambda: deque(maxlen=100_000))
    cpu_reconstruct_s: float = 0.0
    cpu_outputs_s: float = 0.0
    recent_t: deque = field(default_factory=lambda: deque(maxlen=240))


class Pipeline:
    """The live pipeline (see the module docstring).

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
    servo : ServoOutput, optional
        Configured; the pipeline activates it on start and closes it (ease to neutral, torque off) on stop.
    render : RenderServer, optional
        Started by the pipeline; stopped on stop.
    vmc : VMCOutput, optional
    recorder : TakeRecorder, optional
        Closed on stop.
    sync_tolerance : float
        Frame periods; cross-domain grouping tolerance.
    realtime : bool
        False for sources that run as fast as they can (``realtime=False`` simulators and replays):
        they are read in step, in frame-time order, the synchroniser follows frame time only, and no
        frame set is dropped.
    log : callable, optional
        Receives status lines and events.
    on_frame : callable, optional
        Called on the outputs thread with every :class:`SolvedFrame` (tests, the demo's scoring).
    status_interval : float
        Seconds between status lines.
    unpaced_in_flight : int or None
        Unpaced sources only: frame sets in the pipeline at once (``SyncedCapture(in_flight=)``); 1
        (default): the cameras read the next frame set once the previous one's servo bytes are written, so
        no frame set waits behind another (lowest latency); 2: the next set is detected while the previous
        one is reconstructed; None: the cameras read ahead as far as the bounded queues allow.
    clock : callable
        Monotonic seconds: stage times, status lines and the labelling timeout.
    labelling_timeout_s : float
        Seconds (on ``clock``) from the start for the first labelling; then the pipeline ends with a
        :class:`LabellingTimeout` (:attr:`error`) saying what it saw. 0: wait forever.
    """

    def __init__(self, sources, cameras, basis: Basis, markers: MarkerSet, period_s: float,
                 reconstruct_config=None, solver_config=None, servo=None, render=None, vmc=None, recorder=None,
                 sync_tolerance: float = 0.5, realtime: bool = True, log: Callable[[str], None] | None = None,
                 on_frame: Callable[[SolvedFrame], None] | None = None, status_interval: float = 1.0,
                 unpaced_in_flight: int | None = 1, clock: Callable[[], float] = time.monotonic,
                 labelling_timeout_s: float = LABELLING_TIMEOUT_S):
        from livebridge.reconstruct.detect import DetectingSource
        from livebridge.reconstruct.pipeline import ReconstructConfig, Reconstructor
        from livebridge.solve.solver import SolverConfig

        self.clock = clock
        self.cameras = cameras
        self.basis, self.markers = basis, markers
        self.period_s = float(period_s)
        self.reconstruct_config = reconstruct_config or ReconstructConfig()
        self.solver_config = solver_config or SolverConfig()
        self.reconstructor = Reconstructor(cameras, markers, basis, self.reconstruct_config)
        detect_config = self.reconstruct_config.detect
        if len(sources) != len(cameras):
            raise ValueError(f"{len(sources)} camera sources for {len(cameras)} calibrated cameras")
        self.sources = [DetectingSource(source, camera, detect_config, clock=clock)
                        for source, camera in zip(sources, cameras.cameras)]
        self.realtime = bool(realtime)
        self.capture = SyncedCapture(self.sources, self.period_s, queue_size=1, realtime=self.realtime,
                                     tolerance_s=sync_tolerance * self.period_s,
                                     in_flight=None if self.realtime else unpaced_in_flight, clock=clock)
        self.servo, self.render, self.vmc, self.recorder = servo, render, vmc, recorder
        self.log = log or (lambda message: None)
        self.on_frame = on_frame
        self.status_interval = status_interval
        self.labelling_timeout_s = float(labelling_timeout_s)
        self.labelling = LabellingProgress()
        self._faults_logged: set[str] = set()
        self.stats = PipelineStats()
        self._stop = threading.Event()
        self._outputs_gone = threading.Event()  # unpaced: the reconstruct thread waits for the outputs until then
        self._queue: NewestQueue[OutputWork | None] = NewestQueue(1)
        self._ended = threading.Event()
        self._threads: list[threading.Thread] = []
        self._solver = None
        self._solver_state = None
        self._servo_scale = None
        self.error: BaseException | None = None
        self._stopped = False
        self._dead_at_stop: tuple[str, ...] | None = None
        self._next_status = math.inf
        self._cpu_start = 0.0
        self._wall_start = 0.0
        self._garbage = GarbageCollection()
        self._switching = SwitchInterval()
        self._warm_up(detect_config)

    def _hand_over(self, work: OutputWork | None) -> None:
        """To the outputs stage (None: the end); unpaced, waiting for room while the outputs stage runs."""
        if self.realtime or not self._queue.put_waiting(work, lambda: not self._outputs_gone.is_set()):
            self._queue.put(work)

    def _warm_up(self, detect_config) -> None:
        """Run every compiled per-frame kernel once, before any camera starts.

        numba compiles a kernel (seconds, once per installation) or loads it from its cache (a fraction
        of a second) on its first call; in the middle of a take that stall would leave the tracker
        behind the live face. The solver is built only after the first labelling, so a throw-away one
        is stepped here (also with a marker unseen and read-only input: compiled code tells them apart),
        and so is the servos' safety stage.
        """
        from livebridge.reconstruct.detect import detect_blobs
        from livebridge.solve.solver import ContractionSolver

        image = np.zeros((16, 16), np.uint8)
        image[6:9, 6:9] = 255
        detect_blobs(image, detect_config)
        self.reconstructor.warm_up()
        solver = ContractionSolver(self.basis, self.markers, self.solver_config)
        displacements = np.zeros((len(self.markers), 3))
        state, _ = solver.step(solver.initial_state(), displacements)
        displacements[0] = np.nan
        displacements.setflags(write=False)
        solver.step(state, displacements)
        if self.servo is not None:
            mapper = self.servo.mapper
            mapper.step(mapper.start(mapper.neutral, 0.0), np.zeros(mapper.mapping.weights.shape[1]), 0.01)

    # ------------------------------------------------------------------------------ lifecycle
    def start(self) -> Pipeline:
        """Activate the outputs, then start the cameras and the stage threads."""
        if self.render is not None:
            self.render.start()
        if self.servo is not None:
            try:
                self.servo.activate()
            except BaseException:  # interrupted or failed half-way: the buses already activated hold torque
                self.servo.deactivate()
                raise
            low, high = self.servo.mapper.low, self.servo.mapper.high
            self._servo_scale = (low, np.where(high != low, high - low, 1.0))
        self._cpu_start, self._wall_start = time.process_time(), self.clock()
        self._next_status = self.clock() + self.status_interval
        self._garbage.start()
        self._switching.start()
        self.capture.start()
        for name, target in (("reconstruct", self._reconstruct_loop), ("outputs", self._outputs_loop)):
            thread = threading.Thread(target=self._guard(target), name=f"livebridge {name}", daemon=True)
            thread.start()
            self._threads.append(thread)
        return self

    def _guard(self, target):
        def run():
            try:
                target()
            except BaseException as error:  # a stage crashed: remember, stop everything in order
                self.error = error
                self.log(f"pipeline stage failed: {type(error).__name__}: {error}")
                self._stop.set()
                self._ended.set()
                self._hand_over(None)
        return run

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until the pipeline ends by itself (every camera ended, or a stage failed)."""
        return self._ended.wait(timeout)

    def stop(self) -> None:
        """Shut down in order: cameras, stages, servos (ease to neutral, torque off), recorder, render, VMC."""
        if self._stopped:
            return
        self._stopped = True
        self._stop.set()
        self._dead_at_stop = self.capture.sync.dead  # stopping the cameras is not a camera failing
        self.capture.stop()
        for thread in self._threads:
            thread.join(timeout=10)
        self._threads.clear()
        if self.servo is not None:
            try:
                self.servo.close(ease=True)
            except Exception as error:  # noqa: BLE001 - report, and keep closing the rest
                self.log(f"servo shutdown: {type(error).__name__}: {error}")
        if self.recorder is not None:
            self.recorder.close()
        if self.render is not None:
            self.render.stop()
        if self.vmc is not None:
            self.vmc.close()
        self._garbage.stop()
        self._switching.stop()

    def __enter__(self) -> Pipeline:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------------------------ stages
    def _reconstruct_loop(self) -> None:
        state = self.reconstructor.initial_state()
        cpu = 0.0
        while not self._stop.is_set():
            frameset = self.capture.read(timeout=0.05)
            if self._solver is None and self._gave_up():
                break
            if frameset is None:
                if self.capture.ended:
                    self.log("every camera has ended")
                    break
                continue
            t0 = time.thread_time()
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
            if not state.labelled and present < len(self.sources) - len(self.capture.sync.dead):
                self._frameset_done(frameset.t)
                continue  # the first labelling (on the neutral face) waits for a frame set from every camera
            state, labelled = self.reconstructor.step(state, points_2d, frameset.t)
            if not state.labelled:
                self.stats.unlabelled_attempts += 1
                if self._solver is None:
                    self.labelling.add(frameset.source_ids, points_2d, labelled.n_stray)
            reconstructed = self.clock()
            if self._solver is None and state.alignment is not None:
                from livebridge.solve.solver import ContractionSolver

                self._solver = ContractionSolver(self.basis, state.alignment.markers, self.solver_config)
                self._solver_state = self._solver.initial_state()
            self.stats.framesets += 1
            if self._solver is None:
                cpu += time.thread_time() - t0
                self._frameset_done(frameset.t)
                continue  # not labelled yet (the first frames must show the neutral face)
            self._solver_state, result = self._solver.step(self._solver_state, labelled.displacements)
            solved = self.clock()
            t_servo, servo_targets = math.nan, None
            poll_servos = False
            if self.servo is not None:  # the servos first, on this thread: no queue hop before the bytes go out
                poll_servos = self.servo.frames % self.servo.poll_every == 0
                self.servo.send(result.contractions, complete, poll=False)
                t_servo = self.clock()
                low, span = self._servo_scale
                servo_targets = (np.asarray(self.servo.last_targets, dtype=np.float64) - low) / span
            timing = FrameTiming(frameset.t, complete, detected, dequeued, reconstructed, solved, t_servo)
            self._hand_over(OutputWork(SolvedFrame(
                seq, frameset.index, timing, result.contractions, labelled.positions, labelled.positions_world,
                labelled.displacements, (float(result.rms_error_mm[0]), float(result.rms_error_mm[1])),
                labelled.labelled_fraction, labelled.n_stray, present), servo_targets, poll_servos))
            cpu += time.thread_time() - t0
            self.stats.cpu_reconstruct_s = cpu
        self._ended.set()
        self._hand_over(None)

    def _gave_up(self) -> bool:
        """Past the labelling timeout without a first labelling: keep the reason in :attr:`error`."""
        timeout = self.labelling_timeout_s
        if not timeout or self.clock() - self._wall_start <= timeout:
            return False
        self.error = LabellingTimeout(self.labelling.why(timeout, len(self.markers)))
        return True

    def _frameset_done(self, t: float) -> None:
        if not self.realtime:  # unpaced sources wait for the pipeline (SyncedCapture in_flight)
            self.capture.done(t)

    def _outputs_loop(self) -> None:
        try:
            self._run_outputs()
        finally:
            self._outputs_gone.set()

    def _run_outputs(self) -> None:
        cpu = 0.0
        stats = self.stats
        while True:
            work = self._queue.get(timeout=0.1)
            if work is None:
                if self._ended.is_set():
                    break
                self._maybe_status()
                continue
            t0 = time.thread_time()
            frame, servo_targets = work.frame, work.servo_targets
            timing = frame.timing
            t_servo = timing.servo
            if self.render is not None:
                from livebridge.output.render_server import RenderFrame

                self.render.publish(RenderFrame(frame.seq, timing.complete, frame.contractions,
                                                frame.positions_model, frame.region_errors, servo_targets))
                if not self.realtime:  # one frame set at a time, its render message included
                    self.render.wait_sent(frame.seq, timeout=0.05)
            if self.vmc is not None:
                self.vmc.send(frame.contractions)
            if self.recorder is not None:
                self.recorder.record(frame.seq, timing.capture, frame.contractions, frame.positions_world,
                                     frame.displacements, frame.region_errors)
            done = self.clock()
            frame = replace(frame, timing=replace(timing, outputs=done))
            stats.solved += 1
            if math.isnan(stats.first_t):
                stats.first_t = done
            stats.last_t = done
            stats.recent_t.append(done)
            stats.servo_latency.append(t_servo - timing.complete)
            stats.solve_latency.append(timing.solved - timing.complete)
            stats.labelled.append(frame.labelled_fraction)
            stats.errors.append(frame.region_errors)
            if self.on_frame is not None:
                self.on_frame(frame)
            if work.poll_servos:  # the status read-back waits for the servos' replies: after the outputs
                self.servo.poll()
            self._frameset_done(timing.capture)
            self._garbage.collect()  # after the frame set, not in the middle of the next one
            cpu += time.thread_time() - t0
            stats.cpu_outputs_s = cpu
            self._maybe_status()

    # ------------------------------------------------------------------------------ reporting
    def _maybe_status(self) -> None:
        self._log_faults()
        now = self.clock()
        if now < self._next_status:
            return
        self._next_status = now + self.status_interval
        line = self.status_line()
        self.log(line)
        if self.render is not None:
            self.render.publish_status({"line": line})

    def _log_faults(self) -> None:
        """One line per camera that failed, when it is first noticed."""
        for name, error in self.capture.faults.items():
            if name not in self._faults_logged:
                self._faults_logged.add(name)
                self.log(f"camera {name} failed: {error} (the other cameras go on)")

    def status_line(self) -> str:
        """One line: fps, drops, latency p50/p99, labelled fraction, region errors, cameras (and which are dead)."""
        s = self.recent_summary()
        cameras = f"cameras {s.cameras_alive}/{len(self.sources)}"
        if s.dead_cameras:
            cameras += f" (dead: {', '.join(s.dead_cameras)})"
        if s.frames_skipped:
            cameras += f" | frames skipped {s.frames_skipped_total}"
        if not self.stats.solved and self.stats.unlabelled_attempts:
            return (f"waiting for the first labelling: show the neutral face to every camera "
                    f"({self.stats.unlabelled_attempts} frame sets tried) | {cameras}")
        return (f"fps {s.fps:5.1f} | drops {s.drops} | latency servo p50 {s.latency_p50_ms:.2f} "
                f"p99 {s.latency_p99_ms:.2f} ms, render p99 {s.render_latency_p99_ms:.2f} ms | "
                f"labelled {100 * s.labelled_fraction:.1f}% | error upper {s.error_upper_mm:.3f} "
                f"lower {s.error_lower_mm:.3f} mm | {cameras}")

    def summary(self) -> PipelineSummary:
        """Figures of the run so far."""
        stats = self.stats
        fps = (stats.solved - 1) / max(stats.last_t - stats.first_t, 1e-9) if stats.solved > 1 else 0.0
        return self._summary(fps, None)

    def recent_summary(self) -> PipelineSummary:
        """Figures of the run so far, the rates and latencies over the last ~2 s (120 frame sets)."""
        times = list(self.stats.recent_t)
        fps = (len(times) - 1) / max(times[-1] - times[0], 1e-9) if len(times) > 1 else 0.0
        return self._summary(fps, 120)

    def _summary(self, fps: float, window: int | None) -> PipelineSummary:
        stats = self.stats

        def tail(values):
            values = list(values)
            return values[-window:] if window else values

        servo_latency = np.array(tail(stats.servo_latency)) * 1e3
        solve_latency = np.array(tail(stats.solve_latency)) * 1e3
        render_latency = self.render.sent_latencies() * 1e3 if self.render is not None else np.zeros(0)
        if window:
            render_latency = render_latency[-window:]
        primary = servo_latency if self.servo is not None else solve_latency
        errors = np.array(tail(stats.errors)).reshape(-1, 2)
        sync = self.capture.sync.stats
        dead = sync.dead if self._dead_at_stop is None else self._dead_at_stop
        drops = int(self.capture.dropped_framesets + self._queue.dropped)
        camera_drops = sum(sync.drops.values())
        wall = self.clock() - self._wall_start
        cpu = time.process_time() - self._cpu_start
        detect_cpu = sum(s.cpu_s for s in self.sources)
        solved = max(stats.solved, 1)
        return PipelineSummary(
            framesets=stats.framesets,
            solved=stats.solved,
            fps=fps,
            drops=drops,
            camera_frame_drops=camera_drops,
            latency_p50_ms=_percentile(primary, 50),
            latency_p99_ms=_percentile(primary, 99),
            latency_max_ms=float(np.nanmax(primary)) if primary.size else math.nan,
            solve_latency_p50_ms=_percentile(solve_latency, 50),
            solve_latency_p99_ms=_percentile(solve_latency, 99),
            render_latency_p50_ms=_percentile(render_latency, 50),
            render_latency_p99_ms=_percentile(render_latency, 99),
            labelled_fraction=float(np.mean(tail(stats.labelled))) if stats.labelled else math.nan,
            error_upper_mm=float(np.nanmean(errors[:, 0])) if len(errors) else math.nan,
            error_lower_mm=float(np.nanmean(errors[:, 1])) if len(errors) else math.nan,
            cameras=len(self.sources),
            cameras_alive=len(self.sources) - len(dead),
            dead_cameras=tuple(dead),
            camera_errors=self._camera_errors(dead),
            frames_skipped=tuple((s.source_id, n) for s in self.sources if (n := getattr(s, "frames_skipped", 0))),
            cpu_per_frameset_ms=1e3 * cpu / solved,
            pipeline_cpu_per_frameset_ms=1e3 * (stats.cpu_reconstruct_s + stats.cpu_outputs_s + detect_cpu) / solved,
            detect_cpu_per_frameset_ms=1e3 * detect_cpu / solved,
            reconstruct_solve_cpu_per_frameset_ms=1e3 * stats.cpu_reconstruct_s / solved,
            outputs_cpu_per_frameset_ms=1e3 * stats.cpu_outputs_s / solved,
            wall_s=wall,
        )


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


def run_until_stopped(pipeline: Pipeline, frames: int = 0, log: Callable[[str], None] = print,
                      on_start: Callable[[Pipeline], None] | None = None) -> PipelineSummary:
    """Run until Ctrl-C, SIGTERM, every camera ending, or ``frames`` solved frame sets; stop in order.

    ``on_start`` is called once the pipeline runs (e.g. to print the render URL). Ctrl-C while the pipeline
    starts (servos activating, cameras starting) interrupts the start where it is: the pipeline is stopped
    in order (servos already activated ease to neutral and torque off) and KeyboardInterrupt is raised.

    Returns the pipeline's :meth:`~Pipeline.summary`; raises the pipeline's :attr:`~Pipeline.error` (a stage
    failed, or :class:`LabellingTimeout`).
    """
    stop = threading.Event()
    starting = threading.Event()
    starting.set()
    previous = {}

    def handler(signum, _frame):
        if signum == signal.SIGINT and starting.is_set():
            starting.clear()
            raise KeyboardInterrupt  # out of whatever start() is doing; the finally below stops in order
        log(f"{signal.Signals(signum).name}: stopping (servos to neutral, recording closed)")
        stop.set()

    in_main = threading.current_thread() is threading.main_thread()
    if in_main:
        for signum in (signal.SIGINT, signal.SIGTERM):
            previous[signum] = signal.signal(signum, handler)
    try:
        try:
            log("starting: outputs, servos, cameras")
            pipeline.start()
        finally:
            starting.clear()  # from here Ctrl-C stops in order, also while stopping
        if on_start is not None:
            on_start(pipeline)
        while not stop.is_set() and not pipeline.wait(0.05):
            if frames and pipeline.stats.solved >= frames:
                break
    finally:
        pipeline.stop()
        if in_main:
            for signum, old in previous.items():
                signal.signal(signum, old)
    if pipeline.error is not None:
        raise pipeline.error
    return pipeline.summary()
