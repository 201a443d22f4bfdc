"""Live Link Face in: simulated iPhone -> receiver -> ARKit solve -> 16 simulated servos; latency, rate, accuracy.

The simulated iPhone (:mod:`livebridge.simulators.iphone`) sends the app's packets at 60 Hz over loopback
from the performer's ``mixed`` script; the receiver (:mod:`livebridge.arkit.receiver`) takes them off the
socket; each newest packet is solved (:class:`livebridge.arkit.solve.ArkitSolver`, ICT-FaceKit's ARKit shapes
when the reference data is here, else the built-in face with shapes from its muscles) and written to 16
Dynamixel XL330s simulated on a pseudo-terminal (:class:`livebridge.servo.output.ServoOutput`).

Figures:

- ``packet_to_servo_p50_ms`` / ``_p99_ms``: the phone's ``sendto`` of a packet -> that frame's servo bytes
  written (the UDP hop, the receiver's decode and hand-over, the solve, the safety stage and the write);
- ``rmse``: solved contractions against the contractions behind each packet (ground truth);
- ``packets_per_s``: valid packets the receiver thread takes, decodes and hands on per second when the
  phone sends unpaced (``receiver_loss`` the share the socket buffer dropped meanwhile);
- ``decode_ratio``: our decoder's packets per second over a field-by-field ``struct`` decoder's (the way the
  open re-implementations PyLiveLinkFace and LLV parse), on the same packets.
"""

from __future__ import annotations

import multiprocessing
import os
import struct
import time

import numpy as np

P99_BAR_MS = 2.0


def _basis_and_shapes():
    from livebridge.arkit.shapes import arkit_shapes_from_muscles, load_arkit_shapes
    from livebridge.bench.data import ict_basis, shared_data_dir
    from livebridge.face.shipped import load_marker_set

    basis = ict_basis()
    if basis is not None:
        shapes = load_arkit_shapes(shared_data_dir() / "ict-facekit" / "face_region.npz", units="cm")
        return "ict-facekit", basis, load_marker_set("ict-68"), shapes
    from livebridge.face.builtin import builtin_basis

    basis = builtin_basis()
    return "builtin", basis, load_marker_set("builtin"), arkit_shapes_from_muscles(basis)


def _struct_decode(data: bytes) -> tuple:
    """The peer: a field-by-field struct decoder as the open re-implementations write one."""
    (n,) = struct.unpack_from(">i", data, 1)
    device = data[5:5 + n].decode()
    offset = 5 + n
    (m,) = struct.unpack_from(">i", data, offset)
    subject = data[offset + 4:offset + 4 + m].decode()
    offset += 4 + m
    frame, sub_frame, numerator, denominator, count = struct.unpack_from(">ifiiB", data, offset)
    values = struct.unpack_from(">61f", data, offset + 17)
    return device, subject, frame, sub_frame, numerator, denominator, count, values


def _decode_rates(datagrams: list[bytes], repeats: int) -> tuple[float, float]:
    from livebridge.arkit.packet import decode_packet

    rates = []
    for decode in (decode_packet, _struct_decode):
        t0 = time.perf_counter()
        for _ in range(repeats):
            for data in datagrams:
                decode(data)
        rates.append(repeats * len(datagrams) / (time.perf_counter() - t0))
    return rates[0], rates[1]


def _receiver_rate(muscle_names, n: int) -> tuple[float, float]:
    """(valid packets per second the receiver thread handles, share lost) with an unpaced phone."""
    from livebridge.arkit.receiver import LiveLinkReceiver
    from livebridge.simulators.iphone import SimulatedIPhone

    with LiveLinkReceiver("livelinkface://:0") as receiver:
        phone = SimulatedIPhone(muscle_names, port=receiver.bound[1], seed=2)
        datagrams = [phone.datagram(phone.frame0 + k) for k in range(n)]
        import socket

        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
            t0 = time.perf_counter()
            for data in datagrams:
                sender.sendto(data, receiver.bound)
            deadline, last = time.monotonic() + 5.0, -1
            while receiver.received != last and time.monotonic() < deadline:
                last = receiver.received
                time.sleep(0.02)
            elapsed = time.perf_counter() - t0 - 0.02
        return receiver.accepted / elapsed, 1.0 - receiver.received / n


def _phone_process(muscle_names, port: int, n_frames: int, results) -> None:
    """The simulated iPhone in its own process (a phone is its own device): paced packets, then its send times."""
    from livebridge.simulators.iphone import SimulatedIPhone

    phone = SimulatedIPhone(muscle_names, port=port, script="mixed", seed=1)
    phone.run(n_frames, realtime=True)
    results.put(phone.send_times)


def run(quick: bool, log) -> dict:
    from livebridge.arkit.receiver import LiveLinkReceiver
    from livebridge.arkit.solve import ArkitSolver
    from livebridge.servo.output import ServoOutput
    from livebridge.servo.rig import demo_rig
    from livebridge.simulators.iphone import SimulatedIPhone

    face, basis, markers, shapes = _basis_and_shapes()
    n_frames = 240 if quick else 1800
    solver = ArkitSolver(basis, markers, shapes)
    servo = ServoOutput(demo_rig("simdynamixel://?ids=1-16&model=XL330-M288&delay=0", basis.names), basis.names)
    latencies, errors, written = [], [], 0
    try:
        servo.configure()
        servo.activate()
        state = solver.initial_state()
        solver.step(state, np.zeros(52))  # warm: the servo path's first frame compiles, not a measured one
        servo.send(np.zeros(basis.n_muscles), poll=False)
        truth = SimulatedIPhone(basis.names, script="mixed", seed=1)
        context = multiprocessing.get_context("spawn")
        results = context.Queue()
        with LiveLinkReceiver("livelinkface://:0") as receiver:
            log(f"{face}: {n_frames} packets at 60 Hz, simulated iPhone (own process) -> receiver -> solve -> "
                "16 servos")
            phone = context.Process(target=_phone_process, args=(basis.names, receiver.bound[1], n_frames, results))
            phone.start()
            received_at = {}
            while phone.is_alive() or receiver.superseded + written < receiver.accepted:
                arrival = receiver.get(0.1)
                if arrival is None:
                    continue
                state, result = solver.step(state, arrival.packet.weights)
                servo.send(result.contractions, poll=False)
                frame = arrival.packet.frame_number
                received_at[frame] = time.monotonic()  # servo bytes written
                written += 1
                errors.append(result.contractions - truth.truth(frame))
                servo.poll()
            send_times = results.get(timeout=10.0)
            phone.join(timeout=5.0)
            status = receiver.status()
            latencies = [t - send_times[frame] for frame, t in received_at.items()]
    finally:
        servo.close(ease=False)
    latency_ms = 1000 * np.asarray(latencies)
    rmse = float(np.sqrt(np.mean(np.square(errors))))
    pps, loss = _receiver_rate(basis.names, 3000 if quick else 20000)
    sample = [SimulatedIPhone(basis.names, seed=4).datagram(216000 + k) for k in range(200)]
    ours, peer = _decode_rates(sample, 5 if quick else 50)
    result = {
        "face": face, "frames_sent": n_frames, "frames_to_servo": written, "receiver": status,
        "packet_to_servo_p50_ms": float(np.percentile(latency_ms, 50)),
        "packet_to_servo_p99_ms": float(np.percentile(latency_ms, 99)),
        "packet_to_servo_bar_ms": P99_BAR_MS,
        "rmse": rmse,
        "packets_per_s": pps, "receiver_loss": loss,
        "decode_per_s": ours, "peer_decode_per_s": peer, "decode_ratio": ours / peer,
        "peer": "field-by-field struct decoder (as PyLiveLinkFace / LLV parse; it checks nothing)",
        "load_average_1min": os.getloadavg()[0], "cpus": os.cpu_count(),
    }
    log(f"packet -> servo p50 {result['packet_to_servo_p50_ms']:.3f} ms, p99 {result['packet_to_servo_p99_ms']:.3f} "
        f"ms (bar {P99_BAR_MS} ms); rmse {rmse:.4f}; receiver {pps:.0f} packets/s (loss {loss:.1%}); decode "
        f"{ours:.0f}/s vs struct {peer:.0f}/s = {ours / peer:.2f}x")
    return result
