from pathlib import Path

import numpy as np
import pytest
from factories import random_basis

from livebridge.errors import InputError
from livebridge.face.basis import Basis
from livebridge.face.basis_import import import_basis

TEST_MANIFEST = """
format = "livebridge-basis-manifest"
version = 1
neutral = "generic_neutral_mesh"
units = "{units}"
keep_vertices = 9409

[muscles]
jaw = {{ jawOpen = 1.0 }}
zygomatic_major_L = {{ mouthSmile_L = 1.0 }}
frontalis_L = {{ browInnerUp_L = 0.5 }}
"""


def write_manifest(folder: Path, units: str = "cm", text: str = TEST_MANIFEST) -> Path:
    path = folder / "manifest.toml"
    path.write_text(text.format(units=units))
    return path


def test_save_load_round_trip(tmp_path, rng):
    basis = random_basis(rng)
    basis.save(tmp_path / "b.npz")
    loaded = Basis.load(tmp_path / "b.npz")
    assert loaded.muscles == basis.muscles
    np.testing.assert_array_equal(loaded.neutral, basis.neutral)
    np.testing.assert_array_equal(loaded.triangles, basis.triangles)
    np.testing.assert_array_equal(loaded.elements, basis.elements)


def test_synthesis_is_linear_and_batched(rng):
    basis = random_basis(rng)
    x = rng.uniform(size=(5, 7, basis.n_muscles))
    faces = basis.synthesize(x)
    assert faces.shape == (5, 7, basis.n_vertices, 3)
    expected = basis.neutral + np.einsum("m,mvd->vd", x[2, 3], basis.elements)
    np.testing.assert_allclose(faces[2, 3], expected, atol=1e-12)


def test_import_obj_folder_matches_ict_deltas(tmp_path, shared_data):
    basis = import_basis(write_manifest(tmp_path), shared_data / "ict-facekit" / "obj")
    with np.load(shared_data / "ict-facekit" / "face_region.npz") as data:
        names = [str(n) for n in data["names"]]
        deltas_mm = data["deltas"].astype(np.float64) * 10.0
        neutral_mm = data["neutral"].astype(np.float64) * 10.0
        triangles = data["triangles"]
    np.testing.assert_allclose(basis.neutral, neutral_mm, atol=1e-3)
    assert basis.triangles.max() < 9409 and abs(len(basis.triangles) - len(triangles)) <= 2
    expected = {"jaw": deltas_mm[names.index("jawOpen")],
                "zygomatic_major_L": deltas_mm[names.index("mouthSmile_L")],
                "frontalis_L": 0.5 * deltas_mm[names.index("browInnerUp_L")]}
    for name, delta in expected.items():
        # the npz stores float32 centimetres; 1e-4 mm is below its resolution at 20 cm
        assert np.abs(basis.elements[basis.index(name)] - delta).max() <= 1e-4
    assert [m.region for m in basis.muscles] == ["lower", "lower", "upper"]


def test_unknown_unit_names_file_and_field(tmp_path, shared_data):
    path = write_manifest(tmp_path, units="furlong")
    with pytest.raises(InputError, match=r"manifest.toml: units: unknown unit 'furlong'"):
        import_basis(path, shared_data / "ict-facekit" / "obj")


def test_missing_shape_file_is_named(tmp_path, shared_data):
    folder = tmp_path / "meshes"
    folder.mkdir()
    (folder / "generic_neutral_mesh.obj").symlink_to(shared_data / "ict-facekit/obj/generic_neutral_mesh.obj")
    with pytest.raises(InputError, match=r"jawOpen\.obj: shape file not found"):
        import_basis(write_manifest(tmp_path), folder)


def test_topology_mismatch_is_named(tmp_path, shared_data):
    folder = tmp_path / "meshes"
    folder.mkdir()
    for name in ("generic_neutral_mesh", "mouthSmile_L", "browInnerUp_L"):
        (folder / f"{name}.obj").symlink_to(shared_data / f"ict-facekit/obj/{name}.obj")
    (folder / "jawOpen.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(InputError, match=r"jawOpen\.obj: topology mismatch: 3 vertices"):
        import_basis(write_manifest(tmp_path), folder)


def test_unknown_muscle_needs_region(tmp_path, shared_data):
    text = TEST_MANIFEST + "nose_wiggle = {{ jawOpen = 1.0 }}\n"
    with pytest.raises(InputError, match=r"muscles.nose_wiggle: not one of the Choe-Ko muscles"):
        import_basis(write_manifest(tmp_path, text=text), shared_data / "ict-facekit" / "obj")


def test_shipped_manifest_builds_sixteen_muscles(ict):
    assert ict.n_muscles == 16
    assert ict.region_mask("upper").sum() == 6
    assert ict.n_vertices == 9409
    assert 20 < np.abs(ict.elements[ict.index("jaw")]).max() < 100  # mm, not cm
