"""The face-video simulator against its own ground truth: determinism, LEDs, light, muscles, skin, URLs."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from livebridge.devices.registry import open_cameras
from livebridge.errors import InputError
from livebridge.face.builtin import builtin_basis
from livebridge.reconstruct.detect import DetectConfig, detect_blobs
from livebridge.simulators.face_video import FaceVideo, FaceVideoConfig, LightState
from livebridge.simulators.head_rig import HeadRig, load_head_rig
from livebridge.simulators.performer import COMBINED_GESTURES, TRAINING_BLOCK_S, GestureScript

LED_THRESHOLD = DetectConfig(threshold=235.0, min_area=3, max_area=400)


@pytest.fixture(scope="module")
def basis():
    return builtin_basis()


@pytest.fixture(scope="module")
def clean(basis):
    """No noise, still head, steady light: pixel differences come from the scene only."""
    return FaceVideo(basis, FaceVideoConfig(noise=0.0))


@pytest.fixture(scope="module")
def moving(basis):
    return FaceVideo(basis, FaceVideoConfig(seed=3, head_turn_deg=10.0, light_drift=0.2, script="everyday"))


def test_a_seed_gives_the_same_take_and_another_seed_another(basis, moving):
    again = FaceVideo(basis, FaceVideoConfig(seed=3, head_turn_deg=10.0, light_drift=0.2, script="everyday"))
    other = FaceVideo(basis, FaceVideoConfig(seed=4, head_turn_deg=10.0, light_drift=0.2, script="everyday"))
    streamed = list(moving.frames(3, start=40))
    for frame in streamed:
        alone = again.frame(frame.seq)
        assert np.array_equal(frame.image, alone.image)
        assert np.array_equal(frame.head_pose, alone.head_pose)
        np.testing.assert_array_equal(frame.led_points_2d, alone.led_points_2d)
    assert not np.array_equal(streamed[0].image, other.frame(40).image)
    assert not np.allclose(streamed[0].head_pose, other.frame(40).head_pose)


def test_the_leds_are_where_the_camera_projects_them_and_the_blob_detector_finds_them(moving):
    camera = moving.camera()
    checked = 0
    for seq in (30, 90, 150, 210, 270):
        frame = moving.frame(seq)
        world = moving.head_rig_geometry() @ frame.head_pose[:3, :3].T + frame.head_pose[:3, 3]
        projected = camera.project(world)
        shown = np.isfinite(frame.led_points_2d).all(axis=1)
        assert shown.sum() >= 3  # a +-10 degree turn hides at most one
        np.testing.assert_allclose(frame.led_points_2d[shown], projected[shown], atol=1e-6)
        blobs = detect_blobs(frame.image, LED_THRESHOLD)
        assert len(blobs) == shown.sum()
        distance = np.linalg.norm(blobs[:, None] - frame.led_points_2d[None, shown], axis=2)
        assert distance.min(axis=0).max() < 0.3  # every LED found, to a third of a pixel
        checked += 1
    assert checked == 5


def test_a_head_without_a_rig_shows_no_leds(basis):
    video = FaceVideo(basis, FaceVideoConfig(head_rig="none"))
    frame = video.frame(10)
    assert np.isnan(frame.led_points_2d).all()
    assert len(detect_blobs(frame.image, LED_THRESHOLD)) == 0


def test_an_led_behind_the_skin_is_hidden_and_one_turned_away_too(basis, clean):
    """An LED moved behind the skin (inside the head) is not drawn while the others are; a head turned
    beyond the LEDs' viewing angle shows none."""
    positions = clean.head_rig_geometry()
    skin = basis.neutral[np.argmin(np.linalg.norm(basis.neutral[:, :2] - positions[0, :2], axis=1))]
    positions[0, 2] = skin[2] - 15.0
    behind = FaceVideo(basis, FaceVideoConfig(noise=0.0), head_rig=HeadRig(clean.head_rig.names, positions))
    image, leds = behind.render_with_leds(np.zeros(basis.n_muscles))
    assert np.isnan(leds[0]).all() and np.isfinite(leds[1:]).all()
    x, y = (int(round(v)) for v in behind.camera().project(positions[:1])[0])
    assert image[y, x] < 235  # not drawn there
    assert len(detect_blobs(image, LED_THRESHOLD)) == 3
    pose = np.eye(4)
    pivot = basis.neutral.mean(axis=0)
    rotation = cv2.Rodrigues(np.array([0.0, math.radians(85.0), 0.0]))[0]
    pose[:3, :3], pose[:3, 3] = rotation, pivot - rotation @ pivot
    assert np.isnan(clean.render_with_leds(np.zeros(basis.n_muscles), pose)[1]).all()


def _face_mask(video, basis) -> np.ndarray:
    """Pixels inside the outline of the front of the face, shape (height, width) bool."""
    mask = np.zeros((video.config.height, video.config.width), np.uint8)
    front = basis.neutral[basis.neutral[:, 2] > np.median(basis.neutral[:, 2])]
    hull = cv2.convexHull(np.rint(video.camera().project(front) * 16).astype(np.int32))
    cv2.fillConvexPoly(mask, hull, 1, shift=4)
    return mask.astype(bool)


def test_shading_follows_the_light(basis, clean):
    rest = np.zeros(basis.n_muscles)
    face = _face_mask(clean, basis)
    half = clean.config.width // 2
    left_lit = clean.render(rest, light=LightState(np.array([0.8, 0.0, 0.6]), 1.0)).astype(float)  # performer's left
    right_lit = clean.render(rest, light=LightState(np.array([-0.8, 0.0, 0.6]), 1.0)).astype(float)
    # the performer's left (+x) is on the image's right
    image_right = face.copy()
    image_right[:, :half] = False
    image_left = face.copy()
    image_left[:, half:] = False
    assert left_lit[image_right].mean() > right_lit[image_right].mean() + 15
    assert right_lit[image_left].mean() > left_lit[image_left].mean() + 15
    dim = clean.render(rest, light=LightState(np.array([0.0, 0.0, 1.0]), 0.8)).astype(float)
    bright = clean.render(rest, light=LightState(np.array([0.0, 0.0, 1.0]), 1.2)).astype(float)
    assert bright[face].mean() > dim[face].mean() * 1.15


def test_the_light_drifts_within_its_bounds(moving):
    lights = [moving.light_at(t) for t in np.linspace(0.0, 60.0, 300)]
    intensity = np.array([light.intensity for light in lights])
    assert intensity.min() >= 0.8 - 1e-9 and intensity.max() <= 1.2 + 1e-9
    assert np.ptp(intensity) > 0.1  # it does drift
    directions = np.array([light.direction for light in lights])
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0)
    assert np.ptp(directions[:, 0]) > 0.1


@pytest.mark.parametrize("muscle", ["frontalis_L", "corrugator_R", "zygomatic_major_R", "jaw"])
def test_a_contraction_changes_the_pixels_of_its_region_only(basis, clean, muscle):
    index = basis.index(muscle)
    contracted = np.zeros(basis.n_muscles)
    contracted[index] = 1.0
    neutral_image = clean.render(np.zeros(basis.n_muscles)).astype(int)
    changed = np.abs(clean.render(contracted).astype(int) - neutral_image)
    moves = np.linalg.norm(basis.elements[index], axis=1) > 0.05  # mm
    region = np.zeros(changed.shape, np.uint8)
    touched = basis.triangles[moves[basis.triangles].any(axis=1)]
    for step in np.linspace(0.0, 1.0, 5):  # everything the moving skin sweeps over
        pixels = clean.camera().project(basis.neutral + step * basis.elements[index])
        cv2.fillPoly(region, list(np.rint(pixels[touched] * 16).astype(np.int32)), 1, shift=4)
    near = cv2.dilate(region, np.ones((9, 9), np.uint8)).astype(bool)
    assert (changed[near] > 8).sum() > 50  # the region visibly changes
    assert changed[~near].max() <= 2  # nothing far from it does


def test_the_texture_moves_with_the_skin(basis):
    """Raise the left brow: a skin patch on the forehead is found again (template matching) where its
    vertex's projection went, not where it was."""
    video = FaceVideo(basis, FaceVideoConfig(width=720, height=480, noise=0.0, head_rig="none"))
    index = basis.index("frontalis_L")
    field = basis.elements[index]
    camera = video.camera()
    front = basis.neutral[:, 2] > np.percentile(basis.neutral[:, 2], 60)
    vertex = int(np.argmax(np.linalg.norm(field, axis=1) * front))
    start, end = camera.project(np.stack([basis.neutral[vertex], basis.neutral[vertex] + field[vertex]]))
    assert np.linalg.norm(end - start) > 4.0  # the test can tell moved from still
    contracted = np.zeros(basis.n_muscles)
    contracted[index] = 0.6  # partway: the expected motion is 0.6 of the full one
    end = camera.project((basis.neutral[vertex] + 0.6 * field[vertex])[None])[0]
    before = video.render(np.zeros(basis.n_muscles))
    after = video.render(contracted)
    half = 10
    x, y = (int(round(v)) for v in start)
    patch = before[y - half:y + half + 1, x - half:x + half + 1]
    reach = 20
    window = after[y - half - reach:y + half + reach + 1, x - half - reach:x + half + reach + 1]
    score = cv2.matchTemplate(window, patch, cv2.TM_CCOEFF_NORMED)
    dy, dx = np.unravel_index(np.argmax(score), score.shape)
    found = np.array([x - reach + dx, y - reach + dy], dtype=float)
    assert score.max() > 0.6
    assert np.linalg.norm(found - end) <= 1.5
    assert np.linalg.norm(found - start) >= np.linalg.norm(end - start) - 1.5


def test_compressed_skin_wrinkles(basis, clean):
    """Frontalis shortens the forehead: fine dark lines appear there (more high-frequency energy), beyond
    what the moved texture alone would show (the same contraction with wrinkles switched off)."""
    flat = FaceVideo(basis, FaceVideoConfig(noise=0.0, wrinkle=0.0))
    contracted = np.zeros(basis.n_muscles)
    contracted[basis.index("frontalis_L")] = contracted[basis.index("frontalis_R")] = 1.0
    x, y, z = basis.neutral.T
    forehead = basis.neutral[(y > 52) & (y < 75) & (np.abs(x) < 30) & (z > np.median(z))]
    pixels = np.rint(clean.camera().project(forehead)).astype(int)
    box = (slice(pixels[:, 1].min(), pixels[:, 1].max()), slice(pixels[:, 0].min(), pixels[:, 0].max()))

    def detail(image):
        return float(np.abs(cv2.Laplacian(image.astype(np.float32), cv2.CV_32F))[box].mean())

    assert detail(clean.render(contracted)) > 1.3 * detail(flat.render(contracted))
    assert detail(clean.render(np.zeros(basis.n_muscles))) == pytest.approx(
        detail(flat.render(np.zeros(basis.n_muscles))), rel=1e-6)


@pytest.mark.parametrize("size", [(360, 240), (640, 400), (1280, 800)])
def test_sizes(basis, size):
    video = FaceVideo(basis, FaceVideoConfig(width=size[0], height=size[1]))
    frame = video.frame(0)
    assert frame.image.shape == (size[1], size[0]) and frame.image.dtype == np.uint8
    assert np.isfinite(frame.led_points_2d).all()
    camera = video.camera()
    assert camera.size == size
    # the face fills the same share of the picture at every size
    face = _face_mask(video, basis)
    assert 0.2 < face.mean() < 0.5


def test_the_ict_face_renders(ict):
    video = FaceVideo(ict, FaceVideoConfig(seed=1, head_turn_deg=10.0))
    frame = video.frame(30)
    assert np.isfinite(frame.led_points_2d).sum(axis=0).min() >= 3
    assert len(detect_blobs(frame.image, LED_THRESHOLD)) == np.isfinite(frame.led_points_2d).all(axis=1).sum()
    assert 60 < frame.image[_face_mask(video, ict)].mean() < 200


def test_the_gesture_take_sweeps_each_muscle_alone_then_the_combinations(basis):
    script = GestureScript(basis.names)
    assert script.gesture_names[:basis.n_muscles] == basis.names
    assert set(script.gesture_names[basis.n_muscles:]) == set(COMBINED_GESTURES)
    for k, name in enumerate(script.gesture_names):
        middle = (k + 0.5) * TRAINING_BLOCK_S
        x = script(np.array([middle, k * TRAINING_BLOCK_S]))
        assert script.gesture_names[int(script.gesture_at(np.array([middle]))[0])] == name
        assert x[1].max() == 0.0  # neutral between gestures
        if k < basis.n_muscles:
            assert x[0, k] == pytest.approx(1.0) and np.delete(x[0], k).max() == 0.0
        else:
            expected = {basis.index(m): level for m, level in COMBINED_GESTURES[name].items()}
            assert {i: pytest.approx(v) for i, v in expected.items()} == {i: x[0, i] for i in expected}


def test_frames_carry_the_gesture_label(basis):
    video = FaceVideo(basis, FaceVideoConfig(script="gestures", fps=10.0))
    labels = [video.frame(seq).gesture for seq in (5, 25, 45)]  # the middle of blocks 0, 1 and 2
    assert labels == list(basis.names[:3])


def test_the_url_opens_a_source_with_ground_truth():
    sources = open_cameras("sim://face?seed=3&size=320x200&fps=30&light_drift=0.2&head_turn=10&head_rig=leds"
                           "&noise=2&script=mixed&realtime=0&frames=4")
    assert len(sources) == 1
    source = sources[0]
    with source:
        frames = [source.read(timeout=5.0) for _ in range(5)]
    assert frames[-1] is None and source.ended and source.error is None
    assert [f.seq for f in frames[:4]] == [0, 1, 2, 3]
    truth = source.truth(2)
    assert np.array_equal(truth.image, frames[2].image)
    assert source.calibration.size == (320, 200) and frames[0].image.shape == (200, 320)
    assert np.isfinite(truth.contractions).all() and truth.head_pose.shape == (4, 4)


@pytest.mark.parametrize(("url", "field"), [
    ("sim://face?size=10x10", "size"),
    ("sim://face?size=big", "size"),
    ("sim://face?head_rig=helmet", "head_rig"),
    ("sim://face?script=dance", "script"),
    ("sim://face?light_drift=nan", "light_drift"),
    ("sim://face?light_drift=2", "light_drift"),
    ("sim://face?head_turn=-5", "head_turn"),
    ("sim://face?noise=x", "noise"),
    ("sim://face?fps=0", "fps"),
    ("sim://face?seed=-1", "seed"),
    ("sim://face?frames=0", "frames"),
    ("sim://face?basis=missing.npz", None),
    ("sim://face?basis=ict.obj", "basis"),
    ("sim://face?cameras=2", "cameras"),
    ("sim://face?fps=30&fps=60", "fps"),
    ("sim://faces", None),
])
def test_bad_url_options_are_input_errors(url, field):
    with pytest.raises(InputError) as error:
        open_cameras(url)
    if field is not None:
        assert error.value.field == field


def test_the_head_rig_file_round_trips(tmp_path, clean):
    path = tmp_path / "head_rig.toml"
    clean.head_rig.save(path)
    loaded = load_head_rig(path)
    assert loaded.names == clean.head_rig.names
    np.testing.assert_array_equal(loaded.positions, clean.head_rig.positions)


@pytest.mark.parametrize(("text", "field"), [
    ("[other]\n", "leds"),
    ("leds = 3\n", "leds"),
    ("[leds]\na = [0, 0, 0]\nb = [10, 0, 0]\nc = [0, 10, 0]\n", "leds"),
    ("[leds]\na = [0, 0, 0]\nb = [10, 0, 0]\nc = [0, 10, 0]\nd = [10, 10]\n", "leds.d"),
    ("[leds]\na = [0, 0, 0]\nb = [10, 0, 0]\nc = [0, 10, 0]\nd = [10, 10, 'x']\n", "leds.d"),
    ("[leds]\na = [0, 0, 0]\nb = [10, 0, 0]\nc = [0, 10, 0]\nd = [10, 10, nan]\n", "leds.d"),
    ("[leds]\na = [0, 0, 0]\nb = [10, 0, 0]\nc = [0, 10, 0]\nd = [1, 1, 0]\n", "leds.d"),
    ("[leds]\na = [0, 0, 0]\nb = [10, 0, 0]\nc = [20, 0, 0]\nd = [30, 0, 0]\n", "leds"),
    ("[leds\n", None),
])
def test_a_malformed_head_rig_file_names_the_field(tmp_path, text, field):
    path = tmp_path / "head_rig.toml"
    path.write_text(text)
    with pytest.raises(InputError) as error:
        load_head_rig(path)
    assert str(path) in str(error.value)
    if field is not None:
        assert error.value.field == field


def test_a_rig_file_from_the_url(tmp_path, clean):
    rig = HeadRig(("a", "b", "c", "d"), clean.head_rig.positions + np.array([0.0, 3.0, 0.0]))
    rig.save(tmp_path / "rig.toml")
    source = open_cameras(f"sim://face?realtime=0&rig_file={tmp_path / 'rig.toml'}")[0]
    np.testing.assert_allclose(source.video.head_rig_geometry(), rig.positions)
