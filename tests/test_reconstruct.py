"""End-to-end marker reconstruction on the simulated rig with ground truth.

4 cameras, 64 face + 5 head markers, 0.2 px centroid noise (per axis), 10% of marker views occluded
at random on top of the markers facing away, spurious highlights, a moving head.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_correspond import shuffled_detections
from test_triangulate import ring_cameras

from livebridge.bench.reconstruct import evaluate, face_and_markers, rig_cameras, simulate
from livebridge.reconstruct.correspond import Correspondence3D, greedy_disjoint
from livebridge.reconstruct.pipeline import Reconstructor
from livebridge.reconstruct.triangulate import Triangulator


@pytest.fixture(scope="module")
def setup(ict):
    basis, markers = face_and_markers()
    assert int(markers.face_mask.sum()) == 64 and int(markers.head_mask.sum()) >= 4
    return basis, markers, rig_cameras(basis)


def test_take_accuracy_labelling_and_no_swaps(setup):
    basis, markers, cameras = setup
    take = simulate(basis, markers, cameras, 400, seed=5)
    reconstructor = Reconstructor(cameras, markers, basis)
    frames = reconstructor.run(take.frames_2d, take.t)
    result = evaluate(frames, take)
    assert result["swaps"] == 0
    assert result["rmse_mm"] <= 0.2
    assert result["labelled_fraction_reconstructible"] >= 0.99
    assert result["stray_per_frame"] > 0  # the spurious highlights were seen and left unlabelled
    # head pose and model-frame displacements follow the truth
    head = np.stack([f.head2world for f in frames])
    assert np.abs(head[:, :3, 3] - take.head2world[:, :3, 3]).max() < 1.0
    assert result["displacement_rmse_mm"] < 0.5
    # the batch output as a take
    recorded = reconstructor.to_take(frames, fps=60.0)
    assert recorded.displacements.shape == (400, len(markers), 3)


def test_step_api_matches_batch_and_frames_are_frozen(setup):
    basis, markers, cameras = setup
    take = simulate(basis, markers, cameras, 30, seed=6)
    reconstructor = Reconstructor(cameras, markers, basis)
    batch = reconstructor.run(take.frames_2d, take.t)
    state = reconstructor.initial_state()
    for points_2d, t, expected in zip(take.frames_2d, take.t, batch):
        state, frame = reconstructor.step(state, points_2d, t)
        np.testing.assert_array_equal(frame.positions, expected.positions)
    assert state.labelled and state.frames == 30
    with pytest.raises(ValueError):
        frame.displacements[0, 0] = 1.0
    assert frame.head2world.shape == (4, 4) and frame.displacements.shape == (len(markers), 3)


@pytest.mark.parametrize("axis", [(0, 1, 0), (1, 0, 0), (0, 0, 1), (1, -1, 0), (-1, 1, 1)])
def test_first_labelling_with_head_turned_20_degrees(setup, axis):
    basis, markers, cameras = setup
    take = simulate(basis, markers, cameras, 60, seed=7, head_turn_deg=20.0, turn_axis=axis)
    reconstructor = Reconstructor(cameras, markers, basis)
    frames = reconstructor.run(take.frames_2d, take.t)
    assert frames[0].labelled_fraction > 0.8
    result = evaluate(frames, take)
    assert result["swaps"] == 0 and result["labelled_fraction_reconstructible"] >= 0.98
    # the alignment undid the turn: neutral-frame displacements are ~0 and head2world carries the turn
    assert np.nanmax(np.abs(frames[0].displacements)) < 1e-9
    assert np.abs(frames[0].head2world - take.head2world[0]).max() < 0.5


def _false_labels(points, labels, truth):
    """Labelled points nearer another marker's truth than their own, or more than 2 mm from it."""
    labelled = labels >= 0
    distance = np.linalg.norm(points[labelled, None] - truth[None], axis=-1)
    own = distance[np.arange(labelled.sum()), labels[labelled]]
    return int(((distance.argmin(axis=1) != labels[labelled]) | (own > 2.0)).sum())


@pytest.mark.parametrize("seed, axis, spurious", [(7, (0, 1, 0), 3.0), (7, (1, -1, 0), 3.0), (1, (1, 0, 0), 15.0),
                                                  (5, (-1, 1, 1), 15.0), (2, (0, 0, 1), 15.0)])
def test_first_labelling_guided_labels_two_view_markers_and_no_false_ones(setup, seed, axis, spurious):
    """The model-guided second correspondence recovers markers seen by two cameras only, and no label is wrong."""
    from livebridge.reconstruct.label import first_labelling, guided_first_labelling

    basis, markers, cameras = setup
    take = simulate(basis, markers, cameras, 1, seed=seed, head_turn_deg=20.0, turn_axis=axis, spurious=spurious)
    reconstructor = Reconstructor(cameras, markers, basis)
    points_2d, truth = take.frames_2d[0], take.points_3d[0]
    reconstructible = int((np.isfinite(take.labelled_2d[0, ..., 0]).sum(axis=0) >= 2).sum())
    blind_points = reconstructor.points_3d(points_2d).points_3d
    blind = first_labelling(blind_points, reconstructor.model_points)
    calls = []

    def find_points(predicted):
        calls.append(predicted)
        return reconstructor.points_3d(points_2d, predicted).points_3d

    points, labelling = guided_first_labelling(find_points, reconstructor.model_points)
    assert len(calls) == 2 and calls[0] is None and calls[1].shape == (len(markers), 3)
    assert _false_labels(points, labelling.labels, truth) == 0
    assert labelling.n_matched >= reconstructible - 1  # at most one lost to a detection shared with a neighbour
    assert labelling.n_matched >= blind.n_matched - _false_labels(blind_points, blind.labels, truth)
    again_points, again = guided_first_labelling(find_points, reconstructor.model_points)  # deterministic
    np.testing.assert_array_equal(again.labels, labelling.labels)
    np.testing.assert_array_equal(again_points, points)


def test_rendered_images_end_to_end(setup):
    """Detection on the rig's rendered images feeding the reconstructor."""
    from livebridge.simulators.rig import RigConfig, SimRig

    basis, markers, _ = setup
    rig = SimRig(basis, markers, config=RigConfig(spread_deg=120.0, spurious_rate=2.0), seed=2)
    reconstructor = Reconstructor(rig.cameras, markers, basis)
    state = reconstructor.initial_state()
    errors, labelled, reconstructible = [], 0, 0
    for frameset in rig.framesets(12):
        points_2d = reconstructor.detect([frame.image for frame in frameset.frames])
        state, frame = reconstructor.step(state, points_2d, frameset.truth.t)
        truth = frameset.truth.points_3d
        seen = np.isfinite(frame.positions_world).all(axis=1)
        nearest = np.argmin(np.linalg.norm(frame.positions_world[:, None] - truth[None], axis=-1), axis=1)
        assert (nearest[seen] == np.flatnonzero(seen)).all()  # no wrong labels
        errors.append(np.linalg.norm(frame.positions_world[seen] - truth[seen], axis=1))
        possible = frameset.truth.visible.sum(axis=0) >= 2
        labelled += int((seen & possible).sum())
        reconstructible += int(possible.sum())
    errors = np.concatenate(errors)
    assert np.sqrt(np.mean(errors**2)) <= 0.2
    assert labelled / reconstructible >= 0.97


@pytest.mark.slow
def test_soak_10000_frames_no_swaps(setup):
    basis, markers, cameras = setup
    take = simulate(basis, markers, cameras, 10_000, seed=11)
    frames = Reconstructor(cameras, markers, basis).run(take.frames_2d, take.t)
    result = evaluate(frames, take)
    assert result["swaps"] == 0
    assert result["rmse_mm"] <= 0.2
    assert result["labelled_fraction_reconstructible"] >= 0.99


def test_greedy_disjoint_equals_the_sequential_walk(rng):
    def walk(group, order):
        taken, accepted = [set() for _ in group], []
        for k in order:
            views = [(c, int(d)) for c, d in enumerate(group[:, k]) if d >= 0]
            if not any(d in taken[c] for c, d in views):
                for c, d in views:
                    taken[c].add(d)
                accepted.append(k)
        return accepted

    for _ in range(300):
        n_cams, n_groups, n_detections = rng.integers(1, 5), rng.integers(0, 50), rng.integers(1, 15)
        group = np.where(rng.random((n_cams, n_groups)) < 0.3, -1, rng.integers(0, n_detections, (n_cams, n_groups)))
        order = rng.permutation(n_groups)
        assert greedy_disjoint(group, order).tolist() == walk(group, order)


def test_predictions_find_the_same_points(rng):
    """Tracked markers found around their predictions: the same 3D points as the general rounds, no ghosts."""
    cameras = ring_cameras()
    correspond = Correspondence3D(Triangulator(cameras), tolerance_px=1.5)
    grid = np.stack(np.meshgrid(np.arange(-60, 61, 15.0), np.arange(-75, 76, 15.0)), -1).reshape(-1, 2)
    points = np.column_stack([grid + rng.normal(scale=2.0, size=grid.shape), 30 * np.cos(grid[:, 0] / 80)])
    for _ in range(5):
        detections, owners, seen = shuffled_detections(cameras, points, rng)
        plain = correspond(detections)
        predicted = points + rng.normal(scale=0.7, size=points.shape)  # a tracker's prediction error
        guided = correspond(detections, predicted, prior_mm=3.0)
        for result in (plain, guided):
            for k in range(len(result.points_3d)):
                who = {int(owners[c][d]) for c, d in enumerate(result.detections[:, k]) if d >= 0}
                assert len(who) == 1  # never a mix of markers (or of a marker and a stray)
        def by_marker(result, owners=owners):
            out = {}
            for k in range(len(result.points_3d)):
                (who,) = {int(owners[c][d]) for c, d in enumerate(result.detections[:, k]) if d >= 0}
                if who >= 0:
                    out[who] = (result.points_3d[k], tuple(result.detections[:, k]))
            return out
        a, b = by_marker(plain), by_marker(guided)
        assert len(b) >= len(a) - 1
        for marker, (point, views) in b.items():
            assert np.linalg.norm(point - points[marker]) < 1.0
            if marker in a and a[marker][1] == views:  # same views: the same point
                assert np.abs(a[marker][0] - point).max() < 1e-9
