"""Similarity fits, closest points on the mesh, coordinate alignment, first labelling with the head turned."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from livebridge.geometry.transforms import apply, transform_scale, umeyama
from livebridge.reconstruct.align import MeshSurface, align_to_model, closest_barycentric
from livebridge.reconstruct.label import first_labelling
from livebridge.reconstruct.stabilize import head_pose


def similarity(rng, scale=1.0, degrees=20.0, shift=30.0):
    transform = np.eye(4)
    axis = rng.normal(size=3)
    transform[:3, :3] = scale * Rotation.from_rotvec(np.deg2rad(degrees) * axis / np.linalg.norm(axis)).as_matrix()
    transform[:3, 3] = rng.normal(scale=shift, size=3)
    return transform


def test_umeyama_recovers_similarity_and_rigid(rng):
    src = rng.normal(scale=50, size=(30, 3))
    truth = similarity(rng, scale=1.07)
    dst = apply(truth, src)
    dst[3] = np.nan  # ignored
    assert np.abs(umeyama(src, dst) - truth).max() < 1e-9
    rigid = similarity(rng)
    assert np.abs(umeyama(src, apply(rigid, src), with_scale=False) - rigid).max() < 1e-9
    assert np.isnan(umeyama(src[:2], dst[:2])).all()


def test_head_pose_with_model_scale(rng):
    reference = rng.normal(scale=60, size=(5, 3))
    head2world = similarity(rng, scale=1.0)
    head2world[:3, :3] *= 0.9  # world mm per model mm
    world = apply(head2world, reference)
    world[1] = np.nan
    estimate = head_pose(reference, world, model_scale=0.9)
    assert np.abs(estimate - head2world).max() < 1e-9
    assert abs(transform_scale(estimate) - 0.9) < 1e-12


def test_closest_barycentric_against_dense_sampling(rng):
    corners = rng.normal(size=(300, 3, 3))
    points = rng.normal(scale=2, size=(300, 3))
    bary = closest_barycentric(points, corners)
    closest = np.einsum("nc,ncd->nd", bary, corners)
    u, v = np.meshgrid(np.linspace(0, 1, 121), np.linspace(0, 1, 121))
    keep = u + v <= 1
    samples = ((1 - u - v)[keep][None, :, None] * corners[:, None, 0] + u[keep][None, :, None] * corners[:, None, 1]
               + v[keep][None, :, None] * corners[:, None, 2])
    dense = np.linalg.norm(samples - points[:, None], axis=-1).min(axis=1)
    assert (np.linalg.norm(closest - points, axis=1) <= dense + 1e-9).all()
    assert (bary >= 0).all() and np.allclose(bary.sum(1), 1)


@pytest.fixture(scope="module")
def face(ict):
    from livebridge.bench.reconstruct import face_and_markers

    return face_and_markers()


def test_alignment_recovers_capture_to_model_and_surface_markers(face, rng):
    basis, markers = face
    model = markers.neutral_positions(basis)
    capture2model = similarity(rng, scale=1.05, degrees=15)
    captured = apply(np.linalg.inv(capture2model), model)
    captured[markers.face_mask] += rng.normal(scale=0.05, size=(int(markers.face_mask.sum()), 3))
    captured[7] = np.nan
    alignment = align_to_model(captured, markers, basis)
    assert np.abs(alignment.capture2model[:3, :3] - capture2model[:3, :3]).max() < 2e-3
    moved = apply(alignment.capture2model, captured)
    face_rows = markers.face_mask & np.isfinite(captured).all(1)
    placed = alignment.markers.neutral_positions(basis)
    assert np.linalg.norm(placed[face_rows] - moved[face_rows], axis=1).max() < 0.3
    assert alignment.rms_mm < 0.1
    surface = MeshSurface(basis.neutral, basis.triangles)
    _, _, on_surface = surface.closest(placed[face_rows])
    assert np.abs(on_surface - placed[face_rows]).max() < 1e-6


@pytest.mark.parametrize("axis", [(0, 1, 0), (1, 0, 0), (0.3, 1, 0.2), (0, 0, 1)])
def test_first_labelling_with_head_turned_20_degrees(face, rng, axis):
    basis, markers = face
    model = markers.neutral_positions(basis)
    turn = np.eye(4)
    axis = np.asarray(axis, dtype=float)
    turn[:3, :3] = Rotation.from_rotvec(np.deg2rad(20) * axis / np.linalg.norm(axis)).as_matrix()
    turn[:3, 3] = [12.0, -20.0, 35.0]
    captured = apply(turn, model) + rng.normal(scale=0.2, size=model.shape)
    keep = rng.random(len(model)) > 0.08  # some markers unseen
    strays = rng.uniform(captured.min(0), captured.max(0), size=(5, 3))
    points = np.concatenate([captured[keep], strays])
    truth = np.concatenate([np.flatnonzero(keep), np.full(5, -1)])
    order = rng.permutation(len(points))
    labelling = first_labelling(points[order], model)
    labels, truth = labelling.labels, truth[order]
    labelled = labels >= 0
    assert (labels[labelled] == truth[labelled]).all()  # no wrong label
    assert labelled.sum() >= 0.97 * keep.sum()
    assert np.abs(labelling.capture2model[:3, :3] - np.linalg.inv(turn)[:3, :3]).max() < 0.01
