"""Take directories: written incrementally, read back, and survive SIGKILL up to the last second."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from types import SimpleNamespace

import numpy as np
import pytest

from livebridge.errors import InputError
from livebridge.output.record import TakeRecorder, load_take_dir
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


def test_raw_frames_are_written_as_png(tmp_path):
    import cv2

    with TakeRecorder(tmp_path / "t", MUSCLES, MARKERS, record_frames=True) as rec:
        image = (np.arange(48 * 64) % 251).astype(np.uint8).reshape(48, 64)
        rec.record_frames([SimpleNamespace(image=image, seq=3, t_capture=1.5, source_id="cam/0")])
        rec.record(3, 1.5, *_values(3))
    index = (tmp_path / "t" / "frames" / "frames.csv").read_text().splitlines()
    assert index == ["camera,seq,t_capture,file", "cam_0,3,1.500000,cam_0/00000003.png"]
    assert np.array_equal(cv2.imread(str(tmp_path / "t" / "frames" / "cam_0" / "00000003.png"), 0), image)


_CHILD = textwrap.dedent("""
    import sys, time
    import numpy as np
    from livebridge.output.record import TakeRecorder
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
