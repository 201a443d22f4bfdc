"""``livebridge devices`` on a machine without cameras says so plainly; JSON output parses."""

from __future__ import annotations

import json

from click.testing import CliRunner

from livebridge.cli import main


def test_devices_lists_or_says_none():
    result = CliRunner().invoke(main, ["devices"])
    assert result.exit_code == 0, result.output
    for heading in ("V4L2 cameras:", "DepthAI (OAK) devices:", "Serial ports:"):
        assert heading in result.output
    section = result.output.split("V4L2 cameras:")[1].split("DepthAI")[0]
    assert "none" in section or "/dev/video" in section


def test_devices_json_and_help():
    result = CliRunner().invoke(main, ["devices", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.output.strip().splitlines()[-1])
    assert set(data) == {"v4l2", "depthai", "serial"} and all(isinstance(v, list) for v in data.values())
    assert "serial" in CliRunner().invoke(main, ["devices", "--help"]).output.lower()
