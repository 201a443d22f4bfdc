"""Live Link Face in and out: the receiver (loopback, refusals counted, floods), the ARKit solve against
ground truth on ICT-FaceKit and the built-in face, the output's packets, and the simulated iPhone."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from livebridge.arkit.head import head_pose_from_rotation, rotation_from_head_pose
from livebridge.arkit.names import ARKIT_NAMES
from livebridge.arkit.packet import LiveLinkPacket, decode_packet, encode_packet
from livebridge.arkit.receiver import LiveLinkReceiver, parse_receiver_url
from livebridge.arkit.shapes import arkit_shapes_from_deltas, arkit_shapes_from_muscles, load_arkit_shapes
from livebridge.arkit.solve import ArkitSolver
from livebridge.errors import InputError
from livebridge.face.builtin import builtin_basis
from livebridge.face.shipped import load_marker_set
from livebridge.output.blendshapes import BlendshapeMap
from livebridge.output.livelink import LiveLinkEncoder, LiveLinkOutput
from livebridge.simulators.iphone import SimulatedIPhone
from livebridge.simulators.performer import ContractionScript

FPS = 60


def packet(frame: int, device: str = "phone", values=None) -> bytes:
    values = np.zeros(61) if values is None else values
    return encode_packet(LiveLinkPacket(device, "s", frame, 0.0, (FPS, 1), values))


# ------------------------------------------------------------------ receiver
def test_the_receiver_binds_loopback_unless_told_otherwise():
    assert parse_receiver_url("livelinkface://").host == "127.0.0.1"
    assert parse_receiver_url("livelinkface://:11111").port == 11111
    assert parse_receiver_url("livelinkface://0.0.0.0:9000").host == "0.0.0.0"
    receiver = LiveLinkReceiver("livelinkface://:0")
    try:
        host, port = receiver.open()
        assert host == "127.0.0.1" and port > 0
    finally:
        receiver.stop()


def test_ingest_counts_every_refusal_and_gaps():
    receiver = LiveLinkReceiver()
    assert receiver.ingest(packet(100), 1.0) is not None
    receiver.ingest(b"\x06garbage", 1.1)
    receiver.ingest(packet(101, device="another phone"), 1.2)
    receiver.ingest(packet(100), 1.3)  # reordered: behind the last one taken
    assert receiver.ingest(packet(105), 1.4).packet.frame_number == 105
    assert receiver.ingest(packet(105 - 10 * FPS), 1.5) is not None  # ten seconds back: the phone restarted
    assert receiver.dropped == {"short": 1, "other-device": 1, "stale": 1}
    assert (receiver.received, receiver.accepted, receiver.lost) == (6, 3, 4)  # 101..104
    assert receiver.newest().packet.frame_number == 105 - 10 * FPS  # the newest
    assert receiver.superseded == 2
    assert "lost 4" in receiver.status() and "stale 1" in receiver.status()


def test_a_named_device_is_the_only_one_followed():
    receiver = LiveLinkReceiver("livelinkface://:0?device=mine")
    receiver.ingest(packet(1, device="theirs"), 0.0)
    receiver.ingest(packet(2, device="mine"), 0.0)
    assert receiver.dropped == {"other-device": 1} and receiver.accepted == 1


def _flood(datagrams: list[bytes], address, rate_hz: float) -> None:
    """Send ``datagrams`` at ``rate_hz`` from another process, as a phone (or an attacker) would."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
        t0 = time.monotonic()
        for k, datagram in enumerate(datagrams):
            while time.monotonic() < t0 + k / rate_hz:
                pass
            sender.sendto(datagram, address)


def test_a_flood_at_10_khz_of_good_and_bad_packets_is_counted_and_only_the_newest_kept(rng):
    import multiprocessing

    bad = [b"", packet(1)[:-3], b"\x05" + packet(1)[1:], packet(1) + b"x"]
    n, frame, datagrams = 3000, 1000, []
    for k in range(n):
        if k % 3 == 2:
            datagrams.append(bad[k % len(bad)])
        else:
            frame += 1
            values = np.zeros(61)
            values[17] = (frame % 100) / 100
            datagrams.append(packet(frame, values=values))
    with LiveLinkReceiver("livelinkface://:0") as receiver:
        sender = multiprocessing.get_context("fork").Process(target=_flood, args=(datagrams, receiver.bound, 10_000))
        sender.start()
        returned = []  # read as the live front reads, while the flood goes on; then until it stops
        deadline, quiet = time.monotonic() + 60, 0
        while quiet < 5 and time.monotonic() < deadline:
            arrival = receiver.receive(0.1)
            returned += [arrival] if arrival is not None else []
            quiet = 0 if sender.is_alive() or arrival is not None else quiet + 1
        sender.join(timeout=5)
        assert sender.exitcode == 0
        assert receiver.received > 0.5 * n  # loopback may drop some under a flood
        assert receiver.accepted + sum(receiver.dropped.values()) == receiver.received
        assert set(receiver.dropped) <= {"short", "version", "length"} and sum(receiver.dropped.values()) > 0
        assert returned[-1].packet.frame_number == frame or receiver.lost > 0
        assert receiver.newest() is None  # the newest was returned; every older one was superseded
        assert receiver.superseded == receiver.accepted - len(returned)
        assert all(a.packet.frame_number < b.packet.frame_number for a, b in zip(returned, returned[1:]))


def test_a_taken_port_is_a_clear_error():
    with LiveLinkReceiver("livelinkface://:0") as first:
        with pytest.raises(InputError, match="cannot listen"):
            LiveLinkReceiver(f"livelinkface://127.0.0.1:{first.bound[1]}").open()


# ------------------------------------------------------------------ shapes and solve
def _recovery(basis, markers, shapes, sigma: float, seed: int = 1) -> float:
    times = np.arange(0, 40, 1 / FPS)
    truth = ContractionScript(basis.names, "mixed", seed)(times)
    weights = truth @ BlendshapeMap(basis.names).rows_for(ARKIT_NAMES).T
    if sigma:
        weights = weights + np.random.default_rng(seed).normal(0, sigma, weights.shape)
    weights = np.clip(weights, 0, 1)
    solver = ArkitSolver(basis, markers, shapes)
    state, solved = solver.initial_state(), []
    for w in weights:
        state, result = solver.step(state, w)
        solved.append(result.contractions)
    return float(np.sqrt(np.mean((np.array(solved) - truth) ** 2)))


@pytest.fixture(scope="module")
def ict_shapes(shared_data):
    return load_arkit_shapes(shared_data / "ict-facekit" / "face_region.npz", units="cm")


def test_the_ict_shapes_are_arkit_named(ict_shapes, ict):
    assert ict_shapes.missing == ("tongueOut",)  # the kit has every other ARKit shape (two as halves)
    assert ict_shapes.n_vertices == ict.n_vertices
    jaw = ict.elements[ict.index("jaw")]
    np.testing.assert_allclose(ict_shapes.deltas[ARKIT_NAMES.index("jawOpen")], jaw, atol=1e-4)


@pytest.mark.parametrize(("sigma", "bar"), [(0.0, 0.02), (0.03, 0.05)])
def test_ict_weights_come_back_as_the_contractions_that_made_them(ict, ict_shapes, sigma, bar):
    rmse = _recovery(ict, load_marker_set("ict-68"), ict_shapes, sigma)
    assert rmse <= bar


@pytest.mark.parametrize(("sigma", "bar"), [(0.0, 1e-6), (0.03, 0.05)])
def test_the_builtin_face_gets_arkit_shapes_from_its_muscles(sigma, bar):
    basis = builtin_basis()
    shapes = arkit_shapes_from_muscles(basis)
    assert "jawOpen" not in shapes.missing and "tongueOut" in shapes.missing
    assert _recovery(basis, load_marker_set("builtin"), shapes, sigma) <= bar


def test_shape_sets_refuse_what_is_not_arkit_or_not_on_the_mesh(ict):
    with pytest.raises(InputError, match="not an ARKit blendshape"):
        arkit_shapes_from_deltas(["jawOpen", "smirk"], np.zeros((2, 5, 3)))
    with pytest.raises(InputError, match="given twice"):
        arkit_shapes_from_deltas(["jawOpen", "jawOpen"], np.zeros((2, 5, 3)))
    with pytest.raises(InputError, match="NaN"):
        arkit_shapes_from_deltas(["jawOpen"], np.full((1, 5, 3), np.nan))
    small = arkit_shapes_from_deltas(["jawOpen"], np.zeros((1, 5, 3)))
    with pytest.raises(InputError, match="vertices"):
        ArkitSolver(ict, load_marker_set("ict-68"), small)


# ------------------------------------------------------------------ head rotation and output
def test_head_rotation_round_trips_and_is_bounded(rng):
    for _ in range(50):
        angles = rng.uniform(-0.9, 0.9, 3) * np.array([1, 0.5, 1])  # pitch within its Euler range
        np.testing.assert_allclose(rotation_from_head_pose(head_pose_from_rotation(angles)), angles, atol=1e-9)
    assert not rotation_from_head_pose(np.full((4, 4), np.nan)).any()
    assert not rotation_from_head_pose(None).any()


class Frame:
    def __init__(self, contractions, head_pose=None):
        self.contractions, self.head_pose = contractions, head_pose


def test_the_output_sends_the_shared_maps_weights_and_the_head_rotation():
    names = builtin_basis().names
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as listener:
        listener.bind(("127.0.0.1", 0))
        listener.settimeout(2.0)
        output = LiveLinkOutput(names, port=listener.getsockname()[1], subject="Head", device_id="DEV-1")
        try:
            x = np.linspace(0, 1, len(names))
            x[3] = np.nan  # never reaches the wire as NaN
            output.send(Frame(x, head_pose_from_rotation([0.2, -0.1, 0.05])))
            received = decode_packet(listener.recv(2048))
        finally:
            output.close()
    assert (received.subject, received.device_id, received.rate) == ("Head", "DEV-1", (60, 1))
    expected = np.clip(BlendshapeMap(names).rows_for(ARKIT_NAMES) @ np.nan_to_num(x), 0, 1)
    np.testing.assert_allclose(received.weights, expected, atol=1e-6)
    np.testing.assert_allclose(received.head_rotation, [0.2, -0.1, 0.05], atol=1e-6)
    assert "on this machine" in output.describe() and output.sent == 1


def test_the_output_refuses_a_map_to_names_unreal_does_not_know():
    with pytest.raises(InputError, match="not one of the receiver's blendshapes"):
        LiveLinkEncoder(["jaw"], mapping={"jaw": {"mouthWide": 1.0}})
    with pytest.raises(InputError, match="subject"):
        LiveLinkEncoder(["jaw"], subject="")


# ------------------------------------------------------------------ the simulated iPhone end to end
def test_a_simulated_iphone_through_the_receiver_solves_to_its_performer():
    basis = builtin_basis()
    solver = ArkitSolver(basis, load_marker_set("builtin"), arkit_shapes_from_muscles(basis))
    with LiveLinkReceiver("livelinkface://:0") as receiver:
        phone = SimulatedIPhone(basis.names, port=receiver.bound[1], script="everyday", seed=3)
        state, errors = solver.initial_state(), []
        phone.start(120, realtime=False)
        deadline = time.monotonic() + 10
        # until every datagram is off the socket and the newest one solved (the older ones are superseded)
        while (receiver.received < 120 or len(errors) + receiver.superseded < receiver.accepted) \
                and time.monotonic() < deadline:
            arrival = receiver.receive(0.05)
            if arrival is not None:
                state, result = solver.step(state, arrival.packet.weights)
                errors.append(result.contractions - phone.truth(arrival.packet.frame_number))
        phone.stop()
    assert errors and np.sqrt(np.mean(np.square(errors))) < 1e-3
    assert receiver.accepted + receiver.lost == 120 and not receiver.dropped
