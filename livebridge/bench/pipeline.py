"""The whole live pipeline on the unpaced 4-camera simulated rig, to simulated servos and a render client."""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import threading
import time

FRAME_PERIOD_30FPS_MS = 1000.0 / 30.0


def _client(url: str, stop, count) -> None:
    """A render client in its own process (as a browser is): receives every message until ``stop``."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    with connect(url, max_size=None) as ws:
        while not stop.is_set():
            try:
                ws.recv(timeout=0.2)
                with count.get_lock():
                    count.value += 1
            except TimeoutError:
                continue
            except ConnectionClosed:
                return


# ------------------------------------------------------------------------------- the rig in its own process

def _render_frames(shm_name: str, options: dict, slots: int, free, setup, pipes, stop) -> None:
    """Child process: render frame sets of the simulated rig into shared-memory slots, in order, until ``stop``;
    each camera's frame description goes down that camera's pipe."""
    import time as _time
    from multiprocessing import shared_memory

    import numpy as np

    from livebridge.simulators.performer import Performer
    from livebridge.simulators.rig import RigConfig, SimRig, default_face

    os.nice(options["nice"])  # the cameras' stand-in yields the CPU to the pipeline (see ProcessRig)
    if options.get("cpus"):
        os.sched_setaffinity(0, options["cpus"])
    basis, markers = default_face()
    performer = Performer(basis, markers, fps=options["fps"], seed=options["seed"], script=options["script"],
                          realtime=False)
    rig = SimRig(basis, markers, n_cameras=options["cameras"],
                 config=RigConfig(size=tuple(options["size"]), fps=options["fps"], noise_sigma=options["noise"]),
                 seed=options["seed"], performer=performer)
    rig.start()
    width, height = options["size"]
    shm = shared_memory.SharedMemory(name=shm_name)
    try:
        images = np.ndarray((slots, rig.n_cameras, height, width), dtype=np.uint8, buffer=shm.buf)
        setup.send(np.stack([c.projection for c in rig.cameras.cameras]))
        seq, cpu = 0, 0.0
        while not stop.is_set():
            if not free.acquire(timeout=0.1):
                continue
            start = _time.process_time()
            frames, _ = rig.render(seq)
            slot = seq % slots
            for c, frame in enumerate(frames):
                if frame is not None:
                    images[slot, c] = frame.image
            cpu += _time.process_time() - start
            for pipe, frame in zip(pipes, frames):
                meta = None if frame is None else (frame.t_capture, frame.seq, frame.source_id, frame.exposure_us,
                                                   frame.gain, frame.sync_domain)
                pipe.send((seq, slot, meta, cpu))
            seq += 1
    finally:
        del images
        shm.close()


class ProcessRig:
    """The simulated rig of :func:`livebridge.runtime.demo.build_demo`, rendering in a child process.

    Real cameras form their images outside the host's Python interpreter; the simulator stands in for
    them, so here it runs in its own process (same seed, so the same rig and performer as the demo's)
    and hands frames over through shared memory, a few frame sets ahead at most: the rig waits for the
    pipeline (not paced, no frame lost). Its CPU time is reported (``simulator_cpu_s``). It runs at a
    lower scheduling priority (``nice``), and with ``cpus`` only on those CPUs: camera hardware forms
    its images with its own silicon, not with the CPU the pipeline runs on. Each camera's frames come
    down a pipe of their own, read by that camera's reader when it asks for a frame (as a driver's
    queued buffers are): no thread of the pipeline's process wakes up when the rig finishes a frame set.
    :meth:`sources` are ordinary camera sources.
    """

    def __init__(self, cameras: int = 4, seed: int = 1, fps: float = 60.0, size=(1280, 800), noise: float = 2.0,
                 script: str = "mixed", slots: int = 3, nice: int = 10, cpus: set[int] | None = None):
        import multiprocessing
        from multiprocessing import shared_memory

        import numpy as np

        self.options = {"cameras": cameras, "seed": seed, "fps": fps, "size": tuple(size), "noise": noise,
                        "script": script, "nice": nice, "cpus": cpus}
        self.n_cameras, self.slots = cameras, slots
        width, height = size
        context = multiprocessing.get_context("spawn")
        self._shm = shared_memory.SharedMemory(create=True, size=slots * cameras * height * width)
        self._images = np.ndarray((slots, cameras, height, width), dtype=np.uint8, buffer=self._shm.buf)
        self._free, self._stop = context.Semaphore(slots), context.Event()
        self._setup, setup_child = context.Pipe(duplex=False)
        pipes = [context.Pipe(duplex=False) for _ in range(cameras)]
        self._pipes = [receive for receive, _ in pipes]
        self._process = context.Process(target=_render_frames, name="livebridge sim rig", daemon=True,
                                        args=(self._shm.name, self.options, slots, self._free, setup_child,
                                              [send for _, send in pipes], self._stop))
        self._pending = [cameras] * slots  # cameras still to take each slot
        self._lock = threading.Lock()
        self._started = False
        self.projections = None
        self.simulator_cpu_s = 0.0
        self.framesets = 0

    def start(self) -> None:
        if self._started:
            return
        self._started = True
        self._process.start()
        if not self._setup.poll(120):
            raise RuntimeError("the simulated rig's process did not start within 120 s")
        self.projections = self._setup.recv()

    def _taken(self, slot: int) -> None:
        """One camera is done with ``slot``; the last one hands it back to the rig."""
        with self._lock:
            self._pending[slot] -= 1
            done = self._pending[slot] == 0
            if done:
                self._pending[slot] = self.n_cameras
        if done:
            self._free.release()

    def take(self, camera: int, timeout: float | None):
        """The next frame of ``camera`` (a copy out of shared memory), or None on timeout."""
        from livebridge.capture.frame import Frame

        pipe = self._pipes[camera]
        while True:
            if not pipe.poll(timeout):
                return None
            seq, slot, meta, cpu = pipe.recv()
            if camera == 0:
                self.simulator_cpu_s, self.framesets = cpu, seq + 1
            if meta is not None:
                break
            self._taken(slot)  # this camera has no frame in this set
        t_capture, frame_seq, source_id, exposure_us, gain, domain = meta
        image = self._images[slot, camera].copy()
        image.setflags(write=False)
        self._taken(slot)
        return Frame(image, t_capture, frame_seq, source_id, exposure_us, gain, domain)

    def stop(self) -> None:
        self._stop.set()
        if self._process.pid is not None:  # it may have failed to start
            self._process.join(timeout=5)
        if self._process.pid is not None and self._process.is_alive():
            self._process.terminate()
            self._process.join(timeout=5)
        del self._images
        self._shm.close()
        self._shm.unlink()

    def sources(self, names) -> list:
        return [_ProcessRigSource(self, k, name) for k, name in enumerate(names)]


class _ProcessRigSource:
    """One camera of a :class:`ProcessRig` (the camera-source interface)."""

    def __init__(self, rig: ProcessRig, camera: int, source_id: str):
        self.rig, self.camera, self.source_id = rig, camera, source_id
        self.ended, self.error = False, None

    def start(self) -> None:
        self.rig.start()

    def stop(self) -> None:
        self.ended = True

    def read(self, timeout: float | None = None):
        if self.ended:
            return None
        return self.rig.take(self.camera, timeout)

    def status_text(self) -> None:
        return None

    def detect_with(self, config) -> None:
        pass

    def detect_board_with(self, board) -> None:
        pass


def cpu_split() -> tuple[set[int], set[int]] | None:
    """``(pipeline CPUs, rig CPUs)``: the last CPU for the simulated cameras, the others for the pipeline;
    None on a one-CPU machine or where affinity cannot be set."""
    if not hasattr(os, "sched_getaffinity"):
        return None
    cpus = sorted(os.sched_getaffinity(0))
    return (set(cpus[:-1]), {cpus[-1]}) if len(cpus) >= 2 else None


def _pin_servo_simulators(servo, cpus: set[int]) -> None:
    """Keep the simulated servo buses' processes on ``cpus`` (the servos' own silicon on a real rig): a
    simulator woken on the pipeline's CPU by a write would run before the writing thread goes on."""
    for bus in servo.buses.values():
        pid = getattr(bus.companion, "pid", None)
        if pid is not None:
            os.sched_setaffinity(pid, cpus)


def run_once(frames: int, rig_process: bool, log, split: tuple[set[int], set[int]] | None = None) -> dict:
    """One run of the demo pipeline (unpaced 4-camera sim rig, servos, one render client); figures and score.

    ``split``: ``(pipeline CPUs, rig CPUs)`` -- the pipeline's process and the rig's process are kept on
    their own CPUs for the run (with ``rig_process``); the simulated servo bus runs on the rig's CPUs.
    """
    import numpy as np

    from livebridge.runtime.demo import build_demo
    from livebridge.runtime.markers_front import MarkerFront
    from livebridge.runtime.pipeline import Pipeline, run_until_stopped
    from livebridge.simulators.rig_url import rig_from_url

    parts = build_demo(realtime=False, port=0, log=lambda message: None)
    rig, process = rig_from_url(parts.session.camera_urls[0]), None  # the demo's rig (a deterministic one)
    affinity = os.sched_getaffinity(0) if split else None
    if split:
        _pin_servo_simulators(parts.pipeline.servo, split[1])
    if rig_process:
        process = ProcessRig(cameras=rig.n_cameras, seed=1, fps=rig.config.fps, size=rig.config.size,
                             noise=rig.config.noise_sigma, cpus=split[1] if split else None)
        sources = process.sources(rig.names)
        if split:
            os.sched_setaffinity(0, split[0])
    else:
        sources = rig.sources(realtime=False)
    solved = []  # scored against the ground truth after the run: the scoring is not pipeline work
    front = MarkerFront(sources, rig.cameras, rig.basis, rig.markers, rig.period, realtime=False)
    pipeline = Pipeline(front, servo=parts.pipeline.servo, render=parts.pipeline.render, log=lambda message: None,
                        on_frame=solved.append)
    context = multiprocessing.get_context("spawn")
    stop, count, clients = context.Event(), context.Value("q", 0), []

    def started(pipeline):
        if process is not None:  # the child rig must be the demo's rig
            expected = np.stack([c.projection for c in parts.pipeline.front.cameras.cameras])
            if not np.allclose(process.projections, expected, rtol=1e-9, atol=1e-9):
                raise RuntimeError("the rig process built other cameras than the demo's rig")
        url = f"ws://127.0.0.1:{pipeline.render.port}/ws"
        clients.append(context.Process(target=_client, args=(url, stop, count), name="render client", daemon=True))
        clients[0].start()

    cpu_start, wall_start = time.process_time(), time.monotonic()
    try:
        summary = dataclasses.asdict(run_until_stopped(pipeline, frames=frames, log=lambda message: None,
                                                       on_start=started))
    finally:
        stop.set()
        for client in clients:
            client.join(timeout=5)
        if process is not None:
            process.stop()
        if affinity is not None:
            os.sched_setaffinity(0, affinity)
    summary["process_cpu_s"] = time.process_time() - cpu_start
    summary["run_wall_s"] = time.monotonic() - wall_start
    if process is not None:
        summary["simulator_ms_per_frameset"] = 1e3 * process.simulator_cpu_s / max(process.framesets, 1)
    summary["render_messages_received"] = count.value
    for frame in solved:
        parts.score(frame)
    summary["rmse"], summary["label_swaps"] = parts.score.rmse, parts.score.swaps
    return summary


HEADLINE_KEYS = ("latency_p50_ms", "latency_p99_ms", "render_latency_p50_ms", "render_latency_p99_ms", "rmse",
                 "label_swaps", "labelled_fraction", "cpu_per_frameset_ms", "pipeline_cpu_per_frameset_ms",
                 "detect_cpu_per_frameset_ms", "reconstruct_solve_cpu_per_frameset_ms",
                 "outputs_cpu_per_frameset_ms", "simulator_ms_per_frameset")
VARIANT_KEYS = ("latency_p50_ms", "latency_p99_ms", "cpu_per_frameset_ms", "rmse", "label_swaps")


def _figures(summary: dict, keys) -> dict:
    """``framesets_per_s`` and the named figures of a run, rounded (3 decimals; 5 for the RMSE)."""
    figures = {"framesets_per_s": round(summary["fps"], 2)}
    for key in keys:
        value = summary[key]
        figures[key] = value if isinstance(value, int) else round(value, 5 if key == "rmse" else 3)
    return figures


def run(quick: bool, log) -> dict:
    """Frame sets per second, latency (frame set complete -> servo bytes written), contraction RMSE, CPU.

    The simulated rig films 4 cameras at 1280x800 as fast as it can (not paced); frame sets go through
    detection, correspondence, labelling, the solve, to 16 Dynamixel servos simulated on a
    pseudo-terminal by a process of their own (real driver) and to one connected WebSocket render
    client (a process of its own, as a browser is).

    The headline figures run the rig in its own process (:class:`ProcessRig`) on a CPU of its own (the
    last one; the pipeline gets the others), with the simulated servo bus's process: on a real rig the
    images are formed by the cameras' silicon and the servos parse their packets on their own
    controllers, not on the host's CPU. The rig's CPU per frame set is ``simulator_ms_per_frameset``.
    ``rig_sharing_cpus`` is the same run with the rig free to use every CPU (on a 2-CPU machine it then
    takes a third of the pipeline's time), and ``in_process`` runs the rig on the camera reader threads
    of this process (each frame set is rendered before the cameras return it, so the rendering costs
    throughput, not latency).

    Latency is from the moment the last frame of a set reached the host (its camera reader returned
    it, before detection) to the servo bytes written for that set.
    """
    n = 150 if quick else 600
    split = cpu_split()
    where = f"on CPU {sorted(split[1])}, the pipeline on {sorted(split[0])}" if split else "(one CPU: shared)"
    log(f"running {n} frame sets through the pipeline, rig in its own process {where} ...")
    summary = run_once(n, True, log, split)
    log(f"running {n} frame sets, rig in its own process sharing every CPU ...")
    shared = run_once(n, True, log)
    log(f"running {n} frame sets through the pipeline, rig in this process ...")
    inline = run_once(n, False, log)
    quarter = FRAME_PERIOD_30FPS_MS / 4
    result = _figures(summary, HEADLINE_KEYS) | {
        "framesets": summary["solved"],
        "dropped_framesets": summary["drops"],
        "render_messages_received": summary["render_messages_received"],
        "pipeline_cpus": sorted(split[0]) if split else None,
        "rig_cpus": sorted(split[1]) if split else None,
        "rig_sharing_cpus": _figures(shared, VARIANT_KEYS),
        "in_process": _figures(inline, VARIANT_KEYS),
        "cpu_count": os.cpu_count(),
        "load_average_1min": round(os.getloadavg()[0], 2),
        "required": {"framesets_per_s": ">= 60", "latency_p99_ms": f"<= {quarter:.2f} (a quarter of 1/30 s)",
                     "rmse": "<= 0.03"},
    }
    result["pass"] = bool(result["framesets_per_s"] >= 60 and result["latency_p99_ms"] <= quarter
                          and result["rmse"] <= 0.03 and summary["label_swaps"] == 0)
    return result
