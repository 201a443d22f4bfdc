"""The eyelids' first guess: the lid margins' motion from the eye openings of two resampled scans."""

import numpy as np
import pytest

from livebridge.retarget.eyelids import eyelid_guess, lid_columns, lid_columns_from_landmarks
from livebridge.retarget.grid import FaceGrid, resample
from livebridge.retarget.scans import skin_gap_mm

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
    # the columns taper to no motion at the corners
    near_corner = min(columns, key=lambda col: abs(FINE[col] - HALF_WIDTH))
    assert abs(columns[near_corner].upper_motion) < 0.5 * abs(upper_after - 4.0) + 0.5


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
    out = eyelid_guess(neutral, expression, coarse, 4, 0, guess, landmarks, landmarks, skin_gap_mm(COARSE_STEP))
    np.testing.assert_array_equal(out, guess)


def test_a_closing_lid_moves_the_guess_down_above_the_eye(rng):
    neutral, expression = _scan(rng, 4.0, -4.0), _scan(rng, 0.0, 0.0)
    coarse = FaceGrid(FINE[::4], FINE[::4], np.zeros((len(FINE[::4]),) * 2))
    guess = np.zeros((int(coarse.valid.sum()), 3))
    landmarks = {"eye_inner_L": np.r_[CORNERS[0], 0.0], "eye_outer_L": np.r_[CORNERS[1], 0.0]}
    out = eyelid_guess(neutral, expression, coarse, 4, 0, guess, landmarks, landmarks, skin_gap_mm(COARSE_STEP))
    xy = np.stack(np.meshgrid(coarse.x, coarse.y), axis=-1)[coarse.valid]
    above = (np.abs(xy[:, 0]) < 2.5) & (xy[:, 1] > 4.0) & (xy[:, 1] < 6.5)  # the upper lid by its margin
    assert above.any() and np.all(out[above, 1] < -4.0)
    far = np.abs(xy[:, 1]) > 20.0
    assert np.all(out[far] == 0.0)
