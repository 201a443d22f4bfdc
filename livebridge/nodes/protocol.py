"""The camera-node wire format: one msgpack map per ZeroMQ message, versioned, validated, size-limited.

Every message is ``topic + b"\\0" + msgpack(map)``. The topic is the camera id for frames a node publishes
(a host subscribes to one camera by its topic) and empty otherwise. The map always has ``v`` (the
protocol version, :data:`VERSION`) and ``type``:

=============  ==============  ===================================================================================
type           direction       fields
=============  ==============  ===================================================================================
``ping``       host -> node    ``camera``, ``t1`` (host clock), ``images`` (``none``/``thumbnail``/``full``),
                               ``detect`` (the host's detection parameters), ``board`` (None or a calibration
                               board's spec, e.g. ``chessboard:7x7:55``: detect it on the node, and no markers):
                               a heartbeat, a clock probe and the subscription's settings at once
``pong``       node -> host    ``t1`` (echoed), ``t2``, ``t3`` (node clock at receipt and reply), ``node``,
                               ``time_source`` (``ntp``: estimate the offset; ``ptp``/``hardware``: trust it),
                               ``camera``, ``ended`` (None while it runs, else why it ended: ``""`` for a
                               finished take), ``realtime``, ``calibration`` (None or the camera's intrinsics
                               and pose), ``fps`` (the camera's frame rate, NaN when unknown), ``size``
                               (None or the camera's ``[width, height]``)
``grab``       host -> node    ``camera``, ``index``: unpaced cameras send frame ``index`` on request only
                               (asked again for the same index, the node sends the same frame again)
``frame``      node -> host    ``camera``, ``seq``, ``t`` (node clock, mid-exposure; an unpaced camera's own
                               frame time, e.g. a replayed take's, which the host keeps), ``exposure_us``, ``gain``,
                               ``sync_domain``, ``centroids`` (float64 little-endian bytes, (n, 2) distorted
                               pixels; None when not detected: the host asked for board corners only),
                               ``board`` (None or ``[ids, points]``: the board corners found, int32 and
                               (n, 2) float64 little-endian bytes, distorted pixels), ``index`` (-1 for
                               paced cameras), ``t_sent`` (node clock),
                               ``image`` (None or ``[width, height, bytes]``: a thumbnail or the full frame)
=============  ==============  ===================================================================================

:func:`decode` checks everything a peer could get wrong or forge (version, type, every field's type and
range, sizes before anything is unpacked) and raises :class:`ProtocolError` with a short reason;
receivers count the reasons (:class:`DropCounter`) and go on.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from typing import Any

import numpy as np

from livebridge.nodes import require

VERSION = 1
MAX_IMAGE_SIDE = 4096
MAX_CENTROIDS = 4096
MAX_BOARD_CORNERS = 4096
MAX_TEXT = 256
MAX_CONTROL_BYTES = 64 * 1024  # every message but a frame with an image
MAX_MESSAGE_BYTES = MAX_IMAGE_SIDE * MAX_IMAGE_SIDE + MAX_CONTROL_BYTES
IMAGE_MODES = ("none", "thumbnail", "full")
TIME_SOURCES = ("ntp", "ptp", "hardware")
DETECT_FIELDS = {"threshold": (float, type(None)), "contrast": (float,), "min_area": (int,), "max_area": (int,),
                 "min_circularity": (float,), "margin": (int,)}


class ProtocolError(ValueError):
    """A message that is not valid; ``reason`` is one short word for counting (``oversized``, ``malformed``,
    ``version``, ``type``, ``field``)."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason, self.detail = reason, detail


class DropCounter:
    """Messages dropped, by reason (thread-safe enough: one receiving thread counts, others read)."""

    def __init__(self):
        self.counts: Counter[str] = Counter()

    def add(self, reason: str) -> None:
        self.counts[reason] += 1

    @property
    def total(self) -> int:
        return sum(self.counts.values())


@dataclass(frozen=True)
class Ping:
    camera: str
    t1: float
    images: str = "none"
    detect: dict | None = None
    board: str | None = None


@dataclass(frozen=True)
class Pong:
    camera: str
    t1: float
    t2: float
    t3: float
    node: str
    time_source: str = "ntp"
    ended: str | None = None
    realtime: bool = True
    calibration: dict | None = None
    fps: float = math.nan
    size: tuple[int, int] | None = None


@dataclass(frozen=True)
class Grab:
    camera: str
    index: int


@dataclass(frozen=True, eq=False)
class FrameMessage:
    """One frame's detections.

    Attributes
    ----------
    centroids : ndarray, shape (n, 2), or None
        Distorted pixels, read-only; None when the node did not detect markers.
    image : ndarray of uint8, shape (height, width), or None
    board_ids : ndarray of int, shape (m,), or None
        The board corners found (ids as :mod:`livebridge.calibration.boards` numbers them); None when no
        board was asked for.
    board_points : ndarray, shape (m, 2), or None
        Their distorted pixels.
    """

    camera: str
    seq: int
    t: float
    centroids: np.ndarray | None
    exposure_us: float = math.nan
    gain: float = math.nan
    sync_domain: str = ""
    index: int = -1
    t_sent: float = math.nan
    image: np.ndarray | None = None
    board_ids: np.ndarray | None = None
    board_points: np.ndarray | None = None


Message = Ping | Pong | Grab | FrameMessage


# ----------------------------------------------------------------------------------------------- encode

def encode(message: Message, topic: str = "") -> bytes:
    """``topic + b"\\0" + msgpack`` of ``message``."""
    _, msgpack = require()
    body = _fields(message)
    return topic.encode() + b"\0" + msgpack.packb(body, use_bin_type=True)


def _fields(message: Message) -> dict[str, Any]:
    if isinstance(message, FrameMessage):
        image, centroids = message.image, message.centroids
        board = None if message.board_ids is None else [
            np.ascontiguousarray(message.board_ids, dtype="<i4").tobytes(),
            np.ascontiguousarray(message.board_points, dtype="<f8").tobytes()]
        return {"v": VERSION, "type": "frame", "camera": message.camera, "seq": int(message.seq), "t": message.t,
                "centroids": None if centroids is None else np.ascontiguousarray(centroids, dtype="<f8").tobytes(),
                "board": board,
                "exposure_us": float(message.exposure_us), "gain": float(message.gain),
                "sync_domain": message.sync_domain, "index": int(message.index), "t_sent": float(message.t_sent),
                "image": None if image is None else [image.shape[1], image.shape[0],
                                                      np.ascontiguousarray(image, dtype=np.uint8).tobytes()]}
    kind = {Ping: "ping", Pong: "pong", Grab: "grab"}[type(message)]
    fields = dict(message.__dict__)
    if fields.get("size") is not None:
        fields["size"] = list(fields["size"])
    return {"v": VERSION, "type": kind, **fields}


# ----------------------------------------------------------------------------------------------- decode

def decode(data: bytes) -> Message:
    """The message in ``data`` (``topic + b"\\0" + msgpack``), validated.

    Raises
    ------
    ProtocolError
        Anything wrong: too large, truncated, not msgpack, unknown version or type, a field of the
        wrong type or out of range, a topic that is not the frame's camera.
    """
    _, msgpack = require()
    if len(data) > MAX_MESSAGE_BYTES:
        raise ProtocolError("oversized", f"{len(data)} bytes, limit {MAX_MESSAGE_BYTES}")
    topic, separator, payload = bytes(data).partition(b"\0")
    if not separator or len(topic) > MAX_TEXT:
        raise ProtocolError("malformed", "no topic separator")
    try:
        body = msgpack.unpackb(payload, raw=False, strict_map_key=True, max_str_len=MAX_TEXT,
                               max_bin_len=MAX_IMAGE_SIDE * MAX_IMAGE_SIDE, max_array_len=64, max_map_len=64)
    except (ValueError, TypeError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError) as error:
        raise ProtocolError("malformed", f"{type(error).__name__}: {error}") from None
    if not isinstance(body, dict):
        raise ProtocolError("malformed", "not a map")
    if body.get("v") != VERSION:
        raise ProtocolError("version", f"version {body.get('v')!r}, expected {VERSION}")
    kind = body.get("type")
    reader = _READERS.get(kind) if isinstance(kind, str) else None
    if reader is None:
        raise ProtocolError("type", f"unknown message type {kind!r}")
    if kind != "frame" and len(data) > MAX_CONTROL_BYTES:
        raise ProtocolError("oversized", f"{kind} of {len(data)} bytes, limit {MAX_CONTROL_BYTES}")
    message = reader(_Fields(body, kind))
    if topic and getattr(message, "camera", None) != topic.decode(errors="replace"):
        raise ProtocolError("field", f"topic {topic!r} is not the message's camera")
    return message


class _Fields:
    """Typed access to a decoded map; a missing or mistyped field is a :class:`ProtocolError`."""

    def __init__(self, body: dict, kind: str):
        self.body, self.kind = body, kind

    def get(self, name: str, kinds: tuple[type, ...], default=...):
        if name not in self.body:
            if default is ...:
                raise ProtocolError("field", f"{self.kind}: no {name!r}")
            return default
        value = self.body[name]
        if float in kinds and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, kinds) or (isinstance(value, bool) and bool not in kinds):
            raise ProtocolError("field", f"{self.kind}.{name}: {type(value).__name__}")
        return value

    def time(self, name: str, default=...) -> float:
        value = self.get(name, (float,), default)
        if not math.isfinite(value) and default is ...:
            raise ProtocolError("field", f"{self.kind}.{name}: not finite")
        return value

    def number(self, name: str, default: float = math.nan) -> float:
        return self.get(name, (float,), default)

    def text(self, name: str, default=...) -> str:
        return self.get(name, (str,), default)

    def choice(self, name: str, choices: tuple[str, ...], default=...) -> str:
        value = self.text(name, default)
        if value not in choices:
            raise ProtocolError("field", f"{self.kind}.{name}: {value!r} not one of {choices}")
        return value

    def integer(self, name: str, low: int, high: int, default=...) -> int:
        value = self.get(name, (int,), default)
        if not low <= value <= high:
            raise ProtocolError("field", f"{self.kind}.{name}: {value} not in {low}..{high}")
        return value


def _read_ping(f: _Fields) -> Ping:
    detect = f.get("detect", (dict, type(None)), None)
    if detect is not None:
        detect = _detect_fields(detect)
    return Ping(f.text("camera"), f.time("t1"), f.choice("images", IMAGE_MODES, "none"), detect,
                f.get("board", (str, type(None)), None))


def _detect_fields(detect: dict) -> dict:
    if set(detect) - set(DETECT_FIELDS):
        raise ProtocolError("field", f"ping.detect: unknown {sorted(set(detect) - set(DETECT_FIELDS))}")
    checked = {}
    for name, value in detect.items():
        kinds = DETECT_FIELDS[name]
        if float in kinds and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, kinds) or isinstance(value, bool) or (isinstance(value, float)
                                                                        and not math.isfinite(value)):
            raise ProtocolError("field", f"ping.detect.{name}: {value!r}")
        checked[name] = value
    return checked


def _read_pong(f: _Fields) -> Pong:
    calibration = f.get("calibration", (dict, type(None)), None)
    return Pong(f.text("camera"), f.time("t1"), f.time("t2"), f.time("t3"), f.text("node"),
                f.choice("time_source", TIME_SOURCES, "ntp"), f.get("ended", (str, type(None)), None),
                f.get("realtime", (bool,), True), calibration, _fps(f), _size(f))


def _fps(f: _Fields) -> float:
    fps = f.number("fps")
    if not (math.isnan(fps) or 0 < fps <= 100_000):
        raise ProtocolError("field", f"pong.fps: {fps}")
    return fps


def _size(f: _Fields) -> tuple[int, int] | None:
    size = f.get("size", (list, type(None)), None)
    if size is None:
        return None
    if (len(size) != 2 or not all(isinstance(v, int) and not isinstance(v, bool) for v in size)
            or not all(0 <= v <= 1 << 16 for v in size)):
        raise ProtocolError("field", f"pong.size: {size!r}")
    return size[0], size[1]


def _read_grab(f: _Fields) -> Grab:
    return Grab(f.text("camera"), f.integer("index", 0, 2**62))


def _read_frame(f: _Fields) -> FrameMessage:
    raw = f.get("centroids", (bytes, type(None)))
    centroids = None if raw is None else _points(raw, MAX_CENTROIDS, "frame.centroids")
    board_ids, board_points = _board(f)
    return FrameMessage(f.text("camera"), f.integer("seq", -2**62, 2**62), f.time("t"), centroids,
                        f.number("exposure_us"), f.number("gain"), f.text("sync_domain", ""),
                        f.integer("index", -1, 2**62, -1), f.number("t_sent"), _image(f), board_ids, board_points)


def _points(raw: bytes, limit: int, name: str) -> np.ndarray:
    """(n, 2) finite float64 points from little-endian bytes, read-only."""
    if len(raw) % 16 or len(raw) // 16 > limit:
        raise ProtocolError("field", f"{name}: {len(raw)} bytes is not (n <= {limit}, 2) float64")
    points = np.frombuffer(raw, dtype="<f8").reshape(-1, 2).astype(np.float64)
    if not np.isfinite(points).all():
        raise ProtocolError("field", f"{name}: not finite")
    points.setflags(write=False)
    return points


def _board(f: _Fields) -> tuple[np.ndarray | None, np.ndarray | None]:
    """A frame's board corners: unique ids in ``0..MAX_BOARD_CORNERS - 1`` and one finite point each."""
    board = f.get("board", (list, type(None)), None)
    if board is None:
        return None, None
    if len(board) != 2 or not all(isinstance(part, bytes) for part in board) or len(board[0]) % 4:
        raise ProtocolError("field", "frame.board: not [ids, points] bytes")
    ids = np.frombuffer(board[0], dtype="<i4").astype(np.int64)
    points = _points(board[1], MAX_BOARD_CORNERS, "frame.board points")
    if (len(ids) != len(points) or (len(ids) and not 0 <= ids.min() <= ids.max() < MAX_BOARD_CORNERS)
            or len(np.unique(ids)) != len(ids)):
        raise ProtocolError("field", f"frame.board: {len(ids)} ids (unique, < {MAX_BOARD_CORNERS}) for "
                                     f"{len(points)} points")
    ids.setflags(write=False)
    return ids, points


def _image(f: _Fields) -> np.ndarray | None:
    image = f.get("image", (list, type(None)), None)
    if image is None:
        return None
    if (len(image) != 3 or not all(isinstance(v, int) and not isinstance(v, bool) for v in image[:2])
            or not isinstance(image[2], bytes)):
        raise ProtocolError("field", "frame.image: not [width, height, bytes]")
    width, height, pixels = image
    if not (1 <= width <= MAX_IMAGE_SIDE and 1 <= height <= MAX_IMAGE_SIDE) or len(pixels) != width * height:
        raise ProtocolError("field", f"frame.image: {len(pixels)} bytes for {width}x{height}")
    return np.frombuffer(pixels, dtype=np.uint8).reshape(height, width)


_READERS = {"ping": _read_ping, "pong": _read_pong, "grab": _read_grab, "frame": _read_frame}
