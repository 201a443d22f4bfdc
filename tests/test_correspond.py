"""Multi-view correspondence: every point seen by >= 2 cameras found, none invented, strays left out."""

from __future__ import annotations

import numpy as np
from test_triangulate import ring_cameras

from livebridge.reconstruct.correspond import Correspondence3D, fundamental
from livebridge.reconstruct.triangulate import Triangulator


def shuffled_detections(cameras, points, rng, noise_px=0.2, hide=0.1, strays=3):
    """Per-camera undistorted detections (shuffled, with strays) and each detection's true point (-1 stray)."""
    pixels = cameras.project(points) + rng.normal(scale=noise_px, size=(len(cameras), len(points), 2))
    seen = rng.random(pixels.shape[:2]) >= hide
    detections, owners = [], []
    for c, camera in enumerate(cameras.cameras):
        stray = rng.uniform([300, 150], [980, 650], size=(strays, 2))
        both = np.concatenate([pixels[c][seen[c]], stray])
        owner = np.concatenate([np.flatnonzero(seen[c]), np.full(strays, -1)])
        order = rng.permutation(len(both))
        detections.append(camera.undistort_points(both[order]))
        owners.append(owner[order])
    return detections, owners, seen


def test_fundamental_matrix_satisfies_epipolar_constraint(rng):
    cameras = ring_cameras()
    triangulator = Triangulator(cameras)
    points = rng.normal(scale=50.0, size=(20, 3))
    undistorted = triangulator.reproject(points)
    f = fundamental(triangulator.projections[0], triangulator.projections[2])
    xa = np.column_stack([undistorted[0], np.ones(20)])
    xb = np.column_stack([undistorted[2], np.ones(20)])
    lines = xa @ f.T
    distance = np.abs((lines * xb).sum(1)) / np.hypot(lines[:, 0], lines[:, 1])
    assert distance.max() < 1e-6


def test_groups_across_all_cameras(rng):
    cameras = ring_cameras()
    correspond = Correspondence3D(Triangulator(cameras), tolerance_px=1.5)
    # markers on a face-sized patch, ~15 mm apart: plenty of epipolar ambiguity between pairs
    grid = np.stack(np.meshgrid(np.arange(-60, 61, 15.0), np.arange(-75, 76, 15.0)), -1).reshape(-1, 2)
    points = np.column_stack([grid + rng.normal(scale=2.0, size=grid.shape), 30 * np.cos(grid[:, 0] / 80)])
    total_found = total_possible = 0
    for _ in range(5):
        detections, owners, seen = shuffled_detections(cameras, points, rng)
        result = correspond(detections)
        # each group's detections come from one true point, and the group sits on that point
        for k in range(len(result.points_3d)):
            who = {int(owners[c][d]) for c, d in enumerate(result.detections[:, k]) if d >= 0}
            if who == {-1}:
                continue
            assert len(who) == 1 and -1 not in who
            (true,) = who
            assert np.linalg.norm(result.points_3d[k] - points[true]) < 1.0
        assert (result.n_views >= 2).all()
        possible = seen.sum(axis=0) >= 2
        found = np.zeros(len(points), dtype=bool)
        for k in range(len(result.points_3d)):
            d = np.linalg.norm(points - result.points_3d[k], axis=1)
            if d.min() < 1.0:
                found[np.argmin(d)] = True
        assert not (found & ~possible).any()  # nothing invented from fewer than two views
        total_found += found.sum()
        total_possible += possible.sum()
        # grouped across all cameras: points seen by all four use all four views
        all_four = np.flatnonzero(seen.all(axis=0))
        views = {int(np.argmin(np.linalg.norm(points - p, axis=1))): n for p, n in zip(result.points_3d,
                                                                                     result.n_views)}
        assert np.mean([views.get(i, 0) == 4 for i in all_four]) > 0.95
    assert total_found / total_possible > 0.97


def test_noise_free_single_point_and_empty_cameras(rng):
    cameras = ring_cameras()
    correspond = Correspondence3D(Triangulator(cameras))
    point = np.array([[5.0, -3.0, 20.0]])
    detections = [cameras.cameras[c].undistort_points(cameras.cameras[c].project(point)) for c in range(4)]
    detections[3] = np.zeros((0, 2))
    result = correspond(detections)
    assert len(result.points_3d) == 1 and result.n_views[0] == 3
    assert np.abs(result.points_3d[0] - point[0]).max() < 1e-6
    assert len(correspond([np.zeros((0, 2))] * 4).points_3d) == 0
    only_one = [detections[0]] + [np.zeros((0, 2))] * 3
    assert len(correspond(only_one).points_3d) == 0


def test_compiled_kernels_match_their_library_references(rng):
    """The compiled gating, nearest-neighbour and greedy kernels give what numpy, cKDTree and a plain walk give."""
    from scipy.spatial import cKDTree

    from livebridge.reconstruct.correspond import epipolar_pairs, greedy_disjoint, nearest_distance, nearest_within

    cameras = ring_cameras()
    triangulator = Triangulator(cameras)
    undistorted = triangulator.reproject(rng.normal(scale=50.0, size=(40, 3)))
    xa, xb = undistorted[0] + rng.normal(scale=1.0, size=(40, 2)), undistorted[1][rng.permutation(40)]
    f = fundamental(triangulator.projections[0], triangulator.projections[1])
    ha, hb = np.column_stack([xa, np.ones(40)]), np.column_stack([xb, np.ones(40)])
    algebraic = np.abs(ha @ f.T @ hb.T)
    lines_b, lines_a = ha @ f.T, hb @ f
    distance = np.maximum(algebraic / np.hypot(lines_b[:, 0], lines_b[:, 1])[:, None],
                          algebraic / np.hypot(lines_a[:, 0], lines_a[:, 1])[None, :])
    ia, ib = epipolar_pairs(xa, xb, f, 1.5)
    assert 20 <= len(ia) and np.array_equal(np.stack([ia, ib]), np.stack(np.nonzero(distance < 1.5)))

    points, queries = rng.uniform(0, 100, (60, 2)), rng.uniform(0, 100, (200, 2))
    queries[:5] = np.nan
    reference_distance, reference = cKDTree(points).query(np.nan_to_num(queries, nan=1e12), distance_upper_bound=4.0)
    nearest = nearest_within(queries, points, 4.0)
    assert 50 < (nearest >= 0).sum() < 195
    assert np.array_equal(nearest, np.where(np.isfinite(reference_distance), reference, -1))
    points_3d = rng.normal(size=(30, 3))
    known = points_3d[::3] + 0.1
    assert np.allclose(nearest_distance(points_3d, known), cKDTree(known).query(points_3d)[0])

    group = rng.integers(-1, 6, size=(4, 80))
    order = rng.permutation(80)
    accepted, used = [], set()
    for g in order:  # the definition: walk the order, accept what shares no detection with an accepted group
        views = {(c, int(group[c, g])) for c in range(4) if group[c, g] >= 0}
        if not views & used:
            accepted.append(g)
            used |= views
    assert len(accepted) > 3 and greedy_disjoint(group, order).tolist() == accepted
