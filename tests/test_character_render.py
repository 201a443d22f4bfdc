"""``livebridge character render``: a take composited into an H.264 video or a PNG sequence."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from livebridge.character.builtin import builtin_character
from livebridge.character.composite import Compositor
from livebridge.character.definition import read_image, save_character
from livebridge.character.states import ContractionStates
from livebridge.cli import main

MUSCLES = ("jaw", "zygomatic_major_L", "orbicularis_oculi_R", "frontalis_L")


def _contraction_csv(path, n_frames=24, fps=24.0):
    t = np.arange(n_frames) / fps
    values = np.stack([0.5 - 0.5 * np.cos(2 * np.pi * t * (k + 1) / 2) for k in range(len(MUSCLES))], axis=1)
    lines = ["t," + ",".join(MUSCLES)] + [f"{a:.6f}," + ",".join(f"{v:.6f}" for v in row) for a, row in zip(t, values)]
    path.write_text("\n".join(lines) + "\n")
    return values


@pytest.fixture(scope="module")
def small_character(tmp_path_factory):
    folder = tmp_path_factory.mktemp("char") / "builtin_small"
    save_character(builtin_character((160, 120)), folder)
    return folder


def _expected(folder, values):
    from livebridge.character.definition import load_character
    from livebridge.face.builtin import builtin_basis

    character = load_character(folder)
    names = builtin_basis().names
    full = np.zeros((len(values), len(names)))
    for k, name in enumerate(MUSCLES):
        full[:, names.index(name)] = values[:, k]
    mapper = ContractionStates(character.region_muscles, names, character.region_actuations)
    compositor = Compositor(character)
    return [compositor.composite(mapper(row)).copy() for row in full]


def test_render_writes_a_png_sequence_equal_to_the_compositor(tmp_path, small_character):
    values = _contraction_csv(tmp_path / "take.csv")
    result = CliRunner().invoke(main, ["character", "render", str(tmp_path / "take.csv"), "--character",
                                       str(small_character), "--out", str(tmp_path / "frames"), "--no-progress"])
    assert result.exit_code == 0, result.output
    files = sorted((tmp_path / "frames").glob("frame_*.png"))
    assert len(files) == len(values)
    expected = _expected(small_character, values)
    for k in (0, 7, 23):
        np.testing.assert_allclose(read_image(files[k]), expected[k], atol=0.6 / 255)
    assert np.abs(read_image(files[12]) - read_image(files[0])).max() > 0.3  # the face moved


def test_render_encodes_h264_that_decodes_to_the_frames(tmp_path, small_character):
    av = pytest.importorskip("av")
    from livebridge.character.render import video_encoder_problem

    if video_encoder_problem() is not None:
        pytest.skip(video_encoder_problem())
    values = _contraction_csv(tmp_path / "take.csv")
    out = tmp_path / "take.mp4"
    result = CliRunner().invoke(main, ["character", "render", str(tmp_path / "take.csv"), "--character",
                                       str(small_character), "--out", str(out)])
    assert result.exit_code == 0, result.output
    with av.open(str(out)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264" and float(stream.average_rate) == pytest.approx(24.0)
        decoded = [frame.to_ndarray(format="rgb24") for frame in container.decode(stream)]
    assert len(decoded) == len(values)
    expected = _expected(small_character, values)
    for got, want in zip(decoded, expected):
        mse = np.mean(np.square(got / 255.0 - want))
        assert 10 * np.log10(1 / mse) > 30  # lossy, but the same pictures


def test_render_refuses_an_existing_output_without_force(tmp_path, small_character):
    _contraction_csv(tmp_path / "take.csv")
    (tmp_path / "take.mp4").write_bytes(b"keep")
    result = CliRunner().invoke(main, ["character", "render", str(tmp_path / "take.csv"), "--character",
                                       str(small_character), "--out", str(tmp_path / "take.mp4")])
    assert result.exit_code != 0 and "--force" in result.output
    assert (tmp_path / "take.mp4").read_bytes() == b"keep"


def test_without_an_encoder_a_video_becomes_png_frames(tmp_path, monkeypatch):
    from livebridge.character import render

    monkeypatch.setattr(render, "video_encoder_problem", lambda: "PyAV is not installed")
    frames = [np.full((6, 8, 1), k / 4, np.float32) for k in range(5)]
    written, count = render.write_video(iter(frames), tmp_path / "take.mp4", 25.0, progress=False)
    assert written == tmp_path / "take" and count == 5 and not (tmp_path / "take.mp4").exists()
    for k, frame in enumerate(frames):
        np.testing.assert_allclose(read_image(written / f"frame_{k:06d}.png")[..., None], frame, atol=0.5 / 255)
