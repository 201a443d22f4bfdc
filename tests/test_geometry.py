"""The geometry module: transforms, rotation vectors, look-at, and the one camera-visibility model."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from geometry_reference import behind_surface_numpy
from scipy.spatial.transform import Rotation

from livebridge.geometry.transforms import (
    apply,
    invert,
    look_at,
    rotation_matrices,
    rotation_matrix,
    rotation_vector,
    transform_scale,
)
from livebridge.geometry.visibility import behind_surface, depth_cell_mm


def _random_rotvecs(rng, n):
    """Rotation vectors over the whole range of angles, with many near 0 and near a half turn."""
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(0, np.pi, n // 4), np.pi - 10 ** rng.uniform(-9, -1, n // 4),
                             10 ** rng.uniform(-10, -2, n // 4), np.full(n - 3 * (n // 4), np.pi)])
    return axes * angles[:, None]


def test_rotation_matrix_is_rodrigues_formula(rng):
    rotvecs = _random_rotvecs(rng, 400)
    expected = Rotation.from_rotvec(rotvecs).as_matrix()
    assert np.abs(rotation_matrices(rotvecs) - expected).max() < 1e-14
    assert np.abs(rotation_matrix(rotvecs[0]) - cv2.Rodrigues(rotvecs[0])[0]).max() < 1e-14
    rx, ry, rz = tiny = np.array([1e-13, -2e-13, 3e-13])  # first order below 1e-12 rad: I + [r]x
    np.testing.assert_array_equal(rotation_matrix(tiny), [[1.0, -rz, ry], [rz, 1.0, -rx], [-ry, rx, 1.0]])


def test_rotation_vector_inverts_rotation_matrix_at_every_angle(rng):
    """To 1e-14 rad everywhere, also near a half turn (where the antisymmetric part vanishes) and near 0."""
    rotvecs = _random_rotvecs(rng, 400)
    for rotvec, matrix in zip(rotvecs, Rotation.from_rotvec(rotvecs).as_matrix()):
        found = rotation_vector(matrix)
        error = np.abs(found - rotvec).max()
        if np.linalg.norm(rotvec) > np.pi - 1e-6:  # a half turn about k is one about -k
            error = min(error, np.abs(found + rotvec).max())
        assert error < 1e-14, (rotvec, found)
        assert np.linalg.norm(found) <= np.pi + 1e-15


def test_apply_invert_and_scale(rng):
    a2b = np.eye(4)
    a2b[:3, :3] = 1.7 * Rotation.random(random_state=3).as_matrix()
    a2b[:3, 3] = rng.normal(size=3) * 100
    points = rng.normal(size=(10, 3)) * 50
    points[3] = np.nan
    moved = apply(a2b, points)
    assert np.isnan(moved[3]).all()
    np.testing.assert_allclose(apply(invert(a2b), moved), points, atol=1e-10)
    assert transform_scale(a2b) == pytest.approx(1.7, abs=1e-12)
    # one transform per set of points: the same as applying each on its own
    poses = np.stack([a2b, invert(a2b), np.eye(4)])
    sets = rng.normal(size=(3, 5, 3))
    np.testing.assert_allclose(apply(poses, sets), np.stack([apply(p, s) for p, s in zip(poses, sets)]), atol=1e-12)


def test_look_at_points_the_optical_axis_at_the_target():
    center, target = np.array([300.0, 120.0, 700.0]), np.array([10.0, -20.0, 30.0])
    world2cam = look_at(center, target)
    np.testing.assert_allclose(apply(world2cam, center), 0, atol=1e-12)
    in_cam = apply(world2cam, target)
    np.testing.assert_allclose(in_cam[:2], 0, atol=1e-12)
    assert in_cam[2] == pytest.approx(np.linalg.norm(target - center))
    np.testing.assert_allclose(world2cam[:3, :3] @ world2cam[:3, :3].T, np.eye(3), atol=1e-15)
    assert np.linalg.det(world2cam[:3, :3]) == pytest.approx(1.0)
    # world up appears upwards: camera y (down) has a negative world-y component
    assert world2cam[1, 1] < 0


def test_behind_surface_matches_the_numpy_depth_splat(ict, rng):
    world2cam = look_at([150.0, 80.0, 650.0], ict.neutral.mean(axis=0))
    surface = apply(world2cam, ict.neutral)
    sites = apply(world2cam, ict.neutral[ict.triangles].mean(axis=1))
    cosine = rng.uniform(-0.2, 1.0, len(sites))
    cell_mm = depth_cell_mm(ict.neutral, ict.triangles)
    hidden = behind_surface(surface, sites, cosine, cell_mm)
    np.testing.assert_array_equal(hidden, behind_surface_numpy(surface, sites, cosine, cell_mm))
    assert 0.05 < hidden.mean() < 0.6  # the far side of the nose and the cheek's silhouette
    # a point's answer does not depend on which other points are asked about
    some = rng.choice(len(sites), 50, replace=False)
    np.testing.assert_array_equal(behind_surface(surface, sites[some], cosine[some], cell_mm), hidden[some])
    assert behind_surface(surface, np.zeros((0, 3)), np.zeros(0), cell_mm).shape == (0,)


def test_the_rig_and_the_layout_designer_see_the_same_markers(ict):
    """At the neutral pose a simulated camera draws exactly the markers the layout designer counts as seen."""
    from livebridge.face.layout import design_markers
    from livebridge.face.meshio import triangle_normals
    from livebridge.face.rig_visibility import RigVisibility
    from livebridge.simulators.performer import Performer
    from livebridge.simulators.rig import RigConfig, SimRig, generate_cameras

    config = RigConfig(noise_sigma=0.0, max_view_deg=70.0)
    cameras = generate_cameras(ict, 4, config, seed=3)
    markers = design_markers(ict, count=40, n_head=4)
    still = Performer(ict, markers, head_motion=False, realtime=False)  # the first frame is the neutral face
    truth = SimRig(ict, markers, cameras=cameras, config=config, performer=still).truth(0)
    assert not truth.contractions.any() and np.array_equal(truth.head2world, np.eye(4))
    sites = markers.neutral_positions(ict)
    normals = triangle_normals(ict.neutral, ict.triangles[markers.triangles])
    layout = RigVisibility(cameras, min_views=1, max_view_deg=70.0, margin_deg=0.0, model2world=np.eye(4))
    seen = layout.seen(ict, sites, normals)
    np.testing.assert_array_equal(truth.visible, seen)
    assert 0.3 < seen.mean() < 1.0
