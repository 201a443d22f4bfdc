"""Blob detection: sub-pixel centroids, size and circularity filters, undistortion, rig images."""

from __future__ import annotations

import numpy as np
import pytest
from test_triangulate import ring_cameras

from livebridge.reconstruct.detect import DetectConfig, detect_blobs, detect_markers


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


def reference_blobs(image: np.ndarray, config: DetectConfig) -> np.ndarray:
    """Straightforward per-blob form of the detector (OpenCV statistics, one blob at a time), for comparison."""
    import cv2

    from livebridge.reconstruct.detect import _threshold

    gray = np.asarray(image).astype(np.float32)
    level = _threshold(np.asarray(image), config)
    mask = (gray > level).astype(np.uint8)
    _, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    height, width = gray.shape
    m = config.margin
    out = []
    for label in range(1, len(stats)):
        x0, y0, w, h, area = stats[label]
        if not config.min_area <= area <= config.max_area:
            continue
        xa, ya, xb, yb = max(x0 - m, 0), max(y0 - m, 0), min(x0 + w + m, width), min(y0 + h + m, height)
        patch, own = gray[ya:yb, xa:xb].astype(np.float64), labels[ya:yb, xa:xb]
        border = np.concatenate([patch[0], patch[-1], patch[1:-1, 0], patch[1:-1, -1]])
        weight = np.clip(patch - np.median(border), 0.0, None) * ((own == 0) | (own == label))
        total = weight.sum()
        if total <= 0:
            continue
        ys, xs = np.mgrid[ya:yb, xa:xb]
        cx, cy = (weight * xs).sum() / total, (weight * ys).sum() / total
        cxx, cyy = (weight * (xs - cx) ** 2).sum() / total, (weight * (ys - cy) ** 2).sum() / total
        cxy = (weight * (xs - cx) * (ys - cy)).sum() / total
        spread = np.sqrt(((cxx - cyy) / 2) ** 2 + cxy**2)
        major, minor = (cxx + cyy) / 2 + spread, (cxx + cyy) / 2 - spread
        if major > 0 and np.sqrt(max(minor, 0.0) / major) >= config.min_circularity:
            out.append((cx, cy))
    return np.array(out).reshape(-1, 2)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_vectorised_centroids_equal_the_per_blob_form(rng, dtype):
    """Blobs of many sizes and shapes, touching the image edges and each other: same blobs, same centroids."""
    for _ in range(40):
        image = rng.normal(20.0, 3.0, size=(70, 90))
        for _ in range(rng.integers(0, 8)):
            sigma = rng.uniform(0.5, 6.0)
            draw_blob(image, rng.uniform(-3, [93, 73]), sigma=sigma, peak=rng.uniform(50, 230),
                      elongation=rng.uniform(0.3, 3.0))
        image = np.clip(image, 0, 255).astype(dtype)
        config = DetectConfig(max_area=rng.choice([5000, 60]))
        found, expected = detect_blobs(image, config), reference_blobs(image, config)
        assert found.shape == expected.shape
        found, expected = found[np.lexsort(found.T)], expected[np.lexsort(expected.T)]  # label order may differ
        if len(found):
            assert np.abs(found - expected).max() < 1e-4
