"""The Live Link Face packet: one UDP datagram per frame from the iPhone app to Unreal (and from us to Unreal).

Layout (packet version 6, every number big-endian, no padding)::

    uint8    version            6
    int32    n                  device id: byte count, then n bytes of UTF-8 (no terminator)
    int32    m                  subject name: byte count, then m bytes of UTF-8
    int32    frame number       frame time (FFrameTime) ...
    float32  sub-frame          ... fraction of a frame, in [0, 1)
    int32    rate numerator     frame rate (FFrameRate), e.g. 60 / 1
    int32    rate denominator
    uint8    count              61
    float32  values[61]         the 52 ARKit blendshapes in Apple's order, then head yaw, pitch, roll,
                                left eye yaw, pitch, roll, right eye yaw, pitch, roll (:mod:`.names`)

Sources, read and checked against each other:

- Unreal Engine, ``Engine/Plugins/Runtime/AR/AppleAR/AppleARKitFaceSupport/Source/AppleARKitFaceSupport/
  Private/AppleARKitLiveLinkSource.cpp`` (``FAppleARKitLiveLinkRemotePublisher::PublishBlendShapes`` and the
  listener's ``Tick``): the fields above written in that order through ``FNboSerializeToBuffer`` (network
  byte order; a string is an int32 byte count and its UTF-8 bytes), the listener refusing a packet of
  another version or another count. Its history: 4 added the device id, 5 a timecode and a uint32 rate,
  6 the qualified frame time (int32 frame, float sub-frame, int32/int32 rate) used by current versions.
- think-biq/LLV ``src/llv/gesicht.py`` (BSD-2-Clause): a version-6 reader and writer with exactly this
  layout (minimum packet 264 bytes, maximum 774: names of at most 256 characters), and recordings made
  from the app (``examples/*.gesichter``): a frame of those parses here field for field.
- JimWest/PyLiveLinkFace ``pylivelinkface/pylivelinkface.py``: writes the version as a little-endian int32
  ``06 00 00 00`` followed by ``"$" + uuid``; for a 36-character UUID that is the same bytes as the
  version byte and the big-endian length ``00 00 00 24`` (``0x24`` is ``"$"``), so its packets are valid
  version-6 packets, and the tests decode one built its way.

Units: blendshape weights are in [0, 1]. Rotations are normalised as Live Link Face receivers read them:
1.0 is a quarter turn (90 degrees), so they lie in [-1, 1].

Encoding and decoding are pure functions over bytes; :class:`PacketError` says why a datagram is refused
with a short reason (:data:`REASONS`) the receiver counts.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

from livebridge.arkit.names import N_BLENDSHAPES, N_VALUES

VERSION = 6
MAX_NAME_BYTES = 256  # the receivers size their buffer for names of 256 characters
WEIGHT_SLACK = 1e-3  # float rounding on the phone: a weight this far outside [0, 1] is clipped, further refused
MAX_ROTATION = 1.0  # normalised: a quarter turn
REASONS = ("short", "version", "name", "count", "length", "non-finite", "range")
_INT = struct.Struct(">i")
_TIME = struct.Struct(">ifii")
_VALUES = np.dtype(">f4")
_VALUE_STRUCT = struct.Struct(f">{N_VALUES}f")
MIN_SIZE = 1 + 4 + 4 + _TIME.size + 1 + 4 * N_VALUES  # empty names: 270 bytes
MAX_SIZE = MIN_SIZE + 2 * MAX_NAME_BYTES


class PacketError(ValueError):
    """A datagram that is not a valid Live Link Face packet; ``reason`` is one of :data:`REASONS`."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True, eq=False)
class LiveLinkPacket:
    """One Live Link Face frame.

    Attributes
    ----------
    device_id, subject : str
    frame_number : int
    sub_frame : float
        Fraction of a frame, [0, 1).
    rate : tuple of (int, int)
        Frame rate as numerator / denominator (60 / 1).
    values : ndarray, shape (61,)
        Blendshape weights (52, [0, 1]) then the nine normalised rotations ([-1, 1]).
    """

    device_id: str
    subject: str
    frame_number: int
    sub_frame: float
    rate: tuple[int, int]
    values: np.ndarray

    @property
    def weights(self) -> np.ndarray:
        """The 52 ARKit blendshape weights, shape (52,)."""
        return self.values[:N_BLENDSHAPES]

    @property
    def head_rotation(self) -> np.ndarray:
        """Head yaw, pitch, roll, normalised (1.0 = 90 degrees), shape (3,)."""
        return self.values[N_BLENDSHAPES:N_BLENDSHAPES + 3]

    @property
    def time_s(self) -> float:
        """The frame time in seconds (frame number plus sub-frame over the rate)."""
        numerator, denominator = self.rate
        return (self.frame_number + self.sub_frame) * denominator / numerator if numerator else float("nan")


def _name_bytes(text: str, what: str) -> bytes:
    data = text.encode("utf-8")
    if len(data) > MAX_NAME_BYTES:
        raise ValueError(f"{what} is {len(data)} bytes of UTF-8; receivers take at most {MAX_NAME_BYTES}")
    return _INT.pack(len(data)) + data


def encode_packet(packet: LiveLinkPacket) -> bytes:
    """The datagram of ``packet`` (values written as big-endian float32)."""
    values = np.asarray(packet.values, dtype=np.float64)
    if values.shape != (N_VALUES,):
        raise ValueError(f"values must have shape ({N_VALUES},), got {values.shape}")
    return b"".join((bytes((VERSION,)), _name_bytes(packet.device_id, "device id"),
                     _name_bytes(packet.subject, "subject name"),
                     _TIME.pack(int(packet.frame_number), float(packet.sub_frame), *map(int, packet.rate)),
                     bytes((N_VALUES,)), values.astype(_VALUES).tobytes()))


def _read_name(data: bytes, offset: int, what: str) -> tuple[str, int]:
    if len(data) < offset + 4:
        raise PacketError("short", f"ends inside the {what} length")
    (size,) = _INT.unpack_from(data, offset)
    if not 0 <= size <= MAX_NAME_BYTES:
        raise PacketError("name", f"{what} length {size} is outside 0..{MAX_NAME_BYTES}")
    end = offset + 4 + size
    if len(data) < end:
        raise PacketError("short", f"ends inside the {what}")
    try:
        return data[offset + 4:end].decode("utf-8"), end
    except UnicodeDecodeError:
        raise PacketError("name", f"{what} is not UTF-8") from None


def decode_packet(data: bytes) -> LiveLinkPacket:
    """Parse one datagram; anything but a complete, in-range version-6 packet raises :class:`PacketError`.

    Weights within :data:`WEIGHT_SLACK` of [0, 1] are clipped into it; the returned values are finite.
    """
    if len(data) < MIN_SIZE:
        raise PacketError("short", f"{len(data)} bytes; a packet has at least {MIN_SIZE}")
    if data[0] != VERSION:
        raise PacketError("version", f"version {data[0]}; this reads version {VERSION}")
    device_id, offset = _read_name(data, 1, "device id")
    subject, offset = _read_name(data, offset, "subject name")
    if len(data) < offset + _TIME.size + 1:
        raise PacketError("short", "ends inside the frame time")
    frame_number, sub_frame, numerator, denominator = _TIME.unpack_from(data, offset)
    offset += _TIME.size
    if data[offset] != N_VALUES:
        raise PacketError("count", f"{data[offset]} values; Live Link Face sends {N_VALUES}")
    offset += 1
    end = offset + 4 * N_VALUES
    if len(data) != end:
        raise PacketError("short" if len(data) < end else "length",
                          f"{len(data)} bytes; this packet's fields make {end}")
    # builtins over the unpacked tuple: a packet is 61 numbers, where numpy's per-call overhead would dominate
    values = _VALUE_STRUCT.unpack_from(data, offset)
    if not (all(map(math.isfinite, values)) and math.isfinite(sub_frame)):
        raise PacketError("non-finite", "NaN or infinity among the values")
    weights = values[:N_BLENDSHAPES]
    low, high = min(weights), max(weights)
    if low < -WEIGHT_SLACK or high > 1.0 + WEIGHT_SLACK:
        raise PacketError("range", f"a weight outside [0, 1] ({low:.4g} .. {high:.4g})")
    if max(map(abs, values[N_BLENDSHAPES:])) > MAX_ROTATION:
        raise PacketError("range", "a rotation outside [-1, 1] (a quarter turn)")
    values = np.array(values)
    if low < 0.0 or high > 1.0:
        np.clip(values[:N_BLENDSHAPES], 0.0, 1.0, out=values[:N_BLENDSHAPES])
    return LiveLinkPacket(device_id, subject, frame_number, sub_frame, (numerator, denominator), values)
