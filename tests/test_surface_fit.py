"""The neutral mesh's surface fitted to noisy scan points (livebridge/retarget/surface_fit.py)."""

from __future__ import annotations

import numpy as np

from livebridge.retarget.grid import resample, square_axes
from livebridge.retarget.surface_fit import fitted_heights


def _wavy(xy: np.ndarray) -> np.ndarray:
    """A curved surface with features a few mm wide (a dome with ripples)."""
    return np.sqrt(100.0 ** 2 - (xy ** 2).sum(axis=1)) - 100.0 + 1.5 * np.sin(xy[:, 0] / 4.0) * np.cos(xy[:, 1] / 6.0)


def _scan(rng, xy: np.ndarray, heights: np.ndarray, noise: float = 0.2) -> np.ndarray:
    """Points with isotropic Gaussian noise, as a scanner gives them."""
    return np.column_stack([xy, heights]) + rng.normal(0.0, noise, (len(xy), 3))


def test_fitted_surface_averages_the_scanner_noise_and_keeps_the_curvature(rng):
    xy = rng.uniform(-45, 45, (20_000, 2))  # ~2.5 points per mm^2, the bench's 60k-point scans' density
    points = _scan(rng, xy, _wavy(xy))
    x, y = square_axes(40.0, (80, 80))
    grid = resample(points, x, y)
    fitted = fitted_heights(points, grid)
    xx, yy = np.meshgrid(x, y)
    truth = _wavy(np.column_stack([xx.ravel(), yy.ravel()])).reshape(xx.shape)
    valid = grid.valid
    assert np.array_equal(np.isfinite(fitted), valid)  # the mask is the grid's
    interpolated = np.abs(grid.heights - truth)[valid]
    error = np.abs(fitted - truth)[valid]
    assert np.median(error) < 0.5 * np.median(interpolated), (np.median(error), np.median(interpolated))
    assert np.sqrt(np.mean(error ** 2)) < 0.06  # noise 0.2 mm per point; the ripples' curvature not flattened


def test_fitted_surface_leaves_a_step_and_a_hole_edge_as_the_points_give_them(rng):
    """Where a quadratic does not describe the surface (a 4 mm step, as at a lip's edge; deeper ones are two
    surfaces, see below), the vertices keep the interpolated heights instead of a fit that cuts the corner; a
    hole stays a hole."""
    xy = rng.uniform(-30, 30, (12_000, 2))
    xy = xy[np.hypot(xy[:, 0] + 12.0, xy[:, 1]) > 6.0]
    step = np.where(xy[:, 0] > 5.0, 4.0, 0.0)
    points = _scan(rng, xy, step)
    x, y = square_axes(25.0, (60, 60))
    grid = resample(points, x, y)
    fitted = fitted_heights(points, grid)
    xx, _ = np.meshgrid(x, y)
    truth = np.where(xx > 5.0, 4.0, 0.0)
    near_step = grid.valid & (np.abs(xx - 5.0) < 2.0)
    away = grid.valid & (np.abs(xx - 5.0) > 6.0)
    assert np.max(np.abs(fitted - grid.heights)[near_step]) <= 0.85  # at most twice the allowed noise
    assert np.median(np.abs(fitted - truth)[away]) < 0.5 * np.median(np.abs(grid.heights - truth)[away])
    assert np.array_equal(np.isfinite(fitted), grid.valid)


def test_too_few_points_keep_the_interpolated_heights(rng):
    xy = rng.uniform(-10, 10, (60, 2))
    points = _scan(rng, xy, np.zeros(len(xy)))
    x, y = square_axes(8.0, (10, 10))
    grid = resample(points, x, y)
    fitted = fitted_heights(points, grid, spacing=0.05)  # a reach of 0.5 mm: no vertex has 12 points in it
    assert np.array_equal(fitted[grid.valid], grid.heights[grid.valid])


def test_a_vertex_interpolated_between_two_surfaces_takes_the_fit(rng):
    """Where the scanner sees past the skin at some of its points (a nostril's rim, the lip 25 mm behind it)
    the interpolation blends the two depths and leaves the vertex in the air; the fit, robust to the deeper
    points, puts it back on the skin."""
    xy = rng.uniform(-30, 30, (12_000, 2))
    past = (np.hypot(xy[:, 0], xy[:, 1]) < 3.0) & (rng.random(len(xy)) < 0.3)
    points = _scan(rng, xy, np.where(past, -25.0, 0.0))
    x, y = square_axes(25.0, (60, 60))
    grid = resample(points, x, y)
    fitted = fitted_heights(points, grid)
    xx, yy = np.meshgrid(x, y)
    over = grid.valid & (np.hypot(xx, yy) < 2.5)
    in_the_air = over & (grid.heights < -3.0) & (grid.heights > -22.0)
    assert in_the_air.sum() >= 3  # what the interpolation makes of it
    assert np.abs(fitted[in_the_air]).max() < 0.5
