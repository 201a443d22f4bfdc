"""Textured scan meshes: OBJ ``vt`` / MTL ``map_Kd`` and PLY ``TextureFile`` / ``texcoord`` read against the
images written, the textured surface sampled into coloured points against the texture's known colours, and bad
textured files refused by name."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from livebridge.errors import InputError
from livebridge.retarget.scan import read_scan, write_textured_obj
from livebridge.retarget.texture import sample_textured

SQUARE = np.array([[0.0, 0.0, 0.0], [40.0, 0.0, 0.0], [40.0, 30.0, 0.0], [0.0, 30.0, 0.0]])
"""A 40 x 30 mm quad, mapped onto texture coordinates [0.1, 0.9] x [0.2, 0.8]."""
SQUARE_UV = np.array([[0.1, 0.2], [0.9, 0.2], [0.9, 0.8], [0.1, 0.8]])
SQUARE_TRIANGLES = np.array([[0, 1, 2], [0, 2, 3]])


def _gradient(size: int = 64) -> np.ndarray:
    """An image whose colour at texture coordinates (u, v) is (u, v, 0.5) at every texel centre."""
    centres = (np.arange(size) + 0.5) / size
    u, v = np.meshgrid(centres, centres[::-1])  # row 0 at the top: v = 1 there
    return np.dstack([u, v, np.full_like(u, 0.5)])


def _uv_at(points: np.ndarray) -> np.ndarray:
    """The texture coordinates (k, 2) of points on :data:`SQUARE` (linear in x, y)."""
    return np.column_stack([0.1 + 0.8 * points[:, 0] / 40.0, 0.2 + 0.6 * points[:, 1] / 30.0])


def test_textured_obj_is_sampled_into_points_coloured_as_its_image(tmp_path):
    write_textured_obj(tmp_path / "quad.obj", SQUARE, SQUARE_TRIANGLES, SQUARE_UV, _gradient())
    scan = read_scan(tmp_path / "quad.obj")
    assert scan.texture is not None and scan.has_colour and scan.colours is None
    assert scan.texture.names == ("quad.png",) and scan.texture.images[0].shape == (64, 64, 3)
    np.testing.assert_allclose(scan.texture.uv[0], SQUARE_UV[[0, 1, 2]], atol=1e-6)

    points = scan.as_points(spacing=0.5)
    assert not points.texture and not points.is_mesh
    assert abs(len(points.points) - 40 * 30 / 0.5 ** 2) < 0.1 * 40 * 30 / 0.5 ** 2  # a point per spacing^2
    assert np.all((points.points[:, 0] > 0) & (points.points[:, 0] < 40) & (points.points[:, 1] > 0)
                  & (points.points[:, 1] < 30) & (points.points[:, 2] == 0))
    expected = np.column_stack([_uv_at(points.points), np.full(len(points.points), 0.5)])
    # bilinear lookups of a linear image are exact up to the 16-bit PNG's rounding
    np.testing.assert_allclose(points.colours, expected, atol=2e-4)


def test_only_the_triangles_near_the_centre_are_sampled(tmp_path):
    write_textured_obj(tmp_path / "quad.obj", SQUARE, SQUARE_TRIANGLES, SQUARE_UV, _gradient())
    scan = read_scan(tmp_path / "quad.obj")
    near_corner = scan.as_points(np.array([40.0, 0.0, 0.0]), 5.0, spacing=1.0)  # only triangle 0 has that corner
    inside = near_corner.points[:, 0] > near_corner.points[:, 1] * 40 / 30
    assert len(near_corner.points) > 0 and inside.all()


def test_materials_with_map_options_each_colour_their_own_faces(tmp_path):
    for name, bgr in (("red", (0, 0, 255)), ("blue", (255, 0, 0))):
        cv2.imwrite(str(tmp_path / f"{name}.png"), np.full((8, 8, 3), bgr, np.uint8))
    (tmp_path / "two.mtl").write_text("newmtl a\nmap_Kd -s 1 1 1 -clamp on red.png\n\nnewmtl b\nKd 1 1 1\n"
                                      "map_Kd blue.png\n")
    (tmp_path / "two.obj").write_text(
        "mtllib two.mtl\n" + "".join(f"v {x} {y} {z}\n" for x, y, z in SQUARE)
        + "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nusemtl a\nf 1/1 2/2 3/3\nusemtl b\nf 1/1/1 3/3/1 4/4/1\n")
    scan = read_scan(tmp_path / "two.obj")
    assert scan.texture.names == ("red.png", "blue.png")
    points = scan.as_points(spacing=1.0)
    lower = points.points[:, 0] * 30 / 40 > points.points[:, 1]  # triangle 1 2 3 (material a)
    np.testing.assert_allclose(points.colours[lower], [[1, 0, 0]] * lower.sum(), atol=1e-6)
    np.testing.assert_allclose(points.colours[~lower], [[0, 0, 1]] * (~lower).sum(), atol=1e-6)


def test_faces_without_texture_coordinates_give_points_without_colour(tmp_path):
    cv2.imwrite(str(tmp_path / "grey.png"), np.full((4, 4, 3), 128, np.uint8))
    (tmp_path / "m.mtl").write_text("newmtl skin\nmap_Kd grey.png\n")
    (tmp_path / "part.obj").write_text(
        "mtllib m.mtl\nusemtl skin\n" + "".join(f"v {x} {y} {z}\n" for x, y, z in SQUARE)
        + "vt 0 0\nvt 1 0\nvt 1 1\nf 1/1 2/2 3/3\nf 1 3 4\n")
    points = read_scan(tmp_path / "part.obj").as_points(spacing=1.0)
    coloured = np.isfinite(points.colours).all(axis=1)
    assert coloured.any() and not coloured.all()
    np.testing.assert_allclose(points.colours[coloured], 128 / 255, atol=1e-6)
    assert np.all(points.points[~coloured, 1] > points.points[~coloured, 0] * 30 / 40)  # the second face's


def test_texels_finer_than_the_samples_are_averaged_not_aliased():
    """A checkerboard of 0.1 mm texels sampled every 0.5 mm: without the blur to the samples' footprint each
    sample would take one texel (black or white, standard deviation 0.5)."""
    board = np.indices((400, 400)).sum(axis=0) % 2
    image = np.repeat(board[..., None], 3, axis=2).astype(np.float32)
    corners = SQUARE * [1.0, 40 / 30, 1.0]  # 40 x 40 mm over the 400 x 400 texels
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=float)
    from livebridge.retarget.texture import Texture

    texture = Texture(uv[SQUARE_TRIANGLES], np.zeros(2, int), (image,), ("board.png",))
    _, colours = sample_textured(corners, SQUARE_TRIANGLES, texture, spacing=0.5)
    assert abs(colours.mean() - 0.5) < 0.02
    assert colours.std() < 0.1


@pytest.mark.parametrize("case,edit,words", [
    ("the material file missing", lambda d: (d / "quad.mtl").unlink(), ("quad.obj", "mtllib", "quad.mtl")),
    ("the image missing", lambda d: (d / "quad.png").unlink(), ("quad.mtl", "skin.map_Kd", "quad.png", "not there")),
    ("the image not an image", lambda d: (d / "quad.png").write_text("not a png"),
     ("quad.mtl", "skin.map_Kd", "quad.png", "could not be read")),
    ("a texture coordinate that is not there", lambda d: (d / "quad.obj").write_text(
        (d / "quad.obj").read_text().replace("f 1/1 2/2 3/3", "f 1/1 2/9 3/3")),
     ("quad.obj", "line", "texture coordinate 9")),
    ("a texture coordinate that is not a number", lambda d: (d / "quad.obj").write_text(
        (d / "quad.obj").read_text().replace("vt 0.1000000 0.2000000", "vt 0.1 x")), ("quad.obj", "line 6", "numbers")),
])
def test_a_bad_textured_scan_names_the_file_and_what_is_wrong(tmp_path, case, edit, words):
    write_textured_obj(tmp_path / "quad.obj", SQUARE, SQUARE_TRIANGLES, SQUARE_UV, _gradient())
    edit(tmp_path)
    _assert_refused(tmp_path / "quad.obj", case, words)


def _assert_refused(path, case: str, words) -> None:
    """Reading the scan at ``path`` is one :class:`InputError` holding every one of ``words``."""
    with pytest.raises(InputError) as error:
        read_scan(path)
    message = str(error.value)
    for word in words:
        assert word in message, (case, message)


@pytest.mark.parametrize("size", [64, 2048])
def test_the_default_spacing_is_half_a_millimetre_whatever_the_texels(tmp_path, size):
    """Texels of 0.78 mm (a 64 px image on the quad) or 0.024 mm (2048 px): a point per 0.5^2 mm^2 either way."""
    write_textured_obj(tmp_path / "quad.obj", SQUARE, SQUARE_TRIANGLES, SQUARE_UV, _gradient(size))
    points = read_scan(tmp_path / "quad.obj").as_points()
    assert abs(len(points.points) / (40 * 30 / 0.5 ** 2) - 1) < 0.1


def test_retarget_scans_cli_tracks_the_skin_of_textured_meshes(tmp_path, ict):
    """A neutral and a smile written as textured OBJ meshes (what most face scanners export): the skin is
    tracked in the texture, and the smile's element is within the issue's 10% of the ICT element (measured
    0.037 here); read without their texture (no mtllib) the same meshes give 0.60, shape alone."""
    from click.testing import CliRunner

    from livebridge.bench.scans import synthetic_scans, truth_on_grid
    from livebridge.cli import main
    from livebridge.cli.retarget_scans import reference_landmarks
    from livebridge.face.basis import Basis
    from livebridge.retarget.basis import relative_errors
    from livebridge.retarget.landmarks import load_landmark_set
    from livebridge.retarget.normalise import normalisation

    landmarks = load_landmark_set("ict-22")
    neutral, expressions = synthetic_scans(ict, landmarks, np.random.default_rng(3), hole_muscle=None,
                                           muscles=("zygomatic_major_L",), textured=True)
    for name, scan in (("neutral", neutral), ("smile", expressions["zygomatic_major_L"])):
        texture = scan.texture
        uv = np.zeros((len(scan.points), 2))
        uv[scan.triangles] = texture.uv  # per vertex: the simulated texture has one place per vertex
        write_textured_obj(tmp_path / f"{name}.obj", scan.points, scan.triangles, uv, texture.images[0])
        rows = "".join(f"{k},{x:.4f},{y:.4f},{z:.4f}\n" for k, (x, y, z) in scan.landmarks.items())
        (tmp_path / f"{name}.landmarks.csv").write_text("name,x,y,z\n" + rows)

    def build(out):
        result = CliRunner().invoke(main, [
            "retarget", "scans", "--neutral", str(tmp_path / "neutral.obj"), "--neutral-landmarks",
            str(tmp_path / "neutral.landmarks.csv"), "--expression", f"zygomatic_major_L={tmp_path / 'smile.obj'}",
            "--grid", "80x90", "--out", str(out)])
        assert result.exit_code == 0, result.output
        basis = Basis.load(out)
        face2scan = normalisation(neutral.landmarks, reference_landmarks("builtin", 1.0), "rigid")
        truth = truth_on_grid(ict, neutral, SimpleNamespace(scan2face=face2scan, mesh_vertices=basis.neutral),
                              basis.names)
        return result.output, float(relative_errors(basis.elements, truth)[0])

    output, error = build(tmp_path / "textured.npz")
    assert "skin tracked" in output and "no colour" not in output
    for name in ("neutral", "smile"):  # the same meshes without their texture
        obj = tmp_path / f"{name}.obj"
        obj.write_text("\n".join(line for line in obj.read_text().splitlines() if not line.startswith("mtllib")))
    output_plain, error_plain = build(tmp_path / "plain.npz")
    assert "shape only" in next(line for line in output_plain.splitlines() if "largest motion" in line)
    assert error <= 0.10 and error < 0.5 * error_plain, (error, error_plain)


@pytest.mark.parametrize("statement,image", [
    ("map_Kd skin.png", "skin.png"),
    ("map_Kd -s 1 1 1 -clamp on skin.png", "skin.png"),
    ("map_Kd -o 0.5 0.5 skin.png", "skin.png"),  # -o, -s and -t take 1 to 3 numbers
    ("map_Kd -bm 0.8 my skin.png", "my skin.png"),
    ("map_Kd  textures/skin 2.jpg ", "textures/skin 2.jpg"),
])
def test_map_kd_options_are_skipped_to_the_image_name(tmp_path, statement, image):
    from livebridge.retarget.texture import read_materials

    (tmp_path / "m.mtl").write_text(f"# exported\nnewmtl face\nKd 1 1 1\n{statement}\n")
    assert read_materials(tmp_path / "m.mtl", tmp_path / "m.obj") == {"face": tmp_path / image}


# ------------------------------------------------------------------------------------------------ PLY
PLY_POINTS = np.vstack([SQUARE, [[20.0, 0.0, 0.0], [20.0, 30.0, 0.0], [20.0, 36.0, 0.0]]])
""":data:`SQUARE`, its bottom and top middles and a point above the top: faces of every kind on the quad's map."""
PLY_FACES = {
    "triangles": [[0, 1, 2], [0, 2, 3]],
    "quads": [[0, 4, 5, 3], [4, 1, 2, 5]],  # binary: rows of one length, read as one array
    "quads and a triangle": [[0, 4, 5, 3], [4, 1, 2, 5], [3, 5, 6]],  # binary: ragged rows, read one by one
}
PLY_AREA = {"triangles": 1200.0, "quads": 1200.0, "quads and a triangle": 1200.0 + 0.5 * 40 * 6}


def _write_image(path, rgb) -> None:
    """``rgb`` (h, w, 3) in 0-1 as a 16-bit PNG."""
    cv2.imwrite(str(path), np.round(np.asarray(rgb)[..., ::-1] * 65535).astype(np.uint16))


def _write_textured_ply(path, encoding="ascii", faces=PLY_FACES["triangles"], texcoords="corners", texnumbers=None,
                        vertex_uv=None, textures=("gradient.png",), vertex_colours=True, points=PLY_POINTS,
                        vertex_uv_values=None):
    """A PLY as MeshLab writes a textured mesh, by hand: a ``comment TextureFile`` per texture, vertices x y z
    (with ``vertex_uv``: those two properties, ``vertex_uv_values`` or :func:`_uv_at` of the point) and uchar
    red green blue, faces'
    ``vertex_indices``, ``texcoord`` (``"corners"``: :func:`_uv_at` of each corner; a list: the values per face;
    None: no texcoord) and ``texnumbers``."""
    if isinstance(texcoords, str):
        texcoords = [_uv_at(points[face]).ravel().tolist() for face in faces]
    header = ["ply", f"format {encoding} 1.0", "comment made by a scanner"]
    header += [f"comment TextureFile {name}" for name in textures]
    header += [f"element vertex {len(points)}"] + [f"property float {axis}" for axis in "xyz"]
    vertices = [list(point) for point in points]
    if vertex_uv is not None:
        header += [f"property float {name}" for name in vertex_uv]
        uv = _uv_at(points) if vertex_uv_values is None else vertex_uv_values
        vertices = [row + list(pair) for row, pair in zip(vertices, uv)]
    if vertex_colours:
        header += [f"property uchar {name}" for name in ("red", "green", "blue")]
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    header += ["property list uchar float texcoord"] * (texcoords is not None)
    header += ["property int texnumber"] * (texnumbers is not None) + ["end_header", ""]
    if encoding == "ascii":
        rows = [" ".join(f"{value:g}" for value in row) + " 200 10 10" * vertex_colours for row in vertices]
        for k, face in enumerate(faces):
            cells = [len(face), *face]
            cells += [] if texcoords is None else [len(texcoords[k]), *texcoords[k]]
            cells += [] if texnumbers is None else [texnumbers[k]]
            rows.append(" ".join(f"{value:.9g}" for value in cells))
        body = "".join(row + "\n" for row in rows).encode()
    else:
        order = "<" if encoding == "binary_little_endian" else ">"
        parts = [np.array(row, order + "f4").tobytes() + bytes([200, 10, 10] * vertex_colours) for row in vertices]
        for k, face in enumerate(faces):
            parts.append(bytes([len(face)]) + np.array(face, order + "i4").tobytes())
            if texcoords is not None:
                parts.append(bytes([len(texcoords[k])]) + np.array(texcoords[k], order + "f4").tobytes())
            if texnumbers is not None:
                parts.append(np.array(texnumbers[k], order + "i4").tobytes())
        body = b"".join(parts)
    path.write_bytes("\n".join(header).encode() + body)


@pytest.mark.parametrize("layout", list(PLY_FACES))
@pytest.mark.parametrize("encoding", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_textured_ply_is_sampled_into_points_coloured_as_its_image(tmp_path, encoding, layout):
    """Triangles, quads and a mix (each quad's texcoord fanned as its vertices), colours per vertex ignored
    for the texture's."""
    _write_image(tmp_path / "gradient.png", _gradient())
    _write_textured_ply(tmp_path / "mesh.ply", encoding, PLY_FACES[layout])
    scan = read_scan(tmp_path / "mesh.ply")
    assert scan.texture is not None and scan.colours is None
    assert scan.texture.names == ("gradient.png",) and len(scan.texture.uv) == len(scan.triangles)
    np.testing.assert_allclose(scan.texture.uv, _uv_at(PLY_POINTS[scan.triangles].reshape(-1, 3)).reshape(-1, 3, 2),
                               atol=1e-6)

    points = scan.as_points(spacing=0.5)
    assert abs(len(points.points) / (PLY_AREA[layout] / 0.5 ** 2) - 1) < 0.1
    expected = np.column_stack([_uv_at(points.points), np.full(len(points.points), 0.5)])
    np.testing.assert_allclose(points.colours, expected, atol=2e-4)  # float32 texcoords and 16-bit PNG rounding


@pytest.mark.parametrize("names", [("s", "t"), ("u", "v"), ("texture_u", "texture_v"), ("texture_s", "texture_t")])
@pytest.mark.parametrize("encoding", ["ascii", "binary_little_endian"])
def test_ply_texture_coordinates_per_vertex(tmp_path, encoding, names):
    _write_image(tmp_path / "gradient.png", _gradient())
    _write_textured_ply(tmp_path / "mesh.ply", encoding, PLY_FACES["quads"], texcoords=None, vertex_uv=names)
    points = read_scan(tmp_path / "mesh.ply").as_points(spacing=1.0)
    expected = np.column_stack([_uv_at(points.points), np.full(len(points.points), 0.5)])
    np.testing.assert_allclose(points.colours, expected, atol=2e-4)


@pytest.mark.parametrize("encoding", ["ascii", "binary_little_endian"])
def test_ply_texnumber_picks_each_face_its_texture_file(tmp_path, encoding):
    """Two ``comment TextureFile`` lines (one name not ASCII) naming images in a folder beside the PLY (paths
    are relative to the PLY's folder): face 0 shows the second, face 1 the first."""
    (tmp_path / "maps").mkdir()
    _write_image(tmp_path / "maps" / "red.png", np.full((8, 8, 3), [1.0, 0.0, 0.0]))
    _write_image(tmp_path / "maps" / "blué.png", np.full((8, 8, 3), [0.0, 0.0, 1.0]))
    _write_textured_ply(tmp_path / "two.ply", encoding, texnumbers=[1, 0], textures=("maps/red.png", "maps/blué.png"))
    scan = read_scan(tmp_path / "two.ply")
    assert scan.texture.names == ("red.png", "blué.png")
    points = scan.as_points(spacing=1.0)
    lower = points.points[:, 0] * 30 / 40 > points.points[:, 1]  # face 0: 0 1 2
    np.testing.assert_allclose(points.colours[lower], [[0, 0, 1]] * lower.sum(), atol=1e-6)
    np.testing.assert_allclose(points.colours[~lower], [[1, 0, 0]] * (~lower).sum(), atol=1e-6)


def test_ply_without_a_texture_file_keeps_its_vertex_colours(tmp_path):
    _write_textured_ply(tmp_path / "plain.ply", textures=())
    scan = read_scan(tmp_path / "plain.ply")
    assert scan.texture is None
    np.testing.assert_allclose(scan.colours, [[200 / 255, 10 / 255, 10 / 255]] * len(PLY_POINTS))


NAN_CORNERS = [[0.1, 0.2, 0.9, 0.2, 0.9, 0.8], [0.1, 0.2, 0.9, float("nan"), 0.1, 0.8]]


@pytest.mark.parametrize("case,options,edit,words", [
    ("the image missing", {}, lambda d: (d / "gradient.png").unlink(),
     ("mesh.ply", "TextureFile", "gradient.png", "not there", "next to the PLY", "remove the TextureFile comment")),
    ("the image not an image", {}, lambda d: (d / "gradient.png").write_text("not a png"),
     ("mesh.ply", "TextureFile", "gradient.png", "could not be read")),
    ("texnumber out of range", {"texnumbers": [0, 1]}, None, ("mesh.ply", "texnumber", "face 1", "texnumber 1")),
    ("a negative texnumber", {"texnumbers": [-1, 0]}, None, ("mesh.ply", "texnumber", "face 0")),
    ("a texcoord list too short", {"texcoords": [[0.1] * 6, [0.1] * 5]}, None, ("mesh.ply", "texcoord", "face 1", "5")),
    ("texcoord lists all too long", {"texcoords": [[0.1] * 8, [0.1] * 8]}, None,
     ("mesh.ply", "texcoord", "face 0", "8 texcoord values for 3 corners")),
    ("a quad's texcoord for a triangle", {"faces": PLY_FACES["quads"], "texcoords": [[0.1] * 8, [0.1] * 6]}, None,
     ("mesh.ply", "texcoord", "face 1", "6 texcoord values for 4 corners")),
    ("a texcoord not finite", {"texcoords": NAN_CORNERS}, None, ("mesh.ply", "texcoord", "face 1", "not finite")),
    ("a vertex's s t not finite", {"texcoords": None, "vertex_uv": ("s", "t"),
                                   "vertex_uv_values": _uv_at(PLY_POINTS) + np.array([[0, 0]] * 3 + [[np.inf, 0]] * 4)},
     None, ("mesh.ply", "s t", "vertex 3", "not finite")),
])
@pytest.mark.parametrize("encoding", ["ascii", "binary_little_endian"])
def test_a_bad_textured_ply_names_the_file_and_what_is_wrong(tmp_path, encoding, case, options, edit, words):
    _write_image(tmp_path / "gradient.png", _gradient())
    _write_textured_ply(tmp_path / "mesh.ply", encoding, **options)
    if edit is not None:
        edit(tmp_path)
    _assert_refused(tmp_path / "mesh.ply", case, words)


@pytest.mark.parametrize("name,stored", [
    ("textures\\skin.png", "textures/skin.png"),  # written on Windows
    ("C:\\Users\\scan\\Desktop\\skin.png", "skin.png"),  # an absolute path on the machine that made the scan
    ("/home/scan/skin.png", "skin.png"),
])
def test_an_image_named_the_windows_way_or_by_another_machine_s_path_is_found_next_to_the_file(tmp_path, name,
                                                                                                stored):
    from livebridge.retarget.texture import read_materials

    (tmp_path / stored).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(tmp_path / stored), np.zeros((2, 2, 3), np.uint8))
    (tmp_path / "m.mtl").write_text(f"newmtl face\nmap_Kd {name}\n")
    assert read_materials(tmp_path / "m.mtl", tmp_path / "m.obj") == {"face": tmp_path / stored}


def test_retarget_scans_help_names_the_colour_sources():
    from click.testing import CliRunner

    from livebridge.cli import main

    result = CliRunner().invoke(main, ["retarget", "scans", "--help"])
    assert result.exit_code == 0
    text = " ".join(result.output.split())
    for words in ("textured OBJ", "map_Kd", "TextureFile", "--texture-spacing", ".landmarks.csv"):
        assert words in text, words


def test_a_textured_quad_face_is_fanned_with_its_texture_coordinates(tmp_path):
    _write_image(tmp_path / "quad.png", _gradient())
    (tmp_path / "quad.mtl").write_text("newmtl skin\nmap_Kd quad.png\n")
    (tmp_path / "quad.obj").write_text(
        "mtllib quad.mtl\n" + "".join(f"v {x} {y} {z}\n" for x, y, z in SQUARE)
        + "".join(f"vt {u} {v}\n" for u, v in SQUARE_UV[::-1]) + "usemtl skin\nf 1/4 2/3 3/2 4/1\n")
    points = read_scan(tmp_path / "quad.obj").as_points(spacing=1.0)
    assert len(points.points) > 1000
    expected = np.column_stack([_uv_at(points.points), np.full(len(points.points), 0.5)])
    np.testing.assert_allclose(points.colours, expected, atol=2e-4)


def test_a_texture_coordinate_at_the_image_edge_takes_the_edge_texel():
    """u = 1 is the right edge of the atlas: its colour, not a blend with the left edge's (no wrapping)."""
    from livebridge.retarget.texture import Texture

    image = np.array([[[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]]], np.float32)  # 4 x 1: red ... white
    for u, colour in ((1.0, [1, 1, 1]), (0.0, [1, 0, 0]), (1.2, [1, 1, 1])):
        texture = Texture(np.full((1, 3, 2), [u, 0.5]), np.zeros(1, int), (image,), ("strip.png",))
        _, colours = sample_textured(SQUARE, SQUARE_TRIANGLES[:1], texture, spacing=0.5)
        np.testing.assert_allclose(colours, [colour] * len(colours), atol=1e-6)


def test_the_anti_alias_blur_does_not_bleed_the_atlas_padding_into_the_skin():
    """A 4 x 4 mm quad on the right edge of a red chart (texels 0.05 mm, samples 0.5 mm apart: blurred), black
    padding beyond it: the samples stay red (the blur over all texels darkened the edge's to about half)."""
    from livebridge.retarget.texture import Texture

    image = np.zeros((400, 400, 3), np.uint8)
    image[:, :200] = (255, 0, 0)
    uv = np.array([[0.3, 0.3], [0.4995, 0.3], [0.4995, 0.5], [0.3, 0.5]])
    corners = SQUARE * [0.1, 4 / 30, 1.0]  # 4 x 4 mm
    texture = Texture(uv[SQUARE_TRIANGLES], np.zeros(2, int), (image,), ("atlas.png",))
    _, colours = sample_textured(corners, SQUARE_TRIANGLES, texture, spacing=0.5)
    np.testing.assert_allclose(colours, [[1, 0, 0]] * len(colours), atol=0.02)


@pytest.mark.parametrize("usemtl", ["", "usemtl other\n"])
def test_faces_showing_no_image_leave_the_vertex_colours(tmp_path, usemtl):
    """An OBJ with an image in its MTL that no face uses (no usemtl, or one naming another material): its
    vertices' colours are the colour, where the unused texture displaced them (and a scan without them was said
    to be skin tracked while built from its shape)."""
    cv2.imwrite(str(tmp_path / "grey.png"), np.full((4, 4, 3), 128, np.uint8))
    (tmp_path / "m.mtl").write_text("newmtl skin\nmap_Kd grey.png\n")
    colours = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]], float)
    (tmp_path / "scan.obj").write_text(
        "mtllib m.mtl\n" + usemtl + "".join(f"v {x} {y} {z} {r} {g} {b}\n" for (x, y, z), (r, g, b)
                                            in zip(SQUARE, colours))
        + "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n")
    scan = read_scan(tmp_path / "scan.obj")
    assert scan.texture is None
    np.testing.assert_array_equal(scan.colours, colours)
