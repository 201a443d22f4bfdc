import numpy as np
import pytest
from factories import random_basis

from livebridge.errors import InputError
from livebridge.face.markers import MarkerSet


def random_markers(rng, basis, n=10) -> MarkerSet:
    bary = rng.dirichlet(np.ones(3), size=n)
    triangles = rng.integers(0, len(basis.triangles), size=n)
    roles = tuple("head" if i < 2 else "face" for i in range(n))
    regions = tuple("upper" if i % 2 else "lower" for i in range(n))
    return MarkerSet(tuple(f"k{i}" for i in range(n)), triangles, bary, regions, roles)


def test_positions_follow_deformed_mesh(rng):
    basis = random_basis(rng)
    markers = random_markers(rng, basis)
    x = rng.uniform(size=(3, basis.n_muscles))
    deformed = basis.synthesize(x)
    got = markers.positions(deformed, basis.triangles)
    for frame in range(3):
        for k in range(len(markers)):
            corners = deformed[frame][basis.triangles[markers.triangles[k]]]
            np.testing.assert_allclose(got[frame, k], markers.barycentric[k] @ corners, atol=1e-12)
    face = markers.face_mask
    np.testing.assert_allclose(markers.marker_positions(basis, x)[:, face], got[:, face], atol=1e-9)


def test_head_markers_do_not_move_with_expression(rng):
    basis = random_basis(rng)
    markers = random_markers(rng, basis)
    displacement = markers.displacement_matrix(basis)
    assert displacement.shape == (len(markers), basis.n_muscles, 3)
    assert np.all(displacement[markers.head_mask] == 0)


def test_toml_round_trip(tmp_path, rng):
    basis = random_basis(rng)
    markers = random_markers(rng, basis)
    markers.save(tmp_path / "m.toml")
    loaded = MarkerSet.load(tmp_path / "m.toml")
    assert loaded.names == markers.names and loaded.roles == markers.roles
    np.testing.assert_array_equal(loaded.triangles, markers.triangles)
    np.testing.assert_allclose(loaded.barycentric, markers.barycentric)


def test_bad_marker_file_names_the_field(tmp_path):
    path = tmp_path / "m.toml"
    path.write_text('format = "livebridge-markers"\nversion = 1\n[[marker]]\nname = "a"\ntriangle = "x"\n')
    with pytest.raises(InputError, match=r"m.toml: marker\[0\].triangle: expected int"):
        MarkerSet.load(path)
