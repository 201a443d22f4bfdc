"""Closed parts inside a target head (livebridge.retarget.inner_parts): teeth and eyeballs move with their bone
when a basis is retargeted onto a full head, not with the skin nearest them."""

from __future__ import annotations

import numpy as np
import pytest

import livebridge.retarget.basis as basis_module
from livebridge.retarget.basis import retarget_basis
from livebridge.retarget.inner_parts import BoneParts, bone_parts

CUBE_TRIANGLES = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4], [2, 6, 3], [3, 6, 7],
                           [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])
"""A closed cube over the corners ``(i & 1, i >> 1 & 1, i >> 2 & 1)``."""


def _cube(centre: np.ndarray, side: float) -> np.ndarray:
    corners = np.array([[i & 1, i >> 1 & 1, i >> 2 & 1] for i in range(8)], dtype=float) - 0.5
    return centre + side * corners


def _with_parts(vertices, triangles, centres: dict[str, np.ndarray], side: float):
    """The mesh with a closed cube per name added; (vertices, triangles, {name: vertex mask})."""
    masks = {}
    for name, centre in centres.items():
        start = len(vertices)
        vertices = np.vstack([vertices, _cube(centre, side)])
        triangles = np.vstack([triangles, CUBE_TRIANGLES + start])
        masks[name] = np.arange(len(vertices)) >= start
    return vertices, triangles, {name: np.pad(m, (0, len(vertices) - len(m))) for name, m in masks.items()}


def _distances(points: np.ndarray) -> np.ndarray:
    return np.linalg.norm(points[:, None] - points[None], axis=2)


@pytest.fixture(scope="module")
def builtin_head():
    """The built-in face with a cube behind the left eye, an upper and a lower tooth behind the lips and a small
    cube on the outside of the left brow; (basis, landmarks, vertices, triangles, masks)."""
    from livebridge.face.builtin import builtin_basis
    from livebridge.retarget.landmarks import load_landmark_set, place_at_points

    basis, landmarks = builtin_basis(), load_landmark_set("builtin-22")
    at = landmarks.as_dict(basis.neutral, basis.triangles)
    mouth = 0.5 * (at["lip_upper_inner"] + at["lip_lower_inner"])
    up, front = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])
    centres = {"eyeball": 0.5 * (at["eye_outer_L"] + at["eye_inner_L"]) - 14 * front,
               "upper_tooth": mouth - 10 * front + 4 * up, "lower_tooth": mouth - 10 * front - 4 * up,
               "brow_shell": at["brow_middle_L"] + 3 * front}
    vertices, triangles, masks = _with_parts(basis.neutral, basis.triangles, centres, 5.0)
    target = place_at_points(at, vertices, triangles, 1e-6)
    return basis, landmarks, vertices, triangles, masks, target


def test_closed_parts_behind_the_face_are_put_on_the_skull_or_the_jaw(builtin_head):
    _, _, vertices, triangles, masks, landmarks = builtin_head
    parts = bone_parts(vertices, triangles, landmarks)
    assert parts.skull[masks["eyeball"]].all() and parts.skull[masks["upper_tooth"]].all()
    assert parts.jaw[masks["lower_tooth"]].all() and not parts.jaw[~masks["lower_tooth"]].any()
    on_bone = parts.skull | parts.jaw
    assert not on_bone[masks["brow_shell"]].any()  # on the outside of the skin: a brow or beard shell
    assert not on_bone[~np.any(list(masks.values()), axis=0)].any()  # the skin
    assert parts.chin.any() and not parts.chin[on_bone].any()


def test_retargeted_teeth_and_eyes_move_as_their_bones(builtin_head):
    basis, landmarks, vertices, triangles, masks, target = builtin_head
    out = retarget_basis(basis, landmarks, vertices, triangles, target)
    for name in ("eyeball", "upper_tooth"):
        assert np.all(out.elements[:, masks[name]] == 0.0), name
    tooth = vertices[masks["lower_tooth"]]
    jaw = out.elements[out.names.index("jaw")]
    moved = tooth + jaw[masks["lower_tooth"]]
    assert np.allclose(_distances(moved), _distances(tooth), atol=1e-9)  # rigid
    assert jaw[masks["lower_tooth"], 1].mean() < -0.2 * np.linalg.norm(jaw, axis=1).max()  # down with the chin
    frontalis = out.elements[out.names.index("frontalis_L")]
    assert np.linalg.norm(frontalis[masks["brow_shell"]], axis=1).min() > 0.5  # with the brow's skin


def test_a_mesh_of_skin_only_has_no_parts_on_bones():
    from livebridge.face.builtin import builtin_basis
    from livebridge.retarget.landmarks import load_landmark_set

    basis, landmarks = builtin_basis(), load_landmark_set("builtin-22")
    parts = bone_parts(basis.neutral, basis.triangles, landmarks)
    assert not parts.any


def test_ict_full_head_teeth_and_eyes_against_its_own_jaw_open(shared_data, ict, monkeypatch):
    """ICT's basis (face region) onto ICT's whole head (26719 vertices, 56 parts): its upper teeth and eyeballs
    are still in every element (as in ICT's own ``jawOpen``, ``mouthSmile_L``); its lower teeth swing rigidly
    with the chin. Against ``jawOpen`` the lower teeth are 0.21 of their 31.4 mm RMS motion off (the chin's skin
    lags the bone: 20.6 degrees read for 25.3), where the skin nearest them gave 0.39 and moved the upper teeth
    11 mm."""
    from livebridge.face.meshio import read_obj
    from livebridge.retarget.landmarks import load_landmark_set, place_at_points

    folder = shared_data / "ict-facekit" / "obj"
    neutral = read_obj(folder / "generic_neutral_mesh.obj")
    vertices, triangles = neutral.vertices * 10.0, neutral.triangles
    jaw_open = read_obj(folder / "jawOpen.obj").vertices * 10.0 - vertices
    landmarks = load_landmark_set("ict-22")
    target = place_at_points(landmarks.as_dict(ict.neutral, ict.triangles), vertices, triangles, 0.5)
    parts = bone_parts(vertices, triangles, target)
    still = np.linalg.norm(jaw_open, axis=1) == 0.0
    assert parts.skull.sum() > 5000 and still[parts.skull].all()  # upper teeth and eyeballs
    assert parts.jaw.sum() > 2000 and not still[parts.jaw].any()  # lower teeth
    out = retarget_basis(ict, landmarks, vertices, triangles, target)
    assert np.all(out.elements[:, parts.skull] == 0.0)

    def teeth_error(elements):
        error = elements[out.names.index("jaw")][parts.jaw] - jaw_open[parts.jaw]
        return np.sqrt(np.mean(np.sum(error ** 2, axis=1)) / np.mean(np.sum(jaw_open[parts.jaw] ** 2, axis=1)))

    monkeypatch.setattr(basis_module, "bone_parts", lambda *_: BoneParts(*(np.zeros(len(vertices), bool),) * 3))
    skin_nearest = retarget_basis(ict, landmarks, vertices, triangles, target).elements
    assert teeth_error(out.elements) < 0.3 and teeth_error(out.elements) < 0.6 * teeth_error(skin_nearest)
    skin = ~(parts.skull | parts.jaw)
    assert np.array_equal(out.elements[:, skin], skin_nearest[:, skin])


def test_cli_says_which_parts_move_with_a_bone(shared_data, ict, tmp_path):
    from click.testing import CliRunner

    from livebridge.cli import main
    from livebridge.face.basis import Basis
    from livebridge.face.meshio import read_obj
    from livebridge.retarget.landmarks import load_landmark_set, place_at_points

    head = shared_data / "ict-facekit" / "obj" / "generic_neutral_mesh.obj"
    mesh = read_obj(head)
    landmarks = load_landmark_set("ict-22")
    place_at_points(landmarks.as_dict(ict.neutral, ict.triangles), mesh.vertices * 10.0, mesh.triangles,
                    0.5).save(tmp_path / "head.toml")
    ict.save(tmp_path / "ict.npz")
    args = ["retarget", "basis", "--source", str(tmp_path / "ict.npz"), "--source-landmarks", "ict-22", "--target",
            str(head), "--target-landmarks", str(tmp_path / "head.toml"), "--units", "cm", "--out",
            str(tmp_path / "head.npz")]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert "on the skull (still)" in result.output and "on the jaw" in result.output
    parts = bone_parts(mesh.vertices * 10.0, mesh.triangles, load_landmark_set(tmp_path / "head.toml"))
    assert np.all(Basis.load(tmp_path / "head.npz").elements[:, parts.skull] == 0.0)
