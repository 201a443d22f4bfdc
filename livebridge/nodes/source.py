"""The host side of a camera node: ``node://HOST:PORT?camera=ID``, one camera source per remote camera.

A :class:`NodeSource` connects to a node (:mod:`livebridge.nodes.node`), subscribes to one camera and
delivers its frames with their centroids already detected (``Frame.centroids``; no pixels unless asked),
stamped in host time by the node's clock estimate (:mod:`livebridge.nodes.clock`; an unpaced camera's frames
keep their own take time). It is an ordinary :class:`~livebridge.capture.sources.CameraSource`, so
synchronisation, reconstruction, solve and outputs do not know the camera is remote, and remote and local
cameras mix in one session.

One I/O thread owns the two sockets: a SUB (``CONFLATE``: only the newest frame is kept) and a DEALER that
pings the node every ``ping_ms`` (heartbeat, clock exchange, and the settings: images wanted, detection
parameters). A node that stops answering for ``dead_after_s`` is reported (:attr:`NodeSource.events`,
:meth:`NodeSource.status_text`) and the source just delivers nothing, so the synchroniser marks the camera
dead and the rest of the rig goes on; when the node comes back (restarted or reachable again) ZeroMQ
reconnects and its frames flow again, without restarting the host. Messages that are malformed,
truncated, oversized or forged are counted by reason (:attr:`NodeSource.drops`) and dropped.

URL parameters: ``camera`` (required: the camera's id on the node), ``realtime`` (default: as the node's
camera is; 0 for a node's unpaced camera, e.g. ``sim://rig?realtime=0``: frames are then fetched one by one,
none is lost; a URL that says otherwise than the node is reported and delivers nothing),
``images`` (``none``, ``thumbnail``, ``full``: pixels sent along; calibration does not need them: it asks
the node to detect the board, :meth:`NodeSource.detect_board_with`),
``key`` (a shared key file: CURVE), ``dead_after_s``, ``ping_ms``.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import asdict

import numpy as np

from livebridge.capture.frame import Frame
from livebridge.capture.queue import NewestQueue
from livebridge.capture.sources import Capabilities, ExposureSetting, SourceBase
from livebridge.devices.url import DeviceURL
from livebridge.errors import InputError
from livebridge.nodes import protocol, require
from livebridge.nodes.clock import ClockEstimator
from livebridge.nodes.protocol import FrameMessage, Grab, Ping, Pong, ProtocolError

_URL_KEYS = {"camera", "realtime", "images", "key", "dead_after_s", "ping_ms"}
_NO_PIXELS = np.zeros((0, 0), np.uint8)
_REGRAB_S = 0.25  # an unpaced frame asked for and not come: ask again (the node may have restarted)


class NodeSource(SourceBase):
    """One remote camera of a camera node.

    Parameters
    ----------
    host : str
        The node's address (name or IP).
    port : int
        Its frame port (control on ``port + 1``).
    camera : str
        The camera's id on the node; also this source's ``source_id``.
    realtime : bool or None
        False for an unpaced camera on the node: every frame is fetched on request. None: as the node's
        camera is (asked when first needed, waiting up to ``dead_after_s`` for the node).
    images : {"none", "thumbnail", "full"}
    key : SharedKey, optional
    dead_after_s : float
        Seconds without a reply before the node is reported lost.
    ping_ms : float
        Ping interval (heartbeat and clock exchange).
    clock : callable
        The host's monotonic seconds.
    """

    def __init__(self, host: str, port: int, camera: str, realtime: bool | None = None, images: str = "none", key=None,
                 dead_after_s: float = 1.0, ping_ms: float = 100.0, clock=time.monotonic):
        self.zmq, _ = require()
        self.host, self.port, self.camera = host, int(port), camera
        self.source_id = camera
        self._realtime = None if realtime is None else bool(realtime)
        self.images, self.key = images, key
        self.dead_after_s, self.ping_s = float(dead_after_s), float(ping_ms) / 1000
        self.clock = clock
        self.estimator = ClockEstimator()
        self.drops = protocol.DropCounter()
        self.events: list[str] = []
        self.frames = 0
        self.transport_s: list[float] = []  # node send -> host receipt of each frame, host seconds (bounded)
        self._detect: dict | None = None
        self._board = None
        self._size: tuple[int, int] | None = None
        self._queue: NewestQueue[Frame] = NewestQueue(1)
        self._running = threading.Event()
        self._thread: threading.Thread | None = None
        self._stopped = False
        self._last_reply = -math.inf
        self._alive = False
        self._node_name = ""
        self._time_source = "ntp"
        self._calibration = None
        self._node_realtime: bool | None = None
        self._fps = math.nan
        self._ended_on_node: str | None = None
        self._want_index = -1
        self._asked_at = -math.inf
        self._index_lock = threading.Lock()

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    # ------------------------------------------------------------------------------------ CameraSource
    def start(self) -> None:
        if self._thread is not None:
            return
        self._running.set()
        self._thread = threading.Thread(target=self._run, name=f"node {self.address} {self.camera}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stopped = True
        self._running.clear()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        self._end(None)

    def read(self, timeout: float | None = None) -> Frame | None:
        if not self.realtime:
            with self._index_lock:
                if self._want_index < self.frames:
                    self._want_index, self._asked_at = self.frames, -math.inf
        frame = self._queue.get(timeout)
        if frame is None:
            if self._ended_on_node is not None and not self._ended:
                self._end(self._ended_on_node or None)
            return None
        self.frames += 1
        return frame

    def detect_with(self, config) -> None:
        """Detect on the node with the host's parameters (:class:`~livebridge.reconstruct.detect.DetectConfig`)."""
        self._detect = asdict(config)

    def detect_board_with(self, board) -> None:
        """Detect a calibration board (:class:`~livebridge.calibration.boards.Board`) on the node, with the
        host's own detector: frames then carry its corners (``Frame.board_corners``) and no centroids."""
        self._board = board

    def set_exposure(self, manual: bool, exposure_us: float | None = None,
                     gain: float | None = None) -> ExposureSetting:
        return ExposureSetting(False)  # set on the node's own cameras (their URLs)

    @property
    def realtime(self) -> bool:
        """Paced (frames as the node's camera takes them) or unpaced (fetched one by one); fixed on first use:
        the URL's ``realtime``, else the node's camera's (waits up to ``dead_after_s`` for the node), else
        paced."""
        if self._realtime is None:
            self._await_node()
            self._realtime = self._node_realtime if self._node_realtime is not None else True
        return self._realtime

    @property
    def capabilities(self) -> Capabilities:
        """The node camera's image size and frame rate (NaN until the node answered); ``images`` only with
        ``images=full`` (otherwise frames carry centroids, and no pixels or a thumbnail)."""
        camera = self.calibration
        size = camera.size if camera is not None else self._size or (0, 0)
        return Capabilities(size=tuple(int(v) for v in size), fps=self._fps,
                            images=self.images == "full")

    @property
    def calibration(self):
        """The camera as the node knows it (a simulated rig's, a factory calibration), once the node answered
        (waits up to ``dead_after_s`` for it); None when unknown."""
        self._await_node()
        return self._calibration

    def _await_node(self) -> None:
        """Start (if not yet) and wait up to ``dead_after_s`` for the node's first answer."""
        if self._thread is None and not self._stopped:
            self.start()
        deadline = time.monotonic() + self.dead_after_s
        while not self._alive and time.monotonic() < deadline:
            time.sleep(0.01)

    # ------------------------------------------------------------------------------------ reporting
    @property
    def alive(self) -> bool:
        """The node answered within ``dead_after_s``."""
        return self._alive

    def status_text(self) -> str:
        """``node NAME offset +37.012 ms jitter 0.021 ms rtt 0.15 ms`` (``NAME``: the node's ``--name``, by
        default its address; ``HOST:PORT`` before it answered), ``... ptp time, trusted ...`` for a node
        whose clock is synchronised, ``node NAME lost`` while it does not answer."""
        estimate = self.estimator.estimate
        name = f"node {self._node_name or self.address}"
        if not self._alive:
            return f"{name} lost"
        if estimate.trusted:
            clock = f"{self._time_source} time, trusted"
        else:
            clock = f"offset {estimate.offset_at(self.clock()) * 1e3:+.3f} ms jitter {estimate.jitter * 1e3:.3f} ms"
        dropped = f" dropped {self.drops.total}" if self.drops.total else ""
        return f"{name} {clock} rtt {estimate.rtt * 1e3:.2f} ms{dropped}"

    # ------------------------------------------------------------------------------------ I/O thread
    def _sockets(self, context):
        zmq = self.zmq
        sub, dealer = context.socket(zmq.SUB), context.socket(zmq.DEALER)
        for socket in (sub, dealer):
            socket.linger = 0
            socket.reconnect_ivl, socket.reconnect_ivl_max = 100, 1000
            socket.maxmsgsize = protocol.MAX_MESSAGE_BYTES + 1024
            if self.key is not None:
                self.key.connect(socket)
        sub.conflate = True  # newest wins: only the last frame is kept (set before connect)
        sub.setsockopt(zmq.SUBSCRIBE, self.camera.encode() + b"\0")
        dealer.immediate, dealer.sndhwm, dealer.rcvhwm = True, 4, 64
        sub.connect(f"tcp://{self.host}:{self.port}")
        dealer.connect(f"tcp://{self.host}:{self.port + 1}")
        return sub, dealer

    def _run(self) -> None:
        zmq = self.zmq
        context = zmq.Context()
        try:  # destroyed on every path: a context left to the collector can hang it (its term waits)
            sub, dealer = self._sockets(context)
            poller = zmq.Poller()
            poller.register(sub, zmq.POLLIN)
            poller.register(dealer, zmq.POLLIN)
            next_ping = 0.0
            while self._running.is_set():
                now = self.clock()
                if now >= next_ping:
                    board = None if self._board is None else self._board.spec
                    self._send(dealer, Ping(self.camera, self.clock(), self.images, self._detect, board))
                    next_ping = now + self.ping_s
                self._check_alive(now)
                if self._realtime is False:
                    self._ask(dealer, now)
                timeout = max(0.0, min(next_ping - self.clock(), 0.02))
                for socket, _ in poller.poll(timeout * 1000):
                    self._drain(socket)
        finally:
            context.destroy(linger=0)

    def _send(self, dealer, message) -> None:
        try:
            dealer.send(protocol.encode(message), self.zmq.NOBLOCK)
        except self.zmq.Again:  # not connected (node down): the next ping tries again
            pass

    def _ask(self, dealer, now: float) -> None:
        """Unpaced: ask for the frame ``read`` waits for (again after ``_REGRAB_S``)."""
        with self._index_lock:
            index, asked = self._want_index, self._asked_at
            if index < 0 or index < self.frames or now - asked < _REGRAB_S:
                return
            self._asked_at = now
        self._send(dealer, Grab(self.camera, index))

    def _drain(self, socket) -> None:
        zmq = self.zmq
        while True:
            try:
                data = socket.recv(zmq.NOBLOCK, copy=True)
            except zmq.Again:
                return
            t4 = self.clock()
            try:
                message = protocol.decode(data)
            except ProtocolError as error:
                self.drops.add(error.reason)
                continue
            if isinstance(message, Pong):
                self._pong(message, t4)
            elif isinstance(message, FrameMessage) and message.camera == self.camera:
                self._frame(message, t4)
            else:
                self.drops.add("type")

    def _pong(self, pong: Pong, t4: float) -> None:
        if pong.camera != self.camera:
            self.drops.add("field")
            return
        if pong.node != self._node_name or pong.time_source != self._time_source:
            if self._node_name:
                self.estimator.reset()  # another node, or a restarted one: its clock is not the old one
            self._node_name, self._time_source = pong.node, pong.time_source
        self.estimator.trusted = pong.time_source != "ntp"
        self.estimator.add(pong.t1, pong.t2, pong.t3, t4)
        self._last_reply = t4
        if pong.calibration is not None and self._calibration is None:
            self._calibration = self._camera(pong.calibration)
        self._fps, self._size = pong.fps, pong.size
        if self._node_realtime is None:
            self._node_realtime = pong.realtime
        if self._realtime is not None and pong.realtime != self._realtime and self._ended_on_node is None:
            pacing = "paced" if pong.realtime else "unpaced"
            self._ended_on_node = (f"camera {self.camera} on node {pong.node} is {pacing} but its URL says "
                                   f"realtime={int(self._realtime)}: leave realtime out of the URL")
            self._event(self._ended_on_node)
        if pong.ended is not None and self._ended_on_node is None:
            self._ended_on_node = pong.ended
            if pong.ended:
                self._event(f"node {pong.node} ({self.address}) camera {self.camera}: {pong.ended}")
        if not self._alive:  # last: whoever waits for the node's answer reads what it told from here on
            self._alive = True
            self._event(f"node {pong.node} ({self.address}) camera {self.camera}: connected")

    def _camera(self, fields: dict):
        from livebridge.calibration.cameras import Camera

        try:
            camera = Camera(**fields)
            ok = (camera.matrix.shape == (3, 3) and camera.rotation.shape == (3,)
                  and camera.translation.shape == (3,) and np.isfinite(camera.matrix).all())
        except (TypeError, ValueError):
            ok = False
        if not ok:
            self.drops.add("field")
            return None
        return camera

    def _frame(self, message: FrameMessage, t4: float) -> None:
        estimate = self.estimator.estimate
        if not (estimate.trusted or math.isfinite(estimate.offset)):
            self.drops.add("unsynchronised")  # no clock exchange yet: its time would be meaningless here
            return
        if self._realtime is False and message.index != self._want_index:
            return  # an answer to an earlier request, already delivered
        if math.isfinite(message.t_sent):
            self.transport_s.append(t4 - estimate.to_host(message.t_sent))
            del self.transport_s[:-4096]
        image = _NO_PIXELS if message.image is None else message.image
        # an unpaced camera's times are its take's (a replay, a simulated take), not a clock's: kept as they are
        t = message.t if self._realtime is False else estimate.to_host(message.t)
        board_corners = self._board_corners(message)
        if board_corners is False:
            return
        frame = Frame(image, t, message.seq, self.camera, message.exposure_us,
                      message.gain, message.sync_domain or self.camera, centroids=message.centroids,
                      board_corners=board_corners)
        if self._realtime is False:
            with self._index_lock:
                self._want_index = -1
        self._queue.put(frame)

    def _board_corners(self, message: FrameMessage):
        """The frame's board corners as (n_corners, 2), NaN where not found; None when it carries none (or
        this host asked for no board); False (and counted as a drop) when its ids do not fit the board."""
        if message.board_ids is None or self._board is None:
            return None
        corners = np.full((self._board.n_corners, 2), np.nan)
        if len(message.board_ids) and message.board_ids.max() >= len(corners):
            self.drops.add("field")
            return False
        corners[message.board_ids] = message.board_points
        return corners

    def _check_alive(self, now: float) -> None:
        if self._alive and now - self._last_reply > self.dead_after_s:
            self._alive = False
            self._event(f"node {self._node_name} ({self.address}) camera {self.camera}: lost "
                        f"(no reply for {self.dead_after_s:g} s)")

    def _event(self, text: str) -> None:
        self.events.append(text)
        del self.events[:-100]


def open_url(url: DeviceURL) -> list[NodeSource]:
    """The registry hook: ``node://HOST:PORT?camera=ID&realtime=&images=none&key=FILE&dead_after_s=1&ping_ms=100``."""
    require()
    url.check_known(_URL_KEYS)
    if not url.netloc or url.path not in ("", "/"):
        raise InputError("a node URL is node://HOST:PORT?camera=ID", url.url)
    host, _, port_text = url.netloc.rpartition(":")
    if not host or not port_text.isdigit() or not 1 <= int(port_text) <= 65534:
        raise InputError("a node URL needs HOST:PORT with a port in 1..65534 (control on PORT + 1)", url.url)
    camera = url.query.get("camera", "")
    if not camera or len(camera) > protocol.MAX_TEXT:
        raise InputError("a node URL names its camera: node://HOST:PORT?camera=ID", url.url, "camera")
    images = url.query.get("images", "none")
    if images not in protocol.IMAGE_MODES:
        raise InputError(f"images must be one of {', '.join(protocol.IMAGE_MODES)}, got {images!r}", url.url, "images")
    key = None
    if "key" in url.query:
        from livebridge.nodes.keys import SharedKey

        key = SharedKey.load(url.query["key"])
    return [NodeSource(host.strip("[]"), int(port_text), camera, url.take("realtime", bool, None), images, key,
                       url.take("dead_after_s", float, 1.0, within=(0.05, 60.0)),
                       url.take("ping_ms", float, 100.0, within=(5.0, 5000.0)))]
