"""Control points (livebridge.retarget.control_points) and AU transfer (livebridge.retarget.au), thesis §5.5-5.6."""

from __future__ import annotations

import numpy as np
import pytest
from factories import assert_cli_refused

from livebridge.face.basis import CHOE_KO_MUSCLES
from livebridge.face.builtin import builtin_basis
from livebridge.retarget.au import FaceRegions, prepare_transfer, save_obj
from livebridge.retarget.control_points import THESIS_AUS, ControlPointSet, load_control_points
from livebridge.retarget.landmarks import load_landmark_set


@pytest.fixture(scope="module")
def points():
    return load_control_points("thesis")


@pytest.fixture(scope="module")
def builtin():
    return builtin_basis(), load_landmark_set("builtin-22")


@pytest.fixture(scope="module")
def target(ict):
    """The ICT face region with its 22 landmarks: another face, another topology."""
    return (ict.neutral, ict.triangles), load_landmark_set("ict-22")


def test_shipped_set_covers_the_thesis_aus_and_every_choe_ko_muscle(points, tmp_path):
    assert {f"au{n}" for n in THESIS_AUS} | {m.name for m in CHOE_KO_MUSCLES} <= set(points.group_names)
    for group in points.group_names:
        assert points.recipes[group].muscles, group
    assert set(points.regions) == {"upper", "lower"} and set(points.sides) == {"L", "R", "C"}
    points.save(tmp_path / "cp.toml")
    again = ControlPointSet.load(tmp_path / "cp.toml")
    assert again.names == points.names and np.allclose(again.positions, points.positions, atol=1e-4)


def test_carried_points_lie_on_the_target_surface_near_their_landmarks(points, target):
    from livebridge.retarget.landmarks import closest_surface_points

    (vertices, triangles), landmarks = target
    carried = points.on(vertices, triangles, landmarks)
    assert closest_surface_points(carried, vertices, triangles)[2].max() < 1e-6
    marks = landmarks.as_dict(vertices, triangles)
    corner = points.names.index("au12_corner_L")
    assert np.linalg.norm(carried[corner] - marks["mouth_corner_L"]) < 5.0  # the AU12 point sits on the corner


@pytest.mark.parametrize("au", ["au1", "au2", "au4"])
def test_a_brow_expression_never_moves_the_lower_face(points, builtin, target, au):
    basis, source_landmarks = builtin
    (vertices, triangles), landmarks = target
    transfer = prepare_transfer(points, [au], basis, source_landmarks, (vertices, triangles), landmarks)
    moved = transfer.mesh(1.0)
    lower = ~FaceRegions.of(transfer.landmarks).upper(vertices)
    assert np.array_equal(moved[lower], vertices[lower])
    assert np.linalg.norm(moved - vertices, axis=1).max() > 1.0  # and the brows do move


def test_au12_pulls_the_mouth_corners_up_and_out_scaled_by_magnitude(points, builtin, target):
    basis, source_landmarks = builtin
    (vertices, triangles), landmarks = target
    transfer = prepare_transfer(points, ["au12"], basis, source_landmarks, (vertices, triangles), landmarks)
    marks = transfer.landmarks
    corner = np.argmin(np.linalg.norm(vertices - marks["mouth_corner_L"], axis=1))
    full, half = transfer.mesh(1.0), transfer.mesh(0.5)
    move = full[corner] - vertices[corner]
    assert move[0] > 0.5 and move[1] > 0.5  # out (+x on the left) and up
    assert np.allclose(half - vertices, 0.5 * (full - vertices), atol=1e-9)  # the warp is linear in m
    assert np.array_equal(transfer.mesh(0.0), vertices)
    upper = FaceRegions.of(marks).upper(vertices)
    assert np.array_equal(full[upper], vertices[upper])


def test_one_sided_au_moves_that_side_only(points, builtin, target):
    basis, source_landmarks = builtin
    (vertices, triangles), landmarks = target
    transfer = prepare_transfer(points, ["au12"], basis, source_landmarks, (vertices, triangles), landmarks,
                                sides=("L",))
    moved = transfer.mesh(1.0)
    marks = transfer.landmarks
    left = np.argmin(np.linalg.norm(vertices - marks["mouth_corner_L"], axis=1))
    right = np.argmin(np.linalg.norm(vertices - marks["mouth_corner_R"], axis=1))
    assert np.linalg.norm(moved[left] - vertices[left]) > 2.0
    assert np.linalg.norm(moved[right] - vertices[right]) < 0.1 * np.linalg.norm(moved[left] - vertices[left])


def test_combined_aus_move_both_regions(points, builtin, target):
    basis, source_landmarks = builtin
    (vertices, triangles), landmarks = target
    both = prepare_transfer(points, ["au1", "au12"], basis, source_landmarks, (vertices, triangles), landmarks)
    brow = prepare_transfer(points, ["au1"], basis, source_landmarks, (vertices, triangles), landmarks)
    mouth = prepare_transfer(points, ["au12"], basis, source_landmarks, (vertices, triangles), landmarks)
    # the regions are warped apart, so the combination is the sum of the parts
    assert np.allclose(both.mesh(1.0) - vertices, (brow.mesh(1.0) - vertices) + (mouth.mesh(1.0) - vertices),
                       atol=1e-9)


def test_cli_writes_an_au_mesh(tmp_path):
    from click.testing import CliRunner

    from livebridge.cli import main
    from livebridge.face.meshio import read_obj

    out = tmp_path / "au12.obj"
    result = CliRunner().invoke(main, ["retarget", "au", "--source", "builtin", "--source-landmarks", "builtin-22",
                                       "--target", "builtin", "--target-landmarks", "builtin-22", "--au", "12",
                                       "--magnitude", "0.7", "--side", "left", "--out", str(out)])
    assert result.exit_code == 0, result.output
    mesh = read_obj(out)
    basis = builtin_basis()
    assert mesh.vertices.shape == basis.neutral.shape
    assert 1.0 < np.linalg.norm(mesh.vertices - basis.neutral, axis=1).max() < 30.0


def test_cli_names_the_file_of_source_landmarks_the_control_points_need(tmp_path, builtin):
    from click.testing import CliRunner

    from livebridge.cli import main

    _, landmarks = builtin
    landmarks.subset(np.array([name != "chin" for name in landmarks.names])).save(tmp_path / "lm21.toml")
    result = CliRunner().invoke(main, ["retarget", "au", "--source", "builtin", "--source-landmarks",
                                       str(tmp_path / "lm21.toml"), "--target", "builtin", "--target-landmarks",
                                       "builtin-22", "--au", "12", "--out", str(tmp_path / "au.obj")])
    assert_cli_refused(result, "lm21.toml", "landmarks", "chin", "control points")


@pytest.mark.parametrize("verb", ["au", "basis"])
def test_cli_refuses_a_target_in_other_units_naming_the_mesh_and_units(tmp_path, builtin, verb):
    from click.testing import CliRunner

    from livebridge.cli import main

    face, _ = builtin
    save_obj(tmp_path / "metres.obj", face.neutral / 1000, face.triangles)
    args = ["retarget", verb, "--source", "builtin", "--source-landmarks", "builtin-22", "--target",
            str(tmp_path / "metres.obj"), "--target-landmarks", "builtin-22"]
    out = ["--au", "12", "--out", str(tmp_path / "au.obj")] if verb == "au" else ["--out", str(tmp_path / "b.npz")]
    assert_cli_refused(CliRunner().invoke(main, args + out), "metres.obj", "units", "0.001 times")
    result = CliRunner().invoke(main, args + out + ["--units", "m"])
    assert result.exit_code == 0, result.output
