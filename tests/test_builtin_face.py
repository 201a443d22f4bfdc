import numpy as np
import pytest

from livebridge.face import builtin
from livebridge.face.basis import CHOE_KO_MUSCLES
from livebridge.face.builtin import builtin_basis, builtin_markers
from livebridge.face.layout import farthest_point_markers, layout_report
from livebridge.face.meshio import vertex_normals


@pytest.fixture(scope="module")
def face():
    return builtin_basis()


def test_size_units_and_orientation(face):
    assert 3000 <= face.n_vertices <= 10000
    assert np.isfinite(face.neutral).all() and np.isfinite(face.elements).all()
    assert face.names == tuple(m.name for m in CHOE_KO_MUSCLES)
    assert [m.region for m in face.muscles] == [m.region for m in CHOE_KO_MUSCLES]
    width = np.ptp(face.neutral[:, 0])
    assert 130 <= width <= 180  # a human face, in mm
    # +z out of the face: the nose tip is the frontmost point, on the midline, below the eyes
    tip = face.neutral[np.argmax(face.neutral[:, 2])]
    assert abs(tip[0]) < 3 and builtin.MOUTH_Y < tip[1] < builtin.EYE_Y
    # triangles face outwards: normals at the front of the face point towards +z
    normals = vertex_normals(face.neutral, face.triangles)
    front = (np.abs(face.neutral[:, 0]) < 40) & (np.abs(face.neutral[:, 1]) < 60)
    assert np.mean(normals[front, 2] > 0) > 0.9
    assert len(np.unique(face.triangles)) == face.n_vertices  # no stray vertices


def test_deterministic():
    a = builtin_basis.__wrapped__()
    b = builtin_basis.__wrapped__()
    np.testing.assert_array_equal(a.neutral, b.neutral)
    np.testing.assert_array_equal(a.triangles, b.triangles)
    np.testing.assert_array_equal(a.elements, b.elements)
    assert builtin_basis() is builtin_basis()


def test_not_a_sphere_has_features(face):
    # the profile along the midline is far from a circle: nose and lips stand out, eyes are sunken
    v = face.neutral

    def depth_at(x, y):
        near = np.hypot(v[:, 0] - x, v[:, 1] - y)
        front = v[:, 2] > 0
        return v[front][np.argmin(near[front]), 2]

    nose, cheek = depth_at(0, -8), depth_at(40, -8)
    assert nose - cheek > 25
    eye, brow = depth_at(builtin.EYE_X, builtin.EYE_Y), depth_at(builtin.EYE_X, 46)
    assert brow > eye + 3  # the eye sits in its socket under the brow ridge
    lip, below_lip = depth_at(0, builtin.MOUTH_Y - 5), depth_at(0, builtin.MOUTH_Y - 16)
    assert lip > below_lip + 3


def test_magnitudes_and_sides(face):
    peaks = np.linalg.norm(face.elements, axis=2).max(axis=1)
    for name, peak in zip(face.names, peaks):
        assert 3.0 <= peak <= 40.0, (name, peak)
    for name in face.names:
        if name.endswith("_L") or name.endswith("_R"):
            sign = 1 if name.endswith("_L") else -1  # the performer's left is +x
            magnitude = np.linalg.norm(face.elements[face.index(name)], axis=1)
            own, other = sign * face.neutral[:, 0] > 0, sign * face.neutral[:, 0] < 0
            assert np.sum(magnitude[own]) > 20 * np.sum(magnitude[other]), name
    # left and right elements mirror each other (compared on vertices with a unique position)
    rounded = np.round(face.neutral, 6)
    _, first, counts = np.unique(rounded, axis=0, return_index=True, return_counts=True)
    unique = np.sort(first[counts == 1])
    mirror = {tuple(p): i for i, p in zip(unique, rounded[unique] * np.array([-1, 1, 1]))}
    pairs = np.array([(i, mirror[tuple(rounded[i])]) for i in unique if tuple(rounded[i]) in mirror])
    assert len(pairs) > 0.9 * len(unique)
    for muscle in ("frontalis", "orbicularis_oculi", "zygomatic_major", "risorius"):
        left = face.elements[face.index(f"{muscle}_L")][pairs[:, 0]]
        right = face.elements[face.index(f"{muscle}_R")][pairs[:, 1]] * np.array([-1, 1, 1])
        np.testing.assert_allclose(left, right, atol=1e-6)


def test_upper_muscles_move_the_upper_face(face):
    y = face.neutral[:, 1]
    for k, muscle in enumerate(face.muscles):
        magnitude = np.linalg.norm(face.elements[k], axis=1)
        centre = np.sum(magnitude * y) / np.sum(magnitude)
        if muscle.region == "upper":
            assert centre > 15, muscle.name
        else:
            assert centre < 0, muscle.name


def test_jaw_moves_the_chin_most_and_opens_the_mouth(face):
    jaw = face.elements[face.index("jaw")]
    magnitude = np.linalg.norm(jaw, axis=1)
    chin = face.neutral[np.argmax(magnitude)]
    assert chin[1] < builtin.MOUTH_Y - 20 and abs(chin[0]) < 30
    assert 20.0 <= magnitude.max() <= 35.0
    # the chin goes down and back
    assert jaw[np.argmax(magnitude), 1] < -10
    # the forehead and the upper lip stay
    assert magnitude[face.neutral[:, 1] > 20].max() < 0.5
    # the mouth line is cut: twin vertices at the same place part when the jaw opens
    twins = [(i, j) for i, j in _twin_pairs(face)]
    assert len(twins) >= 10
    opened = face.neutral + jaw
    gaps = [np.linalg.norm(opened[i] - opened[j]) for i, j in twins]
    assert max(gaps) > 15


def _twin_pairs(face):
    rounded = {}
    for index, point in enumerate(np.round(face.neutral, 9)):
        rounded.setdefault(tuple(point), []).append(index)
    return [tuple(group) for group in rounded.values() if len(group) == 2]


@pytest.mark.parametrize("side,sign", [("L", 1), ("R", -1)])
def test_eyelid_closes(face, side, sign):
    element = face.elements[face.index(f"orbicularis_oculi_{side}")]
    v = face.neutral
    upper, lower = builtin._eye_margins(np.array(0.0))
    margin_y = builtin.EYE_Y + upper
    near = np.hypot(v[:, 0] - sign * builtin.EYE_X, v[:, 1] - margin_y) + (v[:, 2] < 0) * 1e9
    lid = int(np.argmin(near))
    closed = v[lid] + element[lid]
    assert element[lid, 1] < -0.6 * (upper - lower)  # the upper lid comes down most of the opening
    assert closed[1] < builtin.EYE_Y
    # the lower lid rises a little; the other eye does not move
    low = int(np.argmin(np.hypot(v[:, 0] - sign * builtin.EYE_X, v[:, 1] - builtin.EYE_Y - lower)
                        + (v[:, 2] < 0) * 1e9))
    assert element[low, 1] > 0
    other = np.hypot(v[:, 0] + sign * builtin.EYE_X, v[:, 1] - builtin.EYE_Y) < 12
    assert np.abs(element[other]).max() < 1e-9


def test_builtin_markers_are_a_good_layout(face):
    markers = builtin_markers()
    assert int(markers.face_mask.sum()) == 64 and int(markers.head_mask.sum()) >= 4
    report = layout_report(face, markers)
    baseline = layout_report(face, farthest_point_markers(face, 64, seed=0))
    assert report["condition_whole"] <= 0.5 * baseline["condition_whole"]
    assert report["min_observers"] >= 3
    assert report["head_spread_mm"] > 10 and report["head_motion_mm"] < 0.5
