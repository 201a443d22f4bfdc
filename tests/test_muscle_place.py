"""An element built from a scan is checked against where its muscle is: a scan given for the wrong side or the
wrong muscle gets a warning naming it, and the right ones (ICT's and the built-in face's 16) get none."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner
from factories import write_builtin_scans

from livebridge.face.basis import CHOE_KO_BY_NAME, Muscle
from livebridge.face.muscle_place import misplaced, muscle_for
from livebridge.retarget.landmarks import load_landmark_set


@pytest.fixture(scope="module", params=["ict", "builtin"])
def face(request, ict):
    """(basis, its 22 landmarks as a dict) of the ICT face region and of the built-in face."""
    if request.param == "ict":
        basis = ict
    else:
        from livebridge.face.builtin import builtin_basis

        basis = builtin_basis()
    landmarks = load_landmark_set(f"{request.param}-22").as_dict(basis.neutral, basis.triangles)
    return basis, landmarks


def _element(basis, *names) -> np.ndarray:
    return sum(basis.elements[basis.index(name)] for name in names)


def test_every_element_moves_where_its_muscle_is(face):
    basis, landmarks = face
    for muscle, element in zip(basis.muscles, basis.elements):
        assert misplaced(muscle, element, basis.neutral, landmarks) is None, muscle.name


def test_an_element_given_for_the_other_side_is_named_with_its_side(face):
    basis, landmarks = face
    sided = [m for m in basis.muscles if m.side is not None]
    assert len(sided) == 12
    for muscle in sided:
        other = muscle.name[:-1] + ("R" if muscle.side == "L" else "L")
        why = misplaced(CHOE_KO_BY_NAME[other], _element(basis, muscle.name), basis.neutral, landmarks)
        assert why is not None and f"is its scan {muscle.name}'s?" in why, (muscle.name, why)
        assert f"the subject's {'left' if muscle.side == 'L' else 'right'} side" in why


@pytest.mark.parametrize("given,built,words", [
    ("frontalis_L", ("zygomatic_major_L",), "below the nose tip"),  # a smile given as a brow raise
    ("orbicularis_oculi_R", ("levator_labii_R",), "below the nose tip"),
    ("jaw", ("frontalis_L", "frontalis_R"), "above the outer eye corners"),  # both brows given as the jaw
    ("lips_pressor", ("corrugator_L", "corrugator_R"), "above the outer eye corners"),
    ("orbicularis_oris", ("risorius_L",), "mostly the subject's left side"),  # one side given as both
    ("risorius_R", ("orbicularis_oris",), "both sides alike"),  # both sides given as one
])
def test_an_element_given_for_another_muscle_is_warned_of(face, given, built, words):
    basis, landmarks = face
    why = misplaced(CHOE_KO_BY_NAME[given], _element(basis, *built), basis.neutral, landmarks)
    assert why is not None and words in why, why


def test_a_new_muscle_is_placed_where_its_element_moves(face):
    basis, landmarks = face
    for muscle, element in zip(basis.muscles, basis.elements):
        placed = muscle_for("my_" + muscle.name, element, basis.neutral, landmarks)
        assert (placed.region, placed.side) == (muscle.region, muscle.side), muscle.name
        assert misplaced(placed, element, basis.neutral, landmarks) is None
    assert muscle_for("jaw", basis.elements[0], basis.neutral, landmarks) is CHOE_KO_BY_NAME["jaw"]


def test_noise_over_the_face_does_not_move_a_small_elements_centre(face):
    """A closing eye moves a tenth of the face; tracking noise of 0.15 mm everywhere else must not pull its
    centre below the eye corners (as a centre weighted by the motion itself, not its square, did: a blink from
    scans would have been a lower-face muscle)."""
    basis, landmarks = face
    rng = np.random.default_rng(0)
    element = _element(basis, "orbicularis_oculi_L") + rng.normal(0, 0.15 / np.sqrt(3), basis.neutral.shape)
    muscle = Muscle("orbicularis_oculi_L", "upper", "L")
    assert misplaced(muscle, element, basis.neutral, landmarks) is None
    placed = muscle_for("blink_L", element, basis.neutral, landmarks)
    assert (placed.region, placed.side) == ("upper", "L")


def test_retarget_scans_warns_of_a_scan_given_for_the_other_side(tmp_path):
    from livebridge.cli import main

    write_builtin_scans(tmp_path, 4, {"neutral": "neutral", "zygomatic_major_L": "smile_L"})

    def build(muscle):
        result = CliRunner().invoke(main, [
            "retarget", "scans", "--neutral", str(tmp_path / "neutral.ply"), "--neutral-landmarks",
            str(tmp_path / "neutral.landmarks.csv"), "--expression", f"{muscle}={tmp_path / 'smile_L.ply'}",
            "--grid", "40x40", "--out", str(tmp_path / f"{muscle}.npz")])
        assert result.exit_code == 0, result.output
        return [line for line in result.output.splitlines() if line.startswith("warning:")]

    assert build("zygomatic_major_L") == []
    warnings = build("zygomatic_major_R")
    assert len(warnings) == 1 and "zygomatic_major_R" in warnings[0], warnings
    assert "the subject's left side" in warnings[0] and "is its scan zygomatic_major_L's?" in warnings[0]
    assert (tmp_path / "zygomatic_major_R.npz").exists()  # a warning: the basis is still written


def _import(tmp_path, shapes, swap_brows: bool = False):
    from livebridge.cli import main
    from livebridge.face.basis_import import shipped_manifest

    text = shipped_manifest("choe-ko-ict").read_text()
    if swap_brows:  # an artist's rig whose brow shapes are named by the viewer's side
        text = text.replace("browInnerUp_L = 1.0, browOuterUp_L", "browInnerUp_X = 1.0, browOuterUp_X")
        text = text.replace("browInnerUp_R = 1.0, browOuterUp_R", "browInnerUp_L = 1.0, browOuterUp_L")
        text = text.replace("browInnerUp_X = 1.0, browOuterUp_X", "browInnerUp_R = 1.0, browOuterUp_R")
    (tmp_path / "manifest.toml").write_text(text)
    result = CliRunner().invoke(main, ["basis", "import", str(tmp_path / "manifest.toml"), "--shapes", str(shapes),
                                       "--out", str(tmp_path / "basis.npz"), "--force"])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "basis.npz").exists()
    return [line for line in result.output.splitlines() if line.startswith("warning:")]


def test_basis_import_warns_of_shapes_named_by_the_other_side(tmp_path, shared_data):
    shapes = shared_data / "ict-facekit" / "face_region.npz"
    assert _import(tmp_path, shapes) == []
    warnings = _import(tmp_path, shapes, swap_brows=True)
    assert len(warnings) == 2, warnings
    assert "frontalis_L: it moves the subject's right side" in warnings[0]
    assert "frontalis_R: it moves the subject's left side" in warnings[1]


def test_basis_import_of_a_mirrored_mesh_says_so_once(tmp_path, shared_data):
    with np.load(shared_data / "ict-facekit" / "face_region.npz") as data:
        kit = dict(data)
    flip = np.array([-1.0, 1.0, 1.0], dtype=np.float32)  # a mesh whose +x is the subject's right
    kit["neutral"], kit["deltas"] = kit["neutral"] * flip, kit["deltas"] * flip
    kit["triangles"] = kit["triangles"][:, ::-1]
    np.savez(tmp_path / "mirrored.npz", **kit)
    warnings = _import(tmp_path, tmp_path / "mirrored.npz")
    assert len(warnings) == 1 and "every one-sided element (12)" in warnings[0] and "x -> -x" in warnings[0]
