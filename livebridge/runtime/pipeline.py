"""The live pipeline: a front -> servos -> outputs, on threads.

Stages and threads::

    the front (livebridge.runtime.front)         whatever turns a capture into contractions: the
        │                                        marker front (cameras, detection on each camera's
        │                                        reader thread, synchroniser, reconstruction, solve),
        │                                        markerless, Live Link Face
    "front" thread                               reads the front's next solved frame, then writes the
        │                                        servos right away (ServoOutput: safety stage + one
        │                                        write per bus), on this thread
    bounded queue, keeps the newest (1)
        ▼
    "outputs" thread                             the render client (publish never blocks), every other
                                                 output (VMC datagrams, Live Link packets...), the
                                                 recorder, statistics, then the servo status read-back
                                                 (every few frames; a serial bus is half duplex, so a
                                                 write waits for a poll)

An unpaced front (simulators, replays) is read one frame at a time: it reads the next input once the
outputs of the previous frame are done (:meth:`Front.done`), so no stage of one frame competes with
another's for the CPU, and nothing is dropped.

Every frame carries a :class:`~livebridge.runtime.frame.FrameTiming` (monotonic seconds per stage).
"Complete" is the moment the last input of the frame reached the host; latencies are measured from
there to the servo bytes written and to the render message handed to a client socket.

Stopping (:meth:`Pipeline.stop`, also on Ctrl-C / SIGTERM through :func:`run_until_stopped`) goes in
order: the front's inputs stop, the frames in flight are finished, the servos ease to neutral and
torque off, the recording is flushed and closed, then the render server and the other outputs close.
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
from livebridge.errors import InputError
from livebridge.runtime.frame import SolvedFrame
from livebridge.runtime.front import Front, shown


@dataclass(frozen=True, eq=False)
class OutputWork:
    """What the front thread hands the outputs stage for one frame.

    Attributes
    ----------
    frame : SolvedFrame
    servo_targets : ndarray, shape (n_servos,) or None
        The servo targets written, scaled to [0, 1] between each servo's limits (None without servos).
    poll_servos : bool
        The outputs stage reads the servos' status back after this frame.
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
    quality : tuple of (str, float)
        The front's quality figures (:attr:`SolvedFrame.quality`), mean over the recent frames.
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
    quality: tuple[tuple[str, float], ...] = ()

    @property
    def frames_skipped_total(self) -> int:
        return sum(count for _, count in self.frames_skipped)


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


def milliseconds(value: float) -> str:
    """A latency for people: ``1.23 ms``, or ``none`` when nothing was timed (NaN: no render client, say)."""
    return shown(value, ".2f", " ms")


@dataclass
class PipelineStats:
    """Counters and recent figures of a running pipeline (read by the status line and the summary)."""

    solved: int = 0
    first_t: float = math.nan
    last_t: float = math.nan
    servo_latency: deque = field(default_factory=lambda: deque(maxlen=100_000))
    solve_latency: deque = field(default_factory=lambda: deque(maxlen=100_000))
    labelled: deque = field(default_factory=lambda: deque(maxlen=100_000))
    errors: deque = field(default_factory=lambda: deque(maxlen=100_000))
    quality: deque = field(default_factory=lambda: deque(maxlen=240))
    cpu_front_s: float = 0.0
    cpu_outputs_s: float = 0.0
    recent_t: deque = field(default_factory=lambda: deque(maxlen=240))


class Pipeline:
    """The live pipeline (see the module docstring).

    Parameters
    ----------
    front : Front
        What turns the capture into solved frames (e.g. :class:`~livebridge.runtime.markers_front.MarkerFront`).
    servo : ServoOutput, optional
        Configured; the pipeline activates it on start and closes it (ease to neutral, torque off) on stop.
    render : RenderServer, optional
        Started by the pipeline; stopped on stop.
    outputs : sequence of Output
        Every other output (VMC, Live Link...): ``send(frame)`` per solved frame on the outputs thread,
        ``close()`` on stop (:class:`livebridge.output.Output`).
    recorder : TakeRecorder, optional
        Closed on stop.
    log : callable, optional
        Receives status lines and events.
    on_frame : callable, optional
        Called on the outputs thread with every :class:`SolvedFrame` (tests, the demo's scoring).
    status_interval : float
        Seconds between status lines.
    clock : callable
        Monotonic seconds: stage times and status lines (the front's own clock should be the same).
    """

    def __init__(self, front: Front, servo=None, render=None, outputs=(), recorder=None,
                 log: Callable[[str], None] | None = None, on_frame: Callable[[SolvedFrame], None] | None = None,
                 status_interval: float = 1.0, clock: Callable[[], float] = time.monotonic):
        self.front = front
        self.clock = clock
        self.realtime = bool(front.realtime)
        self.servo, self.render, self.recorder = servo, render, recorder
        self.outputs = tuple(outputs)
        self.log = log or (lambda message: None)
        self.on_frame = on_frame
        self.status_interval = status_interval
        self._faults_logged: set[str] = set()
        self.stats = PipelineStats()
        self._stop = threading.Event()
        self._outputs_gone = threading.Event()  # unpaced: the front thread waits for the outputs until then
        self._queue: NewestQueue[OutputWork | None] = NewestQueue(1)
        self._ended = threading.Event()
        self._threads: list[threading.Thread] = []
        self._servo_scale = None
        self.error: BaseException | None = None
        self._stopped = False
        self._next_status = math.inf
        self._cpu_start = 0.0
        self._wall_start = 0.0
        self._garbage = GarbageCollection()
        self._switching = SwitchInterval()
        self._warm_up()

    def _hand_over(self, work: OutputWork | None) -> None:
        """To the outputs stage (None: the end); unpaced, waiting for room while the outputs stage runs."""
        if self.realtime or not self._queue.put_waiting(work, lambda: not self._outputs_gone.is_set()):
            self._queue.put(work)

    def _warm_up(self) -> None:
        """Run every compiled per-frame kernel once, before any input starts.

        numba compiles a kernel (seconds, once per installation) or loads it from its cache (a fraction
        of a second) on its first call; in the middle of a take that stall would leave the tracker
        behind the live face. The front warms its own; the servos' safety stage is stepped here.
        """
        self.front.warm_up()
        if self.servo is not None:
            mapper = self.servo.mapper
            mapper.step(mapper.start(mapper.neutral, 0.0), np.zeros(mapper.mapping.weights.shape[1]), 0.01)

    # ------------------------------------------------------------------------------ lifecycle
    def start(self) -> Pipeline:
        """Activate the outputs, then start the front's inputs and the stage threads."""
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
        self.front.start()
        for name, target in (("front", self._front_loop), ("outputs", self._outputs_loop)):
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
        """Wait until the pipeline ends by itself (every input ended, or a stage failed)."""
        return self._ended.wait(timeout)

    def stop(self) -> None:
        """Shut down in order: inputs, stages, servos (ease to neutral, torque off), recorder, render, outputs."""
        if self._stopped:
            return
        self._stopped = True
        self._stop.set()
        self.front.stop()
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
        for output in self.outputs:
            output.close()
        self._garbage.stop()
        self._switching.stop()

    def __enter__(self) -> Pipeline:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------------------------ stages
    def _front_loop(self) -> None:
        cpu = 0.0
        front = self.front
        while not self._stop.is_set():
            try:
                frame = front.read(0.05)
            except InputError as error:  # the front cannot go on for a reason the user must fix
                self.error = error
                break
            if frame is None:
                if front.ended:
                    self.log(f"every {front.input_name} has ended")
                    break
                continue
            t0 = time.thread_time()
            t_servo, servo_targets = math.nan, None
            poll_servos = False
            if self.servo is not None:  # the servos first, on this thread: no queue hop before the bytes go out
                poll_servos = self.servo.frames % self.servo.poll_every == 0
                self.servo.send(frame.contractions, frame.timing.complete, poll=False)
                t_servo = self.clock()
                low, span = self._servo_scale
                servo_targets = (np.asarray(self.servo.last_targets, dtype=np.float64) - low) / span
                frame = replace(frame, timing=replace(frame.timing, servo=t_servo))
            self._hand_over(OutputWork(frame, servo_targets, poll_servos))
            cpu += time.thread_time() - t0
            self.stats.cpu_front_s = cpu
        self._ended.set()
        # the end waits for room, paced or not: it must not supersede the last frame (a take's last row)
        if not self._queue.put_waiting(None, lambda: not self._outputs_gone.is_set()):
            self._queue.put(None)

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
            if self.render is not None:
                from livebridge.output.render_server import RenderFrame

                self.render.publish(RenderFrame(frame.seq, timing.complete, frame.contractions,
                                                frame.positions_model, frame.region_errors, servo_targets,
                                                frame.head_pose))
                if not self.realtime:  # one frame at a time, its render message included
                    self.render.wait_sent(frame.seq, timeout=0.05)
            for output in self.outputs:
                output.send(frame)
            if self.recorder is not None:
                self.recorder.record(frame.seq, timing.capture, frame.contractions, frame.positions_world,
                                     frame.displacements, frame.region_errors, frame.packet)
            done = self.clock()
            frame = replace(frame, timing=replace(timing, outputs=done))
            self._count(frame)
            if self.on_frame is not None:
                self.on_frame(frame)
            if work.poll_servos:  # the status read-back waits for the servos' replies: after the outputs
                self.servo.poll()
            self.front.done(frame)
            self._garbage.collect()  # after the frame, not in the middle of the next one
            cpu += time.thread_time() - t0
            stats.cpu_outputs_s = cpu
            self._maybe_status()

    def _count(self, frame: SolvedFrame) -> None:
        stats, timing = self.stats, frame.timing
        stats.solved += 1
        if math.isnan(stats.first_t):
            stats.first_t = timing.outputs
        stats.last_t = timing.outputs
        stats.recent_t.append(timing.outputs)
        stats.servo_latency.append(timing.servo - timing.complete)
        stats.solve_latency.append(timing.solved - timing.complete)
        stats.labelled.append(frame.labelled_fraction)
        stats.errors.append(frame.region_errors)
        if frame.quality:
            stats.quality.append(frame.quality)

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
        """One line per input that failed, when it is first noticed."""
        for name, error in self.front.faults().items():
            if name not in self._faults_logged:
                self._faults_logged.add(name)
                self.log(f"{self.front.input_name} {name} failed: {error} (the other {self.front.input_name}s go on)")

    def status_line(self) -> str:
        """One line: fps, drops, latency p50/p99, then the front's own figures (markers: labelled fraction,
        region errors, cameras and which are dead)."""
        waiting = self.front.waiting() if not self.stats.solved else None
        if waiting:
            return waiting
        s = self.recent_summary()
        return (f"fps {s.fps:5.1f} | drops {s.drops} | latency servo p50 {milliseconds(s.latency_p50_ms)} "
                f"p99 {milliseconds(s.latency_p99_ms)}, render p99 {milliseconds(s.render_latency_p99_ms)} | "
                + self.front.status(s))

    def summary(self) -> PipelineSummary:
        """Figures of the run so far."""
        stats = self.stats
        fps = (stats.solved - 1) / max(stats.last_t - stats.first_t, 1e-9) if stats.solved > 1 else 0.0
        return self._summary(fps, None)

    def recent_summary(self) -> PipelineSummary:
        """Figures of the run so far, the rates and latencies over the last ~2 s (120 frames)."""
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
        labelled = np.array(tail(stats.labelled), dtype=np.float64)
        front = self.front.stats()
        wall = self.clock() - self._wall_start
        cpu = time.process_time() - self._cpu_start
        solved = max(stats.solved, 1)
        return PipelineSummary(
            framesets=front.attempts,
            solved=stats.solved,
            fps=fps,
            drops=int(front.dropped + self._queue.dropped),
            camera_frame_drops=front.input_frame_drops,
            latency_p50_ms=_percentile(primary, 50),
            latency_p99_ms=_percentile(primary, 99),
            latency_max_ms=float(np.nanmax(primary)) if primary.size else math.nan,
            solve_latency_p50_ms=_percentile(solve_latency, 50),
            solve_latency_p99_ms=_percentile(solve_latency, 99),
            render_latency_p50_ms=_percentile(render_latency, 50),
            render_latency_p99_ms=_percentile(render_latency, 99),
            labelled_fraction=_nanmean(labelled),
            error_upper_mm=_nanmean(errors[:, 0]),
            error_lower_mm=_nanmean(errors[:, 1]),
            cameras=front.inputs,
            cameras_alive=front.inputs - len(front.dead),
            dead_cameras=front.dead,
            camera_errors=front.errors,
            frames_skipped=front.frames_skipped,
            cpu_per_frameset_ms=1e3 * cpu / solved,
            pipeline_cpu_per_frameset_ms=1e3 * (stats.cpu_front_s + stats.cpu_outputs_s + front.cpu_s) / solved,
            detect_cpu_per_frameset_ms=1e3 * front.input_cpu_s / solved,
            reconstruct_solve_cpu_per_frameset_ms=1e3 * (front.cpu_s - front.input_cpu_s) / solved,
            outputs_cpu_per_frameset_ms=1e3 * stats.cpu_outputs_s / solved,
            wall_s=wall,
            quality=_mean_quality(list(stats.quality)),
        )


def _nanmean(values: np.ndarray) -> float:
    finite = values[np.isfinite(values)]
    return float(finite.mean()) if finite.size else math.nan


def _mean_quality(frames: list[tuple[tuple[str, float], ...]]) -> tuple[tuple[str, float], ...]:
    """Mean of each named quality figure over ``frames`` (the recent ones), in first-seen order."""
    sums: dict[str, list[float]] = {}
    for quality in frames:
        for name, value in quality:
            sums.setdefault(name, []).append(value)
    return tuple((name, _nanmean(np.asarray(values, dtype=np.float64))) for name, values in sums.items())


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
