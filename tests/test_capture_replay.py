"""Replay: a simulated take recorded with RawFrameWriter plays back identically, timed or as fast as possible."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from livebridge.capture.frame import Frame
from livebridge.capture.sync import Synchronizer
from livebridge.devices.registry import open_camera, open_cameras
from livebridge.errors import InputError


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    from livebridge.take.raw_frames import RawFrameWriter

    folder = tmp_path_factory.mktemp("take")
    sources = open_cameras("sim://rig?cameras=2&seed=3&size=320x200&fps=50&drop=0.1&jitter_ms=1&realtime=0")
    frames = {s.source_id: [] for s in sources}
    with RawFrameWriter(folder) as writer:
        for source in sources:
            with source:
                for _ in range(12):
                    frame = source.read()
                    frames[source.source_id].append(frame)
                    writer.write(frame)
    return folder, frames


def test_replay_as_fast_as_possible_is_exact(recorded):
    folder, frames = recorded
    sources = open_cameras(f"replay://{folder}?realtime=0")
    assert [s.source_id for s in sources] == ["cam0", "cam1"]
    for source in sources:
        with source:
            got = [source.read() for _ in range(12)]
            assert source.read() is None and source.ended and source.error is None
        for a, b in zip(frames[source.source_id], got):
            np.testing.assert_array_equal(a.image, b.image)
            assert (a.seq, a.t_capture, a.sync_domain, a.exposure_us) == (b.seq, b.t_capture, b.sync_domain,
                                                                          b.exposure_us)


def test_replay_original_timing_and_synchronised(recorded):
    folder, frames = recorded
    sources = open_cameras(f"replay://{folder}?cameras=cam0,cam1")
    sync = Synchronizer(["cam0", "cam1"], 1 / 50)
    start = time.monotonic()
    for source in sources:
        source.start()
    out, arrivals = [], []

    def read(source):
        frame = source.read()
        if frame is not None:
            arrivals.append(time.monotonic() - frame.t_capture)
        return frame

    pending = {s.source_id: read(s) for s in sources}
    while any(f is not None for f in pending.values()):  # merge the two streams in time order
        name = min((n for n, f in pending.items() if f is not None), key=lambda n: pending[n].t_capture)
        out += sync.push(pending[name])
        pending[name] = read(next(s for s in sources if s.source_id == name))
    out += sync.flush()
    elapsed = time.monotonic() - start
    recorded_span = max(f.t_capture for fs in frames.values() for f in fs) - min(
        f.t_capture for fs in frames.values() for f in fs)
    assert elapsed >= recorded_span * 0.9
    assert np.median(arrivals) < 0.01 and min(arrivals) > -1e-3  # delivered at its (shifted) capture time
    hardware = frames["cam0"][0].sync_domain == frames["cam1"][0].sync_domain
    assert hardware and len(out) >= 11
    for fs in out:
        seqs = {f.seq for f in fs.frames if f is not None}
        assert len(seqs) == 1  # grouped by seq in the rig's hardware domain


def test_replay_with_gaps_synchronised_in_step(recorded):
    """Cameras with different dropped frames, replayed unpaced in frame-time step: every recorded instant
    becomes one frame set with exactly the cameras that recorded it."""
    from livebridge.capture.sync import SyncedCapture

    folder, frames = recorded
    expected = {}
    for name, stream in frames.items():
        for frame in stream:
            expected.setdefault(frame.seq, set()).add(name)
    assert any(len(v) == 1 for v in expected.values())  # the take has gaps (drop=0.1)
    sources = open_cameras(f"replay://{folder}?realtime=0")
    got = []
    with SyncedCapture(sources, 1 / 50, queue_size=1, realtime=False) as capture:
        while (frameset := capture.read(timeout=2.0)) is not None:
            got.append(frameset)
            if len(got) == len(expected):
                break
    assert [next(f.seq for f in fs.frames if f is not None) for fs in got] == sorted(expected)
    for fs in got:
        present = {name for name, frame in zip(fs.source_ids, fs.frames) if frame is not None}
        assert present == expected[next(f.seq for f in fs.frames if f is not None)]


def test_replay_video_and_bad_input(tmp_path):
    writer = cv2.VideoWriter(str(tmp_path / "left.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 30, (64, 48))
    for k in range(5):
        writer.write(np.full((48, 64, 3), 40 * k, np.uint8))
    writer.release()
    source = open_camera(f"replay://{tmp_path}?realtime=0&fps=30")
    with source:
        got = [source.read() for _ in range(6)]
    assert all(isinstance(f, Frame) for f in got[:5]) and got[5] is None
    assert [f.seq for f in got[:5]] == list(range(5))
    np.testing.assert_allclose([f.t_capture for f in got[:5]], np.arange(5) / 30)
    assert abs(float(got[3].image.mean()) - 120) < 3
    (tmp_path / "left.csv").write_text("seq,t_capture\n0,0.0\n1,zero\n")
    with pytest.raises(InputError, match="left.csv.*line 3"):
        open_cameras(f"replay://{tmp_path}")
    with pytest.raises(InputError, match="no such take"):
        open_cameras(f"replay://{tmp_path}/missing")
    with pytest.raises(InputError, match="unknown parameter"):
        open_cameras(f"replay://{tmp_path}?speed=2")


def _unpaced_capture(pipeline):
    """The synchroniser an unpaced pipeline should have: frame time only and no dropped frame sets, so that
    a run is a deterministic function of its frames (``SyncedCapture(realtime=False)``)."""
    from livebridge.capture.sync import SyncedCapture

    old = pipeline.capture
    pipeline.capture = SyncedCapture(old.sources, old.sync.period_s, queue_size=1, realtime=False,
                                     tolerance_s=old.sync.tolerance_s)
    return pipeline


def test_recorded_demo_replays_through_the_pipeline(tmp_path):
    """Record a simulated demo with raw frames; `replay://TAKE` through the same pipeline gives the same
    contractions (and the recorded take is close to the performer's ground truth)."""
    from livebridge.runtime.build import build_pipeline
    from livebridge.runtime.demo import build_demo
    from livebridge.runtime.pipeline import run_until_stopped
    from livebridge.runtime.session import load_session
    from livebridge.take.directory import load_take_dir

    take = tmp_path / "takes" / "demo"
    parts = build_demo(size=(640, 400), realtime=False, servo=False, render=False, record=take, record_frames=True,
                       log=lambda m: None)
    run_until_stopped(_unpaced_capture(parts.pipeline), frames=60, log=lambda m: None)
    recorded = load_take_dir(take)
    assert recorded.complete and recorded.n_frames >= 60
    written = recorded.manifest["frames_written"]
    assert recorded.manifest["frames_dropped"] == 0 and len(written) == 4 and min(written.values()) >= 60

    session = tmp_path / "replay.toml"  # paths relative to the session file, as a user would write them
    session.write_text('calibration = "takes/demo/calibration.toml"\n'
                       '[cameras]\nurls = ["replay://takes/demo?realtime=0"]\n'
                       '[outputs.render]\nenabled = false\n')
    frames = []
    pipeline = build_pipeline(load_session(session), log=lambda m: None, on_frame=frames.append)
    summary = run_until_stopped(_unpaced_capture(pipeline), log=lambda m: None)  # ends when the take does
    assert summary.cameras_alive == 0 and pipeline.capture.sync.stats.framesets >= min(written.values())
    replayed = {f.seq: f.contractions for f in frames}
    common = [k for k, seq in enumerate(recorded.seq) if seq in replayed]
    assert len(common) >= 0.9 * recorded.n_frames
    difference = np.array([replayed[recorded.seq[k]] - recorded.contractions[k] for k in common])
    assert np.abs(difference).max() < 1e-4  # the same frame sets give the same contractions (CSV: 6 decimals)
    truth = np.array([parts.score.truth(int(recorded.seq[k]))[0] for k in common[1:]])
    assert np.sqrt(np.mean((recorded.contractions[common[1:]] - truth) ** 2)) < 0.03


def test_a_replayed_take_declares_the_calibration_recorded_with_it(tmp_path, recorded):
    from livebridge.calibration.cameras import Camera, CameraGroup
    from livebridge.capture.sources import SourceBase
    from livebridge.take.recorder import TakeRecorder

    cameras = CameraGroup([Camera("dev/CAM_B", (64, 48), np.diag([50.0, 50.0, 1.0]), np.zeros(5),
                                  np.array([0.0, 0.1, 0.0]), np.array([1.0, 0.0, 500.0]))])
    image = np.zeros((48, 64), np.uint8)
    for name, calibration in (("with", cameras), ("without", None)):
        with TakeRecorder(tmp_path / name, ("a",), ("m0",), record_frames=True, lossless_frames=True,
                          cameras=calibration) as recorder:
            recorder.record_frames([Frame(image, 0.0, 0, "dev/CAM_B"), Frame(image, 0.0, 0, "cam1")])
    for url in (f"replay://{tmp_path / 'with'}?realtime=0", f"replay://{tmp_path / 'with' / 'frames'}?realtime=0"):
        by_id = {source.source_id: source for source in open_cameras(url)}
        known = by_id["dev/CAM_B"].calibration
        assert known.name == "dev/CAM_B" and known.size == (64, 48)
        np.testing.assert_array_equal(known.rotation, [0.0, 0.1, 0.0])
        np.testing.assert_array_equal(known.translation, [1.0, 0.0, 500.0])
        assert by_id["cam1"].calibration is None  # not in the recorded calibration
    assert all(s.calibration is None for s in open_cameras(f"replay://{tmp_path / 'without'}?realtime=0"))
    folder, _ = recorded  # raw frames alone, not a take directory: no calibration to know
    assert all(s.calibration is None for s in open_cameras(f"replay://{folder}?realtime=0"))
    assert SourceBase().calibration is None  # the default of every source
