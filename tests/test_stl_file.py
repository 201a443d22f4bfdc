"""Meshes from sculpting and printing tools (STL, binary and ASCII; PLY meshes) are read as the surfaces they hold:
STL's per-triangle corners welded into shared vertices, and a transfer onto such a head equals the transfer onto
the same head given as a basis."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from livebridge.cli import main
from livebridge.face.builtin import builtin_basis
from livebridge.retarget.landmarks import load_landmark_set
from livebridge.retarget.ply_file import write_ply
from livebridge.retarget.scan import read_scan

GRID = (40, 40)
_RECORD = np.dtype([("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attribute", "<u2")])


@pytest.fixture(scope="module")
def face():
    return builtin_basis()


def write_stl(path, vertices: np.ndarray, triangles: np.ndarray, binary: bool = True) -> None:
    """The mesh as an STL file, each triangle its own corners (as every STL writer does); a binary header that
    begins with 'solid', as some CAD tools write it."""
    corners = vertices[triangles].astype(np.float32)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    if binary:
        records = np.zeros(len(corners), _RECORD)
        records["normal"], records["corners"] = normals, corners
        path.write_bytes(b"solid exported by a CAD tool".ljust(80) + np.uint32(len(corners)).tobytes()
                         + records.tobytes())
        return
    lines = ["solid head"]
    for normal, corner in zip(normals, corners):
        lines += [f"  facet normal {normal[0]:.6e} {normal[1]:.6e} {normal[2]:.6e}", "    outer loop"]
        lines += [f"      vertex {x!r} {y!r} {z!r}" for x, y, z in corner.tolist()]
        lines += ["    endloop", "  endfacet"]
    path.write_text("\n".join(lines + ["endsolid head", ""]))


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "ascii"])
def test_stl_corners_weld_into_the_mesh_they_were_written_from(tmp_path, face, binary):
    write_stl(tmp_path / "head.stl", face.neutral, face.triangles, binary)
    scan = read_scan(tmp_path / "head.stl", 10.0)
    assert len(scan.triangles) == len(face.triangles)
    # each triangle's corners in order, at float32's precision (the file's)
    np.testing.assert_array_equal(scan.points[scan.triangles] / 10.0, face.neutral[face.triangles].astype(np.float32))
    # one vertex per place: the built-in face's closed mouth has its lips' vertices in the same places (27 pairs),
    # which no STL can keep apart
    places = np.unique(face.neutral[np.unique(face.triangles)].astype(np.float32), axis=0)
    assert len(scan.points) == len(places) == len(np.unique(face.triangles)) - 27
    # vertices numbered as they first appear in the file
    first = scan.triangles.reshape(-1)
    assert np.all(np.diff(np.maximum.accumulate(first)) <= 1) and first[0] == 0


def _place_and_retarget(runner, head, marks: dict, out):
    """``landmarks place`` on ``head`` (a mesh file in cm) from points, then ``retarget basis`` of the built-in
    basis onto it; the result."""
    from livebridge.face.basis import Basis

    points = head.with_suffix(".csv")
    points.write_text("".join(f"{name},{x / 10:.17g},{y / 10:.17g},{z / 10:.17g}\n"
                              for name, (x, y, z) in marks.items()))
    landmarks = head.with_suffix(".toml")
    placed = runner.invoke(main, ["landmarks", "place", str(head), "--points", str(points), "--units", "cm",
                                  "--out", str(landmarks)])
    assert placed.exit_code == 0, placed.output
    result = runner.invoke(main, ["retarget", "basis", "--source", "builtin", "--source-landmarks", "builtin-22",
                                  "--target", str(head), "--target-landmarks", str(landmarks), "--units", "cm",
                                  "--out", str(out)])
    assert result.exit_code == 0, result.output
    return Basis.load(out)


def _relative(elements: np.ndarray, truth: np.ndarray) -> np.ndarray:
    scale = np.sqrt(np.mean(np.sum(truth ** 2, axis=2), axis=1))
    return np.sqrt(np.mean(np.sum((elements - truth) ** 2, axis=2), axis=1)) / scale


def test_a_basis_retargets_onto_a_ply_mesh_as_onto_the_same_head(tmp_path, face):
    """The built-in face written in cm as PLY, its landmarks placed from points: the retargeted basis is the one
    retargeted onto the built-in face itself."""
    from livebridge.face.basis import Basis

    write_ply(tmp_path / "head.ply", face.neutral / 10.0, face.triangles)
    marks = load_landmark_set("builtin-22").as_dict(face.neutral, face.triangles)
    runner = CliRunner()
    on_file = _place_and_retarget(runner, tmp_path / "head.ply", marks, tmp_path / "file.npz")
    result = runner.invoke(main, ["retarget", "basis", "--source", "builtin", "--source-landmarks", "builtin-22",
                                  "--target", "builtin", "--target-landmarks", "builtin-22", "--out",
                                  str(tmp_path / "face.npz")])
    assert result.exit_code == 0, result.output
    on_face = Basis.load(tmp_path / "face.npz")
    np.testing.assert_allclose(on_file.neutral, on_face.neutral, atol=1e-5)  # mm: the float32 file's rounding
    assert _relative(on_file.elements, on_face.elements).max() < 1e-3


def test_a_basis_retargets_onto_an_stl_mesh_as_onto_its_welded_mesh(tmp_path, face):
    """The same head as binary STL and as the PLY of the mesh its corners weld into: the same retargeted basis."""
    write_stl(tmp_path / "head.stl", face.neutral / 10.0, face.triangles)
    welded = read_scan(tmp_path / "head.stl")
    write_ply(tmp_path / "welded.ply", welded.points, welded.triangles)
    marks = load_landmark_set("builtin-22").as_dict(face.neutral, face.triangles)
    runner = CliRunner()
    on_stl = _place_and_retarget(runner, tmp_path / "head.stl", marks, tmp_path / "stl.npz")
    on_ply = _place_and_retarget(runner, tmp_path / "welded.ply", marks, tmp_path / "ply.npz")
    assert on_stl.n_vertices == len(welded.points) < len(face.neutral)
    np.testing.assert_array_equal(on_stl.elements, on_ply.elements)


def test_a_point_cloud_is_refused_as_a_target_naming_it(tmp_path, face):
    write_ply(tmp_path / "cloud.ply", face.neutral)
    result = CliRunner().invoke(main, ["retarget", "basis", "--source", "builtin", "--source-landmarks",
                                       "builtin-22", "--target", str(tmp_path / "cloud.ply"), "--target-landmarks",
                                       "builtin-22", "--out", str(tmp_path / "out.npz")])
    assert result.exit_code != 0
    assert "cloud.ply" in result.output and "no faces" in result.output, result.output


def test_au_meshes_of_an_stl_head_are_written_in_its_units_as_obj_ply_or_stl(tmp_path, face):
    """AU12 on the built-in face given as STL in cm: written as STL, PLY or OBJ in cm, each the AU12 the built-in
    face itself gets (mm), at every vertex's place; an unknown suffix is refused before any work."""
    write_stl(tmp_path / "head.stl", face.neutral / 10.0, face.triangles)
    marks = load_landmark_set("builtin-22").as_dict(face.neutral, face.triangles)
    runner = CliRunner()
    _place_and_retarget(runner, tmp_path / "head.stl", marks, tmp_path / "unused.npz")
    common = ["retarget", "au", "--source", "builtin", "--source-landmarks", "builtin-22", "--au", "12"]
    on_face = runner.invoke(main, common + ["--target", "builtin", "--target-landmarks", "builtin-22", "--out",
                                            str(tmp_path / "face.obj")])
    assert on_face.exit_code == 0, on_face.output
    expected = read_scan(tmp_path / "face.obj")
    welded = read_scan(tmp_path / "head.stl").triangles.reshape(-1)
    _, first = np.unique(welded, return_index=True)
    original = face.triangles.reshape(-1)[first]  # the built-in face's vertex at each welded vertex's place
    for suffix in (".stl", ".ply", ".obj"):
        out = tmp_path / f"au12{suffix}"
        result = runner.invoke(main, common + ["--target", str(tmp_path / "head.stl"), "--target-landmarks",
                                               str(tmp_path / "head.toml"), "--units", "cm", "--out", str(out)])
        assert result.exit_code == 0 and "triangles, cm" in result.output, result.output
        written = read_scan(out, 10.0)
        assert len(written.points) == len(original)
        moved = expected.points[original]
        assert np.abs(moved - face.neutral[original]).max() > 5.0  # AU12 moves the mouth corners by mm
        np.testing.assert_allclose(written.points, moved, atol=0.01)  # mm: float32 and OBJ's 6 decimals
    refused = runner.invoke(main, common + ["--target", str(tmp_path / "head.stl"), "--target-landmarks",
                                            str(tmp_path / "head.toml"), "--units", "cm", "--out",
                                            str(tmp_path / "au12.txt")])
    assert refused.exit_code != 0 and "au12.txt" in refused.output and ".stl" in refused.output
    assert not (tmp_path / "au12.txt").exists()


def test_corners_at_minus_zero_weld_with_those_at_zero():
    from livebridge.retarget.stl_file import weld

    corners = np.array([[[0, 0, -0.0], [1, 0, 0], [0, 1, 0]], [[0, 0, 0], [0, 1, 0], [-1, 0, 0]]], np.float32)
    vertices, triangles = weld(corners)
    np.testing.assert_array_equal(vertices, [[0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0]])
    np.testing.assert_array_equal(triangles, [[0, 1, 2], [0, 2, 3]])


def test_stl_scans_build_the_basis_their_mesh_builds(tmp_path, face):
    """A neutral and a smile scanned as STL meshes (no colour): the same grid and element as the meshes
    themselves give (the STL's float32 corners aside)."""
    from livebridge.retarget.face_scan import prepare_expression, prepare_neutral
    from livebridge.retarget.scan import Scan
    from livebridge.retarget.scans import basis_from_scans
    from livebridge.retarget.stl_file import stl_bytes

    shapes = {"neutral": face.neutral, "smile": face.neutral + face.elements[face.index("zygomatic_major_L")]}
    marks = {name: load_landmark_set("builtin-22").as_dict(shape, face.triangles) for name, shape in shapes.items()}
    for name, shape in shapes.items():
        (tmp_path / f"{name}.stl").write_bytes(stl_bytes(shape, face.triangles))
    built = []
    for scans in ({name: Scan(shape, face.triangles) for name, shape in shapes.items()},
                  {name: read_scan(tmp_path / f"{name}.stl") for name in shapes}):
        neutral = prepare_neutral(scans["neutral"], marks["neutral"], marks["neutral"], shape=GRID)
        smiling = prepare_expression(scans["smile"], marks["smile"], neutral, "zygomatic_major_L")
        built.append((neutral, basis_from_scans(neutral, {"zygomatic_major_L": smiling})))
    (mesh_grid, from_mesh), (stl_grid, from_stl) = built
    np.testing.assert_array_equal(stl_grid.grid.valid, mesh_grid.grid.valid)
    motion = np.sqrt(np.mean(np.sum(from_mesh.elements[0] ** 2, axis=1)))
    assert motion > 0.5  # mm: the smile moves the grid
    difference = np.sqrt(np.mean(np.sum((from_stl.elements[0] - from_mesh.elements[0]) ** 2, axis=1)))
    print(f"STL against mesh: {difference:.2e} mm RMS of {motion:.2f}")
    assert difference < 0.01 * motion, (difference, motion)
