"""Camera nodes over ZeroMQ: latency added against the same cameras in process, frame sets/s over 4 nodes, clock.

``added_latency_p50_ms`` / ``_p99_ms``: one paced simulated camera at 120 fps; the latency from the end of a
frame's exposure (the rig's ``ready_time``) to its centroids being ready for reconstruction, through a camera
node (a separate process, detection there, msgpack over loopback TCP) minus the same in process
(``DetectingSource`` on the host); goals 0.3 and 1.0 ms. ``framesets_per_s``: 8 cameras at 120 fps over 4
node processes (2 cameras each) into one synchroniser, complete frame sets per second; what limits it on this
machine is reported beside it (``render_detect_ms_per_frame``: simulated rendering plus detection of one camera
frame, times 960 frames/s, against ``os.cpu_count()`` cores). ``framesets_per_s_prerendered``: the same,
but each node replays frames of its cameras rendered before the run (:class:`PrerenderedSource`, a loop of
:data:`PRERENDERED_FRAMES` per camera, paced at 120 fps; detection still runs on the nodes), so the figure
measures the nodes' detection, the transport and the host's synchroniser, not the simulator's renderer.
``clock_offset_error_ms``: a node clock skewed +37 ms and drifting 50 ppm, estimated over the same
connection.
"""

from __future__ import annotations

import math
import os
import select
import subprocess
import sys
import time

import numpy as np

from livebridge.capture.frame import Frame
from livebridge.capture.sources import Capabilities, SourceBase

FPS = 120.0
PRERENDERED_FRAMES = 60
GOALS_MS = {"added_latency_p50_ms": 0.3, "added_latency_p99_ms": 1.0}


def run(quick: bool = False, log=print) -> dict:
    from livebridge.face.builtin import builtin_markers

    seconds = 2.0 if quick else 6.0
    folder = _scratch()
    markers = os.path.join(folder, "markers.toml")
    builtin_markers().save(markers)  # designed once here, read by every node process
    rig = f"sim://rig?seed=1&markers={markers}"
    result = {}
    result.update(_latency(rig, seconds, log))
    result.update(_framesets(rig, seconds, log))
    result.update(_clock(rig, seconds, log))
    result["goals_ms"] = GOALS_MS
    result["meets_latency_goals"] = all(result[key] <= goal for key, goal in GOALS_MS.items())
    return result


def _scratch() -> str:
    import tempfile

    return tempfile.mkdtemp(prefix="livebridge-bench-nodes-")


class _NodeProcess:
    """``livebridge node`` in its own process, on a free loopback port pair."""

    def __init__(self, urls, prerendered: bool = False):
        if prerendered:
            args = [sys.executable, "-m", "livebridge.bench.nodes", *urls]
        else:
            args = [sys.executable, "-m", "livebridge", "node", "--host", "tcp://127.0.0.1:0"]
            for url in urls:
                args += ["--cameras", url]
        self.process = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        ready, _, _ = select.select([self.process.stdout], [], [], 120)
        if not ready:
            self.close()
            raise RuntimeError("the node process did not start")
        self.port = int(self.process.stdout.readline().rpartition(":")[2])

    def close(self) -> None:
        self.process.terminate()
        try:
            self.process.wait(10)
        except subprocess.TimeoutExpired:
            self.process.kill()


def _detection_latencies(source, rig_url: str, camera, seconds: float) -> np.ndarray:
    """Seconds from each frame's end of exposure to its detection, read through ``DetectingSource``."""
    from livebridge.reconstruct.detect import DetectingSource
    from livebridge.simulators.rig_url import rig_from_url

    rig = rig_from_url(rig_url)
    t0 = float(rig_url.rpartition("t0=")[2].split("&")[0])
    detecting = DetectingSource(source, camera)
    latencies = []
    with detecting:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            frame = detecting.read(timeout=5.0)
            if frame is None:
                break
            seq = frame.seq - rig.source_seq(0, 0)
            ready = t0 + (seq + 0.5) / rig.config.fps
            latencies.append(detecting.result(frame).detected - ready)
    return np.array(latencies[int(FPS // 2):])  # the first half second warms up


def _latency(rig: str, seconds: float, log) -> dict:
    from livebridge.devices.registry import open_cameras

    t0 = time.monotonic() + 1.0
    url = f"{rig}&fps={FPS:g}&cameras=1&t0={t0}"
    (local,) = open_cameras(url)
    in_process = _detection_latencies(local, url, local.calibration, seconds)
    node = _NodeProcess([url])
    try:
        (remote,) = open_cameras(f"node://127.0.0.1:{node.port}?camera=cam0")
        time.sleep(0.5)
        via_node = _detection_latencies(remote, url, local.calibration, seconds)
        transport = np.array(remote.transport_s[int(FPS // 2):])
    finally:
        node.close()
    p = {name: np.percentile(values, [50, 99]) * 1e3 for name, values in (("process", in_process),
                                                                         ("node", via_node),
                                                                         ("transport", transport))}
    log(f"latency exposure end -> centroids ready, p50/p99 ms: in process {p['process'][0]:.3f}/{p['process'][1]:.3f}, "
        f"via node {p['node'][0]:.3f}/{p['node'][1]:.3f}; node send -> host receipt {p['transport'][0]:.3f}/"
        f"{p['transport'][1]:.3f}")
    return {"added_latency_p50_ms": float(p["node"][0] - p["process"][0]),
            "added_latency_p99_ms": float(p["node"][1] - p["process"][1]),
            "in_process_latency_p50_ms": float(p["process"][0]), "in_process_latency_p99_ms": float(p["process"][1]),
            "node_latency_p50_ms": float(p["node"][0]), "node_latency_p99_ms": float(p["node"][1]),
            "transport_p50_ms": float(p["transport"][0]), "transport_p99_ms": float(p["transport"][1]),
            "latency_frames": int(min(len(in_process), len(via_node)))}


def _framesets(rig: str, seconds: float, log) -> dict:
    live = _framesets_over_nodes(rig, seconds, prerendered=False)
    replayed = _framesets_over_nodes(rig, seconds, prerendered=True)
    cost_ms = _render_detect_ms(f"{rig}&fps={FPS:g}&cameras=8")
    cores_needed = cost_ms * 8 * FPS / 1e3
    camera_share = live["camera_frames_per_s"] / FPS
    limit = (f"the simulated cameras: they delivered {100 * camera_share:.0f}% of their frames (rendering and "
             f"detection need {cores_needed:.1f} of {os.cpu_count()} cores, shared with everything else running; "
             "a camera that falls behind skips frames the others keep, so frame sets are incomplete)"
             if camera_share < 0.95 else "transport and the host's synchroniser")
    log(f"8 cameras x {FPS:g} fps over 4 nodes: {live['framesets_per_s']:.1f} complete frame sets/s "
        f"({live['framesets_any_per_s']:.1f} in all); rendering + detecting one frame costs {cost_ms:.2f} ms: "
        f"limited by {limit}")
    log(f"the same, the nodes replaying pre-rendered frames (detection on the nodes, no rendering): "
        f"{replayed['framesets_per_s']:.1f} complete frame sets/s ({replayed['framesets_any_per_s']:.1f} in all), "
        f"cameras delivered {100 * replayed['camera_frames_per_s'] / FPS:.0f}% of their frames")
    return {"framesets_per_s": live["framesets_per_s"], "framesets_any_per_s": live["framesets_any_per_s"],
            "camera_frames_per_s": live["camera_frames_per_s"], "render_detect_ms_per_frame": cost_ms,
            "cores_needed": cores_needed, "cores": os.cpu_count(), "framesets_limited_by": limit,
            "framesets_per_s_prerendered": replayed["framesets_per_s"],
            "framesets_any_per_s_prerendered": replayed["framesets_any_per_s"],
            "camera_frames_per_s_prerendered": replayed["camera_frames_per_s"],
            "load_average_1min": os.getloadavg()[0]}


def _framesets_over_nodes(rig: str, seconds: float, prerendered: bool) -> dict:
    """Complete (and any) frame sets per second and frames per second per camera, 8 cameras over 4 nodes."""
    from livebridge.capture.sync import SyncedCapture
    from livebridge.devices.registry import open_cameras

    t0 = time.monotonic() + (20.0 if prerendered else 3.0)  # pre-rendering takes a while on a busy machine
    url = f"{rig}&fps={FPS:g}&cameras=8&t0={t0}"
    nodes = [_NodeProcess([f"{url}&camera={2 * k}", f"{url}&camera={2 * k + 1}"], prerendered) for k in range(4)]
    try:
        sources = [s for k, node in enumerate(nodes) for c in (2 * k, 2 * k + 1)
                   for s in open_cameras(f"node://127.0.0.1:{node.port}?camera=cam{c}")]
        capture = SyncedCapture(sources, 1 / FPS, queue_size=4)
        complete = total = 0
        with capture:
            time.sleep(max(0.0, t0 - time.monotonic()) + 1.0)
            start, end = time.monotonic(), time.monotonic() + seconds
            delivered = [s.frames for s in sources]
            while time.monotonic() < end:
                frameset = capture.read(timeout=1.0)
                if frameset is not None:
                    total += 1
                    complete += frameset.complete
            elapsed = time.monotonic() - start
            delivered = [(s.frames - before) / elapsed for s, before in zip(sources, delivered)]
    finally:
        for node in nodes:
            node.close()
    return {"framesets_per_s": complete / elapsed, "framesets_any_per_s": total / elapsed,
            "camera_frames_per_s": float(np.mean(delivered))}


def _render_detect_ms(url: str) -> float:
    """Milliseconds of CPU to render one simulated camera frame and detect its markers (median of 20)."""
    from livebridge.reconstruct.detect import detect_blobs
    from livebridge.simulators.rig_url import rig_from_url

    rig = rig_from_url(url.partition("&t0=")[0])
    rig.start()
    times = []
    for seq in range(20):
        start = time.thread_time()
        frame = rig.camera_frame(seq, seq % rig.n_cameras)
        detect_blobs(frame.image)
        times.append(time.thread_time() - start)
    return float(np.median(times) * 1e3)


def _clock(rig: str, seconds: float, log) -> dict:
    from livebridge.devices.registry import open_cameras
    from livebridge.nodes.node import CameraNode, SkewedClock
    from livebridge.nodes.source import NodeSource

    t_ref = time.monotonic()
    clock = SkewedClock(0.037, 50e-6, t_ref)
    with CameraNode(open_cameras(f"{rig}&cameras=1&fps=30"), clock=clock) as node:
        source = NodeSource("127.0.0.1", node.port, "cam0")
        with source:
            time.sleep(seconds)
            now = time.monotonic()
            error = source.estimator.estimate.offset_at(now) - clock.offset_at(now)
            status = source.status_text()
    log(f"clock: {status}; true offset {clock.offset_at(now) * 1e3:+.3f} ms, error {error * 1e3:+.4f} ms")
    return {"clock_offset_error_ms": float(abs(error) * 1e3)}


class PrerenderedSource(SourceBase):
    """One camera of a simulated rig replaying frames rendered before it starts: frame ``seq`` shows rendered
    frame ``seq % n`` and is delivered at ``t0 + seq / fps`` (paced, ``time.monotonic``), as the rig would
    deliver it, so node processes sharing ``t0`` deliver frame sets together; a read that comes late skips
    the frames whose time has passed, as a camera does. For the benchmark only: it takes the simulator's
    rendering out of the measurement.

    Parameters
    ----------
    url : str
        A ``sim://rig?...&camera=K&t0=T`` URL (one camera).
    n_frames : int
        Frames rendered up front and looped.
    """

    def __init__(self, url: str, n_frames: int = PRERENDERED_FRAMES):
        from livebridge.devices.url import DeviceURL
        from livebridge.simulators.rig_url import rig_from_url

        parsed = DeviceURL.parse(url)
        camera, self.t0 = int(parsed.query["camera"]), float(parsed.query["t0"])
        rig = rig_from_url(parsed)
        rig.start(0.0)
        frames = [rig.camera_frame(seq, camera) for seq in range(n_frames)]
        self.images = [None if frame is None else frame.image for frame in frames]
        first = next(frame for frame in frames if frame is not None)
        self.source_id, self.sync_domain = first.source_id, first.sync_domain
        self.camera, self.fps = rig.cameras.cameras[camera], rig.config.fps
        self._seq = 0

    @property
    def calibration(self):
        return self.camera

    @property
    def capabilities(self) -> Capabilities:
        return Capabilities(size=self.camera.size, fps=self.fps)

    def start(self) -> None:
        self._seq = max(0, math.ceil((time.monotonic() - self.t0) * self.fps))

    def stop(self) -> None:
        self._end(None)

    def read(self, timeout: float | None = None) -> Frame | None:
        seq = self._seq
        t = self.t0 + seq / self.fps
        wait = t - time.monotonic()
        if timeout is not None and wait > timeout:
            time.sleep(timeout)
            return None
        time.sleep(max(0.0, wait))
        self._seq = max(seq + 1, math.floor((time.monotonic() - self.t0) * self.fps))
        image = self.images[seq % len(self.images)]
        return None if image is None else Frame(image, t, seq, self.source_id, sync_domain=self.sync_domain)


def _serve_prerendered(urls: list[str]) -> None:
    """A camera node serving :class:`PrerenderedSource` cameras on a free loopback port (printed as
    ``tcp://127.0.0.1:PORT``) until SIGTERM."""
    import signal
    import threading

    from livebridge.nodes.node import CameraNode

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    sources = [PrerenderedSource(url) for url in urls]
    with CameraNode(sources, "tcp://127.0.0.1:0", name="prerendered") as node:
        print(f"tcp://127.0.0.1:{node.port}", flush=True)
        stop.wait()


if __name__ == "__main__":
    _serve_prerendered(sys.argv[1:])
