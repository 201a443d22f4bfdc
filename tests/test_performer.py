import csv
import time

import numpy as np
import pytest
from factories import random_basis

from livebridge.face.basis import CHOE_KO_MUSCLES, Basis
from livebridge.face.markers import MarkerSet
from livebridge.simulators.performer import EXPRESSIONS, Performer, perform
from livebridge.take.npz import Take


def choe_ko_basis(rng) -> Basis:
    small = random_basis(rng, n_vertices=64, n_muscles=len(CHOE_KO_MUSCLES))
    return Basis(small.neutral, small.triangles, small.elements, CHOE_KO_MUSCLES)


def some_markers(rng, basis, n=12, n_head=4) -> MarkerSet:
    bary = rng.dirichlet(np.ones(3), size=n)
    triangles = rng.choice(len(basis.triangles), size=n, replace=False)
    roles = tuple("head" if i < n_head else "face" for i in range(n))
    regions = tuple("upper" if i % 2 else "lower" for i in range(n))
    return MarkerSet(tuple(f"k{i}" for i in range(n)), triangles, bary, regions, roles)


@pytest.mark.parametrize("script", ["training", "everyday", "mixed"])
def test_trajectories_equal_synthesis_plus_head_motion(rng, script):
    basis = choe_ko_basis(rng)
    markers = some_markers(rng, basis)
    perf = perform(basis, markers, n_frames=400, fps=30.0, seed=3, script=script)
    # synthesise the whole mesh from the ground-truth contractions, interpolate, then move the head
    mesh = basis.synthesize(perf.contractions)  # (n, V, 3)
    corners = mesh[:, basis.triangles[markers.triangles]]  # (n, k, 3, 3)
    model = np.einsum("nkcd,kc->nkd", corners, markers.barycentric)
    neutral = markers.neutral_positions(basis)
    model[:, markers.head_mask] = neutral[markers.head_mask]  # head-rig markers do not move with expression
    world = np.einsum("nij,nkj->nki", perf.head2world[:, :3, :3], model) + perf.head2world[:, None, :3, 3]
    np.testing.assert_allclose(perf.marker_positions, world, atol=1e-9)
    np.testing.assert_allclose(perf.marker_displacements, model - neutral, atol=1e-9)
    # head markers are rigid: zero displacement in the model frame
    assert np.all(perf.marker_displacements[:, markers.head_mask] == 0)


def test_contractions_bounded_and_smooth(rng):
    basis = choe_ko_basis(rng)
    markers = some_markers(rng, basis)
    perf = perform(basis, markers, n_frames=60 * 130, fps=60.0, seed=5, script="mixed")
    x = perf.contractions
    assert x.min() >= 0.0 and x.max() <= 1.0
    # one mixed cycle per muscle: every muscle gets its full training sweep
    np.testing.assert_allclose(x.max(axis=0), 1.0, atol=1e-3)
    # smooth: per-frame change is small (fastest: blinks)
    assert np.abs(np.diff(x, axis=0)).max() < 0.35
    # compound expressions: several muscles active together at some point
    assert ((x > 0.2).sum(axis=1) >= 3).any()
    # starts at rest: neutral face, head at identity
    np.testing.assert_allclose(x[0], 0, atol=1e-12)
    np.testing.assert_allclose(perf.head2world[0], np.eye(4), atol=1e-12)


def test_training_script_sweeps_each_muscle_alone(rng):
    basis = choe_ko_basis(rng)
    markers = some_markers(rng, basis)
    fps = 50.0
    perf = perform(basis, markers, n_frames=int(16 * 2.0 * fps), fps=fps, seed=0, script="training")
    x = perf.contractions
    assert np.all((x > 1e-9).sum(axis=1) <= 1)  # isolated
    np.testing.assert_allclose(x.max(axis=0), 1.0, atol=1e-3)  # full sweeps
    # in order of the basis
    peaks = np.argmax(x, axis=0)
    assert np.all(np.diff(peaks) > 0)


def test_everyday_script_plays_named_expressions(rng):
    basis = choe_ko_basis(rng)
    markers = some_markers(rng, basis)
    perf = perform(basis, markers, n_frames=60 * 120, fps=60.0, seed=2, script="everyday", head_motion=False)
    x = perf.contractions
    jaw = x[:, basis.index("jaw")]
    assert jaw.max() > 0.2
    blink = np.minimum(x[:, basis.index("orbicularis_oculi_L")], x[:, basis.index("orbicularis_oculi_R")])
    assert blink.max() > 0.9
    smile = np.minimum(x[:, basis.index("zygomatic_major_L")], x[:, basis.index("zygomatic_major_R")])
    assert smile.max() > 0.4 or "smile" not in EXPRESSIONS
    np.testing.assert_allclose(perf.head2world, np.broadcast_to(np.eye(4), perf.head2world.shape))


def test_head_motion_is_a_few_cm_and_degrees(rng):
    basis = choe_ko_basis(rng)
    markers = some_markers(rng, basis)
    perf = perform(basis, markers, n_frames=60 * 30, fps=60.0, seed=9)
    rotation = perf.head2world[:, :3, :3]
    np.testing.assert_allclose(rotation @ np.swapaxes(rotation, 1, 2), np.broadcast_to(np.eye(3), rotation.shape),
                               atol=1e-9)
    angles = np.degrees(np.arccos(np.clip((np.trace(rotation, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert 1.0 < angles.max() < 15.0
    centre = basis.neutral.mean(axis=0)
    moved = np.einsum("nij,j->ni", rotation, centre) + perf.head2world[:, :3, 3] - centre
    assert 5.0 < np.linalg.norm(moved, axis=1).max() < 80.0


def test_seeded_determinism(rng):
    basis = choe_ko_basis(rng)
    markers = some_markers(rng, basis)
    a = perform(basis, markers, n_frames=300, seed=4)
    b = perform(basis, markers, n_frames=300, seed=4)
    c = perform(basis, markers, n_frames=300, seed=5)
    np.testing.assert_array_equal(a.marker_positions, b.marker_positions)
    np.testing.assert_array_equal(a.contractions, b.contractions)
    assert not np.allclose(a.marker_positions, c.marker_positions)


def test_live_frames_match_batch_and_pace(rng):
    basis = choe_ko_basis(rng)
    markers = some_markers(rng, basis)
    perf = perform(basis, markers, n_frames=100, fps=60.0, seed=1)
    live = list(Performer(basis, markers, fps=60.0, seed=1, realtime=False).frames(n_frames=100, chunk=7))
    assert [f.seq for f in live] == list(range(100))
    np.testing.assert_allclose(np.stack([f.marker_positions for f in live]), perf.marker_positions, atol=1e-12)
    np.testing.assert_allclose(np.stack([f.contractions for f in live]), perf.contractions, atol=1e-12)
    with pytest.raises(ValueError):
        live[0].contractions[0] = 1.0
    # real-time pacing: 12 frames at 100 fps take at least 0.11 s
    start = time.monotonic()
    frames = Performer(basis, markers, fps=100.0, seed=1, realtime=True).frames()
    for _, frame in zip(range(12), frames):  # noqa: B007
        pass
    assert time.monotonic() - start >= 0.105
    assert frame.seq == 11


def test_take_and_csv_export(tmp_path, rng):
    basis = choe_ko_basis(rng)
    markers = some_markers(rng, basis)
    perf = perform(basis, markers, n_frames=50, fps=30.0, seed=1)
    perf.to_take().save(tmp_path / "take.npz")
    take = Take.load(tmp_path / "take.npz")
    np.testing.assert_allclose(take.positions, perf.marker_positions)
    np.testing.assert_allclose(take.contractions, perf.contractions)
    assert take.muscle_names == basis.names and take.fps == 30.0
    perf.save_csv(tmp_path / "take.csv")
    with (tmp_path / "take.csv").open() as stream:
        rows = list(csv.reader(stream))
    header = rows[0]
    assert len(rows) == 51
    assert header[:3] == ["frame", "t", "x.frontalis_L"]
    column = header.index("k5.y")
    np.testing.assert_allclose([float(r[column]) for r in rows[1:]], perf.marker_positions[:, 5, 1])
    column = header.index("x.jaw")
    np.testing.assert_allclose([float(r[column]) for r in rows[1:]], perf.contractions[:, basis.index("jaw")])
