"""A camera node: local cameras, detection on the node, centroids streamed to the host over ZeroMQ.

The node binds two sockets on one address (127.0.0.1 unless another is given): a PUB on ``PORT`` that
publishes each paced camera's frames on the camera's topic, and a ROUTER on ``PORT + 1`` that answers the
host's pings (heartbeat, clock probe and subscription settings in one message), sends unpaced cameras'
frames on request and reports cameras that ended. The node binds and the host connects, so either side
may restart while the other runs: ZeroMQ reconnects, and every setting a host asked for is soft state
renewed by its pings (it lapses :data:`SETTINGS_TTL_S` after the last one).

Newest wins on every link: the PUB keeps at most :data:`SEND_HWM` frames per host connection (a host
that falls behind loses frames, never gets a queue), and the host's subscription keeps only the newest
frame per camera (``CONFLATE``). One thread owns the sockets; each camera's reader thread detects and
hands its encoded frames over an ``inproc`` socket of its own.
"""

from __future__ import annotations

import dataclasses
import math
import queue
import threading
import time
from dataclasses import dataclass

import numpy as np

from livebridge.nodes import protocol
from livebridge.nodes.protocol import FrameMessage, Grab, Ping, Pong, ProtocolError

SEND_HWM = 8
SETTINGS_TTL_S = 2.0
THUMBNAIL_SCALE = 4
POLL_MS = 20


class NodeClock:
    """The node's clock: ``time.monotonic`` (what its camera sources stamp frames with), NTP-estimated by the
    host. A subclass for a PTP-disciplined or hardware clock sets ``time_source`` so the host trusts it."""

    time_source = "ntp"

    def now(self) -> float:
        return self.from_monotonic(time.monotonic())

    def from_monotonic(self, t: float) -> float:
        """Node time of a ``time.monotonic`` time (a frame's ``t_capture``)."""
        return t


@dataclass(frozen=True)
class SkewedClock(NodeClock):
    """A node clock ``offset_s`` ahead of ``time.monotonic`` at ``t_ref`` and running ``drift`` fast (50 ppm:
    5e-5): a PC whose clock nobody synchronised (tests and the benchmark inject it)."""

    offset_s: float = 0.0
    drift: float = 0.0
    t_ref: float = 0.0

    def from_monotonic(self, t: float) -> float:
        return t + self.offset_s + self.drift * (t - self.t_ref)

    def offset_at(self, t: float) -> float:
        """Node minus ``time.monotonic`` seconds at monotonic time ``t`` (the truth the host estimates)."""
        return self.offset_s + self.drift * (t - self.t_ref)


@dataclass
class _Settings:
    """What the hosts asked of one camera, renewed by their pings."""

    images: str = "none"
    images_until: float = -math.inf
    detect: object = None
    board: object = None  # a calibration Board: detected instead of the markers while asked for
    board_until: float = -math.inf

    def board_now(self):
        """The board asked for, None when none is (or the ask lapsed)."""
        return self.board if time.monotonic() <= self.board_until else None


class CameraNode:
    """Serve local camera sources to hosts.

    Parameters
    ----------
    sources : list of CameraSource
        Not started (the node starts and stops them). Camera ids must be unique.
    address : str
        ``tcp://HOST:PORT``; frames on ``PORT``, control on ``PORT + 1``. ``PORT`` 0: a free pair.
    key : SharedKey, optional
        CURVE encryption and authentication (:mod:`livebridge.nodes.keys`).
    clock : NodeClock
    name : str
        How the host names this node in its status line.
    log : callable, optional
    """

    def __init__(self, sources, address: str = "tcp://127.0.0.1:0", key=None, clock: NodeClock | None = None,
                 name: str = "node", log=None):
        from livebridge.nodes import require

        self.zmq, _ = require()
        self.sources = {s.source_id: s for s in sources}
        if len(self.sources) != len(sources):
            raise ValueError("camera ids on one node must be unique")
        self.address, self.key, self.name = address, key, name
        self.clock = clock or NodeClock()
        self.log = log or (lambda message: None)
        self.drops = protocol.DropCounter()
        self.ended: dict[str, str] = {}
        self.sent = 0
        self.cpu_detect_s = 0.0
        self._settings = {camera: _Settings() for camera in self.sources}
        self._grabs = {camera: queue.Queue() for camera in self.sources}
        self._running = threading.Event()
        self._threads: list[threading.Thread] = []
        self._context = None
        self._auth = None
        self.port: int | None = None

    # ------------------------------------------------------------------------------------ lifecycle
    def start(self) -> CameraNode:
        """Bind, start the cameras and the threads; :attr:`port` is the frame port afterwards."""
        from livebridge.reconstruct.detect import detect_blobs

        zmq = self.zmq
        image = np.zeros((16, 16), np.uint8)
        image[6:9, 6:9] = 255
        image.setflags(write=False)  # frames are read-only, and compiled code tells them apart
        detect_blobs(image)  # load the compiled detector before the cameras run
        self._context = zmq.Context()
        try:
            self._open(zmq)
        except BaseException:
            self.stop()  # a half-started node must not leave its context to the collector (its term can hang)
            raise
        self.log(f"node {self.name}: {len(self.sources)} camera(s) ({', '.join(self.sources)}) on "
                 f"{self.address.rpartition(':')[0]}:{self.port} (control {self.port + 1})")
        return self

    def _open(self, zmq) -> None:
        """Bind the sockets, start the cameras and the threads."""
        if self.key is not None:
            self._auth = self.key.authenticator(self._context)
        self._pub, self._router = self._context.socket(zmq.PUB), self._context.socket(zmq.ROUTER)
        for socket in (self._pub, self._router):
            socket.linger = 0
            socket.sndhwm = SEND_HWM
            if self.key is not None:
                self.key.serve(socket)
        self._router.rcvhwm = 64
        self._router.maxmsgsize = protocol.MAX_CONTROL_BYTES * 4
        self.port = _bind_pair(zmq, self._pub, self._router, self.address)
        self._inbox = self._context.socket(zmq.PULL)
        self._inbox.bind(f"inproc://node-{id(self)}")
        self._running.set()
        for source in self.sources.values():
            source.start()
        # what every pong tells about each camera (asked once: a driver may query its device for it)
        self._described = {camera: (_camera_fields(source), float(source.capabilities.fps),
                                    _size(source.capabilities.size)) for camera, source in self.sources.items()}
        self._spawn(self._serve, "node control")
        for camera, source in self.sources.items():
            self._spawn(self._stream if source.realtime else self._on_request, f"node {camera}", camera)

    def stop(self) -> None:
        self._running.clear()
        for thread in self._threads:
            thread.join(timeout=5)
        self._threads.clear()
        for source in self.sources.values():
            source.stop()
        if self._auth is not None:
            self._auth.stop()
            self._auth = None
        if self._context is not None:
            self._context.destroy(linger=0)
            self._context = None

    def __enter__(self) -> CameraNode:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _spawn(self, target, name: str, *args) -> None:
        thread = threading.Thread(target=target, args=args, name=name, daemon=True)
        thread.start()
        self._threads.append(thread)

    # ------------------------------------------------------------------------------------ control thread
    def _serve(self) -> None:
        zmq = self.zmq
        poller = zmq.Poller()
        poller.register(self._router, zmq.POLLIN)
        poller.register(self._inbox, zmq.POLLIN)
        while self._running.is_set():
            ready = dict(poller.poll(POLL_MS))
            if self._router in ready:
                self._drain_router()
            if self._inbox in ready:
                self._drain_inbox()

    def _drain_router(self) -> None:
        zmq = self.zmq
        while True:
            try:
                parts = self._router.recv_multipart(zmq.NOBLOCK, copy=True)
            except zmq.Again:
                return
            t2 = self.clock.now()
            if len(parts) != 2:
                self.drops.add("malformed")
                continue
            identity, data = parts
            try:
                message = protocol.decode(data)
            except ProtocolError as error:
                self.drops.add(error.reason)
                continue
            if isinstance(message, Ping):
                self._answer_ping(identity, message, t2)
            elif isinstance(message, Grab) and message.camera in self._grabs:
                self._grabs[message.camera].put((identity, message.index))
            else:
                self.drops.add("type")

    def _answer_ping(self, identity: bytes, ping: Ping, t2: float) -> None:
        source = self.sources.get(ping.camera)
        if source is None:
            ended = f"no camera {ping.camera!r} on node {self.name} (it has: {', '.join(self.sources)})"
            realtime, calibration, fps, size = True, None, math.nan, None
        else:
            self._renew(ping)
            calibration, fps, size = self._described[ping.camera]
            ended, realtime = self.ended.get(ping.camera), source.realtime
        pong = Pong(ping.camera, ping.t1, t2, self.clock.now(), self.name, self.clock.time_source, ended, realtime,
                    calibration, fps, size)
        self._send_router(identity, protocol.encode(pong))

    def _renew(self, ping: Ping) -> None:
        from livebridge.reconstruct.detect import DetectConfig

        settings = self._settings[ping.camera]
        now = time.monotonic()
        if ping.images != "none" or now > settings.images_until:
            settings.images = ping.images
        if ping.images != "none":
            settings.images_until = now + SETTINGS_TTL_S
        if ping.board is not None:
            self._renew_board(settings, ping.board, now)
        if ping.detect is not None:
            try:
                detect = DetectConfig(**ping.detect)
            except (TypeError, ValueError):
                self.drops.add("field")
                return
            if detect != settings.detect:
                settings.detect = detect

    def _renew_board(self, settings: _Settings, spec: str, now: float) -> None:
        from livebridge.calibration.boards import parse_board
        from livebridge.errors import InputError

        if settings.board is None or settings.board.spec != spec:
            try:
                settings.board = parse_board(spec)
            except InputError:
                self.drops.add("field")
                return
        settings.board_until = now + SETTINGS_TTL_S

    def _send_router(self, identity: bytes, data: bytes) -> None:
        try:
            self._router.send_multipart([identity, data], self.zmq.NOBLOCK)
        except self.zmq.ZMQError:  # that host is gone or slow: its frames are dropped, newest wins
            pass

    def _drain_inbox(self) -> None:
        zmq = self.zmq
        while True:
            try:
                route, data = self._inbox.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return
            if route:
                self._send_router(route, data)
            else:
                try:
                    self._pub.send(data, zmq.NOBLOCK)
                except zmq.Again:
                    pass
            self.sent += 1

    # ------------------------------------------------------------------------------------ camera threads
    def _outbox(self):
        socket = self._context.socket(self.zmq.PUSH)
        socket.linger = 0
        socket.connect(f"inproc://node-{id(self)}")
        return socket

    def _stream(self, camera: str) -> None:
        """A paced camera: publish every frame it delivers."""
        source, outbox = self.sources[camera], self._outbox()
        try:
            while self._running.is_set():
                frame = self._read(camera, source)
                if frame is not None:
                    outbox.send_multipart([b"", protocol.encode(self._message(camera, frame, -1), camera)])
        finally:
            outbox.close()

    def _on_request(self, camera: str) -> None:
        """An unpaced camera: frame ``index`` when a host asks for it (the same frame when asked again)."""
        source, outbox, grabs = self.sources[camera], self._outbox(), self._grabs[camera]
        last_index, last_data = -1, None
        try:
            while self._running.is_set():
                try:
                    identity, index = grabs.get(timeout=0.05)
                except queue.Empty:
                    continue
                if index != last_index or last_data is None:
                    frame = None
                    while frame is None and self._running.is_set() and camera not in self.ended:
                        frame = self._read(camera, source)
                    if frame is None:
                        continue
                    last_index, last_data = index, protocol.encode(self._message(camera, frame, index))
                outbox.send_multipart([identity, last_data])
        finally:
            outbox.close()

    def _read(self, camera: str, source):
        frame = source.read(timeout=0.1)
        if frame is None and source.ended and camera not in self.ended:
            self.ended[camera] = source.error or ""
            self.log(f"camera {camera} ended" + (f": {source.error}" if source.error else ""))
        return frame

    def _message(self, camera: str, frame, index: int) -> FrameMessage:
        from livebridge.reconstruct.detect import DetectConfig, detect_blobs

        settings = self._settings[camera]
        board = settings.board_now()
        centroids = board_ids = board_points = None
        if board is not None:  # calibration: the board, and no markers (their detection would only cost time)
            board_ids, board_points = _board_corners(board, frame.image)
        else:
            cpu = time.thread_time()
            centroids = detect_blobs(frame.image, settings.detect or DetectConfig())
            self.cpu_detect_s += time.thread_time() - cpu
        source = self.sources[camera]
        # a paced camera's time is a clock reading (the host maps it to its own); an unpaced one's is its take's
        t = self.clock.from_monotonic(frame.t_capture) if source.realtime else frame.t_capture
        return FrameMessage(camera, frame.seq, t, centroids,
                            frame.exposure_us, frame.gain, frame.sync_domain, index, self.clock.now(),
                            _image(frame.image, settings), board_ids, board_points)


def _board_corners(board, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The board corners found in ``image`` by the host's own detector: ids (m,) and pixels (m, 2)."""
    from livebridge.calibration.detect import detect_board

    corners = detect_board(board, image)
    ids = np.flatnonzero(np.isfinite(corners[:, 0]))
    return ids, corners[ids]


def _size(size) -> tuple[int, int] | None:
    """A camera's ``(width, height)``; None when unknown."""
    width, height = (int(v) for v in size)
    return (width, height) if width > 0 and height > 0 else None


def _image(image: np.ndarray, settings: _Settings) -> np.ndarray | None:
    """The image the hosts asked for: None, a thumbnail (1/4 size) or the full frame."""
    if settings.images == "none" or time.monotonic() > settings.images_until:
        return None
    if settings.images == "full":
        return image
    import cv2

    height, width = image.shape
    return cv2.resize(image, (max(1, width // THUMBNAIL_SCALE), max(1, height // THUMBNAIL_SCALE)),
                      interpolation=cv2.INTER_AREA)


def _camera_fields(source) -> dict | None:
    """The source's calibration as plain msgpack-able fields (None when it has none)."""
    camera = source.calibration
    if camera is None:
        return None
    fields = dataclasses.asdict(camera)
    return {key: np.asarray(value).tolist() if isinstance(value, np.ndarray | tuple) else value
            for key, value in fields.items()}


def _bind_pair(zmq, pub, router, address: str) -> int:
    """Bind ``pub`` to ``address``'s port and ``router`` to the next one; port 0: the first free pair."""
    host, _, port_text = address.rpartition(":")
    port = int(port_text)
    for _ in range(50 if port == 0 else 1):
        chosen = pub.bind_to_random_port(host, 20000, 60000) if port == 0 else (pub.bind(address), port)[1]
        try:
            router.bind(f"{host}:{chosen + 1}")
            return chosen
        except zmq.ZMQError:
            pub.unbind(f"{host}:{chosen}")
            if port != 0:
                raise
    raise OSError(f"no free pair of ports on {host}")
