"""Camera nodes over ZeroMQ (loopback only): node processes filming cameras of one simulated rig feed a host."""

from __future__ import annotations

import math
import select
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

zmq = pytest.importorskip("zmq")
msgpack = pytest.importorskip("msgpack")

from livebridge.nodes import protocol  # noqa: E402
from livebridge.nodes.clock import ClockEstimator  # noqa: E402
from livebridge.nodes.protocol import FrameMessage, Grab, Ping, Pong, ProtocolError  # noqa: E402

NODE_SCRIPT = Path(__file__).with_name("node_process.py")
ROOT = Path(__file__).resolve().parents[1]
HANG_S = 60.0


@pytest.fixture(scope="module")
def rig_url(tmp_path_factory) -> str:
    """The simulated rig's URL; the built-in marker layout is designed once and read from a file by every
    node process (designing it takes seconds)."""
    from livebridge.face.builtin import builtin_markers

    path = tmp_path_factory.mktemp("nodes") / "markers.toml"
    builtin_markers().save(path)
    return f"sim://rig?seed=3&size=640x400&fps=30&lead_in_s=0.5&markers={path}"


# ---------------------------------------------------------------------------------------------- helpers

class NodeProcess:
    """A camera node in its own process (``tests/node_process.py``); ``port`` once it serves."""

    def __init__(self, urls, port: int = 0, offset_s: float = 0.0, drift: float = 0.0, t_ref: float = 0.0):
        self.urls, self.port, self.clock = list(urls), port, (offset_s, drift, t_ref)
        self.process = None
        self.start()

    def start(self) -> None:
        args = [sys.executable, str(NODE_SCRIPT), str(self.port), *map(str, self.clock), *self.urls]
        self.process = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=ROOT)
        ready, _, _ = select.select([self.process.stdout], [], [], HANG_S)
        assert ready, "node process did not start"
        self.port = int(self.process.stdout.readline())

    def kill(self) -> None:
        self.process.kill()
        self.process.wait(10)

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.stdin.close()
            try:
                self.process.wait(10)
            except subprocess.TimeoutExpired:
                self.kill()


@pytest.fixture
def nodes():
    started: list[NodeProcess] = []

    def start(*args, **kwargs) -> NodeProcess:
        started.append(NodeProcess(*args, **kwargs))
        return started[-1]

    yield start
    for node in started:
        node.close()


def _node_sources(urls):
    from livebridge.devices.registry import open_cameras

    return [source for url in urls for source in open_cameras(url)]


def _until(condition, timeout: float = HANG_S, what: str = "") -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)


def _pipeline(sources, rig, realtime: bool, frames: list, log=None):
    from livebridge.runtime.markers_front import MarkerFront
    from livebridge.runtime.pipeline import Pipeline

    front = MarkerFront(sources, rig.cameras, rig.basis, rig.markers, rig.period, realtime=realtime,
                        labelling_timeout_s=HANG_S)
    return Pipeline(front, on_frame=frames.append, log=log or (lambda line: None))


# ---------------------------------------------------------------------------------------------- protocol

def _frame_message(**changes) -> FrameMessage:
    fields = dict(camera="cam0", seq=7, t=12.5, centroids=np.array([[1.25, 2.5], [300.125, 4.0]]), exposure_us=2000.0,
                  gain=1.0, sync_domain="rig", index=-1, t_sent=12.6, image=None)
    fields.update(changes)
    return FrameMessage(**fields)


def test_every_message_survives_encoding_exactly():
    image = np.arange(12, dtype=np.uint8).reshape(3, 4)
    frame = protocol.decode(protocol.encode(_frame_message(image=image), "cam0"))
    assert (frame.camera, frame.seq, frame.t, frame.sync_domain, frame.t_sent) == ("cam0", 7, 12.5, "rig", 12.6)
    assert np.array_equal(frame.centroids, [[1.25, 2.5], [300.125, 4.0]]) and np.array_equal(frame.image, image)
    for message in (Ping("cam1", 3.25, "thumbnail", {"threshold": None, "min_area": 4}),
                    Pong("cam1", 1.0, 2.0, 3.0, "n", "ptp", "", False, {"name": "cam1"}), Grab("cam1", 41)):
        assert protocol.decode(protocol.encode(message)) == message


def _bad_messages() -> dict[str, list[bytes]]:
    good = protocol.encode(_frame_message(), "cam0")
    body = msgpack.unpackb(good[5:])
    packed = lambda **changes: b"\0" + msgpack.packb({**body, **changes})  # noqa: E731
    return {
        "oversized": [b"\0" + bytes(protocol.MAX_MESSAGE_BYTES),
                      b"\0" + msgpack.packb({"v": 1, "type": "ping", "camera": "c", "t1": 1.0, "pad": bytes(70000)})],
        "malformed": [b"no separator", b"\0\xc1", good[:len(good) // 2], good[:-1], b"\0" + msgpack.packb([1, 2])],
        "version": [packed(v=2), b"\0" + msgpack.packb({"type": "frame"})],
        "type": [packed(type="hello"), packed(type=5)],
        "field": [packed(centroids=np.array([[np.nan, 1.0]]).tobytes()), packed(centroids=b"\0" * 15),
                  packed(seq="7"), packed(t=math.inf), packed(image=[4, 4, b"\0" * 15]), packed(camera=None),
                  b"cam9" + good[4:], b"\0" + msgpack.packb({"v": 1, "type": "ping", "camera": "c", "t1": 1.0,
                                                              "detect": {"min_area": "3"}})],
    }


@pytest.mark.parametrize("reason", ["oversized", "malformed", "version", "type", "field"])
def test_bad_messages_are_refused_with_their_reason(reason):
    for data in _bad_messages()[reason]:
        with pytest.raises(ProtocolError) as caught:
            protocol.decode(data)
        assert caught.value.reason == reason, (data[:40], caught.value)


def test_random_bytes_never_escape_as_anything_but_a_protocol_error():
    rng = np.random.default_rng(5)
    good = protocol.encode(_frame_message(image=np.zeros((4, 4), np.uint8)), "cam0")
    for _ in range(3000):
        data = bytearray(good)
        for index in rng.integers(0, len(data), rng.integers(1, 6)):
            data[index] = rng.integers(0, 256)
        try:
            message = protocol.decode(bytes(data[:rng.integers(1, len(data) + 1)]))
        except ProtocolError:
            continue
        assert isinstance(message, FrameMessage) and np.isfinite(message.centroids).all()


# ---------------------------------------------------------------------------------------------- clock

def test_clock_estimate_of_a_skewed_drifting_clock_through_noisy_exchanges():
    rng = np.random.default_rng(1)
    estimator = ClockEstimator()
    offset = lambda t: 0.037 + 50e-6 * (t - 100.0)  # noqa: E731 - node minus host
    for k in range(200):  # 20 s of pings at 10 Hz
        t1 = 100.0 + 0.1 * k
        out, back = rng.exponential(100e-6, 2) + 50e-6
        if rng.random() < 0.2:  # a busy host or network: one way much slower
            out += rng.uniform(1e-3, 20e-3)
        t2 = t1 + out + offset(t1 + out)
        t3 = t2 + 20e-6
        t4 = t3 - offset(t1 + out + 20e-6) + back
        estimate = estimator.add(t1, t2, t3, t4)
    assert abs(estimate.offset_at(t4) - offset(t4)) < 0.2e-3
    assert estimate.drift == pytest.approx(50e-6, abs=10e-6)
    assert estimate.to_host(100.5 + offset(100.5)) == pytest.approx(100.5, abs=0.2e-3)


# ---------------------------------------------------------------------------------------------- live, in processes

def test_a_skewed_drifting_node_clock_is_estimated_and_its_frames_arrive_in_host_time(nodes, rig_url):
    t_ref = time.monotonic()
    t0 = t_ref + 1.0
    node = nodes([f"{rig_url}&cameras=2&camera=0&t0={t0}"], offset_s=0.037, drift=50e-6, t_ref=t_ref)
    (source,) = _node_sources([f"node://127.0.0.1:{node.port}?camera=cam0&ping_ms=20"])
    errors = []
    with source:
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            frame = source.read(timeout=HANG_S)
            assert frame is not None and frame.centroids is not None and frame.image.size == 0
            errors.append(frame.t_capture - (t0 + frame.seq / 30.0))  # the rig's own capture time of that frame
        now = time.monotonic()
        estimated = source.estimator.estimate.offset_at(now)
        status = source.status_text()
    assert abs(estimated - (0.037 + 50e-6 * (now - t_ref))) < 0.2e-3
    assert np.abs(errors[-30:]).max() < 0.2e-3
    shown = float(status.split("offset ")[1].split(" ms")[0])
    assert shown == pytest.approx(1e3 * (0.037 + 50e-6 * (now - t_ref)), abs=0.2) and "jitter" in status


def _reference_and_nodes(nodes, rig_url, layout, n_frames):
    """Contractions of the rig in one process and over node processes (``layout``: camera indices per node)."""
    from livebridge.devices.registry import open_cameras
    from livebridge.simulators.rig import rig_from_url

    n_cameras = sum(len(cams) for cams in layout)
    # t0: one time base for the rig in every process (each would start its own clock), as one trigger gives
    url = f"{rig_url}&cameras={n_cameras}&realtime=0&frames={n_frames}&t0=1000"
    rig = rig_from_url(url)
    results = {}
    for kind in ("process", "nodes"):
        if kind == "process":
            sources = open_cameras(url)
        else:
            served = [nodes([f"{url}&camera={c}" for c in cams]) for cams in layout]
            sources = _node_sources([f"node://127.0.0.1:{node.port}?camera=cam{c}&realtime=0"
                                     for node, cams in zip(served, layout) for c in cams])
        frames = []
        with _pipeline(sources, rig, False, frames) as pipeline:
            assert pipeline.wait(HANG_S), "pipeline did not end"
        assert pipeline.error is None
        results[kind] = {f.seq: f for f in frames}
    return results["process"], results["nodes"]


def test_nodes_give_the_contractions_of_the_same_rig_in_one_process(nodes, rig_url):
    alone, remote = _reference_and_nodes(nodes, rig_url, [[0, 1], [2], [3]], n_frames=30)
    assert len(alone) >= 20 and alone.keys() == remote.keys()
    for seq, frame in alone.items():
        assert np.array_equal(frame.contractions, remote[seq].contractions)
        # the same labels in the same places
        assert np.array_equal(frame.positions_world, remote[seq].positions_world, equal_nan=True)


@pytest.mark.slow
def test_eight_nodes_give_the_contractions_of_the_same_rig_in_one_process(nodes, rig_url):
    alone, remote = _reference_and_nodes(nodes, rig_url, [[c] for c in range(8)], n_frames=40)
    assert len(alone) >= 30 and alone.keys() == remote.keys()
    for seq, frame in alone.items():
        assert np.array_equal(frame.contractions, remote[seq].contractions)


def test_a_node_killed_mid_take_is_reported_and_rejoins_without_a_host_restart(nodes, rig_url):
    from livebridge.simulators.rig import rig_from_url

    t0 = time.monotonic() + 4.0
    url = f"{rig_url}&cameras=5&t0={t0}"
    layout = [[0, 1], [2, 3], [4]]
    served = [nodes([f"{url}&camera={c}" for c in cams]) for cams in layout]
    sources = _node_sources([f"node://127.0.0.1:{node.port}?camera=cam{c}&dead_after_s=0.5"
                             for node, cams in zip(served, layout) for c in cams])
    frames = []
    with _pipeline(sources, rig_from_url(url), True, frames) as pipeline:
        _until(lambda: len(frames) >= 15, what="solving")
        served[2].kill()
        _until(lambda: "cam4" in pipeline.front.capture.sync.dead, what="cam4 reported dead")
        count = len(frames)
        _until(lambda: len(frames) >= count + 15, what="solving without cam4")
        assert all(f.n_cameras <= 4 for f in frames[count + 5:])
        assert any("lost" in event for event in sources[4].events) and sources[4].status_text().endswith("lost")
        served[2].start()  # the same port: the host reconnects by itself
        _until(lambda: frames[-1].n_cameras == 5, what="cam4 back")
        _until(lambda: "cam4" not in pipeline.front.capture.sync.dead, what="cam4 alive")
    assert pipeline.error is None


def test_malformed_truncated_oversized_messages_and_a_flood_are_counted_and_dropped(nodes, rig_url):
    from livebridge.simulators.rig import rig_from_url

    t0 = time.monotonic() + 3.0
    url = f"{rig_url}&cameras=3&t0={t0}"
    node = nodes([f"{url}&camera={c}" for c in range(3)])
    relay = _HostileRelay(node.port)
    sources = _node_sources([f"node://127.0.0.1:{relay.port}?camera=cam0"] +
                            [f"node://127.0.0.1:{node.port}?camera=cam{c}" for c in (1, 2)])
    frames = []
    try:
        with _pipeline(sources, rig_from_url(url), True, frames) as pipeline:
            _until(lambda: len(frames) >= 10, what="solving")
            relay.attack.set()
            _until(lambda: relay.attacks >= 3, what="attacks")
            count = len(frames)
            _until(lambda: len(frames) >= count + 15, what="solving under attack")
            assert frames[-1].n_cameras == 3
    finally:
        relay.close()
    drops = sources[0].drops.counts
    assert {"oversized", "malformed", "version", "type", "field"} <= set(drops), drops
    assert sources[0].drops.total > 1000  # the flood reached the host and was dropped there
    assert pipeline.error is None


class _HostileRelay:
    """Sits between a host source and a node: forwards both ways, and on ``attack`` also sends the host
    bad messages (each kind of :func:`_bad_messages`) and floods of garbage, on both of its links."""

    def __init__(self, node_port: int):
        self.context = zmq.Context()
        self.pub, self.router = self.context.socket(zmq.PUB), self.context.socket(zmq.ROUTER)
        self.port = self.pub.bind_to_random_port("tcp://127.0.0.1", 20000, 60000)
        self.router.bind(f"tcp://127.0.0.1:{self.port + 1}")
        self.sub, self.dealer = self.context.socket(zmq.SUB), self.context.socket(zmq.DEALER)
        self.sub.setsockopt(zmq.SUBSCRIBE, b"")
        self.sub.connect(f"tcp://127.0.0.1:{node_port}")
        self.dealer.connect(f"tcp://127.0.0.1:{node_port + 1}")
        for socket in (self.pub, self.router, self.sub, self.dealer):
            socket.linger = 0
        self.pub.sndhwm = self.router.sndhwm = 100000
        self.attack, self.stop, self.attacks = threading.Event(), threading.Event(), 0
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        poller = zmq.Poller()
        for socket in (self.router, self.sub, self.dealer):
            poller.register(socket, zmq.POLLIN)
        host, next_attack = None, 0.0
        while not self.stop.is_set():
            for socket, _ in poller.poll(10):
                if socket is self.router:
                    host, data = self.router.recv_multipart()
                    self.dealer.send(data)
                elif socket is self.dealer:
                    if host is not None:
                        self.router.send_multipart([host, self.dealer.recv()])
                else:
                    self.pub.send(self.sub.recv())
            if self.attack.is_set() and host is not None and time.monotonic() > next_attack:
                self._send_attack(host)
                next_attack = time.monotonic() + 0.3

    def _send_attack(self, host: bytes) -> None:
        for reason, messages in _bad_messages().items():
            for data in messages:
                self.router.send_multipart([host, data])
                if reason != "oversized":
                    self.pub.send(b"cam0" + data[data.index(b"\0"):] if b"\0" in data else data)
        for _ in range(500):  # a flood: far more than the host's queues hold
            self.router.send_multipart([host, b"\0\x92garbage"], zmq.NOBLOCK)
        self.attacks += 1

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)
        self.context.destroy(linger=0)
