"""Control points (livebridge.retarget.control_points) and AU transfer (livebridge.retarget.au), thesis §5.5-5.6."""

from __future__ import annotations

import numpy as np
import pytest
from factories import assert_cli_refused, split_triangles

from livebridge.face.basis import CHOE_KO_MUSCLES
from livebridge.face.builtin import builtin_basis
from livebridge.retarget.au import FaceRegions, prepare_transfer, save_mesh
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


def _recipe_expression(basis, points, group):
    """The source's neutral under ``group``'s muscle recipe: the expressive face the recipe stands for."""
    x = np.zeros(basis.n_muscles)
    for name, value in points.recipes[group].muscles.items():
        x[basis.index(name)] = value
    return basis.synthesize(x)


def _posed(vertices):
    """The same face with the head turned (0.12 rad) and moved (35 mm): no part of an expression."""
    from scipy.spatial.transform import Rotation

    return vertices @ Rotation.from_rotvec([0.05, -0.1, 0.04]).as_matrix().T + np.array([5.0, -12.0, 30.0])


@pytest.mark.parametrize("au", ["au12", "au1", "orbicularis_oculi_L"])
def test_an_expressive_blendshape_in_another_pose_transfers_as_the_recipe_does(points, builtin, target, au):
    basis, source_landmarks = builtin
    (vertices, triangles), landmarks = target
    expression = ((_posed(_recipe_expression(basis, points, au)), basis.triangles), source_landmarks, "au.obj")
    recipe = prepare_transfer(points, [au], basis, source_landmarks, (vertices, triangles), landmarks).mesh(1.0)
    shown = prepare_transfer(points, [au], (basis.neutral, basis.triangles), source_landmarks,
                             (vertices, triangles), landmarks, expression=expression).mesh(1.0)
    assert np.linalg.norm(recipe - vertices, axis=1).max() > 3.0
    assert np.abs(shown - recipe).max() < 1e-3  # the head's motion is taken out; the blendshape read exactly


def test_an_expressive_mesh_of_another_topology_is_read_the_thesis_way(points, builtin, target):
    """Landmark spline and nearest surface point (§5.5.3): the motion along the skin is the landmarks' only, so
    it reads AU12 0.37 of its RMS motion off the exact one (measured), but moves the mouth corners as it does."""
    from livebridge.retarget.landmarks import place_at_points

    basis, source_landmarks = builtin
    (vertices, triangles), landmarks = target
    expressive = _recipe_expression(basis, points, "au12")
    split_vertices, split_faces = split_triangles(expressive, basis.triangles)
    on_split = place_at_points(source_landmarks.as_dict(expressive, basis.triangles), split_vertices,
                               split_faces, 1e-6)
    exact = prepare_transfer(points, ["au12"], basis, source_landmarks, (vertices, triangles), landmarks)
    shown = [prepare_transfer(points, ["au12"], (basis.neutral, basis.triangles), source_landmarks,
                              (vertices, triangles), landmarks,
                              expression=((pose(split_vertices), split_faces), on_split, "au12.obj")).mesh(1.0)
             for pose in (lambda v: v, _posed)]
    assert np.abs(shown[1] - shown[0]).max() < 0.05  # the head's pose is taken out
    truth = exact.mesh(1.0) - vertices
    size = np.linalg.norm(truth, axis=1)
    moved = size > 0.01 * size.max()
    error = np.sqrt(np.mean(np.sum((shown[0] - vertices - truth)[moved] ** 2, axis=1)) / np.mean(size[moved] ** 2))
    assert error < 0.5
    corner = np.argmin(np.linalg.norm(vertices - exact.landmarks["mouth_corner_L"], axis=1))
    move = shown[0][corner] - vertices[corner]
    assert move @ truth[corner] > 0.7 * np.linalg.norm(move) * np.linalg.norm(truth[corner])


def test_cli_carries_an_expressive_obj_and_refuses_one_it_cannot_place(tmp_path, points):
    from click.testing import CliRunner

    from livebridge.cli import main
    from livebridge.face.meshio import read_obj

    basis = builtin_basis()
    save_mesh(tmp_path / "neutral.obj", basis.neutral, basis.triangles)
    save_mesh(tmp_path / "smile.obj", _posed(_recipe_expression(basis, points, "au12")), basis.triangles)
    save_mesh(tmp_path / "split.obj", *split_triangles(basis.neutral, basis.triangles))
    common = ["retarget", "au", "--source-landmarks", "builtin-22", "--target", "builtin", "--target-landmarks",
              "builtin-22", "--au", "12"]
    runner = CliRunner()
    by_recipe = runner.invoke(main, [*common, "--source", "builtin", "--out", str(tmp_path / "recipe.obj")])
    shown = runner.invoke(main, [*common, "--source", str(tmp_path / "neutral.obj"), "--expression",
                                 str(tmp_path / "smile.obj"), "--out", str(tmp_path / "shown.obj")])
    assert by_recipe.exit_code == 0 and shown.exit_code == 0, by_recipe.output + shown.output
    recipe, moved = (read_obj(tmp_path / name).vertices for name in ("recipe.obj", "shown.obj"))
    assert np.linalg.norm(recipe - basis.neutral, axis=1).max() > 3.0
    assert np.abs(moved - recipe).max() < 1e-3
    refused = runner.invoke(main, [*common, "--source", str(tmp_path / "neutral.obj"), "--expression",
                                   str(tmp_path / "split.obj"), "--out", str(tmp_path / "split_au.obj")])
    assert refused.exit_code != 0
    assert "split.obj" in refused.output and "--expression-landmarks" in refused.output
    assert not (tmp_path / "split_au.obj").exists()


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
    save_mesh(tmp_path / "metres.obj", face.neutral / 1000, face.triangles)
    args = ["retarget", verb, "--source", "builtin", "--source-landmarks", "builtin-22", "--target",
            str(tmp_path / "metres.obj"), "--target-landmarks", "builtin-22"]
    out = ["--au", "12", "--out", str(tmp_path / "au.obj")] if verb == "au" else ["--out", str(tmp_path / "b.npz")]
    assert_cli_refused(CliRunner().invoke(main, args + out), "metres.obj", "units", "0.001 times")
    result = CliRunner().invoke(main, args + out + ["--units", "m"])
    assert result.exit_code == 0, result.output
