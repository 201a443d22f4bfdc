"""Live Link Face in, through the real pipeline: simulated iPhone -> receiver -> LiveLinkFront -> Pipeline -> servos.

The simulated iPhone (:mod:`livebridge.simulators.iphone`), in its own process as a phone is its own device,
sends the app's packets at 60 Hz over loopback from the performer's ``mixed`` script; the pipeline is the one
``livebridge run`` builds for a phone session: :class:`~livebridge.arkit.front.LiveLinkFront` (reads the
socket on the front thread, newest packet, ARKit solve with ICT-FaceKit's ARKit shapes when the reference
data is here, else the built-in face with shapes from its muscles) in
:class:`~livebridge.runtime.pipeline.Pipeline`, writing 16 Dynamixel XL330s simulated on a pseudo-terminal by
a simulator in its own process (the demo's bus).

Figures:

- ``packet_to_servo_p50_ms`` / ``_p99_ms``: a packet's arrival at this machine (the kernel's receive time of
  the datagram, ``SO_TIMESTAMPNS``) -> that frame's servo bytes written by the pipeline's front thread
  (``FrameTiming.servo - FrameTiming.complete``): the wait in the socket, decode, the solve, the safety
  stage and the bus write; ``send_to_servo_p50_ms`` / ``_p99_ms`` also count the loopback hop from the
  phone process's ``sendto``;
- ``rmse``: solved contractions against the contractions behind each solved packet (ground truth);
- ``packets_per_s``: valid packets the receiver takes, decodes and hands on per second, read as the live
  front reads it, when the phone sends unpaced from another process (``receiver_loss``: the share the
  socket buffer dropped meanwhile);
- ``decode_ratio``: our decoder's packets per second over a field-by-field ``struct`` decoder's (the way the
  open re-implementations PyLiveLinkFace and LLV parse), on the same packets.

The machine's 1-minute load average is reported with the figures: latency percentiles on a shared machine
move with it.
"""

from __future__ import annotations

import multiprocessing
import os
import queue
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


def _send_all(datagrams: list[bytes], address) -> None:
    """Send ``datagrams`` as fast as the socket takes them (an unpaced phone, in its own process)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
        for data in datagrams:
            sender.sendto(data, address)


def _receiver_rate(muscle_names, n: int) -> tuple[float, float]:
    """(valid packets per second the receiver takes, decodes and hands on, read as the live front reads it;
    share lost) with an unpaced phone in another process."""
    from livebridge.arkit.receiver import LiveLinkReceiver
    from livebridge.simulators.iphone import SimulatedIPhone

    with LiveLinkReceiver("livelinkface://:0") as receiver:
        phone = SimulatedIPhone(muscle_names, port=receiver.bound[1], seed=2)
        datagrams = [phone.datagram(phone.frame0 + k) for k in range(n)]
        sender = multiprocessing.get_context("fork").Process(target=_send_all, args=(datagrams, receiver.bound))
        t0 = time.perf_counter()
        sender.start()
        t_last, quiet = t0, 0
        while quiet < 10:  # until the phone is done and nothing came for 10 reads of 20 ms
            received = receiver.received
            receiver.receive(0.02)
            if receiver.received != received:
                t_last, quiet = time.perf_counter(), 0
            elif not sender.is_alive():
                quiet += 1
        sender.join()
        return receiver.accepted / (t_last - t0), 1.0 - receiver.received / n


def _phone_process(muscle_names, port: int, n_frames: int, results) -> None:
    """The simulated iPhone in its own process (a phone is its own device): paced packets, then its send times."""
    from livebridge.simulators.iphone import SimulatedIPhone

    phone = SimulatedIPhone(muscle_names, port=port, script="mixed", seed=1)
    phone.run(n_frames, realtime=True)
    results.put(phone.send_times)


def _through_the_pipeline(basis, markers, shapes, n_frames: int, log) -> dict:
    """Run the phone against the real pipeline; per solved frame: (frame number, arrival, servo written, x)."""
    from livebridge.arkit.front import LiveLinkFront
    from livebridge.arkit.receiver import LiveLinkReceiver
    from livebridge.arkit.solve import ArkitSolver
    from livebridge.runtime.pipeline import Pipeline
    from livebridge.servo.output import ServoOutput
    from livebridge.servo.rig import demo_rig

    receiver = LiveLinkReceiver("livelinkface://127.0.0.1:0")
    receiver.open()
    front = LiveLinkFront(receiver, ArkitSolver(basis, markers, shapes))
    servo = ServoOutput(demo_rig("simdynamixel://?ids=1-16&model=XL330-M288&delay=0&process=1", basis.names),
                        basis.names, poll_every=15)
    frames = []
    try:
        servo.configure()
    except BaseException:
        receiver.stop()
        raise
    pipeline = Pipeline(front, servo=servo, on_frame=frames.append)
    context = multiprocessing.get_context("spawn")
    results = context.Queue()
    phone = context.Process(target=_phone_process, args=(basis.names, receiver.bound[1], n_frames, results))
    status = ""
    with pipeline:
        phone.start()
        deadline = time.monotonic() + 60.0 + 2 * n_frames / 60  # a hang guard: the phone sends for n_frames / 60 s
        send_times = None
        while send_times is None:  # read before joining: a child holding queued data does not exit
            try:
                send_times = results.get(timeout=0.05)
            except queue.Empty:
                if time.monotonic() > deadline or not phone.is_alive():
                    raise RuntimeError("the simulated iPhone's process ended without its send times") from None
            if not status and front.frames >= n_frames // 2:
                status = pipeline.status_line()  # the live status line, half-way
        phone.join(timeout=5.0)
        deadline = time.monotonic() + 5.0
        while front.frames + receiver.superseded < receiver.accepted and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.1)  # the outputs of the last frame
    return {"frames": frames, "send_times": send_times, "status": status, "received": receiver.received,
            "accepted": receiver.accepted, "superseded": receiver.superseded, "lost": receiver.lost}


def run(quick: bool, log) -> dict:
    from livebridge.simulators.iphone import SimulatedIPhone

    face, basis, markers, shapes = _basis_and_shapes()
    n_frames = 240 if quick else 1800
    log(f"{face}: {n_frames} packets at 60 Hz, simulated iPhone (own process) -> receiver -> LiveLinkFront -> "
        "Pipeline -> 16 simulated servos (own process)")
    load_before = os.getloadavg()[0]
    run_ = _through_the_pipeline(basis, markers, shapes, n_frames, log)
    frames = [f for f in run_["frames"] if np.isfinite(f.timing.servo)]
    arrival_ms = 1000 * np.array([f.timing.servo - f.timing.complete for f in frames])
    send_ms = 1000 * np.array([f.timing.servo - run_["send_times"][f.seq] for f in frames
                               if f.seq in run_["send_times"]])
    truth = SimulatedIPhone(basis.names, script="mixed", seed=1)
    x = np.array([f.contractions for f in frames])
    rmse = float(np.sqrt(np.mean((x - truth.truth(np.array([f.seq for f in frames]))) ** 2)))
    pps, loss = _receiver_rate(basis.names, 3000 if quick else 20000)
    sample = [SimulatedIPhone(basis.names, seed=4).datagram(216000 + k) for k in range(200)]
    ours, peer = _decode_rates(sample, 5 if quick else 50)
    result = {
        "face": face, "frames_sent": n_frames, "datagrams_received": run_["received"],
        "frames_to_servo": len(frames), "superseded": run_["superseded"], "lost": run_["lost"],
        "status_line": run_["status"],
        "packet_to_servo_p50_ms": float(np.percentile(arrival_ms, 50)),
        "packet_to_servo_p99_ms": float(np.percentile(arrival_ms, 99)),
        "packet_to_servo_max_ms": float(arrival_ms.max()),
        "packet_to_servo_bar_ms": P99_BAR_MS,
        "send_to_servo_p50_ms": float(np.percentile(send_ms, 50)),
        "send_to_servo_p99_ms": float(np.percentile(send_ms, 99)),
        "rmse": rmse,
        "packets_per_s": pps, "receiver_loss": loss,
        "decode_per_s": ours, "peer_decode_per_s": peer, "decode_ratio": ours / peer,
        "peer": "field-by-field struct decoder (as PyLiveLinkFace / LLV parse; it checks nothing)",
        "load_average_1min_before": load_before, "load_average_1min": os.getloadavg()[0], "cpus": os.cpu_count(),
    }
    log(f"packet -> servo p50 {result['packet_to_servo_p50_ms']:.3f} ms, p99 {result['packet_to_servo_p99_ms']:.3f} "
        f"ms (bar {P99_BAR_MS} ms; load {result['load_average_1min']:.1f} on {os.cpu_count()} CPUs); rmse "
        f"{rmse:.4f}; receiver {pps:.0f} packets/s (loss {loss:.1%}); decode {ours:.0f}/s vs struct {peer:.0f}/s "
        f"= {ours / peer:.2f}x")
    return result
