"""``livebridge basis export``: a basis as OBJ blendshapes and the manifest ``basis import`` reads them back by;
with ``--like``, every file keeps the layout of the mesh the basis lives on (texture coordinates, quads,
materials)."""

from __future__ import annotations

import numpy as np
from click.testing import CliRunner
from factories import assert_cli_refused

from livebridge.cli import main
from livebridge.face.basis import Basis, Muscle
from livebridge.face.meshio import read_obj

SIDE = 6
"""The quad grid's vertices per side."""


def _quad_obj(path, units_per_mm: float) -> None:
    """A 6 x 6 vertex grid of quads with texture coordinates and a material, in cm when ``units_per_mm`` is 0.1."""
    lines = ["mtllib skin.mtl", "o face"]
    for j in range(SIDE):
        for i in range(SIDE):
            x, y, z = 8.0 * i, 8.0 * j, 3.0 * np.sin(i + 2 * j)
            lines += [f"v {x * units_per_mm:.6f} {y * units_per_mm:.6f} {z * units_per_mm:.6f}",
                      f"vt {i / (SIDE - 1):.4f} {j / (SIDE - 1):.4f}"]
    lines.append("usemtl skin")
    for j in range(SIDE - 1):
        for i in range(SIDE - 1):
            a = j * SIDE + i + 1
            lines.append("f " + " ".join(f"{k}/{k}" for k in (a, a + 1, a + SIDE + 1, a + SIDE)))
    path.write_text("\n".join(lines) + "\n")


def _basis_on(path, rng) -> Basis:
    """A basis on the OBJ at ``path`` (read in cm) with a Choe-Ko muscle and one of the user's own."""
    mesh = read_obj(path)
    muscles = (Muscle("jaw", "lower", None, "rotates the jaw open about its hinge"),
               Muscle("ear_wiggle", "upper", "L", "moves the left ear"))
    return Basis(mesh.vertices * 10.0, mesh.triangles, rng.normal(0.0, 2.0, (2, len(mesh.vertices), 3)), muscles)


def test_export_and_import_give_the_basis_back(tmp_path, rng):
    obj = tmp_path / "head.obj"
    _quad_obj(obj, 0.1)
    basis = _basis_on(obj, rng)
    basis.save(tmp_path / "head.npz")
    runner = CliRunner()
    for layout in ([], ["--like", str(obj)]):
        out = tmp_path / ("like" if layout else "plain")
        result = runner.invoke(main, ["basis", "export", str(tmp_path / "head.npz"), "--out", str(out),
                                      "--units", "cm", *layout])
        assert result.exit_code == 0, result.output
        again = runner.invoke(main, ["basis", "import", str(out / "basis.toml"), "--out", str(out / "back.npz")])
        assert again.exit_code == 0, again.output
        back = Basis.load(out / "back.npz")
        assert back.names == basis.names and np.array_equal(back.triangles, basis.triangles)
        assert np.allclose(back.neutral, basis.neutral, atol=1e-4)
        assert np.allclose(back.elements, basis.elements, atol=1e-4)  # written in cm, 6 decimals or 9 digits
        assert back.muscles == basis.muscles  # the user's own muscle's region, side and description too
    jaw = (tmp_path / "like" / "jaw.obj").read_text().splitlines()
    original = obj.read_text().splitlines()
    assert [line for line in jaw if not line.startswith("v ")] == [line for line in original
                                                                   if not line.startswith("v ")]
    assert sum(line.startswith("f ") and len(line.split()) == 5 for line in jaw) == (SIDE - 1) ** 2  # quads


def test_export_refuses_another_mesh_and_files_already_there(tmp_path, rng):
    obj = tmp_path / "head.obj"
    _quad_obj(obj, 0.1)
    _basis_on(obj, rng).save(tmp_path / "head.npz")
    runner = CliRunner()
    export = ["basis", "export", str(tmp_path / "head.npz"), "--out", str(tmp_path / "out")]
    assert_cli_refused(runner.invoke(main, [*export, "--like", str(obj)]), "head.obj", "--units")  # read in mm
    other = tmp_path / "other.obj"
    other.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    assert_cli_refused(runner.invoke(main, [*export, "--like", str(other), "--units", "cm"]), "other.obj",
                       "not the basis's mesh")
    stl = tmp_path / "head.stl"
    stl.write_bytes(b"\0" * 84)
    assert_cli_refused(runner.invoke(main, [*export, "--like", str(stl), "--units", "cm"]), "head.stl", "--like",
                       "not an OBJ")
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
    assert runner.invoke(main, export).exit_code == 0
    before = (tmp_path / "out" / "jaw.obj").read_bytes()
    assert_cli_refused(runner.invoke(main, [*export, "--units", "cm"]), "jaw.obj", "--force")
    assert (tmp_path / "out" / "jaw.obj").read_bytes() == before
    assert runner.invoke(main, [*export, "--units", "cm", "--force"]).exit_code == 0
    assert (tmp_path / "out" / "jaw.obj").read_bytes() != before
