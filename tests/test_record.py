"""Take directories: written incrementally, read back, and survive SIGKILL up to the last second."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
import warnings

import numpy as np
import pytest

from livebridge.errors import InputError
from livebridge.take.c3d import export_c3d
from livebridge.take.directory import load_take_dir
from livebridge.take.recorder import TakeRecorder
from livebridge.tomlio import load_toml

MUSCLES = ("a", "b", "c")
MARKERS = ("m0", "m1")


def _values(k: int):
    contractions = np.array([k * 1e-3, 0.5, np.sin(k)])
    markers = np.array([[k, 2.0 * k, -1.5], [np.nan, np.nan, np.nan] if k % 3 == 0 else [0.25, 0.5, k / 7]])
    return contractions, markers


def test_round_trip_with_copies_and_unseen_markers(tmp_path):
    session = tmp_path / "s.toml"
    session.write_text("[outputs]\n")
    calibration = tmp_path / "rig.toml"
    calibration.write_text("cameras = []\n")
    take = tmp_path / "take"
    with TakeRecorder(take, MUSCLES, MARKERS, session, calibration, fps=60) as rec:
        for k in range(50):
            x, m = _values(k)
            rec.record(100 + k, 10 + k / 60, x, m, m - 1, (0.1, 0.2))
    loaded = load_take_dir(take)
    assert loaded.complete and loaded.n_frames == 50
    assert loaded.muscle_names == MUSCLES and loaded.marker_names == MARKERS
    assert np.array_equal(loaded.seq, 100 + np.arange(50))
    assert np.allclose(loaded.t, 10 + np.arange(50) / 60, atol=1e-6)
    for k in (0, 1, 3, 49):
        x, m = _values(k)
        assert np.allclose(loaded.contractions[k], x, atol=1e-6)
        assert np.allclose(loaded.markers[k], m, atol=1e-4, equal_nan=True)
        assert np.allclose(loaded.displacements[k], m - 1, atol=1e-4, equal_nan=True)
    assert np.allclose(loaded.region_errors, [0.1, 0.2])
    assert (take / "session.toml").read_text() == session.read_text()
    assert (take / "calibration.toml").read_text() == calibration.read_text()
    manifest = load_toml(take / "take.toml")
    assert manifest["frames"] == 50 and manifest["fps"] == 60 and manifest["t0"] == pytest.approx(10)
    header = (take / "markers.csv").read_text().splitlines()[0]
    assert header == "frame,seq,t,m0_x,m0_y,m0_z,m1_x,m1_y,m1_z"
    as_take = loaded.to_take()
    assert as_take.n_frames == 50 and as_take.muscle_names == MUSCLES


def test_data_reaches_the_disk_within_the_flush_interval_without_close(tmp_path):
    rec = TakeRecorder(tmp_path / "t", MUSCLES, MARKERS, flush_interval=0.2)
    try:
        x, m = _values(1)
        rec.record(0, 0.0, x, m)
        deadline = time.monotonic() + 1.0
        while load_take_dir(tmp_path / "t").n_frames < 1:
            assert time.monotonic() < deadline, "the frame was not flushed within a second"
            time.sleep(0.02)
        assert not load_take_dir(tmp_path / "t").complete
    finally:
        rec.close()


def test_torn_last_line_is_dropped(tmp_path):
    with TakeRecorder(tmp_path / "t", MUSCLES, MARKERS) as rec:
        for k in range(5):
            rec.record(k, k / 30, *_values(k))
    with open(tmp_path / "t" / "markers.csv", "a") as stream:
        stream.write("5,5,0.16,1.0,2")  # a crash in the middle of a line
    loaded = load_take_dir(tmp_path / "t")
    assert loaded.n_frames == 5 and not loaded.complete


def test_refuses_a_non_empty_directory_and_bad_files(tmp_path):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("")
    with pytest.raises(InputError, match="not empty"):
        TakeRecorder(tmp_path / "full", MUSCLES, MARKERS)
    with TakeRecorder(tmp_path / "t", MUSCLES, MARKERS) as rec:
        rec.record(0, 0.0, *_values(0))
    text = (tmp_path / "t" / "contractions.csv").read_text().replace("0.500000", "half")
    (tmp_path / "t" / "contractions.csv").write_text(text)
    with pytest.raises(InputError, match="contractions.csv"):
        load_take_dir(tmp_path / "t")


def test_raw_frames_use_the_replay_format_and_replay_as_cameras(tmp_path):
    from livebridge.capture.frame import Frame
    from livebridge.devices.registry import open_cameras

    images = [(np.arange(48 * 64) % 251 + k).astype(np.uint8).reshape(48, 64) for k in range(3)]
    with TakeRecorder(tmp_path / "t", MUSCLES, MARKERS, record_frames=True, lossless_frames=True) as rec:
        for k, image in enumerate(images):
            rec.record_frames([Frame(image, 1.5 + k / 30, 3 + 2 * k, "dev/CAM_B", 900.0, 2.0, "oak"),
                               Frame(image[::-1].copy(), 1.5 + k / 30, 3 + 2 * k, "cam1", sync_domain="oak")])
            rec.record(3 + 2 * k, 1.5 + k / 30, *_values(k))
    manifest = load_toml(tmp_path / "t" / "take.toml")
    assert manifest["raw_frames"] == "frames" and manifest["frames_written"] == {"dev_CAM_B": 3, "cam1": 3}
    assert sorted(p.name for p in (tmp_path / "t" / "frames").iterdir()) == [
        "cam1", "cam1.csv", "dev_CAM_B", "dev_CAM_B.csv"]
    assert sorted(p.name for p in (tmp_path / "t" / "frames" / "cam1").iterdir()) == [
        "000000.pgm", "000001.pgm", "000002.pgm"]  # uncompressed by default: fast enough for live cameras
    sources = open_cameras(f"replay://{tmp_path / 't'}?realtime=0")  # the take directory itself
    assert [s.source_id for s in sources] == ["cam1", "dev/CAM_B"]  # original names, for the calibration
    with sources[1] as source:
        got = [source.read() for _ in range(4)]
        assert source.capabilities.fps == pytest.approx(60.0)  # seq steps of 2 at 1/30 s: a 60 fps camera
    assert got[3] is None
    for k, frame in enumerate(got[:3]):
        assert np.array_equal(frame.image, images[k]) and frame.seq == 3 + 2 * k
        assert (frame.t_capture, frame.exposure_us, frame.gain, frame.sync_domain) == (1.5 + k / 30, 900.0, 2.0, "oak")


def test_raw_frames_as_png_on_request_and_bad_formats_refused(tmp_path):
    from livebridge.capture.frame import Frame
    from livebridge.devices.registry import open_cameras

    image = (np.arange(48 * 64) % 251).astype(np.uint8).reshape(48, 64)
    with TakeRecorder(tmp_path / "t", MUSCLES, MARKERS, record_frames=True, lossless_frames=True,
                      frame_format=".png") as rec:
        rec.record_frames([Frame(image, 0.5, 0, "cam0")])
    assert [p.name for p in (tmp_path / "t" / "frames" / "cam0").iterdir()] == ["000000.png"]
    (source,) = open_cameras(f"replay://{tmp_path / 't'}?realtime=0")
    with source:
        assert np.array_equal(source.read().image, image)
    with pytest.raises(InputError, match="frame_format"):
        TakeRecorder(tmp_path / "u", MUSCLES, MARKERS, record_frames=True, frame_format=".jpg")


def test_a_take_cut_short_replays_up_to_its_last_complete_frame(tmp_path):
    """An image without its timestamp row (killed in between) and a half-written image are ignored."""
    from livebridge.capture.frame import Frame
    from livebridge.devices.registry import open_cameras
    from livebridge.take.raw_frames import RawFrameWriter

    writer = RawFrameWriter(tmp_path)
    for k in range(4):
        writer.write(Frame(np.full((8, 8), k, np.uint8), k / 60, k, "cam0"))
    writer.close()  # no close needed for the rows to be on disk: simulate the crash on top
    (tmp_path / "cam0" / "000004.png").write_bytes((tmp_path / "cam0" / "000003.png").read_bytes())
    (tmp_path / "cam0" / ".000005.png.part").write_bytes(b"\x89PNG torn")
    with open_cameras(f"replay://{tmp_path}?realtime=0")[0] as source:
        seqs = [source.read() for _ in range(5)]
    assert [f.seq for f in seqs[:4]] == [0, 1, 2, 3] and seqs[4] is None


def test_recorder_writes_the_cameras_calibration_when_there_is_no_file(tmp_path):
    from livebridge.calibration.calibfile import load_calibration
    from livebridge.calibration.cameras import Camera, CameraGroup

    cameras = CameraGroup([Camera(f"cam{k}", (64, 48), np.diag([50.0, 50.0, 1.0]), np.zeros(5),
                                  np.array([0.0, 0.1 * k, 0.0]), np.array([k, 0.0, 500.0])) for k in range(2)])
    with TakeRecorder(tmp_path / "t", MUSCLES, MARKERS, cameras=cameras) as rec:
        rec.record(0, 0.0, *_values(0))
    loaded = load_calibration(tmp_path / "t" / "calibration.toml")
    assert loaded.names == cameras.names
    assert np.allclose(loaded.cameras[1].rotation, cameras.cameras[1].rotation)
    assert load_take_dir(tmp_path / "t").manifest["calibration"] == "calibration.toml"


_CHILD = textwrap.dedent("""
    import sys, time
    import numpy as np
    from livebridge.take.recorder import TakeRecorder
    rec = TakeRecorder(sys.argv[1], ("a", "b", "c"), ("m0", "m1"), flush_interval=0.5)
    k = 0
    while True:
        rec.record(k, k / 200, np.array([k * 1e-3, 0.5, np.sin(k)]),
                   np.array([[k, 2.0 * k, -1.5], [0.25, 0.5, k / 7]]))
        print(k, time.monotonic(), flush=True)
        k += 1
        time.sleep(0.005)
""")


def test_sigkill_during_recording_keeps_everything_up_to_the_last_second(tmp_path):
    take = tmp_path / "killed"
    child = subprocess.Popen([sys.executable, "-c", _CHILD, str(take)], stdout=subprocess.PIPE, text=True)
    recorded = []  # (frame, monotonic time record() returned)
    try:
        start = None
        for line in child.stdout:
            k, t = line.split()
            recorded.append((int(k), float(t)))
            start = start or float(t)
            if float(t) - start > 2.3:
                break
        t_kill = time.monotonic()
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.wait(10)
    assert child.returncode == -signal.SIGKILL
    loaded = load_take_dir(take)
    must_have = max(k for k, t in recorded if t < t_kill - 1.0)
    assert loaded.n_frames >= must_have + 1, (loaded.n_frames, must_have)
    assert not loaded.complete
    frames = np.arange(loaded.n_frames)
    assert np.array_equal(loaded.seq, frames)
    assert np.allclose(loaded.contractions[:, 0], frames * 1e-3, atol=1e-6)
    assert np.allclose(loaded.contractions[:, 2], np.sin(frames), atol=1e-6)
    assert np.allclose(loaded.markers[:, 0, 1], 2.0 * frames, atol=1e-4)
    assert np.allclose(loaded.markers[:, 1, 2], frames / 7, atol=1e-4)


def test_a_busy_disk_drops_whole_frame_sets(tmp_path):
    import threading

    from livebridge.capture.frame import Frame
    from livebridge.devices.registry import open_cameras

    release = threading.Event()
    rec = TakeRecorder(tmp_path / "t", MUSCLES, MARKERS, record_frames=True, frame_queue=2)
    write = rec._write_image
    rec._write_image = lambda frame: (release.wait(), write(frame))  # the disk stalls
    image = np.zeros((8, 8), np.uint8)
    for seq in range(6):
        rec.record_frames([Frame(image, seq / 60, seq, f"cam{k}", sync_domain="rig") for k in range(3)])
        if seq >= 3:
            release.set()  # the disk catches up
            while rec._frame_queue.qsize():
                time.sleep(0.01)
    rec.close()
    written = load_toml(tmp_path / "t" / "take.toml")["frames_written"]
    assert rec.frames_dropped > 0 and rec.frames_dropped % 3 == 0
    assert sorted(written) == ["cam0", "cam1", "cam2"] and len(set(written.values())) == 1
    seqs = []
    for source in open_cameras(f"replay://{tmp_path / 't'}?realtime=0"):
        with source:
            seqs.append([frame.seq for frame in iter(source.read, None)])
    assert seqs[0] == seqs[1] == seqs[2] and 0 in seqs[0] and 5 in seqs[0] and len(seqs[0]) < 6


class _FakeClock:
    """Monotonic seconds that move only when the test says so."""

    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_flushes_follow_the_injected_clock(tmp_path):
    clock = _FakeClock()
    rec = TakeRecorder(tmp_path / "t", MUSCLES, MARKERS, flush_interval=0.05, clock=clock)
    try:
        rec.record(0, 0.0, *_values(0))
        time.sleep(0.3)  # six flush intervals of real time, none on the recorder's clock
        assert load_take_dir(tmp_path / "t").n_frames == 0
        clock.t += 0.05
        deadline = time.monotonic() + 5.0
        while load_take_dir(tmp_path / "t").n_frames < 1:
            assert time.monotonic() < deadline, "no flush once the clock reached the interval"
            time.sleep(0.01)
    finally:
        rec.close()


def test_frames_dropped_counts_every_drop_of_concurrent_readers(tmp_path):
    """Reader threads record at once while the disk stalls: every frame is either written or counted (the
    count is updated under a lock; under the GIL a lost update is rare enough that this cannot catch it)."""
    import threading

    from livebridge.capture.frame import Frame

    release = threading.Event()
    rec = TakeRecorder(tmp_path / "t", MUSCLES, MARKERS, record_frames=True, frame_queue=1)
    write = rec._write_image
    rec._write_image = lambda frame: (release.wait(), write(frame))  # the disk stalls
    image = np.zeros((4, 4), np.uint8)
    n_threads, n_frames = 4, 500

    def reader(k):
        for seq in range(n_frames):
            rec.record_frames([Frame(image, seq / 60, seq, f"cam{k}", sync_domain=f"cam{k}")])

    switch = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # thread switches as often as the interpreter allows
    try:
        threads = [threading.Thread(target=reader, args=(k,)) for k in range(n_threads)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    finally:
        sys.setswitchinterval(switch)
        release.set()
        rec.close()
    written = load_toml(tmp_path / "t" / "take.toml")["frames_written"]
    assert rec.frames_dropped > 0 and rec.frames_dropped + sum(written.values()) == n_threads * n_frames


def _read_c3d(path):
    """Labels, rate, units, frame count and points (n_frames, n_markers, 5) of a C3D file, read with py-c3d."""
    import c3d

    with open(path, "rb") as handle, warnings.catch_warnings():
        warnings.filterwarnings("ignore", "No analog data")  # markers only: no analog channels
        reader = c3d.Reader(handle)
        points = np.array([p for _, p, _ in reader.read_frames()])
        units = reader.get("POINT:UNITS").string_value.strip()
        return ([label.strip() for label in reader.point_labels], reader.point_rate, units, reader.frame_count,
                points)


def _assert_c3d_matches(points, markers):
    """C3D points (n_frames, n_markers, 5) hold ``markers`` (n_frames, n_markers, 3); unseen = invalid."""
    seen = ~np.isnan(markers).any(axis=-1)
    assert np.array_equal(points[..., 3], np.where(seen, 0.0, -1.0))  # residual -1: C3D's invalid point
    assert not points[~seen][:, :3].any()  # and its coordinates 0, not the marker's last ones
    assert np.allclose(points[seen][:, :3], markers[seen], atol=1e-3)  # float32 of the CSV's 1e-4 mm
    as_nan = np.where(points[..., 3:4] < 0, np.nan, points[..., :3])
    assert np.allclose(as_nan, markers, atol=1e-3, equal_nan=True)


def test_close_writes_markers_as_c3d(tmp_path):
    take = tmp_path / "take"
    with TakeRecorder(take, MUSCLES, MARKERS, fps=60) as rec:
        for k in range(20):
            rec.record(k, k / 60, *_values(k))
    labels, rate, units, n_frames, points = _read_c3d(take / "markers.c3d")
    assert labels == list(MARKERS) and rate == 60.0 and units == "mm" and n_frames == 20
    expected = np.array([_values(k)[1] for k in range(20)])
    assert np.isnan(expected).any() and points.shape == (20, 2, 5)
    _assert_c3d_matches(points, expected)
    _assert_c3d_matches(points, load_take_dir(take).markers)
    assert not list(take.glob("*.partial"))


def test_a_take_never_closed_exports_to_c3d_from_the_command_line(tmp_path):
    from click.testing import CliRunner

    from livebridge.cli import main

    take = tmp_path / "crashed"
    rec = TakeRecorder(take, MUSCLES, MARKERS, flush_interval=0.1)  # no fps: the rate comes from the times
    try:
        for k in range(12):
            rec.record(k, 3.0 + k / 50, *_values(k))
        deadline = time.monotonic() + 5.0
        while load_take_dir(take).n_frames < 12:
            assert time.monotonic() < deadline, "the frames were not flushed"
            time.sleep(0.02)
        with open(take / "markers.csv", "a") as stream:
            stream.write("12,12,3.24,1.0,2")  # a crash in the middle of a line
        result = CliRunner().invoke(main, ["take", "export-c3d", str(take)])
        assert result.exit_code == 0, result.output
        assert "markers.c3d" in result.output
        labels, rate, _, n_frames, points = _read_c3d(take / "markers.c3d")
        assert labels == list(MARKERS) and rate == 50.0 and n_frames == 12
        _assert_c3d_matches(points, np.array([_values(k)[1] for k in range(12)]))
    finally:
        rec.close()


def test_dropped_frame_sets_are_gaps_in_the_c3d_export(tmp_path):
    recorded = [k for k in range(20) if k not in (4, 5, 11)]  # frame sets the pipeline dropped
    jitter = np.random.default_rng(0).uniform(-3e-3, 3e-3, 20)  # capture times a few ms off the grid
    with TakeRecorder(tmp_path / "t", MUSCLES, MARKERS, fps=60) as rec:
        for k in recorded:
            rec.record(k, 5.0 + k / 60 + jitter[k], *_values(k))
    expected = np.array([_values(k)[1] if k in recorded else np.full((2, 3), np.nan) for k in range(20)])
    for path in (tmp_path / "t" / "markers.c3d", export_c3d(tmp_path / "t", tmp_path / "again.c3d")):
        _, rate, _, n_frames, points = _read_c3d(path)
        assert rate == 60.0 and n_frames == 20
        _assert_c3d_matches(points, expected)


def test_c3d_export_needs_a_frame_rate(tmp_path):
    with TakeRecorder(tmp_path / "t", MUSCLES, MARKERS) as rec:  # one frame, no fps: no rate to write
        rec.record(0, 0.0, *_values(1))
    assert not (tmp_path / "t" / "markers.c3d").exists()
    with pytest.raises(InputError, match="frame rate"):
        export_c3d(tmp_path / "t")
    out = export_c3d(tmp_path / "t", tmp_path / "one.c3d", rate=30.0)
    _, rate, _, n_frames, points = _read_c3d(out)
    assert rate == 30.0 and n_frames == 1
    _assert_c3d_matches(points, _values(1)[1][None])
