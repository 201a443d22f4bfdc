"""The simulated camera rig: rendering, ground truth, occlusion, misbehaviour, URL and sources."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from geometry_reference import behind_surface_numpy

from livebridge.capture.frame import Frame, FrameSet
from livebridge.capture.sources import CameraSource
from livebridge.devices.registry import open_camera, open_cameras
from livebridge.errors import InputError
from livebridge.geometry.transforms import apply
from livebridge.geometry.visibility import depth_cell_mm
from livebridge.simulators.drawing import render_discs
from livebridge.simulators.rig import RigConfig, SimRig, generate_cameras, generate_markers


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
    sources = open_cameras("sim://rig?cameras=3&seed=2&noise=0&realtime=0&size=640x400&drop=0.3")
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
        open_camera("sim://rig?cameras=3&realtime=0")
    with pytest.raises(InputError, match="nosie"):
        open_cameras("sim://rig?nosie=1")
    with pytest.raises(InputError, match="sync"):
        open_cameras("sim://rig?sync=sometimes")


def test_realtime_source_is_paced():
    """No frame is delivered before its exposure ends, and a reader asking before the next one's has ended gets
    none.

    Only lower bounds on time are asserted: a loaded machine (or the first frame's set-up) may take longer than a
    frame period, and a late reader then rightly skips to the newest frame
    (``test_late_realtime_reader_skips_to_the_newest_frame_without_a_backlog``)."""
    import time

    source = open_camera("sim://rig?cameras=1&fps=20&noise=0&size=320x200")
    with source:
        frames = []
        for _ in range(6):
            frames.append(source.read(timeout=1.0))
            assert time.monotonic() >= source.rig.ready_time(frames[-1].seq, source.camera)
        asked = time.monotonic()
        following = source.read(timeout=0.0)
        exposed = source.rig.ready_time(frames[-1].seq + 1, source.camera)
    seqs = [frame.seq for frame in frames]
    assert seqs == sorted(set(seqs)) and seqs[0] == 0
    assert following is None if asked < exposed else following.seq > seqs[-1]


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
    corners_world = apply(board2world, board.object_points)
    for camera, image in zip(rig.cameras.cameras, images):
        assert image.shape == (400, 640) and image.dtype == np.uint8
        found = detect_board(board, image)
        seen = np.isfinite(found).all(axis=1)
        assert seen.sum() >= 0.8 * len(found)
        expected = camera.project(corners_world)
        # a chessboard's corner order is ambiguous up to a half turn: match each corner to the nearest projection
        error = np.linalg.norm(found[seen][:, None] - expected[None], axis=-1).min(axis=1)
        assert np.sqrt((error ** 2).mean()) < 0.5


# ---------------------------------------------------------------- the compiled renderer against the numpy one
# A straightforward numpy renderer (the one the compiled kernels replaced), drawing from the rig's ground
# truth and seeds; images and visibility must match it bit for bit.

def _reference_discs(image, centers, radii, levels):
    """render_discs in numpy: one patch size for all discs, each disc blended in turn."""
    if len(centers) == 0:
        return
    centers = np.asarray(centers, dtype=np.float64)
    if centers.ndim == 2:
        centers = centers[:, None, :]
    height, width = image.shape
    mid = centers.mean(axis=1)
    extent = np.abs(centers - mid[:, None]).max(axis=(1, 2))
    half = int(np.ceil(float(np.max(radii + extent)) + 1.5))
    offsets = np.arange(-half, half + 1, dtype=np.float64)
    corner = np.rint(mid).astype(np.int64)
    fx = (corner[:, None, 0] - centers[:, :, 0])[:, :, None] + offsets
    fy = (corner[:, None, 1] - centers[:, :, 1])[:, :, None] + offsets
    distance = np.sqrt(fy[:, :, :, None] ** 2 + fx[:, :, None, :] ** 2)
    coverage = np.clip(radii[:, None, None, None] + 0.5 - distance, 0.0, 1.0).mean(axis=1)
    for k in range(len(coverage)):
        x0, y0 = corner[k] - half
        cx0, cy0, cx1, cy1 = max(x0, 0), max(y0, 0), min(x0 + 2 * half + 1, width), min(y0 + 2 * half + 1, height)
        if cx0 < cx1 and cy0 < cy1:
            region = image[cy0:cy1, cx0:cx1]
            alpha = coverage[k, cy0 - y0:cy1 - y0, cx0 - x0:cx1 - x0]
            region[...] = np.clip(region + alpha * (levels[k] - region) + 0.5, 0, 255).astype(np.uint8)


def _reference_visible(rig, seq, c):
    """Markers camera ``c`` sees in frame ``seq``: facing it, in the image, not behind a depth splat of the mesh
    (numpy, for the compiled :func:`livebridge.geometry.visibility.behind_surface`)."""
    camera, state = rig.cameras.cameras[c], rig._state(seq)
    to_camera = camera.center - state.markers
    cosine = np.einsum("nd,nd->n", state.normals, to_camera) / np.linalg.norm(to_camera, axis=1)
    marker_cam = apply(camera.world2cam, state.markers)
    pixels = camera.project(state.markers)
    width, height = camera.size
    visible = (cosine >= np.cos(np.radians(rig.config.max_view_deg))) & (marker_cam[:, 2] > 0)
    visible &= (pixels[:, 0] >= -0.5) & (pixels[:, 0] < width - 0.5) & (pixels[:, 1] >= -0.5) & \
        (pixels[:, 1] < height - 0.5)
    if visible.any():
        cell_mm = depth_cell_mm(rig.basis.neutral, rig.basis.triangles)
        surface = apply(camera.world2cam, state.vertices)
        visible[visible] = ~behind_surface_numpy(surface, marker_cam[visible], cosine[visible], cell_mm)
    return visible


def _reference_image(rig, seq, c, truth, tiles):
    """Camera ``c``'s image of frame ``seq`` drawn in numpy from ``truth``, None where the camera drops it.

    ``tiles`` caches the noise tiles, ``(plus, minus)`` per camera."""
    from livebridge.simulators.rig import face_centre

    config, camera, state = rig.config, rig.cameras.cameras[c], rig._state(seq)
    rng = np.random.default_rng([rig.seed, seq, c, 29])
    if config.drop_rate > 0 and rng.random() < config.drop_rate:
        return None, (0, 0)
    exposure_us, gain = rig._exposure[c]
    scale = exposure_us / config.exposure_us * gain
    background = rig._background(c, scale)
    dx = dy = 0
    if config.follow_head and not np.allclose(state.head2world, np.eye(4), atol=1e-9):
        anchor = face_centre(rig.basis)[None]
        dx, dy = np.rint(camera.project(apply(state.head2world, anchor))[0] - camera.project(anchor)[0]).astype(int)
    height, width = background.shape
    image = np.full_like(background, int(round(config.ambient_level)))
    image[max(dy, 0):height + min(dy, 0), max(dx, 0):width + min(dx, 0)] = \
        background[max(-dy, 0):height + min(-dy, 0), max(-dx, 0):width + min(-dx, 0)]
    count = int(rng.poisson(config.spurious_rate)) if config.spurious_rate > 0 else 0
    if count:
        pick = rng.integers(0, len(rig.basis.neutral), size=count)
        spurious = camera.project(apply(state.head2world, rig.basis.neutral[pick]))
        spurious = spurious[np.isfinite(spurious).all(axis=1)]
        np.testing.assert_array_equal(spurious, truth.spurious_2d[c])
        _reference_discs(image, spurious, rng.uniform(0.8, 2.5, size=len(spurious)),
                         np.minimum(255.0, rng.uniform(0.5, 1.1, size=len(spurious)) * config.marker_level))
    seen = truth.visible[c]
    centers = truth.points_2d[c, seen]
    if config.motion_blur:
        previous = camera.project(state.previous[seen])
        steps = np.linspace(-0.5, 0.5, 7)[None, :, None]
        centers = centers[:, None, :] + steps * (exposure_us * 1e-6 * config.fps) * (centers - previous)[:, None, :]
    level = min(255.0, config.marker_level * scale)
    _reference_discs(image, centers, truth.radius_px[c, seen], np.full(seen.sum(), level))
    if config.noise_sigma > 0:
        if c not in tiles:
            noise = np.rint(np.random.default_rng([rig.seed * 1000 + c, 13]).normal(
                0.0, config.noise_sigma, size=(height + 97, width + 97)).astype(np.float32))
            tiles[c] = np.clip(noise, 0, 255).astype(np.uint8), np.clip(-noise, 0, 255).astype(np.uint8)
        ox, oy = rng.integers(0, 97, size=2)
        cv2.add(image, tiles[c][0][oy:oy + height, ox:ox + width], dst=image)
        cv2.subtract(image, tiles[c][1][oy:oy + height, ox:ox + width], dst=image)
    return image, (dx, dy)


def test_render_discs_matches_numpy_with_blur_overlaps_and_edges(rng):
    image = rng.integers(0, 80, size=(90, 160)).astype(np.uint8)
    n = 40
    centers = np.column_stack([rng.uniform(-8, 168, n), rng.uniform(-8, 98, n)])  # some past the edges
    centers[1:6] = centers[0] + rng.uniform(-4, 4, (5, 2))  # discs on top of each other
    radii, levels = rng.uniform(0.6, 7.0, n), rng.uniform(120, 255, n)
    for samples in (centers, centers[:, None] + rng.uniform(-3, 3, (n, 7, 2))):  # plain and motion-blurred
        expected, got = image.copy(), image.copy()
        _reference_discs(expected, samples, radii, levels)
        render_discs(got, samples, radii, levels)
        np.testing.assert_array_equal(got, expected)
        assert (got != image).sum() > 1000


@pytest.mark.parametrize("config, n_cameras", [
    (RigConfig(), 4),  # the demo's rig: noise, the background following the head
    (RigConfig(noise_sigma=70.0, spurious_rate=4.0, motion_blur=True, drop_rate=0.2, size=(640, 400)), 3),
    (RigConfig(noise_sigma=0.0, spread_deg=150.0, marker_diameter_mm=6.0, size=(640, 400)), 5),
])
def test_images_and_visibility_match_the_numpy_renderer(face, config, n_cameras):
    basis, markers = face
    rig = SimRig(basis, markers, n_cameras=n_cameras, config=config, seed=6)
    rig.set_exposure(0, 6000.0, 1.5)  # a brighter camera, and a long exposure to blur
    tiles, shifts, drawn = {}, set(), 0
    for seq in (0, 17, 60, 95, 140):
        frames, truth = rig.render(seq)
        for c in range(n_cameras):
            expected, shift = _reference_image(rig, seq, c, truth, tiles)
            assert (frames[c] is None) == (expected is None) == truth.dropped[c]
            if expected is not None:
                np.testing.assert_array_equal(frames[c].image, expected)
                np.testing.assert_array_equal(truth.visible[c], _reference_visible(rig, seq, c))
                shifts.add(shift)
                drawn += 1
    assert drawn >= 10 and len(shifts) > 1  # the background did move with the head


# ------------------------------------------------------------------------------------- random occlusion

def test_occlusion_rate_hides_views_at_random_and_leaves_them_undrawn(face):
    basis, markers = face
    config, rate = RigConfig(noise_sigma=0.0), 0.3
    clean = SimRig(basis, markers, n_cameras=4, config=config, seed=5)
    occluded = SimRig(basis, markers, n_cameras=4, config=replace(config, occlusion_rate=rate), seed=5)
    seqs = range(0, 240, 6)
    before = np.array([clean.truth(seq).visible for seq in seqs])
    after = np.array([occluded.truth(seq).visible for seq in seqs])
    assert not (after & ~before).any()  # it only hides
    assert (before & ~after).sum() / before.sum() == pytest.approx(rate, abs=0.03)
    frames, truth = occluded.render(42)
    seen = clean.truth(42)
    hidden = seen.visible & ~truth.visible
    assert hidden.any() and np.isnan(truth.points_2d[hidden]).all() and np.isnan(truth.radius_px[hidden]).all()
    for c, m in zip(*np.nonzero(hidden)):
        others = truth.points_2d[c, truth.visible[c]]
        if np.linalg.norm(others - seen.points_2d[c, m], axis=1).min() > 15:  # no visible marker's disc nearby
            x, y = np.rint(seen.points_2d[c, m]).astype(int)
            assert frames[c].image[y - 1:y + 2, x - 1:x + 2].max() < 100  # markers are drawn at 230


def test_occlusion_rate_is_seeded_and_order_independent(face):
    basis, markers = face
    config = RigConfig(noise_sigma=0.0, occlusion_rate=0.4, drop_rate=0.1, size=(320, 200))
    a = SimRig(basis, markers, n_cameras=3, config=config, seed=8)
    b = SimRig(basis, markers, n_cameras=3, config=config, seed=8)
    forward = [a.render(seq, cameras=[2])[1].visible[2] for seq in range(12)]
    backward = [b.truth(seq).visible[2] for seq in reversed(range(12))][::-1]  # other order, truth only
    np.testing.assert_array_equal(forward, backward)
    other = SimRig(basis, markers, n_cameras=3, config=config, seed=9)
    assert not np.array_equal(forward, [other.truth(seq).visible[2] for seq in range(12)])


@pytest.mark.parametrize("rate", [-0.1, 1.0, 2.0])
def test_occlusion_rate_is_validated(rate):
    with pytest.raises(InputError, match="occlusion_rate") as error:
        RigConfig(occlusion_rate=rate)
    assert error.value.field == "occlusion_rate"


def test_sim_url_takes_the_occlusion_rate():
    from livebridge.simulators.rig_url import rig_from_url

    assert rig_from_url("sim://rig?cameras=1&size=64x40&occlusion_rate=0.25").config.occlusion_rate == 0.25
    with pytest.raises(InputError, match="occlusion_rate") as error:
        rig_from_url("sim://rig?cameras=1&occlusion_rate=1.5")
    assert error.value.field == "occlusion_rate" and "sim://rig" in error.value.path


_BAD_RIG_URLS = [  # (query, the parameter the error names, a piece of the range it quotes)
    ("cameras=1000", "cameras", "1..16"), ("cameras=0", "cameras", "1..16"), ("cameras=-3", "cameras", "1..16"),
    ("size=0x0", "size", "16..4096"), ("size=-5x10", "size", "16..4096"),
    ("size=100000x100000", "size", "16..4096"), ("size=640x5", "size", "16..4096"),
    ("fps=nan", "fps", "[1, 1000]"), ("fps=inf", "fps", "[1, 1000]"), ("fps=0", "fps", "[1, 1000]"),
    ("fps=-1", "fps", "[1, 1000]"), ("fps=100000", "fps", "[1, 1000]"),
    ("noise=-1", "noise", "[0, 255]"), ("noise=nan", "noise", "[0, 255]"), ("noise=inf", "noise", "[0, 255]"),
    ("seed=-1", "seed", "0..4294967295"), ("seed=99999999999", "seed", "0..4294967295"),
    ("drop=1", "drop", "[0, 1)"), ("drop=nan", "drop", "[0, 1)"),
    ("occlusion_rate=1.5", "occlusion_rate", "[0, 1)"), ("occlusion_rate=nan", "occlusion_rate", "[0, 1)"),
    ("spurious=inf", "spurious", "[0, 100]"), ("spurious=1e9", "spurious", "[0, 100]"),
    ("jitter_ms=inf", "jitter_ms", "[0, 1000]"), ("jitter_ms=-1", "jitter_ms", "[0, 1000]"),
    ("diameter_mm=0", "diameter_mm", "(0, 50]"), ("diameter_mm=nan", "diameter_mm", "(0, 50]"),
    ("frames=0", "frames", "1..1000000000"), ("script=dance", "script", "training"),
]


@pytest.mark.parametrize("query, field, allowed", _BAD_RIG_URLS)
def test_sim_url_values_are_bounded_before_anything_is_built(monkeypatch, query, field, allowed):
    import livebridge.simulators.rig_url as rig_url

    def built(*args, **kwargs):
        raise AssertionError("the rig was built before its URL was checked")

    monkeypatch.setattr(rig_url, "default_face", built)
    with pytest.raises(InputError) as error:
        open_cameras(f"sim://rig?{query}&realtime=0")
    assert error.value.field == field and allowed in error.value.message and field in error.value.message
    assert "sim://rig" in error.value.path


@pytest.mark.parametrize("changes", [{"fps": float("inf")}, {"size": (8, 8)}, {"fill": 0.0},
                                     {"distance_mm": (800.0, 600.0)}, {"exposure_us": float("nan")},
                                     {"max_view_deg": 270.0}, {"buffers": 0}, {"marker_level": 300.0}])
def test_rig_config_values_are_bounded(changes):
    with pytest.raises(InputError) as error:
        RigConfig(**changes)
    assert error.value.field == next(iter(changes))


def test_sim_url_cameras_must_match_its_calibration(tmp_path, face):
    from livebridge.calibration.calibfile import save_calibration

    basis, _ = face
    save_calibration(tmp_path / "calib.toml", generate_cameras(basis, 3, RigConfig(size=(64, 40))))
    with pytest.raises(InputError, match="cameras=4 but the calibration has 3") as error:
        open_cameras(f"sim://rig?cameras=4&calibration={tmp_path / 'calib.toml'}&realtime=0")
    assert error.value.field == "cameras"
    assert len(open_cameras(f"sim://rig?cameras=3&calibration={tmp_path / 'calib.toml'}&realtime=0")) == 3
