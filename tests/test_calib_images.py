"""Calibration from images: rendered boards through the CLI, the real stereo pairs, board printouts."""

from __future__ import annotations

import dataclasses
import re

import cv2
import numpy as np
import pytest
from calib_factories import assert_calibration_matches
from click.testing import CliRunner

from livebridge.calibration.boards import parse_board
from livebridge.cli import main
from livebridge.simulators.board_render import example_board_poses, example_rig, render_board_view

SPEC = "charuco:8x6:60:45:DICT_4X4_50"
N_VIEWS = 16


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """4 cameras x 16 views rendered with blur and noise, written with mixed names, formats and one odd size."""
    board = parse_board(SPEC)
    rig = example_rig(4, size=(720, 540), seed=0)
    odd = rig.cameras[3]
    odd = dataclasses.replace(odd, size=(641, 479), matrix=odd.matrix - np.array([[0, 0, 40], [0, 0, 30], [0, 0, 0]]))
    rig = type(rig)(list(rig.cameras[:3]) + [odd])
    poses = example_board_poses(board, N_VIEWS, seed=1)
    rng = np.random.default_rng(5)
    root = tmp_path_factory.mktemp("rig")
    folders = {}
    for c, camera in enumerate(rig.cameras):
        folder = root / camera.name
        folder.mkdir()
        for v, pose in enumerate(poses):
            if c == 2 and v == 3:
                continue  # a missing file
            image = render_board_view(board, camera, pose, blur_px=0.7, noise=2.0, rng=rng, supersample=2)
            if c == 1:
                cv2.imwrite(str(folder / f"frame{v}.jpg"), image, [cv2.IMWRITE_JPEG_QUALITY, 97])
            else:
                name = f"{camera.name}_{v:04d}.png" if c != 3 else f"IMG_{v:03d}.PNG"
                cv2.imwrite(str(folder / name), image)
        folders[camera.name] = folder
    (folders["cam0"] / "notes.txt").write_text("not an image")
    blank = np.full((540, 720), 110, np.uint8)
    cv2.imwrite(str(folders["cam0"] / f"cam0_{N_VIEWS:04d}.png"), blank)  # no board in this one
    return board, rig, poses, folders, root


def test_cli_calibration_of_rendered_rig_meets_accuracy(rendered):
    board, rig, poses, folders, root = rendered
    out = root / "calibration.toml"
    args = ["calibrate", "run", "--board", SPEC, "--out", str(out), "--quiet"]
    for name, folder in folders.items():
        args += ["--images", f"{name}={folder}"]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    _, metadata = assert_calibration_matches(out, rig, poses)
    assert metadata["views_used"]["cam2"] <= N_VIEWS - 1
    report = root / "calibration_report"
    assert (report / "reprojection_errors.png").stat().st_size > 1000
    assert all((report / f"coverage_{name}.png").exists() for name in folders)


def test_cli_errors_are_clear(rendered, tmp_path):
    board, rig, poses, folders, root = rendered
    runner = CliRunner()
    result = runner.invoke(main, ["calibrate", "run", "--board", "charuco:8x6:60", "--images", f"a={folders['cam0']}",
                                  "--out", str(tmp_path / "x.toml")])
    assert result.exit_code != 0 and "board spec" in result.output
    result = runner.invoke(main, ["calibrate", "run", "--board", SPEC, "--images", f"a={tmp_path / 'nope'}",
                                  "--out", str(tmp_path / "x.toml")])
    assert result.exit_code != 0 and "nope" in result.output
    result = runner.invoke(main, ["calibrate", "run", "--board", SPEC, "--sources", "a=sim://rig",
                                  "--images", f"a={folders['cam0']}", "--out", str(tmp_path / "x.toml")])
    assert result.exit_code != 0 and "exactly one" in result.output


def test_real_stereo_pairs_match_opencv_stereo_calibrate(shared_data):
    """Real webcam pairs: the board is found in >= 13 pairs and our RMS is within 1.1x of cv2.stereoCalibrate."""
    from livebridge.calibration.detect import detect_images
    from livebridge.calibration.run import calibrate

    folder = shared_data / "stereo-chessboard"
    board = parse_board("chessboard:8x5:1")
    detections = detect_images(board, {"left": folder / "left*.jpg", "right": folder / "right*.jpg"}, progress=False)
    both = (detections.counts() >= board.min_corners).all(axis=0)
    assert both.sum() >= 13
    result = calibrate(detections, board)
    # the same pairs for both methods: those our outlier pruning kept in both cameras
    kept = both & result.inliers.all(axis=2).all(axis=0)
    assert kept.sum() >= 13
    ours = float(np.sqrt(np.mean(result.errors[:, kept] ** 2)))
    baseline = stereo_calibrate_rms(board, detections.corners[:, kept], detections.sizes[0])
    print(f"stereo-chessboard: {kept.sum()} pairs, ours RMS {ours:.4f} px, cv2.stereoCalibrate {baseline:.4f} px")
    assert ours <= 1.1 * baseline


def stereo_calibrate_rms(board, corners, size) -> float:
    """Best RMS of cv2.stereoCalibrate (5-term model) from calibrateCamera intrinsics or from scratch."""
    objects = [board.object_points.astype(np.float32)] * corners.shape[1]
    left = [c.astype(np.float32).reshape(-1, 1, 2) for c in corners[0]]
    right = [c.astype(np.float32).reshape(-1, 1, 2) for c in corners[1]]
    intrinsics = [cv2.calibrateCamera(objects, points, size, None, None)[1:3] for points in (left, right)]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    guessed = cv2.stereoCalibrate(objects, left, right, *intrinsics[0], *intrinsics[1], size,
                                  flags=cv2.CALIB_USE_INTRINSIC_GUESS, criteria=criteria)[0]
    scratch = cv2.stereoCalibrate(objects, left, right, None, None, None, None, size, flags=0, criteria=criteria)[0]
    return float(min(guessed, scratch))


@pytest.mark.parametrize("suffix", [".png", ".pdf"])
def test_printed_board_has_exact_physical_size(tmp_path, suffix):
    out = tmp_path / f"board{suffix}"
    result = CliRunner().invoke(main, ["calibrate", "board", "charuco:5x7:30:22:DICT_4X4_50", "--out", str(out),
                                       "--dpi", "150"])
    assert result.exit_code == 0, result.output
    width_mm, height_mm = (float(v) for v in re.findall(r"page ([\d.]+) x ([\d.]+) mm", result.output)[0])
    assert width_mm >= 5 * 30 and height_mm >= 7 * 30
    if suffix == ".png":
        image = cv2.imread(str(out), cv2.IMREAD_GRAYSCALE)
        assert abs(image.shape[1] - width_mm / 25.4 * 150) <= 1 and abs(image.shape[0] - height_mm / 25.4 * 150) <= 1
        # the printed board is detectable, and its squares are 30 mm at 150 dpi
        corners = cv2.aruco.CharucoDetector(parse_board("charuco:5x7:30:22:DICT_4X4_50").cv_board).detectBoard(image)
        assert corners[1] is not None and len(corners[1]) == 24
        spacing = np.median(np.linalg.norm(np.diff(corners[0].reshape(-1, 2)[:4], axis=0), axis=1))
        assert abs(spacing - 30 / 25.4 * 150) < 1.0
    else:
        box = re.search(rb"/MediaBox \[\s*([\d.]+) ([\d.]+) ([\d.]+) ([\d.]+)\s*\]", out.read_bytes())
        assert box and abs(float(box.group(3)) - width_mm / 25.4 * 72) < 0.5
        assert abs(float(box.group(4)) - height_mm / 25.4 * 72) < 0.5
