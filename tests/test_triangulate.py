"""Batched DLT triangulation: agreement with aniposelib and per-point SVD, outlier views, refinement."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from livebridge.calibration.cameras import Camera, CameraGroup
from livebridge.reconstruct.triangulate import Triangulator


def ring_cameras(n: int = 4, distance: float = 800.0, spread_deg: float = 90.0, k1: float = -0.05) -> CameraGroup:
    """Cameras on an arc at +z looking at the origin (world2cam via a look-at)."""
    cameras = []
    for k, azimuth in enumerate(np.deg2rad(np.linspace(-spread_deg / 2, spread_deg / 2, n))):
        elevation = np.deg2rad(10.0 if k % 2 else -8.0)
        centre = distance * np.array([np.sin(azimuth) * np.cos(elevation), np.sin(elevation),
                                      np.cos(azimuth) * np.cos(elevation)])
        z = -centre / np.linalg.norm(centre)
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        rotation = np.stack([x, y, z])
        matrix = np.array([[1400.0, 0, 639.5], [0, 1400.0, 399.5], [0, 0, 1]])
        cameras.append(Camera(f"c{k}", (1280, 800), matrix, np.array([k1, 0, 0, 0, 0]),
                              cv2.Rodrigues(rotation)[0].ravel(), -rotation @ centre))
    return CameraGroup(cameras)


def observe(cameras, points, rng, noise_px=0.0, hide=0.0):
    pixels = cameras.project(points) + rng.normal(scale=noise_px, size=(len(cameras), len(points), 2))
    pixels[rng.random(pixels.shape[:2]) < hide] = np.nan
    return cameras.undistort_points(pixels)


def svd_reference(triangulator, points_2d):
    """One SVD per point, the textbook DLT in normalised coordinates."""
    normalized = triangulator.normalize(points_2d)
    out = np.full((points_2d.shape[1], 3), np.nan)
    for i in range(points_2d.shape[1]):
        rows = []
        for c in range(len(triangulator)):
            if np.isfinite(normalized[c, i]).all():
                p = triangulator.extrinsics[c]
                rows += [normalized[c, i, 0] * p[2] - p[0], normalized[c, i, 1] * p[2] - p[1]]
        if len(rows) >= 4:
            v = np.linalg.svd(np.array(rows))[2][-1]
            out[i] = v[:3] / v[3]
    return out


def test_dlt_recovers_exact_points_and_matches_per_point_svd(rng):
    cameras = ring_cameras()
    triangulator = Triangulator(cameras)
    points = rng.normal(scale=60.0, size=(200, 3))
    exact = triangulator.dlt(observe(cameras, points, rng))
    assert np.abs(exact - points).max() < 1e-6
    noisy = observe(cameras, points, rng, noise_px=0.5, hide=0.3)
    ours = triangulator.dlt(noisy)
    reference = svd_reference(triangulator, noisy)
    assert np.array_equal(np.isnan(ours), np.isnan(reference))
    assert np.nanmax(np.abs(ours - reference)) < 1e-6


def test_fewer_than_two_views_give_nan(rng):
    cameras = ring_cameras()
    triangulator = Triangulator(cameras)
    points_2d = observe(cameras, rng.normal(scale=50.0, size=(10, 3)), rng)
    points_2d[1:, 3] = np.nan  # point 3 seen only by camera 0
    points_2d[:, 7] = np.nan  # point 7 seen by nobody
    result = triangulator.dlt(points_2d)
    assert np.isnan(result[[3, 7]]).all()
    assert np.isfinite(np.delete(result, [3, 7], axis=0)).all()


def test_matches_aniposelib_within_a_nanometre(rng):
    anipose = pytest.importorskip("aniposelib.cameras")
    pytest.importorskip("jax")
    cameras = ring_cameras()
    group = anipose.CameraGroup([anipose.Camera(matrix=c.matrix, dist=c.distortions, size=c.size, rvec=c.rotation,
                                                tvec=c.translation) for c in cameras.cameras])
    points = rng.normal(scale=60.0, size=(100, 3))
    pixels = cameras.project(points) + rng.normal(scale=0.3, size=(len(cameras), 100, 2))
    pixels[rng.random(pixels.shape[:2]) < 0.2] = np.nan
    theirs = group.triangulate(pixels)  # aniposelib undistorts itself
    ours = Triangulator(cameras).dlt(cameras.undistort_points(pixels))
    both = np.isfinite(theirs).all(1) & np.isfinite(ours).all(1)
    assert both.sum() > 80
    assert np.abs(ours[both] - theirs[both]).max() < 1e-6


def test_outlier_view_is_rejected(rng):
    cameras = ring_cameras()
    triangulator = Triangulator(cameras)
    points = rng.normal(scale=50.0, size=(30, 3))
    points_2d = observe(cameras, points, rng, noise_px=0.1)
    points_2d[2, :10] += 25.0  # camera 2 sees something else for the first 10 points
    result = triangulator.triangulate(points_2d, max_residual_px=1.5)
    assert not result.used[2, :10].any() and result.used[:, 10:].all()
    assert np.linalg.norm(result.points_3d - points, axis=1).max() < 0.5
    assert (result.max_residual_px <= 1.5).all()
    # with only two views and one of them wrong, the point is dropped, not invented
    two = observe(cameras, points[:1], rng)
    two[2:] = np.nan
    two[1] += 30.0
    assert np.isnan(triangulator.triangulate(two, max_residual_px=1.5).points_3d).all()


def test_refinement_does_not_increase_pixel_error(rng):
    cameras = ring_cameras()
    triangulator = Triangulator(cameras)
    points_2d = observe(cameras, rng.normal(scale=60.0, size=(100, 3)), rng, noise_px=1.0)
    linear = triangulator.dlt(points_2d)
    refined = triangulator.refine(linear, points_2d, iterations=3)
    before = np.nansum(triangulator.residuals(linear, points_2d) ** 2, axis=0)
    after = np.nansum(triangulator.residuals(refined, points_2d) ** 2, axis=0)
    assert (after <= before + 1e-9).all() and after.sum() < before.sum()


def test_skewed_intrinsics(rng):
    cameras = ring_cameras()
    skewed = CameraGroup([Camera(c.name, c.size, c.matrix + np.array([[0, 3.0, 0], [0, 0, 0], [0, 0, 0]]),
                                 c.distortions, c.rotation, c.translation) for c in cameras.cameras])
    triangulator = Triangulator(skewed)
    noisy = observe(skewed, rng.normal(scale=60.0, size=(50, 3)), rng, noise_px=0.5, hide=0.2)
    assert np.nanmax(np.abs(triangulator.dlt(noisy) - svd_reference(triangulator, noisy))) < 1e-6
