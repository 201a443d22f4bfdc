"""The render client: a WebSocket server that also serves the browser page.

One port serves both. Plain HTTP ``GET /`` (and the few files of the
``static`` folder next to this module) returns the page; ``/ws`` upgrades to
a WebSocket that streams the face. Every other path answers 404, and only the
files found in the static folder when the server starts can ever be read, so
no path (``..``, percent-encoding, absolute paths, symlinks added later)
reaches anything else.

Wire protocol (little-endian; every array starts on a 4-byte boundary)
------------------------------------------------------------------------
On connect the server sends two messages:

1. text, JSON ``{"type": "init", "muscles": [names], "regions": [...],
   "markers": [names], "marker_regions": [...], "marker_roles": [...],
   "servos": [names], "n_vertices": V, "n_triangles": T}``;
2. binary *mesh*: ``uint32[4] = (1, V, T, M)``, then ``float32 neutral
   (V, 3)``, ``float32 normals (V, 3)``, ``uint32 triangles (T, 3)``,
   ``float32 elements (M, V, 3)``, ``float32 normal_elements (M, V, 3)``
   (change of the vertex normal when a muscle is fully contracted, so the
   page shades the deformed face without recomputing normals).

Then per published frame (newest wins, see below), binary *frame*:
``uint32[5] = (2, seq, M, n_markers, n_servos)``, ``float32[3] =
(error_upper_mm, error_lower_mm, latency_ms)``, ``float32 contractions
(M,)``, ``float32 markers (n_markers, 3)`` in the model frame (NaN: not
seen), ``float32 servo_targets (n_servos,)`` normalised to [0, 1] between
each servo's limits (NaN: unknown), ``float32 head (4, 4)`` row-major head
model -> world pose (NaN: unknown; the page turns the face by its rotation
and keeps it centred). And now and then a text JSON
``{"type": "status", ...}`` with the runtime's live status line.

A 2D character (:meth:`RenderServer.show_character`) adds its own init text and samples message after the
mesh, and per frame a states message (:meth:`RenderServer.publish_character`, newest wins); their layout is
in :mod:`livebridge.character.live`. The server passes them through as they are.

Only the page itself may connect (cross-site WebSocket hijacking, DNS
rebinding): every request's ``Host`` must name the bound address (for a
loopback bind, any of ``127.0.0.1``, ``localhost``, ``[::1]``; for a
wildcard bind, an IP address or this machine's name), and a WebSocket's
``Origin``, when the client sends one (browsers always do), must be the
page's own origin (``http://`` + that host + the port; loopback names are
equivalent) or one the user listed in ``allowed_origins``. Anything else
answers 403.

A client that stops reading is dropped: every ``ping_interval`` seconds the
server pings each client and closes the connection if the pong (which
follows everything sent before it) does not arrive within ``ping_timeout``.

Slow or vanished clients never slow the publisher: :meth:`RenderServer.publish`
only stores the newest frame and wakes the server's event loop (at most once
until it runs); each client has a one-slot buffer that the newest frame
overwrites, and its own sender task.
"""

from __future__ import annotations

import asyncio
import email.utils
import ipaddress
import json
import re
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass
from http import HTTPStatus
from pathlib import Path

import numpy as np

from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.face.markers import MarkerSet
from livebridge.face.meshio import vertex_normals

STATIC_DIR = Path(__file__).with_name("static")
WS_PATH = "/ws"
_CONTENT_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".png": "image/png",
    ".svg": "image/svg+xml",
    ".ico": "image/x-icon",
}
MESH_KIND = 1
FRAME_KIND = 2
LOOPBACK_NAMES = frozenset({"127.0.0.1", "localhost", "::1"})
WILDCARD_HOSTS = frozenset({"", "0.0.0.0", "::"})
_AUTHORITY = re.compile(r"(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9._-]+)(?::(\d{1,5}))?")
_DEFAULT_PORTS = {"http": 80, "https": 443}


@dataclass(frozen=True, eq=False)
class RenderFrame:
    """One frame for the render client.

    Attributes
    ----------
    seq : int
        Frame-set sequence number.
    t_ref : float
        Monotonic time (s) the frame set was complete; the server measures
        the latency to the moment the frame is handed to a client's socket.
    contractions : ndarray, shape (n_muscles,)
    markers : ndarray, shape (n_markers, 3), optional
        Labelled marker positions in the face model frame, mm; NaN rows unseen.
    region_errors : tuple of float
        RMS marker error of the (upper, lower) face solve, mm.
    servo_targets : ndarray, shape (n_servos,), optional
        Servo targets normalised to [0, 1] between each servo's limits.
    head_pose : ndarray, shape (4, 4), optional
        Head model -> world, where the front measures the head (the phone's head rotation).
    """

    seq: int
    t_ref: float
    contractions: np.ndarray
    markers: np.ndarray | None = None
    region_errors: tuple[float, float] = (float("nan"), float("nan"))
    servo_targets: np.ndarray | None = None
    head_pose: np.ndarray | None = None


def encode_mesh(basis: Basis) -> bytes:
    """The binary mesh message (layout in the module docstring)."""
    neutral_normals = vertex_normals(basis.neutral, basis.triangles)
    contracted = basis.neutral[None] + basis.elements  # (M, V, 3)
    normal_elements = np.stack([vertex_normals(v, basis.triangles) for v in contracted]) - neutral_normals
    header = np.array([MESH_KIND, basis.n_vertices, len(basis.triangles), basis.n_muscles], dtype="<u4")
    parts = [
        header,
        basis.neutral.astype("<f4"),
        neutral_normals.astype("<f4"),
        basis.triangles.astype("<u4"),
        basis.elements.astype("<f4"),
        normal_elements.astype("<f4"),
    ]
    return b"".join(np.ascontiguousarray(p).tobytes() for p in parts)


def encode_frame(frame: RenderFrame, n_markers: int, n_servos: int, latency_ms: float = float("nan")) -> bytes:
    """The binary frame message (layout in the module docstring)."""
    contractions = np.asarray(frame.contractions, dtype="<f4").reshape(-1)
    markers = np.full((n_markers, 3), np.nan, "<f4") if frame.markers is None else \
        np.asarray(frame.markers, dtype="<f4").reshape(n_markers, 3)
    servos = np.full(n_servos, np.nan, "<f4") if frame.servo_targets is None else \
        np.asarray(frame.servo_targets, dtype="<f4").reshape(n_servos)
    head = np.full(16, np.nan, "<f4") if frame.head_pose is None else \
        np.asarray(frame.head_pose, dtype="<f4").reshape(16)
    header = np.array([FRAME_KIND, frame.seq & 0xFFFFFFFF, len(contractions), n_markers, n_servos], dtype="<u4")
    floats = np.array([frame.region_errors[0], frame.region_errors[1], latency_ms], dtype="<f4")
    return b"".join((header.tobytes(), floats.tobytes(), contractions.tobytes(), markers.tobytes(),
                     servos.tobytes(), head.tobytes()))


@dataclass(frozen=True, eq=False)
class FrameMessage:
    """A frame message as a client receives it (:func:`decode_frame`; float32 arrays).

    Attributes
    ----------
    seq : int
        Frame-set sequence number (low 32 bits).
    region_errors : tuple of float
        RMS marker error of the (upper, lower) face solve, mm.
    latency_ms : float
        Frame set complete -> handed to this client's socket.
    contractions : ndarray, shape (n_muscles,)
    markers : ndarray, shape (n_markers, 3)
        NaN rows unseen.
    servo_targets : ndarray, shape (n_servos,)
    head_pose : ndarray, shape (4, 4)
        NaN: unknown.
    """

    seq: int
    region_errors: tuple[float, float]
    latency_ms: float
    contractions: np.ndarray
    markers: np.ndarray
    servo_targets: np.ndarray
    head_pose: np.ndarray


def decode_frame(data: bytes) -> FrameMessage:
    """Inverse of :func:`encode_frame` (for tests and tools)."""
    kind, seq, m, n, s = np.frombuffer(data, "<u4", 5)
    if kind != FRAME_KIND:
        raise ValueError(f"not a frame message (kind {kind})")
    floats = np.frombuffer(data, "<f4", offset=20)
    end = 3 + m + 3 * n + s
    return FrameMessage(int(seq), (float(floats[0]), float(floats[1])), float(floats[2]), floats[3:3 + m].copy(),
                        floats[3 + m:3 + m + 3 * n].reshape(n, 3).copy(), floats[3 + m + 3 * n:end].copy(),
                        floats[end:end + 16].reshape(4, 4).copy())


class _Client:
    """One connected page: its socket and a one-slot newest-wins buffer per message kind."""

    __slots__ = ("connection", "frame", "status", "character", "wake")

    def __init__(self, connection):
        self.connection = connection
        self.frame: tuple[int, float, bytes] | None = None
        self.status: str | None = None
        self.character: bytes | None = None
        self.wake = asyncio.Event()


class RenderServer:
    """WebSocket + static page server for the browser render client.

    Parameters
    ----------
    basis : Basis
        The face drawn by the page (sent once to each client).
    markers : MarkerSet, optional
        Marker names, regions and roles shown with the 3D markers.
    host : str
        Interface to bind; ``127.0.0.1`` keeps the page on this machine.
    port : int
        TCP port; 0 picks a free one (read :attr:`url` after :meth:`start`).
    servo_names : sequence of str, optional
        Names of the servo targets carried by each frame.
    static_dir : Path, optional
        Folder of the page's files (default: the one shipped in the package).
    allowed_origins : sequence of str
        Other origins whose pages may connect, e.g. ``https://studio.example:8443`` (a page behind a
        proxy); their host names are accepted in ``Host`` too.
    ping_interval, ping_timeout : float
        Seconds between keepalive pings, and how long a client may take to answer one before it is dropped.
    """

    def __init__(self, basis: Basis, markers: MarkerSet | None = None, host: str = "127.0.0.1", port: int = 0,
                 servo_names=(), static_dir: Path | None = None, allowed_origins=(), ping_interval: float = 5.0,
                 ping_timeout: float = 10.0):
        self.basis = basis
        self.markers = markers
        self.host = host
        self.port = port
        self.allowed_origins = frozenset(parse_origin(origin) for origin in allowed_origins)
        self.ping_interval, self.ping_timeout = ping_interval, ping_timeout
        self.servo_names = tuple(servo_names)
        self._static = _static_files(Path(static_dir) if static_dir else STATIC_DIR)
        self._init_text = json.dumps({
            "type": "init",
            "muscles": list(basis.names),
            "regions": [m.region for m in basis.muscles],
            "markers": list(markers.names) if markers else [],
            "marker_regions": list(markers.regions) if markers else [],
            "marker_roles": list(markers.roles) if markers else [],
            "servos": list(self.servo_names),
            "n_vertices": basis.n_vertices,
            "n_triangles": len(basis.triangles),
        })
        self._mesh = encode_mesh(basis)
        self._n_markers = len(markers) if markers else 0
        self._clients: set[_Client] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._started = threading.Event()
        self._stop_future: asyncio.Future | None = None
        self._startup_error: BaseException | None = None
        self._pending_frame: RenderFrame | None = None
        self._pending_status: str | None = None
        self._pending_character: bytes | None = None
        self._character_init: tuple[str, bytes] | None = None
        self._wake_scheduled = False
        self._lock = threading.Lock()
        self._latencies = deque(maxlen=100_000)
        self._last_timed_seq = -1
        self._sent = threading.Condition()  # notified when a frame first reaches a client socket
        self.frames_published = 0
        self.messages_sent = 0
        self.connections_total = 0

    # ---------------------------------------------------------------- lifecycle
    def start(self) -> RenderServer:
        """Start serving on a background thread; returns once the port is bound."""
        if self._thread is not None:
            return self
        self._thread = threading.Thread(target=self._run, name="render-server", daemon=True)
        self._thread.start()
        self._started.wait()
        if self._startup_error is not None:
            self._thread.join()
            self._thread = None
            error = self._startup_error
            if isinstance(error, OSError):  # port in use, address not on this machine: name the address
                host = f"[{self.host}]" if ":" in self.host else self.host
                raise OSError(error.errno, error.strerror or str(error), f"render server {host}:{self.port}") \
                    from None
            raise error
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Close every connection and the port, and join the server thread."""
        if self._thread is None:
            return
        loop, future = self._loop, self._stop_future
        if loop is not None and future is not None and not loop.is_closed():
            loop.call_soon_threadsafe(lambda: future.done() or future.set_result(None))
        self._thread.join(timeout)
        self._thread = None

    def __enter__(self) -> RenderServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def url(self) -> str:
        """``http://host:port/`` of the page (after :meth:`start`)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    @property
    def n_clients(self) -> int:
        return len(self._clients)

    # ---------------------------------------------------------------- publisher side (any thread)
    def publish(self, frame: RenderFrame) -> None:
        """Hand the newest frame to every client; never blocks, never waits for a client."""
        self.frames_published += 1
        self._hand_over("_pending_frame", frame)

    def publish_status(self, status: dict) -> None:
        """Send the runtime's live status (a JSON-able dict) to every client, newest wins."""
        text = json.dumps({"type": "status", **status}, default=float)
        self._hand_over("_pending_status", text)

    def show_character(self, init_text: str, samples: bytes) -> None:
        """Show a 2D character in the page: its init text and samples message go to every client that
        connects from now on (call before :meth:`start`, or earlier clients see it after a reload)."""
        self._character_init = (init_text, samples)

    def publish_character(self, states: bytes) -> None:
        """Hand the newest character states message to every client; never blocks (as :meth:`publish`)."""
        self._hand_over("_pending_character", states)

    def _hand_over(self, pending: str, value) -> None:
        """Leave ``value`` in the ``pending`` slot (newest wins) and wake the server loop's distribution once."""
        with self._lock:
            setattr(self, pending, value)
            schedule = not self._wake_scheduled
            self._wake_scheduled = True
        if schedule:
            self._call_soon(self._distribute)

    def wait_sent(self, seq: int, timeout: float) -> bool:
        """Wait until frame ``seq`` (or a later one) reached a client socket, or no client is connected.

        For unpaced runs, whose cameras wait for the pipeline anyway: the next frame set then does not
        compete with this one's send for the CPU. Live, never call it (publish does not wait for clients).
        """
        with self._sent:
            return self._sent.wait_for(lambda: self._last_timed_seq >= seq or not self._clients, timeout)

    def sent_latencies(self) -> np.ndarray:
        """Seconds from each frame's ``t_ref`` to its first hand-over to a client socket, shape (n,)."""
        return np.array(self._latencies, dtype=np.float64)

    def _call_soon(self, callback) -> None:
        loop = self._loop
        if loop is None or loop.is_closed():
            with self._lock:
                self._wake_scheduled = False
            return
        try:
            loop.call_soon_threadsafe(callback)
        except RuntimeError:  # the loop closed between the check and the call
            with self._lock:
                self._wake_scheduled = False

    # ---------------------------------------------------------------- event loop side
    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._main())
        except BaseException as error:  # report a bind failure to start()
            if not self._started.is_set():
                self._startup_error = error
        finally:
            self._started.set()
            try:
                loop.run_until_complete(loop.shutdown_asyncgens())
            finally:
                loop.close()

    async def _main(self) -> None:
        from websockets.asyncio.server import serve

        self._stop_future = asyncio.get_running_loop().create_future()
        async with serve(self._handler, self.host, self.port, process_request=self._process_request,
                         compression=None, max_size=2**16, ping_interval=None, close_timeout=1,
                         write_limit=2**16, server_header=None) as server:
            self.port = server.sockets[0].getsockname()[1]
            self._started.set()
            await self._stop_future
            for client in list(self._clients):
                client.wake.set()

    def _process_request(self, connection, request):
        from websockets.datastructures import Headers
        from websockets.http11 import Response

        path = request.path.split("?", 1)[0].split("#", 1)[0]
        refusal = self._refusal(request.headers, websocket=path == WS_PATH)
        target = self._static.get(path)
        if refusal is not None:
            body = f"403 forbidden: {refusal}\n".encode()
            status, content_type = HTTPStatus.FORBIDDEN, "text/plain; charset=utf-8"
        elif path == WS_PATH:
            return None  # let the WebSocket handshake proceed
        elif target is None:
            body = b"404 not found\n"
            status, content_type = HTTPStatus.NOT_FOUND, "text/plain; charset=utf-8"
        else:
            body = target.read_bytes()
            status, content_type = HTTPStatus.OK, _CONTENT_TYPES.get(target.suffix, "application/octet-stream")
        headers = Headers([
            ("Date", email.utils.formatdate(usegmt=True)),
            ("Connection", "close"),
            ("Content-Length", str(len(body))),
            ("Content-Type", content_type),
            ("Cache-Control", "no-store"),
            ("X-Content-Type-Options", "nosniff"),
        ])
        return Response(status.value, status.phrase, headers, body)

    def _refusal(self, headers, websocket: bool) -> str | None:
        """Why a request is refused (a foreign ``Host``, or a WebSocket from a foreign ``Origin``), or None."""
        hosts = headers.get_all("Host")
        try:
            host, port = _parse_authority(hosts[0]) if len(hosts) == 1 else (None, None)
        except ValueError:
            host = None
        if host is None or not self._host_allowed(host, port):
            return "Host does not name this server"
        origins = headers.get_all("Origin")
        if not websocket or not origins:
            return None  # only browsers send Origin, and they send it on every WebSocket handshake
        if len(origins) > 1:
            return "more than one Origin"
        try:
            origin = parse_origin(origins[0])
        except InputError:
            return "Origin is not an http(s) origin"
        if origin in self.allowed_origins:
            return None
        scheme, origin_host, origin_port = origin
        same_host = origin_host == host or origin_host in LOOPBACK_NAMES and host in LOOPBACK_NAMES
        if scheme == "http" and same_host and origin_port == self.port:
            return None
        return "Origin is not this page's origin (add it to allowed_origins to let that page connect)"

    def _host_allowed(self, host: str, port: int | None) -> bool:
        if port is not None and port != self.port and all(port != p for _, _, p in self.allowed_origins):
            return False
        if any(host == h for _, h, _ in self.allowed_origins):
            return True
        bound = self.host.strip("[]").lower()
        if bound in WILDCARD_HOSTS:
            return _is_ip(host) or host in ("localhost", socket.gethostname().lower())
        if bound in LOOPBACK_NAMES or _is_ip(bound) and ipaddress.ip_address(bound).is_loopback:
            return host == bound or host in LOOPBACK_NAMES
        return host == bound

    def _distribute(self) -> None:
        with self._lock:
            frame, status, character = self._pending_frame, self._pending_status, self._pending_character
            self._pending_frame = self._pending_status = self._pending_character = None
            self._wake_scheduled = False
        if not self._clients:
            return
        if frame is not None:
            data = encode_frame(frame, self._n_markers, len(self.servo_names),
                                latency_ms=(time.monotonic() - frame.t_ref) * 1e3)
            for client in self._clients:
                client.frame = (frame.seq, frame.t_ref, data)
                client.wake.set()
        if status is not None:
            for client in self._clients:
                client.status = status
                client.wake.set()
        if character is not None:
            for client in self._clients:
                client.character = character
                client.wake.set()

    async def _handler(self, connection) -> None:
        from websockets.exceptions import ConnectionClosed

        client = _Client(connection)
        self.connections_total += 1
        sender = None
        keepalive = asyncio.create_task(self._keepalive(connection))
        try:
            await connection.send(self._init_text)
            await connection.send(self._mesh)
            if self._character_init is not None:
                for message in self._character_init:
                    await connection.send(message)
            self._clients.add(client)
            sender = asyncio.create_task(self._sender(client))
            async for _message in connection:  # the page sends nothing we need; this notices the close
                pass
        except ConnectionClosed:
            pass
        finally:
            self._clients.discard(client)
            keepalive.cancel()
            if sender is not None:
                sender.cancel()
                try:
                    await sender
                except (asyncio.CancelledError, ConnectionClosed):
                    pass

    async def _keepalive(self, connection) -> None:
        """Ping every ``ping_interval``; a client whose pong is ``ping_timeout`` late is cut off.

        The pong follows everything sent before the ping, so a client that stopped reading never answers,
        and the ping itself may wait behind its full socket: the timeout covers both (websockets' own
        keepalive starts its clock only once the ping is written, which a stalled client never allows).
        """
        from websockets.exceptions import ConnectionClosed

        async def ping_pong():
            pong = await connection.ping()
            await pong

        try:
            while True:
                await asyncio.sleep(self.ping_interval)
                await asyncio.wait_for(ping_pong(), self.ping_timeout)
        except asyncio.TimeoutError:
            connection.transport.abort()
        except ConnectionClosed:
            pass

    async def _sender(self, client: _Client) -> None:
        connection = client.connection
        stop = self._stop_future
        while not (stop is not None and stop.done()):
            await client.wake.wait()
            client.wake.clear()
            frame, status, character = client.frame, client.status, client.character
            client.frame = client.status = client.character = None
            if frame is not None:
                seq, t_ref, data = frame
                await connection.send(data)
                self.messages_sent += 1
                if seq != self._last_timed_seq:
                    self._latencies.append(time.monotonic() - t_ref)
                    with self._sent:
                        self._last_timed_seq = seq
                        self._sent.notify_all()
            if status is not None:
                await connection.send(status)
            if character is not None:
                await connection.send(character)


def _static_files(folder: Path) -> dict[str, Path]:
    """URL path -> file for the regular files directly inside ``folder`` (resolved once, at start)."""
    files = {}
    if folder.is_dir():
        for entry in sorted(folder.iterdir()):
            if entry.is_file() and not entry.is_symlink() and not entry.name.startswith("."):
                files["/" + entry.name] = entry.resolve()
    if "/index.html" in files:
        files["/"] = files["/index.html"]
    return files


def parse_origin(text: str) -> tuple[str, str, int]:
    """``(scheme, host, port)`` of a web origin such as ``http://127.0.0.1:8765``; anything else raises.

    Raises
    ------
    InputError
        Naming ``allowed_origins``: not ``http(s)://host[:port]`` with nothing after it.
    """
    scheme, sep, authority = text.partition("://") if isinstance(text, str) else ("", "", "")
    scheme = scheme.lower()
    try:
        host, port = _parse_authority(authority)
    except ValueError:
        host = None
    if not sep or scheme not in _DEFAULT_PORTS or host is None:
        raise InputError(f"expected an origin like http://host:port, got {text!r}", field="allowed_origins")
    return scheme, host, _DEFAULT_PORTS[scheme] if port is None else port


def _parse_authority(text: str) -> tuple[str, int | None]:
    """``(lower-case host without brackets, port or None)`` of ``host[:port]``; no user info, no path."""
    match = _AUTHORITY.fullmatch(text)
    if match is None:
        raise ValueError(f"not host[:port]: {text!r}")
    port = None if match.group(2) is None else int(match.group(2))
    if port is not None and not 0 < port < 65536:
        raise ValueError(f"port out of range: {port}")
    return match.group(1).strip("[]").lower(), port


def _is_ip(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True
