"""The eyeballs a scanner sees between the lids are told from the skin by their colour and left out of the
scans (:mod:`livebridge.retarget.eyeballs`), so the eye openings stay holes for the eyelids' tracking."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner
from factories import write_builtin_scans

from livebridge.bench.data import ict_eyeballs
from livebridge.bench.scan_eyes import IRIS, PUPIL, SCLERA
from livebridge.bench.scans import SKIN_TONE, build_and_measure
from livebridge.cli import main
from livebridge.retarget.eyeballs import eyeball_points
from livebridge.retarget.landmarks import load_landmark_set

CORNERS = {"eye_inner_L": np.array([-13.0, 0.0, 0.0]), "eye_outer_L": np.array([13.0, 0.0, 0.0])}
BLUE = np.array([0.35, 0.45, 0.55])


def an_eye(rng, open_mm: float = 3.5, iris=IRIS, noise: float = 0.01, spacing: float = 0.8, skin=SKIN_TONE):
    """Points (n, 3) and colours (n, 3) of lid skin around an eye between :data:`CORNERS` (26 mm wide), open
    ``open_mm`` above and below its corners' line (an almond shape: 0 is a closed eye), which of them are the
    eye's (sclera, an iris 11 mm across with its pupil in the middle, 1 mm behind the lids), and how far each lies
    above or below the nearer lid's margin (n,) mm (negative: in the opening)."""
    xy = rng.uniform([-30, -25], [30, 25], (int(60 * 50 / spacing**2), 2))
    half_height = open_mm * np.clip(1 - (xy[:, 0] / 13.0) ** 2, 0, None)
    eye = np.abs(xy[:, 1]) < half_height
    off_margin = np.abs(xy[:, 1]) - half_height
    radius = np.linalg.norm(xy, axis=1)
    albedo = 0.7 + 0.25 * rng.random(len(xy))  # pores and blotches
    colours = albedo[:, None] * skin
    colours[eye] = np.where((radius[eye] < 1.1)[:, None], PUPIL, np.where((radius[eye] < 5.5)[:, None], iris, SCLERA))
    colours = np.clip(colours + rng.normal(0, noise, colours.shape), 0, 1)
    points = np.column_stack([xy, np.where(eye, -1.0, 0.0)])
    return points, colours, eye, off_margin


@pytest.mark.parametrize("iris", [IRIS, BLUE], ids=["brown", "blue"])
def test_an_open_eye_s_eyeball_is_found_and_the_lids_kept(rng, iris):
    points, colours, eye, off_margin = an_eye(rng, iris=iris)
    found = eyeball_points(points, colours, CORNERS)
    assert found[eye].mean() > 0.99
    assert np.all(off_margin[found & ~eye] < 0.5)  # the opening's edge is found within half a mm


def test_a_brown_iris_by_a_brown_skin_is_found_between_the_whites(rng):
    """Skin and iris alike in hue and brightness: the iris is left out as part of the opening the whites
    either side of it outline, all but a crescent along each lid (the hull's chord between the whites, and its
    edge, where only points unlike skin are taken)."""
    points, colours, eye, off_margin = an_eye(rng, skin=np.array([0.45, 0.30, 0.22]))
    iris = eye & (np.linalg.norm(points[:, :2], axis=1) < 5.5)
    found = eyeball_points(points, colours, CORNERS)
    assert found[iris].mean() > 0.55  # 0.05 without the hull
    assert np.all(found[iris] | (off_margin[iris] > -1.5))
    assert np.all(off_margin[found & ~eye] < 0.5)


def test_a_closed_eye_loses_nothing(rng):
    points, colours, eye, _ = an_eye(rng, open_mm=0.0)
    assert not eye.any()
    assert not eyeball_points(points, colours, CORNERS).any()


def test_a_squint_s_slit_is_found(rng):
    points, colours, eye, off_margin = an_eye(rng, open_mm=1.2, spacing=0.5)
    found = eyeball_points(points, colours, CORNERS)
    assert found[eye].mean() > 0.95
    assert np.all(off_margin[found & ~eye] < 0.5)


def test_a_dark_mole_on_the_lid_is_skin(rng):
    points, colours, eye, _ = an_eye(rng)
    mole = np.linalg.norm(points[:, :2] - [4.0, 8.0], axis=1) < 1.5
    colours[mole] = 0.15 * SKIN_TONE
    found = eyeball_points(points, colours, CORNERS)
    assert not found[mole].any()
    assert found[eye].mean() > 0.99


def test_nothing_is_found_without_colour_or_without_the_eye_s_corners(rng):
    points, colours, _, _ = an_eye(rng)
    assert not eyeball_points(points, None, CORNERS).any()
    assert not eyeball_points(points, colours, {"eye_inner_L": CORNERS["eye_inner_L"]}).any()
    elsewhere = {name.replace("_L", "_R"): corner + [0.0, 60.0, 0.0] for name, corner in CORNERS.items()}
    assert not eyeball_points(points, colours, elsewhere).any()  # only between an eye's own corners


def test_scanned_eyes_left_out_track_the_eyelids_as_scans_without_them(ict):
    """The ICT head's eyeballs seen between the lids (`livebridge bench scans`, ``scanned_eyes``): kept in the
    scans they fill the openings the eyelids are read from, and the lids' elements are several times as far
    off; left out, the lids are as scans without eyes make them (60k points on the 150 x 150 grid: 0.197 / 0.203
    from scans with eyes, 0.195 / 0.190 from scans without)."""
    options = {"grid": (100, 100), "muscles": ("orbicularis_oculi_L", "orbicularis_oculi_R", "frontalis_L"),
               "hole_muscle": None, "eyes": ict_eyeballs()}
    landmarks = load_landmark_set("ict-22")
    left_out = build_and_measure(ict, landmarks, np.random.default_rng(7), **options)
    kept = build_and_measure(ict, landmarks, np.random.default_rng(7), leave_out_eyeballs=False, **options)
    assert left_out.neutral.eyeball_points > 500 and kept.neutral.eyeball_points == 0
    lids = [left_out.names.index(name) for name in options["muscles"][:2]]
    assert np.all(left_out.errors[lids] < 0.3)
    assert np.all(left_out.errors[lids] < 0.5 * kept.errors[lids])
    brow = left_out.names.index("frontalis_L")
    assert left_out.errors[brow] < 0.1


@pytest.mark.parametrize("keep", [False, True])
def test_retarget_scans_says_it_left_the_eyeballs_out(tmp_path, ict, keep):
    write_builtin_scans(tmp_path, 4, {"neutral": "neutral", "orbicularis_oculi_L": "blink"}, ict, colour=True,
                        landmarks="ict-22", n_points=40000, eyes=ict_eyeballs())
    result = CliRunner().invoke(main, ["retarget", "scans", "--neutral", str(tmp_path / "neutral.ply"),
                                       "--expression", f"orbicularis_oculi_L={tmp_path / 'blink.ply'}",
                                       "--grid", "40x40", "--out", str(tmp_path / "basis.npz")]
                                + ["--keep-eyeballs"] * keep)
    assert result.exit_code == 0, result.output
    said = [line for line in result.output.splitlines() if line.startswith("eyes: ")]
    assert (said == []) if keep else ("are eyeballs seen between the lids" in said[0])


def test_a_textured_mesh_s_eyeballs_are_left_out_through_its_texture(ict):
    """Textured meshes that keep the eyeball triangles the scanner saw (their own texture image): found in the
    points the meshes are sampled into, the eyelids are as from meshes without eyes (kept: 0.68 / 0.76 relative
    RMS on this grid)."""
    built = build_and_measure(ict, load_landmark_set("ict-22"), np.random.default_rng(7), grid=(100, 100),
                              muscles=("orbicularis_oculi_L", "orbicularis_oculi_R"), hole_muscle=None,
                              textured=True, eyes=ict_eyeballs())
    assert built.neutral.eyeball_points > 1000
    assert np.all(built.errors < 0.25)
