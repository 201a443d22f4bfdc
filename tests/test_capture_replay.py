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

    old = pipeline.front.capture
    pipeline.front.capture = SyncedCapture(old.sources, old.sync.period_s, queue_size=1, realtime=False,
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
    assert summary.cameras_alive == 0 and pipeline.front.capture.sync.stats.framesets >= min(written.values())
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


def _small_take(folder, suffix: str, n: int = 8, cameras=("cam0", "cam1")):
    """A raw-frame take of ``n`` distinct frames per camera (frame k is filled with 10 * k + camera, mod 256)."""
    from livebridge.take.raw_frames import RawFrameWriter

    with RawFrameWriter(folder, suffix) as writer:
        for c, name in enumerate(cameras):
            for k in range(n):
                writer.write(Frame(np.full((24, 32), (10 * k + c) % 256, np.uint8), 1.0 + k / 30, k, name, 1000.0, 1.0,
                                   "sync"))
    return folder


def _damage(path, how: str) -> None:
    if how == "truncate":
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    elif how == "garbage":
        path.write_bytes(b"\x00garbage\xff" * 40)
    elif how == "empty":
        path.write_bytes(b"")
    elif how == "delete":
        path.unlink()


@pytest.mark.parametrize("suffix", [".pgm", ".png"])
@pytest.mark.parametrize("realtime", [False, True])
def test_a_damaged_take_skips_and_counts_the_frames_it_cannot_read(tmp_path, caplog, suffix, realtime):
    folder = _small_take(tmp_path / "take", suffix)
    damaged = {1: "truncate", 3: "delete", 4: "garbage", 6: "empty"}
    for k, how in damaged.items():
        _damage(folder / "cam0" / f"{k:06d}{suffix}", how)
    sources = open_cameras(f"replay://{folder}?realtime={int(realtime)}")
    got = {}
    for source in sources:
        with source:
            got[source.source_id] = [f for f in iter(lambda s=source: s.read(timeout=1.0), None)]
            assert source.ended and source.error is None
    assert [f.seq for f in got["cam0"]] == [k for k in range(8) if k not in damaged]
    assert [int(f.image[0, 0]) for f in got["cam0"]] == [10 * k for k in range(8) if k not in damaged]
    assert [f.seq for f in got["cam1"]] == list(range(8))
    assert [s.frames_skipped for s in sources] == [4, 0]
    skipped = [r.getMessage() for r in caplog.records if "skipped" in r.getMessage()]
    assert len(skipped) == 1 and f"000001{suffix}" in skipped[0]  # logged once, naming the first file


def test_skipped_frames_are_logged_once_per_hundred(tmp_path, caplog):
    folder = _small_take(tmp_path / "take", ".pgm", n=250, cameras=("cam0",))
    for k in range(0, 250, 2):
        _damage(folder / "cam0" / f"{k:06d}.pgm", "garbage")
    source = open_camera(f"replay://{folder}?realtime=0")
    with source:
        frames = list(iter(source.read, None))
    assert [f.seq for f in frames] == list(range(1, 250, 2))
    assert source.frames_skipped == 125 and source.error is None
    assert len([r for r in caplog.records if "skipped" in r.getMessage()]) == 2  # the 1st and the 101st


@pytest.mark.parametrize("loop", [0, 1])
def test_a_take_with_no_readable_image_ends_with_an_error_naming_it(tmp_path, loop):
    folder = _small_take(tmp_path / "take", ".png", n=4, cameras=("cam0",))
    for path in (folder / "cam0").iterdir():
        _damage(path, "truncate")
    source = open_camera(f"replay://{folder}?realtime=0&loop={loop}")
    with source:
        assert source.read() is None and source.read() is None
    assert source.ended and "none of the 4 images" in source.error and "cam0" in source.error
    assert source.frames_skipped == 4


def test_a_camera_folder_vanishing_during_replay_ends_that_source(tmp_path):
    import shutil

    folder = _small_take(tmp_path / "take", ".pgm", n=6)
    sources = open_cameras(f"replay://{folder}?realtime=0")
    for source in sources:
        source.start()
    assert sources[0].read().seq == 0
    shutil.rmtree(folder / "cam0")
    assert sources[0].read() is None and sources[0].ended
    assert "vanished" in sources[0].error and str(folder / "cam0") in sources[0].error
    assert [f.seq for f in iter(sources[1].read, None)] == list(range(6))  # the other camera plays on


def test_an_unreadable_video_ends_the_source_or_is_refused_at_open(tmp_path):
    (tmp_path / "left.avi").write_bytes(b"RIFF not really a video" * 10)
    with pytest.raises(InputError, match="left.avi.*cannot open"):
        open_camera(f"replay://{tmp_path}?realtime=0")
    (tmp_path / "left.csv").write_text("seq,t_capture\n0,0.0\n1,0.1\n")  # timestamps: opened, fails at start
    source = open_camera(f"replay://{tmp_path}?realtime=0")
    with source:
        assert source.read() is None
    assert source.ended and "left.avi" in source.error


def test_a_timestamp_row_torn_by_a_crash_is_dropped(tmp_path):
    folder = _small_take(tmp_path / "take", ".pgm", n=5, cameras=("cam0",))
    with open(folder / "cam0.csv", "a") as stream:
        stream.write("5,1.1")  # the image of row 5 was never written either
    source = open_camera(f"replay://{folder}?realtime=0")
    with source:
        assert [f.seq for f in iter(source.read, None)] == list(range(5))
    assert source.error is None and source.frames_skipped == 0
