"""Blob detection: sub-pixel centroids, size and circularity filters, undistortion, rig images."""

from __future__ import annotations

import numpy as np
import pytest
from test_triangulate import ring_cameras

from livebridge.reconstruct.detect import DetectConfig, detect_blobs, detect_markers

DEFAULT = DetectConfig()


def draw_blob(image, center, sigma=1.6, peak=200.0, elongation=1.0):
    """Add a Gaussian spot (supersampled; ``elongation`` stretches it along x)."""
    ys, xs = np.mgrid[0:image.shape[0], 0:image.shape[1]]
    image += peak * np.exp(-(((xs - center[0]) / (sigma * elongation)) ** 2 + ((ys - center[1]) / sigma) ** 2) / 2)


def test_subpixel_centroids_are_not_rounded(rng):
    image = np.full((120, 160), 20.0)
    centers = np.array([[20.3, 30.7], [60.55, 25.2], [100.81, 80.49], [140.1, 100.9], [40.5, 90.25]])
    for center in centers:
        draw_blob(image, center)
    image += rng.normal(scale=1.0, size=image.shape)
    found = detect_blobs(np.clip(image, 0, 255).astype(np.uint8))
    assert len(found) == len(centers)
    distance = np.linalg.norm(found[:, None] - centers[None], axis=-1).min(axis=0)
    assert distance.max() < 0.08
    # a mask centroid would be rounded to the pixel grid far more often than this
    assert np.abs(found - np.round(found)).max() > 0.1


def test_size_and_circularity_filters(rng):
    image = np.full((100, 200), 10.0)
    draw_blob(image, (30.2, 50.4))  # a marker
    draw_blob(image, (100.0, 50.0), elongation=5.0)  # a streak (specular line)
    image[10:60, 150:195] += 200.0  # a large bright area
    image[90, 10] += 200.0  # a single hot pixel
    found = detect_blobs(np.clip(image, 0, 255).astype(np.uint8), DetectConfig(min_area=3, max_area=400))
    assert len(found) == 1
    assert np.linalg.norm(found[0] - [30.2, 50.4]) < 0.1


def test_centroids_are_undistorted(rng):
    cameras = ring_cameras(k1=-0.2)
    camera = cameras.cameras[0]
    true_pixels = np.array([[100.3, 80.6], [1150.2, 700.7], [640.0, 400.0]])
    images = []
    for c in range(len(cameras)):
        image = np.full((800, 1280), 8.0)
        if c == 0:
            sub = np.zeros((800, 1280))
            for p in true_pixels:
                x0, y0 = int(p[0]) - 10, int(p[1]) - 10
                patch = sub[y0:y0 + 20, x0:x0 + 20]
                draw_blob(patch, (p[0] - x0, p[1] - y0))
            image += sub
        images.append(np.clip(image, 0, 255).astype(np.uint8))
    found = detect_markers(images, cameras)
    assert [len(f) for f in found] == [3, 0, 0, 0]
    expected = camera.undistort_points(true_pixels)
    assert np.linalg.norm(expected - true_pixels, axis=1).max() > 5  # the distortion matters here
    assert np.linalg.norm(found[0][:, None] - expected[None], axis=-1).min(axis=0).max() < 0.1


def test_rig_images_centroids_match_truth(ict):
    from livebridge.simulators.rig import RigConfig, SimRig, generate_markers

    markers = generate_markers(ict, n_face=40, n_head=4)
    rig = SimRig(ict, markers, config=RigConfig(spurious_rate=2.0), seed=3)
    errors, expected, hits = [], 0, 0
    for frameset in rig.framesets(2):
        truth = frameset.truth
        for c, frame in enumerate(frameset.frames):
            found = detect_blobs(frame.image)
            expected_blobs = reference_blobs(frame.image)
            assert found.shape == expected_blobs.shape and np.abs(found - expected_blobs).max() <= 1e-9
            true = truth.points_2d[c][truth.visible[c]]
            distance = np.linalg.norm(found[:, None] - true[None], axis=-1).min(axis=0)
            expected += len(true)
            hits += int((distance < 1.0).sum())
            errors.append(distance[distance < 1.0])
    errors = np.concatenate(errors)
    assert hits / expected > 0.97
    assert np.sqrt(np.mean(errors**2)) < 0.15


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_other_image_types(dtype):
    image = np.full((60, 60), 100.0)
    draw_blob(image, (30.4, 20.6), peak=3000.0)
    found = detect_blobs(image.astype(dtype))
    assert len(found) == 1 and np.linalg.norm(found[0] - [30.4, 20.6]) < 0.05


def reference_threshold(gray: np.ndarray, config: DetectConfig) -> float:
    """The documented threshold with plain ``np.median`` on every 4th pixel of every 4th row."""
    if config.threshold is not None:
        return float(config.threshold)
    sample = gray[::4, ::4]
    background = float(np.median(sample))
    noise = 1.4826 * float(np.median(np.abs(sample - background)))
    return max(background + config.contrast * (float(gray.max()) - background), background + 6 * noise)


def reference_blobs(image: np.ndarray, config: DetectConfig = DEFAULT) -> np.ndarray:
    """Plain per-blob form of the detector, for comparison: OpenCV labelling, then one blob at a time in numpy.

    Labels the bright pixels' bounding box grown by the margin, as the detector numbers its blobs, so the
    blobs come in the same order.
    """
    import cv2

    image = np.asarray(image)
    if image.ndim == 3:
        image = image.mean(axis=2)
    gray = image if image.dtype == np.uint8 else image.astype(np.float32)
    mask = (gray > reference_threshold(gray, config)).astype(np.uint8)  # 8-bit: in float64; float32: in float32
    if not mask.any():
        return np.zeros((0, 2))
    ys, xs = np.nonzero(mask)
    m = config.margin
    top, left = max(ys.min() - m, 0), max(xs.min() - m, 0)
    gray = gray[top:ys.max() + 1 + m, left:xs.max() + 1 + m]
    _, labels, stats, _ = cv2.connectedComponentsWithStats(mask[top:top + gray.shape[0], left:left + gray.shape[1]],
                                                           connectivity=8)
    height, width = gray.shape
    out = []
    for label in range(1, len(stats)):
        x0, y0, w, h, area = stats[label]
        if not config.min_area <= area <= config.max_area:
            continue
        xa, ya, xb, yb = max(x0 - m, 0), max(y0 - m, 0), min(x0 + w + m, width), min(y0 + h + m, height)
        patch, own = gray[ya:yb, xa:xb].astype(np.float64), labels[ya:yb, xa:xb]
        border = np.zeros(patch.shape, dtype=bool)
        border[[0, -1], :] = border[:, [0, -1]] = True
        mine = (own == 0) | (own == label)
        weight = np.where(mine, np.maximum(patch - np.median(patch[border]), 0.0), 0.0)
        total = weight.sum()
        if not total > 0:
            continue
        ys, xs = np.mgrid[ya:yb, xa:xb]
        cx, cy = (weight * xs).sum() / total, (weight * ys).sum() / total
        cxx, cyy = (weight * (xs - cx) ** 2).sum() / total, (weight * (ys - cy) ** 2).sum() / total
        cxy = (weight * (xs - cx) * (ys - cy)).sum() / total
        spread = np.sqrt(((cxx - cyy) / 2) ** 2 + cxy**2)
        major, minor = (cxx + cyy) / 2 + spread, (cxx + cyy) / 2 - spread
        if major > 0 and np.sqrt(max(minor, 0.0) / major) >= config.min_circularity:
            out.append((cx + left, cy + top))
    return np.array(out).reshape(-1, 2)


def assert_same_blobs(image, config: DetectConfig = DEFAULT):
    """``detect_blobs`` finds the blobs of :func:`reference_blobs`, in the same order, to 1e-9 px."""
    found, expected = detect_blobs(image, config), reference_blobs(image, config)
    assert found.shape == expected.shape
    if len(found):
        assert np.abs(found - expected).max() <= 1e-9


@pytest.mark.parametrize("kind", ["uint8", "uint16", "float32", "colour"])
def test_centroids_equal_the_per_blob_form(rng, kind):
    """Blobs of many sizes and shapes, touching the image edges and each other, several configurations."""
    for trial in range(40):
        height, width = rng.integers(20, 90, size=2)
        image = rng.normal(20.0, 3.0, size=(height, width))
        for _ in range(rng.integers(0, 10)):
            draw_blob(image, rng.uniform(-3, [width + 3, height + 3]), sigma=rng.uniform(0.4, 6.0),
                      peak=rng.uniform(50, 230), elongation=rng.uniform(0.3, 3.0))
        image = np.clip(image, 0, 255)
        if kind == "colour":
            image = np.dstack([image, 0.5 * image, np.roll(image, 1, axis=1)]).astype(np.uint8)
        else:
            image = (image * (200 if kind == "uint16" else 1)).astype(kind)
        config = DetectConfig(threshold=[None, None, 70.5 * (200 if kind == "uint16" else 1)][trial % 3],
                              max_area=int(rng.choice([5000, 60])), margin=int(rng.integers(0, 4)),
                              min_area=int(rng.integers(1, 4)), min_circularity=float(rng.choice([0.0, 0.5, 0.8])))
        assert_same_blobs(image, config)


def test_centroids_equal_the_per_blob_form_in_corner_cases(rng):
    """Nearby and touching blobs, blobs cut by the image border, empty images, single pixels and lines."""
    background = np.full((60, 80), 12.0) + rng.normal(0, 1.0, size=(60, 80))
    nearby = background.copy()
    for center in [(20.0, 20.0), (25.5, 21.0), (29.0, 26.5), (58.0, 30.0), (64.0, 30.5)]:  # windows overlap
        draw_blob(nearby, center, sigma=1.2)
    corners = background.copy()
    for center in [(0.0, 0.0), (79.4, 0.3), (0.2, 59.0), (79.0, 59.0), (40.0, 0.0), (0.5, 30.0)]:
        draw_blob(corners, center, sigma=2.0)
    diagonal = np.full((30, 30), 10.0)
    diagonal[[5, 6, 7, 8], [5, 6, 7, 8]] = 200.0  # 8-connected: one blob, not four
    diagonal[[5, 6], [20, 20]] = 180.0
    diagonal[[7, 8], [21, 21]] = 190.0  # touches the one above at a corner only
    images = [nearby, corners, diagonal, background, np.zeros((40, 50)), np.full((40, 50), 7.0),
              rng.integers(0, 2, size=(50, 70)) * 200.0, np.pad(np.full((1, 9), 200.0), 2)]
    for image in images:
        for config in [DetectConfig(), DetectConfig(min_area=1, min_circularity=0.0), DetectConfig(margin=0)]:
            assert_same_blobs(np.clip(image, 0, 255).astype(np.uint8), config)
            assert_same_blobs(image.astype(np.float32) * 3.5, config)
    assert len(detect_blobs(np.clip(nearby, 0, 255).astype(np.uint8))) == 5
    assert len(detect_blobs(np.zeros((40, 50), np.uint8))) == 0


def test_empty_or_one_dimensional_input_is_an_error():
    with pytest.raises(ValueError, match="empty image"):
        detect_blobs(np.zeros((0, 10), np.uint8))
    with pytest.raises(ValueError, match="expected an image"):
        detect_blobs(np.zeros(10, np.uint8))
