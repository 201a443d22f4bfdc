"""Camera nodes over ZeroMQ (loopback only): node processes filming cameras of one simulated rig feed a host.

Node processes take seconds to start (imports, the rig), so the paced ones are started once per module
(:func:`paced`: one rig whose performer holds a neutral face throughout, so any test may label at any time)
and the unpaced ones, whose frames are used up, per test; every wait has a hang guard (``HANG_S``).
"""

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


@pytest.fixture(autouse=True)
def every_zmq_context_destroyed():
    """After each test no zmq context of this process is left open: one left to the collector can hang
    ``gc.collect()`` for good (in a garbage cycle its ``__del__`` finds its socket set already cleared, and
    its ``term`` waits for the socket still open)."""
    yield
    import gc

    def open_contexts():
        return [o for o in gc.get_objects() if isinstance(o, zmq.Context) and not o.closed]

    # a source's stop waits up to 5 s for its I/O thread
    _until(lambda: not open_contexts(), 6.0,
           f"the zmq contexts to be destroyed ({len(open_contexts())} open when the test ended)")


@pytest.fixture(scope="module")
def rig_url(tmp_path_factory) -> str:
    """The simulated rig's URL; the built-in marker layout is designed once and read from a file by every
    node process (designing it takes seconds)."""
    from livebridge.face.builtin import builtin_markers

    path = tmp_path_factory.mktemp("nodes") / "markers.toml"
    builtin_markers().save(path)
    return f"sim://rig?seed=3&size=640x400&fps=30&markers={path}"


# ---------------------------------------------------------------------------------------------- helpers

class NodeProcess:
    """A camera node in its own process (``tests/node_process.py``); :meth:`ready` waits for its port."""

    def __init__(self, urls, port: int = 0, offset_s: float = 0.0, drift: float = 0.0, t_ref: float = 0.0):
        self.urls, self.port, self.clock = list(urls), port, (offset_s, drift, t_ref)
        self.process = None
        self.spawn()

    @property
    def name(self) -> str:
        return f"node-{self.port}"

    def spawn(self) -> None:
        args = [sys.executable, str(NODE_SCRIPT), str(self.port), *map(str, self.clock), *self.urls]
        self.process = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=ROOT)

    def ready(self) -> NodeProcess:
        ready, _, _ = select.select([self.process.stdout], [], [], HANG_S)
        assert ready, "node process did not start"
        line = self.process.stdout.readline()
        assert line.strip().isdigit(), f"node process failed: {line!r}"
        self.port = int(line)
        return self

    def start(self) -> None:
        self.spawn()
        self.ready()

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


def _start_nodes(*specs) -> list[NodeProcess]:
    """Node processes started side by side (``specs``: (urls, keyword arguments)), once each serves."""
    started = [NodeProcess(urls, **options) for urls, options in specs]
    try:
        return [node.ready() for node in started]
    except BaseException:
        for node in started:
            node.close()
        raise


@pytest.fixture
def nodes():
    """Start node processes for one test: ``nodes((urls, options), ...)``; closed after it."""
    started: list[NodeProcess] = []

    def start(*specs) -> list[NodeProcess]:
        started.extend(_start_nodes(*specs))
        return started[-len(specs):]

    yield start
    for node in started:
        node.close()


class PacedRig:
    """Five paced cameras of one rig on three node processes: ``a`` (cam0, cam1; its clock +37 ms ahead and
    50 ppm fast), ``b`` (cam2, cam3), ``c`` (cam4). The performer holds a neutral face throughout."""

    def __init__(self, rig_url: str):
        self.t_ref = time.monotonic()
        self.t0 = self.t_ref + 1.0  # one time base in every process, as one trigger gives
        self.url = f"{rig_url}&cameras=5&lead_in_s=3600&t0={self.t0}"
        self.markers = rig_url.partition("markers=")[2]
        self.a, self.b, self.c = _start_nodes(
            ([f"{self.url}&camera={c}" for c in (0, 1)], dict(offset_s=0.037, drift=50e-6, t_ref=self.t_ref)),
            ([f"{self.url}&camera={c}" for c in (2, 3)], {}), ([f"{self.url}&camera=4"], {}))
        self.port = {"cam0": self.a.port, "cam1": self.a.port, "cam2": self.b.port, "cam3": self.b.port,
                     "cam4": self.c.port}

    def node_url(self, camera: str, options: str = "") -> str:
        return f"node://127.0.0.1:{self.port[camera]}?camera={camera}{options}"

    def true_offset(self, t: float) -> float:
        """Node ``a``'s clock minus the host's at host time ``t``, seconds."""
        return 0.037 + 50e-6 * (t - self.t_ref)

    def close(self) -> None:
        for node in (self.a, self.b, self.c):
            node.close()


@pytest.fixture(scope="module")
def paced(rig_url):
    rig = PacedRig(rig_url)
    yield rig
    rig.close()


def _node_sources(urls):
    from livebridge.devices.registry import open_cameras

    return [source for url in urls for source in open_cameras(url)]


def _until(condition, timeout: float = HANG_S, what: str = "") -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)


def _pipeline(sources, markers_path: str, frames: list):
    """A live pipeline of ``sources`` (their own calibrations) solving the built-in face with these markers."""
    from livebridge.face.builtin import builtin_basis
    from livebridge.face.shipped import load_marker_set
    from livebridge.runtime.markers_front import MarkerFront
    from livebridge.runtime.pipeline import Pipeline

    front = MarkerFront(sources, _cameras(sources), builtin_basis(), load_marker_set(markers_path), 1 / 30,
                        labelling_timeout_s=HANG_S)
    return Pipeline(front, on_frame=frames.append, log=lambda line: None)


def _cameras(sources):
    """The calibrated cameras the nodes report."""
    from livebridge.calibration.cameras import CameraGroup

    return CameraGroup([source.calibration for source in sources])


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
    for message in (Ping("cam1", 3.25, "thumbnail", {"threshold": None, "min_area": 4}, "chessboard:7x7:55"),
                    Pong("cam1", 1.0, 2.0, 3.0, "n", "ptp", "", False, {"name": "cam1"}, 120.0, (640, 480)),
                    Grab("cam1", 41)):
        assert protocol.decode(protocol.encode(message)) == message
    corners = protocol.decode(protocol.encode(_frame_message(centroids=None, board_ids=np.array([0, 5, 48]),
                                                             board_points=[[1.5, 2.0], [3.0, 4.25], [5.0, 6.0]])))
    assert corners.centroids is None and np.array_equal(corners.board_ids, [0, 5, 48])
    assert np.array_equal(corners.board_points, [[1.5, 2.0], [3.0, 4.25], [5.0, 6.0]])


def _bad_messages() -> dict[str, list[bytes]]:
    good = protocol.encode(_frame_message(), "cam0")
    body = msgpack.unpackb(good[5:])
    packed = lambda **changes: b"\0" + msgpack.packb({**body, **changes})  # noqa: E731
    ids = lambda *values: np.array(values, "<i4").tobytes()  # noqa: E731
    points = lambda n: np.arange(2.0 * n).tobytes()  # noqa: E731
    ping = lambda **changes: b"\0" + msgpack.packb({"v": 1, "type": "ping", "camera": "c", "t1": 1.0, **changes})  # noqa: E731
    pong = lambda **changes: b"\0" + msgpack.packb({"v": 1, "type": "pong", "camera": "c", "t1": 1.0, "t2": 1.0,  # noqa: E731
                                                    "t3": 1.0, "node": "n", **changes})
    return {
        "oversized": [b"\0" + bytes(protocol.MAX_MESSAGE_BYTES),
                      b"\0" + msgpack.packb({"v": 1, "type": "ping", "camera": "c", "t1": 1.0, "pad": bytes(70000)})],
        "malformed": [b"no separator", b"\0\xc1", good[:len(good) // 2], good[:-1], b"\0" + msgpack.packb([1, 2])],
        "version": [packed(v=2), b"\0" + msgpack.packb({"type": "frame"})],
        "type": [packed(type="hello"), packed(type=5)],
        "field": [packed(centroids=np.array([[np.nan, 1.0]]).tobytes()), packed(centroids=b"\0" * 15),
                  packed(seq="7"), packed(t=math.inf), packed(image=[4, 4, b"\0" * 15]), packed(camera=None),
                  b"cam9" + good[4:], ping(detect={"min_area": "3"}),
                  # board corners: ids and points that do not pair, repeat, or lie out of range; a spec not text
                  packed(board=[ids(0, 1), points(3)]), packed(board=[ids(2, 2), points(2)]),
                  packed(board=[ids(-1), points(1)]), packed(board=[ids(protocol.MAX_BOARD_CORNERS), points(1)]),
                  packed(board=[ids(0)[:3], points(1)]), packed(board=[ids(0), np.array([[np.nan, 1.0]]).tobytes()]),
                  packed(board=ids(0)), ping(board=7), pong(size=[640]), pong(size=[-1, 480]), pong(size="640x480")],
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

def test_a_skewed_drifting_node_clock_is_estimated_and_its_frames_arrive_in_host_time(paced):
    (source,) = _node_sources([paced.node_url("cam0", "&ping_ms=20")])
    errors = []

    def estimated_well() -> bool:  # converges within seconds (the busier the machine, the longer)
        frame = source.read(timeout=HANG_S)
        assert frame is not None and frame.centroids is not None and frame.image.size == 0
        errors.append(frame.t_capture - (paced.t0 + frame.seq / 30.0))  # the rig's own capture time of that frame
        now = time.monotonic()
        return (len(errors) > 60 and abs(source.estimator.estimate.offset_at(now) - paced.true_offset(now)) < 0.2e-3
                and np.abs(errors[-30:]).max() < 0.2e-3)

    with source:
        _until(estimated_well, what="the node's clock estimated within 0.2 ms")
        now = time.monotonic()
        status = source.status_text()
    shown = float(status.split("offset ")[1].split(" ms")[0])
    assert status.startswith(f"node {paced.a.name} offset") and "jitter" in status
    assert shown == pytest.approx(1e3 * paced.true_offset(now), abs=0.2)


def test_the_status_line_shows_each_node_and_a_node_killed_mid_take_is_reported_and_rejoins(paced):
    sources = _node_sources([paced.node_url(f"cam{c}", "&dead_after_s=0.5") for c in range(5)])
    frames = []
    with _pipeline(sources, paced.markers, frames) as pipeline:
        _until(lambda: len(frames) >= 15, what="solving")

        def estimated() -> bool:  # early estimates on a busy machine can be a ms off: the line shows the estimate
            now = time.monotonic()
            return all(abs(sources[c].estimator.estimate.offset_at(now) - paced.true_offset(now)) < 0.5e-3
                       for c in (0, 1))

        _until(estimated, what="the node's clock estimated within 0.5 ms")
        line = pipeline.status_line()
        for camera in ("cam0", "cam1"):
            shown = float(line.split(f"{camera} node {paced.a.name} offset ")[1].split(" ms")[0])
            assert shown == pytest.approx(1e3 * paced.true_offset(time.monotonic()), abs=1.0), line
        assert f"cam4 node {paced.c.name} offset " in line and line.count("jitter") == 5, line
        paced.c.kill()
        _until(lambda: "cam4" in pipeline.front.capture.sync.dead, what="cam4 reported dead")
        count = len(frames)
        _until(lambda: len(frames) >= count + 15, what="solving without cam4")
        assert all(f.n_cameras <= 4 for f in frames[count + 5:])
        assert any("lost" in event for event in sources[4].events)
        line = pipeline.status_line()
        assert "cameras 4/5 (dead: cam4)" in line and f"cam4 node {paced.c.name} lost" in line, line
        paced.c.start()  # the same port: the host reconnects by itself
        _until(lambda: frames[-1].n_cameras == 5, what="cam4 back")
        _until(lambda: "cam4" not in pipeline.front.capture.sync.dead, what="cam4 alive")
    assert pipeline.error is None


def test_a_node_camera_is_read_as_paced_as_it_is_and_a_url_saying_otherwise_is_reported(paced):
    (adopted,) = _node_sources([paced.node_url("cam2")])
    (contrary,) = _node_sources([paced.node_url("cam3", "&realtime=0")])
    with adopted, contrary:
        assert adopted.realtime and adopted.capabilities.fps == 30.0 and not adopted.capabilities.images
        assert adopted.read(timeout=HANG_S) is not None
        _until(lambda: contrary.read(timeout=0.1) is None and contrary.ended, what="the contrary URL reported")
    assert "cam3 on node" in contrary.error and "is paced but its URL says realtime=0" in contrary.error


def test_malformed_truncated_oversized_messages_and_a_flood_are_counted_and_dropped(paced):
    relay = _HostileRelay(paced.a.port)
    sources = _node_sources([f"node://127.0.0.1:{relay.port}?camera=cam0", paced.node_url("cam1"),
                             paced.node_url("cam2")])
    frames = []
    try:
        with _pipeline(sources, paced.markers, frames) as pipeline:
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


def test_with_a_shared_key_only_hosts_holding_it_get_frames_and_the_node_keeps_serving(rig_url, tmp_path):
    from livebridge.devices.registry import open_cameras
    from livebridge.nodes.node import CameraNode

    key, other = tmp_path / "rig.key", tmp_path / "other.key"
    key.write_bytes(np.random.default_rng(1).bytes(32))
    other.write_bytes(np.random.default_rng(2).bytes(32))
    small = rig_url.replace("size=640x400", "size=320x200") + "&cameras=1"
    with CameraNode(open_cameras(small), key=_shared_key(key)) as node:
        url = f"node://127.0.0.1:{node.port}?camera=cam0&dead_after_s=0.3"
        for options, admitted in (("", False), (f"&key={other}", False), (f"&key={key}", True)):
            (source,) = _node_sources([url + options])
            with source:
                frame = source.read(timeout=HANG_S if admitted else 1.5)
                assert (frame is not None) == admitted and source.alive == admitted, options
                if admitted:
                    assert frame.centroids is not None and len(frame.centroids) > 10
        assert node.sent > 0 and node.drops.total == 0  # refused at the handshake: nothing reached the node


def _shared_key(path):
    from livebridge.nodes.keys import SharedKey

    return SharedKey.load(path)


@pytest.mark.parametrize("content, says", [(None, "cannot read the key file"), (b"x" * 31, "at least 32 bytes")])
def test_a_missing_or_short_key_file_is_an_input_error_naming_it(tmp_path, content, says):
    from livebridge.errors import InputError

    path = tmp_path / "rig.key"
    if content is not None:
        path.write_bytes(content)
    for load in (lambda: _shared_key(path), lambda: _node_sources([f"node://127.0.0.1:7000?camera=c&key={path}"])):
        with pytest.raises(InputError) as caught:
            load()
        assert caught.value.path == str(path) and says in caught.value.message


def _session(folder: Path, urls, markers: str, extra: str = "") -> Path:
    path = folder / "session.toml"
    quoted = ", ".join(f'"{url}"' for url in urls)
    path.write_text(f'[cameras]\nurls = [{quoted}]\n[face]\nmarkers = "{markers}"\n'
                    '[outputs.render]\nenabled = false\n' + extra)
    return path


@pytest.mark.parametrize("layout, local", [([[0, 1], [2]], [3]),
                                           pytest.param([[c] for c in range(8)], [], marks=pytest.mark.slow)],
                         ids=["2 nodes and a local camera", "8 nodes"])
def test_a_session_mixing_node_and_local_cameras_records_the_take_of_the_same_rig_in_one_process(nodes, rig_url,
                                                                                                 tmp_path, layout,
                                                                                                 local):
    """``livebridge run`` with node processes (``layout``: camera indices per node) and local cameras
    (unpaced, no calibration file: each camera's own): the take recorded equals the one of the same rig in one
    process, number for number."""
    from click.testing import CliRunner

    from livebridge.cli import main
    from livebridge.take.directory import load_take_dir

    markers = rig_url.partition("markers=")[2]
    n_cameras = sum(map(len, layout)) + len(local)
    rig = f"{rig_url.partition('&markers=')[0]}&lead_in_s=0.5&cameras={n_cameras}&realtime=0&frames=40&t0=1000"
    served = nodes(*[([f"{rig}&camera={c}&markers={markers}" for c in cameras], {}) for cameras in layout])
    remote = [f"node://127.0.0.1:{node.port}?camera=cam{c}" for node, cameras in zip(served, layout) for c in cameras]
    layouts = {"process": [rig], "nodes": [*remote, *[f"{rig}&camera={c}" for c in local]]}
    takes = {}
    for kind, urls in layouts.items():
        folder = tmp_path / kind
        folder.mkdir()
        session = _session(folder, urls, markers, '[recording]\nenabled = true\ndirectory = "takes"\n')
        result = CliRunner().invoke(main, ["run", str(session), "--frames", "25"])
        assert result.exit_code == 0, result.output
        (take,) = (folder / "takes").iterdir()
        takes[kind] = load_take_dir(take)
    alone, remote = takes["process"], takes["nodes"]
    n = min(len(alone.seq), len(remote.seq))  # --frames 25: a frame or two more may be on their way at the stop
    assert n >= 25 and np.array_equal(alone.seq[:n], remote.seq[:n])
    assert np.array_equal(alone.contractions[:n], remote.contractions[:n])
    assert alone.contractions[:n].max() > 0.01  # the face moved: past the neutral lead-in
    assert np.array_equal(alone.markers[:n], remote.markers[:n], equal_nan=True)  # the same labels in the same places


def test_recording_raw_frames_from_a_centroid_only_node_is_refused_before_anything_starts(paced, tmp_path):
    from click.testing import CliRunner

    from livebridge.cli import main

    urls = [paced.node_url(f"cam{c}") for c in range(3)]
    session = _session(tmp_path, urls, paced.markers,
                       '[recording]\nenabled = true\ndirectory = "takes"\nraw_frames = true\n')
    result = CliRunner().invoke(main, ["run", str(session)])
    assert result.exit_code == 1 and not (tmp_path / "takes").exists(), result.output
    assert "recording.raw_frames" in result.output and "cam0, cam1, cam2 send only their markers' centroids" \
        in result.output and "images=full" in result.output
    talking = [t.name for t in threading.enumerate() if t.name.startswith("node 127.0.0.1:")]
    assert not talking, f"the refused session left its node sources running: {talking}"


def test_a_node_that_cannot_bind_its_port_destroys_what_it_opened():
    from livebridge.devices.registry import open_cameras
    from livebridge.nodes.node import CameraNode

    url = "sim://rig?cameras=1&size=160x100"
    with CameraNode(open_cameras(url)) as first:
        second = CameraNode(open_cameras(url), f"tcp://127.0.0.1:{first.port}")
        with pytest.raises(zmq.ZMQError):
            second.start()
        assert second._context is None and not second._threads  # nothing left for the collector to term


BOARD = "chessboard:7x7:55"
BOARD_RIG = f"sim://rig?board={BOARD}&cameras=2&seed=4&views=8&size=640x480"


def test_a_node_asked_for_a_board_sends_the_corners_the_host_would_find_and_no_image_nor_centroids():
    from livebridge.calibration.boards import parse_board
    from livebridge.calibration.detect import detect_board
    from livebridge.devices.registry import open_cameras
    from livebridge.nodes.node import CameraNode
    from livebridge.nodes.source import NodeSource

    board = parse_board(BOARD)
    local = open_cameras(f"{BOARD_RIG}&camera=1")[0]
    with CameraNode(open_cameras(f"{BOARD_RIG}&camera=1")) as node, local:
        remote = NodeSource("127.0.0.1", node.port, "cam1", dead_after_s=HANG_S)
        remote.detect_board_with(board)
        remote.start()
        try:
            found = 0
            for _ in range(4):
                frame, truth = remote.read(HANG_S), local.read(HANG_S)
                assert frame.image.size == 0 and frame.centroids is None
                assert np.array_equal(frame.board_corners, detect_board(board, truth.image), equal_nan=True)
                found += np.isfinite(frame.board_corners[:, 0]).sum()
            assert found >= board.n_corners and remote.capabilities.size == (640, 480)
        finally:
            remote.stop()
        assert node.cpu_detect_s == 0.0  # no marker detection for a host that asked for the board


def test_calibrate_run_with_node_sources_detects_the_board_on_the_nodes_as_the_host_does(nodes, tmp_path):
    """``calibrate run --sources node://...`` without images: the nodes detect the board; the calibration
    equals the one from the same cameras read in this process (the host detecting), and finds the rig."""
    from click.testing import CliRunner

    from livebridge.calibration.calibfile import load_calibration
    from livebridge.cli import main
    from livebridge.simulators.board_render import example_rig

    (node,) = nodes(([f"{BOARD_RIG}&camera=0", f"{BOARD_RIG}&camera=1"], {}))

    def calibrate(out: Path, urls) -> list:
        args = ["calibrate", "run", "--board", BOARD, "--out", str(out), "--quiet", "--frames", "8", "--every", "1"]
        for name, url in zip(("left", "right"), urls):
            args += ["--sources", f"{name}={url}"]
        result = CliRunner().invoke(main, args)
        assert result.exit_code == 0, result.output
        return load_calibration(out).cameras

    on_host = calibrate(tmp_path / "host.toml", [f"{BOARD_RIG}&camera={c}" for c in (0, 1)])
    on_nodes = calibrate(tmp_path / "nodes.toml", [f"node://127.0.0.1:{node.port}?camera=cam{c}" for c in (0, 1)])
    for camera, reference in zip(on_nodes, on_host):
        for field in ("matrix", "distortions", "rotation", "translation", "size"):
            assert np.array_equal(getattr(camera, field), getattr(reference, field)), (camera.name, field)
    truth = example_rig(2, size=(640, 480), seed=4)
    baseline = np.linalg.norm(on_nodes[1].center - on_nodes[0].center)
    assert abs(baseline - np.linalg.norm(truth.cameras[1].center - truth.cameras[0].center)) < 2.0
    for camera, true_camera in zip(on_nodes, truth.cameras):
        focal, true_focal = camera.matrix[[0, 1], [0, 1]], true_camera.matrix[[0, 1], [0, 1]]
        assert np.all(np.abs(focal / true_focal - 1) < 0.01), (camera.name, focal, true_focal)


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
