"""Calibration core: boards, lens model, files, pose graph, bundle adjustment, checks, determinism."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from calib_factories import centres_in_cam0, synthetic_detections

from livebridge.calibration.boards import parse_board
from livebridge.calibration.bundle import distort
from livebridge.calibration.calibfile import load_calibration, load_metadata, save_calibration
from livebridge.calibration.cameras import Camera, CameraGroup
from livebridge.calibration.detect import Detections, detect_board, pair_images
from livebridge.calibration.run import calibrate, world_axes
from livebridge.errors import InputError
from livebridge.simulators.board_render import example_rig, render_board_view


def test_board_specs_parse_and_reject_with_reasons():
    board = parse_board("charuco:7x5:40:30:4x4_50")
    assert board.spec == "charuco:7x5:40:30:DICT_4X4_50"
    assert parse_board(board.spec) == board
    assert board.n_corners == 24 and board.object_points.shape == (24, 3)
    chess = parse_board("chessboard:8x5:25")
    assert chess.n_corners == 40 and chess.squares == (9, 6)
    assert np.allclose(chess.object_points[1] - chess.object_points[0], [25, 0, 0])
    assert parse_board("charuco:6x6:30:20:DICT_5X5_100:legacy").legacy
    assert parse_board("chessboard:7x7:25").n_corners == 49  # square boards: the corner order is resolved later
    for bad, words in [("charuco:7x5:40:45:DICT_4X4_50", "smaller"), ("charuco:7x5:40:30:NOPE", "dictionary"),
                       ("chessboard:8x5", "fields"), ("hexboard:3x3:1", "kind"), ("chessboard:1x5:10", "2x2"),
                       ("charuco:20x20:40:30:DICT_4X4_50", "markers"), ("chessboard:8x5:-1", "positive")]:
        with pytest.raises(InputError, match=words):
            parse_board(bad)


def test_legacy_charuco_detected_only_with_the_legacy_option():
    """Even-row ChArUco boards changed layout in OpenCV 4.6; the ':legacy' spec still reads old prints."""
    legacy = parse_board("charuco:6x6:40:30:DICT_4X4_50:legacy")
    modern = parse_board("charuco:6x6:40:30:DICT_4X4_50")
    camera = Camera("c", (640, 480), [[600, 0, 320], [0, 600, 240], [0, 0, 1]], np.zeros(5))
    board2world = np.eye(4)
    board2world[:3, 3] = [-120, -120, 600]
    image = render_board_view(legacy, camera, board2world, supersample=2)
    truth = camera.project(legacy.object_points + board2world[:3, 3])
    found = detect_board(legacy, image)
    seen = np.isfinite(found[:, 0])
    assert seen.sum() >= 20
    assert np.max(np.linalg.norm(found[seen] - truth[seen], axis=1)) < 0.5
    wrong = detect_board(modern, image)
    assert np.isfinite(wrong[:, 0]).sum() < seen.sum() / 2


@pytest.mark.parametrize("fisheye", [False, True])
def test_vectorised_lens_model_matches_opencv(fisheye, rng):
    camera = example_rig(1, fisheye=fisheye, seed=3).cameras[0]
    points = rng.uniform([-400, -300, 600], [400, 300, 1500], (200, 3))
    points = (points - camera.translation) @ cv2.Rodrigues(camera.rotation)[0]  # in front of the camera
    in_cam = points @ cv2.Rodrigues(camera.rotation)[0].T + camera.translation
    k = camera.matrix
    ours = distort(in_cam[:, :2] / in_cam[:, 2:], np.tile([k[0, 0], k[1, 1], k[0, 2], k[1, 2]], (200, 1)),
                   np.tile(camera.distortions, (200, 1)), fisheye)
    assert np.allclose(ours, camera.project(points), atol=1e-8)
    assert np.allclose(camera.undistort_points(camera.project(points)),
                       in_cam[:, :2] / in_cam[:, 2:] * k[[0, 1], [0, 1]] + k[:2, 2], atol=1e-6)


def test_calibration_file_round_trip_and_aniposelib_format(tmp_path):
    group = example_rig(3)
    fisheye_cam = dataclasses.replace(example_rig(1, fisheye=True, seed=5).cameras[0], name="fish")
    group = CameraGroup(list(group.cameras) + [fisheye_cam])
    path = tmp_path / "calibration.toml"
    save_calibration(path, group, {"board": "chessboard:8x5:25", "rms_px": {"cam0": np.float64(0.1)}})
    loaded = load_calibration(path)
    assert loaded.names == group.names
    for a, b in zip(loaded.cameras, group.cameras):
        assert a.fisheye == b.fisheye and a.size == b.size
        for field in ("matrix", "distortions", "rotation", "translation"):
            assert np.array_equal(getattr(a, field), getattr(b, field))  # exact: floats round-trip
    assert load_metadata(path)["rms_px"]["cam0"] == 0.1
    # aniposelib writes these files with the `toml` package (its own layout, 1-term distortion allowed)
    anipose = tmp_path / "anipose.toml"
    anipose.write_text('[cam_0]\nname = "A"\nsize = [ 640, 480,]\nmatrix = [ [ 500.0, 0.0, 320.0,], '
                       '[ 0.0, 500.0, 240.0,], [ 0.0, 0.0, 1.0,],]\ndistortions = [ -0.1,]\n'
                       'rotation = [ 0.0, 0.1, 0.0,]\ntranslation = [ 10.0, 0.0, 0.0,]\n\n[metadata]\n')
    cam = load_calibration(anipose).cameras[0]
    assert cam.name == "A" and np.allclose(cam.distortions, [-0.1, 0, 0, 0, 0])


@pytest.mark.parametrize("text, field", [
    ('[cam_0]\nname = "a"\nsize = [640]\n', "cam_0.size"),
    ('[cam_0]\nname = "a"\nsize = [640, 480]\nmatrix = [[1, 0], [0, 1]]\n', "cam_0.matrix"),
    ('[cam_0]\nname = "a"\nsize = [640, 480]\nmatrix = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]\n', "cam_0.distortions"),
    ('[cam_0]\nname = "a"\nsize = [640, 480]\nmatrix = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]\n'
     'distortions = [0, 0, 0, 0, 0]\nrotation = [0, 0, "x"]\ntranslation = [0, 0, 0]\n', "cam_0.rotation"),
    ('[cam_0]\nname = "a"\nsize = [640, 480]\nmatrix = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]\n'
     'distortions = [0, 0, 0, 0, 0]\nrotation = [0, 0, 0]\ntranslation = [0, 0, nan]\n', "cam_0.translation"),
    ('[camera]\nname = "a"\n', "camera"),
    ('[cam_0]\nname = "a"\nsize = [640, 480]\nmatrix = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]\n'
     'distortions = [0, 0, 0, 0, 0]\nrotation = [1e308, 0, 0]\ntranslation = [0, 0, 0]\n', "cam_0.rotation"),
    ('[cam_0]\nname = "a"\nsize = [640, 480]\nmatrix = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]\n'
     'distortions = [0, 0, 0, 0, 0]\nrotation = [0, 0, 0]\ntranslation = [0, 0, 0]\nfishey = true\n',
     "cam_0.fishey"),
])
def test_bad_calibration_files_name_the_field(tmp_path, text, field):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(InputError) as error:
        load_calibration(path)
    assert error.value.field == field and str(path) in str(error.value)


def test_pairing_by_name_number_or_order(tmp_path):
    from pathlib import Path

    same = [[Path("a/0001.png"), Path("a/0002.png")], [Path("b/0002.png"), Path("b/0001.png"), Path("b/0003.png")]]
    names, table = pair_images(same)
    assert names == ["0001", "0002", "0003"] and table[0][2] is None and table[1][0].name == "0001.png"
    numbered = [[Path("left1.jpg"), Path("left02.jpg")], [Path("right02.jpg"), Path("right01.jpg")]]
    names, table = pair_images(numbered)
    assert [p.name for p in table[1]] == ["right01.jpg", "right02.jpg"]


def test_synthetic_calibration_accuracy_and_bit_for_bit_determinism(tmp_path):
    board, truth, _, detections = synthetic_detections(n_views=40, noise_px=0.1, seed=1)
    first = calibrate(detections, board)
    second = calibrate(detections, board)
    for a, b, t in zip(first.group.cameras, second.group.cameras, truth.cameras):
        for field in ("matrix", "distortions", "rotation", "translation"):
            assert np.array_equal(getattr(a, field), getattr(b, field))
        assert np.allclose(a.matrix[[0, 1], [0, 1]], t.matrix[[0, 1], [0, 1]], rtol=0.005)
        assert np.allclose(a.matrix[:2, 2], t.matrix[:2, 2], atol=2.0)
    assert np.max(np.linalg.norm(centres_in_cam0(first.group) - centres_in_cam0(truth), axis=1)) < 1.0
    assert np.all(first.rms_px() < 0.3)
    paths = [tmp_path / "a.toml", tmp_path / "b.toml"]
    for path, result in zip(paths, (first, second)):
        save_calibration(path, result.group, result.metadata(date="2026-01-01"))
    assert paths[0].read_bytes() == paths[1].read_bytes()


def test_world_frame_is_the_origin_board_with_stated_axes():
    board, truth, poses, detections = synthetic_detections(n_views=30)
    for up in ("y", "z"):
        result = calibrate(detections, board, up=up, origin_view=5)
        axes = world_axes(up, "upright")
        assert np.isclose(np.linalg.det(axes), 1.0)
        # truth: world frame at view 5's board with the stated axes
        board2new = np.eye(4)
        board2new[:3, :3] = axes.T
        old2new = board2new @ np.linalg.inv(poses[5])
        for cam, true_cam in zip(result.group.cameras, truth.cameras):
            expected = (old2new @ np.r_[true_cam.center, 1])[:3]
            assert np.linalg.norm(cam.center - expected) < 1.0
        # the cameras look at the printed side, which faces +z (up y) or -y (up z) in the world
        centres = np.array([c.center for c in result.group.cameras])
        assert np.all(centres[:, 2] > 300) if up == "y" else np.all(centres[:, 1] < -300)


def test_fisheye_calibration(rng):
    board, truth, _, detections = synthetic_detections(n_views=40, noise_px=0.1, fisheye=True, seed=4)
    result = calibrate(detections, board, fisheye=True)
    for cam, true_cam in zip(result.group.cameras, truth.cameras):
        assert cam.fisheye and cam.distortions.shape == (4,)
        assert np.allclose(cam.matrix[[0, 1], [0, 1]], true_cam.matrix[[0, 1], [0, 1]], rtol=0.005)
    assert np.max(np.linalg.norm(centres_in_cam0(result.group) - centres_in_cam0(truth), axis=1)) < 1.0


def test_outliers_are_pruned():
    board, truth, _, detections = synthetic_detections(n_views=40, noise_px=0.1, seed=7)
    corners = detections.corners.copy()
    seen = np.argwhere(np.isfinite(corners[..., 0]))
    picks = seen[np.random.default_rng(0).choice(len(seen), size=len(seen) // 100, replace=False)]
    corners[tuple(picks.T)] += np.array([15.0, -9.0])
    result = calibrate(dataclasses.replace(detections, corners=corners), board)
    pruned = ~result.inliers & np.isfinite(result.errors)
    assert pruned[tuple(picks.T)].all()
    assert pruned.sum() < 2 * len(picks)
    assert np.max(np.linalg.norm(centres_in_cam0(result.group) - centres_in_cam0(truth), axis=1)) < 1.0


def test_cameras_that_share_no_view_are_named():
    board, _, _, detections = synthetic_detections(n_views=40)
    corners = detections.corners.copy()
    corners[:2, 20:] = np.nan  # cam0, cam1 only see views 0..19
    corners[2:, :20] = np.nan  # cam2, cam3 only views 20..39
    with pytest.raises(InputError, match=r"2 groups.*\[cam0, cam1\]; \[cam2, cam3\]"):
        calibrate(dataclasses.replace(detections, corners=corners), board)


def test_mirrored_camera_is_reported():
    board, group, _, detections = synthetic_detections(n_views=30)
    corners = detections.corners.copy()
    width = group.cameras[2].size[0]
    corners[2, ..., 0] = width - 1 - corners[2, ..., 0]  # what a mirrored webcam image gives
    with pytest.raises(InputError, match="cam2.*behind.*mirrored"):
        calibrate(dataclasses.replace(detections, corners=corners), board)


def test_too_few_views_names_the_camera():
    board, _, _, detections = synthetic_detections(n_views=20)
    corners = detections.corners.copy()
    corners[1, 2:] = np.nan
    with pytest.raises(InputError, match="cam1.*only 2 views"):
        calibrate(Detections(detections.camera_names, detections.sizes, corners, detections.view_names), board)
