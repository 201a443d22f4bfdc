"""The render page's 2D character view in real headless Chromium: drawn, and following the CR states."""

from __future__ import annotations

import numpy as np
import pytest
from test_browser import browser  # noqa: F401  (the module's Chromium fixture)

from livebridge.character.builtin import builtin_character
from livebridge.character.live import CharacterOutput
from livebridge.character.states import NEUTRAL
from livebridge.output.render_server import RenderServer

pytestmark = pytest.mark.browser


def _canvas_pixels(page) -> np.ndarray:
    import cv2

    png = page.locator("#character").screenshot()
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1].astype(np.int16)  # RGB


class _Frame:
    def __init__(self, seq, contractions):
        self.seq, self.contractions = seq, contractions


def test_the_page_draws_the_character_and_follows_the_states(browser):  # noqa: F811
    from livebridge.face.builtin import builtin_basis

    basis = builtin_basis()
    character = builtin_character((320, 240))
    errors = []
    with RenderServer(basis) as server:
        output = CharacterOutput(character, basis.names, server)
        page = browser.new_page(viewport={"width": 1500, "height": 800})
        page.on("pageerror", lambda error: errors.append(str(error)))
        page.goto(server.url)
        page.wait_for_function("window.livebridgeCharacter && window.livebridgeCharacter.ready", timeout=30_000)
        output.send(_Frame(1, np.zeros(basis.n_muscles)))
        page.wait_for_function("window.livebridgeCharacter.drawnSeq >= 1", timeout=10_000)
        neutral = _canvas_pixels(page)
        assert neutral.shape[:2] == (240, 320)
        expected = np.rint(output.image() * 255)
        assert np.abs(neutral - expected).max() <= 2, "the page's neutral face is not the character's"

        x = np.zeros(basis.n_muscles)
        for name, value in (("jaw", 1.0), ("frontalis_L", 0.5), ("orbicularis_oculi_R", 0.8),
                            ("zygomatic_major_L", 0.6)):
            x[basis.names.index(name)] = value
        output.send(_Frame(2, x))
        assert (output.states.muscle != NEUTRAL).sum() >= 4
        page.wait_for_function("window.livebridgeCharacter.drawnSeq >= 2", timeout=10_000)
        moved = _canvas_pixels(page)
        changed = np.abs(moved - neutral).sum(axis=-1) > 30
        assert changed.mean() > 0.01, "the character did not change with the states"
        difference = np.abs(moved - np.rint(output.image() * 255))
        assert difference.mean() < 0.5 and np.percentile(difference, 99.9) <= 4, \
            "the page composites otherwise than the compositor"
        assert page.evaluate("window.livebridgeCharacter.error") is None
        page.close()
    assert not errors, errors
