"""The lighting in a scan's colours: fitted from the surface's normals, divided out, and only when it is there."""

import numpy as np
import pytest
from click.testing import CliRunner

from livebridge.bench.scans import FLASH, build_and_measure, synthetic_scans
from livebridge.cli import main
from livebridge.face.builtin import builtin_basis
from livebridge.retarget.face_scan import prepare_expression, prepare_neutral
from livebridge.retarget.landmarks import load_landmark_set
from livebridge.retarget.shading import LUMINANCE, MIN_EXPLAINED, fit_shading, surface_normals, unshaded
from tests.factories import write_builtin_scans


def _neutral_scans(n_points: int = 20_000):
    """The built-in face's neutral scanned twice with the same points and skin: under the bench's flash, and
    with colours that hold the skin alone."""
    basis, landmarks = builtin_basis(), load_landmark_set("builtin-22")
    flat, _ = synthetic_scans(basis, landmarks, np.random.default_rng(5), n_points=n_points, muscles=())
    lit, _ = synthetic_scans(basis, landmarks, np.random.default_rng(5), n_points=n_points, muscles=(), lit=True)
    assert np.array_equal(flat.points, lit.points)
    return flat, lit


def _log_brightness_off(colours, skin) -> np.ndarray:
    return np.log(np.maximum(colours @ LUMINANCE, 1e-3) / np.maximum(skin @ LUMINANCE, 1e-3))


def test_surface_normals_of_a_noisy_sphere_point_out_of_it(rng):
    direction = rng.normal(size=(20_000, 3))
    direction[:, 2] = np.abs(direction[:, 2])
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    points = 60.0 * direction + rng.normal(0.0, 0.2, direction.shape)
    normals = surface_normals(points)
    angle = np.degrees(np.arccos(np.clip(np.sum(normals * direction, axis=1), -1.0, 1.0)))
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0)
    assert np.median(angle) < 2.0 and np.percentile(angle, 95) < 6.0


def test_the_flash_s_shading_is_found_and_divided_out():
    flat, lit = _neutral_scans()
    normals = surface_normals(lit.points)
    shading = fit_shading(lit.points, lit.colours, normals)
    assert shading.explained > 0.3
    before = _log_brightness_off(lit.colours, flat.colours)
    after = _log_brightness_off(unshaded(lit.colours, normals, shading), flat.colours)
    # one factor between the skin and the unshaded colours is no shading: compare spreads
    assert after.std() < 0.3 * before.std()


def test_skin_without_lighting_is_not_taken_for_shading():
    flat, _ = _neutral_scans()
    assert fit_shading(flat.points, flat.colours).explained < 0.5 * MIN_EXPLAINED


def test_a_scan_too_dark_to_fit_has_no_shading_and_keeps_its_colours(rng):
    points = rng.normal(size=(5000, 3))
    colours = np.zeros((5000, 3))
    colours[:50] = 0.5
    shading = fit_shading(points, colours)
    assert shading.explained == 0.0 and not shading.coefficients.any()
    assert np.array_equal(unshaded(colours, surface_normals(points), shading), colours)


def test_the_neutral_decides_and_its_expressions_follow():
    basis, landmarks = builtin_basis(), load_landmark_set("builtin-22")
    for lit in (False, True):
        neutral_scan, scans = synthetic_scans(basis, landmarks, np.random.default_rng(6), n_points=8000,
                                              hole_muscle=None, muscles=("jaw",), lit=lit)
        for remove in (None, True, False):
            neutral = prepare_neutral(neutral_scan.as_scan(), neutral_scan.landmarks, neutral_scan.landmarks,
                                      shape=(40, 40), remove_shading=remove)
            jaw = prepare_expression(scans["jaw"].as_scan(), scans["jaw"].landmarks, neutral)
            expected = lit if remove is None else remove
            assert neutral.shading_removed == jaw.shading_removed == expected, (lit, remove)
            assert (neutral.shading.explained >= MIN_EXPLAINED) == lit


@pytest.mark.parametrize("lit", [False, True])
def test_a_textured_mesh_s_lighting_is_found_in_its_texture(lit):
    """A scanner's textured mesh has its light baked into the texture: read through the texture, the neutral's
    shading is found (and removed) when the texture was lit, not when it holds the skin alone."""
    from livebridge.bench.scans import lambertian, texel_shading
    from livebridge.face.meshio import vertex_normals

    basis, landmarks = builtin_basis(), load_landmark_set("builtin-22")
    neutral_scan, _ = synthetic_scans(basis, landmarks, np.random.default_rng(5), muscles=(), textured=True, lit=lit)
    neutral = prepare_neutral(neutral_scan.as_scan(), neutral_scan.landmarks, neutral_scan.landmarks, shape=(60, 60))
    assert neutral.shading_removed == lit
    assert (neutral.shading.explained > 2 * MIN_EXPLAINED) == lit
    if lit:  # the simulator's texture: at each vertex's texel, the vertex's own shading
        from livebridge.simulators.skin import make_skin

        skin = make_skin(basis.neutral, 1, landmarks.as_dict(basis.neutral, basis.triangles)).level(1.0)
        texels = texel_shading(basis.neutral, basis.triangles, skin, *FLASH)
        at = np.round(skin.vertex_texels).astype(int)
        inside = (at[:, 0] < texels.shape[1]) & (at[:, 1] < texels.shape[0])
        own = lambertian(vertex_normals(basis.neutral, basis.triangles), *FLASH)
        assert np.median(np.abs(texels[at[inside, 1], at[inside, 0]] - own[inside])) < 0.02


def test_removing_the_flash_s_shading_tracks_an_opening_jaw_as_unlit_scans_do(ict):
    """The flash's shading on the chin and lips changes as the jaw opens: left in the colours, the tracked jaw
    is half as far off again as unlit scans make it (`livebridge bench scans`, ``lit_scans``)."""
    landmarks = load_landmark_set("ict-22")
    options = {"grid": (100, 100), "muscles": ("jaw", "corrugator_L"), "hole_muscle": None, "lit": True}
    removed = build_and_measure(ict, landmarks, np.random.default_rng(7), **options)
    kept = build_and_measure(ict, landmarks, np.random.default_rng(7), remove_shading=False, **options)
    assert removed.neutral.shading_removed and not kept.neutral.shading_removed
    jaw, brow = removed.names.index("jaw"), removed.names.index("corrugator_L")
    assert removed.errors[jaw] < 0.1 < kept.errors[jaw]
    assert removed.errors[jaw] < 0.7 * kept.errors[jaw]
    assert removed.errors[brow] < kept.errors[brow] + 0.01


@pytest.mark.parametrize("lighting, said", [("auto", "removed from"), ("keep", "left in")])
def test_retarget_scans_says_what_it_did_with_the_lighting(tmp_path, lighting, said):
    write_builtin_scans(tmp_path, 4, {"neutral": "neutral", "jaw": "jaw"}, colour=True, lit=True)
    result = CliRunner().invoke(main, ["retarget", "scans", "--neutral", str(tmp_path / "neutral.ply"),
                                       "--expression", f"jaw={tmp_path / 'jaw.ply'}", "--grid", "40x40",
                                       "--out", str(tmp_path / "basis.npz"), "--lighting", lighting])
    assert result.exit_code == 0, result.output
    assert f"lighting: {said} the scans' colours" in result.output
