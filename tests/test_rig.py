"""The simulated camera rig: rendering, ground truth, occlusion, misbehaviour, URL and sources."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from livebridge.capture.frame import Frame, FrameSet
from livebridge.capture.sources import CameraSource, open_source, open_sources
from livebridge.errors import InputError
from livebridge.simulators.rig import RigConfig, SimRig, generate_cameras, generate_markers, render_discs


@pytest.fixture(scope="module")
def face(ict):
    return ict, generate_markers(ict, n_face=30, n_head=4, seed=2)


def _centroids(image, truth_2d, radius, background):
    """Intensity-weighted centroids of the discs around the true positions (background subtracted)."""
    out = []
    for (x, y), r in zip(truth_2d, radius):
        h = int(np.ceil(r + 3))
        ix, iy = int(round(x)), int(round(y))
        patch = image[iy - h:iy + h + 1, ix - h:ix + h + 1].astype(float)
        base = background[iy - h:iy + h + 1, ix - h:ix + h + 1].astype(float)
        w = np.clip(patch - base, 0, None)
        yy, xx = np.mgrid[iy - h:iy + h + 1, ix - h:ix + h + 1]
        out.append([(w * xx).sum() / w.sum(), (w * yy).sum() / w.sum()])
    return np.array(out)


def test_render_discs_centroid_is_subpixel_exact(rng):
    image = np.zeros((60, 400), np.uint8)
    centers = np.column_stack([np.linspace(20, 380, 12) + rng.uniform(-0.5, 0.5, 12), rng.uniform(20, 40, 12)])
    radii = rng.uniform(1.5, 6.0, 12)
    render_discs(image, centers, radii, np.full(12, 220.0))
    found = _centroids(image, centers, radii, np.zeros_like(image))
    assert np.sqrt(((found - centers) ** 2).sum(1).mean()) < 0.05
    # area (sum of coverage) ~ pi r^2
    for (x, y), r in zip(centers, radii):
        h = int(np.ceil(r + 2))
        total = image[int(y) - h:int(y) + h + 2, int(x) - h:int(x) + h + 2].sum() / 220.0
        assert total == pytest.approx(np.pi * r * r, rel=0.06)


def test_frameset_truth_and_subpixel_markers_at_zero_noise(face):
    basis, markers = face
    rig = SimRig(basis, markers, n_cameras=3, config=RigConfig(noise_sigma=0.0, follow_head=False), seed=4)
    assert len(rig.cameras) == 3 and rig.names == ("cam0", "cam1", "cam2")
    for camera in rig.cameras.cameras:
        distance = np.linalg.norm(camera.center - basis.neutral.mean(axis=0))
        assert 450 < distance < 1050 and camera.size == (1280, 800)
    errors = []
    for frameset in rig.framesets(3, start=20):
        assert isinstance(frameset, FrameSet) and frameset.complete and frameset.skew == 0.0
        truth = frameset.truth
        np.testing.assert_allclose(truth.points_3d, rig._performer.performance(21 + frameset.index)
                                   .marker_positions[frameset.index])
        for c, frame in enumerate(frameset.frames):
            assert frame.image.shape == (800, 1280) and frame.image.dtype == np.uint8
            assert frame.source_id == rig.names[c] and frame.seq == frameset.index
            visible = truth.visible[c]
            assert visible.sum() >= 10
            assert np.isnan(truth.points_2d[c, ~visible]).all()
            expected = rig.cameras.cameras[c].project(truth.points_3d[visible])
            np.testing.assert_allclose(truth.points_2d[c, visible], expected)
            background = rig._background(c, 1.0)
            found = _centroids(frame.image, truth.points_2d[c, visible], truth.radius_px[c, visible], background)
            # skip markers whose discs touch another marker's
            pts = truth.points_2d[c, visible]
            gap = np.linalg.norm(pts[:, None] - pts[None], axis=-1) + np.eye(len(pts)) * 1e9
            alone = gap.min(axis=1) > 4 * truth.radius_px[c, visible].max()
            errors.append(found[alone] - pts[alone])
            # markers are bright on a dark image
            assert np.median(frame.image) < 30 and frame.image.max() > 150
    errors = np.concatenate(errors)
    assert np.sqrt((errors ** 2).sum(1).mean()) < 0.1


def _ray_hits_mesh(origin, target, vertices, triangles, margin=2.0):
    """Brute force: does the segment origin->target cross a triangle more than ``margin`` mm before target?"""
    direction = target - origin
    length = np.linalg.norm(direction)
    direction = direction / length
    v0, v1, v2 = (vertices[triangles[:, k]] for k in range(3))
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(direction, e2)
    det = np.einsum("nd,nd->n", e1, p)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1 / np.where(ok, det, 1), 0)
    s = origin - v0
    u = np.einsum("nd,nd->n", s, p) * inv
    q = np.cross(s, e1)
    v = (q @ direction) * inv
    t = np.einsum("nd,nd->n", e2, q) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (t < length - margin)
    return bool(hit.any())


def test_occlusion_agrees_with_ray_casting(face):
    basis, markers = face
    config = RigConfig(noise_sigma=0.0, spread_deg=150.0)  # side cameras: the nose hides markers
    rig = SimRig(basis, markers, n_cameras=5, config=config, seed=1)
    facing = SimRig(basis, markers, n_cameras=5, config=replace(config, occlusion=False), seed=1).truth(40).visible
    truth = rig.truth(40)
    state = rig._state(40)
    assert (facing & ~truth.visible).sum() >= 3  # some markers face the camera but lie behind the face
    agree = total = 0
    for c, camera in enumerate(rig.cameras.cameras):
        for m in np.flatnonzero(facing[c]):
            expected = not _ray_hits_mesh(camera.center, truth.points_3d[m], state.vertices, basis.triangles, 4.0)
            agree += expected == truth.visible[c, m]
            total += 1
    assert agree / total > 0.95, (agree, total)


def test_seeded_and_order_independent(face):
    basis, markers = face
    config = RigConfig(noise_sigma=3.0, spurious_rate=2.0, drop_rate=0.2, jitter_s=0.001)
    a = SimRig(basis, markers, n_cameras=2, config=config, seed=9)
    b = SimRig(basis, markers, n_cameras=2, config=config, seed=9)
    a.start(100.0)
    b.start(100.0)
    frames_a = [a.camera_frame(s, 1) for s in range(12)]
    frames_b = [b.camera_frame(s, 1) for s in reversed(range(12))][::-1]  # other order
    for fa, fb in zip(frames_a, frames_b):
        assert (fa is None) == (fb is None)
        if fa is not None:
            np.testing.assert_array_equal(fa.image, fb.image)
            assert fa.t_capture == fb.t_capture
    assert any(f is None for f in frames_a) and any(f is not None for f in frames_a)
    times = np.array([f.t_capture - 100.0 - f.seq / 60 for f in frames_a if f is not None])
    assert np.all(np.abs(times) <= 0.003 + 1e-12) and np.std(times) > 0
    c = SimRig(basis, markers, n_cameras=2, config=config, seed=10)
    c.start(100.0)
    assert not any(fc is not None and fa is not None and np.array_equal(fa.image, fc.image)
                   for fa, fc in zip(frames_a, (c.camera_frame(s, 1) for s in range(12))))


def test_spurious_highlights_and_motion_blur(face):
    basis, markers = face
    rig = SimRig(basis, markers, n_cameras=1, config=RigConfig(noise_sigma=0, spurious_rate=3.0), seed=3)
    truth = rig.render(5)[1]
    assert len(truth.spurious_2d[0]) > 0
    # motion blur: a long exposure smears fast markers along their motion
    sharp = SimRig(basis, markers, n_cameras=1, config=RigConfig(noise_sigma=0, follow_head=False), seed=3)
    smeared = SimRig(basis, markers, n_cameras=1, config=RigConfig(noise_sigma=0, follow_head=False,
                                                                   motion_blur=True), seed=3)
    smeared.set_exposure(0, 14000.0, 1.0)
    sharp.set_exposure(0, 14000.0, 1.0)
    seq = 70
    img_sharp, img_blur = sharp.camera_frame(seq, 0).image, smeared.camera_frame(seq, 0).image
    assert not np.array_equal(img_sharp, img_blur)
    # blurred discs keep their energy (same total brightness above background) but a lower peak
    bg = sharp._background(0, 14000.0 / 2000.0)
    above_sharp = np.clip(img_sharp.astype(int) - bg, 0, None)
    above_blur = np.clip(img_blur.astype(int) - bg, 0, None)
    assert above_blur.sum() == pytest.approx(above_sharp.sum(), rel=0.05)


def test_exposure_changes_brightness(face):
    basis, markers = face
    rig = SimRig(basis, markers, n_cameras=1, config=RigConfig(noise_sigma=0, marker_level=100), seed=3)
    source = rig.sources(realtime=False)[0]
    with source:
        dim = source.read()
        applied = source.set_exposure(True, 4000.0, 1.5)
        assert applied.manual and applied.exposure_us == 4000.0 and applied.gain == 1.5
        bright = source.read()
    assert bright.exposure_us == 4000.0 and bright.gain == 1.5
    assert bright.image.max() > 2 * dim.image.max() > 150
    assert source.ended


def test_sim_url_opens_one_source_per_camera():
    sources = open_sources("sim://rig?cameras=3&seed=2&noise=0&realtime=0&size=640x400&drop=0.3")
    assert [s.source_id for s in sources] == ["cam0", "cam1", "cam2"]
    assert all(isinstance(s, CameraSource) for s in sources)
    assert sources[0].capabilities.size == (640, 400) and sources[0].capabilities.hardware_sync
    for source in sources:
        source.start()
    frames = [[source.read(timeout=1.0) for _ in range(5)] for source in sources]
    for source in sources:
        source.stop()
    for per_camera in frames:
        assert all(isinstance(f, Frame) and f.image.shape == (400, 640) for f in per_camera)
        seqs = [f.seq for f in per_camera]
        assert seqs == sorted(seqs) and len(set(seqs)) == 5  # dropped frames skipped, never repeated
    assert len({f.sync_domain for per in frames for f in per}) == 1
    with pytest.raises(InputError, match="names 3 cameras"):
        open_source("sim://rig?cameras=3&realtime=0")
    with pytest.raises(InputError, match="nosie"):
        open_sources("sim://rig?nosie=1")
    with pytest.raises(InputError, match="sync"):
        open_sources("sim://rig?sync=sometimes")


def test_realtime_source_is_paced():
    import time

    source = open_source("sim://rig?cameras=1&fps=20&noise=0&size=320x200")
    with source:
        start = time.monotonic()
        frames = [source.read(timeout=1.0) for _ in range(6)]
        elapsed = time.monotonic() - start
        assert source.read(timeout=0.0) is None  # the next frame is not exposed yet
    assert elapsed > 4 / 20
    assert [f.seq for f in frames] == list(range(6))


def test_late_realtime_reader_skips_to_the_newest_frame_without_a_backlog(face):
    """Like a camera driver: a reader that falls behind gets the newest due frame, the skipped are counted."""
    import time

    basis, markers = face
    rig = SimRig(basis, markers, n_cameras=2, config=RigConfig(size=(160, 100), fps=50, noise_sigma=0), seed=0)
    first, second = rig.sources(realtime=True)
    with first, second:
        assert first.read(timeout=1.0).seq == 0
        time.sleep(10 * rig.period)  # the consumer is late by ~10 frames
        late = first.read(timeout=1.0)
        due = rig.due_seq(time.monotonic(), 0)
        assert due - 2 <= late.seq <= due and late.seq >= 9  # the newest frame, not frame 1
        assert first.skipped == late.seq - 1 and first.delivered == 2
        assert time.monotonic() - late.t_capture < 4 * rig.period  # no backlog: the frame is recent
        # the other camera, as late, takes the frame the first one took while that one is still buffered
        assert second.read(timeout=1.0).seq == late.seq
        following = [first.read(timeout=1.0).seq for _ in range(3)]  # back on time: every frame, paced
        assert following == [late.seq + 1, late.seq + 2, late.seq + 3]


def test_killed_camera_ends_cleanly(face):
    basis, markers = face
    rig = SimRig(basis, markers, n_cameras=2, config=RigConfig(size=(320, 200)), seed=0)
    source = rig.sources(realtime=False)[1]
    source.kill_after(2)
    with source:
        got = [source.read() for _ in range(5)]
    assert [f.seq for f in got[:3]] == [0, 1, 2] and got[3] is None and got[4] is None
    assert source.ended and "stopped delivering" in source.error


def test_generated_cameras_look_at_the_face(ict):
    cameras = generate_cameras(ict, 6, RigConfig(), seed=3)
    centre = 0.5 * (ict.neutral.min(0) + ict.neutral.max(0))
    pixels = cameras.project(centre[None])[:, 0]
    np.testing.assert_allclose(pixels, [[639.5, 399.5]] * 6, atol=1e-6)
    assert all(c.center[2] > centre[2] + 300 for c in cameras.cameras)  # in front of the face (+z)


@pytest.mark.parametrize("spec", ["charuco:7x5:30:22:DICT_4X4_50", "chessboard:8x6:25"])
def test_rig_renders_calibration_boards(face, spec):
    from livebridge.calibration.boards import parse_board
    from livebridge.calibration.detect import detect_board
    from livebridge.simulators.rig import face_centre

    basis, markers = face
    board = parse_board(spec)
    rig = SimRig(basis, markers, n_cameras=3, config=RigConfig(size=(640, 400), noise_sigma=1.0), seed=2)
    board2world = np.eye(4)
    board2world[:3, :3] = np.diag([1.0, -1.0, -1.0])  # printed side towards the cameras (+z)
    width, height = board.size_mm
    board2world[:3, 3] = face_centre(basis) + [-width / 2, height / 2, 60.0]
    images = rig.render_board(board, board2world, blur_px=0.5)
    assert len(images) == 3
    corners_world = board.object_points @ board2world[:3, :3].T + board2world[:3, 3]
    for camera, image in zip(rig.cameras.cameras, images):
        assert image.shape == (400, 640) and image.dtype == np.uint8
        found = detect_board(board, image)
        seen = np.isfinite(found).all(axis=1)
        assert seen.sum() >= 0.8 * len(found)
        expected = camera.project(corners_world)
        # a chessboard's corner order is ambiguous up to a half turn: match each corner to the nearest projection
        error = np.linalg.norm(found[seen][:, None] - expected[None], axis=-1).min(axis=1)
        assert np.sqrt((error ** 2).mean()) < 0.5
