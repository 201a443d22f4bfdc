"""``[face] display``: the render client shows a retargeted face driven by the solving basis's contractions."""

from __future__ import annotations

import numpy as np
import pytest

from livebridge.errors import InputError
from livebridge.face.builtin import builtin_basis
from livebridge.output.render_server import encode_mesh
from livebridge.runtime.build import display_face
from livebridge.runtime.session import session_from_dict


def _session(tmp_path, display):
    return session_from_dict({"cameras": {"urls": ["sim://rig?cameras=2&seed=1"]}, "face": {"display": display}},
                             tmp_path / "session.toml")


def test_the_display_face_replaces_the_solving_basis_in_the_render_mesh(tmp_path):
    basis = builtin_basis()
    shown = basis.with_elements(basis.elements * 0.5)  # any basis with the same muscles
    shown.save(tmp_path / "target.npz")
    session = _session(tmp_path, "target.npz")
    assert session.display == tmp_path / "target.npz"
    face = display_face(session, basis)
    assert face.names == basis.names and np.allclose(face.elements, shown.elements)
    assert encode_mesh(face) == encode_mesh(shown)
    without = session_from_dict({"cameras": {"urls": ["sim://rig"]}}, tmp_path / "s.toml")
    assert without.display is None and display_face(without, basis) is basis


def test_a_display_face_with_other_muscles_is_refused_naming_the_file(tmp_path):
    from livebridge.face.basis import Basis

    basis = builtin_basis()
    Basis(basis.neutral, basis.triangles, basis.elements[:2], basis.muscles[:2]).save(tmp_path / "two.npz")
    with pytest.raises(InputError) as error:
        display_face(_session(tmp_path, "two.npz"), basis)
    assert "two.npz" in str(error.value) and "display" in str(error.value)
    with pytest.raises(InputError, match="face.display"):
        _session(tmp_path, "target.obj")


def test_beside_shows_both_faces_apart_moving_with_the_same_contractions(tmp_path):
    basis = builtin_basis()
    shown = basis.with_elements(basis.elements * 0.5)
    shown.save(tmp_path / "target.npz")
    session = session_from_dict({"cameras": {"urls": ["sim://rig?cameras=2&seed=1"]},
                                 "face": {"display": "target.npz", "display_mode": "beside"}},
                                tmp_path / "session.toml")
    both = display_face(session, basis)
    n = basis.n_vertices
    assert both.names == basis.names and both.n_vertices == n + shown.n_vertices
    assert np.array_equal(both.neutral[:n], basis.neutral)  # the solving face keeps its place (markers stay on it)
    assert both.neutral[n:, 0].min() > basis.neutral[:, 0].max()  # the display face to its right, apart
    assert np.array_equal(both.triangles[len(basis.triangles):] - n, shown.triangles)
    x = np.random.default_rng(3).uniform(0, 1, basis.n_muscles)
    moved = both.synthesize(x)
    assert np.allclose(moved[:n], basis.synthesize(x))
    assert np.allclose(moved[n:] - both.neutral[n:], shown.synthesize(x) - shown.neutral)
    with pytest.raises(InputError, match="face.display_mode"):
        session_from_dict({"cameras": {"urls": ["sim://rig"]}, "face": {"display": "target.npz",
                                                                        "display_mode": "next"}},
                          tmp_path / "session.toml")


@pytest.mark.browser
def test_the_render_page_draws_both_faces_beside_and_both_move(tmp_path):
    """Headless Chromium: the left and the right half of the canvas each hold a face, and each changes when
    the contractions do."""
    import shutil
    import time
    from pathlib import Path

    from test_browser import BACKGROUND, CHROMIUM, CHROMIUM_ARGS, _canvas_pixels

    from livebridge.face.markers import MarkerSet
    from livebridge.output.render_server import RenderFrame, RenderServer
    from livebridge.retarget.compare import side_by_side

    if not (Path(CHROMIUM).exists() or shutil.which(CHROMIUM)):
        pytest.skip(f"no chromium at {CHROMIUM}")
    sync_api = pytest.importorskip("playwright.sync_api")
    basis = builtin_basis()
    both = side_by_side(basis, basis.with_elements(basis.elements * 0.8))
    markers = MarkerSet(("m0", "m1"), np.array([0, 1]), np.full((2, 3), 1 / 3), ("upper", "lower"),
                        ("face", "face"))
    with sync_api.sync_playwright() as playwright, RenderServer(both, markers) as server:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1140, "height": 760})
        page.goto(server.url)
        page.wait_for_function("window.livebridge && window.livebridge.ready", timeout=30_000)
        frames = []
        for seq, value in ((1, 0.0), (2, 1.0)):
            x = np.zeros(basis.n_muscles)
            x[basis.index("jaw")] = value
            x[basis.index("frontalis_L")] = value
            server.publish(RenderFrame(seq, time.monotonic(), x, markers.marker_positions(both, x), (0.1, 0.2),
                                       np.array([])))
            page.wait_for_function(f"window.livebridge.drawnSeq >= {seq}", timeout=10_000)
            frames.append(_canvas_pixels(page))
        assert page.evaluate("window.livebridge.error") is None
        browser.close()
    neutral, moved = frames
    middle = neutral.shape[1] // 2
    for half in (slice(0, middle), slice(middle, None)):
        face = np.abs(neutral[:, half] - BACKGROUND).sum(axis=-1) > 30
        changed = np.abs(moved[:, half] - neutral[:, half]).sum(axis=-1) > 30
        assert face.mean() > 0.05, "a face is missing from its half of the canvas"
        assert changed.mean() > 0.002, "a face did not move with the contractions"
