"""2D characters: alpha ramps, compositing against a straightforward blend, CR states, the character folder."""

from __future__ import annotations

import numpy as np
import pytest
from character_factories import random_character, random_states, reference_blend

from livebridge.character.alpha import feathered_alpha
from livebridge.character.composite import Compositor, neighbours
from livebridge.character.definition import (
    Character,
    CharacterRegion,
    Sample,
    load_character,
    save_character,
    write_image,
)
from livebridge.character.states import NEUTRAL, ContractionStates, CRStates, states_from_regions
from livebridge.errors import InputError


# ------------------------------------------------------------------------------------------------ alpha
def _ramp_width(profile: np.ndarray) -> int:
    """Pixels from the last 0 outside the shape to the first 1 inside, along a line into it."""
    outside = np.flatnonzero(profile == 0.0).max()
    full = np.flatnonzero(profile >= 1.0).min()
    return int(full - outside)


@pytest.mark.parametrize("feather", [10.0, 4.0])
def test_the_alpha_ramp_is_as_wide_as_asked(feather):
    shape = np.zeros((120, 140), bool)
    shape[20:100, 30:120] = True
    alpha = feathered_alpha(shape, feather)
    assert _ramp_width(alpha[60, :70]) == feather  # from the left edge
    assert _ramp_width(alpha[::-1, 70][:60]) == feather  # from the bottom edge
    assert alpha[60, 30] == pytest.approx(1 / feather)  # the first pixel inside
    assert alpha[~shape].max() == 0.0 and alpha.max() == 1.0
    assert np.all(np.diff(alpha[60, 30:30 + int(feather)]) > 0)  # rising all the way


def test_the_alpha_ramp_on_a_round_mask_and_at_the_sample_edge():
    yy, xx = np.mgrid[:101, :101]
    disc = np.hypot(xx - 50, yy - 50) <= 40
    alpha = feathered_alpha(disc)
    assert abs(_ramp_width(alpha[50, :50]) - 10) <= 1  # a digital circle's boundary is ragged by a pixel
    diagonal = alpha[np.arange(50), np.arange(50)]  # along the diagonal: 10 px of ramp measured radially
    inside = np.flatnonzero(diagonal > 0)
    ramp_px = (np.flatnonzero(diagonal >= 1.0).min() - inside.min() + 1) * np.sqrt(2)
    assert ramp_px == pytest.approx(10, abs=1.5)
    full = feathered_alpha(np.ones((30, 30), bool))  # the sample's own edge is a boundary
    assert full[15, 0] == pytest.approx(0.1) and full[15, 9] == 1.0


# ------------------------------------------------------------------------------------------------ compositing
@pytest.mark.parametrize("seed", range(6))
def test_compositing_equals_a_straightforward_alpha_blend(seed):
    rng = np.random.default_rng(seed)
    character = random_character(rng, n_channels=3 if seed % 2 else 1)
    compositor = Compositor(character)
    out = np.empty_like(character.neutral)
    for _ in range(8):
        states = random_states(rng, character)
        got = compositor.composite(states, out)
        np.testing.assert_allclose(got, reference_blend(character, states), atol=2e-5)


def test_the_builtin_character_composites_as_the_straightforward_blend(rng):
    from livebridge.character.builtin import builtin_character

    character = builtin_character((320, 240))
    compositor = Compositor(character)
    for _ in range(3):
        states = random_states(rng, character)
        np.testing.assert_allclose(compositor.composite(states), reference_blend(character, states), atol=2e-5)


def test_a_level_between_samples_blends_its_two_neighbours_and_moves_smoothly():
    rng = np.random.default_rng(3)
    character = random_character(rng, n_regions=1)
    region = character.regions[0]
    m = max(range(len(region.muscles)), key=lambda i: len(region.samples[i]))
    n = len(region.samples[m])
    compositor = Compositor(character)

    def frame(level):
        return compositor.composite(CRStates(np.array([m]), np.array([level]))).astype(np.float64)

    neutral = character.neutral.astype(np.float64)
    at = [neutral] + [frame(k / n) for k in range(1, n + 1)]
    for k in range(n):
        for f in (0.25, 0.5):
            np.testing.assert_allclose(frame((k + f) / n), (1 - f) * at[k] + f * at[k + 1], atol=2e-5)
    levels = np.linspace(0, 1, 201)
    steps = [np.abs(frame(b) - frame(a)).max() for a, b in zip(levels[:-1], levels[1:])]
    assert max(steps) < 0.05 * n + 1e-6  # no jump between two close levels
    assert neighbours(1.0, n) == (n - 1, n, 1.0) and neighbours(0.0, n) == (0, 1, 0.0)


def _flat_region(name, mask, colour, size):
    width, height = size
    sample = Sample(np.full((height, width, 3), colour, np.float32), np.ones((height, width), np.float32), (0, 0))
    return CharacterRegion(name, ("m",), ((sample,),), mask)


def test_two_active_regions_cross_fade_where_they_overlap():
    size = (200, 60)
    a, b = np.zeros((60, 200), bool), np.zeros((60, 200), bool)
    a[:, :120] = True
    b[:, 80:] = True  # overlap: columns 80..119
    character = Character("two", np.zeros((60, 200, 3), np.float32),
                          (_flat_region("a", a, (1, 0, 0), size), _flat_region("b", b, (0, 0, 1), size)), 0.0)
    compositor = Compositor(character)
    both = compositor.composite(CRStates(np.array([0, 0]), np.array([1.0, 1.0])))
    row = both[30]
    assert row[40].tolist() == [1, 0, 0] and row[160].tolist() == [0, 0, 1]
    red, blue = row[80:120, 0], row[80:120, 2]
    np.testing.assert_allclose(red + blue, 1.0, atol=1e-6)  # a partition: nothing of the neutral black shows
    assert np.all(np.diff(blue) > 0)  # b's share rises across the overlap ...
    assert abs(blue[19] - 0.5) < 0.05 and abs(blue[20] - 0.5) < 0.05  # ... through half and half
    only_b = compositor.composite(CRStates(np.array([NEUTRAL, 0]), np.array([0.0, 1.0])))
    assert np.all(only_b[30, 80:120] == [0, 0, 1])  # a resting neighbour does not fade b


# ------------------------------------------------------------------------------------------------ states
def test_contraction_states_pick_the_muscle_that_best_explains_the_region():
    names = ("frontalis_L", "corrugator_L", "jaw")
    mapper = ContractionStates((("frontalis_L", "corrugator_L", "frontalis_L+corrugator_L"), ("jaw",)), names)
    states = mapper(np.array([0.6, 0.0, 0.0]))
    assert states.muscle.tolist() == [0, NEUTRAL] and states.level[0] == pytest.approx(0.6)
    states = mapper(np.array([0.5, 0.4, 0.9]))  # both: the pseudo-muscle at their mean
    assert states.muscle.tolist() == [2, 0] and states.level.tolist() == pytest.approx([0.45, 0.9])
    states = mapper(np.array([0.1, 0.7, np.nan]))  # one clearly: that one alone
    assert states.muscle.tolist() == [1, NEUTRAL] and states.level[0] == pytest.approx(0.7)
    with pytest.raises(InputError, match="'smile'"):
        ContractionStates((("smile",),), names)


def test_region_states_from_the_analysis_are_used_when_the_regions_match():
    from types import SimpleNamespace as State

    got = states_from_regions(("mouth", "brows"), [State(region="brows", muscle=1, level=0.5),
                                                     State(region="mouth", muscle=-1, level=0.0)])
    assert got.muscle.tolist() == [NEUTRAL, 1] and got.level.tolist() == [0.0, 0.5]
    assert states_from_regions(("mouth",), [State(region="lips", muscle=0, level=1.0)]) is None


# ------------------------------------------------------------------------------------------------ the folder
def test_a_character_folder_round_trips(tmp_path, rng):
    character = random_character(rng, n_channels=3)
    save_character(character, tmp_path / "char")
    loaded = load_character(tmp_path / "char")
    assert loaded.region_names == character.region_names and loaded.region_muscles == character.region_muscles
    states = random_states(rng, character)
    np.testing.assert_allclose(Compositor(loaded).composite(states), Compositor(character).composite(states),
                               atol=3 / 255)


def _one_region_folder(folder, at=(10, 10), sample_size=(30, 20), mask_size=(100, 80), states=2,
                       drop_state=None, mask_space=None, warp=None):
    from livebridge.tomlio import save_toml

    folder.mkdir()
    write_image(folder / "neutral.png", np.full((80, 100, 3), 0.5, np.float32))
    mask = np.zeros((mask_size[1], mask_size[0]), np.float32)
    mask[5:60, 5:70] = 1.0
    write_image(folder / "mask.png", mask)
    samples = []
    for k in range(1, states + 1):
        write_image(folder / f"s{k}.png", np.full((sample_size[1], sample_size[0], 3), 0.1 * k, np.float32))
        if k != drop_state:
            samples.append({"muscle": "jaw", "state": k, "image": f"s{k}.png", "at": list(at)})
    region = {"name": "mouth", "muscles": ["jaw"], "states": [states], "mask": "mask.png", "samples": samples}
    table = {"format": "livebridge-character", "version": 1, "neutral": "neutral.png", "regions": [region]}
    if mask_space:
        region["mask_space"] = mask_space
    if warp:
        table["warp"] = warp
    save_toml(folder / "character.toml", table)
    return folder


@pytest.mark.parametrize(("kwargs", "words"), [
    ({"drop_state": 2}, ("character.toml", "regions[0].samples", "jaw state 2")),
    ({"at": (80, 10)}, ("s1.png", "jaw state 1", "outside the 100x80 canvas")),
    ({"at": (75, 65), "sample_size": (20, 10)}, ("s1.png", "jaw state 1", "outside the region's mask")),
    ({"mask_size": (90, 80)}, ("mask.png", "regions[0].mask", "90x80", "100x80")),
    ({"mask_space": "face"}, ("character.toml", "mask_space", "[warp]")),
])
def test_the_loader_names_the_file_and_the_state(tmp_path, kwargs, words):
    folder = _one_region_folder(tmp_path / "char", **kwargs)
    with pytest.raises(InputError) as error:
        load_character(folder)
    for word in words:
        assert word in str(error.value)


def test_a_mask_drawn_on_the_face_is_warped_onto_the_character(tmp_path):
    # the face is half the character's size: the points map by a scale of 2 (plus a shift)
    face_points = [[0, 0], [50, 0], [0, 40], [50, 40], [25, 20]]
    warp = {"face_points": face_points, "character_points": [[2 * x, 2 * y] for x, y in face_points]}
    folder = _one_region_folder(tmp_path / "char", mask_size=(50, 40), mask_space="face", warp=warp)
    mask = load_character(folder).regions[0].mask
    expected = np.zeros((80, 100), bool)
    expected[10:80, 10:100] = True  # face rows 5..39 and columns 5..49, doubled, cut at the canvas
    assert mask.shape == (80, 100)
    assert np.mean(mask != expected) < 0.02
