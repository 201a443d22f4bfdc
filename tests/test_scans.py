"""Scans: readers against the bytes they wrote, resampling against an analytic surface, normalisation and
registration against known transforms, and a basis from simulated ICT scans against the ICT elements."""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest
from click.testing import CliRunner
from factories import assert_cli_refused, interior_holes, write_builtin_scans

from livebridge.bench.scans import ERROR_LIMIT, build_and_measure, synthetic_scans
from livebridge.errors import InputError
from livebridge.geometry.transforms import apply
from livebridge.retarget.grid import crop_sphere, resample, square_axes
from livebridge.retarget.normalise import NORMALISATION_LANDMARKS, normalisation, register_rigid
from livebridge.retarget.ply_file import write_ply
from livebridge.retarget.scan import read_scan


# ------------------------------------------------------------------------------------------------ reading
@pytest.mark.parametrize("encoding", ["ascii", "binary_little_endian", "binary_big_endian"])
@pytest.mark.parametrize("with_faces", [True, False])
def test_ply_round_trip(tmp_path, rng, encoding, with_faces):
    points = rng.normal(0, 50, (200, 3))
    triangles = rng.integers(0, 200, (300, 3)) if with_faces else None
    write_ply(tmp_path / "s.ply", points, triangles, encoding)
    scan = read_scan(tmp_path / "s.ply", scale=10.0)
    np.testing.assert_allclose(scan.points, 10 * points.astype(np.float32), rtol=1e-6, atol=1e-5)  # ascii: 6 decimals
    assert scan.is_mesh == with_faces
    if with_faces:
        np.testing.assert_array_equal(scan.triangles, triangles)


def test_a_binary_ply_s_signalling_nan_is_refused_without_a_warning(tmp_path, rng):
    """A float32 signalling NaN (a damaged binary file) warned "invalid value encountered in cast" on the way to the
    error; the error alone names the file and the point."""
    import warnings

    write_ply(tmp_path / "s.ply", rng.normal(0, 50, (20, 3)), None, "binary_little_endian")
    data = bytearray((tmp_path / "s.ply").read_bytes())
    start = data.index(b"end_header\n") + len(b"end_header\n")
    data[start + 5 * 12:start + 5 * 12 + 4] = (0x7FA00000).to_bytes(4, "little")  # point 5's x
    (tmp_path / "s.ply").write_bytes(bytes(data))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match="vertex 5 is not finite") as caught:
            read_scan(tmp_path / "s.ply")
    assert "s.ply" in str(caught.value)


def test_ply_with_quads_colours_and_extra_elements(tmp_path):
    header = ("ply\nformat binary_big_endian 1.0\ncomment made by a scanner\nelement vertex 5\nproperty double x\n"
              "property double y\nproperty double z\nproperty uchar red\nelement face 2\n"
              "property list uchar uint vertex_indices\nelement edge 1\nproperty int vertex1\nproperty int vertex2\n"
              "end_header\n")
    vertices = np.zeros(5, np.dtype([("p", ">f8", 3), ("r", "u1")]))
    vertices["p"] = np.arange(15).reshape(5, 3)
    quad = b"\x04" + np.array([0, 1, 2, 3], ">u4").tobytes()
    tri = b"\x03" + np.array([2, 3, 4], ">u4").tobytes()
    (tmp_path / "q.ply").write_bytes(header.encode() + vertices.tobytes() + quad + tri + np.array([0, 1], ">i4")
                                     .tobytes())
    scan = read_scan(tmp_path / "q.ply")
    np.testing.assert_array_equal(scan.points, np.arange(15).reshape(5, 3))
    np.testing.assert_array_equal(scan.triangles, [[0, 1, 2], [0, 2, 3], [2, 3, 4]])


@pytest.mark.parametrize("faces,expected", [
    ("3 0 1 2\n3 2 3 4\n", [[0, 1, 2], [2, 3, 4]]),  # one length: read at once
    ("4 0 1 2 3\n3 2 3 4\n", [[0, 1, 2], [0, 2, 3], [2, 3, 4]]),  # mixed: row by row
    ("3 0 1 2\n\n3 2 3 4\n", [[0, 1, 2], [2, 3, 4]]),  # a blank line: row by row
])
def test_ascii_ply_reads_the_same_at_once_or_row_by_row(tmp_path, faces, expected):
    header = ("ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nelement face {}\n"
              "property list uchar int vertex_indices\nend_header\n")
    rows = "".join(f"{k} {2 * k} {3 * k} {10 * k} 0 255\n" for k in range(5))
    (tmp_path / "a.ply").write_text(header.format(len(expected) if "4 0" not in faces else 2) + rows + faces)
    scan = read_scan(tmp_path / "a.ply")
    np.testing.assert_array_equal(scan.points, np.arange(5)[:, None] * [1, 2, 3])
    np.testing.assert_allclose(scan.colours, np.column_stack([10 * np.arange(5), np.zeros(5), np.full(5, 255)]) / 255)
    np.testing.assert_array_equal(scan.triangles, expected)
    (tmp_path / "b.ply").write_text(header.format(2) + rows + "3 0 1 2\n3 2 3 4.5\n")  # no whole number
    with pytest.raises(InputError, match=r"line 19 \(face 1\)"):
        read_scan(tmp_path / "b.ply")


def test_obj_and_text_point_lists(tmp_path):
    (tmp_path / "s.obj").write_text("# scan\nv 0 0 0 255 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\n"
                                    "f 1/1 2/1 3/1 4/1\nf -1 -2 -3\n")
    scan = read_scan(tmp_path / "s.obj")
    np.testing.assert_array_equal(scan.triangles, [[0, 1, 2], [0, 2, 3], [3, 2, 1]])
    (tmp_path / "s.csv").write_text("# exported\nnx;X;Y;Z\n9;1;2;3\n9;4;5;6\n")
    np.testing.assert_array_equal(read_scan(tmp_path / "s.csv").points, [[1, 2, 3], [4, 5, 6]])
    (tmp_path / "s.xyz").write_text("1 2 3 0.1 0.2 0.3\n\n4\t5\t6 0 0 1\n")
    np.testing.assert_array_equal(read_scan(tmp_path / "s.xyz").points, [[1, 2, 3], [4, 5, 6]])


@pytest.mark.parametrize("encoding", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_colours_round_trip(tmp_path, rng, encoding):
    points, colours = rng.normal(0, 50, (100, 3)), rng.random((100, 3))
    write_ply(tmp_path / "c.ply", points, None, encoding, colours)
    scan = read_scan(tmp_path / "c.ply")
    assert scan.has_colour
    np.testing.assert_allclose(scan.colours, colours, atol=0.5 / 255 + 1e-9)  # stored as uchar


@pytest.mark.parametrize("names,dtype,scale", [(("red", "green", "blue"), "<f4", 1.0),
                                               (("diffuse_red", "diffuse_green", "diffuse_blue"), "<u2", 65535.0)])
def test_ply_float_and_diffuse_colours(tmp_path, rng, names, dtype, scale):
    kind = "float" if dtype == "<f4" else "ushort"
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 20\nproperty float x\nproperty float y\n"
              "property float z\n" + "".join(f"property {kind} {n}\n" for n in names) + "end_header\n")
    table = np.zeros(20, np.dtype([("p", "<f4", 3), ("c", dtype, 3)]))
    colours = rng.random((20, 3))
    table["p"], table["c"] = rng.normal(size=(20, 3)), colours * scale
    (tmp_path / "f.ply").write_bytes(header.encode() + table.tobytes())
    np.testing.assert_allclose(read_scan(tmp_path / "f.ply").colours, table["c"] / scale, rtol=1e-6)


def test_obj_and_text_colours(tmp_path):
    (tmp_path / "c.obj").write_text("v 0 0 0 1 0 0.5\nv 1 0 0 0 1 0\nv 0 1 0 0 0 1\nf 1 2 3\n")
    np.testing.assert_allclose(read_scan(tmp_path / "c.obj").colours, [[1, 0, 0.5], [0, 1, 0], [0, 0, 1]])
    (tmp_path / "plain.obj").write_text("v 0 0 0\nv 1 0 0 0 1 0\nv 0 1 0\n")  # not every vertex: no colour
    assert not read_scan(tmp_path / "plain.obj").has_colour
    (tmp_path / "c.xyz").write_text("1 2 3 255 0 51\n4 5 6 0 255 0\n")  # no header: whole numbers 0-255
    np.testing.assert_allclose(read_scan(tmp_path / "c.xyz").colours, [[1, 0, 0.2], [0, 1, 0]])
    (tmp_path / "c.csv").write_text("X,Y,Z,Red,Green,Blue,intensity\n1,2,3,0.5,0.25,1,9\n")
    np.testing.assert_allclose(read_scan(tmp_path / "c.csv").colours, [[0.5, 0.25, 1]])
    (tmp_path / "n.xyz").write_text("1 2 3 0 0 1\n4 5 6 0.6 0 0.8\n")  # normals, not colour
    assert not read_scan(tmp_path / "n.xyz").has_colour


def test_colour_out_of_range_is_refused(tmp_path):
    from livebridge.errors import InputError

    (tmp_path / "bad.csv").write_text("x,y,z,r,g,b\n1,2,3,0.5,-0.2,1\n")
    with pytest.raises(InputError, match="colour"):
        read_scan(tmp_path / "bad.csv")


# ------------------------------------------------------------------------------------------------ resampling
def _dome(rng, n=20_000, radius=60.0, hole=None):
    """Points of the cap z = sqrt(R^2 - x^2 - y^2) - R over |(x, y)| < radius (R = 100), optional hole."""
    xy = rng.uniform(-radius, radius, (n, 2))
    xy = xy[np.linalg.norm(xy, axis=1) < radius]
    if hole is not None:
        xy = xy[np.linalg.norm(xy - hole[0], axis=1) > hole[1]]
    return np.column_stack([xy, np.sqrt(100.0 ** 2 - (xy ** 2).sum(axis=1)) - 100.0])


def test_resampling_follows_the_surface_and_masks_a_hole(rng):
    hole = (np.array([20.0, -10.0]), 8.0)
    x, y = square_axes(70.0, (120, 100))
    grid = resample(_dome(rng, hole=hole), x, y)
    vertices = grid.vertices
    truth = np.sqrt(100.0 ** 2 - (vertices[:, :2] ** 2).sum(axis=1)) - 100.0
    error = np.abs(vertices[:, 2] - truth)  # linear interpolation of a curved surface: the chord error
    assert np.median(error) < 0.01 and error.max() < 0.15
    from_hole = np.linalg.norm(vertices[:, :2] - hole[0], axis=1)
    assert from_hole.min() > hole[1] - 2.5  # nothing invented inside the hole (up to the gap allowance)
    xx, yy = np.meshgrid(x, y)
    inside = (np.hypot(xx, yy) < 55) & (np.hypot(xx - hole[0][0], yy - hole[0][1]) > hole[1] + 3)
    assert grid.valid[inside].all()  # everywhere else on the scan: a vertex
    assert not grid.valid[np.hypot(xx, yy) > 63].any()
    corners = vertices[grid.triangles]
    normal_z = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])[:, 2]
    assert (normal_z > 0).all()
    assert grid.uv.min() >= 0 and grid.uv.max() <= 1 and len(grid.uv) == len(vertices)


def test_a_grid_point_between_random_points_is_no_hole_but_a_scan_s_hole_is(rng):
    """Points about 0.44 mm apart, denser on one side (a scanner's density changes over a face) around an 8 mm
    hole: with the gap alone (3 spacings, here one 1.49 mm cell) some grid points fell where no point did; with
    the holes seeded (as a face scan's grid is resampled) only the scan's hole is one, and just as far out."""
    xy = rng.uniform(-40.0, 40.0, (20_000, 2))
    xy = xy[rng.uniform(0.0, 1.0, len(xy)) < 0.25 + 0.2 * (xy[:, 0] + 40.0) / 80.0]
    xy = xy[np.hypot(xy[:, 0] - 10.0, xy[:, 1] - 5.0) > 8.0]
    points = np.column_stack([xy, -0.01 * (xy ** 2).sum(axis=1)])
    x = y = np.linspace(-35.0, 35.0, 48)
    speckled = interior_holes(resample(points, x, y))
    seeded = interior_holes(resample(points, x, y, seeded_holes=True))
    xx, yy = np.meshgrid(x, y)
    hole = speckled.ravel()[np.argmin(np.hypot(xx - 10.0, yy - 5.0))]
    assert len(np.unique(speckled)) > 2  # the speckle (and the hole)
    assert np.array_equal(seeded > 0, speckled == hole)


def test_two_scans_of_one_skin_make_the_same_skin_image(rng):
    """Two random samplings of one skin pattern (30k points over 76 mm, 0.01 colour noise) resampled onto the
    0.5 mm skin image: each lies close to the pattern and to the other (measured 0.024 and 0.022 RMS, the
    pattern's own spread 0.25); an average of the points by distance measured 0.040 and 0.052 (see grid.py)."""
    texture = _texture(rng, 0.8)
    _, _, fine_x, fine_y = _skin_axes()
    xx, yy = np.meshgrid(fine_x, fine_y)
    inner = (np.abs(xx) < 34) & (np.abs(yy) < 34)
    pattern = texture(np.column_stack([yy[inner], xx[inner]]))

    def skin_image():
        skin = rng.uniform(-38, 38, (30_000, 2))
        grey = texture(skin[:, ::-1]) + rng.normal(0, 0.01, len(skin))
        points = np.column_stack([skin, rng.normal(0, 0.1, len(skin))])
        return resample(points, fine_x, fine_y, colours=np.repeat(grey[:, None], 3, axis=1)).colours[inner][:, 0]

    first, second = skin_image(), skin_image()
    assert np.isfinite(first).mean() > 0.99 and np.isfinite(second).mean() > 0.99
    assert np.sqrt(np.nanmean((first - pattern) ** 2)) < 0.03
    assert np.sqrt(np.nanmean((first - second) ** 2)) < 0.03


def test_resampling_keeps_the_front_surface(rng):
    front = _dome(rng)
    behind = front - [0, 0, 40.0]  # e.g. the back of a head seen through the face
    x, y = square_axes(70.0, (60, 60))
    grid = resample(np.vstack([front, behind]), x, y)
    truth = np.sqrt(100.0 ** 2 - (grid.vertices[:, :2] ** 2).sum(axis=1)) - 100.0
    assert np.abs(grid.vertices[:, 2] - truth).max() < 0.1


def test_flying_points_are_found_on_the_steep_sides_too(rng):
    """2 % of a dome's points (its sides as steep as a face's outline) thrown 3-20 mm along the view either way:
    nearly all are found, nearly no point of the surface is."""
    from livebridge.retarget.grid import spikes

    points = _dome(rng, n=30_000, radius=97.0)  # slopes up to 4
    points[:, 2] += rng.normal(0.0, 0.1, len(points))
    stray = rng.random(len(points)) < 0.02
    thrown = points.copy()
    thrown[stray, 2] += rng.choice([-1.0, 1.0], stray.sum()) * rng.uniform(3.0, 20.0, stray.sum())
    found = spikes(thrown)
    assert (found & stray).sum() > 0.95 * stray.sum(), ((found & stray).sum(), stray.sum())
    assert (found & ~stray).sum() < 0.002 * (~stray).sum()
    assert not spikes(points).any()


def test_the_resampling_s_barycentric_transforms_are_scipy_s(rng):
    """The interpolation's triangles and weights are those of scipy's own point location, degenerate
    (collinear) triangles of a grid-aligned point set included."""
    from scipy.spatial import Delaunay

    from livebridge.retarget.grid import _linear, barycentric_transforms

    points = np.vstack([rng.uniform(-50, 50, (3000, 2)), np.stack(np.meshgrid(np.arange(5.0), [0.0, 1e-13, 1.0]),
                                                                   axis=-1).reshape(-1, 2)])
    triangulation = Delaunay(points, qhull_options="QJ")  # joggled: flat triangles are kept
    ours = barycentric_transforms(triangulation.points, triangulation.simplices)
    theirs = triangulation.transform
    assert np.isnan(theirs).any() and np.array_equal(np.isnan(ours), np.isnan(theirs))
    assert np.nanmax(np.abs(ours - theirs) / np.maximum(1.0, np.abs(theirs))) < 1e-9
    values, queries = rng.normal(size=(len(points), 2)), rng.uniform(-60, 60, (2000, 2))
    from scipy.interpolate import griddata

    assert np.allclose(_linear(points, values, queries), griddata(points, values, queries), equal_nan=True)


# ------------------------------------------------------------------------------------------------ normalising
def _landmarks(rng):
    names = NORMALISATION_LANDMARKS + ("eye_inner_L", "eye_inner_R", "nose_saddle_L", "nose_saddle_R")
    base = {"eye_outer_L": [45, 35, -45], "eye_outer_R": [-45, 35, -45], "chin": [0, -80, -25],
            "nose_tip": [0, 0, 0], "eye_inner_L": [18, 32, -38], "eye_inner_R": [-18, 32, -38],
            "nose_saddle_L": [9, 29, -27], "nose_saddle_R": [-9, 29, -27]}
    return {name: np.array(base[name], float) + rng.normal(0, 2, 3) for name in names}


def test_thesis_affine_puts_the_four_landmarks_on_the_reference(rng):
    reference, scan = _landmarks(rng), _landmarks(rng)
    pose = np.eye(4)
    pose[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0] * 1.3
    pose[:3, 3] = [5, -40, 300]
    moved = {name: apply(pose, p[None])[0] for name, p in scan.items()}
    scan2face = normalisation(moved, reference, "affine")
    for name in NORMALISATION_LANDMARKS:
        np.testing.assert_allclose(apply(scan2face, moved[name][None])[0], reference[name] - reference["nose_tip"],
                                   atol=1e-9)


def test_rigid_normalisation_undoes_a_head_pose(rng):
    reference = _landmarks(rng)
    pose = np.eye(4)
    pose[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    if np.linalg.det(pose[:3, :3]) < 0:
        pose[:3, :3] *= -1
    pose[:3, 3] = [100, 20, -30]
    moved = {name: apply(pose, p[None])[0] for name, p in reference.items()}
    expected = np.eye(4)
    expected[:3, 3] = -reference["nose_tip"]  # the normalised nose tip is the origin
    np.testing.assert_allclose(normalisation(moved, reference, "rigid") @ pose, expected, atol=1e-9)


def _face_like(rng, n=30_000):
    """The dome with a nose and a brow ridge: no rotation slides it onto itself."""
    points = _dome(rng, n=n, radius=80.0)
    x, y = points[:, 0], points[:, 1]
    points[:, 2] += 25 * np.exp(-(x / 12) ** 2 - ((y + 10) / 25) ** 2) + 8 * np.exp(-((y - 35) / 8) ** 2)
    return points


def test_registration_ignores_the_part_that_moved(rng):
    from livebridge.face.meshio import vertex_normals

    grid = resample(_face_like(rng), *square_axes(85.0, (120, 120)))
    face, normals = grid.vertices, vertex_normals(grid.vertices, grid.triangles)
    expression = _face_like(rng)
    lower = expression[:, 1] < -30
    expression[lower, 2] += 6.0 * np.exp(-((expression[lower, 1] + 60) / 15) ** 2)  # a "jaw" bulge
    pose = np.eye(4)
    pose[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)) * 0.02 + np.eye(3))[0]
    pose[:3, :3] *= np.sign(np.diag(pose[:3, :3]))  # a small rotation, not a reflection
    pose[:3, 3] = [3, -2, 4]
    landmarks = _landmarks(rng)
    scan_landmarks = {name: apply(pose, p[None])[0] + rng.normal(0, 0.5, 3) for name, p in landmarks.items()}
    found = register_rigid(apply(pose, expression), scan_landmarks, face, normals, landmarks, 90.0)
    error = apply(found @ pose, face) - face
    assert np.linalg.norm(error, axis=1).max() < 0.3


def test_crop_sphere(rng):
    points = rng.normal(0, 50, (1000, 3))
    kept = crop_sphere(points, np.array([10.0, 0, 0]), 40.0)
    np.testing.assert_array_equal(kept, np.linalg.norm(points - [10, 0, 0], axis=1) <= 40)


# ------------------------------------------------------------------------------------------------ skin tracking
def _skin_axes() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The grid lines (x, y) of a 41x41 grid over 60 mm and the skin image's finer lines (fine x, fine y)
    reaching 4 cells beyond it, as :func:`~livebridge.retarget.face_scan.prepare_neutral` lays them out."""
    from livebridge.retarget.skin_flow import fine_axes

    x, y = square_axes(30.0, (41, 41))
    margin = 4
    step = x[1] - x[0]
    wide = np.linspace(-30 - margin * step, 30 + margin * step, 41 + 2 * margin)
    fine_x, fine_y, _ = fine_axes(wide, wide)
    return x, y, fine_x, fine_y


def _texture(rng, blur_mm: float = 0.8):
    """A skin pattern over [-42, 42]^2 mm: grey values about 0.5 (a quarter of their spread each way) of white
    noise on 0.25 mm texels blurred by ``blur_mm``, as a function of (y, x) points (n, 2)."""
    import cv2
    from scipy.interpolate import RegularGridInterpolator

    texel = 0.25
    axis = np.arange(-42, 42 + texel, texel)
    noise = cv2.GaussianBlur(rng.normal(size=(len(axis), len(axis))).astype(np.float32), (0, 0), blur_mm / texel)
    return RegularGridInterpolator((axis, axis), 0.5 + noise / (4 * noise.std()))



def _slid_scan(rng, texture, shift=None, n: int = 12_000) -> tuple[np.ndarray, np.ndarray]:
    """A sparse scan (``n`` points, 0.1 mm noise; colours: ``texture`` with 0.03 noise, grey) of a gently curved
    surface whose skin is moved by ``shift`` (a function of the neutral skin's x-y (n, 2) to its offset (n, 2); None:
    the neutral): (points (n, 3), colours (n, 3)). Each scan resolves the fine pattern its own way."""
    skin = rng.uniform(-38, 38, (n, 2))
    at = skin if shift is None else skin + shift(skin)
    grey = texture(skin[:, ::-1]) + rng.normal(0, 0.03, n)
    points = np.column_stack([at, 10 * np.exp(-(at ** 2).sum(axis=1) / 40.0 ** 2)]) + rng.normal(0, 0.1, (n, 3))
    return points, np.repeat(grey[:, None], 3, axis=1)

def _tracked_slide(rng, peak_mm: float, width_mm: float = 12.0, blur_mm: float = 0.8) -> tuple[float, float]:
    """A textured (:func:`_texture` of ``blur_mm``), gently curved surface whose skin slides by a known smooth
    field ``d`` (``peak_mm`` at its peak, Gaussian of ``width_mm``) in an expression scan with other sampling
    and noise, tracked from a zero first guess: (the tracked motion's RMS error relative to ``d``'s RMS, the
    mean trust)."""

    from livebridge.retarget.skin_flow import pixels_of, skin_motion

    texture = _texture(rng, blur_mm)

    def surface(xy):
        return np.column_stack([xy, 20 * np.exp(-(xy ** 2).sum(axis=1) / 40.0 ** 2)])

    def slide(xy):
        bump = np.exp(-((xy - [5.0, -5.0]) ** 2).sum(axis=1) / width_mm ** 2)
        return peak_mm * bump[:, None] * np.array([[0.8, 0.6]])

    def scan(moved: bool):
        skin = rng.uniform(-38, 38, (30_000, 2))  # where each point's skin is on the neutral
        at = skin + slide(skin) if moved else skin
        grey = texture(np.clip(skin[:, ::-1], -42, 42)) + rng.normal(0, 0.01, len(skin))
        return surface(at) + rng.normal(0, 0.1, (len(skin), 3)), np.repeat(grey[:, None], 3, axis=1)

    x, y, fine_x, fine_y = _skin_axes()
    (neutral_points, neutral_colours), (points, colours) = scan(False), scan(True)
    neutral = resample(neutral_points, x, y)
    neutral_skin = resample(neutral_points, fine_x, fine_y, colours=neutral_colours)
    motion, trust = skin_motion(neutral_skin, resample(points, fine_x, fine_y, colours=colours),
                                pixels_of(neutral_skin, neutral.vertices[:, :2]), np.zeros((len(neutral.vertices), 3)))
    truth = slide(neutral.vertices[:, :2])  # the neutral skin at each vertex moves by d
    error = np.linalg.norm(motion[:, :2] - truth, axis=1)
    return float(np.sqrt(np.mean(error ** 2) / np.mean((truth ** 2).sum(axis=1)))), float(trust.mean())


def test_skin_tracking_recovers_a_known_slide_of_the_skin(rng):
    """A 3 mm slide is tracked from a zero first guess (measured 0.074 of its RMS)."""
    relative, trust = _tracked_slide(rng, 3.0)
    assert trust > 0.9
    assert relative < 0.1, relative


def test_skin_tracking_reaches_a_slide_far_from_the_first_guess(rng, monkeypatch):
    """A 12 mm slide of a 20 mm wide patch from a zero first guess (a landmark warp extrapolated to the
    face's outline is that far off): the coarse flow before the full-resolution passes brings it within their
    reach (measured 0.060 of its RMS; 0.218 with a third full-resolution pass in its place)."""
    from livebridge.retarget import skin_flow

    with_coarse, _ = _tracked_slide(np.random.default_rng(5), 12.0, 20.0)
    monkeypatch.setattr(skin_flow, "COARSE_FACTOR", 1)
    without, _ = _tracked_slide(np.random.default_rng(5), 12.0, 20.0)
    assert with_coarse < 0.1, with_coarse
    assert with_coarse < 0.5 * without, (with_coarse, without)


def test_coarse_flow_sees_the_pattern_its_own_pixels_resolve(monkeypatch):
    """The coarse flow's images are contrast-normalised over COARSE_FACTOR times CONTRAST_MM: on blotchy skin
    (3 mm blotches) a 12 mm slide is tracked closer than with the coarse images normalised at the
    full-resolution width (measured 0.226 against 0.237 summed relative error over four draws)."""
    from livebridge.retarget import skin_flow

    def summed():
        return sum(_tracked_slide(np.random.default_rng(seed), 12.0, 20.0, 3.0)[0] for seed in range(4))

    scaled = summed()
    full_width = skin_flow.skin_image
    monkeypatch.setattr(skin_flow, "skin_image", lambda grid, contrast_mm=None: full_width(grid))
    assert scaled < 0.4, scaled
    assert scaled < 0.97 * summed(), scaled


def _raw_flow_error(rng) -> float:
    """RMS error (mm) of the flow itself (track_skin, no smoothing) on trusted skin of a blotchy pattern
    with little fine detail (3 mm blotches, per-point colour noise of 0.05: like a 60k-point face scan's
    skin, where the flow is noise-limited) sliding by a known 3 mm bump, two independent samplings."""
    from livebridge.retarget.skin_flow import track_skin

    texture = _texture(rng, 3.0)

    def slide(xy):
        return 3.0 * np.exp(-((xy - [5.0, -5.0]) ** 2).sum(axis=1) / 12.0 ** 2)[:, None] * np.array([[0.8, 0.6]])

    def skin_image(moved: bool):
        skin = rng.uniform(-38, 38, (30_000, 2))
        at = skin + slide(skin) if moved else skin
        grey = texture(skin[:, ::-1]) + rng.normal(0, 0.05, len(skin))
        points = np.column_stack([at, 20 * np.exp(-(at ** 2).sum(axis=1) / 40.0 ** 2)])
        points = points + rng.normal(0, 0.1, points.shape)
        return resample(points, fine_x, fine_y, colours=np.repeat(grey[:, None], 3, axis=1))

    _, _, fine_x, fine_y = _skin_axes()
    neutral, expression = skin_image(False), skin_image(True)
    xy, trust = track_skin(neutral, expression, np.zeros(neutral.shape + (2,)))
    rows, cols = np.indices(neutral.shape)
    truth = slide(np.column_stack([fine_x[cols.ravel()], fine_y[rows.ravel()]])).reshape(xy.shape)
    inner = np.zeros(neutral.shape, dtype=bool)
    inner[20:-20, 20:-20] = True  # away from the images' rims
    error = np.linalg.norm(xy - truth, axis=2)[inner & (trust > 0.9)]
    return float(np.sqrt(np.mean(error ** 2)))


def test_flow_refinement_settles_the_flow_on_weakly_patterned_skin(monkeypatch):
    """DIS's variational refinement run to REFINEMENT_ITERATIONS a level settles the dense flow between the
    patches' estimates: the flow's own error on blotchy, noisy skin is lower than with the MEDIUM preset's
    5 iterations (measured 0.273 / 0.237 mm against 0.286 / 0.254 mm on two draws; a third 0.271 / 0.274)."""
    from livebridge.retarget import skin_flow

    refined = [_raw_flow_error(np.random.default_rng(seed)) for seed in (0, 1)]
    monkeypatch.setattr(skin_flow, "REFINEMENT_ITERATIONS", 5)
    preset = [_raw_flow_error(np.random.default_rng(seed)) for seed in (0, 1)]
    assert max(refined) < 0.3, refined
    assert sum(refined) < 0.97 * sum(preset), (refined, preset)


def test_points_behind_the_front_surface_are_found_on_a_steep_face():
    """Speckle 20 mm behind a flat front (another surface seen through gaps, at 40 % of the points of a patch)
    is found; the points of the flat skin and of skin curving away down to a slope of 15 (the face's side at
    its outline) are not."""
    from livebridge.retarget.skin_flow import behind_front

    step = 0.4
    rows, cols = np.indices((120, 120))
    out = np.maximum(cols - 60, 0) * step  # mm past the flat part: the slope grows to 15 at the image's edge
    heights = -15.0 * out ** 2 / (2 * 54 * step)
    speckle = (np.random.default_rng(3).random(heights.shape) < 0.4) & (np.abs(rows - 60) < 15) & (cols < 40)
    heights = np.where(speckle, heights - 20.0, heights)
    heights[:, 115:] = np.nan
    found = behind_front(heights, step)
    assert found[speckle].mean() > 0.9
    assert not found[~speckle].any()


def test_skin_images_leave_out_points_seen_past_the_skin(rng):
    """A front surface (flat, then curving away to a slope of 5) with a nostril-like gap, and a surface 7 mm
    behind it (nearer than the resampling's own occlusion test reaches): all of the back one's points in the
    gap, and 3 % of them everywhere else (hidden points a scanner's occlusion test let through), with their
    own colour. The back's points outside the gap on the flat skin are left out of the skin image (on the
    slope 7 mm is within what the front itself falls), the front's kept (the steep ones too, but for the odd
    noisy one), and the image there is the front's colour again; the gap's inside stays (it is all there is
    to see)."""
    from livebridge.retarget.skin_flow import fine_axes, in_front

    def surface(xy):
        out = np.maximum(xy[:, 0] - 5.0, 0.0)
        return -5.0 * out ** 2 / (2 * 15.0)  # slope 5 at x = 20

    n = 40_000
    front = rng.uniform(-20, 20, (n, 2))
    gap = np.linalg.norm(front - [-8.0, 0.0], axis=1) < 3.0
    front = front[~gap]
    back = rng.uniform(-20, 20, (n, 2))
    in_gap = np.linalg.norm(back - [-8.0, 0.0], axis=1) < 3.0
    back = back[in_gap | (rng.random(n) < 0.03)]
    points = np.vstack([np.column_stack([front, surface(front)]), np.column_stack([back, surface(back) - 7.0])])
    points += rng.normal(0.0, 0.2, points.shape)
    colours = np.vstack([np.full((len(front), 3), 0.8), np.full((len(back), 3), 0.2)])
    x, y, _ = fine_axes(np.linspace(-18, 18, 19), np.linspace(-18, 18, 19))
    image = resample(points, x, y, colours=colours)
    kept = in_front(image, points)
    is_back = np.arange(len(points)) >= len(front)
    away = (np.linalg.norm(points[:, :2] - [-8.0, 0.0], axis=1) > 5.0) & (np.abs(points[:, :2]) < 18.0).all(axis=1)
    away &= points[:, 0] < 5.0  # on the flat skin (on the slope 7 mm is within what the front itself falls)
    assert kept[~is_back].mean() > 0.999  # a few noisy points on the steep skin may go: their neighbours fill in
    assert kept[~is_back & (points[:, 0] > 15.0)].mean() > 0.99  # the steep part (slope 3.3-5)
    assert not kept[is_back & away].any()
    inside = is_back & (np.linalg.norm(points[:, :2] - [-8.0, 0.0], axis=1) < 2.0)
    assert kept[inside].mean() > 0.5  # inside the gap: the only surface there
    clean = resample(points[kept], x, y, colours=colours[kept])
    xx, yy = np.meshgrid(x, y)
    outside = (np.hypot(xx + 8.0, yy) > 5.0) & (np.abs(yy) < 17.0) & (xx > -17.0) & (xx < 4.0)
    assert np.nanmin(clean.colours[outside][:, 0]) > 0.79
    assert np.nanmin(image.colours[outside][:, 0]) < 0.5  # what the back's points had mixed in


def test_heights_ignore_another_surface_showing_through_a_gap(rng):
    """The known slide of the skin over a curved face, with a patch (a nostril) where 60 % of each scan's
    points are on a surface 25 mm behind the skin, different points in each scan: the tracked motion along
    the face's normal there stays on the skin's (measured 0.05 mm RMS error; 0.61 mm when those points'
    heights counted, without ``behind_front``)."""

    from livebridge.retarget.skin_flow import pixels_of, skin_motion

    texture = _texture(rng)
    nostril = np.array([-10.0, 8.0])

    def surface(xy):
        return np.column_stack([xy, 20 * np.exp(-(xy ** 2).sum(axis=1) / 40.0 ** 2)])

    def slide(xy):
        return 2.0 * np.exp(-((xy - [5.0, -5.0]) ** 2).sum(axis=1) / 15.0 ** 2)[:, None] * np.array([[0.8, 0.6]])

    def scan(moved: bool):
        skin = rng.uniform(-38, 38, (30_000, 2))
        at = skin + slide(skin) if moved else skin
        grey = texture(skin[:, ::-1]) + rng.normal(0, 0.01, len(skin))
        points = surface(at) + rng.normal(0, 0.1, (len(skin), 3))
        inside = (np.linalg.norm(at - nostril, axis=1) < 7.0) & (rng.random(len(skin)) < 0.6)
        points[inside, 2] -= 25.0
        return points, np.repeat(grey[:, None], 3, axis=1)

    x, y, fine_x, fine_y = _skin_axes()
    (neutral_points, neutral_colours), (points, colours) = scan(False), scan(True)
    skin = neutral_points[:, 2] > surface(neutral_points[:, :2])[:, 2] - 10.0
    neutral = resample(neutral_points[skin], x, y)  # the grid's own heights are the skin's
    neutral_skin = resample(neutral_points, fine_x, fine_y, colours=neutral_colours)
    motion, _ = skin_motion(neutral_skin, resample(points, fine_x, fine_y, colours=colours),
                            pixels_of(neutral_skin, neutral.vertices[:, :2]), np.zeros((len(neutral.vertices), 3)))
    xy = neutral.vertices[:, :2]
    truth = surface(xy + slide(xy)) - surface(xy)
    near = np.linalg.norm(xy - nostril, axis=1) < 7.0
    error = np.sqrt(np.mean((motion[near, 2] - truth[near, 2]) ** 2))
    assert error < 0.2, error


def test_noise_shrinkage_keeps_still_skin_still_and_moving_skin_moving(rng):
    """A slide over a third of a flat face plus noise correlated over millimetres (what the flow leaves): the
    shrinkage, with the noise level read from the data, brings the still skin nearer to still and leaves the
    slide (much larger than the noise) nearly whole."""
    from scipy.ndimage import gaussian_filter

    from livebridge.retarget.skin_smoothing import shrink_noise

    x, y = square_axes(40.0, (81, 81))
    grid = resample(np.column_stack([rng.uniform(-41, 41, (20_000, 2)), np.zeros(20_000)]), x, y)
    xy = grid.vertices[:, :2]
    slide = 3.0 * np.exp(-((xy - [15.0, 0.0]) ** 2).sum(axis=1) / 8.0 ** 2)[:, None] * np.array([[0.0, 1.0, 0.0]])
    noise = np.stack([gaussian_filter(rng.normal(0, 1, grid.shape), 2.0)[grid.valid] for _ in range(3)], axis=1)
    noise *= 0.2 / noise[:, :2].std()
    noise[:, 2] = 0.0
    normals = np.tile([0.0, 0.0, 1.0], (len(xy), 1))
    shrunk = shrink_noise(grid, normals, slide + noise, np.ones(len(xy)))
    still = np.linalg.norm(slide, axis=1) < 0.01
    moving = np.linalg.norm(slide, axis=1) > 1.5

    def rms(values, where):
        return float(np.sqrt(np.mean(np.sum(values[where] ** 2, axis=1))))

    assert rms(shrunk - slide, still) < 0.6 * rms(noise, still)
    assert rms(shrunk - slide, moving) < 1.2 * rms(noise, moving)


@pytest.mark.parametrize("moved", [0.0, 0.3, 0.6])
def test_noise_level_is_read_from_the_still_skin_however_much_of_the_face_moves(rng, moved):
    """Sizes of 2D motions: a fraction ``moved`` moved (0.3-3 mm) plus the noise, the rest the noise alone
    (Gaussian, 0.12 mm per axis): the noise level comes back within 15 % (0.92-1.12 times it over 20 draws),
    also where moved skin reaches below the :data:`STILL_FRACTION` quantile (read as the noise's own, that
    quantile gave 1.3 times the level with 30 % moved, 2.4-2.9 times with 60 %)."""
    from livebridge.retarget.skin_smoothing import still_noise_variance

    n = 6000
    noise = rng.normal(0.0, 0.12, (n, 2))
    angle = rng.uniform(0, 2 * np.pi, n)
    motion = rng.uniform(0.3, 3.0, n)[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    motion[rng.uniform(size=n) >= moved] = 0.0
    sigma = np.sqrt(still_noise_variance(np.linalg.norm(motion + noise, axis=1)))
    assert abs(sigma / 0.12 - 1.0) < 0.15


def test_noise_shrinkage_keeps_a_slide_over_most_of_the_face(rng):
    """A 1 mm slide (five times the noise) over two thirds of a flat face: with the noise level read from the
    still third, the shrinkage leaves the moving skin nearer the truth than unshrunk (0.69-0.75 times the
    noise's error over four seeds: the noise across the slide is shrunk away) and still brings the still skin
    nearer to still. The lowest 40 % of sizes read as the noise alone
    (moving skin among them) shrank the slide away: 3.2-3.4 times the noise's error on the moving skin."""
    from scipy.ndimage import gaussian_filter

    from livebridge.retarget.skin_smoothing import shrink_noise

    x, y = square_axes(40.0, (81, 81))
    grid = resample(np.column_stack([rng.uniform(-41, 41, (20_000, 2)), np.zeros(20_000)]), x, y)
    xy = grid.vertices[:, :2]
    slide = np.zeros((len(xy), 3))
    slide[:, 1] = 1.0 / (1.0 + np.exp(-(xy[:, 0] + 12.0) / 1.5))  # along y, on x > -12 mm
    noise = np.stack([gaussian_filter(rng.normal(0, 1, grid.shape), 2.0)[grid.valid] for _ in range(3)], axis=1)
    noise *= 0.2 / noise[:, :2].std()
    noise[:, 2] = 0.0
    normals = np.tile([0.0, 0.0, 1.0], (len(xy), 1))
    shrunk = shrink_noise(grid, normals, slide + noise, np.ones(len(xy)))
    still = xy[:, 0] < -20.0
    moving = xy[:, 0] > -4.0

    def rms(values, where):
        return float(np.sqrt(np.mean(np.sum(values[where] ** 2, axis=1))))

    assert rms(shrunk - slide, moving) < 0.9 * rms(noise, moving)
    assert rms(shrunk - slide, still) < 0.4 * rms(noise, still)


def test_noise_shrinkage_on_steep_skin_takes_the_flow_noise_lifted_onto_the_slope(rng):
    """A face whose sides are steep (|n_z| about 0.34 at the edges), a 1 mm slide down its middle, and the
    flow's noise: the same in x and y (0.2 mm, correlated over millimetres), lifted onto the surface, where
    along the slope it grows by 1 / |n_z|. The shrinkage takes out most of it on the steep still skin (0.10
    of the noise's RMS there, mean of 4 draws; one noise level for both directions along the skin, read from
    the lifted sizes, left 0.40) and leaves the slide's skin about as near the truth as unshrunk (1.03 of the
    noise there; the one level 1.63: it shrank the slide)."""
    from scipy.ndimage import gaussian_filter

    from livebridge.face.meshio import vertex_normals
    from livebridge.retarget.skin_smoothing import shrink_noise

    def rms(values, where):
        return float(np.sqrt(np.mean(np.sum(values[where] ** 2, axis=1))))

    x, y = square_axes(40.0, (81, 81))
    steep_left, moving_left = [], []
    for _ in range(4):
        points = rng.uniform(-41, 41, (30_000, 2))
        grid = resample(np.column_stack([points, -points[:, 0] ** 2 / 25.0]), x, y)
        xy = grid.vertices[:, :2]
        normals = vertex_normals(grid.vertices, grid.triangles)
        slide = np.zeros((len(xy), 3))
        slide[:, 1] = np.exp(-xy[:, 0] ** 2 / (2 * 8.0 ** 2))  # along the level lines
        flow = np.stack([gaussian_filter(rng.normal(0, 1, grid.shape), 2.0)[grid.valid] for _ in range(2)], axis=1)
        flow *= 0.2 / flow.std()
        noise = np.column_stack([flow, -xy[:, 0] / 12.5 * flow[:, 0]])  # z = -x^2 / 25 rises by dz/dx dx
        shrunk = shrink_noise(grid, normals, slide + noise, np.ones(len(xy)))
        steep, moving = np.abs(xy[:, 0]) > 28.0, np.abs(xy[:, 0]) < 5.0
        assert abs(normals[steep, 2]).mean() < 0.4
        steep_left.append(rms(shrunk - slide, steep) / rms(noise, steep))
        moving_left.append(rms(shrunk - slide, moving) / rms(noise, moving))
    assert np.mean(steep_left) < 0.25, steep_left
    assert np.mean(moving_left) < 1.2, moving_left


def test_noise_shrinkage_lifts_the_noise_by_the_chart_view_not_by_z():
    """A face that is half a cylinder (|n_z| about 0.44 on its sides), skin images in the cylinder chart about
    its axis (they face the skin everywhere), the flow's noise the same in both axes of those images (0.2 mm,
    correlated over millimetres) and a 0.5 mm slide round the cylinder on one side. Lifted by the chart's
    view the noise is not grown there, and the shrinkage leaves the slide's skin nearer the truth than
    unshrunk (0.74-0.85 of the noise's RMS, 4 draws); lifted by ``1 / |n_z|`` (the x-y images' model) it
    took the slide for noise and shrank it (1.21-1.49: worse than no shrinkage). The still front is shrunk
    towards still either way (0.14-0.34)."""
    from scipy.ndimage import gaussian_filter

    from livebridge.face.meshio import vertex_normals
    from livebridge.retarget.chart import SkinChart
    from livebridge.retarget.skin_smoothing import shrink_noise

    def rms(values, where):
        return float(np.sqrt(np.mean(np.sum(values[where] ** 2, axis=1))))

    chart = SkinChart("cylinder", np.array([0.0, 0.0, -60.0]), 60.0)
    x, y = square_axes(58.0, (97, 97))
    kept, z_lifted, still_left = [], [], []
    for seed in range(4):
        rng = np.random.default_rng(seed)
        angle, height = rng.uniform(-1.3, 1.3, 60_000), rng.uniform(-56, 56, 60_000)
        grid = resample(chart.from_chart(np.column_stack([60.0 * angle, height, np.zeros(len(angle))])), x, y)
        points = grid.vertices
        normals = vertex_normals(points, grid.triangles)
        theta = chart.to_chart(points)[:, 0] / 60.0
        around = np.column_stack([np.cos(theta), np.zeros(len(theta)), -np.sin(theta)])
        slide = (0.5 / (1.0 + np.exp(-(theta - 0.85) / 0.05)))[:, None] * around
        flow = np.stack([gaussian_filter(rng.normal(0, 1, grid.shape), 2.0)[grid.valid] for _ in range(2)], axis=1)
        flow *= 0.2 / flow.std()
        noise = flow[:, :1] * around + flow[:, 1:] * np.array([0.0, 1.0, 0.0])  # (u, v) of the chart's images
        moving, still = theta > 1.0, np.abs(theta) < 0.5
        assert abs(normals[moving, 2]).mean() < 0.5
        for view, left in ((chart.view_directions(points), kept), (None, z_lifted)):
            shrunk = shrink_noise(grid, normals, slide + noise, np.ones(len(points)), view=view)
            left.append(rms(shrunk - slide, moving) / rms(noise, moving))
            if view is not None:
                still_left.append(rms(shrunk - slide, still) / rms(noise, still))
    assert np.mean(kept) < 0.95, kept
    assert np.mean(z_lifted) > 1.1, z_lifted  # the x-y model's lift: the reason for the view
    assert np.mean(still_left) < 0.4, still_left


def test_adaptive_smoothing_averages_noise_away_on_flat_motion_and_keeps_a_sharp_bump(rng):
    """A sharp bump of motion (sigma 4 px) on still skin plus white noise: smoothed at the base width (4 px)
    the still skin keeps noise that twice the width would halve, and at twice the width the bump loses much
    of its height. The adaptive smoothing, with the noise level read from the data, does both: less noise
    on the still skin than the base width, no more bias on the bump."""
    from livebridge.retarget.skin_smoothing import WIDTHS, adaptive_smooth, weighted_blur

    rows, cols = np.indices((160, 160))
    bump = 2.0 * np.exp(-((rows - 80) ** 2 + (cols - 80) ** 2) / (2 * 4.0 ** 2))
    truth = np.dstack([bump, 0.5 * bump])
    values = truth + rng.normal(0.0, 1.0, truth.shape)
    weight = np.ones(bump.shape)

    def smoothed(width):
        return np.dstack([weighted_blur(values[..., k], weight, width) for k in (0, 1)])

    adaptive = adaptive_smooth([smoothed(4.0 * factor) for factor in WIDTHS], weight, 4.0)
    distance = np.hypot(rows - 80, cols - 80)
    inner = (rows > 20) & (rows < 140) & (cols > 20) & (cols < 140)
    still, on_bump = inner & (distance > 30), distance < 6

    def rms(field, where):
        return float(np.sqrt(np.mean(np.sum((field - truth)[where] ** 2, axis=1))))

    assert rms(adaptive, still) < 0.7 * rms(smoothed(4.0), still)
    assert rms(adaptive, on_bump) < 1.1 * rms(smoothed(4.0), on_bump)
    assert rms(adaptive, on_bump) < 0.8 * rms(smoothed(4.0 * max(WIDTHS)), on_bump)


def test_skin_template_averages_the_scans_into_a_cleaner_neutral_skin(rng):
    """A neutral and seven expression scans of one textured skin, each sliding it by its own smooth field, each
    with its own sampling and colour noise: the first expression's template (the six others warped back by
    their motion and averaged with the neutral) is nearer the true skin pattern than the neutral scan's own
    image, and that expression's slide tracked against it is nearer the truth than tracked against the
    neutral (measured: 1 - correlation with the true pattern 0.027 against 0.059; RMS error 0.047 against
    0.051 mm with the adaptive smoothing of the motion, which takes noise out of both; 0.049 against 0.057
    with one smoothing width)."""

    from livebridge.retarget.grid import FaceGrid
    from livebridge.retarget.skin_flow import pixels_of, skin_image, skin_motion
    from livebridge.retarget.skin_template import skin_templates

    texture = _texture(rng, 0.6)

    def slide(xy, centre, size):
        return size * np.exp(-((xy - centre) ** 2).sum(axis=1) / 12.0 ** 2)[:, None] * np.array([[0.8, 0.6]])

    def scan(centre, size):
        return _slid_scan(rng, texture, lambda skin: slide(skin, centre, size))

    x, y, fine_x, fine_y = _skin_axes()
    points, colours = scan([0.0, 0.0], 0.0)
    neutral, neutral_skin = resample(points, x, y), resample(points, fine_x, fine_y, colours=colours)
    moves = [(rng.uniform(-15, 15, 2), rng.uniform(1.0, 3.0)) for _ in range(7)]
    skins = [resample(p, fine_x, fine_y, colours=c) for p, c in (scan(centre, size) for centre, size in moves)]
    xy = neutral.vertices[:, :2]
    ones = np.ones(len(xy))
    at = pixels_of(neutral_skin, xy)
    template = skin_templates(neutral_skin, at, [(skin, np.column_stack([slide(xy, *m), 0 * ones]), ones)
                                                      for skin, m in zip(skins, moves)])[0]  # all but skins[0]
    rows, cols = np.meshgrid(fine_y, fine_x, indexing="ij")
    grey = texture(np.stack([rows, cols], axis=-1))
    clean = skin_image(FaceGrid(fine_x, fine_y, np.zeros(rows.shape), np.repeat(grey[..., None], 3, axis=2)))[0]
    inner = (slice(20, -20), slice(20, -20))

    def mismatch(image):  # 1 - the correlation with the true pattern
        return 1.0 - float(np.corrcoef(image[inner].ravel(), clean[inner].ravel())[0, 1])

    assert mismatch(skin_image(template)[0]) < 0.7 * mismatch(skin_image(neutral_skin)[0])

    def tracking_error(template):
        motion, _ = skin_motion(neutral_skin, skins[0], at, np.zeros((len(xy), 3)), template=template)
        truth = slide(xy, *moves[0])
        return float(np.sqrt(np.mean(np.sum((motion[:, :2] - truth) ** 2, axis=1))))

    assert tracking_error(template) < 0.95 * tracking_error(None)


def test_the_neutral_scan_s_noise_shared_by_every_tracked_slide_is_taken_out(rng):
    """A neutral and eight expression scans of one textured skin, each sliding its own 10 mm patch of it by 1-3
    mm in its own direction, each with its own sampling and noise, each tracked against the neutral: the
    neutral's own noise misplaces its skin alike in every tracking, and the skin each expression leaves still
    shows it (:mod:`~livebridge.retarget.neutral_noise`). Taken out, every slide is nearer the truth (measured
    here 0.060 -> 0.051 mm mean RMS error, on three other draws 0.060 -> 0.050, 0.062 -> 0.054, 0.061 -> 0.053;
    every slide better)."""
    from livebridge.retarget.neutral_noise import neutral_noise
    from livebridge.retarget.skin_flow import pixels_of, skin_motion

    texture = _texture(rng, 0.6)

    def slide(xy, centre, size, direction):
        return size * np.exp(-((xy - centre) ** 2).sum(axis=1) / 10.0 ** 2)[:, None] * direction

    def scan(move):
        points, colours = _slid_scan(rng, texture, None if move is None else lambda skin: slide(skin, *move))
        return resample(points, fine_x, fine_y, colours=colours), points

    x, y, fine_x, fine_y = _skin_axes()
    neutral_skin, points = scan(None)
    xy = resample(points, x, y).vertices[:, :2]
    at = pixels_of(neutral_skin, xy)
    directions = rng.normal(size=(8, 2))
    moves = [(rng.uniform(-20, 20, 2), rng.uniform(1.0, 3.0), d / np.linalg.norm(d)) for d in directions]
    tracked = np.array([skin_motion(neutral_skin, scan(move)[0], at, np.zeros((len(xy), 3)))[0] for move in moves])
    truth = np.array([slide(xy, *move) for move in moves])
    inner = (np.abs(xy) < 30).all(axis=1)  # the flow's own edge effects aside

    def errors(motions):
        return np.sqrt(np.mean(np.sum((motions[:, inner, :2] - truth[:, inner]) ** 2, axis=2), axis=1))

    before, after = errors(tracked), errors(tracked - neutral_noise(tracked))
    assert np.all(after < before), (before.round(3), after.round(3))
    assert after.mean() < 0.92 * before.mean(), (before.mean(), after.mean())


def test_second_tracking_trusts_no_skin_the_first_could_not_track():
    """A smooth slide of textured skin tracked a second time, from the first tracking's motion, against a
    template that is wrong over a patch (there it shows the skin 2.8 mm off, as a template averaged from
    scans that saw that skin poorly does): the flow against it lands off the truth and the check against the
    neutral's own skin still half trusts it (measured 1.35 mm of error, trust 0.47). Where the first
    tracking was not trusted, the second is not either: the patch takes the motion carried from the tracked
    skin around it (measured 0.14 mm; the opened jaw's chin from underneath, retarget/scans._within)."""

    from livebridge.retarget.face_scan import FaceScan
    from livebridge.retarget.scans import tracked_motion
    from livebridge.retarget.skin_flow import fine_axes

    rng = np.random.default_rng(3)
    texture = _texture(rng)
    patch, radius = np.array([8.0, -6.0]), 7.0

    def slide(xy):  # smooth over the face: the spline through the skin around the patch carries it
        return np.column_stack([1.5 + 0.04 * xy[:, 0], -1.0 + 0.03 * xy[:, 1]])

    x, y = square_axes(30.0, (41, 41))
    margin = 4
    wide = np.linspace(-30 - margin * (x[1] - x[0]), 30 + margin * (x[1] - x[0]), 41 + 2 * margin)
    fine_x, fine_y, factor = fine_axes(wide, wide)

    def scan(moved: bool) -> FaceScan:
        skin = rng.uniform(-38, 38, (30_000, 2))
        at = skin + slide(skin) if moved else skin
        points = np.column_stack([at, 20 * np.exp(-(at ** 2).sum(axis=1) / 40.0 ** 2)])
        points += rng.normal(0, 0.1, points.shape)
        grey = texture(np.clip(skin[:, ::-1], -42, 42)) + rng.normal(0, 0.01, len(skin))
        colours = np.repeat(grey[:, None], 3, axis=1)
        return FaceScan(resample(points, x, y), {}, np.eye(4), resample(points, fine_x, fine_y, colours=colours),
                        factor, margin, 0.4)

    neutral, expression = scan(False), scan(True)
    rows, cols = np.meshgrid(fine_y, fine_x, indexing="ij")
    xy = np.stack([cols, rows], axis=-1)
    off = np.where((np.linalg.norm(xy - patch, axis=-1) < radius)[..., None], [2.0, 2.0], 0.0)
    grey = texture(np.clip((xy + off)[..., ::-1], -42, 42))
    own = replace(neutral, template=replace(neutral.skin, colours=np.repeat(grey[..., None], 3, axis=2)))
    vertices = neutral.vertices
    truth = slide(vertices[:, :2])
    first, trust = tracked_motion(neutral, expression, start=np.zeros_like(vertices))
    assert trust.mean() > 0.95
    distance = np.linalg.norm(vertices[:, :2] - patch, axis=1)
    first_trust = np.where(distance < radius + 1, 0.0, trust)  # the first tracking did not trust the patch
    inside = distance < radius - 2

    def patch_error(start_trust):
        motion, trust = tracked_motion(own, expression, start=first, start_trust=start_trust)
        error = np.linalg.norm(motion[:, :2] - truth, axis=1)
        return float(np.sqrt(np.mean(error[inside] ** 2))), trust

    free, _ = patch_error(None)
    within, trust = patch_error(first_trust)
    assert np.all(trust <= first_trust + 1e-12)
    assert free > 0.8, free  # the wrong template misleads a second tracking left to itself
    assert within < 0.3, within
    assert within < 0.25 * free, (within, free)


# ------------------------------------------------------------------------------------------------ bases from scans
def test_adaptive_smoothing_follows_a_steep_ramp_of_motion_with_the_twiced_candidate(rng):
    """A plateau of motion (9 mm) falling to none over ~3 base widths (a closing lid's skin at its crease)
    plus white noise: every Gaussian width rounds the ramp's ends off, and the adaptive smoothing with widths
    alone keeps the base width's bias there. With the twiced base width as a candidate it keeps about half
    that (measured 0.32 / 0.63 px RMS at noise 0.3, 0.35-0.46 / 0.63-0.68 at noise 1) and the still skin's
    smoothing is the same as without (the candidate is not taken where only noise tells it apart)."""
    from livebridge.retarget.skin_smoothing import WIDTHS, adaptive_smooth, twiced, weighted_blur

    rows, cols = np.indices((160, 160))
    ramp = 9.0 / (1.0 + np.exp((rows - 80) / 2.0))
    truth = np.dstack([0.1 * ramp, -ramp])
    inner = (cols > 20) & (cols < 140)
    on_ramp, still = inner & (abs(rows - 80) < 12), inner & (rows > 110) & (rows < 140)

    def rms(field, where):
        return float(np.sqrt(np.mean(np.sum((field - truth)[where] ** 2, axis=1))))

    def blur_at(width):
        return lambda images, weight: [weighted_blur(image, weight, width) for image in images]

    for noise in (0.3, 1.0):
        values = truth + rng.normal(0.0, noise, truth.shape)
        weight = np.ones(ramp.shape)
        channels = [values[..., 0], values[..., 1]]
        means = [np.dstack(blur_at(4.0 * factor)(channels, weight)) for factor in WIDTHS]
        plain = adaptive_smooth(means, weight, 4.0)
        sharp = adaptive_smooth(means, weight, 4.0, np.dstack(twiced(blur_at(4.0), channels, weight)))
        assert rms(sharp, on_ramp) < 0.75 * rms(plain, on_ramp), noise
        assert rms(sharp, still) < 1.02 * rms(plain, still), noise


SCAN_MUSCLES = ("frontalis_L", "zygomatic_major_L", "depressor_anguli_oris", "orbicularis_oculi_L")
"""A brow, a smile, a lip corner, an eyelid (the full 16 are in `livebridge bench scans`)."""
EYELIDS = ("orbicularis_oculi_L", "orbicularis_oculi_R")


@pytest.fixture(scope="module")
def ict_scan_figures(ict):
    from livebridge.retarget.landmarks import load_landmark_set

    return build_and_measure(ict, load_landmark_set("ict-22"), np.random.default_rng(7), grid=(100, 100),
                             muscles=SCAN_MUSCLES)


def _share_where_ict_moves(element, true) -> float:
    """The fraction of an element's squared motion on the vertices the ICT element moves (> 10% of its max)."""
    size, true_size = np.linalg.norm(element, axis=1), np.linalg.norm(true, axis=1)
    moved = true_size > 0.1 * true_size.max()
    return float(np.sum(size[moved] ** 2) / np.sum(size ** 2))


def test_scan_basis_moves_the_face_where_the_ict_elements_do(ict_scan_figures):
    figures = ict_scan_figures
    assert set(figures.names) == set(SCAN_MUSCLES)
    assert np.isfinite(figures.with_colour).all() and np.isfinite(figures.without_colour).all()
    for name, element, true in zip(figures.names, figures.with_colour, figures.truth):
        if name not in EYELIDS:
            assert _share_where_ict_moves(element, true) > 0.75, name


def test_scans_of_one_face_are_not_told_as_another(ict_scan_figures):
    """Every expression scan of the ICT face lies on the neutral's surface within the limit of
    :func:`~livebridge.retarget.same_face.another_face` (tests/test_same_face.py has one that does not)."""
    figures = ict_scan_figures
    assert (figures.gaps < 0.8).all(), dict(zip(figures.names, np.round(figures.gaps, 3)))


def test_skin_tracking_measures_the_motion_along_the_skin(ict_scan_figures):
    """With colour, the brow's, the smile's, the lip corner's and the eyelid's errors are at most half of what
    shape alone gives (which knows the sliding of the skin at the landmarks only, and the lids' from the eye
    openings). Measured here 0.15, 0.09, 0.19 and the eyelid 0.40; over all 16 elements in `livebridge bench
    scans` 0.08-0.22, the jaw 0.34, the eyelids 0.37 and 0.43."""
    figures = ict_scan_figures
    ratio = dict(zip(figures.names, figures.errors / figures.errors_without_colour))
    for name, value in ratio.items():
        assert value < 0.5, (name, round(float(value), 3))


def test_scan_basis_surface_within_10_percent(ict_scan_figures):
    """The expression the built basis gives (its neutral mesh plus the element) lies on the true expressive
    surface within 10% of the element's RMS motion: measured 0.036 (brow), 0.026 (smile), 0.057 (lip corner)
    and 0.087 (eyelid) here. Met since the neutral mesh is fitted to the scan's points
    (livebridge/retarget/surface_fit.py): with the interpolated grid the eyelid was 0.110, the lip corner 0.091."""
    figures = ict_scan_figures
    assert np.nanmax(figures.surface) <= ERROR_LIMIT, dict(zip(figures.names, np.round(figures.surface, 3)))


def test_scan_basis_eyelids(ict_scan_figures):
    """The eyelid's element moves the face where the ICT one does (measured 0.94 of its squared motion here).

    Met since the tracked motion that is not above the flow's noise is shrunk (0.52 without). The lid's error
    stays over the bar (0.23 relative RMS here): its skin slides ~9 mm over the eye, partly hidden and folded.
    """
    figures = ict_scan_figures
    for name in set(EYELIDS) & set(figures.names):
        k = figures.names.index(name)
        assert _share_where_ict_moves(figures.with_colour[k], figures.truth[k]) > 0.75, name


def test_shape_alone_holds_the_skin_still_where_the_scans_show_no_motion(ict_scan_figures):
    """Without colour the motion along the skin is known at the landmarks only. The thesis's spline through
    them alone carries a moved landmark's motion over all the face no landmark pins: here the brow 0.86, the
    smile 0.61 and the lip corner 0.90 relative RMS (1.27-1.52 for a lip corner pull in `livebridge bench
    scans`, worse than no motion). Held still where the expressive surface meets the neutral's away from the
    moved landmarks (``scans.still_anchors``): 0.45, 0.54 and 0.57. The eyelid's slide is in no landmark (0.98);
    read from where the eye opening went (``scans.shape_element``), 0.56."""
    figures = ict_scan_figures
    errors = dict(zip(figures.names, np.round(figures.errors_without_colour, 3)))
    assert all(error < 0.7 for error in errors.values()), errors


def test_the_outline_share_falls_to_nothing_at_the_skin_s_outline_and_not_at_its_holes(rng):
    """Within ``OUTLINE_MM[0]`` of where the skin stops on its way out (or of the image's edge) a point keeps none
    of its own flow, beyond ``OUTLINE_MM[1]`` all of it, linearly between; an eye or a nostril inside the face
    does not count."""
    from livebridge.retarget.grid import FaceGrid
    from livebridge.retarget.skin_flow import OUTLINE_MM, outline_share

    inner, outer = OUTLINE_MM
    radius, step = 2 * outer, 0.5
    x = y = np.arange(-radius - 5.0, radius + 5.0 + step / 2, step)
    xx, yy = np.meshgrid(x, y)
    face = (np.hypot(xx, yy) <= radius) & (np.hypot(xx, yy) > 5.0)  # a disc with a hole in its middle
    colours = np.where(face[..., None], rng.random((*face.shape, 3)), np.nan)
    grid = FaceGrid(x, y, np.where(face, 0.0, np.nan), colours)
    points = np.array([[0.0, radius - inner / 2], [0.0, radius - (inner + outer) / 2], [outer + 2.0 - radius, 0.0],
                       [6.0, 0.0]])
    at = np.column_stack([(points[:, 1] - y[0]) / step, (points[:, 0] - x[0]) / step])  # (row, column)
    share = outline_share(grid, at)
    assert share[0] == 0.0
    assert share[1] == pytest.approx(0.5, abs=0.03)  # the distance transform's own rounding
    assert share[2] == 1.0
    assert share[3] == 1.0  # 1 mm from the hole
    everywhere = FaceGrid(x, y, np.zeros(xx.shape), rng.random((*xx.shape, 3)))
    middle = len(x) // 2
    edge = np.array([[middle, 0.0], [middle, middle]], dtype=float)  # the middle of the left edge, of the image
    assert outline_share(everywhere, edge).tolist() == [0.0, 1.0]


def test_skin_an_expression_does_not_move_stays_still_at_the_face_s_outline(ict):
    """Near the skin images' outline a DIS patch matches the two scans' outlines (silhouettes, which differ
    between scans in different poses), so the flow kept its first guess there: the landmark spline extrapolated
    70-100 mm out. There the carried motion of the well-tracked skin is taken instead (``skin_flow.OUTLINE_MM``).
    On another face (the ICT face under the retarget bench's known warp: flatter sides), the skin within the
    outline's reach that the element moves less than 0.05 mm moves at most 1.01 mm in the built brow and 0.40 mm
    in the built eyelid (without: 0.96 and 4.01 mm; seed 8 0.57 and 0.88, without 2.56 and 2.72)."""
    from livebridge.bench.retarget import warped_basis
    from livebridge.retarget.landmarks import load_landmark_set
    from livebridge.retarget.skin_flow import outline_share

    landmarks = load_landmark_set("ict-22")
    other = warped_basis(ict, landmarks.as_dict(ict.neutral, ict.triangles))
    figures = build_and_measure(other, landmarks, np.random.default_rng(7), grid=(100, 100),
                                muscles=("frontalis_L", "orbicularis_oculi_L"))
    near = outline_share(figures.neutral.skin, figures.neutral.skin_pixels()) < 1.0
    for name, element, true in zip(figures.names, figures.with_colour, figures.truth):
        still = near & (np.linalg.norm(true, axis=1) < 0.05)
        assert still.sum() >= 100, name
        largest = np.linalg.norm(element[still], axis=1).max()
        assert largest < 1.5, (name, largest)


def test_closing_holes_are_the_neutral_s_holes_a_closing_eye_touches():
    """The holes of the neutral's skin that a closing eye's opening touches are filled, each whole; another hole
    (a nostril) and the gap beyond the face's outline are not, even where the opening reaches them."""
    from livebridge.retarget.skin_flow import closing_holes

    rows, cols = np.indices((60, 80))
    valid = np.ones((60, 80), bool)
    valid[:, :5] = False  # beyond the face's outline, open to the image's edge
    eye = ((rows - 20) / 4.0) ** 2 + ((cols - 30) / 10.0) ** 2 < 1
    nostril = ((rows - 45) / 3.0) ** 2 + ((cols - 50) / 3.0) ** 2 < 1
    valid &= ~eye & ~nostril
    closing = np.zeros_like(valid)
    closing[19:22, 28:33] = True  # the middle of the eye's opening only
    closing[45, :3] = True  # and a stray bit out beyond the outline
    filled = closing_holes(valid, closing)
    assert (filled == eye).all()
    assert not closing_holes(valid, np.zeros_like(valid)).any()


def test_a_closing_eye_s_opening_shows_the_flow_the_expression_s_skin(ict, monkeypatch):
    """A DIS patch across a closing eye's empty opening, which the closed eye does not have, matched nothing there
    and pulled the lid's skin off its motion; the neutral's hole there now shows the flow the expression's skin
    (``skin_flow.closing_holes``). One eyelid scan of the other face (the ICT face under the retarget bench's
    known warp), 100 x 100 grid: measured 0.217 relative RMS with the fill, 0.294 without (seeds 8-10: 0.237 /
    0.281, 0.325 / 0.340, 0.230 / 0.236; on the ICT face within 0.01 either way)."""
    from livebridge.bench.retarget import warped_basis
    from livebridge.retarget import skin_flow
    from livebridge.retarget.landmarks import load_landmark_set

    landmarks = load_landmark_set("ict-22")
    other = warped_basis(ict, landmarks.as_dict(ict.neutral, ict.triangles))

    def eyelid_error():
        figures = build_and_measure(other, landmarks, np.random.default_rng(7), grid=(100, 100),
                                    muscles=("orbicularis_oculi_L",))
        return float(figures.errors[0])

    filled = eyelid_error()
    monkeypatch.setattr(skin_flow, "closing_holes", lambda valid, closing: np.zeros_like(valid))
    unfilled = eyelid_error()
    assert filled < 0.25, filled
    assert filled < 0.85 * unfilled, (filled, unfilled)


@pytest.mark.xfail(strict=True, reason="open: here 0.047-0.105 relative RMS and the eyelid 0.223; in `livebridge "
                   "bench scans` (skin images in the cylinder chart) every element but the eyelids within 0.10 at "
                   "150k points a scan (0.028-0.072; eyelids 0.179 / 0.176), 12 of 16 at 60k (over: lip corner "
                   "0.108, lip press 0.107, eyelids 0.195 / 0.190): the eyelids' closing skin is hidden or folded "
                   "in the closed eye and its stretched pattern does not locate its motion (tested to 600k points), "
                   "and at 60k the flow's noise (what the skin images resolve); clouds sampled over the whole "
                   "mesh 11 of 16 (their hidden skin mixes into the front's), 12 of 16 with their normals")
def test_scan_basis_reproduces_the_ict_elements_within_10_percent(ict_scan_figures):
    figures = ict_scan_figures
    assert np.nanmax(figures.errors) <= ERROR_LIMIT, dict(zip(figures.names, np.round(figures.errors, 3)))


def test_expression_scans_prepared_in_worker_processes_give_the_same_basis(tmp_path):
    """``--workers 2`` (spawned processes, each sent the neutral once) writes the basis ``--workers 1`` does, bit
    for bit, skin tracked; an expression that fails in a worker is refused naming its file and landmark, as in
    one process."""
    from livebridge.cli import main

    stems = {"neutral": "neutral", "zygomatic_major_L": "smile", "jaw": "jaw"}
    write_builtin_scans(tmp_path, 8, stems, colour=True)
    command = ["retarget", "scans", "--neutral", str(tmp_path / "neutral.ply"), "--neutral-landmarks",
               str(tmp_path / "neutral.landmarks.csv"), "--grid", "40x40"]
    for muscle, stem in list(stems.items())[1:]:
        command += ["--expression", f"{muscle}={tmp_path / stem}.ply"]
    built = {}
    for workers in (1, 2):
        out = tmp_path / f"basis{workers}.npz"
        result = CliRunner().invoke(main, command + ["--out", str(out), "--workers", str(workers)])
        assert result.exit_code == 0, result.output
        assert result.output.count("skin tracked") == 2, result.output
        built[workers] = np.load(out)
    assert sorted(built[1].files) == sorted(built[2].files)
    for key in built[1].files:
        np.testing.assert_array_equal(built[1][key], built[2][key], err_msg=key)
    marks = (tmp_path / "jaw.landmarks.csv").read_text().splitlines()
    marks = [line if not line.startswith("brow_outer_L,") else "brow_outer_L,900,900,900" for line in marks]
    (tmp_path / "jaw.landmarks.csv").write_text("\n".join(marks) + "\n")
    result = CliRunner().invoke(main, command + ["--out", str(tmp_path / "bad.npz"), "--workers", "2"])
    assert_cli_refused(result, "jaw.landmarks.csv", "brow_outer_L", "from the nearest point of jaw.ply")
    assert not (tmp_path / "bad.npz").exists()


class _DiesWhenUnpickled:
    """Sent to a worker process, it ends that process at once (as the system's out-of-memory killer would)."""

    def __reduce__(self):
        import os

        return os._exit, (9,)


def test_a_worker_process_that_dies_is_a_clear_error_naming_the_scan_and_workers(tmp_path):
    from livebridge.cli.retarget_scans import prepared_expressions

    jobs = [(name, tmp_path / f"{name}.ply", tmp_path / f"{name}.csv", 1.0, None) for name in ("jaw", "smile")]
    with pytest.raises(InputError, match="a worker process stopped.*give fewer --workers") as caught:
        list(prepared_expressions(_DiesWhenUnpickled(), jobs, 2))
    assert caught.value.path == str(tmp_path / "jaw.ply") and caught.value.field == "--workers"


def test_skin_motion_smoothing_follows_the_point_spacing_down_to_half_a_skin_pixel():
    from livebridge.retarget.scans import SMOOTH_SPACINGS, TYPICAL_SPACING_MM, smoothing_mm

    assert smoothing_mm((0.47, 0.30), 0.49) == pytest.approx(SMOOTH_SPACINGS * 0.47)  # 60k points: the spacing
    assert smoothing_mm((0.083, 0.08), 0.49) == pytest.approx(SMOOTH_SPACINGS * 0.245)  # 1.7M: the pixel's floor
    assert smoothing_mm((np.nan, 0.0), 0.49) == pytest.approx(SMOOTH_SPACINGS * TYPICAL_SPACING_MM)


def test_workers_by_default_one_for_small_scans_else_bounded_by_scans_cores_and_free_memory(tmp_path, monkeypatch):
    import os

    from livebridge.cli import retarget_scans
    from livebridge.cli.retarget_scans import worker_count

    small = [tmp_path / f"small{k}.ply" for k in range(4)]
    big = [tmp_path / f"big{k}.ply" for k in range(4)]
    for path in small:
        path.write_bytes(b"x" * 1000)
    for path in big:  # 30 MB: 2M points of binary PLY, float x y z and uchar colour
        with open(path, "wb") as stream:
            stream.truncate(30_000_000)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(8)), raising=False)
    free = [8.0e9]
    monkeypatch.setattr(retarget_scans, "available_memory", lambda: free[0])
    assert worker_count(None, small) == 1  # starting processes would cost more than it saves
    assert worker_count(None, big) == 3  # 2.4 GB a worker: 3 fit, not the 4 scans or 8 cores
    assert worker_count(None, big[:2]) == 2
    assert worker_count(None, big[:1]) == 1
    assert worker_count(3, small) == 3  # asked for
    assert worker_count(8, small[:2]) == 2  # no more than there are scans
    free[0] = 400e9
    assert worker_count(None, big) == 4


def test_available_memory_is_what_this_system_says():
    import os

    from livebridge.cli.retarget_scans import available_memory

    meminfo = open("/proc/meminfo").read() if os.path.exists("/proc/meminfo") else ""
    line = next((row for row in meminfo.splitlines() if row.startswith("MemAvailable:")), None)
    if line is None:
        pytest.skip("no MemAvailable on this system")
    assert abs(available_memory() - 1024 * float(line.split()[1])) < 0.1 * available_memory()


def test_retarget_scans_cli_writes_a_basis(tmp_path, ict):
    from livebridge.cli import main
    from livebridge.face.basis import Basis
    from livebridge.retarget.landmarks import load_landmark_set

    landmarks = load_landmark_set("ict-22")
    neutral, expressions = synthetic_scans(ict, landmarks, np.random.default_rng(3), n_points=20_000,
                                           hole_muscle=None)

    def write(name, scan, encoding):
        write_ply(tmp_path / f"{name}.ply", scan.points, None, encoding, scan.colours)
        rows = "".join(f"{k},{x:.4f},{y:.4f},{z:.4f}\n" for k, (x, y, z) in scan.landmarks.items())
        (tmp_path / f"{name}.landmarks.csv").write_text("name,x,y,z\n" + rows)

    write("neutral", neutral, "binary_little_endian")
    write("smile", expressions["zygomatic_major_L"], "binary_big_endian")
    jaw = expressions["jaw"]  # a scanner without colour: plain x y z
    (tmp_path / "jaw.xyz").write_text("".join(f"{x:.5f} {y:.5f} {z:.5f}\n" for x, y, z in jaw.points))
    (tmp_path / "jaw.landmarks.csv").write_text("name,x,y,z\n" + "".join(
        f"{k},{x:.4f},{y:.4f},{z:.4f}\n" for k, (x, y, z) in jaw.landmarks.items()))
    result = CliRunner().invoke(main, [
        "retarget", "scans", "--neutral", str(tmp_path / "neutral.ply"), "--neutral-landmarks",
        str(tmp_path / "neutral.landmarks.csv"), "--expression", f"jaw={tmp_path / 'jaw.xyz'}",
        "--expression", f"zygomatic_major_L={tmp_path / 'smile.ply'}:{tmp_path / 'smile.landmarks.csv'}",
        "--grid", "80x90", "--out", str(tmp_path / "b.npz"), "--grid-obj", str(tmp_path / "grid.obj"),
        "--landmarks-out", str(tmp_path / "lm.toml")])
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    table = [line.strip() for line in lines if "largest motion" in line]
    assert "shape only" in next(line for line in table if line.startswith("jaw"))
    assert "skin tracked" in next(line for line in table if line.startswith("zygomatic_major_L"))
    progress = [line.strip() for line in lines if line.startswith("  ") and "/2" in line]
    assert progress == ["jaw: shape only (1/2)", "zygomatic_major_L: tracking the skin (2/2)"], lines
    assert "note: no colour in jaw" in result.output
    basis = Basis.load(tmp_path / "b.npz")
    assert basis.names == ("jaw", "zygomatic_major_L")
    assert basis.muscles[1].side == "L" and basis.muscles[0].region == "lower"
    chin = load_landmark_set(tmp_path / "lm.toml").positions(basis.neutral, basis.triangles)[-1]
    jaw = basis.elements[0]
    near_chin = np.linalg.norm(basis.neutral - chin, axis=1) < 10
    assert np.linalg.norm(jaw[near_chin], axis=1).mean() > 15  # the ICT jaw opens ~20-40 mm at the chin
    grid_mesh = read_scan(tmp_path / "grid.obj")
    assert grid_mesh.triangles.shape == basis.triangles.shape
    assert np.allclose(grid_mesh.points, basis.neutral, atol=1e-5)  # the OBJ is the basis's (fitted) neutral


# ------------------------------------------------------------------------------------------------ bad scans
@pytest.fixture(scope="module")
def small_scans(tmp_path_factory):
    """A neutral and a jaw scan of the built-in face (8000 points, no colour) with their landmark files."""
    folder = tmp_path_factory.mktemp("scans")
    write_builtin_scans(folder, 3, {"neutral": "neutral", "jaw": "jaw"})
    return folder


def _spoil(folder, name, points=None, landmarks=None):
    """Rewrite ``name``'s scan by ``points(p)`` and its landmarks by ``landmarks(dict)``."""
    if points is not None:
        write_ply(folder / f"{name}.ply", points(read_scan(folder / f"{name}.ply").points), None, "ascii")
    if landmarks is not None:
        from livebridge.retarget.point_files import read_points_csv

        marks = landmarks(read_points_csv(folder / f"{name}.landmarks.csv"))
        (folder / f"{name}.landmarks.csv").write_text("".join(f"{k},{x},{y},{z}\n" for k, (x, y, z) in marks.items()))


def _flat(p):
    return p * [1.0, 1.0, 0.0]


def _moved(name, by):
    return lambda marks: {**marks, name: marks[name] + by}


def _same(marks):
    return {name: marks["nose_tip"] for name in marks}


def _sides_swapped(marks):
    swap = {"_L": "_R", "_R": "_L"}
    return {name[:-2] + swap[name[-2:]] if name[-2:] in swap else name: xyz for name, xyz in marks.items()}


BAD_SCANS = [  # (case, scan to spoil, its points, its landmarks, extra options, words of the error)
    ("a flat neutral", "neutral", _flat, lambda m: {k: _flat(v) for k, v in m.items()}, (),
     ("neutral.ply", "points", "flat")),
    ("the neutral in metres", "neutral", lambda p: p / 1000, lambda m: {k: v / 1000 for k, v in m.items()}, (),
     ("neutral.landmarks.csv", "units", "is it in mm?")),
    ("the neutral scan in metres, its landmarks in mm", "neutral", lambda p: p / 1000, None, (),
     ("neutral.ply", "no point of the scan", "same units")),
    ("the neutral's left and right swapped", "neutral", None, _sides_swapped, (),
     ("neutral.landmarks.csv", "left and right swapped")),
    ("the neutral mirrored", "neutral", lambda p: p * [-1, 1, 1], lambda m: {k: v * [-1, 1, 1] for k, v in m.items()},
     (), ("neutral.landmarks.csv", "mirrored")),
    ("the neutral's landmarks at one point", "neutral", None, _same, (), ("neutral.landmarks.csv", "both at")),
    ("a crop radius of 9 m", "neutral", None, None, ("--crop-radius", "9000"), ("neutral.landmarks.csv", "points",
                                                                                "no surface")),
    ("an expression landmark 50 mm off", "jaw", None, _moved("chin", [0, 0, 50]), (),
     ("jaw.landmarks.csv", "chin", "from the nearest point of jaw.ply")),
    ("an expression scan of one point", "jaw", lambda p: p[:1], None, (), ("jaw.landmarks.csv", "jaw.ply")),
    ("an expression in metres", "jaw", lambda p: p / 1000, lambda m: {k: v / 1000 for k, v in m.items()}, (),
     ("jaw.ply", "landmarks", "0.00", "times as far apart")),
    ("an expression 1.3 times the size", "jaw", lambda p: p * 1.3, lambda m: {k: v * 1.3 for k, v in m.items()}, (),
     ("jaw.ply", "landmarks", "1.3", "times as far apart")),
    ("an expression's left and right landmarks swapped", "jaw", None, lambda m: {_mirrored(k): v for k, v in m.items()},
     (), ("jaw.landmarks.csv", "inside out", "left and right")),
]


def _mirrored(name: str) -> str:
    return name.replace("_L", "_X").replace("_R", "_L").replace("_X", "_R")


@pytest.mark.parametrize("case,name,points,landmarks,extra,words", BAD_SCANS, ids=[c[0] for c in BAD_SCANS])
def test_retarget_scans_refuses_a_bad_scan_naming_the_file_and_landmark(tmp_path, small_scans, case, name, points,
                                                                        landmarks, extra, words):
    import shutil

    from livebridge.cli import main

    for path in small_scans.iterdir():
        shutil.copy(path, tmp_path / path.name)
    _spoil(tmp_path, name, points, landmarks)
    result = CliRunner().invoke(main, [
        "retarget", "scans", "--neutral", str(tmp_path / "neutral.ply"), "--neutral-landmarks",
        str(tmp_path / "neutral.landmarks.csv"), "--expression", f"jaw={tmp_path / 'jaw.ply'}", "--grid", "40x40",
        "--out", str(tmp_path / "b.npz"), *extra])
    assert_cli_refused(result, *words)
    assert not (tmp_path / "b.npz").exists()


def _occluded(points, marks, forward_mm):
    """A scan with a hand before its left cheek: the skin within 25 mm of the point between the left mouth corner
    and outer eye corner is gone (the scanner cannot see it), and the hand's surface is there instead,
    ``forward_mm`` towards the scanner."""
    forward = marks["nose_tip"] - np.mean([marks["eye_outer_L"], marks["eye_outer_R"], marks["chin"]], axis=0)
    forward /= np.linalg.norm(forward)
    cheek = 0.5 * (marks["mouth_corner_L"] + marks["eye_outer_L"])
    behind = np.linalg.norm(points - cheek, axis=1) < 25.0
    return points[~behind], np.vstack([points[~behind], points[behind] + forward_mm * forward])


def test_something_between_the_scanner_and_the_face_is_left_out_and_said(tmp_path, small_scans, monkeypatch):
    """A hand 40 mm before the cheek is the surface the scanner saw first there: the resampling would take it for
    the face. Off the neutral's face by more than OFF_FACE_MM once registered, it is left out: the element is the
    one the scan with the hole alone gives, and the build says what it left out."""
    import shutil

    import livebridge.retarget.face_scan as face_scan_module
    from livebridge.cli import main
    from livebridge.face.basis import Basis
    from livebridge.retarget.point_files import read_points_csv

    marks = read_points_csv(small_scans / "jaw.landmarks.csv")
    holed, with_hand = _occluded(read_scan(small_scans / "jaw.ply").points, marks, 40.0)

    def build(points, out):
        for path in small_scans.iterdir():
            shutil.copy(path, tmp_path / path.name)
        write_ply(tmp_path / "jaw.ply", points, None, "ascii")
        result = CliRunner().invoke(main, [
            "retarget", "scans", "--neutral", str(tmp_path / "neutral.ply"), "--neutral-landmarks",
            str(tmp_path / "neutral.landmarks.csv"), "--expression", f"jaw={tmp_path / 'jaw.ply'}", "--grid",
            "40x40", "--out", str(tmp_path / out)])
        assert result.exit_code == 0, result.output
        return Basis.load(tmp_path / out).elements[0], result.output

    reference, said = build(holed, "holed.npz")
    assert "left out" not in said
    element, said = build(with_hand, "hand.npz")
    assert "jaw (jaw.ply)" in said and "left out" in said and "a hand" in said
    size = np.sqrt(np.mean(np.sum(reference ** 2, axis=1)))
    assert np.sqrt(np.mean(np.sum((element - reference) ** 2, axis=1))) < 0.02 * size  # 0.005 measured
    monkeypatch.setattr(face_scan_module, "OFF_FACE_MM", np.inf)  # the hand kept: the element is not the jaw's
    spoiled, _ = build(with_hand, "kept.npz")
    assert np.sqrt(np.mean(np.sum((spoiled - reference) ** 2, axis=1))) > 0.15 * size  # 0.23 measured


def test_something_before_the_face_in_the_neutral_scan_is_told(tmp_path, small_scans):
    """The neutral is the reference the expressions are registered on, so nothing can be cut from it; but no
    expression comes near a hand held before its cheek, and the build says where that is."""
    import shutil

    from livebridge.cli import main
    from livebridge.retarget.point_files import read_points_csv

    def build(folder, out):
        return CliRunner().invoke(main, [
            "retarget", "scans", "--neutral", str(folder / "neutral.ply"), "--expression", f"jaw={folder / 'jaw.ply'}",
            "--grid", "40x40", "--out", str(out)])

    clean = build(small_scans, tmp_path / "clean.npz")
    assert clean.exit_code == 0, clean.output
    assert "warning" not in clean.output
    for path in small_scans.iterdir():
        shutil.copy(path, tmp_path / path.name)
    marks = read_points_csv(small_scans / "neutral.landmarks.csv")
    _, with_hand = _occluded(read_scan(small_scans / "neutral.ply").points, marks, 40.0)
    write_ply(tmp_path / "neutral.ply", with_hand, None, "ascii")
    told = build(tmp_path, tmp_path / "told.npz")
    assert told.exit_code == 0, told.output
    assert "warning: neutral.ply" in told.output and "a hand" in told.output and "hole in the expression" in told.output


def test_the_build_tells_of_each_element_in_both_passes():
    """Coloured scans are tracked twice (against the neutral, then against the template of all the scans' skin):
    each pass names each element as it starts, so a build of minutes shows where it is."""
    from livebridge.face.builtin import builtin_basis
    from livebridge.retarget.face_scan import prepare_expression, prepare_neutral
    from livebridge.retarget.landmarks import load_landmark_set
    from livebridge.retarget.scans import basis_from_scans

    neutral_scan, scans = synthetic_scans(builtin_basis(), load_landmark_set("builtin-22"), np.random.default_rng(6),
                                          n_points=8000, hole_muscle=None, muscles=("jaw", "zygomatic_major_L"))
    neutral = prepare_neutral(neutral_scan.as_scan(), neutral_scan.landmarks, neutral_scan.landmarks, shape=(40, 40))
    faces = {name: prepare_expression(scan.as_scan(), scan.landmarks, neutral) for name, scan in scans.items()}
    lines = []
    basis_from_scans(neutral, faces, log=lines.append)
    first, second = faces
    assert [line.strip() for line in lines[:4]] == [
        f"{first}: tracking the skin (1/2, first pass, against the neutral)",
        f"{second}: tracking the skin (2/2, first pass, against the neutral)",
        f"{first}: tracking the skin (1/2, second pass, against the template)",
        f"{second}: tracking the skin (2/2, second pass, against the template)"]
    # and what it took out of both (retarget/neutral_noise.py), in mm
    assert len(lines) == 5 and re.fullmatch(r"the neutral scan's own noise, which every tracked element shares: "
                                            r"0\.\d\d mm RMS, taken out of all 2", lines[4].strip()), lines[4:]


@pytest.mark.parametrize("units, factor", [("m", 0.001), ("cm", 0.1)])
def test_retarget_scans_in_other_units_are_refused_naming_the_landmarks_and_units(tmp_path, units, factor):
    """Scans and landmarks written in metres or centimetres, read as mm: the crop then held no point and the
    error asked about the nose tip and the crop radius; now the size of the neutral's landmarks against the
    reference face's says which unit, before any work, and with ``--units`` the same files build."""
    from livebridge.cli import main
    from livebridge.retarget.ply_file import write_ply
    from livebridge.retarget.scan import read_scan

    write_builtin_scans(tmp_path, 6, {"neutral": "mm", "jaw": "jaw_mm"})
    for stem in ("mm", "jaw_mm"):
        write_ply(tmp_path / f"{stem[:-2]}{units}.ply", read_scan(tmp_path / f"{stem}.ply").points * factor, None,
                  "ascii")
        rows = (tmp_path / f"{stem}.landmarks.csv").read_text().splitlines()[1:]
        (tmp_path / f"{stem[:-2]}{units}.landmarks.csv").write_text("".join(
            f"{name},{float(x) * factor!r},{float(y) * factor!r},{float(z) * factor!r}\n"
            for name, x, y, z in (row.split(",") for row in rows)))
    args = ["retarget", "scans", "--neutral", str(tmp_path / f"{units}.ply"), "--neutral-landmarks",
            str(tmp_path / f"{units}.landmarks.csv"), "--expression", f"jaw={tmp_path / f'jaw_{units}.ply'}",
            "--grid", "40x40", "--out", str(tmp_path / "basis.npz")]
    assert_cli_refused(CliRunner().invoke(main, args), f"{units}.landmarks.csv", "units", "times the reference",
                       "is it in mm?")
    result = CliRunner().invoke(main, [*args, "--units", units])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "basis.npz").exists()


def test_the_basis_is_written_on_the_scan_with_frame_scan(tmp_path):
    """``--frame scan`` writes the basis (and the grid OBJ) in the neutral scan's own coordinates: on its points,
    whatever the normalisation; the rigid build is the face-frame basis moved rigidly, elements turned with it."""
    from livebridge.cli import main
    from livebridge.face.basis import Basis
    from livebridge.geometry.transforms import umeyama
    from livebridge.retarget.landmarks import surface_values

    write_builtin_scans(tmp_path, 6, {"neutral": "neutral", "jaw": "jaw"})
    points = read_scan(tmp_path / "neutral.ply").points
    built = {}
    for frame, method in (("face", "rigid"), ("scan", "rigid"), ("scan", "affine")):
        tag = f"{frame}_{method}"
        result = CliRunner().invoke(main, [
            "retarget", "scans", "--neutral", str(tmp_path / "neutral.ply"), "--neutral-landmarks",
            str(tmp_path / "neutral.landmarks.csv"), "--expression", f"jaw={tmp_path / 'jaw.ply'}", "--grid", "40x40",
            "--frame", frame, "--normalise", method, "--out", str(tmp_path / f"{tag}.npz"), "--grid-obj",
            str(tmp_path / f"{tag}.obj")])
        assert result.exit_code == 0, result.output
        assert f"{frame} frame" in result.output
        built[tag] = Basis.load(tmp_path / f"{tag}.npz")
        assert np.allclose(read_scan(tmp_path / f"{tag}.obj").points, built[tag].neutral, atol=1e-5)
    def on_it(basis):  # the share of the scan's points within 0.5 mm of the basis's neutral surface
        on = surface_values(points, basis.neutral, basis.triangles, basis.neutral)
        return float(np.mean(np.linalg.norm(points - on, axis=1) < 0.5))

    share = {tag: on_it(basis) for tag, basis in built.items()}
    assert share["face_rigid"] < 0.01, share  # the scan is posed away from the face frame
    # the grid covers the face crop, about half of the scan (measured 0.42 in both)
    assert share["scan_rigid"] > 0.35 and share["scan_affine"] > 0.35, share
    face, scan = built["face_rigid"], built["scan_rigid"]
    face2scan = umeyama(face.neutral, scan.neutral, with_scale=False)
    np.testing.assert_allclose(apply(face2scan, face.neutral), scan.neutral, atol=1e-6)
    np.testing.assert_allclose(face.elements @ face2scan[:3, :3].T, scan.elements, atol=1e-6)


def test_a_reference_face_without_the_normalisation_landmarks_is_refused_naming_its_file(tmp_path):
    from livebridge.cli import main

    write_builtin_scans(tmp_path, 6, {"neutral": "neutral", "jaw": "jaw"})
    (tmp_path / "reference.csv").write_text("nose_tip,0,0,0\nbrow_inner_L,10,50,-20\n")
    result = CliRunner().invoke(main, [
        "retarget", "scans", "--neutral", str(tmp_path / "neutral.ply"), "--neutral-landmarks",
        str(tmp_path / "neutral.landmarks.csv"), "--expression", f"jaw={tmp_path / 'jaw.ply'}", "--reference",
        str(tmp_path / "reference.csv"), "--out", str(tmp_path / "basis.npz")])
    assert_cli_refused(result, "reference.csv", "missing: eye_outer_L, eye_outer_R, chin")


def test_scans_of_one_colour_everywhere_are_built_from_their_shape_and_say_so(tmp_path):
    """Some exporters write every point white: tracking that 'skin' followed nothing (a basis 0.63-0.73 off
    where shape alone gave 0.59, each element said to be skin tracked). One colour over the face is no pattern:
    the build is the shape-only one, and the CLI says there is no colour."""
    from livebridge.cli import main
    from livebridge.face.basis import Basis
    from livebridge.retarget.ply_file import write_ply
    from livebridge.retarget.scan import read_scan

    write_builtin_scans(tmp_path, 6, {"neutral": "neutral", "jaw": "jaw"})
    for stem in ("neutral", "jaw"):
        points = read_scan(tmp_path / f"{stem}.ply").points
        write_ply(tmp_path / f"{stem}_white.ply", points, None, "ascii", colours=np.ones((len(points), 3)))
        (tmp_path / f"{stem}_white.landmarks.csv").write_text((tmp_path / f"{stem}.landmarks.csv").read_text())
    built = {}
    for tag in ("", "_white"):
        result = CliRunner().invoke(main, [
            "retarget", "scans", "--neutral", str(tmp_path / f"neutral{tag}.ply"), "--neutral-landmarks",
            str(tmp_path / f"neutral{tag}.landmarks.csv"), "--expression", f"jaw={tmp_path / f'jaw{tag}.ply'}",
            "--grid", "40x40", "--out", str(tmp_path / f"basis{tag}.npz")])
        assert result.exit_code == 0, result.output
        assert "(shape only)" in result.output and "note: no colour in the neutral scan" in result.output
        built[tag] = Basis.load(tmp_path / f"basis{tag}.npz").elements
    np.testing.assert_allclose(built["_white"], built[""], atol=1e-9)


def test_a_landmark_file_given_as_the_expression_scan_is_refused_as_too_sparse(tmp_path):
    """An expression 'scan' of its own 22 landmarks (a user's slip: --expression jaw=jaw.landmarks.csv) built a
    36 mm jaw from a spline through them; the face crop's points must lie within a few grid cells."""
    from livebridge.cli import main

    write_builtin_scans(tmp_path, 6, {"neutral": "neutral", "jaw": "jaw"})
    landmarks = tmp_path / "jaw.landmarks.csv"
    result = CliRunner().invoke(main, [
        "retarget", "scans", "--neutral", str(tmp_path / "neutral.ply"), "--neutral-landmarks",
        str(tmp_path / "neutral.landmarks.csv"), "--expression", f"jaw={landmarks}:{landmarks}", "--grid", "40x40",
        "--out", str(tmp_path / "basis.npz")])
    assert_cli_refused(result, "jaw.landmarks.csv", "points", "too sparse", "--grid")


def test_landmarks_of_a_68_point_detector_build_as_the_thesis_s_22(tmp_path):
    """Landmark files that number the 68 iBUG points (what dlib or face-alignment write) build the basis as the
    thesis's 22 names do: the built-in face's smile and jaw, shape only, within 0.05 of the 22's errors (measured
    68: 0.75 / 0.25, 22: 0.78 / 0.31 relative RMS); and through the command, whose landmark file out names the 22."""
    from livebridge.cli import main
    from livebridge.face.builtin import builtin_basis
    from livebridge.retarget.landmarks import THESIS_22_NAMES, LandmarkSet, load_landmark_set

    errors = {landmarks: build_and_measure(builtin_basis(), load_landmark_set(landmarks), np.random.default_rng(5),
                                           grid=(60, 60), n_points=8000, hole_muscle=None, colour=False,
                                           muscles=("zygomatic_major_L", "jaw")).errors_without_colour
              for landmarks in ("builtin-22", "builtin-68")}
    assert (errors["builtin-68"] < errors["builtin-22"] + 0.05).all(), errors
    write_builtin_scans(tmp_path, 5, {"neutral": "neutral", "jaw": "jaw"}, landmarks="builtin-68")
    assert "lm_30," in (tmp_path / "jaw.landmarks.csv").read_text()
    result = CliRunner().invoke(main, [
        "retarget", "scans", "--neutral", str(tmp_path / "neutral.ply"), "--expression", f"jaw={tmp_path / 'jaw.ply'}",
        "--grid", "40x40", "--out", str(tmp_path / "basis.npz"), "--landmarks-out", str(tmp_path / "lm.toml")])
    assert result.exit_code == 0, result.output
    assert set(THESIS_22_NAMES) <= set(LandmarkSet.load(tmp_path / "lm.toml").names)
