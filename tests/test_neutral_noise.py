"""The neutral scan's noise, shared by every tracked element, found on the skin each leaves still and taken out."""

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from livebridge.retarget.neutral_noise import MIN_ELEMENTS, neutral_noise

SIDE = 60  # a 60 x 60 grid of vertices, 1 mm apart


def _muscles(rng, k):
    """k elements (k, n, 3), each a smooth bump of motion (3-8 mm at its centre) somewhere on the grid."""
    rows, cols = np.indices((SIDE, SIDE))
    out = []
    for _ in range(k):
        centre = rng.uniform(8, SIDE - 8, 2)
        bump = np.exp(-((rows - centre[0]) ** 2 + (cols - centre[1]) ** 2) / (2 * rng.uniform(4, 8) ** 2))
        direction = rng.normal(size=3)
        out.append(bump.ravel()[:, None] * direction / np.linalg.norm(direction) * rng.uniform(3, 8))
    return np.array(out)


def _smooth_noise(rng, mm, sigma=4.0):
    """A smooth random field (n, 3) of RMS ``mm``."""
    field = np.dstack([gaussian_filter(rng.normal(size=(SIDE, SIDE)), sigma) for _ in range(3)]).reshape(-1, 3)
    return field * mm / np.sqrt(np.mean(np.sum(field ** 2, axis=1)))


def _relative(elements, truth):
    return np.sqrt(np.sum((elements - truth) ** 2, axis=(1, 2)) / np.sum(truth ** 2, axis=(1, 2)))


def test_the_shared_noise_is_taken_out_and_the_muscles_kept():
    rng = np.random.default_rng(3)
    truth = _muscles(rng, 16)
    shared = _smooth_noise(rng, 0.2)
    own = np.array([_smooth_noise(rng, 0.1) for _ in truth])
    built = truth + shared + own
    cleaned = built - neutral_noise(built)
    before, after = _relative(built, truth), _relative(cleaned, truth)
    assert np.all(after < before)
    assert np.mean(after) < 0.6 * np.mean(before)
    # the estimate is the shared field, not the muscles' motion
    found = neutral_noise(built)
    assert np.sqrt(np.mean(np.sum((found - shared) ** 2, axis=1))) < 0.6 * 0.2


def test_noise_free_elements_are_left_almost_as_they_are():
    truth = _muscles(np.random.default_rng(4), 16)
    cleaned = truth - neutral_noise(truth)
    assert np.all(_relative(cleaned, truth) < 0.02)


def test_with_too_few_elements_nothing_is_taken():
    rng = np.random.default_rng(5)
    built = _muscles(rng, MIN_ELEMENTS - 1) + _smooth_noise(rng, 0.2)
    assert np.array_equal(built - neutral_noise(built), built)
    assert not neutral_noise(built).any()


@pytest.mark.parametrize("k", [MIN_ELEMENTS, 8])
def test_a_few_elements_do_not_make_it_worse(k):
    """Few scans: the estimate is a mean of few, each with its own noise; shrunk, it still helps."""
    rng = np.random.default_rng(6)
    truth = _muscles(rng, k)
    built = truth + _smooth_noise(rng, 0.2) + np.array([_smooth_noise(rng, 0.1) for _ in truth])
    assert np.mean(_relative(built - neutral_noise(built), truth)) < np.mean(_relative(built, truth))
