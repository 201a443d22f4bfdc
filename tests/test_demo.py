"""End to end: the demo pipeline (performer, 4-camera rig, real driver on a simulated servo bus, render
client) against the simulator's ground truth."""

from __future__ import annotations

import threading

import numpy as np

from livebridge.geometry.transforms import apply
from livebridge.runtime.demo import build_demo
from livebridge.runtime.pipeline import run_until_stopped


def test_demo_end_to_end_matches_ground_truth():
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    received = []
    parts = build_demo(realtime=False, port=0, log=lambda m: None)  # 1280x800 cameras, 16 servos, render client
    pipeline = parts.pipeline
    stop = threading.Event()

    def client(url):
        with connect(url, max_size=None) as ws:
            while not stop.is_set():
                try:
                    message = ws.recv(timeout=0.5)
                except TimeoutError:
                    continue
                except ConnectionClosed:
                    return
                if isinstance(message, bytes):
                    received.append(message[:4])

    def started(p):
        thread = threading.Thread(target=client, args=(f"ws://127.0.0.1:{p.render.port}/ws",), daemon=True)
        thread.start()

    try:
        summary = run_until_stopped(pipeline, frames=300, log=lambda m: None, on_start=started)
    finally:
        stop.set()
    score = parts.score
    assert summary.solved >= 300 and score.frames >= 300
    assert score.rmse <= 0.03, score.rmse
    assert score.swaps == 0
    assert summary.labelled_fraction > 0.95  # markers seen by fewer than 2 cameras are never labelled
    assert summary.error_upper_mm < 0.5 and summary.error_lower_mm < 0.5
    assert np.isfinite(summary.latency_p99_ms) and np.isfinite(summary.render_latency_p50_ms)
    assert received[0] == (1).to_bytes(4, "little") and len(received) > 10  # the mesh, then frames
    servo = pipeline.servo
    assert servo.frames >= 300 and not servo.faults()


def test_lead_in_holds_a_still_neutral_face_then_performs():
    from livebridge.simulators.lead_in import LeadIn
    from livebridge.simulators.performer import Performer
    from livebridge.simulators.rig import default_face

    basis, markers = default_face()
    performer = Performer(basis, markers, fps=60, seed=3, realtime=False)
    lead = LeadIn(performer, 0.5)
    frames = list(lead.frames(100))
    original = list(performer.frames(70))
    neutral = markers.marker_positions(basis, np.zeros(len(basis.names)))
    rest = performer.head(np.zeros(1))[0]
    for frame in frames[:30]:
        assert not frame.contractions.any() and np.allclose(frame.head2world, rest)
        assert np.allclose(frame.marker_positions, apply(rest, neutral))
    for frame in frames[30:]:
        before = original[frame.seq - 30]
        assert np.allclose(frame.contractions, before.contractions) and np.allclose(frame.head2world, before.head2world)
        assert np.allclose(frame.marker_positions, before.marker_positions, atol=1e-9)
    assert np.allclose(lead.script(np.array([1.0]))[0], performer.script(np.array([0.5]))[0])


def test_demo_record_frames_needs_a_record_folder():
    from click.testing import CliRunner

    from livebridge.cli import main

    result = CliRunner().invoke(main, ["demo", "--record-frames", "--frames", "1"])
    assert result.exit_code != 0 and "--record" in result.output


def test_three_cameras_label_on_the_first_frame_and_follow_the_face():
    """With 3 cameras only 2 head markers are seen twice on the neutral frame: the first labelling is still
    taken there (three quarters of the markers matched), and the head pose comes from the markers that
    stay put on the skull, so the contractions follow the performer."""
    first = []
    parts = build_demo(cameras=3, size=(640, 400), realtime=False, servo=False, render=False, log=lambda m: None,
                       on_frame=lambda frame: first.append(frame.seq) if not first else None)
    summary = run_until_stopped(parts.pipeline, frames=200, log=lambda m: None)
    assert first == [0]  # labelled on the neutral frame, not on a later one with an expression
    assert summary.solved >= 200 and parts.score.swaps == 0 and parts.score.rmse <= 0.02, parts.score.rmse
