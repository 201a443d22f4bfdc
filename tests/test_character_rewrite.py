"""Video rewrite and guide sheets on a tiny model whose every state's appearance is known."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from character_factories import TOY_REGIONS, toy_appearance, toy_model
from click.testing import CliRunner

from livebridge.character.composite import Compositor
from livebridge.character.definition import load_character, write_image
from livebridge.character.rewrite import character_from_model, rewrite_scores
from livebridge.character.states import NEUTRAL, CRStates
from livebridge.cli import main


def _held_out_take(rng, n_frames=40, noise=2.0):
    """True frames (in [0, 1]) of random performances and their CR states, levels anywhere in [0, 1]."""
    for _ in range(n_frames):
        levels, muscle, level = {}, [], []
        for _, muscles, _, _ in TOY_REGIONS:
            m = int(rng.integers(-1, len(muscles)))
            value = float(rng.uniform(0.05, 1.0)) if m >= 0 else 0.0
            if m >= 0:
                levels[muscles[m]] = value
            muscle.append(m)
            level.append(value)
        truth = toy_appearance(levels) + rng.normal(0, noise, (72, 96))
        yield np.clip(truth, 0, 255) / 255.0, CRStates(np.array(muscle), np.array(level))


def test_a_take_rebuilt_from_the_training_samples_beats_the_neutral_image_everywhere():
    model = toy_model()
    character = character_from_model(model, feather_px=3.0)
    assert character.region_names == ("upper", "lower") and character.size == (96, 72)
    assert [len(s) for s in character.regions[1].samples] == [3, 2, 2]  # one sample per non-neutral state
    score = rewrite_scores(Compositor(character), [r.mask for r in model.regions],
                           _held_out_take(np.random.default_rng(0)))
    assert score.frames == 40
    for region, rewrite, neutral in zip(score.regions, score.rewrite_db, score.neutral_db):
        assert rewrite > neutral + 3.0, (region, rewrite, neutral)
    assert score.overall_rewrite_db > score.overall_neutral_db + 3.0


def test_a_state_on_a_training_sample_rebuilds_that_training_frame():
    model = toy_model()
    compositor = Compositor(character_from_model(model, feather_px=3.0))
    frame = compositor.composite(CRStates(np.array([NEUTRAL, 0]), np.array([0.0, 2 / 3])))[..., 0] * 255
    truth = model.state_frame("lower", "b", 2)
    inside = model.regions[1].mask
    np.testing.assert_allclose(frame[inside], truth[inside], atol=0.5)  # the region itself: exactly the sample
    assert np.abs(frame[~inside] - model.neutral_image[~inside]).max() <= 80  # the ramp just outside it only
    far = np.ones_like(inside)
    far[28:72, 14:82] = False
    np.testing.assert_allclose(frame[far], model.neutral_image[far], atol=0.5)


def test_from_training_writes_the_rewrite_character(tmp_path):
    model = toy_model()
    model.save(tmp_path / "model.npz")
    result = CliRunner().invoke(main, ["character", "from-training", str(tmp_path / "model.npz"), "--out",
                                       str(tmp_path / "char"), "--feather", "3"])
    assert result.exit_code == 0, result.output
    loaded = load_character(tmp_path / "char")
    direct = character_from_model(model, 3.0)
    states = CRStates(np.array([0, 1]), np.array([0.6, 0.75]))
    np.testing.assert_allclose(Compositor(loaded).composite(states), Compositor(direct).composite(states),
                               atol=1.5 / 255)


def test_template_lists_every_sample_and_its_skeleton_loads_once_drawn(tmp_path):
    model = toy_model()
    model.save(tmp_path / "model.npz")
    out = tmp_path / "sheets"
    result = CliRunner().invoke(main, ["character", "template", str(tmp_path / "model.npz"), "--out", str(out)])
    assert result.exit_code == 0, result.output
    with (out / "samples.csv").open() as stream:
        rows = list(csv.DictReader(stream))
    expected = [(name, m, k) for name, muscles, n_states, _ in TOY_REGIONS for m, n in zip(muscles, n_states)
                for k in range(1, n)]
    assert [(r["region"], r["muscle"], int(r["state"])) for r in rows] == expected
    import cv2

    guide = cv2.imread(str(out / rows[0]["guide"]))[..., ::-1].astype(int)
    orange = (guide[..., 0] > 200) & (guide[..., 1] < 150) & (guide[..., 2] < 80)
    assert orange.sum() > 50  # the region's outline is drawn on the training frame
    # the artist draws: here, each sample is the training frame's box, on a neutral of the face's size
    write_image(out / "neutral.png", model.neutral_image / 255)
    for row in rows:
        x, y, w, h = (int(row[k]) for k in ("x", "y", "width", "height"))
        frame = model.state_frame(row["region"], row["muscle"], int(row["state"])) / 255
        write_image(out / row["draw"], frame[y:y + h, x:x + w])
    drawn = load_character(out)
    for region, cr in zip(drawn.regions, model.regions):
        assert np.mean(region.mask != cr.mask) < 0.01  # the identity warp keeps the masks in place


@pytest.mark.parametrize("missing", ["samples.csv"])
def test_template_refuses_an_existing_folder(tmp_path, missing):
    model = toy_model()
    model.save(tmp_path / "model.npz")
    (tmp_path / "sheets").mkdir()
    result = CliRunner().invoke(main, ["character", "template", str(tmp_path / "model.npz"), "--out",
                                       str(tmp_path / "sheets")])
    assert result.exit_code != 0 and "already exists" in result.output
    assert not (tmp_path / "sheets" / missing).exists()


def test_a_rewrite_character_keeps_the_models_pseudo_muscles_and_contractions_select_them(tmp_path):
    from livebridge.character.definition import save_character
    from livebridge.character.states import ContractionStates

    character = character_from_model(toy_model(), 3.0)
    assert character.regions[1].actuations == {"mix": {"b": 1.0, "c": 0.5}}
    save_character(character, tmp_path / "char")
    loaded = load_character(tmp_path / "char")
    assert loaded.region_actuations == character.region_actuations
    states = ContractionStates(loaded.region_muscles, ("a", "b", "c"), loaded.region_actuations)
    chosen = states(np.array([0.0, 0.8, 0.4]))  # b with half as much c: the trained combination
    assert chosen.muscle.tolist() == [NEUTRAL, 2] and chosen.level[1] == pytest.approx(0.8)
    chosen = states(np.array([0.3, 0.0, 0.6]))
    assert chosen.muscle.tolist() == [0, 1] and chosen.level.tolist() == pytest.approx([0.3, 0.6])
