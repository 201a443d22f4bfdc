"""The render server: static page over HTTP, WebSocket protocol, newest-wins fan-out, no leaks."""

from __future__ import annotations

import errno
import os
import socket
import struct
import threading
import time

import numpy as np
import pytest
from factories import random_basis

from livebridge.errors import InputError
from livebridge.face.markers import MarkerSet
from livebridge.face.meshio import vertex_normals
from livebridge.output.render_server import (
    STATIC_DIR,
    RenderFrame,
    RenderServer,
    decode_frame,
    encode_mesh,
)

_HANDSHAKE = (
    "GET /ws HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
    "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
)


def _markers(basis, n=6):
    return MarkerSet(tuple(f"k{i}" for i in range(n)), np.arange(n), np.full((n, 3), 1 / 3),
                     ("upper", "lower") * (n // 2), ("face",) * (n - 1) + ("head",))


@pytest.fixture
def server(rng):
    basis = random_basis(rng, n_vertices=49, n_muscles=4)
    with RenderServer(basis, _markers(basis), servo_names=("jaw", "brow")) as srv:
        yield srv


def _http_get(port: int, raw_path: str) -> tuple[int, dict, bytes]:
    with socket.create_connection(("127.0.0.1", port), timeout=5) as conn:
        conn.sendall(f"GET {raw_path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
        data = b""
        while True:
            chunk = conn.recv(65536)
            if not chunk:
                break
            data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.lower(): v.strip() for k, v in (line.split(":", 1) for line in lines[1:])}
    return int(lines[0].split()[1]), headers, body


def test_page_and_assets_are_served(server):
    status, headers, body = _http_get(server.port, "/")
    assert status == 200 and headers["content-type"].startswith("text/html")
    assert body == (STATIC_DIR / "index.html").read_bytes()
    for name, kind in (("app.js", "text/javascript"), ("style.css", "text/css")):
        status, headers, body = _http_get(server.port, f"/{name}?v=1")
        assert status == 200 and headers["content-type"].startswith(kind)
        assert body == (STATIC_DIR / name).read_bytes()
        assert int(headers["content-length"]) == len(body)


@pytest.mark.parametrize("path", [
    "/nothing-here", "/../render_server.py", "/%2e%2e/render_server.py", "/static/../render_server.py",
    "//etc/passwd", "/..%2f..%2fetc%2fpasswd", "/app.js/../../render_server.py", "/./app.js", "/APP.JS",
    "/index.html%00", "/.", "/..", "/etc/passwd", "/%2fetc%2fpasswd", "/..\\render_server.py",
])
def test_every_other_path_is_404_and_reads_nothing_outside(server, path):
    status, _, body = _http_get(server.port, path)
    assert status == 404
    assert b"import" not in body and b"root:" not in body


def test_files_added_outside_or_later_are_never_served(rng, tmp_path):
    static = tmp_path / "static"
    static.mkdir()
    (static / "index.html").write_text("<p>hi</p>")
    (tmp_path / "secret.txt").write_text("secret")
    (static / "link.txt").symlink_to(tmp_path / "secret.txt")
    with RenderServer(random_basis(rng, 16, 2), static_dir=static) as srv:
        (static / "late.txt").write_text("late")
        assert _http_get(srv.port, "/")[0] == 200
        for path in ("/link.txt", "/late.txt", "/../secret.txt", "/secret.txt"):
            status, _, body = _http_get(srv.port, path)
            assert status == 404 and b"secret" not in body and b"late" not in body


def test_vertex_normals_of_a_flat_grid_point_along_z(rng):
    basis = random_basis(rng, 25, 1)
    flat = basis.neutral.copy()
    flat[:, 2] = 0
    normals = vertex_normals(flat, basis.triangles)
    assert np.allclose(np.abs(normals[:, 2]), 1) and np.allclose(np.linalg.norm(normals, axis=1), 1)
    batch = vertex_normals(np.stack([flat, basis.neutral]), basis.triangles)
    assert np.allclose(batch[0], normals) and np.allclose(batch[1], vertex_normals(basis.neutral, basis.triangles))


def test_client_gets_init_mesh_then_frames(server):
    from websockets.sync.client import connect

    basis = server.basis
    with connect(f"ws://127.0.0.1:{server.port}/ws") as ws:
        import json
        init = json.loads(ws.recv(timeout=5))
        assert init["type"] == "init" and init["muscles"] == list(basis.names)
        assert init["markers"] == list(server.markers.names) and init["servos"] == ["jaw", "brow"]
        mesh = ws.recv(timeout=5)
        assert mesh == encode_mesh(basis)
        kind, v, t, m = struct.unpack_from("<4I", mesh)
        assert (kind, v, t, m) == (1, basis.n_vertices, len(basis.triangles), basis.n_muscles)
        neutral = np.frombuffer(mesh, "<f4", v * 3, 16).reshape(v, 3)
        assert np.allclose(neutral, basis.neutral, atol=1e-4)
        offset = 16 + 2 * 4 * v * 3 + 4 * t * 3
        elements = np.frombuffer(mesh, "<f4", m * v * 3, offset).reshape(m, v, 3)
        assert np.allclose(elements, basis.elements, atol=1e-5)
        _wait(lambda: server.n_clients == 1)
        x = np.array([0.1, 0.2, 0.3, 0.4])
        markers = np.arange(18.0).reshape(6, 3)
        markers[2] = np.nan
        server.publish(RenderFrame(7, time.monotonic(), x, markers, (0.25, 0.5), np.array([0.0, 1.0])))
        frame = decode_frame(ws.recv(timeout=5))
        assert frame.seq == 7 and np.allclose(frame.contractions, x)
        assert np.allclose(frame.markers, markers, equal_nan=True)
        assert frame.region_errors == (0.25, 0.5) and np.allclose(frame.servo_targets, [0, 1])
        assert np.isnan(frame.head_pose).all()  # no head pose: unknown
        pose = np.eye(4)
        pose[:3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]
        pose[:3, 3] = [1, 2, 3]
        server.publish(RenderFrame(8, time.monotonic(), x, None, servo_targets=None, head_pose=pose))
        frame = decode_frame(ws.recv(timeout=5))
        assert np.allclose(frame.head_pose, pose) and np.isnan(frame.markers).all()
        server.publish_status({"line": "fps 60"})
        assert json.loads(ws.recv(timeout=5)) == {"type": "status", "line": "fps 60"}
    assert len(server.sent_latencies()) == 2 and 0 <= server.sent_latencies()[0] < 5


def test_a_stalled_client_never_slows_the_publisher_or_the_other_clients(rng):
    """One client stops reading entirely; publishing waits for no client (nor for the server's loop) and a live
    client gets the newest frame."""
    from websockets.sync.client import connect

    basis = random_basis(rng, 49, 4)
    markers = MarkerSet(tuple(f"k{i}" for i in range(60)), np.arange(60) % len(basis.triangles),
                        np.full((60, 3), 1 / 3), ("upper",) * 60, ("face",) * 60)
    with RenderServer(basis, markers) as srv:
        stalled = socket.socket()
        stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        stalled.connect(("127.0.0.1", srv.port))
        stalled.sendall(_HANDSHAKE.encode())
        with connect(f"ws://127.0.0.1:{srv.port}/ws") as live:
            live.recv(timeout=5), live.recv(timeout=5)
            _wait(lambda: srv.n_clients == 2)
            # with the server's loop held, 100 publishes still return: publish takes a lock and wakes the loop,
            # it never waits for the loop or a client
            gate = threading.Event()
            srv._call_soon(lambda: gate.wait(30))
            publisher = threading.Thread(target=lambda: [
                srv.publish(RenderFrame(-1, time.monotonic(), np.zeros(4), np.zeros((60, 3)))) for _ in range(100)])
            publisher.start()
            publisher.join(timeout=20)
            held = publisher.is_alive()
            gate.set()
            assert not held
            for seq in range(3000):  # ~2.6 MB: far more than the stalled socket's buffers hold
                srv.publish(RenderFrame(seq, time.monotonic(), np.full(4, seq % 7 / 7), np.zeros((60, 3))))
                if seq % 10 == 0:
                    time.sleep(0.001)
            last = None
            deadline = time.monotonic() + 5
            while time.monotonic() < deadline:
                last = decode_frame(live.recv(timeout=5)).seq
                if last == 2999:
                    break
            assert last == 2999  # the live client caught up with the newest frame
        stalled.close()


def test_100_abrupt_disconnects_leak_nothing(server):
    from websockets.sync.client import connect

    def open_fds():
        return len(os.listdir("/proc/self/fd"))

    threads_before, fds_before = set(threading.enumerate()), open_fds()
    for k in range(100):
        sock = socket.create_connection(("127.0.0.1", server.port))
        sock.sendall(_HANDSHAKE.encode())
        reply = b""
        while b"\r\n\r\n" not in reply:
            reply += sock.recv(4096)
        assert reply.startswith(b"HTTP/1.1 101")
        if k % 2:
            server.publish(RenderFrame(k, time.monotonic(), np.zeros(4)))
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # close sends RST
        sock.close()
    _wait(lambda: server.n_clients == 0, timeout=10)
    _wait(lambda: open_fds() <= fds_before, timeout=10)
    # no thread started here is left alive (one of an earlier test may end meanwhile: not counted)
    _wait(lambda: not set(threading.enumerate()) - threads_before, timeout=10)
    assert server.connections_total >= 100
    with connect(f"ws://127.0.0.1:{server.port}/ws") as ws:  # still serving
        ws.recv(timeout=5), ws.recv(timeout=5)
        _wait(lambda: server.n_clients == 1)
        server.publish(RenderFrame(1000, time.monotonic(), np.ones(4)))
        assert decode_frame(ws.recv(timeout=5)).seq == 1000


def test_stop_closes_the_port_and_publish_after_stop_is_harmless(rng):
    srv = RenderServer(random_basis(rng, 16, 2)).start()
    port = srv.port
    srv.stop()
    srv.publish(RenderFrame(0, time.monotonic(), np.zeros(2)))
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=1)


def test_port_in_use_raises_on_start(rng, server):
    with pytest.raises(OSError) as info:
        RenderServer(random_basis(rng, 16, 2), port=server.port).start()
    assert info.value.errno == errno.EADDRINUSE and info.value.filename == f"render server 127.0.0.1:{server.port}"


def test_an_address_not_on_this_machine_raises_naming_it(rng):
    with pytest.raises(OSError) as info:
        RenderServer(random_basis(rng, 16, 2), host="192.0.2.7", port=0).start()
    assert info.value.errno == errno.EADDRNOTAVAIL and info.value.filename == "render server 192.0.2.7:0"


def _wait(condition, timeout=5.0):
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        time.sleep(0.01)


def _handshake_status(port: int, host: str | None, origin: str | None = None, path: str = "/ws") -> int:
    """Status of a raw HTTP/1.1 WebSocket handshake with these ``Host`` and ``Origin`` headers."""
    lines = [f"GET {path} HTTP/1.1", "Upgrade: websocket", "Connection: Upgrade",
             "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==", "Sec-WebSocket-Version: 13"]
    lines += [f"Host: {host}"] if host is not None else []
    lines += [f"Origin: {origin}"] if origin is not None else []
    with socket.create_connection(("127.0.0.1", port), timeout=5) as conn:
        conn.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
        reply = b""
        while b"\r\n" not in reply:
            chunk = conn.recv(4096)
            if not chunk:
                break
            reply += chunk
    return int(reply.split()[1])


@pytest.mark.parametrize("host,origin,status", [
    ("127.0.0.1:{port}", "http://127.0.0.1:{port}", 101),  # the page's own origin
    ("127.0.0.1:{port}", "http://localhost:{port}", 101),  # loopback names are one machine
    ("localhost:{port}", "http://[::1]:{port}", 101),
    ("LOCALHOST:{port}", "HTTP://LocalHost:{port}", 101),
    ("127.0.0.1:{port}", None, 101),  # not a browser: no page to hijack
    ("127.0.0.1:{port}", "https://studio.example:8443", 101),  # listed by the user
    ("127.0.0.1:{port}", "http://evil.example", 403),  # cross-site WebSocket hijacking
    ("127.0.0.1:{port}", "http://evil.example:{port}", 403),
    ("127.0.0.1:{port}", "http://127.0.0.1:1", 403),  # another local page, another port
    ("127.0.0.1:{port}", "https://127.0.0.1:{port}", 403),
    ("127.0.0.1:{port}", "null", 403),  # sandboxed iframe, file:// page
    ("127.0.0.1:{port}", "http://127.0.0.1:{port}/", 403),
    ("evil.example:{port}", "http://evil.example:{port}", 403),  # DNS rebinding: the page's own origin, foreign Host
    ("evil.example:{port}", None, 403),
    ("127.0.0.1.evil.example:{port}", None, 403),
    ("evil.example@127.0.0.1:{port}", None, 403),
    ("127.0.0.1:1", None, 403),
    ("192.0.2.7:{port}", None, 403),
    (None, None, 403),
])
def test_websocket_accepts_only_its_own_page_and_listed_origins(rng, host, origin, status):
    basis = random_basis(rng, 16, 2)
    with RenderServer(basis, allowed_origins=["https://studio.example:8443"]) as srv:
        fill = {"port": srv.port}
        assert _handshake_status(srv.port, host and host.format(**fill), origin and origin.format(**fill)) == status


def test_a_foreign_host_gets_no_page_either(server):
    assert _handshake_status(server.port, f"evil.example:{server.port}", path="/") == 403
    assert _handshake_status(server.port, f"127.0.0.1:{server.port}", path="/") == 200


@pytest.mark.parametrize("origin", ["127.0.0.1:8765", "ftp://x", "http://", "http://a/b", "http://a:99999", 5])
def test_a_malformed_allowed_origin_is_an_input_error(rng, origin):
    with pytest.raises(InputError) as info:
        RenderServer(random_basis(rng, 16, 2), allowed_origins=[origin])
    assert info.value.field == "allowed_origins"


def test_a_client_that_never_reads_is_dropped_within_ping_interval_plus_timeout(rng):
    """A raw socket completes the handshake and then never reads while frames are broadcast: the server
    cuts it off after one unanswered ping, while a client that reads stays connected."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    basis = random_basis(rng, 49, 4)
    interval, timeout = 0.5, 1.0
    with RenderServer(basis, ping_interval=interval, ping_timeout=timeout) as srv:
        stalled = socket.socket()
        stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        stalled.connect(("127.0.0.1", srv.port))
        stalled.sendall(_HANDSHAKE.encode())
        with connect(f"ws://127.0.0.1:{srv.port}/ws") as live:
            received = []

            def read():
                try:
                    while True:
                        received.append(live.recv())
                except ConnectionClosed:
                    pass

            reader = threading.Thread(target=read, daemon=True)
            reader.start()
            _wait(lambda: srv.n_clients == 2)
            start, seq, dropped = time.monotonic(), 0, None
            while time.monotonic() - start < 2 * (interval + timeout) + 1:
                srv.publish(RenderFrame(seq, time.monotonic(), np.full(4, seq % 7 / 7)))
                seq += 1
                time.sleep(0.01)
                if dropped is None and srv.n_clients == 1:
                    dropped = time.monotonic() - start
            assert dropped is not None and dropped <= interval + timeout + 0.5, dropped
            assert srv.n_clients == 1 and reader.is_alive()  # the reading client answers its pings
        reader.join(5)
        kind, last_seq = struct.unpack_from("<2I", received[-1])
        assert kind == 2 and last_seq >= seq - 50  # the newest frames kept arriving
        stalled.close()
