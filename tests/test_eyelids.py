"""The eyelids' first guess: the lid margins' motion from the eye openings of two resampled scans."""

import numpy as np
import pytest

from livebridge.retarget.eyelids import (
    TAPER_BEYOND_EYE_WIDTHS,
    eyelid_guess,
    lid_columns,
    lid_columns_from_landmarks,
)
from livebridge.retarget.grid import FaceGrid, resample
from livebridge.retarget.scans import skin_gap_mm
from livebridge.retarget.skin_flow import pixels_of

HALF_WIDTH = 12.0  # the eye's corners at x = -12 and +12 mm, the opening an ellipse between them
COARSE_STEP = 1.4  # the skin images of a 150 x 150 grid: holes shrink by 2.1 mm a side
FINE = np.arange(-30.0, 30.0 + 1e-9, 0.5)


def _scan(rng, upper: float, lower: float) -> FaceGrid:
    """A gently curved face scanned as ~0.3 mm-spaced points, its eye opening between the lid margins
    ``y = upper * s(x)`` and ``y = lower * s(x)`` (``s`` an ellipse's profile; equal margins: a closed eye),
    resampled on the fine grid as the skin images are."""
    points = rng.uniform(-30.0, 30.0, (40_000, 2))
    shape = np.sqrt(np.clip(1.0 - (points[:, 0] / HALF_WIDTH) ** 2, 0.0, None))
    open_ = (points[:, 1] < upper * shape) & (points[:, 1] > lower * shape)
    points = points[~open_]
    z = -0.01 * (points ** 2).sum(axis=1) + rng.normal(0.0, 0.1, len(points))
    return resample(np.column_stack([points, z]), FINE, FINE, skin_gap_mm(COARSE_STEP))


CORNERS = (np.array([-HALF_WIDTH, 0.0]), np.array([HALF_WIDTH, 0.0]))


@pytest.mark.parametrize("upper_after, lower_after", [(-4.0, -4.0), (2.0, -4.0), (6.0, -5.0)],
                         ids=["closed", "squint", "wide"])
def test_the_margins_go_where_the_opening_went(rng, upper_after, lower_after):
    neutral = _scan(rng, 4.0, -4.0)
    expression = _scan(rng, upper_after, lower_after) if upper_after > lower_after else _scan(rng, 0.0, 0.0)
    columns = lid_columns(neutral, expression, *CORNERS, skin_gap_mm(COARSE_STEP))
    centre = int(np.argmin(np.abs(FINE)))
    lid = columns[centre]
    step = FINE[1] - FINE[0]
    # the neutral's margins at y = +-4 (the hole of the resampled grid is smaller: grown back)
    assert abs(FINE[0] + lid.upper * step - 4.0) < 1.0 and abs(FINE[0] + lid.lower * step + 4.0) < 1.0
    assert lid.upper_motion == pytest.approx(upper_after - 4.0, abs=1.0)
    assert lid.lower_motion == pytest.approx(lower_after + 4.0, abs=1.0)
    # past the opening the columns taper to no motion a tenth of the eye's width beyond its corners
    reach = HALF_WIDTH + TAPER_BEYOND_EYE_WIDTHS * 2 * HALF_WIDTH
    assert max(abs(FINE[col]) for col in columns) < reach
    outermost = columns[max(columns)]
    assert abs(outermost.upper_motion) < 0.25 * abs(upper_after - 4.0) + 0.5


def test_lid_landmarks_give_the_margins_and_their_motion():
    grid = FaceGrid(FINE, FINE, np.zeros((len(FINE), len(FINE))))
    before = {"lm_43": np.array([-4.0, 4.0, 0.0]), "lm_44": np.array([4.0, 4.0, 0.0]),
              "lm_47": np.array([-4.0, -4.0, 0.0]), "lm_46": np.array([4.0, -4.0, 0.0])}
    after = {**before, "lm_43": np.array([-4.0, -3.0, 0.0]), "lm_44": np.array([4.0, -3.5, 0.0])}
    columns = lid_columns_from_landmarks(grid, before, after, "L", *CORNERS)
    at = {x: columns[int(np.argmin(np.abs(FINE - x)))] for x in (-4.0, 0.0, 4.0)}
    assert at[-4.0].upper_motion == pytest.approx(-7.0) and at[4.0].upper_motion == pytest.approx(-7.5)
    assert at[0.0].upper_motion == pytest.approx(-7.25) and at[0.0].lower_motion == pytest.approx(0.0)
    assert FINE[0] + at[0.0].upper * (FINE[1] - FINE[0]) == pytest.approx(4.0)


def test_an_eye_that_did_not_move_keeps_the_first_guess(rng):
    """Two scans of the same open eye: no lid motion, so the first guess comes back as it was."""
    neutral, expression = _scan(rng, 4.0, -4.0), _scan(rng, 4.0, -4.0)
    coarse = FaceGrid(FINE[::4], FINE[::4], np.zeros((len(FINE[::4]),) * 2))
    guess = rng.normal(0.0, 0.3, (int(coarse.valid.sum()), 3))
    landmarks = {"eye_inner_L": np.r_[CORNERS[0], 0.0], "eye_outer_L": np.r_[CORNERS[1], 0.0]}
    out = eyelid_guess(neutral, expression, pixels_of(neutral, coarse.vertices[:, :2]), guess, landmarks, landmarks,
                       skin_gap_mm(COARSE_STEP))
    np.testing.assert_array_equal(out, guess)


def test_a_closing_lid_moves_the_guess_down_above_the_eye(rng):
    neutral, expression = _scan(rng, 4.0, -4.0), _scan(rng, 0.0, 0.0)
    coarse = FaceGrid(FINE[::4], FINE[::4], np.zeros((len(FINE[::4]),) * 2))
    guess = np.zeros((int(coarse.valid.sum()), 3))
    landmarks = {"eye_inner_L": np.r_[CORNERS[0], 0.0], "eye_outer_L": np.r_[CORNERS[1], 0.0]}
    out = eyelid_guess(neutral, expression, pixels_of(neutral, coarse.vertices[:, :2]), guess, landmarks, landmarks,
                       skin_gap_mm(COARSE_STEP))
    xy = np.stack(np.meshgrid(coarse.x, coarse.y), axis=-1)[coarse.valid]
    above = (np.abs(xy[:, 0]) < 2.5) & (xy[:, 1] > 4.0) & (xy[:, 1] < 6.5)  # the upper lid by its margin
    assert above.any() and np.all(out[above, 1] < -4.0)
    far = np.abs(xy[:, 1]) > 20.0
    assert np.all(out[far] == 0.0)


def test_retarget_scans_takes_lid_landmarks_beside_the_22(tmp_path, ict):
    """A landmark file with the thesis's 22 and the lids' iBUG points (as a 68-point detector gives them):
    `livebridge retarget scans` matches them by name, and the built eyelid element closes the upper lid as the
    ICT element does (its 20 most moved vertices move down, within 40% of the ICT's motion: measured 0.26-0.32;
    the flow from the shape warp alone gave about 0.6)."""
    from click.testing import CliRunner

    from livebridge.bench.scans import synthetic_scans, truth_on_grid, with_landmarks
    from livebridge.cli import main
    from livebridge.face.basis import Basis
    from livebridge.retarget.eyelids import LID_LANDMARKS
    from livebridge.retarget.landmarks import load_landmark_set
    from livebridge.retarget.scan import write_ply

    lids = [name for side in LID_LANDMARKS.values() for pair in side for name in pair]
    landmarks = with_landmarks(load_landmark_set("ict-22"), load_landmark_set("ict-68"), lids)
    neutral, expressions = synthetic_scans(ict, landmarks, np.random.default_rng(3), n_points=60_000,
                                           hole_muscle=None, muscles=("orbicularis_oculi_L",))
    for name, scan in (("neutral", neutral), ("lid", expressions["orbicularis_oculi_L"])):
        write_ply(tmp_path / f"{name}.ply", scan.points, None, "binary_little_endian", scan.colours)
        rows = "".join(f"{k},{x:.4f},{y:.4f},{z:.4f}\n" for k, (x, y, z) in scan.landmarks.items())
        (tmp_path / f"{name}.landmarks.csv").write_text("name,x,y,z\n" + rows)
    result = CliRunner().invoke(main, [
        "retarget", "scans", "--neutral", str(tmp_path / "neutral.ply"), "--neutral-landmarks",
        str(tmp_path / "neutral.landmarks.csv"), "--expression", f"orbicularis_oculi_L={tmp_path / 'lid.ply'}",
        "--grid", "100x100", "--out", str(tmp_path / "b.npz")])
    assert result.exit_code == 0, result.output
    basis = Basis.load(tmp_path / "b.npz")
    element = basis.elements[0]
    # the ICT element on the same grid (the CLI's grid is the neutral's: rebuild its frame the same way)
    from livebridge.retarget.scan import read_scan
    from livebridge.retarget.scans import prepare_neutral

    face = prepare_neutral(read_scan(tmp_path / "neutral.ply"), neutral.landmarks, _builtin_reference(),
                           shape=(100, 100))
    np.testing.assert_allclose(face.vertices, basis.neutral, atol=0.01)  # landmarks written to 0.1 µm
    truth = truth_on_grid(ict, neutral, face, ["orbicularis_oculi_L"])[0]
    lid = np.argsort(np.linalg.norm(truth, axis=1))[-20:]  # the upper lid's 20 most moved grid vertices
    assert np.all(element[lid, 1] < 0)
    assert np.linalg.norm(element[lid] - truth[lid], axis=1).mean() < 0.4 * np.linalg.norm(truth[lid], axis=1).mean()


def _builtin_reference():
    from livebridge.cli.retarget_scans import reference_landmarks

    return reference_landmarks("builtin", 1.0)




def test_a_closing_eye_s_opening_is_not_skin_up_to_its_margins(rng):
    """The closing eye's opening, grown back to the lids' margins (the band the resampling filled from the
    rims included), is what the skin flow leaves out of the depth change; an eye that did not move gives none."""
    from livebridge.retarget.eyelids import closing_openings

    gap = skin_gap_mm(COARSE_STEP)
    landmarks = {"eye_inner_L": np.r_[CORNERS[0], 0.0], "eye_outer_L": np.r_[CORNERS[1], 0.0]}
    neutral = _scan(rng, 4.0, -4.0)
    assert closing_openings(neutral, _scan(rng, 4.0, -4.0), landmarks, landmarks, gap) is None
    opening = closing_openings(neutral, _scan(rng, 0.0, 0.0), landmarks, landmarks, gap)
    xx, yy = np.meshgrid(FINE, FINE)
    margin = 4.0 * np.sqrt(np.clip(1.0 - (xx / HALF_WIDTH) ** 2, 0.0, None))  # the true margins: y = +-margin
    middle = np.abs(xx) < 0.6 * HALF_WIDTH
    hole = ~np.isfinite(neutral.heights)
    filled = middle & ~hole & (np.abs(yy) < margin - 0.75)  # the resampling's fill inside the true opening
    assert filled.any() and opening[filled].all() and opening[middle & hole & (np.abs(yy) < margin)].all()
    assert not opening[middle & (np.abs(yy) > margin + 1.0)].any()  # the skin beyond the margins counts
