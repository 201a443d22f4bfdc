"""The Live Link Face packet: golden bytes from the documented layout, round trips, the open
re-implementations' packets, and every malformed datagram refused with its reason."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from livebridge.arkit.names import ARKIT_NAMES, LIVELINK_NAMES, N_VALUES
from livebridge.arkit.packet import (
    MIN_SIZE,
    REASONS,
    LiveLinkPacket,
    PacketError,
    decode_packet,
    encode_packet,
)


def hand_built(device: bytes, subject: bytes, frame: int, sub_frame: float, rate: tuple[int, int],
               values) -> bytes:
    """A version-6 packet written field by field from the documented layout, without the codec."""
    out = bytearray([6])
    out += len(device).to_bytes(4, "big") + device
    out += len(subject).to_bytes(4, "big") + subject
    out += frame.to_bytes(4, "big", signed=True) + struct.pack(">f", sub_frame)
    out += rate[0].to_bytes(4, "big") + rate[1].to_bytes(4, "big")
    out += bytes([61])
    for value in values:
        out += struct.pack(">f", value)
    return bytes(out)


def sample_values(rng) -> np.ndarray:
    values = np.concatenate([rng.uniform(0, 1, 52), rng.uniform(-1, 1, 9)])
    return values.astype(np.float32).astype(np.float64)  # what survives the wire


def test_the_names_are_apples_52_then_the_nine_rotations():
    assert len(ARKIT_NAMES) == 52 and len(set(ARKIT_NAMES)) == 52 and N_VALUES == 61
    assert ARKIT_NAMES[0] == "eyeBlinkLeft" and ARKIT_NAMES[17] == "jawOpen" and ARKIT_NAMES[-1] == "tongueOut"
    assert LIVELINK_NAMES[52:55] == ("headYaw", "headPitch", "headRoll")


def test_our_packet_equals_one_built_by_hand_byte_for_byte(rng):
    values = sample_values(rng)
    packet = LiveLinkPacket("7A3E5C1B-0000-4C6D-8E9F-0A1B2C3D4E5F", "Gesicht ü", 216_123, 0.25, (60, 1), values)
    expected = hand_built(packet.device_id.encode(), "Gesicht ü".encode(), 216_123, 0.25, (60, 1), values)
    assert encode_packet(packet) == expected
    assert expected[:5] == b"\x06\x00\x00\x00\x24"  # version 6, then the 36-byte device id's length


def test_ours_parses_back_to_the_same_values(rng):
    values = sample_values(rng)
    packet = LiveLinkPacket("phone", "", -5, 0.5, (30000, 1001), values)
    back = decode_packet(encode_packet(packet))
    assert (back.device_id, back.subject, back.frame_number, back.sub_frame, back.rate) == \
        ("phone", "", -5, 0.5, (30000, 1001))
    np.testing.assert_array_equal(back.values, values)
    np.testing.assert_array_equal(back.head_rotation, values[52:55])
    assert back.time_s == pytest.approx(-4.5 * 1001 / 30000)


def test_a_pylivelinkface_packet_parses():
    # PyLiveLinkFace's README example: a face with the head turned, encoded its way: the version as a
    # little-endian int32, "$" + uuid as the id (the "$" is the length byte 36), a name with a big-endian
    # length, frame and the int 1056060032 as the sub-frame, fps/denominator, count and 61 floats.
    uuid = "0fa1d9e2-3b7c-11ee-9a4d-0242ac120002"
    shapes = [0.0] * 61
    shapes[52], shapes[53], shapes[54] = 0.25, -0.5, 0.125  # HeadYaw, HeadPitch, HeadRoll
    data = (struct.pack("<I", 6) + ("$" + uuid).encode() + struct.pack("!i", len("Python_LiveLinkFace"))
            + b"Python_LiveLinkFace" + struct.pack("!II", 1234, 1056060032) + struct.pack("!II", 60, 1)
            + struct.pack("!B61f", 61, *shapes))
    packet = decode_packet(data)
    assert packet.device_id == uuid and packet.subject == "Python_LiveLinkFace"
    assert packet.frame_number == 1234 and packet.rate == (60, 1)
    assert packet.sub_frame == pytest.approx(struct.unpack(">f", struct.pack(">I", 1056060032))[0])
    np.testing.assert_array_equal(packet.head_rotation, [0.25, -0.5, 0.125])


def test_an_llv_default_frame_parses():
    # think-biq/LLV's documented default frame (FaceFrame.from_default): its device id and subject,
    # frame 1337, sub-frame 0.121, 60/1, every blendshape 0; LLV's bounds: 264..774 bytes.
    data = hand_built(b"DEADC0DE-1337-1337-1337-CAFEBABE", b"LLV Default Device", 1337, 0.121, (60, 1),
                      [0.0] * 61)
    assert 264 <= len(data) <= 774
    packet = decode_packet(data)
    assert packet.device_id == "DEADC0DE-1337-1337-1337-CAFEBABE" and packet.frame_number == 1337
    assert packet.sub_frame == pytest.approx(0.121) and not packet.values.any()


def _valid(rng) -> bytes:
    return encode_packet(LiveLinkPacket("dev", "subj", 10, 0.0, (60, 1), sample_values(rng)))


def _with_value(index: int, value: float) -> bytes:
    values = [0.0] * 61
    values[index] = value
    return hand_built(b"dev", b"subj", 10, 0.0, (60, 1), values)


MALFORMED = [
    ("empty", lambda good: b"", "short"),
    ("one byte short", lambda good: good[:-1], "short"),
    ("a version byte only", lambda good: b"\x06", "short"),
    ("version 5", lambda good: b"\x05" + good[1:], "version"),
    ("version 7", lambda good: b"\x07" + good[1:], "version"),
    ("trailing byte", lambda good: good + b"\x00", "length"),
    ("count 52", lambda good: good[:1 + 7 + 8 + 16] + bytes([52]) + good[1 + 7 + 8 + 17:], "count"),
    ("negative name length", lambda good: good[:1] + b"\xff\xff\xff\xfd" + good[5:], "name"),
    ("huge name length", lambda good: good[:1] + b"\x7f\x00\x00\x00" + good[5:], "name"),
    ("name longer than the packet", lambda good: good[:1] + (len(good)).to_bytes(4, "big") + good[5:], "name"),
    ("device id not UTF-8", lambda good: good[:5] + b"\xff\xfe\xfd" + good[8:], "name"),
    ("NaN weight", lambda good: _with_value(3, float("nan")), "non-finite"),
    ("infinite rotation", lambda good: _with_value(53, float("inf")), "non-finite"),
    ("weight 1.5", lambda good: _with_value(17, 1.5), "range"),
    ("weight -0.2", lambda good: _with_value(0, -0.2), "range"),
    ("head yaw 3 quarter turns", lambda good: _with_value(52, 3.0), "range"),
]


@pytest.mark.parametrize(("what", "make", "reason"), MALFORMED, ids=[row[0] for row in MALFORMED])
def test_malformed_packets_are_refused_with_their_reason(rng, what, make, reason):
    with pytest.raises(PacketError) as caught:
        decode_packet(make(_valid(rng)))
    assert caught.value.reason == reason and reason in REASONS


def test_a_nan_sub_frame_is_refused():
    data = bytearray(_with_value(0, 0.0))
    data[1 + 7 + 8 + 4:1 + 7 + 8 + 8] = struct.pack(">f", float("nan"))
    with pytest.raises(PacketError, match="NaN"):
        decode_packet(bytes(data))


def test_rounding_just_outside_the_weight_range_is_clipped_not_refused():
    packet = decode_packet(_with_value(5, 1.0004))
    assert packet.values[5] == 1.0
    assert MIN_SIZE == 270


def test_random_bytes_never_pass_or_crash(rng):
    good = _valid(rng)
    for _ in range(2000):
        data = bytearray(good)
        for position in rng.integers(0, len(data), rng.integers(1, 6)):
            data[position] = rng.integers(0, 256)
        try:
            packet = decode_packet(bytes(data))
        except PacketError:
            continue
        assert np.isfinite(packet.values).all()
        assert packet.weights.min() >= 0 and packet.weights.max() <= 1
        assert np.abs(packet.values[52:]).max() <= 1
