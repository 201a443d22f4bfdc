"""The render page in real headless Chromium: the face is drawn and follows the contractions."""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from livebridge.output.render_server import RenderFrame, RenderServer

pytestmark = pytest.mark.browser

CHROMIUM = os.environ.get("LIVEBRIDGE_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--no-first-run",
    "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
]
BACKGROUND = np.array([29, 33, 39])  # the canvas clear colour (0.114, 0.129, 0.153)


@pytest.fixture(scope="module")
def browser():
    if not (Path(CHROMIUM).exists() or shutil.which(CHROMIUM)):
        pytest.skip(f"no chromium at {CHROMIUM}")
    sync_api = pytest.importorskip("playwright.sync_api")
    with sync_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield browser
        browser.close()


def _canvas_pixels(page) -> np.ndarray:
    import cv2

    png = page.locator("#face").screenshot()
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]  # RGB
    return image.astype(np.int16)


def test_page_draws_the_face_and_follows_the_contractions(browser, face_basis, tmp_path):
    basis = face_basis
    from livebridge.face.markers import MarkerSet

    n = 12
    triangles = np.linspace(0, len(basis.triangles) - 1, n).astype(int)
    markers = MarkerSet(tuple(f"m{i}" for i in range(n)), triangles, np.full((n, 3), 1 / 3),
                        ("upper", "lower") * (n // 2), ("face",) * n)
    errors = []
    with RenderServer(basis, markers, servo_names=("jaw",)) as server:
        page = browser.new_page(viewport={"width": 1140, "height": 760})
        page.on("pageerror", lambda error: errors.append(str(error)))
        page.goto(server.url)
        page.wait_for_function("window.livebridge && window.livebridge.ready", timeout=30_000)
        x = np.zeros(basis.n_muscles)
        server.publish(RenderFrame(1, time.monotonic(), x, markers.marker_positions(basis, x), (0.1, 0.2),
                                   np.array([0.5])))
        page.wait_for_function("window.livebridge.drawnSeq >= 1", timeout=10_000)
        neutral = _canvas_pixels(page)
        page.screenshot(path=str(tmp_path / "neutral.png"))

        face = np.abs(neutral - BACKGROUND).sum(axis=-1) > 30
        assert face.mean() > 0.05, "the face covers almost nothing of the canvas"
        assert not face.all(), "the whole canvas is foreground: the view is broken"

        x = np.zeros(basis.n_muscles)
        x[-1] = 1.0  # the last muscle (the jaw in the Choe-Ko order)
        x[0] = 1.0
        server.publish(RenderFrame(2, time.monotonic(), x, markers.marker_positions(basis, x), (0.1, 0.2),
                                   np.array([0.9])))
        page.wait_for_function("window.livebridge.drawnSeq >= 2", timeout=10_000)
        moved = _canvas_pixels(page)
        page.screenshot(path=str(tmp_path / "contracted.png"))
        changed = np.abs(moved - neutral).sum(axis=-1) > 30
        assert changed.mean() > 0.002, "the face did not change with the contractions"

        turned = np.eye(4)  # the head turned a quarter turn about its up axis: the page turns the face
        turned[:3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]
        server.publish(RenderFrame(3, time.monotonic(), x, markers.marker_positions(basis, x), (0.1, 0.2),
                                   np.array([0.9]), turned))
        page.wait_for_function("window.livebridge.drawnSeq >= 3", timeout=10_000)
        profile = _canvas_pixels(page)
        changed = np.abs(profile - moved).sum(axis=-1) > 30
        assert changed.mean() > 0.02, "the face did not turn with the head pose"

        assert page.evaluate("window.livebridge.error") is None
        assert page.evaluate("window.livebridge.framesReceived") == 3
        page.close()
    assert not errors, errors
    out = os.environ.get("LIVEBRIDGE_SCREENSHOT_DIR")
    if out:
        Path(out).mkdir(parents=True, exist_ok=True)
        for name in ("neutral.png", "contracted.png"):
            shutil.copy(tmp_path / name, Path(out) / name)
