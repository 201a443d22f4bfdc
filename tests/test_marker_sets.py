"""Shipped 68-point marker sets (``builtin-68``, ``ict-68``), loading marker sets by name, and matching a
file's marker names (or OpenFace's landmark numbers) to a marker set."""

from __future__ import annotations

import numpy as np
import pytest

from livebridge.errors import InputError
from livebridge.face import SHIPPED_MARKER_SETS
from livebridge.face.builtin import BUILTIN_68_HEAD, builtin_basis, builtin_landmarks, builtin_markers
from livebridge.face.markers import (
    LANDMARKS_68_UPPER,
    MarkerSet,
    landmark_name,
    landmark_number,
    match_markers,
)
from livebridge.face.shipped import load_marker_set
from livebridge.geometry.transforms import apply, invert, umeyama
from livebridge.simulators.performer import Performer
from livebridge.solve.solver import ContractionSolver


def test_builtin_68_solves_a_simulated_take(capsys):
    """Ground truth: the performer on the built-in face carrying the 68 landmarks, head moving, 0.2 mm noise.
    Head pose from the set's head markers, then the live solver: contraction RMSE at most 0.03."""
    basis, markers = builtin_basis(), builtin_landmarks()
    performance = Performer(basis, markers, fps=60.0, seed=3, realtime=False).performance(600)
    rng = np.random.default_rng(0)
    world = performance.marker_positions + rng.normal(scale=0.2, size=performance.marker_positions.shape)
    neutral = markers.neutral_positions(basis)
    head = markers.head_mask
    displacements = np.empty_like(world)
    for k, frame in enumerate(world):
        head2world = umeyama(neutral[head], frame[head], with_scale=False)
        displacements[k] = apply(invert(head2world), frame) - neutral
    solution = ContractionSolver(basis, markers).solve_take(displacements)
    rmse = float(np.sqrt(np.mean((solution.contractions - performance.contractions) ** 2)))
    with capsys.disabled():
        print(f"\nbuiltin-68 on a simulated take (600 frames, 0.2 mm noise): contraction RMSE {rmse:.4f}")
    assert rmse <= 0.03


def test_builtin_68_layout():
    markers = builtin_landmarks()
    assert markers.names == tuple(landmark_name(i) for i in range(68))
    assert [i for i, r in enumerate(markers.regions) if r == "upper"] == list(LANDMARKS_68_UPPER)
    assert [i for i, r in enumerate(markers.roles) if r == "head"] == list(BUILTIN_68_HEAD)
    basis = builtin_basis()
    p = markers.neutral_positions(basis)
    # the subject's right is -x: landmark 0 (right ear) and 36 (right eye outer corner) lie at -x, mirrors at +x
    assert p[0, 0] < -40 and p[16, 0] > 40 and p[36, 0] < p[39, 0] < 0 < p[42, 0] < p[45, 0]
    np.testing.assert_allclose(p[:17, 0], -p[16::-1, 0], atol=1.0)  # the jaw line is symmetric
    assert p[8, 1] < p[57, 1] < p[51, 1] < p[33, 1] < p[30, 1] < p[27, 1] < p[19, 1]  # chin .. brow upwards
    # the head markers do not move with any muscle, the face markers do
    moves = np.linalg.norm(markers.positions(basis.elements, basis.triangles) - 0, axis=-1).max(axis=0)
    assert np.all(moves[list(BUILTIN_68_HEAD)] < 0.3)
    assert np.all(np.delete(moves, BUILTIN_68_HEAD) > 0.5)


def test_ict_68_sits_on_the_ict_landmark_vertices(ict, shared_data):
    markers = load_marker_set("ict-68")
    markers.check_mesh(len(ict.triangles))
    with np.load(shared_data / "ict-facekit" / "face_region.npz") as data:
        vertices, rigid = data["landmark_vertices"], data["rigid_landmarks"]
    np.testing.assert_allclose(markers.neutral_positions(ict), ict.neutral[vertices], atol=1e-9)
    assert [i for i, r in enumerate(markers.roles) if r == "head"] == sorted(rigid.tolist())
    assert [i for i, r in enumerate(markers.regions) if r == "upper"] == list(LANDMARKS_68_UPPER)
    # and deforms with the basis as the landmark vertices do
    jaw = ict.names.index("jaw")
    np.testing.assert_allclose(markers.positions(ict.elements[jaw], ict.triangles), ict.elements[jaw][vertices],
                               atol=1e-9)


def test_every_shipped_name_loads():
    for name in SHIPPED_MARKER_SETS:
        assert len(load_marker_set(name)) > 0
    assert load_marker_set("builtin") is builtin_markers()
    with pytest.raises(InputError, match="not found|No such"):
        load_marker_set("ict-69")


def test_session_accepts_a_shipped_marker_set(tmp_path):
    from livebridge.runtime.build import load_face
    from livebridge.runtime.session import load_session

    (tmp_path / "s.toml").write_text('[cameras]\nurls = ["sim://rig"]\n[face]\nmarkers = "builtin-68"\n')
    _, markers = load_face(load_session(tmp_path / "s.toml"))
    assert markers.names == builtin_landmarks().names


# -------------------------------------------------------------------------------------------- match_markers
def _set(names) -> MarkerSet:
    n = len(names)
    return MarkerSet(tuple(names), np.arange(n), np.tile([1.0, 0, 0], (n, 1)), ("upper",) * n, ("face",) * n)


def test_match_by_name_in_any_order():
    markers = _set(["a", "b", "c"])
    np.testing.assert_array_equal(match_markers(["c", "a", "b"], markers), [1, 2, 0])


@pytest.mark.parametrize("style", ["{}", "X_{}", "x{}", "lm_{:02d}", "landmark {}"])
def test_openface_numbered_columns_match_by_landmark_number(style):
    markers = builtin_landmarks()
    order = np.random.default_rng(1).permutation(68)
    names = [style.format(int(i)) for i in order]
    index = match_markers(names, markers)
    assert [landmark_number(names[k]) for k in index] == list(range(68))


def test_missing_and_extra_markers_are_named():
    markers = _set(["lm_00", "lm_01", "nose"])
    with pytest.raises(InputError, match=r"missing from the file: 'nose'"):
        match_markers(["0", "1"], markers)
    np.testing.assert_array_equal(match_markers(["0", "1"], markers, allow_missing=True), [0, 1, -1])
    with pytest.raises(InputError, match=r"not in the marker set: 'chin'"):
        match_markers(["0", "1", "nose", "chin"], markers)
    np.testing.assert_array_equal(match_markers(["0", "chin", "1", "nose"], markers, ignore_extra=True), [0, 2, 3])
    with pytest.raises(InputError, match="both carry landmark number 1"):
        match_markers(["X_1", "x1", "nose", "0"], markers)
    with pytest.raises(InputError, match="twice"):
        match_markers(["nose", "nose"], markers)


def test_a_set_made_for_another_mesh_is_refused_even_where_its_indices_fit(tmp_path):
    """ict-68 names triangles of the 18460-triangle ICT face region: on a bigger mesh (the full-head OBJ) every
    index fits but points elsewhere, so the set's mesh fingerprint refuses it."""
    from livebridge.face.shipped import shipped_marker_set

    ict = shipped_marker_set("ict-68")
    assert ict.mesh_triangles == 18460
    ict.check_mesh(18460)
    with pytest.raises(InputError, match="made for a mesh of 18460 triangles; this mesh has 52000"):
        ict.check_mesh(52000)
    ict.save(tmp_path / "copy.toml")
    assert MarkerSet.load(tmp_path / "copy.toml").mesh_triangles == 18460
    assert ict.subset(ict.face_mask).mesh_triangles == 18460
    (tmp_path / "bad.toml").write_text((tmp_path / "copy.toml").read_text().replace("18460", "-3", 1))
    with pytest.raises(InputError, match="mesh_triangles"):
        MarkerSet.load(tmp_path / "bad.toml")
