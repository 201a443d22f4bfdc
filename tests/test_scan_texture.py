"""Textured scan meshes: OBJ ``vt`` / MTL ``map_Kd`` read against the images written, the textured surface
sampled into coloured points against the texture's known colours, and bad textured files refused by name."""

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

    points = scan.coloured(spacing=0.5)
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
    near_corner = scan.coloured(np.array([40.0, 0.0, 0.0]), 5.0, spacing=1.0)  # only triangle 0 has that corner
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
    points = scan.coloured(spacing=1.0)
    lower = points.points[:, 0] * 30 / 40 > points.points[:, 1]  # triangle 1 2 3 (material a)
    np.testing.assert_allclose(points.colours[lower], [[1, 0, 0]] * lower.sum(), atol=1e-6)
    np.testing.assert_allclose(points.colours[~lower], [[0, 0, 1]] * (~lower).sum(), atol=1e-6)


def test_faces_without_texture_coordinates_give_points_without_colour(tmp_path):
    cv2.imwrite(str(tmp_path / "grey.png"), np.full((4, 4, 3), 128, np.uint8))
    (tmp_path / "m.mtl").write_text("newmtl skin\nmap_Kd grey.png\n")
    (tmp_path / "part.obj").write_text(
        "mtllib m.mtl\nusemtl skin\n" + "".join(f"v {x} {y} {z}\n" for x, y, z in SQUARE)
        + "vt 0 0\nvt 1 0\nvt 1 1\nf 1/1 2/2 3/3\nf 1 3 4\n")
    points = read_scan(tmp_path / "part.obj").coloured(spacing=1.0)
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
    with pytest.raises(InputError) as error:
        read_scan(tmp_path / "quad.obj")
    message = str(error.value)
    for word in words:
        assert word in message, (case, message)


@pytest.mark.parametrize("size,spacing", [(64, 0.5), (2048, 0.3)])
def test_the_default_spacing_is_a_texel_within_its_bounds(tmp_path, size, spacing):
    """Texels of 0.78 mm (a 64 px image on the quad) give points 0.5 mm apart, the coarsest; 0.024 mm (2048 px)
    give 0.3 mm, the finest: a point per spacing^2 of surface either way."""
    write_textured_obj(tmp_path / "quad.obj", SQUARE, SQUARE_TRIANGLES, SQUARE_UV, _gradient(size))
    points = read_scan(tmp_path / "quad.obj").coloured()
    assert abs(len(points.points) / (40 * 30 / spacing ** 2) - 1) < 0.1


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
    assert "shape only" in output_plain
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
