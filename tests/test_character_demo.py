"""``livebridge demo --character builtin``: the demo drives the 2D character through its render page."""

from __future__ import annotations

import re

from click.testing import CliRunner

from livebridge.cli import main


def test_the_demo_drives_the_builtin_character():
    result = CliRunner().invoke(main, ["demo", "--character", "builtin", "--frames", "40", "--unpaced",
                                       "--no-servo", "--size", "320x200", "--port", "0"])
    assert result.exit_code == 0, result.output
    match = re.search(r"2D character 'builtin': (\d+) frames of region states \(shown in the render page\)",
                      result.output)
    assert match and int(match.group(1)) >= 40, result.output
