"""Live Link Face output: contractions and head rotation to Unreal Engine as the iPhone app sends them.

``[outputs.livelink]`` sends one version-6 Live Link Face packet per frame (:mod:`livebridge.arkit.packet`)
over UDP to ``host:port`` (default ``127.0.0.1:11111``, Unreal's Live Link Face port), with a configurable
subject name and device id. The 52 blendshape weights come from the contractions through the muscle ->
blendshape map the VMC output uses (:class:`~livebridge.output.blendshapes.BlendshapeMap`, ARKit names);
the head's yaw, pitch and roll from the frame's head pose (:mod:`livebridge.arkit.head`); the eyes rest.
The frame time is the frame's capture time on the output's frame rate (frame number and sub-frame).
Sending never blocks: a datagram the OS refuses is dropped and counted.
"""

from __future__ import annotations

import ipaddress
import math
import socket
import time
import uuid
from collections.abc import Mapping, Sequence

import numpy as np

from livebridge.arkit.head import rotation_from_head_pose
from livebridge.arkit.names import ARKIT_NAMES, HEAD_ROTATION, N_BLENDSHAPES, N_VALUES
from livebridge.arkit.packet import MAX_NAME_BYTES, LiveLinkPacket, encode_packet
from livebridge.errors import InputError
from livebridge.output.blendshapes import BlendshapeMap
from livebridge.output.vmc import resolve_destination

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 11111
DEFAULT_SUBJECT = "livebridge"
DEFAULT_FPS = 60


def default_device_id() -> str:
    """A device id stable on this machine (a UUID made from its network address), as the app's are UUIDs."""
    return str(uuid.uuid5(uuid.NAMESPACE_OID, f"livebridge-{uuid.getnode()}")).upper()


def _checked_name(value: str, field: str) -> str:
    if not isinstance(value, str) or not value:
        raise InputError(f"must be non-empty text, got {value!r}", field=field)
    if len(value.encode("utf-8")) > MAX_NAME_BYTES:
        raise InputError(f"at most {MAX_NAME_BYTES} bytes of UTF-8", field=field)
    return value


class LiveLinkEncoder:
    """Contractions and head pose -> Live Link Face packets (pure; no socket).

    Parameters
    ----------
    muscle_names : sequence of str
    subject, device_id : str
    mapping : see :class:`BlendshapeMap` (camel-case ARKit names)
    fps : int
        The frame rate the frame time is counted in.
    """

    def __init__(self, muscle_names: Sequence[str], subject: str = DEFAULT_SUBJECT, device_id: str | None = None,
                 mapping: Mapping | str | None = None, fps: int = DEFAULT_FPS):
        self.subject = _checked_name(subject, "subject")
        self.device_id = _checked_name(device_id or default_device_id(), "device_id")
        if isinstance(fps, bool) or not isinstance(fps, int) or not 1 <= fps <= 1000:
            raise InputError(f"must be a whole number of frames per second 1..1000, got {fps!r}", field="fps")
        self.fps = fps
        self.map = BlendshapeMap(muscle_names, mapping, "camel")
        self.rows = self.map.rows_for(ARKIT_NAMES)  # (52, n_muscles)

    def values(self, contractions: np.ndarray, head_pose: np.ndarray | None = None) -> np.ndarray:
        """The 61 packet values, shape (61,): weights in [0, 1] (NaN contractions count as 0), head rotation."""
        values = np.zeros(N_VALUES)
        x = np.nan_to_num(np.asarray(contractions, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
        values[:N_BLENDSHAPES] = np.clip(self.rows @ x, 0.0, 1.0)
        values[HEAD_ROTATION] = rotation_from_head_pose(head_pose)
        return values

    def packet(self, contractions: np.ndarray, head_pose: np.ndarray | None, t: float) -> LiveLinkPacket:
        """The packet of one frame at time ``t`` (s)."""
        frames = t * self.fps if math.isfinite(t) else 0.0
        number = math.floor(frames)
        return LiveLinkPacket(self.device_id, self.subject, int(number) % 2**31, frames - number, (self.fps, 1),
                              self.values(contractions, head_pose))

    def encode(self, contractions: np.ndarray, head_pose: np.ndarray | None, t: float) -> bytes:
        return encode_packet(self.packet(contractions, head_pose, t))


class LiveLinkOutput:
    """Sends every solved frame to a Live Link Face receiver (Unreal) over UDP.

    Parameters
    ----------
    muscle_names : sequence of str
    host, port : str, int
        Default ``127.0.0.1:11111``; another machine only when its host is given (:meth:`describe` says so).
    subject, device_id, mapping, fps : see :class:`LiveLinkEncoder`
    clock : callable
        Frame time for frames without a capture time.
    """

    def __init__(self, muscle_names: Sequence[str], host: str = DEFAULT_HOST, port: int = DEFAULT_PORT,
                 subject: str = DEFAULT_SUBJECT, device_id: str | None = None, mapping: Mapping | str | None = None,
                 fps: int = DEFAULT_FPS, clock=time.monotonic):
        self.encoder = LiveLinkEncoder(muscle_names, subject, device_id, mapping, fps)
        family, self.address = resolve_destination(host, port)
        self.host = host
        self.is_local = ipaddress.ip_address(self.address[0].split("%")[0]).is_loopback
        self.clock = clock
        self._socket = socket.socket(family, socket.SOCK_DGRAM)
        self._socket.setblocking(False)
        self.sent = self.dropped = self.bytes_sent = 0
        self.last_error: OSError | None = None

    def describe(self) -> str:
        """One line for the start-up banner: where the packets go, and whether they leave this machine."""
        ip, port = self.address[:2]
        where = f"[{ip}]:{port}" if ":" in ip else f"{ip}:{port}"
        named = "" if self.host == ip else f" ({self.host})"
        subject = f"subject {self.encoder.subject!r}"
        if self.is_local:
            return f"Live Link Face: sending to {where}{named} on this machine, {subject}"
        return (f"Live Link Face: sending to {where}{named}, {subject}, ANOTHER MACHINE: the face's contractions "
                "leave this computer")

    def send(self, frame) -> None:
        """Send one solved frame (its ``contractions``, ``head_pose`` and capture time)."""
        timing = getattr(frame, "timing", None)
        t = getattr(timing, "capture", math.nan)
        t = t if math.isfinite(t) else self.clock()
        self.send_values(frame.contractions, getattr(frame, "head_pose", None), t)

    def send_values(self, contractions: np.ndarray, head_pose: np.ndarray | None, t: float) -> None:
        datagram = self.encoder.encode(contractions, head_pose, t)
        try:
            self.bytes_sent += self._socket.sendto(datagram, self.address)
            self.sent += 1
        except OSError as error:  # full buffer, nobody listening, network down: drop, never stall
            self.dropped += 1
            self.last_error = error

    def close(self) -> None:
        self._socket.close()

    def __enter__(self) -> LiveLinkOutput:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
