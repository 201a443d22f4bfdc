"""``livebridge calibrate run --videos`` on real encoded videos (OpenCV's VideoWriter) of rendered boards, and
``--sources`` on the simulated rig filming a board (``sim://rig?board=...``)."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from livebridge.calibration.boards import parse_board
from livebridge.calibration.calibfile import load_calibration, load_metadata
from livebridge.cli import main
from livebridge.simulators.board_render import example_board_poses, example_rig, project_board, render_board_view

SPEC = "chessboard:7x7:55"
N_VIEWS = 10
CODECS = [("MJPG", ".avi"), ("mp4v", ".mp4"), ("avc1", ".mp4")]  # avc1: H.264, where OpenCV has an encoder


@pytest.fixture(scope="module")
def filmed():
    """2 cameras, the board in 10 poses seen whole by both: (rig, frames per camera (n_views, h, w) uint8)."""
    board = parse_board(SPEC)
    rig = example_rig(2, size=(640, 480), seed=0)
    poses = example_board_poses(board, 3 * N_VIEWS, seed=2, tilt_deg=35.0)
    whole = np.isfinite(project_board(board, rig, poses)[..., 0]).all(axis=(0, 2))
    poses = poses[whole][:N_VIEWS]
    assert len(poses) == N_VIEWS
    rng = np.random.default_rng(3)
    frames = [np.stack([render_board_view(board, camera, pose, blur_px=0.7, noise=2.0, rng=rng, supersample=2)
                        for pose in poses]) for camera in rig.cameras]
    return rig, frames


def write_video(path, frames: np.ndarray, fourcc: str) -> bool:
    """Encode grayscale frames (n, h, w) with OpenCV; False when OpenCV has no encoder for ``fourcc``."""
    height, width = frames.shape[1:]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 10.0, (width, height))
    if not writer.isOpened():
        return False
    for frame in frames:
        writer.write(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR))
    writer.release()
    return path.stat().st_size > 0


@pytest.mark.parametrize("fourcc,suffix", CODECS)
def test_calibration_from_encoded_videos(filmed, tmp_path, fourcc, suffix):
    rig, frames = filmed
    args = ["calibrate", "run", "--board", SPEC, "--out", str(tmp_path / "calibration.toml"), "--every", "1",
            "--quiet"]
    for camera, camera_frames in zip(rig.cameras, frames):
        path = tmp_path / f"{camera.name}{suffix}"
        if not write_video(path, camera_frames, fourcc):
            pytest.skip(f"OpenCV has no {fourcc} encoder for {suffix} here")
        args += ["--videos", f"{camera.name}={path}"]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    found = dict(re.findall(r"(cam\d) (\d+)/(?:\d+)", result.output))
    assert found == {"cam0": str(N_VIEWS), "cam1": str(N_VIEWS)}, result.output
    group, metadata = load_calibration(tmp_path / "calibration.toml"), load_metadata(tmp_path / "calibration.toml")
    baseline = np.linalg.norm(group.cameras[1].center - group.cameras[0].center)
    true_baseline = np.linalg.norm(rig.cameras[1].center - rig.cameras[0].center)
    print(f"{fourcc}{suffix}: RMS {metadata['rms_px']}, baseline {baseline:.2f} mm (true {true_baseline:.2f})")
    assert abs(baseline - true_baseline) < 2.0
    for camera, truth in zip(group.cameras, rig.cameras):
        focal, true_focal = camera.matrix[[0, 1], [0, 1]], truth.matrix[[0, 1], [0, 1]]
        assert np.all(np.abs(focal / true_focal - 1) < 0.01), (fourcc, camera.name, focal, true_focal)
        assert np.all(np.abs(camera.matrix[:2, 2] - truth.matrix[:2, 2]) < 4.0)
        assert metadata["rms_px"][camera.name] <= 0.5


def test_calibration_from_simulated_rig_sources(tmp_path):
    """Two cameras of ``sim://rig?board=...`` through ``--sources``: the rig's own cameras come back."""
    url = f"sim://rig?board={SPEC}&cameras=2&seed=4&views=12&size=640x480"
    out = tmp_path / "calibration.toml"
    result = CliRunner().invoke(main, ["calibrate", "run", "--board", SPEC, "--out", str(out), "--quiet",
                                       "--sources", f"left={url}&camera=0", "--sources", f"right={url}&camera=1",
                                       "--frames", "12", "--every", "1"])
    assert result.exit_code == 0, result.output
    truth = example_rig(2, size=(640, 480), seed=4)
    group, metadata = load_calibration(out), load_metadata(out)
    assert group.names == ("left", "right")
    baseline = np.linalg.norm(group.cameras[1].center - group.cameras[0].center)
    true_baseline = np.linalg.norm(truth.cameras[1].center - truth.cameras[0].center)
    assert abs(baseline - true_baseline) < 2.0, (baseline, true_baseline)
    for camera, true_camera in zip(group.cameras, truth.cameras):
        focal, true_focal = camera.matrix[[0, 1], [0, 1]], true_camera.matrix[[0, 1], [0, 1]]
        assert np.all(np.abs(focal / true_focal - 1) < 0.01), (camera.name, focal, true_focal)
        assert metadata["rms_px"][camera.name] <= 0.3
