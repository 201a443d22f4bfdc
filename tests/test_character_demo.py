"""``livebridge demo --character builtin``: the demo drives the 2D character through its render page, and the
take it records renders offline with the same character."""

from __future__ import annotations

import re

import pytest
from click.testing import CliRunner

from livebridge.cli import main


def test_the_demo_drives_the_builtin_character_and_its_take_renders(tmp_path):
    result = CliRunner().invoke(main, ["demo", "--character", "builtin", "--frames", "40", "--unpaced",
                                       "--no-servo", "--size", "320x200", "--port", "0", "--record",
                                       str(tmp_path / "take")])
    assert result.exit_code == 0, result.output
    match = re.search(r"2D character 'builtin': (\d+) frames of region states \(shown in the render page\)",
                      result.output)
    assert match and int(match.group(1)) >= 40, result.output

    from livebridge.take.directory import load_take_dir

    n_frames = load_take_dir(tmp_path / "take").n_frames
    result = CliRunner().invoke(main, ["character", "render", str(tmp_path / "take"), "--character", "builtin",
                                       "--out", str(tmp_path / "frames"), "--no-progress"])
    assert result.exit_code == 0, result.output
    assert len(list((tmp_path / "frames").glob("frame_*.png"))) == n_frames > 0


@pytest.mark.slow
def test_the_markerless_demo_drives_the_builtin_character():
    """Trains a markerless model on a simulated take first (about a minute)."""
    result = CliRunner().invoke(main, ["demo", "--markerless", "--character", "builtin", "--frames", "300",
                                       "--unpaced", "--no-servo", "--port", "0"])
    assert result.exit_code == 0, result.output
    match = re.search(r"2D character 'builtin': (\d+) frames of region states", result.output)
    assert match and int(match.group(1)) >= 300, result.output
