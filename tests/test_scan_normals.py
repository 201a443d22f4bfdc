"""A point cloud's normals: read from PLY and point lists, checked, and used to leave out the skin that faces away
from the front of the face (hidden from every frontal view), whichever way the file's normals point."""

from __future__ import annotations

import numpy as np
import pytest
from factories import run_retarget_scans

from livebridge.errors import InputError
from livebridge.face.builtin import builtin_basis
from livebridge.retarget.face_scan import prepare_neutral
from livebridge.retarget.landmarks import load_landmark_set
from livebridge.retarget.scan import Scan, read_scan

GRID = (60, 60)
POINTS = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]])
NORMALS = np.array([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0], [0.0, -1.0, 0.0]])


def _ply(encoding: str, names=("nx", "ny", "nz"), faces: bool = False) -> bytes:
    header = (f"ply\nformat {encoding} 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
              f"property uchar red\nproperty uchar green\nproperty uchar blue\n"
              + "".join(f"property float {name}\n" for name in names)
              + ("element face 1\nproperty list uchar int vertex_indices\n" if faces else "") + "end_header\n")
    rgb = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]])
    if encoding == "ascii":
        rows = "".join(" ".join(f"{v:g}" for v in [*p, *c, *n]) + "\n" for p, c, n in zip(POINTS, rgb, NORMALS))
        return (header + rows + ("3 0 1 2\n" if faces else "")).encode()
    order = "<" if encoding == "binary_little_endian" else ">"
    row = np.dtype([("p", order + "f4", 3), ("c", "u1", 3), ("n", order + "f4", 3)])
    table = np.zeros(3, row)
    table["p"], table["c"], table["n"] = POINTS, rgb, NORMALS
    face = (np.array([3], "u1").tobytes() + np.array([0, 1, 2], order + "i4").tobytes()) if faces else b""
    return header.encode() + table.tobytes() + face


@pytest.mark.parametrize("encoding", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_a_ply_cloud_s_normals_are_read_with_its_colours(tmp_path, encoding):
    path = tmp_path / "cloud.ply"
    path.write_bytes(_ply(encoding))
    scan = read_scan(path)
    np.testing.assert_allclose(scan.normals, NORMALS, atol=1e-7)
    np.testing.assert_allclose(scan.colours, np.eye(3))
    path.write_bytes(_ply(encoding, ("normal_x", "normal_y", "normal_z")))
    np.testing.assert_allclose(read_scan(path).normals, NORMALS, atol=1e-7)
    path.write_bytes(_ply(encoding, faces=True))
    assert read_scan(path).normals is None  # a mesh faces the way its triangles say


@pytest.mark.parametrize("text", [
    "x y z nx ny nz\n{p} {n}\n",
    "X,Y,Z,Nx,Ny,Nz\n{pc},{nc}\n",
    "//X,Y,Z,R,G,B,Nx,Ny,Nz\n{pc},255,0,0,{nc}\n",  # CloudCompare's header is a comment line
    "{p} {n}\n",
    "{p} 255 0 0 {n}\n",
    "{p} {n} 255 0 0\n",
])
def test_a_point_list_s_normals_are_read_with_or_without_a_header(tmp_path, text):
    lines = [text.split("\n", 1)[0]] if "{" not in text.split("\n", 1)[0] else []
    row = text.rsplit("\n", 2)[-2]
    for p, n in zip(POINTS, NORMALS):
        lines.append(row.format(p=" ".join(map(str, p)), n=" ".join(map(str, n)), pc=",".join(map(str, p)),
                                nc=",".join(map(str, n))))
    path = tmp_path / "cloud.xyz"
    path.write_text("\n".join(lines) + "\n")
    scan = read_scan(path)
    np.testing.assert_allclose(scan.points, POINTS)
    np.testing.assert_allclose(scan.normals, NORMALS)
    if "255" in text and not text.startswith("//"):
        assert scan.colours is None or np.allclose(scan.colours[:, 0], 1.0)


def test_columns_that_are_not_unit_length_are_not_taken_for_normals(tmp_path):
    path = tmp_path / "cloud.xyz"
    path.write_text("1 2 3 0.5 0.5 0.5\n4 5 6 0 0 1\n")
    assert read_scan(path).normals is None
    path.write_text("x y z nx ny nz\n1 2 3 0 0 2\n4 5 6 0 0 0\n")  # named: made unit, a zero row kept as unknown
    np.testing.assert_allclose(read_scan(path).normals, [[0, 0, 1], [0, 0, 0]])


def test_a_normal_that_is_not_finite_is_refused_naming_the_file_and_point(tmp_path):
    path = tmp_path / "cloud.csv"
    path.write_text("x,y,z,nx,ny,nz\n1,2,3,0,0,1\n4,5,6,nan,0,1\n")
    with pytest.raises(InputError, match=r"cloud\.csv.*point 1: normal"):
        read_scan(path)


@pytest.fixture(scope="module")
def clouds():
    """The built-in face scanned from the front with its normals, and a hidden sheet 4 mm behind its lower face
    facing into the head, as the inner side of a lip or the skin under a fold is: (front points, front normals,
    sheet points, sheet normals, landmarks)."""
    from livebridge.bench.scans import scan_surface

    basis = builtin_basis()
    landmarks = load_landmark_set("builtin-22").as_dict(basis.neutral, basis.triangles)
    rng = np.random.default_rng(5)
    points, _, normals = scan_surface(basis.neutral, basis.triangles, 40_000, 0.1, rng, normals=True)
    centre = 0.5 * (landmarks["mouth_corner_L"] + landmarks["nose_tip"])
    sheet = points[np.linalg.norm(points[:, :2] - centre[:2], axis=1) < 15.0] - [0.0, 0.0, 4.0]
    sheet_normals = np.tile([0.0, 0.0, -1.0], (len(sheet), 1))
    return points, normals, sheet, sheet_normals, landmarks


def _grid(points, normals, landmarks):
    face = prepare_neutral(Scan(points, np.zeros((0, 3)), normals=normals), landmarks, landmarks, shape=GRID)
    return face.grid, face.facing


def test_skin_facing_away_from_the_front_is_left_out_by_the_cloud_s_normals(clouds):
    points, normals, sheet, sheet_normals, landmarks = clouds
    front, said = _grid(points, normals, landmarks)
    assert said.orientation == "outward" and said.left_out < 0.01 * len(points)  # a frontal scan loses little
    both = np.vstack([points, sheet])
    cut, said = _grid(both, np.vstack([normals, sheet_normals]), landmarks)
    kept, _ = _grid(both, None, landmarks)
    assert said.orientation == "outward" and said.left_out >= len(sheet)
    valid = front.valid & cut.valid & kept.valid
    off_cut = np.abs(cut.heights - front.heights)[valid]
    off_kept = np.abs(kept.heights - front.heights)[valid]
    assert off_kept.max() > 1.0  # the sheet is within the resampling's own 10 mm cut, and mixed into the heights
    assert off_cut.max() < 0.05, off_cut.max()


def test_normals_into_the_face_are_turned_round_and_unoriented_ones_are_not_used(clouds):
    points, normals, sheet, sheet_normals, landmarks = clouds
    both, outward = np.vstack([points, sheet]), np.vstack([normals, sheet_normals])
    out_grid, _ = _grid(both, outward, landmarks)
    in_grid, said = _grid(both, -outward, landmarks)
    assert said.orientation == "inward"
    np.testing.assert_array_equal(in_grid.heights, out_grid.heights)
    signs = np.where(np.random.default_rng(1).random(len(both)) < 0.5, -1.0, 1.0)[:, None]
    either, said = _grid(both, signs * outward, landmarks)
    kept, _ = _grid(both, None, landmarks)
    assert said.orientation == "unoriented" and said.left_out == 0
    np.testing.assert_array_equal(either.heights, kept.heights)
    zeros, said = _grid(both, np.zeros_like(outward), landmarks)  # placeholders some writers put: no normals
    assert said.orientation == "" and said.left_out == 0
    np.testing.assert_array_equal(zeros.heights, kept.heights)


def test_retarget_scans_tells_what_each_cloud_s_normals_did(tmp_path):
    """A neutral cloud with normals out of the face, an expression's into it and another's either way: the build
    says what it left out, that it turned the second's round, and that it did not use the third's."""
    from livebridge.bench.scans import synthetic_scans

    basis = builtin_basis()
    neutral, expressions = synthetic_scans(basis, load_landmark_set("builtin-22"), np.random.default_rng(3),
                                           n_points=8000, hole_muscle=None, colour=False,
                                           muscles=("jaw", "frontalis_L"), whole=True, normals=True)
    signs = {"neutral": 1.0, "jaw": -1.0,
             "frontalis_L": np.where(np.random.default_rng(2).random(len(expressions["frontalis_L"].points)) < 0.5,
                                     -1.0, 1.0)[:, None]}
    for name, scan in [("neutral", neutral), *expressions.items()]:
        normals = signs[name] * scan.normals
        (tmp_path / f"{name}.xyz").write_text("x y z nx ny nz\n" + "".join(
            " ".join(f"{v:.6f}" for v in row) + "\n" for row in np.hstack([scan.points, normals])))
        (tmp_path / f"{name}.landmarks.csv").write_text("name,x,y,z\n" + "".join(
            f"{k},{x:.6f},{y:.6f},{z:.6f}\n" for k, (x, y, z) in scan.landmarks.items()))
    result = run_retarget_scans(tmp_path, "neutral.xyz", {"jaw": "jaw.xyz", "frontalis_L": "frontalis_L.xyz"},
                                out="b.npz")
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    neutral_line = next(line for line in lines if "neutral.xyz face away" in line)
    assert int(neutral_line.split()[1]) > 0.1 * len(neutral.points)  # the sides and under the nose and chin
    assert any("jaw.xyz" in line and "turned round" in line for line in lines), lines
    assert any("frontalis_L.xyz's normals point both ways" in line for line in lines), lines
    assert (tmp_path / "b.npz").exists()
