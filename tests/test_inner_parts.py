"""Closed parts inside a target head (livebridge.retarget.inner_parts): teeth and eyeballs move with their bone
when a basis is retargeted or AUs are carried onto a full head, not with the skin nearest them."""

from __future__ import annotations

import numpy as np
import pytest

import livebridge.retarget.au as au_module
import livebridge.retarget.basis as basis_module
from livebridge.retarget.basis import retarget_basis
from livebridge.retarget.inner_parts import BoneParts, bone_parts, jaw_turners

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
    others = [k for k, name in enumerate(out.names) if name != "jaw"]
    assert np.all(out.elements[others][:, masks["lower_tooth"]] == 0.0)  # a smile moves the chin's skin, not the jaw


def test_a_basis_naming_no_jaw_muscle_moves_the_jaw_parts_as_its_chin_moves(builtin_head):
    from dataclasses import replace

    from livebridge.face.basis import Basis

    basis, landmarks, vertices, triangles, masks, target = builtin_head
    renamed = Basis(basis.neutral, basis.triangles, basis.elements,
                    tuple(replace(m, name=f"m{k}") for k, m in enumerate(basis.muscles)))
    assert jaw_turners(renamed.names).all() and jaw_turners(basis.names).sum() == 1
    out = retarget_basis(renamed, landmarks, vertices, triangles, target)
    jaw = out.elements[basis.names.index("jaw")][masks["lower_tooth"]]
    assert jaw[:, 1].mean() < -0.2 * np.linalg.norm(out.elements[basis.names.index("jaw")], axis=1).max()


def test_a_mesh_of_skin_only_has_no_parts_on_bones():
    from livebridge.face.builtin import builtin_basis
    from livebridge.retarget.landmarks import load_landmark_set

    basis, landmarks = builtin_basis(), load_landmark_set("builtin-22")
    parts = bone_parts(basis.neutral, basis.triangles, landmarks)
    assert not parts.any


@pytest.fixture(scope="module")
def ict_head(shared_data, ict):
    """ICT's whole head (26719 vertices, 56 parts, mm) with the 22 landmarks of its face region; (vertices,
    triangles, landmarks, parts, {name: ICT's own expression minus the neutral} for jawOpen and mouthSmile_L)."""
    from livebridge.face.meshio import read_obj
    from livebridge.retarget.landmarks import load_landmark_set, place_at_points

    folder = shared_data / "ict-facekit" / "obj"
    neutral = read_obj(folder / "generic_neutral_mesh.obj")
    vertices, triangles = neutral.vertices * 10.0, neutral.triangles
    shown = {name: read_obj(folder / f"{name}.obj").vertices * 10.0 - vertices for name in ("jawOpen", "mouthSmile_L")}
    target = place_at_points(load_landmark_set("ict-22").as_dict(ict.neutral, ict.triangles), vertices, triangles, 0.5)
    return vertices, triangles, target, bone_parts(vertices, triangles, target), shown


def test_ict_full_head_teeth_and_eyes_against_its_own_jaw_open(ict, ict_head, monkeypatch):
    """ICT's basis (face region) onto ICT's whole head: its upper teeth and eyeballs are still in every element (as
    in ICT's own ``jawOpen``, ``mouthSmile_L``); its lower teeth swing rigidly with the chin in the jaw's element
    and stay still in the smile's, as in ``mouthSmile_L``. Against ``jawOpen`` the lower teeth are 0.21 of their
    31.4 mm RMS motion off (the chin's skin lags the bone: 20.6 degrees read for 25.3), where the skin nearest
    them gave 0.39 and moved the upper teeth 11 mm."""
    from livebridge.retarget.landmarks import load_landmark_set

    vertices, triangles, target, parts, shown = ict_head
    jaw_open, landmarks = shown["jawOpen"], load_landmark_set("ict-22")
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
    assert np.abs(shown["mouthSmile_L"][parts.jaw]).max() < 0.01  # mm: ICT's OBJ rounding
    assert not out.elements[ict.index("zygomatic_major_L")][parts.jaw].any()


def test_au_meshes_keep_teeth_and_eyes_on_their_bones(ict, ict_head, monkeypatch):
    """AUs carried onto ICT's whole head: in a smile (AU12, as in ICT's own ``mouthSmile_L``) and a brow raise
    the teeth and eyes stay still, where the regions' splines moved the upper teeth up to 12 mm and the eyes 4;
    opening the jaw swings the lower teeth rigidly down. The skin is the splines' either way."""
    from livebridge.retarget.control_points import load_control_points
    from livebridge.retarget.landmarks import load_landmark_set

    vertices, triangles, target, parts, shown = ict_head
    points, landmarks = load_control_points("thesis"), load_landmark_set("ict-22")

    def au_mesh(groups, sides=("L", "R", "C")):
        return au_module.prepare_transfer(points, groups, ict, landmarks, (vertices, triangles), target,
                                          sides).mesh(1.0)

    smile, brows, jaw = au_mesh(["au12"], ("L",)), au_mesh(["au1", "au2"]), au_mesh(["jaw"])
    on_bone = parts.skull | parts.jaw
    assert np.array_equal(smile[on_bone], vertices[on_bone]) and np.array_equal(brows[on_bone], vertices[on_bone])
    assert np.abs(shown["mouthSmile_L"][on_bone]).max() < 0.01  # mm: ICT's OBJ rounding
    assert np.array_equal(jaw[parts.skull], vertices[parts.skull])
    teeth, swung = vertices[parts.jaw][::40], jaw[parts.jaw][::40]
    assert np.allclose(_distances(swung), _distances(teeth), atol=1e-6)  # rigid
    assert (swung - teeth)[:, 1].mean() < -10.0  # down, mm
    monkeypatch.setattr(au_module, "bone_parts", lambda *_: BoneParts(*(np.zeros(len(vertices), bool),) * 3))
    spline_smile, spline_brows = au_mesh(["au12"], ("L",)), au_mesh(["au1", "au2"])
    assert np.linalg.norm(spline_smile - vertices, axis=1)[parts.skull].max() > 5.0
    assert np.linalg.norm(spline_brows - vertices, axis=1)[parts.skull].max() > 2.0
    assert np.array_equal(spline_smile[~on_bone], smile[~on_bone])


def test_cli_says_which_parts_move_with_a_bone(shared_data, ict, ict_head, tmp_path):
    from click.testing import CliRunner

    from livebridge.cli import main
    from livebridge.face.basis import Basis
    from livebridge.face.meshio import read_obj

    vertices, _, target, parts, _ = ict_head
    head = shared_data / "ict-facekit" / "obj" / "generic_neutral_mesh.obj"
    in_cm = vertices / 10.0  # as the OBJ has them
    target.save(tmp_path / "head.toml")
    ict.save(tmp_path / "ict.npz")
    args = ["retarget", "basis", "--source", str(tmp_path / "ict.npz"), "--source-landmarks", "ict-22", "--target",
            str(head), "--target-landmarks", str(tmp_path / "head.toml"), "--units", "cm", "--out",
            str(tmp_path / "head.npz")]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert "on the skull (still)" in result.output and "on the jaw" in result.output
    assert np.all(Basis.load(tmp_path / "head.npz").elements[:, parts.skull] == 0.0)
    args = ["retarget", "au", "--source", str(tmp_path / "ict.npz"), "--source-landmarks", "ict-22", "--target",
            str(head), "--target-landmarks", str(tmp_path / "head.toml"), "--units", "cm", "--au", "12", "--out",
            str(tmp_path / "smile.obj")]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert "on the skull (still)" in result.output and "in cm" in result.output
    smile = read_obj(tmp_path / "smile.obj")
    assert np.allclose(smile.vertices[parts.skull], in_cm[parts.skull], rtol=1e-8, atol=0)  # the OBJ's cm
    assert np.abs(smile.vertices - in_cm).max() > 1.0  # the smile, in cm

    def kept(path):  # the quads with their texture coordinates, the materials
        return [line for line in path.read_text().splitlines() if line.startswith(("f ", "vt ", "usemtl", "mtllib"))]

    assert kept(tmp_path / "smile.obj") == kept(head)
