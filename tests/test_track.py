"""Tracking: labels kept through occlusion gaps and head motion, strays ignored, no swaps."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from livebridge.reconstruct.track import TrackConfig, Tracker


def scene(rng, n_frames=240, fps=60.0):
    """Head markers (rigid) + face markers moving smoothly in the head frame, under head motion."""
    t = np.arange(n_frames) / fps
    head_ref = np.array([[-80, 60, 0], [80, 60, 0], [0, 110, 40], [0, 30, 90.0], [-60, 100, 30]])
    face_rest = np.column_stack([rng.uniform(-60, 60, 40), rng.uniform(-90, 40, 40), rng.uniform(40, 100, 40)])
    # keep face markers >= 9 mm apart
    for i in range(len(face_rest)):
        while np.linalg.norm(np.delete(face_rest, i, 0) - face_rest[i], axis=1).min() < 9:
            face_rest[i] = [rng.uniform(-60, 60), rng.uniform(-90, 40), rng.uniform(40, 100)]
    phase = rng.uniform(0, 2 * np.pi, size=(40, 3))
    amplitude = rng.uniform(0, 3.0, size=(40, 3))
    motion = amplitude * np.sin(2 * np.pi * 1.5 * t[:, None, None] + phase)  # (f, 40, 3) mm
    model = np.concatenate([np.broadcast_to(head_ref, (n_frames, 5, 3)), face_rest + motion], axis=1)
    rotvec = np.column_stack([0.2 * np.sin(2 * np.pi * 0.5 * t), 0.3 * np.sin(2 * np.pi * 0.4 * t), 0.05 * t])
    head2world = np.tile(np.eye(4), (n_frames, 1, 1))
    head2world[:, :3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    head2world[:, :3, 3] = np.column_stack([40 * np.sin(2 * np.pi * 0.3 * t), 10 * t, np.zeros(n_frames)])
    world = np.einsum("fij,fnj->fni", head2world[:, :3, :3], model) + head2world[:, None, :3, 3]
    head_mask = np.arange(45) < 5
    return t, world, model, head2world, head_mask


def test_labels_survive_gaps_head_motion_and_strays(rng):
    t, world, model, head2world, head_mask = scene(rng)
    tracker = Tracker(head_mask, model[0])
    state = tracker.start(t[0], model[0], np.ones(45, bool), head2world[0])
    gap = (np.arange(len(t))[:, None] >= 50) & (np.arange(len(t))[:, None] < 58) & (np.arange(45) % 4 == 1)[None]
    labelled = wrong = 0
    strays_total = 0
    for f in range(1, len(t)):
        visible = ~gap[f] & (rng.random(45) > 0.05)
        strays = rng.uniform(world[f].min(0), world[f].max(0), size=(3, 3))
        points = np.concatenate([world[f][visible] + rng.normal(scale=0.1, size=(visible.sum(), 3)), strays])
        truth = np.concatenate([np.flatnonzero(visible), np.full(3, -1)])
        order = rng.permutation(len(points))
        state, out = tracker.step(state, points[order], t[f])
        labels, truth = out.labels, truth[order]
        wrong += int(((labels >= 0) & (labels != truth)).sum())
        labelled += int(((labels >= 0) & (labels == truth)).sum())
        strays_total += 3
        assert out.n_stray >= int((truth == -1).sum() - (labels[truth == -1] >= 0).sum())
        if f == 58:  # right after the 8-frame gap the gapped markers are picked up again
            back = np.flatnonzero(gap[57] & visible)
            assert np.isin(back, labels).mean() > 0.9
        assert np.abs(out.head2world - head2world[f]).max() < 0.5
        assert np.nanmax(np.abs(out.positions_model - model[f])) < 1.0
    assert wrong == 0
    expected = sum(int((~gap[f]).sum()) for f in range(1, len(t))) * 0.95
    assert labelled > 0.98 * expected


def test_swap_is_refused_when_two_markers_meet(rng):
    """Two markers pass within 1 mm of each other: labels may drop for a frame but never cross."""
    n_frames = 120
    t = np.arange(n_frames) / 60.0
    head_ref = np.array([[-80, 60, 0], [80, 60, 0], [0, 110, 40], [0, 30, 90.0]])
    x = np.linspace(-20, 20, n_frames)
    a = np.column_stack([x, np.full(n_frames, 0.5), np.full(n_frames, 60.0)])  # moving +x
    b = np.column_stack([-x, np.full(n_frames, -0.5), np.full(n_frames, 60.0)])  # moving -x
    model = np.concatenate([np.broadcast_to(head_ref, (n_frames, 4, 3)), a[:, None], b[:, None]], axis=1)
    tracker = Tracker(np.arange(6) < 4, model[0], config=TrackConfig())
    state = tracker.start(0.0, model[0], np.ones(6, bool), np.eye(4))
    for f in range(1, n_frames):
        points = model[f] + rng.normal(scale=0.05, size=(6, 3))
        state, out = tracker.step(state, points, t[f])
        for label in (4, 5):
            position = out.positions_world[label]
            if np.isfinite(position).all():
                assert np.linalg.norm(position - model[f, label]) < np.linalg.norm(position - model[f, 9 - label])
    assert np.isfinite(out.positions_world).all()  # both labels are held again after the crossing
